"""Order statistics of long arrays: the same numbers as numpy's, in a fraction of the time.

``np.median`` and ``np.quantile`` select their two neighbouring order statistics with one ``partition``
call for several positions, which numpy's introselect does about five times slower than for one
position (11 ms against 2.5 ms for 590,000 doubles). Here one position is selected and its neighbour
is the largest value to its left (every value there is no larger): the same two order statistics, then
numpy's own arithmetic on them, so the results are the same bits (``tests/measure/test_stats.py``
compares them with numpy's on many arrays). Pure functions, numpy in and out.
"""

from __future__ import annotations

import numpy as np


def _nan_result(a: np.ndarray, right: np.ndarray) -> bool:
    """Whether the selection holds a NaN (numpy then returns NaN): NaNs sort after every number."""
    return a.dtype.kind == "f" and right.size > 0 and bool(np.isnan(right.max()))


def _int_select(a: np.ndarray, k: int) -> int:
    """The k-th smallest (0-based) of small integers (8 or 16 bits): a binary search over the values by
    counting, each count one fast pass (no sort or partition, which many equal values slow down)."""
    lo, hi = int(a.min()), int(a.max())
    while lo < hi:
        mid = (lo + hi) // 2
        if int(np.count_nonzero(a <= mid)) > k:
            hi = mid
        else:
            lo = mid + 1
    return lo


def median(values) -> float:
    """``float(np.median(values))`` of a 1-D (or flattened) array, the same bits, one selection."""
    a = np.asarray(values).ravel()
    n = a.size
    if n < 64 or a.dtype.kind != "f":
        return float(np.median(a))
    half = n // 2
    part = np.partition(a, half)
    if _nan_result(a, part[half:]):
        return float("nan")
    upper = part[half]
    if n % 2:
        return float(upper)
    lower = part[:half].max()
    # np.median takes np.mean of the two: (lower + upper) / 2 in the array's type (for doubles, the same
    # two IEEE operations in Python's floats).
    if a.dtype == np.float64:
        return (float(lower) + float(upper)) / 2.0
    return float(np.mean(np.array([lower, upper], dtype=a.dtype)))


def quantile(values, q: float) -> float:
    """``float(np.quantile(values, q))`` (the default, linear method) of a 1-D (or flattened) float64 or
    integer array for a Python float *q* in [0, 1], the same bits, one selection."""
    a = np.asarray(values).ravel()
    n = a.size
    q = float(q)
    if n < 64 or not (a.dtype == np.float64 or a.dtype.kind in "iu") or not 0.0 <= q <= 1.0:
        return float(np.quantile(a, q))
    # numpy's virtual index for the linear method and its neighbours
    virtual = (n - 1) * q
    if virtual >= n - 1:
        if a.dtype.kind in "iu":
            return float(a.max())
        part = np.partition(a, n - 1)
        return float("nan") if _nan_result(a, part[n - 1:]) else float(part[n - 1])
    previous = int(np.floor(virtual))
    nxt = previous + 1
    if a.dtype.kind in "iu" and a.itemsize <= 2:
        lo, b = float(_int_select(a, previous)), float(_int_select(a, nxt))
        gamma = virtual - float(previous)
        diff = b - lo
        return b - diff * (1.0 - gamma) if gamma >= 0.5 else lo + diff * gamma
    part = np.partition(a, nxt)
    if _nan_result(a, part[nxt:]):
        return float("nan")
    b = float(part[nxt])
    lo = float(part[:nxt].max())
    gamma = virtual - float(previous)
    # numpy's _lerp: a + (b - a) gamma, or b - (b - a)(1 - gamma) when gamma >= 1/2
    diff = b - lo
    return b - diff * (1.0 - gamma) if gamma >= 0.5 else lo + diff * gamma
