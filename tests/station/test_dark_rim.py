"""Issue 26, item 3: a glass rim the design declares dark (``edge_rim_dark``) puts the outline the rim's
width outside the edge the image shows, to a few hundredths of a pixel; a rim so declared that shows the
screen after all is named from its fringes and put midway, as a rim of unknown kind.

The twin draws the rim (`twin/edges.py`: a band ``bevel_width_mm`` wide inside the outline, its normal
turned outward by ``bevel_tilt_mrad``): 400 mrad looks past the screen (dark), 5 mrad shows the screen a
few centimetres from where the mirror beside it does (lit). The dish's camera at a quarter of its
resolution (the rim 0.6 px wide in the image), the heliostat's at half.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.measure import corners
from tests.station.test_corners_on_twin import corner_rms_px, measure


def rim_px(kind: str, scale: int, width_mm: float, dark: bool) -> float:
    from tests.station.test_corners_on_twin import scaled

    cfg, _ = scaled(kind, scale)
    design = dataclasses.replace(cfg.design, edge_rim_m=1e-3 * width_mm, edge_rim_dark=dark)
    hints = corners.outline_hints(design, cfg.geometry.camera, cfg.geometry.fixture_to_camera)
    return float(np.median(hints["rim_px"]))


@pytest.mark.parametrize("kind,scale", [("dish", 4), ("heliostat", 2)])
def test_a_dark_rim_declared_dark_puts_the_corners_on_the_outline(kind, scale):
    optics = {"bevel_width_mm": 2.5, "bevel_tilt_mrad": 400.0, "bevel_reflectance": 0.9}
    dark, twin = measure(kind, scale, optics=optics, rim_dark=True)
    unknown, _ = measure(kind, scale, optics=optics, rim_dark=False)
    w = rim_px(kind, scale, 2.5, True)
    e_dark, e_unknown = corner_rms_px(dark, twin), corner_rms_px(unknown, twin)
    print(f"{kind}: rim {w:.2f} px; corners {e_dark:.3f} px declared dark, {e_unknown:.3f} px of unknown kind")
    assert dark.figures["outline_lit_rim_sides"] == []
    assert e_dark < 0.05
    # of unknown kind the side is put midway: half the rim's width off, which the dark declaration removes
    # (both sides through a corner move: the corner by sqrt(2) times a side's offset)
    assert e_unknown == pytest.approx(np.sqrt(2) * 0.5 * w, rel=0.2)


@pytest.mark.parametrize("kind,scale", [("dish", 4), ("heliostat", 2)])
def test_a_rim_declared_dark_that_shows_the_screen_is_named_and_put_midway(kind, scale):
    optics = {"bevel_width_mm": 2.5, "bevel_tilt_mrad": 5.0, "bevel_reflectance": 0.9}
    a, twin = measure(kind, scale, optics=optics, rim_dark=True)
    w = rim_px(kind, scale, 2.5, True)
    err = corner_rms_px(a, twin)
    print(f"{kind}: rim {w:.2f} px, lit; sides named {a.figures['outline_lit_rim_sides']}, corners {err:.3f} px")
    assert a.figures["outline_lit_rim_sides"] == [1, 2, 3, 4]
    # placed as dark the sides would lie r w = 0.9 w outside the outline (corners 1.27 w off); midway
    # (0.5 - r) w = 0.4 w inside (corners 0.57 w)
    assert err < 0.7 * w


def test_the_rim_declaration_is_checked_and_kept():
    from sofast_station.errors import ConfigError
    from sofast_station.facet import FacetDesign
    from tests.station.test_corners_on_twin import scaled

    design = scaled("dish", 4)[0].design
    with pytest.raises(ConfigError, match="edge_rim_dark = true needs the rim's width, edge_rim_m"):
        dataclasses.replace(design, edge_rim_m=0.0, edge_rim_dark=True)
    with pytest.raises(ConfigError, match="edge_rim_dark must be true or false, got 'yes'"):
        dataclasses.replace(design, edge_rim_m=0.002, edge_rim_dark="yes")
    dark = dataclasses.replace(design, edge_rim_m=0.002, edge_rim_dark=True)
    assert FacetDesign.from_dict(dark.to_dict()).edge_rim_dark is True
    # a design without the declaration writes what it wrote before (its recipe hash unchanged)
    assert "edge_rim_dark" not in dataclasses.replace(design, edge_rim_m=0.002).to_dict()
