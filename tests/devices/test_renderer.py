"""The shader's images against a numpy evaluation of the same definition."""

import numpy as np
import pytest

from sofast_station.devices.renderer import FringeRenderer
from sofast_station.errors import DisplayError
from sofast_station.fringes import FringeSet, Pattern


@pytest.fixture(scope="module")
def renderer():
    r = FringeRenderer(640, 360)
    yield r
    r.release()


def expected_fringe(width, height, pattern, lut=None, floor=0.0, maximum=1.0):
    if pattern.axis == "x":
        frac = (np.arange(width) + 0.5) / width
        frac = np.broadcast_to(frac, (height, width))
    else:
        frac = (height - np.arange(height) - 0.5) / height
        frac = np.broadcast_to(frac[:, None], (height, width))
    t = 0.5 + 0.5 * np.cos(2 * np.pi * pattern.periods * frac - pattern.shift_rad)
    y = floor + (maximum - floor) * t
    if lut is not None:
        y = np.interp(y, np.linspace(0, 1, lut.size), lut)
    return np.floor(y * 255 + 0.5)


def test_each_fringe_matches_its_definition(renderer):
    for pattern in FringeSet().patterns()[2:]:
        img = renderer.render(pattern).astype(int)
        ref = expected_fringe(640, 360, pattern)
        # float32 in the shader against float64 here: at most one level, at rounding ties only
        assert np.abs(img - ref).max() <= 1, pattern.label
        assert np.mean(img != ref) < 0.03, pattern.label


def test_row_zero_is_the_top_and_phase_zero_is_at_the_bottom_for_y(renderer):
    img = renderer.render(Pattern("fringe", axis="y", periods=1.0, shift_rad=0.0))
    # cos(2 pi u / H) is brightest at u = 0 (bottom edge = last row) and at u = H.
    assert img[-1, 0] >= 254 and img[0, 0] >= 254 and img[180, 0] <= 1


def test_uniform_frames(renderer):
    assert renderer.render(Pattern("uniform", command=0)).max() == 0
    assert renderer.render(Pattern("uniform", command=255)).min() == 255
    assert np.all(renderer.render(Pattern("uniform", command=77)) == 77)


def test_lookup_table_and_levels_are_applied():
    lut = np.linspace(0, 1, 512) ** (1 / 2.2)
    with FringeRenderer(320, 200, lut=lut, floor_level=0.1, max_level=0.9) as r:
        p = Pattern("fringe", axis="x", periods=4.0, shift_rad=np.pi / 2)
        img = r.render(p).astype(int)
        ref = expected_fringe(320, 200, p, lut, 0.1, 0.9)
        assert np.abs(img - ref).max() <= 1


def test_bad_lookup_table_is_refused():
    with pytest.raises(DisplayError, match="lookup table must increase"):
        FringeRenderer(32, 32, lut=np.array([0.0, 0.5, 0.4, 1.0]))
    with pytest.raises(DisplayError, match="finite"):
        FringeRenderer(32, 32, lut=np.array([0.0, np.nan, 1.0]))
