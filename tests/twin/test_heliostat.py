"""Issue 30, item 2: the twin renders a heliostat (several facets with gaps, each its own shape and canting
error) and gives every facet's truth.

Independent references: facet corners composed here with scipy's rotations and projected with OpenCV (not
the twin's own transforms), the canting truth of perfect facets solved here with scipy's root finder
(Levenberg-Marquardt).
A 400 x 300 camera (the 2x2 heliostat spans about 240 px) keeps each trace under a second.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.optimize import root
from scipy.spatial.transform import Rotation

from sofast_station.ensemble import load_ensemble
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.twin.parameters import TrueFacet, TwinOptics
from sofast_station.twin.heliostat import TrueHeliostat, TwinHeliostat, draw_heliostat, heliostat_truth, merge_traces
from sofast_station.twin.trace import TRACE_ARRAYS
from tests.conftest import ROOT

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")


def small_geometry(ensemble=ENSEMBLE, scale: int = 4):
    w, h = 1600 // scale, 1200 // scale
    cam = CameraIntrinsics(w, h, [[3000 / scale, 0, (w - 1) / 2], [0, 3000 / scale, (h - 1) / 2], [0, 0, 1]],
                           [-0.03, 0.02, 0, 0, 0])
    return layout_station(ensemble.layout_design(), cam, ScreenSpec(2600, 2600, 0.0011), separation_m=1.6)


GEOMETRY = small_geometry()


def perfect(canting=((0.0, 0.0, 0.0),) * 4, placement_mm=(0.0, 0.0, 0.0), placement_mrad=(0.0, 0.0, 0.0), **kw):
    facets = tuple(TrueFacet(placement_mrad=tuple(c)) for c in canting)
    return TrueHeliostat(facets=facets, placement_mm=placement_mm, placement_mrad=placement_mrad, **kw)


def rot(mrad):
    """R_z R_y R_x of (rx, ry, rz) mrad, by scipy."""
    rx, ry, rz = (1e-3 * a for a in mrad)
    return Rotation.from_euler("ZYX", [rz, ry, rx]).as_matrix()


def true_corners_px(heliostat: TrueHeliostat, i: int, geometry=GEOMETRY) -> np.ndarray:
    """Facet i's true corners in the image: composed here (fixture <- heliostat placement <- design pose <- the
    facet's own placement about its middle) and projected by OpenCV."""
    f = ENSEMBLE.facets[i]
    tf = heliostat.facets[i]
    xy = f.design.outline_m
    corners = np.column_stack([xy, (xy ** 2).sum(axis=1) / (4 * f.design.focal_length_m)])
    mid = np.array([*f.design.centroid_m, 0.0])
    in_design = (corners - mid) @ rot(tf.placement_mrad).T + mid + 1e-3 * np.asarray(tf.placement_mm)
    in_heliostat = in_design @ f.rotation.T + f.position_m
    in_fixture = in_heliostat @ rot(heliostat.placement_mrad).T + 1e-3 * np.asarray(heliostat.placement_mm)
    pose = geometry.fixture_to_camera
    rvec, _ = cv2.Rodrigues(pose.rotation)
    px, _ = cv2.projectPoints(in_fixture.reshape(-1, 1, 3), rvec, pose.translation, geometry.camera.matrix,
                              geometry.camera.distortion)
    return px.reshape(-1, 2)


def shoelace(p):
    return 0.5 * abs(float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])))


@pytest.fixture(scope="module")
def misplaced():
    h = perfect(canting=((1.0, -0.5, 2.0), (0.0, 0.8, -1.0), (-0.6, 0.0, 0.0), (0.3, 0.3, 0.5)),
                placement_mm=(2.0, -1.5, 3.0), placement_mrad=(1.5, -2.0, 1.0))
    return h, TwinHeliostat(GEOMETRY, ENSEMBLE, h, TwinOptics.noise_free())


def test_every_facet_is_seen_where_its_true_outline_projects(misplaced):
    h, twin = misplaced
    owner = twin.owner_image
    cover = twin.coverage
    for i in range(4):
        corners = true_corners_px(h, i)
        assert twin.facet_twins[i].corner_pixels() == pytest.approx(corners, abs=1e-6)
        area, perimeter = shoelace(corners), float(np.sum(np.linalg.norm(corners - np.roll(corners, 1, 0), axis=1)))
        seen = float(cover[owner == i].sum())
        # the coverage sums to the polygon's area, up to the curved edges' sub-pixel bow (a fraction of a pixel
        # along the perimeter)
        print(f"facet {i}: {seen:.1f} px covered, polygon {area:.1f} px")
        assert abs(seen - area) < 0.05 * perimeter
    # the gaps between the facets are dark: a row through the middle of the picture crosses them
    mid = owner[int(np.mean([true_corners_px(h, i)[:, 1].mean() for i in range(4)]))]
    assert (mid == -1).sum() > 0 and set(mid[mid >= 0].tolist()) <= {0, 1, 2, 3}


def test_a_white_frame_shows_four_facets_apart(misplaced):
    _, twin = misplaced
    white = twin.capture(np.full((2600, 2600), 255, np.uint8))
    n, labels = cv2.connectedComponents((white > 60).view(np.uint8))
    assert n - 1 == 4
    owner = twin.owner_image
    for c in range(1, n):
        assert len(set(owner[labels == c].tolist()) - {-1}) == 1       # each bright region is one facet


def test_a_missing_and_a_half_hidden_facet():
    h = perfect(missing=("R1C2",), obstructed={"R2C1": 0.5})
    twin = TwinHeliostat(GEOMETRY, ENSEMBLE, h, TwinOptics.noise_free())
    owner = twin.owner_image
    counts = {i: int((owner == i).sum()) for i in range(4)}
    assert counts[1] == 0 and 1 not in twin.facet_twins
    assert 0.4 < counts[2] / counts[0] < 0.6


def fake_trace(idx, hit, value, cov):
    t = SimpleNamespace(seen_idx=np.asarray(idx), hit_range_m=np.asarray(hit, float),
                        seen_coverage=np.asarray(cov, float))
    for name in TRACE_ARRAYS:
        if name != "hit_range_m":
            setattr(t, name, np.column_stack([np.asarray(value, float)] * 2))
    return t


def test_the_merged_picture_keeps_the_nearest_hit_and_adds_coverages():
    a = fake_trace([1, 2, 3], [5.0, 5.0, 5.0], [10, 20, 30], [1.0, 1.0, 0.4])
    b = fake_trace([3, 4], [4.0, 6.0], [300, 400], [0.3, 1.0])
    c = fake_trace([1], [4.5], [100], [1.0])
    coverage, seen, owner, arrays = merge_traces({7: a, 8: b, 9: c}, (1, 6))
    assert seen.tolist() == [1, 2, 3, 4]
    assert owner.tolist() == [9, 7, 8, 8]                 # pixel 1: c is nearer; pixel 3: b is nearer
    assert arrays["x_facet_m"][:, 0].tolist() == [100, 20, 300, 400]
    assert coverage.ravel().tolist() == pytest.approx([0, 1.0, 1.0, 0.7, 1.0, 0])   # summed, at most 1


def expected_canting(errors: dict) -> dict:
    """Canting of perfect facets (their optical frame is their true frame) by the definition, solved by scipy:
    the tilt T = R_y(b) R_x(a) of zero-mean rx, ry of R_i^T T^T R_i E_i."""
    rots = {i: ENSEMBLE.facets[i].rotation for i in errors}

    def angles(a, b):
        t = Rotation.from_euler("YX", [b, a]).as_matrix()
        out = []
        for i, e in errors.items():
            m = rots[i].T @ t.T @ rots[i] @ e
            out.append((math.atan2(m[2, 1], m[2, 2]), -math.asin(m[2, 0])))
        return np.array(out)

    a, b = root(lambda v: angles(*v).mean(axis=0), [0.0, 0.0], method="lm", tol=1e-15).x
    return {i: 1e3 * v for i, v in zip(errors, angles(a, b))}


def test_truth_of_perfect_facets_is_their_canting_error_less_the_mean(misplaced):
    h, twin = misplaced
    truth = heliostat_truth(twin, twin.coverage >= 1.0)
    expected = expected_canting({i: rot(h.facets[i].placement_mrad) for i in range(4)})
    for i, f in enumerate(ENSEMBLE.facets):
        got = truth["facets"][f.label]
        assert [got["canting_mrad"]["x"], got["canting_mrad"]["y"]] == pytest.approx(expected[i], abs=1e-9)
        # a perfect facet's optical frame is its true frame: its boresight did not turn it
        assert abs(got["boresight_mrad"]["x"]) < 1e-7 and abs(got["boresight_mrad"]["y"]) < 1e-7
    # the facets' mean tilt is not a canting error (here they lean +0.175, +0.15 mrad on average)
    assert sum(truth["facets"][f.label]["canting_mrad"]["x"] for f in ENSEMBLE.facets) == pytest.approx(0, abs=1e-9)
    assert truth["heliostat"]["common_tilt_mrad"]["x"] == pytest.approx(0.175, abs=2e-3)


def test_truth_canting_does_not_follow_the_heliostat_in_the_fixture(misplaced):
    h, moved = misplaced
    level = TwinHeliostat(GEOMETRY, ENSEMBLE, perfect(canting=tuple(f.placement_mrad for f in h.facets)),
                          TwinOptics.noise_free())
    a = heliostat_truth(moved, moved.coverage >= 1.0)["facets"]
    b = heliostat_truth(level, level.coverage >= 1.0)["facets"]
    for label in a:
        for ax in "xy":
            assert a[label]["canting_mrad"][ax] == pytest.approx(b[label]["canting_mrad"][ax], abs=1e-9)
        # ... but a facet's placement against its nominal frame in the fixture does
        assert a[label]["placement"]["mrad"] != pytest.approx(b[label]["placement"]["mrad"], abs=0.5)


def test_drawn_heliostats_differ_facet_by_facet():
    h = draw_heliostat(ENSEMBLE, np.random.default_rng(5), canting_mrad=1.0)
    assert len({f.surface_seed for f in h.facets}) == 4
    assert len({f.placement_mrad for f in h.facets}) == 4
    cant = np.array([f.placement_mrad[:2] for f in h.facets])
    assert 0.1 < np.abs(cant).max() < 5.0


def test_the_range_finder_reads_the_measure_facet(misplaced):
    h, twin = misplaced
    i = ENSEMBLE.measure_facet
    f, tf = ENSEMBLE.facets[i], h.facets[i]
    point = np.array([0.0, 0.0, 0.0])           # the measure point: the facet's centre, its paraboloid's vertex
    in_heliostat = (point - 0) @ rot(tf.placement_mrad).T @ f.rotation.T + f.position_m   # the vertex is its middle
    in_fixture = in_heliostat @ rot(h.placement_mrad).T + 1e-3 * np.asarray(h.placement_mm)
    screen_centre = GEOMETRY.fixture_to_camera.inverse().apply(GEOMETRY.screen_to_camera.translation)
    assert twin.measured_distance_m() == pytest.approx(float(np.linalg.norm(in_fixture - screen_centre)), abs=1e-9)
