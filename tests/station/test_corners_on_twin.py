"""Issue 12, item 5: facet corners to a tenth of a pixel against the twin's true corners, on sharply
area-sampled, blurred and point-sampled edges, and the gore's twist and optical tilt that depend on them.

Cameras are scaled down (same field of view) to keep the tests cheap: the dish, gore and heliostat
stations at a quarter of their resolution for the corners, the gore at half for its twist and tilt
(a corner error of 0.03 px there turns the boresight frame about the gore's normal by ~0.05 mrad, and a
turn of delta puts delta / (2 f) of twist on this off-axis facet's slopes).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.calibrate.records import load_radiometric
from sofast_station.config import load_config
from sofast_station.devices.renderer import FringeRenderer
from sofast_station.measure.analysis import analyse
from sofast_station.twin.parameters import TrueFacet, TwinOptics
from sofast_station.twin.station import TwinStation
from sofast_station.twin.truth import ground_truth
from tests.conftest import ROOT
from tests.station.test_facets import FACETS


def scaled(kind: str, scale: int, k1: float | None = None):
    """The station of *kind* with its camera's resolution divided by *scale* (same field of view), and its
    lens's radial distortion k1 when given."""
    path, facet = FACETS[kind]
    cfg = load_config(ROOT / path)
    cam = cfg.geometry.camera
    k = cam.matrix.copy()
    k[:2] /= scale
    w, h = cam.width_px // scale, cam.height_px // scale
    k[0, 2], k[1, 2] = (w - 1) / 2, (h - 1) / 2
    distortion = np.array(cam.distortion, dtype=float)
    if k1 is not None:
        distortion[0] = k1
    cam = dataclasses.replace(cam, width_px=w, height_px=h, matrix=k, distortion=distortion)
    return dataclasses.replace(cfg, geometry=dataclasses.replace(cfg.geometry, camera=cam)), facet


def measure(kind: str, scale: int, blur_px: float = 0.0, edge_sampling: str = "area", rz_mrad: float = 0.0,
            k1: float | None = None, optics: dict | None = None, uncertainty: bool = False, rim_dark: bool = False,
            shape: dict | None = None):
    """The twin's station of *kind* analysed (noise-free), and the twin; *shape* overrides the true facet's keys."""
    cfg, facet = scaled(kind, scale, k1)
    facet = {**facet, **(shape or {})}
    optics = {"blur_px": blur_px, "edge_sampling": edge_sampling, **(optics or {})}
    if optics.get("bevel_width_mm"):          # the design declares its glass rim (and, with rim_dark, its kind)
        rim_m = 1e-3 * optics["bevel_width_mm"]
        cfg = dataclasses.replace(cfg, design=dataclasses.replace(cfg.design, edge_rim_m=rim_m, edge_rim_dark=rim_dark))
    twin = TwinStation(cfg.geometry, cfg.design, TrueFacet.from_dict({**facet, "placement_mrad": [0.0, 0.0, rz_mrad]}),
                       TwinOptics(**optics).noise_free())
    record = load_radiometric(ROOT / "calibration/simulated_radiometric.json")
    scr = cfg.geometry.screen
    with FringeRenderer(scr.width_px, scr.height_px, lut=record.lut, floor_level=record.floor_level,
                        max_level=record.max_level) as renderer:
        frames = np.stack([twin.capture(img) for img in renderer.render_all(cfg.fringes.patterns())])
    a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                uncertainty=cfg.uncertainty if uncertainty else None)
    return a, twin


def corner_rms_px(a, twin) -> float:
    err = a.corners_px - twin.corner_pixels()         # both in the design outline's corner order
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))


@pytest.mark.parametrize("kind", ["dish", "gore", "heliostat"])
@pytest.mark.parametrize("edge", ["sharp", "blurred"])
def test_corners_within_a_tenth_of_a_pixel(kind, edge):
    a, twin = measure(kind, 4, blur_px=1.0 if edge == "blurred" else 0.0)
    rms = corner_rms_px(a, twin)
    print(f"{kind}, {edge}: corners {rms:.3f} px RMS from truth")
    assert rms < 0.1


@pytest.mark.parametrize("kind", ["dish", "heliostat"])
def test_point_sampled_staircase_edges(kind):
    """Point-sampled edges (each pixel facet or background: a staircase) of a facet turned 20 mrad in
    the fixture, so its sides cross rows and columns: the steps locate them."""
    a, twin = measure(kind, 2, edge_sampling="point", rz_mrad=20.0)
    rms = corner_rms_px(a, twin)
    print(f"{kind}, point-sampled: corners {rms:.3f} px RMS from truth")
    assert rms < 0.1


def twist_and_tilt_errors(a, twin, label: str) -> tuple[float, dict]:
    """The twist's (mrad/m) and the optical tilt's (mrad, x and y) errors against the twin's truth, printed."""
    truth = ground_truth(twin, a.valid)
    twist = a.figures["twist_mrad_per_m"] - truth["twist_mrad_per_m"]
    tilt = {ax: a.figures["optical_tilt_mrad"][ax] - truth["optical_tilt_mrad"][ax] for ax in "xy"}
    print(f"gore, {label}: corners {corner_rms_px(a, twin):.3f} px, twist error {twist:+.5f} mrad/m, "
          f"optical tilt error {tilt['x']:+.4f}, {tilt['y']:+.4f} mrad")
    return twist, tilt


@pytest.mark.parametrize("blur_px", [0.0, 1.0])
def test_gore_twist_and_optical_tilt(blur_px):
    """The gore's twist within 0.002 mrad/m and its optical tilt within 0.05 mrad of truth (the corner
    errors of sharply sampled edges once put 0.009 mrad/m and 0.4 mrad there)."""
    a, twin = measure("gore", 2, blur_px=blur_px)
    twist, tilt = twist_and_tilt_errors(a, twin, f"blur {blur_px} px")
    assert abs(twist) < 0.002
    assert abs(tilt["x"]) < 0.05 and abs(tilt["y"]) < 0.05


@pytest.mark.parametrize("model", ["disk blur", "bevelled rim"])
def test_gore_twist_on_other_edge_models_through_a_distorting_lens(model):
    """Issue 26: on an independent renderer the gore's twist was 0.0065-0.0071 mrad/m off (its corners 0.7 px).
    On the twin's other edge models (a 1.5 px defocus disk, a 2 mm glass rim the design declares dark),
    through a lens with k1 = -0.3: within 0.002 mrad/m, the optical tilt within 0.05 mrad. (Strong
    vignetting: 0.0002 mrad/m, left to the corner tests, tests/station/test_corner_models.py.)"""
    optics = {"disk blur": {"defocus_px": 1.5},
              "bevelled rim": {"bevel_width_mm": 2.0, "bevel_tilt_mrad": 400.0}}[model]
    a, twin = measure("gore", 2, k1=-0.3, optics=optics, rim_dark=True)
    twist, tilt = twist_and_tilt_errors(a, twin, f"{model}, k1 -0.3")
    assert abs(twist) < 0.002
    assert abs(tilt["x"]) < 0.05 and abs(tilt["y"]) < 0.05


@pytest.mark.parametrize("rz_mrad", [3.0, -8.0])
def test_gore_twist_at_its_own_resolution_on_a_coarse_supersampled_edge(rz_mrad):
    """Issue 26, item 3: a 2 x 2 sub-ray renderer draws the edge as half-pixel steps (corners 0.07-0.13 px
    at half resolution, the twist 0.004-0.009 mrad/m off there). At the gore station's own 1600 x 1200, the
    same edge through k1 = -0.3, the facet turned a few mrad in the fixture so that its sides step through
    the pixel rows, leaves the twist within 0.002 mrad/m. (Exactly square to the pixel grid the short sides
    are known only to their half-pixel interval, as point-sampled ones: 0.005 mrad/m, within U; the verdict
    names such sides.) docs/uncertainty.md, the gore's twist by resolution."""
    a, twin = measure("gore", 1, k1=-0.3, rz_mrad=rz_mrad, optics={"edge_sampling": "grid", "edge_grid": 2})
    twist, _ = twist_and_tilt_errors(a, twin, f"2 x 2 grid, full resolution, turned {rz_mrad:g} mrad")
    assert abs(twist) < 0.002


def test_gore_twist_on_point_sampled_edges_within_its_uncertainty():
    """Point sampled, the gore's short sides square to the pixel grid are only known to lie between two
    pixel centres (0.26 px of corner error here): its twist is not within 0.002 mrad/m, and cannot be
    from this image, but within the U it states."""
    a, twin = measure("gore", 2, edge_sampling="point", k1=-0.3, uncertainty=True)
    twist, _ = twist_and_tilt_errors(a, twin, f"point sampled, k1 -0.3, twist U {a.figures['twist_mrad_per_m_U']:.4f}")
    assert abs(twist) <= a.figures["twist_mrad_per_m_U"]


def test_gore_placement_tilt_does_not_follow_its_twist():
    """Issue 47, item 2: the gore turned 20 mrad about its normal (sharp edges, corners within 0.02 px),
    with a twist of 0.42 mrad/m its placement's tilt about x was 1.29 mrad off at full resolution (1.1 times
    its U): the corners were taken at the design surface's height, the twist lifts the wide end's by
    -+0.29 mm, and four corners cannot tell that from a tilt (3.3 mrad about x per mrad/m of twist; a
    Jacobian of the corner pose puts 0.008 px of corner error at only 0.15 mrad). The corners now lie on
    the measured surface. Two facets that differ only in their twist (0 and 0.42 mrad/m) have the same
    placement: the difference of their errors cancels the corners' own error (the edge pixels move by the
    surface's 0.3 mm of height, < 0.005 px), so it is held to 0.15 mrad, a tenth of the twist's old
    effect (1.4 mrad here before the change). Each error, and the boresight's about x (measured from the
    same corner pose: it was 1.34 mrad off), is held to 0.5 mrad, below the spread the corners' 0.02 px give
    it at half resolution (their Jacobian: 39 mrad per px, about 0.6 mrad for 0.015 px per coordinate; here
    deterministic, measured -0.05 to -0.21 mrad). The boresight's change with the twist also holds the
    optical tilt's (-0.1 mrad: the shape is still measured in the first pose's frame), so only its size is held."""
    errors = {}
    for twist in (0.0, 0.42):
        a, twin = measure("gore", 2, rz_mrad=20.0, shape={"twist_mrad_per_m": twist})
        truth = ground_truth(twin, a.valid)
        errors[twist] = (a.figures["placement"]["mrad"][0] - truth["placement"]["mrad"][0],
                         a.figures["boresight_mrad"]["x"] - truth["boresight_mrad"]["x"])
        print(f"twist {twist} mrad/m: corners {corner_rms_px(a, twin):.3f} px, placement rx error "
              f"{errors[twist][0]:+.3f} mrad, boresight x error {errors[twist][1]:+.3f} mrad")
    change = errors[0.42][0] - errors[0.0][0]
    assert abs(change) < 0.15, f"the placement's rx moved by {change:+.3f} mrad with the twist"
    assert all(abs(e) < 0.5 for pair in errors.values() for e in pair)
