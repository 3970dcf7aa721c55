"""The lit-rim check (measure/rim.py) on a drawn square outline and a drawn screen-position field: no side
flagged over 50 noise draws without a rim's jump; the side whose edge pixels jump, and only it, flagged."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.measure.corners import OutlineFit
from sofast_station.measure.rim import lit_rim_flags, lit_rim_sides, rim_jumps

SHAPE = (400, 400)
RIM_PX = 0.6
LO, HI = 100.3, 299.7          # the found edge (a dark rim's inner edge), pixels


def square_outline() -> OutlineFit:
    """Sides placed the rim's width outside the found edge (as for a rim declared dark)."""
    lo, hi = LO - RIM_PX, HI + RIM_PX
    corners = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]])
    sides = []
    for i in range(4):
        p, q = corners[i], corners[(i + 1) % 4]
        t = (q - p) / np.linalg.norm(q - p)
        sides.append([p[0], p[1], t[0], t[1], 0.0, 0.0, 0.0])
    return OutlineFit(corners, np.array(sides), np.zeros(4), np.full(4, 200), design_sides=np.array([2, 3, 0, 1]))


def field(rng, noise_m: float, jump_m: float = 0.0):
    """Region pixels (flat indices) and their screen positions (2, M), metres: a smooth curved field, noise,
    and *jump_m* (about 3.5 times the residuals' scatter) added to the top row's pixels (the side from
    corner 0 to 1, design side 3)."""
    rows, cols = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    inside = (cols >= np.floor(LO)) & (cols <= np.ceil(HI)) & (rows >= np.floor(LO)) & (rows <= np.ceil(HI))
    idx = np.flatnonzero(inside)
    r, c = np.divmod(idx, SHAPE[1])
    pos = np.vstack([0.004 * c + 2e-6 * (r - 200.0) ** 2, 0.005 * r - 3e-6 * (c - 200.0) ** 2])
    pos += noise_m * rng.standard_normal(pos.shape)
    pos[:, r == np.floor(LO)] += np.array([[0.3], [1.0]]) * jump_m
    return idx, pos


def test_no_side_flagged_without_a_jump_over_50_noise_draws():
    outline = square_outline()
    flagged = 0
    for seed in range(50):
        idx, pos = field(np.random.default_rng(seed), 0.002)
        jumps = rim_jumps(outline, np.full(4, RIM_PX), SHAPE, idx, pos)
        assert np.all(np.isfinite(jumps))
        flagged += len(lit_rim_sides(jumps, outline.design_sides))
    assert flagged == 0


@pytest.mark.parametrize("seed", range(5))
def test_the_side_whose_edge_jumps_is_flagged_alone(seed):
    outline = square_outline()
    idx, pos = field(np.random.default_rng(seed), 0.002, jump_m=0.02)
    jumps = rim_jumps(outline, np.full(4, RIM_PX), SHAPE, idx, pos)
    assert jumps[0, 0] == pytest.approx(0.02 * np.hypot(0.3, 1.0), rel=0.2)
    assert lit_rim_sides(jumps, outline.design_sides) == [3]
    assert lit_rim_sides(jumps, None) == [1]


def test_a_side_without_decoded_pixels_is_not_judged():
    outline = square_outline()
    idx, pos = field(np.random.default_rng(0), 0.002, jump_m=0.02)
    pos[:, :] = np.nan
    jumps = rim_jumps(outline, np.full(4, RIM_PX), SHAPE, idx, pos)
    assert np.all(np.isnan(jumps)) and lit_rim_sides(jumps, outline.design_sides) == []


def test_flags_and_numbering():
    jumps = np.array([[5.0, 0.5, 1.0], [1.5, 0.1, 1.0], [5.0, 2.0, 1.0], [np.nan, np.nan, np.nan]])
    # only the first is over twice the scatter and five standard errors
    assert list(lit_rim_flags(jumps)) == [True, False, False, False]
    assert lit_rim_sides(jumps, np.array([2, 3, 0, 1])) == [3]
    assert lit_rim_sides(jumps, np.array([-1, 3, 0, 1])) == [1]          # unmatched: the outline's own number
