"""Issue 30, item 3: the heliostat analysis's pure parts, each against a forward model built here.

The whole analysis against the twin's truth: tests/station/test_heliostat_accuracy.py.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sofast_station.ensemble import load_ensemble
from sofast_station.errors import FacetNotFoundError
from sofast_station.geometry import CameraIntrinsics, Pose, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.measure.camera import RayTable, pixel_rays, project
from sofast_station.measure.heliostat import (WindowRays, canting_errors, canting_u, capture_scaled, combined_u,
                                              find_facets, nominal_outlines, tilted, window_camera)
from sofast_station.measure.uncertainty import Input, Sensitivities
from tests.conftest import ROOT

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")
CAMERA = CameraIntrinsics(400, 300, [[750, 0, 199.5], [0, 750, 149.5], [0, 0, 1]], [-0.03, 0.02, 0, 0, 0])
GEOMETRY = layout_station(ENSEMBLE.layout_design(), CAMERA, ScreenSpec(2600, 2600, 0.0011), separation_m=1.6)


def rot(rx_mrad, ry_mrad, rz_mrad=0.0):
    return Rotation.from_euler("ZYX", [1e-3 * rz_mrad, 1e-3 * ry_mrad, 1e-3 * rx_mrad]).as_matrix()


def test_canting_errors_recover_turns_and_remove_their_mean():
    design = {i: f.rotation for i, f in enumerate(ENSEMBLE.facets)}
    turns = {0: (0.8, -0.2, 1.0), 1: (-0.3, 0.5, -2.0), 2: (0.1, 0.1, 0.0), 3: (0.2, 0.4, 0.5)}
    common = rot(0.7, -1.1)            # the whole frame leaning: no canting error
    optical = {i: common @ design[i] @ rot(*turns[i]) for i in design}
    out = canting_errors(design, optical)
    mean = np.mean([t[:2] for t in turns.values()], axis=0)
    for i, t in turns.items():
        # to first order the turn less the facets' mean; to 1e-3 mrad exactly (the frame's 1.3 mrad lean is
        # taken out about the facets' own axes, each canted by 1.6 mrad)
        assert np.subtract(out["canting_mrad"][i], np.subtract(t[:2], mean)) == pytest.approx([0, 0], abs=2e-3)
        assert out["rz_mrad"][i] == pytest.approx(t[2], abs=2e-2)
    assert np.mean([out["canting_mrad"][i] for i in design], axis=0) == pytest.approx([0, 0], abs=1e-9)
    assert out["tilt_mrad"] == pytest.approx(np.add([0.7, -1.1], mean), abs=5e-3)


def sens(values_x: dict, kind="systematic") -> Sensitivities:
    inputs = [Input(name, "g", 1.0, "1", kind) for name in values_x]
    paths = [("optical_tilt_mrad", "x")]
    lin = np.array([[v] for v in values_x.values()])
    return Sensitivities(inputs, paths, lin, np.zeros_like(lin), 100)


def test_combined_u_adds_shared_inputs_before_squaring_and_random_parts_after():
    s = {0: sens({"camera fy": 0.1, "screen rz": 0.04}), 1: sens({"camera fy": 0.1, "screen rz": -0.04})}
    u_rand = {0: 0.02, 1: 0.04}
    w = {0: 0.5, 1: -0.5}                      # facet 0's canting: half the difference of the two
    got = combined_u(w, s, u_rand, ("optical_tilt_mrad", "x"))
    # camera fy moves both alike: gone; screen rz turns them apart: 0.5 * 0.08; random: halves of 0.01, 0.02
    expected = 2.0 * np.sqrt(0.04 ** 2 + (0.5 * 0.01) ** 2 + (0.5 * 0.02) ** 2)
    assert got == pytest.approx(expected, rel=1e-12)
    assert combined_u(w, {0: s[0], 1: None}, u_rand, ("optical_tilt_mrad", "x")) is None


def test_every_facets_canting_u_at_once_is_the_difference_from_the_mean():
    rng = np.random.default_rng(3)
    s = {i: sens({"camera fy": float(rng.normal()), "screen rz": float(rng.normal()), "distance": 0.1 * i})
         for i in range(5)}
    u_rand = {i: 0.01 * (i + 1) for i in range(5)}
    path = ("optical_tilt_mrad", "x")
    every = canting_u(s, u_rand, path)
    for i in range(5):
        w = {j: (1.0 if j == i else 0.0) - 0.2 for j in range(5)}
        assert every[i] == pytest.approx(combined_u(w, s, u_rand, path), rel=1e-12)


def test_canting_u_keeps_the_curvatures_offset_as_the_single_facet_budget_does():
    # An input the tilt responds to as q z^2 (no linear part) moves every facet's tilt by q on average, not
    # only spreads it: the single facet's budget adds that offset (budget.combine), and so must the canting's.
    s = {0: sens({"screen rz": 0.0}), 1: sens({"screen rz": 0.0})}
    s[0].curvature[0, 0], s[1].curvature[0, 0] = 0.03, -0.01
    u_rand = {0: 0.0, 1: 0.0}
    w = {0: 0.5, 1: -0.5}
    q = 0.5 * 0.03 + 0.5 * 0.01                  # the difference's curvature
    assert combined_u(w, s, u_rand, ("optical_tilt_mrad", "x")) == pytest.approx(2.0 * np.sqrt(2 * q ** 2 + q ** 2),
                                                                                  rel=1e-12)
    assert canting_u(s, u_rand, ("optical_tilt_mrad", "x"))[0] == pytest.approx(2.0 * np.sqrt(3.0) * q, rel=1e-12)


def test_canting_u_takes_the_display_response_at_the_captures_own_evidence():
    # The sensitivities are computed at [uncertainty] response_phase_rad; the single facet's budget scales the
    # display response's rows to what the capture shows (capture_evidence.capture_scales): so must the canting.
    inputs = [Input("display response cos", "display response", 0.003, "rad"),
              Input("screen rz", "camera-to-screen rotation", 0.5, "mrad")]
    lin = np.array([[0.02], [0.04]])
    cur = np.array([[0.001], [0.002]])
    s = Sensitivities(inputs, [("optical_tilt_mrad", "x")], lin, cur, 100)
    figures = {"uncertainty_budget": {"display_response": {"u_rad": 0.012, "source": "capture"}}}
    scaled = capture_scaled(s, figures)
    assert scaled.linear[:, 0] == pytest.approx([0.08, 0.04], rel=1e-12)       # 4 times the reference u
    assert scaled.curvature[:, 0] == pytest.approx([0.016, 0.002], rel=1e-12)
    assert s.linear[0, 0] == 0.02                                                # the cached record unchanged
    assert capture_scaled(s, {}) is s                                            # no evidence: as computed


def test_the_pose_turned_about_its_measure_point_keeps_the_distance():
    pose = GEOMETRY.fixture_to_camera
    p = ENSEMBLE.measure_point_m
    moved = tilted(pose, ENSEMBLE, (1.5, -2.0))
    assert moved.apply(p) == pytest.approx(pose.apply(p), abs=1e-12)
    expected = pose.rotation @ Rotation.from_euler("YX", [-2.0e-3, 1.5e-3]).as_matrix()
    assert moved.rotation == pytest.approx(expected, abs=1e-14)


def test_a_window_is_the_same_camera_with_its_principal_point_moved():
    window = (40, 70, 200, 260)
    cam = window_camera(CAMERA, window)
    assert (cam.width_px, cam.height_px) == (190, 160)
    pts = np.array([[0.1, -0.05, 4.0], [-0.2, 0.1, 4.5]])
    ident = Pose(np.eye(3), np.zeros(3))
    assert project(cam, ident, pts) == pytest.approx(project(CAMERA, ident, pts) - [70, 40], abs=1e-9)
    table = RayTable(CAMERA)
    idx = np.array([0, 5, 190 * 7 + 3, 190 * 160 - 1])
    rows, cols = np.divmod(idx, 190)
    assert np.array_equal(WindowRays(table, window, 400).take(idx), pixel_rays(CAMERA, cols + 70, rows + 40))


def painted(outlines, keep=(0, 1, 2, 3), shift_px=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Dark and white frames with the facets' nominal images painted white (a forward model of the mask)."""
    import cv2
    white = np.full(CAMERA.shape, 5, np.uint8)
    for i in keep:
        cv2.fillPoly(white, [np.round((outlines[i] + shift_px) * 16).astype(np.int32)], 200, shift=4)
    return np.full(CAMERA.shape, 5, np.uint8), white


def test_facets_are_found_and_told_apart_or_named():
    outlines = nominal_outlines(GEOMETRY, ENSEMBLE)
    dark, white = painted(outlines, shift_px=(2.0, -1.5))       # the heliostat 2 px off its nominal place
    regions, labels = find_facets(dark, white, GEOMETRY, ENSEMBLE, 20)
    assert [r.status for r in regions] == ["measured"] * 4
    for r in regions:
        assert len(r.components) == 1 and abs(r.area_px / r.expected_area_px - 1) < 0.05
    assert len({r.components[0] for r in regions}) == 4
    dark, white = painted(outlines, keep=(0, 2, 3))
    regions, _ = find_facets(dark, white, GEOMETRY, ENSEMBLE, 20)
    assert regions[1].status == "missing" and "R1C2 is missing" in regions[1].reason


def test_two_facets_that_are_one_region_are_refused_naming_both():
    import cv2
    outlines = nominal_outlines(GEOMETRY, ENSEMBLE)
    dark, white = painted(outlines)
    a, b = outlines[0], outlines[1]        # fill the gap between R1C1 and R1C2
    bridge = np.array([a[np.argmax(a[:, 0])], b[np.argmin(b[:, 0])]])
    cv2.line(white, tuple(np.round(bridge[0]).astype(int)), tuple(np.round(bridge[1]).astype(int)), 200, 3)
    with pytest.raises(FacetNotFoundError, match="R1C1, R1C2 are one region"):
        find_facets(dark, white, GEOMETRY, ENSEMBLE, 20)


def test_a_facet_beyond_its_window_is_cut_off():
    outlines = nominal_outlines(GEOMETRY, ENSEMBLE)
    moved = [o + ([40.0, 0.0] if i == 3 else [0.0, 0.0]) for i, o in enumerate(outlines)]
    dark, white = painted(moved)
    regions, _ = find_facets(dark, white, dataclasses.replace(GEOMETRY), ENSEMBLE, 20)
    assert regions[3].status == "cut off" and "R2C2" in regions[3].reason
