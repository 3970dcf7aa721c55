"""Ground truth from the exact true surface."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.errors import AnalysisError
from sofast_station.twin import ground_truth

KEYS = {"focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m", "twist_mrad_per_m",
        "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m", "axis_angle_rad",
        "coefficients", "slope_rms_mrad", "n_points"}


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
    # the axis of the shorter focal length (larger curvature, here near y) at 0.5 atan2(E, A - B)
    assert truth["axis_angle_rad"] == pytest.approx(0.5 * np.arctan2(1e-4, a - b), rel=1e-9)
    lam, vec = np.linalg.eigh([[a, e / 2], [e / 2, b]])
    angle_short = np.arctan2(vec[1, 1], vec[0, 1])            # eigenvector of the larger curvature
    assert np.mod(truth["axis_angle_rad"] - angle_short + np.pi / 2, np.pi) - np.pi / 2 == pytest.approx(0, abs=1e-9)
    for axis in ("x", "y", "magnitude"):
        assert truth["slope_rms_mrad"]["parabola"][axis] < 1e-6
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
