"""The budget's row for what the fitted figures' sharpening leaves (measure/analysis.py, add_sharpening_row): its
size from the correction, pooled over the axes, and the U's it grows (in quadrature, k = 2). Pure dicts."""

from __future__ import annotations

import math

import pytest

from sofast_station.measure.analysis import SHARPENING_GROUP, add_sharpening_row
from sofast_station.measure.deblur import ROUGHNESS_LEFT


def _figures(correction):
    names = ["focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "twist_mrad_per_m", "slope_rms_mrad.design.x"]
    figures = {"focal_length_x_m": 100.0, "focal_length_y_m": 50.0, "curvature_x_per_m": 0.01,
               "twist_mrad_per_m": 0.1, "focal_length_x_m_U": 0.3, "focal_length_y_m_U": 0.2,
               "curvature_x_per_m_U": 4e-5, "twist_mrad_per_m_U": 0.02, "edge_blur_px": 0.7,
               "uncertainty_budget": {"figures": names, "rows": [], "combined_standard": [0.15, 0.1, 2e-5, 0.01, 0.1]}}
    if correction is not None:
        figures["lens_blur_sharpening"] = correction
    return figures


def test_the_row_is_the_pooled_correction_and_grows_each_u_in_quadrature():
    correction = {"curvature_x_per_m": 3e-7, "curvature_y_per_m": -4e-7, "twist_e1_mrad_per_m": 6e-4,
                  "twist_e2_mrad_per_m": 8e-4, "focal_length_x_m": -3e-3}
    figures = _figures(correction)
    added = add_sharpening_row(figures)
    u_curvature = ROUGHNESS_LEFT * math.sqrt((3e-7 ** 2 + 4e-7 ** 2) / 2)
    u_twist = ROUGHNESS_LEFT * math.sqrt((6e-4 ** 2 + 8e-4 ** 2) / 2)
    assert added["curvature_x_per_m"] == pytest.approx(2 * u_curvature)
    assert added["focal_length_x_m"] == pytest.approx(2 * u_curvature * 100.0 ** 2)
    assert added["focal_length_y_m"] == pytest.approx(2 * u_curvature * 50.0 ** 2)
    assert added["twist_mrad_per_m"] == pytest.approx(2 * u_twist)
    assert figures["focal_length_x_m_U"] == pytest.approx(math.hypot(0.3, 2 * u_curvature * 1e4))
    row = figures["uncertainty_budget"]["rows"][-1]
    assert row["group"] == SHARPENING_GROUP and row["kind"] == "systematic"
    assert row["contributions"][0] == pytest.approx(u_curvature * 1e4, rel=1e-2)
    assert row["contributions"][-1] == 0.0                      # the slope RMS is not refitted
    assert "0.70 px" in row["inputs"][0]


def test_a_sharp_lens_or_an_unstated_correction_adds_no_row():
    for correction in (None, {}, {"curvature_x_per_m": None, "curvature_y_per_m": 1e-7}):
        figures = _figures(correction)
        assert add_sharpening_row(figures) == {}
        assert figures["uncertainty_budget"]["rows"] == [] and figures["focal_length_x_m_U"] == 0.3
