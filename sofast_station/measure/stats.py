"""Order statistics of long arrays: the same numbers as numpy's, in a fraction of the time.

``np.median`` and ``np.quantile`` select their two neighbouring order statistics with one ``partition``
call for several positions, which numpy's introselect does about five times slower than for one
position (11 ms against 2.5 ms for 590,000 doubles). Here one position is selected and its neighbour
is the largest value to its left (every value there is no larger): the same two order statistics, then
numpy's own arithmetic on them, so the results are the same bits (``tests/measure/test_stats.py``
compares them with numpy's on many arrays). Camera counts (unsigned 8 or 16 bits) take both order
statistics from one histogram pass instead. Pure functions, numpy in and out.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Values per histogram call: float32 bin counts are exact integers up to 2**24.
_HIST_CHUNK = 1 << 23


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


def _unsigned_counts(a: np.ndarray) -> np.ndarray:
    """How many times each value 0 .. 2^bits - 1 occurs in the 1-D unsigned 8- or 16-bit *a* (int64 counts).

    One pass of OpenCV's histogram (a third of ``np.bincount``'s time, which first widens every value to
    64 bits); it counts in integers and returns them as float32, exact below 2^24 per call, so chunks of
    2^23 values are counted separately and added as integers."""
    bins = 1 << (8 * a.itemsize)
    counts = np.zeros(bins, dtype=np.int64)
    for start in range(0, a.size, _HIST_CHUNK):
        part = np.ascontiguousarray(a[start:start + _HIST_CHUNK]).reshape(1, -1)
        counts += cv2.calcHist([part], [0], None, [bins], [0, bins]).ravel().astype(np.int64)
    return counts


def _unsigned_select(a: np.ndarray, ks: tuple[int, ...]) -> list[int]:
    """The ks-th smallest (0-based) values of the unsigned 8- or 16-bit *a*, from one histogram."""
    cumulative = np.cumsum(_unsigned_counts(a))
    # the k-th smallest is the first value whose cumulative count exceeds k
    return [int(np.searchsorted(cumulative, k, side="right")) for k in ks]


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
    if a.dtype.kind == "u" and a.itemsize <= 2:
        lo, b = (float(v) for v in _unsigned_select(a, (previous, nxt)))
    elif a.dtype.kind == "i" and a.itemsize <= 2:
        lo, b = float(_int_select(a, previous)), float(_int_select(a, nxt))
    else:
        part = np.partition(a, nxt)
        if _nan_result(a, part[nxt:]):
            return float("nan")
        b = float(part[nxt])
        lo = float(part[:nxt].max())
    gamma = virtual - float(previous)
    # numpy's _lerp: a + (b - a) gamma, or b - (b - a)(1 - gamma) when gamma >= 1/2
    diff = b - lo
    return b - diff * (1.0 - gamma) if gamma >= 0.5 else lo + diff * gamma
