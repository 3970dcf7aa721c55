"""The display's self-test (issue 44, item 2): the fringes' mean level against the dark and white frames.

The frames are drawn here from their definition (a display of relative response v^p to a linear level v, a
facet of random reflectance, room light in every frame), not by the code under test."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.fringes import FringeSet
from sofast_station.measure.display_response import expected_mean_level, fringe_mean_levels


def _frames(power: float, rng, shape=(120, 160), floor=0.02, top=1.0, noise_dn=0.0):
    """Dark, white and the phase-step sets of a display whose response is level**power, seen on a facet of
    reflectance 40-200 DN of white over a room light of 5-15 DN; the outer 20 px are background."""
    fringes = FringeSet()
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    white_dn = rng.uniform(40.0, 200.0, shape)
    room = rng.uniform(5.0, 15.0, shape)
    inside = (rows >= 20) & (rows < shape[0] - 20) & (cols >= 20) & (cols < shape[1] - 20)
    white_dn[~inside] = 0.0
    frames = [room, room + white_dn]
    for axis, periods in (("x", fringes.periods_x), ("y", fringes.periods_y)):
        coord = (cols / shape[1]) if axis == "x" else (rows / shape[0])
        for p in periods:
            for k in range(fringes.phase_steps):
                level = floor + (top - floor) * (0.5 + 0.5 * np.cos(2 * np.pi * p * coord - 2 * np.pi * k / 4))
                frames.append(room + white_dn * level ** power)
    frames = np.array(frames) + rng.normal(0.0, noise_dn, (len(frames),) + shape)
    return frames, fringes


def test_a_linear_display_reads_the_tables_mean_level():
    """Linear (power 1): every pixel's mean over the four steps is (floor + top) / 2 exactly, whatever its
    reflectance and room light; the background is left out. With 1 DN of noise on 40-200 DN of white the
    per-pixel ratio scatters by about 1 / (2 sqrt(4)) / 120 ~ 0.002, its median over the 2,400 pixels of the grid
    (every 2nd pixel) by ~5e-5: within 5e-4."""
    rng = np.random.default_rng(3)
    frames, fringes = _frames(1.0, rng)
    found = fringe_mean_levels(frames, fringes.slices(), min_span_dn=10.0)
    assert found["level"] == pytest.approx(expected_mean_level(0.02, 1.0), abs=1e-6)
    assert found["n_pixels"] == 40 * 60 and set(found["levels"]) == {"x0", "x1", "y0", "y1"}
    noisy = fringe_mean_levels(_frames(1.0, rng, noise_dn=1.0)[0], fringes.slices(), min_span_dn=10.0)
    assert noisy["level"] == pytest.approx(0.51, abs=5e-4)


@pytest.mark.parametrize("power", [0.85, 1.15])
def test_a_display_whose_response_moved_reads_its_own_mean(power):
    """A response level**power (a display at gamma 2.2 * power behind a table made at 2.2): the mean level is
    the mean over a period of (floor + (top - floor)(1 + cos phi) / 2)**power, computed here by quadrature;
    the median of a ratio sampled at the pixels' phases (the x sets' columns sample a period unevenly) departs
    from the period's mean by the sampling only: within 2e-3, while the departure itself is 0.02 or more."""
    rng = np.random.default_rng(5)
    frames, fringes = _frames(power, rng)
    found = fringe_mean_levels(frames, fringes.slices(), min_span_dn=10.0)
    phi = np.linspace(0.0, 2 * np.pi, 100000, endpoint=False)
    want = float(np.mean((0.02 + 0.98 * (0.5 + 0.5 * np.cos(phi))) ** power))
    assert abs(want - 0.51) > 0.02
    assert found["level"] == pytest.approx(want, abs=2e-3)


def test_a_frame_with_no_facet_reads_nothing():
    frames = np.full((18, 30, 40), 12.0)
    found = fringe_mean_levels(frames, FringeSet().slices(), min_span_dn=10.0)
    assert found["level"] is None and found["n_pixels"] == 0
    with pytest.raises(ValueError, match="frames must be"):
        fringe_mean_levels(frames[0], FringeSet().slices(), min_span_dn=10.0)
