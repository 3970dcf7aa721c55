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


def with_curl(anti, sym, noise, sd):
    return changed(slope_curl={"antisymmetric_rms_per_m": anti, "symmetric_rms_per_m": sym,
                               "antisymmetric_noise_per_m": noise, "symmetric_noise_per_m": noise,
                               "antisymmetric_noise_ms_sd_per_m2": sd, "n": 80_000, "step_px": 7, "stride_px": 3})


@pytest.mark.parametrize("fig, invalid", [
    # issue 26: the shipped heliostat at 2 DN: turning 8.5 against stretching 9.9 mrad/m, both mostly noise
    # (8.52 predicted): judged as a ratio of the two (0.86) it was "swapped"; against its noise it is not
    (with_curl(8.48e-3, 9.93e-3, 8.52e-3, 4.0e-7), False),
    # the same facet's sets swapped: the turning part 26 % of its mean square beyond the noise
    (with_curl(9.97e-3, 11.04e-3, 8.54e-3, 4.0e-7), True),
    # far beyond the noise, but turning much less than it stretches: a real surface (noise-free dish)
    (with_curl(0.54e-3, 16.1e-3, 0.12e-3, 1e-10), False),
    # swapped dish, noise-free
    (with_curl(23.9e-3, 21.1e-3, 0.12e-3, 1e-10), True),
    # weak fluctuations below the floor of what can be judged
    (with_curl(1.5e-3, 1.6e-3, 0.1e-3, 1e-10), False),
])
def test_the_curl_is_judged_against_its_noise(fig, invalid):
    v = judge(fig, DISH, Limits(), Quality())
    assert (v["verdict"] == "invalid") == invalid, v
    assert invalid == any("fringe sets were swapped" in r for r in v["reasons"])


def test_a_facet_far_from_its_place_in_the_fixture_is_invalid_as_misplaced():
    """Beyond [quality] max_placement_mm / _mrad by more than the placement's own U: misplaced. Within its U
    of the limit, not (the corner pose of a small camera is uncertain by several mm)."""
    seated = changed(placement={"mm": [0.5, -0.3, 0.1], "mrad": [0.2, 0.1, -0.3]},
                     placement_U={"mm": [10.8, 10.3, 2.9], "mrad": [11.7, 16.4, 1.5]})
    assert judge(seated, DISH, Limits(), Quality())["verdict"] == "pass"
    near = changed(placement={"mm": [28.0, 0.0, 0.0], "mrad": [0.0, 0.0, 0.0]}, placement_U=seated["placement_U"])
    assert judge(near, DISH, Limits(), Quality())["verdict"] == "pass"
    moved = changed(placement={"mm": [152.0, 0.0, 0.0], "mrad": [0.0, 0.0, 44.0]}, placement_U=seated["placement_U"])
    v = judge(moved, DISH, Limits(), Quality())
    assert v["verdict"] == "invalid" and len(v["reasons"]) == 1
    # each placement written with its U by the one digit rule (result/formatting.py: U to two digits)
    assert "misplaced in the fixture" in v["reasons"][0] and "x +152 ± 11 mm" in v["reasons"][0], v["reasons"]
    assert "about z +44.0" in v["reasons"][0] and "reseat" in v["reasons"][0]
    # the corner pose's tilt is poorly resolved (a 400 x 300 dish seen on a coarsely supersampled edge came
    # out 46 mrad about x, 3.7 of its U): the tilt judged is the optical tilt, which the slopes fix
    tilted_corners = changed(placement={"mm": [3.1, 0.0, 0.0], "mrad": [46.5, -30.6, -2.3]},
                             placement_U={"mm": [6.3, 6.0, 2.9], "mrad": [12.6, 27.8, 1.1]},
                             optical_tilt_mrad={"x": 0.4, "y": -0.2}, optical_tilt_mrad_U={"x": 2.6, "y": 2.4})
    assert judge(tilted_corners, DISH, Limits(), Quality())["verdict"] == "pass"
    tilted = changed(optical_tilt_mrad={"x": 45.0, "y": -0.2}, optical_tilt_mrad_U={"x": 2.6, "y": 2.4})
    assert "tilt about x +45.0" in judge(tilted, DISH, Limits(), Quality())["reasons"][0]


def test_slopes_far_beyond_what_the_layout_allows_are_no_facet_of_the_recipes_type():
    """Issue 26: the x and y sets swapped on a nearly flat facet seen by a small camera turn too little to
    show above the slope noise, but read as a facet of f = 2 m, 160 mrad RMS from a design the station is
    laid out for within 2 mrad: invalid, naming the sets. A facet merely out of tolerance fails."""
    heliostat = FacetDesign("h", "heliostat", 100.0, [[0.6, -0.6], [0.6, 0.6], [-0.6, 0.6], [-0.6, -0.6]], [0, 0],
                            [0, 0], layout={"distance_m": 4.0, "max_slope_error_mrad": 2.0})
    base = {**GOOD, "curvature_x_per_m": 0.0101, "curvature_y_per_m": 0.0099}
    swapped = {**base, "curvature_x_per_m": 0.4878, "curvature_y_per_m": 0.5055,
               "slope_rms_mrad": {"design": {"magnitude": 163.5}, "parabola": {"magnitude": 1.97}}}
    v = judge(swapped, heliostat, Limits(), Quality())
    assert v["verdict"] == "invalid" and "fringe sets swapped" in v["reasons"][0] and "82 times" in v["reasons"][0]
    bad = {**base, "slope_rms_mrad": {"design": {"magnitude": 4.0}, "parabola": {"magnitude": 1.5}}}
    assert judge(bad, heliostat, Limits(), Quality())["verdict"] == "fail"


def test_sides_along_the_pixel_grid_warn_without_changing_the_verdict():
    fig = changed(outline_staircase_sides=[2, 4])
    out = judge(fig, DISH, Limits(), Quality())
    assert out["verdict"] == "pass" and out["reasons"] == []
    assert len(out["warnings"]) == 1 and "edges 2, 4 of the facet (numbered as in its design file) line up " \
        "exactly with the camera's pixel grid" in out["warnings"][0] and "turn the camera" in out["warnings"][0]
    assert judge(changed(outline_staircase_sides=[]), DISH, Limits(), Quality())["warnings"] == []


def test_a_dark_declared_rim_that_shows_the_screen_warns_without_changing_the_verdict():
    out = judge(changed(outline_lit_rim_sides=[3]), DISH, Limits(), Quality())
    assert out["verdict"] == "pass" and out["reasons"] == []
    assert len(out["warnings"]) == 1
    assert "says is dark (edge_rim_dark), shows the screen on edge 3 of the facet" in out["warnings"][0]
    assert "set edge_rim_dark = false" in out["warnings"][0]
    assert judge(changed(outline_lit_rim_sides=[]), DISH, Limits(), Quality())["warnings"] == []
