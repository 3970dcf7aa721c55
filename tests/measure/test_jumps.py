"""Isolated position faults (sofast_station.measure.jumps): a pixel with a wrong fringe order is dropped, a
real cluster and the field's own gradient and noise are not.

The fields are drawn here (a smooth screen-position field, a quadratic in the pixel coordinates with a step of
0.3-15 mm per pixel, on an elliptical region, Gaussian noise of 0.1-5 mm per pixel, a dim rim ten times
noisier), 24 of them; the truth is which pixels were planted, never the code's own answer."""

from __future__ import annotations

import numpy as np

from sofast_station.measure.jumps import JUMP_SIGMAS, JUMP_STEPS, isolated_jumps


def _field(rng, shape=(120, 160)):
    rows, cols = shape
    r, c = np.mgrid[0:rows, 0:cols]
    inside = ((r - rows / 2) / (0.42 * rows)) ** 2 + ((c - cols / 2) / (0.42 * cols)) ** 2 <= 1.0
    idx = np.flatnonzero(inside)
    rr, cc = np.divmod(idx, cols)
    step = rng.uniform(0.3e-3, 15e-3)                         # metres of screen per pixel
    curv = rng.uniform(-1, 1, 2) * step / cols
    sigma = np.full(idx.size, rng.uniform(0.1e-3, 5e-3))
    # the rim (a pixel with a missing 4-neighbour) is dimmer: ten times the noise
    pad = np.pad(inside, 1)
    rim = ~(pad[rr, cc + 1] & pad[rr + 2, cc + 1] & pad[rr + 1, cc] & pad[rr + 1, cc + 2])
    sigma[rim] *= 10.0
    pos = {"x": step * cc + curv[0] * cc ** 2 + rng.normal(0, 1, idx.size) * sigma,
           "y": step * rr + curv[1] * rr ** 2 + rng.normal(0, 1, idx.size) * sigma}
    return shape, idx, rim, pos, {"x": sigma, "y": sigma}, step


def test_planted_fringe_order_errors_are_dropped_and_nothing_else():
    """On each of 24 drawn fields: one rim pixel and one interior pixel off by a fringe period (the screen's
    1 m over 8 periods, 125 mm, or 2.5 x 23 linear steps and 9 of its sigmas when that is larger: the quadratic
    field's steepest step is up to 2.5 times its linear one) are found; a 3 x 3 cluster moved by the same (a
    dust grain, a scratch: a real feature) and every other pixel are kept. Over the 24 fields' 255,000
    unplanted pixels not one is dropped: at 20 steps plus 6 sigmas a normal pixel's chance is about 1e-9."""
    rng = np.random.default_rng(47)
    kept_wrong = 0
    for _ in range(24):
        shape, idx, rim, pos, sig, step = _field(rng)
        ok = np.ones(idx.size, bool)
        planted = [int(rng.choice(np.flatnonzero(rim))), int(rng.choice(np.flatnonzero(~rim)))]
        for p in planted:
            jump = max(0.125, 2.5 * (JUMP_STEPS + 3) * step + (JUMP_SIGMAS + 3) * sig["x"][p])
            pos["x" if p % 2 else "y"][p] += jump * rng.choice([-1, 1])
        # a 3 x 3 cluster inside, moved alike
        centre = idx[np.flatnonzero(~rim)[len(np.flatnonzero(~rim)) // 3]]
        cr, cc = divmod(int(centre), shape[1])
        cluster = np.flatnonzero(np.isin(idx, [(cr + a) * shape[1] + cc + b for a in (-1, 0, 1) for b in (-1, 0, 1)]))
        pos["x"][cluster] += 0.2
        bad = isolated_jumps(shape, idx, ok, pos, sig)
        assert bad[planted].all(), "a pixel a fringe order off was kept"
        assert not bad[cluster].any(), "a real 3 x 3 feature was dropped as a fault"
        bad[planted] = False
        kept_wrong += int(bad.sum())
    assert kept_wrong == 0


def test_only_trusted_pixels_are_judged_and_used():
    """A pixel already distrusted is neither dropped again nor a neighbour: the faulty pixel beside a distrusted
    one is still found, and a field with no trusted pixels returns nothing."""
    rng = np.random.default_rng(3)
    shape, idx, rim, pos, sig, step = _field(rng)
    ok = np.ones(idx.size, bool)
    p = int(np.flatnonzero(~rim)[500])
    pos["y"][p] += 1.0
    ok[p + 1] = False
    pos["y"][p + 1] += 1.0                # distrusted, moved alike: must not shield p
    bad = isolated_jumps(shape, idx, ok, pos, sig)
    assert bad[p] and not bad[p + 1]
    assert not isolated_jumps(shape, idx, np.zeros(idx.size, bool), pos, sig).any()
