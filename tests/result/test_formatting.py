"""'value ± U' is written one way everywhere (GUM 7.2.6): U to two significant digits, the value to the same
decimal place."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from sofast_station.result.formatting import budget_text, u_decimals, value_and_u, with_u

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("value, u, shown", [
    (5.418342, 0.002137, "5.4183 ± 0.0021"),     # U's two significant digits fix the value's place
    (115.7381, 1.564, "115.7 ± 1.6"),
    (0.61234, 0.0304, "0.612 ± 0.030"),           # a trailing zero of U is significant: kept
    (0.61234, 0.0996, "0.61 ± 0.10"),             # U rounding up to the next power of ten: one place less
    (1234.5, 156.0, "1230 ± 160"),                # U of hundreds: both to tens
    (-0.00041, 0.000123, "-0.00041 ± 0.00012"),
    (5.4183, 0.0, "5.4183"),                      # no (positive) U: the value to its own decimals
    (5.4183, None, "5.4183"),
])
def test_u_has_two_significant_digits_and_the_value_its_decimal_place(value, u, shown):
    assert with_u(value, u) == shown


def test_units_scale_sign_and_missing_values():
    assert with_u(0.0054183, 0.0000213, " mm", scale=1000.0) == "5.418 ± 0.021 mm"
    assert with_u(0.1234, 0.0042, sign=True) == "+0.1234 ± 0.0042"
    assert with_u(None, 0.1) == "-" and with_u(None, 0.1, missing="inf") == "inf"
    assert with_u(float("inf"), None, " m") == "inf m"
    assert value_and_u(2.0, 0.5, 3) == ("2.00", "0.50")
    assert u_decimals(float("nan")) is None and u_decimals(-1.0) is None and u_decimals(0.0021) == 4


def test_the_budget_table_shows_each_input_group_against_the_figures():
    rec = {"uncertainty_budget": {
        "figures": ["focal_length_x_m", "twist_mrad_per_m"], "coverage_factor": 2, "sensitivity_points": 4000,
        "rows": [{"group": "measured distance", "kind": "systematic", "inputs": ["distance (0.5 mm)"],
                  "contributions": [1.2e-3, 2e-3]}],
        "combined_standard": [1.5e-3, 3e-3], "random_standard": [1e-4, 1e-3]}}
    text = budget_text(rec)
    assert "measured distance" in text and "1.20e-03" in text and "3.00e-03" in text   # expanded: 2 x 1.5e-3
    assert budget_text({}) == "no uncertainty budget in this record"


def test_no_module_writes_a_value_with_its_u_by_its_own_rule():
    """Every '± U' shown goes through result/formatting.py: no other module formats a U's digits itself (the
    seven places that did each had their own rule)."""
    own_rule = re.compile(r"±\s?\{[^{}]*:[^{}<>]*\.\d*[fge]|±\s?\{[\w.* ]+:\.\{|[\"'] ± [\"'] \+")
    found = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
             for p in sorted((ROOT / "sofast_station").rglob("*.py")) if p.name not in ("formatting.py", "gum.py")
             for i, line in enumerate(p.read_text().splitlines(), 1) if own_rule.search(line)]
    assert not found, "values with U formatted outside sofast_station/result/formatting.py:\n" + "\n".join(found)


def test_an_aperture_is_said_in_words_not_as_its_dict():
    """Issue 43: the heliostat summary printed "aperture {'shape': 'circle', 'radius_m': 0.5}"."""
    from sofast_station.result.formatting import aperture_text

    assert aperture_text({"shape": "circle", "radius_m": 0.5}) == "a circle of 0.500 m radius"
    assert aperture_text({"shape": "rectangle", "width_m": 1.2, "height_m": 0.8}) == "a 1.200 m x 0.800 m rectangle"


def test_a_records_figure_is_written_one_way_by_its_key():
    """figure_text: a record's figure by its dotted key with its NAME_U sibling (nested ones too), by GUM's rule;
    without a U, every screen gives a figure the same decimals (the console showed slope RMS to 2, the page to
    3); a flat facet's missing focal length is infinite, a missing figure a dash."""
    from sofast_station.result.formatting import figure_parts, figure_text

    rec = {"focal_length_x_m": 5.420521550041019, "focal_length_x_m_U": 0.000969132939163216,
           "focal_length_y_m": None, "curvature_y_per_m": 1e-10, "curvature_x_per_m": 0.18448412,
           "twist_mrad_per_m": 0.23114, "slope_rms_mrad": {"design": {"x": 0.56241, "magnitude": 0.76093}},
           "slope_rms_mrad_U": {"design": {"magnitude": 0.0043}},
           "optics": {"intercept": 0.91234567, "intercept_U": 0.0271}}
    assert figure_text(rec, "focal_length_x_m", " m") == "5.42052 ± 0.00097 m"
    assert figure_parts(rec, "focal_length_x_m") == ("5.42052", "0.00097")
    assert figure_text(rec, "slope_rms_mrad.design.magnitude") == "0.7609 ± 0.0043"
    assert figure_text(rec, "optics.intercept") == "0.912 ± 0.027"
    assert figure_text(rec, "slope_rms_mrad.design.x") == "0.562"          # no U: 3 decimals, everywhere
    assert figure_text(rec, "twist_mrad_per_m", " mrad/m") == "0.231 mrad/m"
    assert figure_text(rec, "curvature_x_per_m") == "0.184484"
    assert figure_text(rec, "focal_length_y_m") == "inf" and figure_text(rec, "twist_e1_mrad_per_m") == "-"
    assert figure_parts(rec, "twist_e1_mrad_per_m") is None
