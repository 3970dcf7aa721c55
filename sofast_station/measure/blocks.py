"""Element-wise work on long per-point arrays, block by block, so that its temporaries stay in cache.

A chain of numpy operations over 590,000 points makes a pass over main memory per operation (each
temporary is 4.7 MB, more than a core's cache); run on blocks of 16,384 points, the same operations read
and write the cache instead, about twice as fast for the ray/surface and residual chains of the analysis.
Only for element-wise functions: each point's result is then the same bits whichever block it is in, so
:func:`blockwise` gives the same arrays as calling the function once on everything. Sums over the points
are not element-wise (their rounding depends on the grouping): the compiled kernels of ``kernels.py`` form
them block by block and add the blocks in order.
"""

from __future__ import annotations

import numpy as np

#: Points per block: a few dozen float64 temporaries of a block fit in a core's 2 MB cache.
BLOCK = 16384


def _tuple(result) -> tuple:
    return result if isinstance(result, tuple) else (result,)


def blockwise(fn, *columns: np.ndarray, pool=None, block: int = BLOCK, **kwargs) -> tuple:
    """``fn(*columns, **kwargs)`` computed on consecutive blocks of the columns' last axis.

    *fn* must be element-wise along that axis and return an array or a tuple of arrays whose last axis is
    the block's; the results are assembled into arrays of the full length (a tuple, always). With *pool*
    (an executor) the second half of the blocks runs on it beside the first.
    """
    n = columns[0].shape[-1]
    if block < 1:
        raise ValueError(f"block must be at least 1, got {block}")
    head = min(block, n)
    first = _tuple(fn(*(c[..., :head] for c in columns), **kwargs))
    outs = tuple(np.empty(r.shape[:-1] + (n,), dtype=r.dtype) for r in first)
    for o, r in zip(outs, first):
        o[..., :head] = r

    def run(lo: int, hi: int) -> None:
        for i in range(lo, hi, block):
            j = min(i + block, hi)
            for o, r in zip(outs, _tuple(fn(*(c[..., i:j] for c in columns), **kwargs))):
                o[..., i:j] = r

    if pool is None or n - head < 2 * block:
        run(head, n)
    else:
        mid = head + ((n - head) // (2 * block)) * block
        second = pool.submit(run, mid, n)
        run(head, mid)
        second.result()
    return outs
