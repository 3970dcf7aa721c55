"""Isolated position faults: a pixel whose decoded screen position leaps away from all of its neighbours'.

A facet reflects the screen smoothly, so the screen position decoded in a pixel differs from its neighbours'
by about one pixel's step of the position field (the field's gradient, a few millimetres on the screen) plus
the noise. A pixel on the facet's rim that sees a bevel or the edge's mixed light can pass the consistency
and unwrapping checks with a wrong fringe order: its position then sits tens of centimetres from its
neighbours', and its slope tens of mrad off. One such pixel among 34,000 raised a nearly flat facet's
slope RMS x from 0.65 to 0.83 mrad (population seed 0, station 7, capture 7: 637 mm off, 66 of the field's
steps, where the bevelled rim's worst pixel of 19 other captures was 10 steps off, and a dish's, a gore's
and a heliostat's at most 4.3). Such a pixel is no surface: it is dropped and counted
(``Phases.dropped["isolated_jump"]``).

The test: a pixel is a fault when at most :data:`MAX_AGREEING` of its trusted 8-neighbours lie within
:data:`JUMP_STEPS` times the field's typical step (the median absolute difference between neighbouring
pixels, along rows and columns, the larger) plus :data:`JUMP_SIGMAS` times its own position noise of its
position, in either axis. A rim pixel is judged on the neighbours it has; a feature a few pixels across (a
real scratch, a dust grain) has neighbours that agree with it and is kept, for the figures to show.

Pure numpy: image shape, pixel indices, positions in; a mask out.
"""

from __future__ import annotations

import numpy as np

#: A position this many of the field's neighbour steps from its neighbours' median is a fault (2x the
#: worst of the population's bevelled rims, 5x the other edges' worst).
JUMP_STEPS = 20.0
#: ... plus this many of the pixel's own position noise standard deviations (a dim rim pixel's noise is up to
#: 16 times the facet's median: station 7's faulty pixel was 61 mm noisy and 10 of its sigmas off; a normal
#: pixel's excess over its neighbours is a few sigmas, 1e-9 per pixel beyond 6 for normal noise).
JUMP_SIGMAS = 6.0
#: Fewest trusted neighbours for a pixel to be judged (a lone pixel has no field to leap from).
MIN_NEIGHBOURS = 2
#: A pixel is isolated when at most this many of its trusted 8-neighbours lie within its limit (a faulty pair
#: goes together; a 3 x 3 feature's corner pixel has three such neighbours and stays).
MAX_AGREEING = 1

_OFFSETS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def isolated_jumps(shape: tuple[int, int], idx: np.ndarray, ok: np.ndarray, positions_m: dict,
                   sigma_m: dict) -> np.ndarray:
    """Which pixels of *idx* (flat indices into an image of *shape*) hold an isolated position fault.

    Parameters
    ----------
    shape : (rows, columns)
        The camera image's shape.
    idx : (M,) int array
        Flat indices of the region's pixels.
    ok : (M,) bool array
        The pixels whose positions are trusted so far; only they are judged and used as neighbours.
    positions_m : dict
        ``{"x": (M,), "y": (M,)}`` decoded screen positions, metres.
    sigma_m : dict
        ``{"x": (M,) or scalar, "y": ...}`` each pixel's position noise, metres.

    Returns
    -------
    (M,) bool array, True where a trusted pixel's position leaps from its neighbours' in either axis.
    """
    cols = shape[1]
    out = np.zeros(idx.size, dtype=bool)
    take = np.flatnonzero(ok)
    if take.size < 9:
        return out
    flat = idx[take]
    # the trusted pixels' box, padded by one pixel of NaN: whole-image slices of it stand for the neighbours
    r0, r1 = int(flat.min() // cols), int(flat.max() // cols) + 1
    width = cols + 2
    padded = flat + (flat // cols - r0) * 2 - r0 * cols + width + 1   # flat index into the (r1 - r0 + 2, cols + 2) box
    for axis in ("x", "y"):
        # float32 is ample for a test at tens of the field's steps, and halves the slices' memory traffic
        img = np.full((r1 - r0 + 2, width), np.nan, dtype=np.float32)
        img.ravel()[padded] = positions_m[axis][take]
        step = _typical_step(img)
        sig_all = np.asarray(sigma_m[axis], float)
        # candidates first: a leap from every 4-neighbour present beyond the smallest pixel's limit
        floor = JUMP_STEPS * step + JUMP_SIGMAS * float(np.min(sig_all))
        mid = img[1:-1, 1:-1]
        near = np.fmax(np.fmax(np.abs(mid - img[:-2, 1:-1]), np.abs(mid - img[2:, 1:-1])),
                       np.fmax(np.abs(mid - img[1:-1, :-2]), np.abs(mid - img[1:-1, 2:])))
        cand = np.flatnonzero(near.ravel()[flat - r0 * cols] > floor)
        if cand.size == 0:
            continue
        limit = JUMP_STEPS * step + JUMP_SIGMAS * np.broadcast_to(sig_all, idx.shape)[take[cand]]
        at = padded[cand]
        own = img.ravel()[at]
        nb = np.stack([img.ravel()[at + dr * width + dc] for dr, dc in _OFFSETS])
        n = np.count_nonzero(np.isfinite(nb), axis=0)
        with np.errstate(invalid="ignore"):
            agree = np.count_nonzero(np.abs(nb - own) <= limit, axis=0)
        bad = (n >= MIN_NEIGHBOURS) & (agree <= MAX_AGREEING)
        out[take[cand[bad]]] = True
    return out


def _typical_step(img: np.ndarray, stride: int = 16) -> float:
    """The field's typical change from one pixel to the next (the image's units): the median absolute
    difference between neighbours along rows and along columns, the larger, on every *stride*-th row and
    column (the median of a smooth field's steps needs no more)."""
    steps = []
    for d in (np.diff(img[::stride], axis=1), np.diff(img[:, ::stride], axis=0)):
        d = np.abs(d[np.isfinite(d)])
        steps.append(float(np.median(d)) if d.size else 0.0)
    return max(steps)
