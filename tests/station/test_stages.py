"""The reduction's named stages: running them one by one gives the same bits as ``analyse``, and a stage
rerun with one input changed moves the figures the way that input should."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.geometry import Pose
from sofast_station.measure import analysis, pipeline
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import capture


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    from tests.conftest import ROOT, SMALL_STATION
    tmp = tmp_path_factory.mktemp("stages")
    path = tmp / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    cfg = load_config(path)
    station = open_station(cfg, seed=4)
    try:
        frames, distance = capture(station)
    finally:
        station.close()
    return cfg, frames, distance


def _figures(a):
    return {k: v for k, v in a.figures.items() if k != "timings_s"}


def test_stages_give_the_same_bits_as_analyse(small_capture):
    cfg, frames, distance = small_capture
    a = analysis.analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis)
    red, timings = pipeline.reduce_stages(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis)
    b = pipeline.to_analysis(red, timings)
    assert _figures(a) == _figures(b)
    assert np.array_equal(a.slopes, b.slopes) and np.array_equal(a.points_facet_m, b.points_facet_m)
    assert {"mask", "phase", "rays", "pose", "iterate", "fit", "report"} == set(timings)
    # Rerunning any stage with the same inputs reproduces the figures exactly.
    for start in pipeline.STAGES[1:]:
        again = pipeline.rerun(red, start, fringes=cfg.fringes, geometry=cfg.geometry, design=cfg.design,
                               measured_distance_m=distance, settings=cfg.analysis)
        assert again.figures == red.figures, start


def test_rerun_with_one_input_changed(small_capture):
    cfg, frames, distance = small_capture
    red, _ = pipeline.reduce_stages(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis)
    common = dict(fringes=cfg.fringes, design=cfg.design, settings=cfg.analysis)
    f0 = red.figures["focal_length_x_m"]
    # A longer measured distance puts the facet farther away: the same slopes over a larger lever arm,
    # so a longer focal length (roughly in proportion for a facet near its centre of curvature).
    far = pipeline.rerun(red, "pose", geometry=cfg.geometry, measured_distance_m=distance + 0.01, **common)
    assert far.figures["focal_length_x_m"] > f0
    assert far.figures["measured_distance_m"] == pytest.approx(distance + 0.01)
    assert far.pose.facet_to_camera.translation[2] != red.pose.facet_to_camera.translation[2]
    # A screen shifted along its own x by 1 mm tilts every measured normal by about 0.5 mm / (2 d): the
    # boresight takes that up, the focal length barely moves.
    g = cfg.geometry
    shift = Pose(np.eye(3), g.screen_to_camera.rotation @ np.array([0.001, 0.0, 0.0]))
    moved = dataclasses.replace(g, screen_to_camera=shift.compose(g.screen_to_camera))
    r2 = pipeline.rerun(red, "rays", geometry=moved, measured_distance_m=distance, **common)
    assert r2.phases is red.phases and r2.region is red.region
    d_bore = r2.figures["boresight_mrad"]["y"] - red.figures["boresight_mrad"]["y"]
    assert abs(abs(d_bore) - 1000 * 0.001 / (2 * distance)) < 0.3 * 1000 * 0.001 / (2 * distance)
    assert abs(r2.figures["focal_length_x_m"] / f0 - 1) < 1e-3
