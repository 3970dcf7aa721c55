"""Gaussian sensor noise for the twin's frames, drawn cheaply, and per-thread scratch arrays for it.

numpy's ``Generator.standard_normal`` (a ziggurat) costs about three times as much per float32 value as
the Box-Muller transform done in float32 array passes on the generator's raw 64-bit words, and the sensor
noise of 18 frames of 1600 x 1200 pixels was most of the twin's render. Box-Muller (Box and Muller, "A
note on the generation of random normal deviates", Ann. Math. Statist. 1958) is exact for uniform inputs:
with u1 = (k + 1/2) 2^-32 from a 32-bit word k (never 0) and the angle 2 pi k' 2^-32 from another, the
deviates are standard normal except that none exceeds sqrt(-2 ln 2^-33) = 6.77 in magnitude (a normal
deviate does with probability 1.3e-11) and values are spaced by float32 rounding.

A frame's arrays are megabytes: a fresh one per pass costs as much as the pass (the allocator hands it
new pages from the kernel each time), and a pass over megabytes runs at the speed of memory, not of the
core. So the twin draws and finishes a frame a block of rows at a time, in working arrays kept per thread
(:func:`scratch_f32`) and small enough to stay in the core's cache from one pass to the next.
"""

from __future__ import annotations

import math
import threading

import numpy as np

_TO_UNIT = np.float32(2.0 ** -32)
_TO_ANGLE = np.float32(2.0 * np.pi * 2.0 ** -32)
_LOCAL = threading.local()


def scratch_f32(name: str, shape) -> np.ndarray:
    """A float32 array of *shape* kept for the calling thread under *name* (its contents are garbage).

    Only for arrays used and dropped within one call: the next call of the same thread with the same
    *name* returns the same memory.
    """
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(s) for s in shape)
    size = math.prod(shape)
    store = getattr(_LOCAL, "arrays", None)
    if store is None:
        store = _LOCAL.arrays = {}
    buf = store.get(name)
    if buf is None or buf.size < size:
        buf = store[name] = np.empty(size, dtype=np.float32)
    return buf[:size].reshape(shape)


def standard_normal_f32(rng: np.random.Generator, n: int, out: np.ndarray | None = None) -> np.ndarray:
    """*n* independent standard normal deviates (float32), two per 64-bit word of *rng*'s bit generator.

    The same *rng* state gives the same deviates; the stream differs from ``rng.standard_normal``'s.
    *out*, a contiguous float32 array of *n* elements, receives them (a new array when None). The pair
    (cosine, sine) of one draw lands at *i* and *i + (n + 1) // 2*.
    """
    n = int(n)
    if out is None:
        out = np.empty(n, dtype=np.float32)
    if out.size != n or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a contiguous float32 array of {n} elements")
    flat = out.reshape(-1)          # a view (contiguous)
    if n == 0:
        return out
    m = (n + 1) // 2
    words = rng.bit_generator.random_raw(m).view(np.uint32)      # 2m independent 32-bit words
    # (the conversion of the words to float32 rides in the first arithmetic pass: numpy casts in cached chunks)
    r = np.add(words[:m], np.float32(0.5), out=scratch_f32("normal.radius", m), dtype=np.float32, casting="unsafe")
    r *= _TO_UNIT                                                 # u1 in (0, 1]
    np.log(r, out=r)
    r *= np.float32(-2.0)
    np.sqrt(r, out=r)                                             # radius sqrt(-2 ln u1)
    angle = np.multiply(words[m:], _TO_ANGLE, out=scratch_f32("normal.angle", m), dtype=np.float32,
                        casting="unsafe")
    np.cos(angle, out=flat[:m])
    flat[:m] *= r
    np.sin(angle[:n - m], out=flat[m:])
    flat[m:] *= r[:n - m]
    return out
