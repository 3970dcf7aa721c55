"""Ground truth from the exact true surface."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sofast_station.errors import AnalysisError
from sofast_station.facet import FacetDesign
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.twin import TrueFacet, TwinOptics, TwinStation, ground_truth
from sofast_station.twin import truth as truth_module

KEYS = {"focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m", "twist_mrad_per_m",
        "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m", "principal_curvatures_per_m",
        "axis_angle_rad",
        "coefficients", "slope_rms_mrad", "boresight_mrad", "optical_tilt_mrad", "placement", "n_points"}


def test_pure_paraboloid_is_recovered_exactly(parabola_station):
    station = parabola_station
    kept = station.coverage >= 1
    truth = ground_truth(station, kept)
    assert set(truth) == KEYS
    assert truth["n_points"] == int(kept.sum())
    assert truth["focal_length_x_m"] == pytest.approx(5.42, rel=1e-9)
    assert truth["focal_length_y_m"] == pytest.approx(5.35, rel=1e-9)
    assert truth["curvature_x_per_m"] == pytest.approx(1 / 5.42, rel=1e-9)
    for key in ("twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m"):
        assert truth[key] == pytest.approx(0.1, rel=1e-9)
    a, b, c, d, e = truth["coefficients"]
    assert abs(c) < 1e-12 and abs(d) < 1e-12          # the vertex is the frame's origin
    lam = np.linalg.eigvalsh([[1 / (4 * 5.42), 0.5e-4], [0.5e-4, 1 / (4 * 5.35)]])   # ascending
    f_short, f_long = 1 / (4 * lam[1]), 1 / (4 * lam[0])
    assert truth["principal_focal_lengths_m"] == pytest.approx([f_short, f_long], rel=1e-9)
    assert truth["principal_curvatures_per_m"] == pytest.approx([1 / f_short, 1 / f_long], rel=1e-9)
    # the axis of the shorter focal length (larger curvature, here near y) at 0.5 atan2(E, A - B)
    assert truth["axis_angle_rad"] == pytest.approx(0.5 * np.arctan2(1e-4, a - b), rel=1e-9)
    lam, vec = np.linalg.eigh([[a, e / 2], [e / 2, b]])
    angle_short = np.arctan2(vec[1, 1], vec[0, 1])            # eigenvector of the larger curvature
    assert np.mod(truth["axis_angle_rad"] - angle_short + np.pi / 2, np.pi) - np.pi / 2 == pytest.approx(0, abs=1e-9)
    for axis in ("x", "y", "magnitude"):
        assert truth["slope_rms_mrad"]["parabola"][axis] < 1e-6
        assert truth["slope_rms_mrad"]["higher_order"][axis] < 1e-6
    # its own vertex is at the alignment point: the boresight frame is the true facet frame
    assert abs(truth["boresight_mrad"]["x"]) < 1e-9 and abs(truth["boresight_mrad"]["y"]) < 1e-9
    assert truth["placement"] == {"mm": [0.5, -0.3, 1.0], "mrad": [0.4, -0.2, 0.3]}
    # the design residual, computed here from the exact points: atan(true slope) - atan(design slope)
    xy = station.surface_point_facet_m[kept][:, :2]
    f = station.design.focal_length_m
    e_x = 1e3 * (np.arctan(xy[:, 0] / (2 * 5.42) + 1e-4 * xy[:, 1]) - np.arctan(xy[:, 0] / (2 * f)))
    e_y = 1e3 * (np.arctan(xy[:, 1] / (2 * 5.35) + 1e-4 * xy[:, 0]) - np.arctan(xy[:, 1] / (2 * f)))
    design = truth["slope_rms_mrad"]["design"]
    assert design["x"] == pytest.approx(np.sqrt(np.mean(e_x ** 2)), rel=1e-9)
    assert design["y"] == pytest.approx(np.sqrt(np.mean(e_y ** 2)), rel=1e-9)
    assert design["magnitude"] == pytest.approx(np.sqrt(np.mean(e_x ** 2 + e_y ** 2)), rel=1e-9)
    assert design["x"] > 0.1


def test_flat_facet_has_no_focal_length(flat_station):
    truth = ground_truth(flat_station, flat_station.coverage >= 1)
    assert truth["focal_length_x_m"] is None and truth["focal_length_y_m"] is None
    assert truth["principal_focal_lengths_m"] == [None, None]
    assert truth["principal_curvatures_per_m"] == pytest.approx([0.0, 0.0], abs=1e-9)


def test_rich_facet_fits_and_skips_pixels_without_facet(rich_station):
    kept = np.ones(rich_station.geometry.camera.shape, bool)
    truth = ground_truth(rich_station, kept)
    assert truth["n_points"] == int((rich_station.coverage > 0).sum())
    assert truth["focal_length_x_m"] == pytest.approx(5.40, rel=0.01)
    assert 0.3 < truth["slope_rms_mrad"]["parabola"]["magnitude"] < 1.0
    with pytest.raises(AnalysisError):
        ground_truth(rich_station, np.zeros_like(kept))
    with pytest.raises(AnalysisError):
        ground_truth(rich_station, kept[:10])


# ---------------------------------------------------------------------------------------------------------
# The boresight frame (docs/conventions.md#boresight, #ground-truth) and the
# higher-order model. Dish stations here use a quarter-resolution camera (same field of view): tracing takes
# a tenth of a second and still gives ~36,000 facet pixels.

GORE = FacetDesign(name="gore-5.33", kind="gore", focal_length_m=5.33,
                   outline_m=[[1.5, -0.2], [4.5, -0.55], [4.5, 0.55], [1.5, 0.2]],
                   measure_point_m=[3.0, 0.0], alignment_point_m=[3.75, 0.0])


@pytest.fixture(scope="module")
def small_geometry(design):
    camera = CameraIntrinsics(400, 300, [[3409, 0, 199.5], [0, 3409, 149.5], [0, 0, 1]], [0] * 5)
    return layout_station(design, camera, ScreenSpec(1920, 1080, 0.000275), separation_m=0.34)


def _dish(small_geometry, design, **facet):
    return TwinStation(small_geometry, design, TrueFacet(**facet), TwinOptics.noise_free())


@pytest.fixture(scope="module")
def design_dish(small_geometry, design):
    """The design itself (paraboloid of revolution, f = 5.33 m), placed exactly."""
    return _dish(small_geometry, design)


@pytest.fixture(scope="module")
def gore_station():
    camera = CameraIntrinsics(1600, 1200, [[5400, 0, 799.5], [0, 5400, 599.5], [0, 0, 1]], [0] * 5)
    geometry = layout_station(GORE, camera, ScreenSpec(1920, 1080, 0.000275), separation_m=0.34)
    return TwinStation(geometry, GORE, TrueFacet(focal_length_x_m=5.42, focal_length_y_m=5.35),
                       TwinOptics.noise_free())


def _fit_in_test(station, kept, alpha, beta):
    """Rotate the exact samples by R_y(beta) R_x(alpha) about P_a (scipy) and fit the two slope equations."""
    xs = station.surface_point_facet_m[kept]
    s = station.slope_true[kept]
    n = np.column_stack([-s[:, 0], -s[:, 1], np.ones(len(s))])
    x_a, y_a = station.design.alignment_point_m
    p_a = np.array([x_a, y_a, (x_a ** 2 + y_a ** 2) / (4 * station.design.focal_length_m)])
    r = Rotation.from_euler("YX", [beta, alpha]).as_matrix()          # intrinsic: R_y(beta) @ R_x(alpha)
    x_b = (xs - p_a) @ r.T + p_a
    n_b = n @ r.T
    s_b = -n_b[:, :2] / n_b[:, 2:]
    x, y = x_b[:, 0], x_b[:, 1]
    fx = np.linalg.lstsq(np.column_stack([2 * x, np.ones_like(x), y]), s_b[:, 0], rcond=None)[0]
    fy = np.linalg.lstsq(np.column_stack([2 * y, np.ones_like(y), x]), s_b[:, 1], rcond=None)[0]
    return fx, fy      # (A, C, E1), (B, D, E2)


def test_design_facet_placed_exactly_needs_no_boresight(design_dish):
    truth = ground_truth(design_dish, design_dish.coverage >= 1)
    assert abs(truth["boresight_mrad"]["x"]) < 1e-6 and abs(truth["boresight_mrad"]["y"]) < 1e-6   # < 1e-9 rad
    assert truth["focal_length_x_m"] == pytest.approx(5.33, rel=1e-9)
    assert truth["focal_length_y_m"] == pytest.approx(5.33, rel=1e-9)
    for model in ("design", "parabola", "higher_order"):
        assert truth["slope_rms_mrad"][model]["magnitude"] < 1e-6
    assert truth["placement"] == {"mm": [0.0, 0.0, 0.0], "mrad": [0.0, 0.0, 0.0]}


def test_placement_tilt_does_not_change_the_truth(design_dish, small_geometry, design):
    """The truth starts in the true facet frame, so a tilted placement changes only which points are seen.

    The boresight is relative to the true placement (as the pipeline's is relative to its corner pose, which
    finds that placement): a perfect facet, however placed, needs none.
    """
    tilted = _dish(small_geometry, design, placement_mrad=(2.0, -3.0, 0.0))
    straight = ground_truth(design_dish, design_dish.coverage >= 1)
    truth = ground_truth(tilted, tilted.coverage >= 1)
    assert truth["n_points"] != straight["n_points"]                 # really another set of pixels
    for key in ("focal_length_x_m", "focal_length_y_m"):
        assert truth[key] == pytest.approx(straight[key], rel=1e-6)
    assert truth["twist_mrad_per_m"] == pytest.approx(straight["twist_mrad_per_m"], abs=1e-6)
    for model in ("design", "parabola", "higher_order"):
        assert truth["slope_rms_mrad"][model]["magnitude"] < 1e-6
    assert abs(truth["boresight_mrad"]["x"]) < 1e-6 and abs(truth["boresight_mrad"]["y"]) < 1e-6
    assert truth["placement"]["mrad"] == [2.0, -3.0, 0.0]


def test_boresight_undoes_a_tilt_of_the_surface_in_its_frame(design_dish):
    """The design surface tilted by R_p = R_y(ry) R_x(rx) about its middle (= alignment point = vertex).

    The boresight R = R_y(beta) R_x(alpha) must bring the vertex normal back to +z: R R_p e_z = e_z, i.e.
    beta = -asin(cos rx sin ry), alpha = atan2(-sin rx, cos rx cos ry), about (-2, +3) mrad but not exactly.
    """
    rx, ry = 2e-3, -3e-3
    r_p = Rotation.from_euler("YX", [ry, rx]).as_matrix()
    kept = design_dish.coverage >= 1
    points = np.array(design_dish.surface_point_facet_m)
    slopes = np.array(design_dish.slope_true)
    n = np.stack([-slopes[..., 0], -slopes[..., 1], np.ones(slopes.shape[:2])], axis=-1)
    n_tilted = n @ r_p.T
    tilted = types.SimpleNamespace(           # the station as ground_truth sees it, surface tilted in its frame
        geometry=design_dish.geometry, coverage=design_dish.coverage, design=design_dish.design,
        facet=design_dish.facet, surface_point_facet_m=points @ r_p.T,     # P_mid = origin
        slope_true=-n_tilted[..., :2] / n_tilted[..., 2:])
    truth = ground_truth(tilted, kept)
    beta = -math.asin(math.cos(rx) * math.sin(ry))
    alpha = math.atan2(-math.sin(rx), math.cos(rx) * math.cos(ry))
    r = Rotation.from_euler("YX", [beta, alpha]).as_matrix()
    assert np.allclose(r @ r_p @ [0, 0, 1], [0, 0, 1], atol=1e-15)          # the expectation itself
    assert abs(1e3 * alpha + 2.0) > 5e-6 and abs(1e3 * beta - 3.0) > 5e-6     # not simply (-rx, -ry)
    assert truth["boresight_mrad"]["x"] == pytest.approx(1e3 * alpha, abs=1e-6)
    assert truth["boresight_mrad"]["y"] == pytest.approx(1e3 * beta, abs=1e-6)
    # The boresight frame's tilt (placement zero here) is R^T read as R_z R_y R_x (scipy's intrinsic ZYX):
    # the surface's own tilt to first order, (2, -3) mrad, not exactly (convention, 6e-6 rad second order)
    _, ry_b, rx_b = Rotation.from_matrix(r.T).as_euler("ZYX")
    assert truth["optical_tilt_mrad"]["x"] == pytest.approx(1e3 * rx_b, abs=1e-6)
    assert truth["optical_tilt_mrad"]["y"] == pytest.approx(1e3 * ry_b, abs=1e-6)
    assert truth["optical_tilt_mrad"]["x"] == pytest.approx(2.0, abs=0.01)
    assert truth["optical_tilt_mrad"]["y"] == pytest.approx(-3.0, abs=0.01)
    assert truth["focal_length_x_m"] == pytest.approx(5.33, rel=1e-6)
    assert truth["focal_length_y_m"] == pytest.approx(5.33, rel=1e-6)
    assert abs(truth["twist_mrad_per_m"]) < 1e-6
    for model in ("design", "parabola", "higher_order"):
        assert truth["slope_rms_mrad"][model]["magnitude"] < 1e-6


def test_gore_boresight_meets_the_design_slope_at_the_alignment_point(gore_station):
    kept = gore_station.coverage >= 1
    truth = ground_truth(gore_station, kept)
    a, b, c, d, e = truth["coefficients"]
    x_a, y_a = GORE.alignment_point_m
    f = GORE.focal_length_m
    assert abs(math.atan(2 * a * x_a + c + e * y_a) - math.atan(x_a / (2 * f))) < 1e-9
    assert abs(math.atan(2 * b * y_a + d + e * x_a) - math.atan(y_a / (2 * f))) < 1e-9
    # the reported angles really give that frame: redo the rotation and the fits here
    alpha, beta = 1e-3 * truth["boresight_mrad"]["x"], 1e-3 * truth["boresight_mrad"]["y"]
    (ta, tc, te1), (tb, td, te2) = _fit_in_test(gore_station, kept, alpha, beta)
    assert [ta, tb] == pytest.approx([a, b], rel=1e-9)
    assert [tc, td] == pytest.approx([c, d], abs=1e-11)
    assert 1e3 * te1 == pytest.approx(truth["twist_e1_mrad_per_m"], abs=1e-6)
    assert 1e3 * te2 == pytest.approx(truth["twist_e2_mrad_per_m"], abs=1e-6)
    # The true facet touches the design at its middle (centroid x_c); with f_x = 5.42 against 5.33 m its
    # slope at x_a differs from the design's by about 2 (a - a_d)(x_a - x_c), so the frame turns about y by
    # about that much, which changes the focal lengths (~0.08 % per mrad on a gore:
    # docs/conventions.md#facet-frame); the facet is symmetric about y = 0
    x_c = float(GORE.centroid_m[0])
    expected_mrad = 1e3 * (math.atan(x_a / (2 * f) + (x_a - x_c) * (1 / (2 * 5.42) - 1 / (2 * f)))
                           - math.atan(x_a / (2 * f)))
    assert abs(expected_mrad) > 0.3
    assert truth["boresight_mrad"]["y"] == pytest.approx(expected_mrad, rel=0.1)
    assert abs(truth["boresight_mrad"]["x"]) < 1e-3
    assert truth["focal_length_x_m"] == pytest.approx(5.42, rel=0.01)
    assert truth["focal_length_y_m"] == pytest.approx(5.35, rel=0.01)
    assert abs(truth["focal_length_x_m"] / 5.42 - 1) > 1e-5
    assert truth["slope_rms_mrad"]["higher_order"]["magnitude"] < truth["slope_rms_mrad"]["parabola"]["magnitude"]


def test_boresight_that_does_not_converge_raises(gore_station, monkeypatch):
    monkeypatch.setattr(truth_module, "BORESIGHT_MAX_ITERATIONS", 2)
    with pytest.raises(RuntimeError, match="did not converge"):
        ground_truth(gore_station, gore_station.coverage >= 1)


def test_higher_order_model_absorbs_cubic_shape_error(small_geometry, design):
    station = _dish(small_geometry, design, focal_length_x_m=5.40, focal_length_y_m=5.30, twist_mrad_per_m=0.3,
                    placement_mm=(1.5, -2.0, 3.0), placement_mrad=(1.0, -0.8, 2.0),
                    cubic_per_m2=(2e-4, -1e-4, 5e-5, 1.5e-4))
    rms = ground_truth(station, station.coverage >= 1)["slope_rms_mrad"]
    for axis in ("x", "y", "magnitude"):
        assert rms["higher_order"][axis] < 1e-6
        assert rms["parabola"][axis] > 1e-3


def test_higher_order_fit_is_joint_with_shared_coefficients():
    """Slopes that no single surface has (s_x = y, s_y = 0: curl != 0) tell a joint fit from separate ones.

    Reference: the stacked least-squares solution built here in raw (unscaled) x, y; separate fits would
    reproduce s_x = y and s_y = 0 exactly, the joint fit splits the difference (z ~ x y / 2).
    """
    rng = np.random.default_rng(0)
    xy = rng.uniform([1.5, -0.5], [4.5, 0.5], (2000, 2))
    slopes = np.column_stack([xy[:, 1], np.zeros(len(xy))])
    x, y = xy.T
    terms = [(i, k - i) for k in (1, 2, 3) for i in range(k + 1)]
    m = np.vstack([np.column_stack([i * x ** max(i - 1, 0) * y ** j if i else 0 * x for i, j in terms]),
                   np.column_stack([j * x ** i * y ** max(j - 1, 0) if j else 0 * x for i, j in terms])])
    c = np.linalg.lstsq(m, np.concatenate([slopes[:, 0], slopes[:, 1]]), rcond=None)[0]
    want = (m @ c).reshape(2, -1).T
    got = truth_module.higher_order_slopes(xy, slopes)
    assert np.allclose(got, want, rtol=0, atol=1e-9)
    assert np.sqrt(np.mean((got - slopes) ** 2)) > 0.1       # not the separate fits' exact reproduction


def test_random_slope_error_orders_the_models(small_geometry, design):
    station = _dish(small_geometry, design, slope_error_rms_mrad=0.5, surface_seed=3)
    rms = ground_truth(station, station.coverage >= 1)["slope_rms_mrad"]
    for axis in ("x", "y", "magnitude"):
        assert rms["higher_order"][axis] <= rms["parabola"][axis] <= rms["design"][axis]
    assert 0.3 < rms["higher_order"]["magnitude"] < 1.0
