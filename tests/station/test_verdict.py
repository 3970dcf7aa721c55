"""Verdicts: invalid first (untrustworthy measurement), then fail against limits, else pass."""

import copy

import pytest

from sofast_station.facet import FacetDesign
from sofast_station.result.verdict import Limits, Quality, judge

DISH = FacetDesign("dish", "dish", 5.33, [[0.3, -0.3], [0.3, 0.3], [-0.3, 0.3], [-0.3, -0.3]], [0, 0], [0, 0])
HELIOSTAT = FacetDesign("h", "heliostat", 100.0, [[0.6, -0.6], [0.6, 0.6], [-0.6, 0.6], [-0.6, -0.6]], [0, 0], [0, 0])

GOOD = {"valid_fraction": 0.99, "median_modulation_dn": 100.0, "unwrap_disagreements": 0, "facet_pixels": 500_000,
        "outline_agreement": 0.995, "corner_reprojection_rms_px": 0.02,
        "iterations": {"converged": True, "boresight": 2, "shape": 4},
        "focal_length_x_m": 5.40, "focal_length_y_m": 5.35, "curvature_x_per_m": 1 / 5.40,
        "curvature_y_per_m": 1 / 5.35, "twist_mrad_per_m": 0.1,
        "slope_rms_mrad": {"design": {"magnitude": 1.0}, "parabola": {"magnitude": 0.7},
                           "higher_order": {"magnitude": 0.6}}}


def changed(**kw):
    fig = copy.deepcopy(GOOD)
    for k, v in kw.items():
        fig[k] = v
    return fig


def test_good_facet_passes():
    assert judge(GOOD, DISH, Limits(), Quality()) == {"verdict": "pass", "reasons": [], "warnings": []}


@pytest.mark.parametrize("fig, words", [
    (changed(valid_fraction=0.5), "valid"),
    (changed(median_modulation_dn=3.0), "contrast"),
    (changed(unwrap_disagreements=50_000), "disagree"),
    (changed(outline_agreement=0.8), "corner pose does not match the mask"),
    (changed(iterations={"converged": False, "boresight": 20, "shape": 60}), "converge"),
])
def test_untrustworthy_measurements_are_invalid(fig, words):
    v = judge(fig, DISH, Limits(), Quality())
    assert v["verdict"] == "invalid" and any(words in r for r in v["reasons"])


@pytest.mark.parametrize("fig, words", [
    (changed(focal_length_x_m=5.6, curvature_x_per_m=1 / 5.6), "focal length x"),
    (changed(focal_length_y_m=None, curvature_y_per_m=0.0), "infinite"),
    (changed(twist_mrad_per_m=-2.0), "twist"),
    (changed(slope_rms_mrad={"design": {"magnitude": 3.5}, "parabola": {"magnitude": 0.7}}), "design slope error"),
])
def test_out_of_limits_fails(fig, words):
    v = judge(fig, DISH, Limits(), Quality())
    assert v["verdict"] == "fail" and any(words in r for r in v["reasons"])


def test_long_focal_lengths_are_judged_on_curvature():
    fig = changed(focal_length_x_m=95.0, focal_length_y_m=104.0, curvature_x_per_m=1 / 95.0,
                  curvature_y_per_m=1 / 104.0)
    # 1/95 - 1/100 = 5.3e-4 /m: beyond a 2e-4 /m limit although f is "only" 5 % off
    v = judge(fig, HELIOSTAT, Limits(curvature_tolerance_per_m=2e-4), Quality())
    assert v["verdict"] == "fail" and "curvature x" in v["reasons"][0]
    assert judge(fig, HELIOSTAT, Limits(curvature_tolerance_per_m=1e-3), Quality())["verdict"] == "pass"


# -- decision rules (ISO 14253-1 guarded acceptance) and the noise-corrected slope RMS ------------------
GUARDED = Limits(decision_rule="guarded", max_twist_mrad_per_m=1.0)


def with_twist(value, u):
    return changed(twist_mrad_per_m=value, twist_mrad_per_m_U=u)


@pytest.mark.parametrize("value,u,simple,guarded", [
    (0.5, 0.1, "pass", "pass"),                 # well inside: both pass
    (0.95, 0.1, "pass", "indeterminate"),       # inside, but within U of the limit
    (1.05, 0.1, "fail", "indeterminate"),       # beyond, but within U of the limit
    (1.2, 0.1, "fail", "fail"),                 # beyond the limit plus U
    (-1.2, 0.1, "fail", "fail"),                # the limit is on |twist|
])
def test_guarded_rule_needs_the_uncertainty_zone_cleared(value, u, simple, guarded):
    assert judge(with_twist(value, u), DISH, Limits(), Quality())["verdict"] == simple
    out = judge(with_twist(value, u), DISH, GUARDED, Quality())
    assert out["verdict"] == guarded
    if guarded == "indeterminate":
        assert any("twist" in r and "within its U" in r for r in out["reasons"])


def test_guarded_focal_length_uses_its_U_relative_to_design():
    # 2 % of 5.33 m is 0.1066 m: f = 5.33 * 1.019 is inside, by 0.0053 m.
    fig = changed(focal_length_x_m=5.33 * 1.019, focal_length_x_m_U=0.002)
    assert judge(fig, DISH, GUARDED, Quality())["verdict"] == "pass"
    fig["focal_length_x_m_U"] = 0.01
    assert judge(fig, DISH, GUARDED, Quality())["verdict"] == "indeterminate"


def test_a_fail_wins_over_an_indeterminate_figure():
    fig = changed(twist_mrad_per_m=0.98, twist_mrad_per_m_U=0.1, focal_length_x_m=6.0)
    assert judge(fig, DISH, GUARDED, Quality())["verdict"] == "fail"


def test_limits_can_apply_to_the_noise_corrected_rms():
    fig = changed(slope_rms_mrad={"design": {"magnitude": 3.05}, "parabola": {"magnitude": 0.7}},
                  slope_rms_corrected_mrad={"design": {"magnitude": 2.95}, "parabola": {"magnitude": 0.69}})
    assert judge(fig, DISH, Limits(), Quality())["verdict"] == "fail"
    out = judge(fig, DISH, Limits(slope_rms_value="corrected"), Quality())
    assert out["verdict"] == "pass"


@pytest.mark.parametrize("table,words", [({"decision_rule": "strict"}, "decision_rule"),
                                          ({"slope_rms_value": "best"}, "slope_rms_value")])
def test_bad_decision_settings_are_refused(table, words):
    from sofast_station.errors import ConfigError
    from sofast_station.result.verdict import limits_from_table
    with pytest.raises(ConfigError, match=words):
        limits_from_table(table, "station.toml [limits]")
