"""Issue 12, item 10: bad captures made by the twin are refused, or judged invalid, for the right cause.

Each was once passed or blamed on something else: y sets captured before x sets passed with wrong
focal lengths; a fully saturated capture was "white equals dark"; a facet 40 % out of view was "corners
far from where the fixture puts them"; room light at 90 % of white was "frames out of order".
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.calibrate.records import load_radiometric
from sofast_station.config import load_config
from sofast_station.devices.renderer import FringeRenderer
from sofast_station.errors import CaptureError, FacetNotFoundError
from sofast_station.measure.analysis import analyse
from sofast_station.result.verdict import judge
from sofast_station.twin.parameters import TrueFacet, TwinOptics
from sofast_station.twin.station import TwinStation
from tests.conftest import ROOT, SMALL_STATION


@pytest.fixture(scope="module")
def station(tmp_path_factory):
    """The small dish station: its configuration, the displayed images and the traced twin."""
    path = tmp_path_factory.mktemp("causes") / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=path.parent / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    cfg = load_config(path)
    record = load_radiometric(ROOT / "calibration/simulated_radiometric.json")
    scr = cfg.geometry.screen
    with FringeRenderer(scr.width_px, scr.height_px, lut=record.lut, floor_level=record.floor_level,
                        max_level=record.max_level) as renderer:
        images = renderer.render_all(cfg.fringes.patterns())
    twin = TwinStation(cfg.geometry, cfg.design, TrueFacet.from_dict(cfg.simulation["facet"]), TwinOptics())
    return cfg, images, twin


def capture(twin, images, seed=1, **kwargs):
    rng = np.random.default_rng(seed)
    return np.stack([twin.capture(img, rng, **kwargs) for img in images])


def judged(cfg, twin, frames):
    a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis)
    return a, judge(a.figures, cfg.design, cfg.limits, cfg.quality)


def test_y_sets_captured_before_x_sets_are_invalid(station):
    cfg, images, twin = station
    frames = capture(twin, images)
    a, verdict = judged(cfg, twin, frames)
    assert verdict["verdict"] == "pass", verdict            # no false alarm on the right order
    curl = a.figures["slope_curl"]
    assert curl["antisymmetric_rms_per_m"] < 0.2 * curl["symmetric_rms_per_m"]
    swapped = frames.copy()
    swapped[2:10], swapped[10:18] = frames[10:18], frames[2:10]
    a, verdict = judged(cfg, twin, swapped)
    print(a.figures["slope_curl"], verdict)
    assert verdict["verdict"] == "invalid"
    assert any("x and y fringe sets were swapped" in r for r in verdict["reasons"])


def test_fully_saturated_capture_is_refused_as_saturated(station):
    cfg, images, twin = station
    for frames in (np.full_like(capture(twin, images[:2]), 255, shape=(18, *cfg.geometry.camera.shape)),
                   capture(twin, images, exposure_s=100 * twin.optics.reference_exposure_s)):
        with pytest.raises(CaptureError, match="saturated") as info:
            judged(cfg, twin, frames)
        assert "white frame equals the dark" not in str(info.value)


def test_facet_forty_percent_out_of_view_is_refused_as_cut_off(station):
    """The camera aimed 130 px too high (its principal point moved): 40 % of the facet below the image."""
    cfg, images, twin = station
    cam = cfg.geometry.camera
    k = cam.matrix.copy()
    rows = np.flatnonzero(twin.coverage.any(axis=1))
    k[1, 2] += (cam.height_px - 1 - rows[-1]) + 0.4 * (rows[-1] - rows[0])
    aimed = TwinStation(dataclasses.replace(cfg.geometry, camera=dataclasses.replace(cam, matrix=k)), cfg.design,
                        twin.facet, twin.optics)
    seen = np.flatnonzero(aimed.coverage.any(axis=1))
    assert seen[-1] == cam.height_px - 1
    with pytest.raises(FacetNotFoundError, match="cut off at the image's bottom edge") as info:
        judged(cfg, aimed, capture(aimed, images))
    assert "out of view" in str(info.value) and "corners" not in str(info.value)


def test_room_light_at_ninety_percent_of_white_is_low_contrast(station):
    cfg, images, twin = station
    optics = dataclasses.replace(twin.optics, ambient=9.0 * twin.optics.reflectance)    # 90 % of white
    bright = twin.with_optics(optics)
    with pytest.raises(CaptureError, match="too much ambient light, too little contrast") as info:
        judged(cfg, bright, capture(bright, images))
    assert "out of order" not in str(info.value) and "too small" not in str(info.value)
