"""Issue 4: all three facet types, noise-free, against the twin's ground truth in the boresight frame,
and the gore facet misplaced in its fixture.

Tolerances: f within 0.1 % of truth (the heliostat's curvature within 1e-5 /m), twist within
0.02 mrad/m, every residual RMS (design, parabola, higher order) within 0.02 mrad of truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import inspect

FACETS = {
    # station file, true facet (the paper's ADDS figures for the dish and gore)
    "dish": ("station.toml", {"focal_length_x_m": 5.42, "focal_length_y_m": 5.35, "twist_mrad_per_m": 0.1,
                              "slope_error_rms_mrad": 0.5, "slope_error_correlation_m": 0.02, "surface_seed": 11,
                              "dents": [{"x_m": 0.1, "y_m": -0.1, "depth_m": -20e-6, "radius_m": 0.03}]}),
    "gore": ("fixtures/stations/gore.toml", {"focal_length_x_m": 5.42, "focal_length_y_m": 5.35,
                                             "twist_mrad_per_m": 0.12, "slope_error_rms_mrad": 0.5,
                                             "slope_error_correlation_m": 0.03, "surface_seed": 5,
                                             "cubic_per_m2": [2e-4, 0.0, -1e-4, 0.0]}),
    "heliostat": ("fixtures/stations/heliostat.toml", {"focal_length_x_m": 95.0, "focal_length_y_m": 104.0,
                                                       "twist_mrad_per_m": 0.05, "slope_error_rms_mrad": 0.3,
                                                       "slope_error_correlation_m": 0.04, "surface_seed": 9}),
}


def measure(repo_root, kind, **placement):
    path, facet = FACETS[kind]
    cfg = load_config(repo_root / path)
    cfg = dataclasses.replace(cfg, simulation={"seed": 1, "facet": {**facet, **placement}})
    station = open_station(cfg, noise=False)
    try:
        return inspect(station, f"{kind.upper()}-NF")
    finally:
        station.close()


def check_against_truth(rec: dict, long_focus: bool, tilt: bool = True) -> dict:
    truth, err = rec["truth"], {}
    for axis in ("x", "y"):
        if long_focus:
            k = f"curvature_{axis}_per_m"
            err[k] = rec[k] - truth[k]
            assert abs(err[k]) < 1e-5, f"{k}: {rec[k]:.7f} vs truth {truth[k]:.7f} /m"
        else:
            k = f"focal_length_{axis}_m"
            err[k] = rec[k] / truth[k] - 1
            assert abs(err[k]) < 1e-3, f"{k}: {rec[k]:.5f} vs truth {truth[k]:.5f} m"
    for k in ("twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m"):
        err[k] = rec[k] - truth[k]
        assert abs(err[k]) < 0.02, f"{k}: {rec[k]:.4f} vs truth {truth[k]:.4f} mrad/m"
    for model in ("design", "parabola", "higher_order"):
        for axis in ("x", "y", "magnitude"):
            got, want = rec["slope_rms_mrad"][model][axis], truth["slope_rms_mrad"][model][axis]
            err[f"{model}_{axis}"] = got - want
            assert abs(got - want) < 0.02, f"{model} RMS {axis}: {got:.4f} vs truth {want:.4f} mrad"
    # The boresight frame's tilt in the fixture is the direction of a fitted normal: a slope, held to the
    # slopes' 0.02 mrad. (The boresight rotation alone is not comparable: it also undoes the corner pose's
    # tilt error, up to a few mrad about x; the tilt is free of it.)
    for axis in ("x", "y") if tilt else ():
        got, want = rec["optical_tilt_mrad"][axis], truth["optical_tilt_mrad"][axis]
        err[f"optical_tilt_{axis}"] = got - want
        assert abs(got - want) < 0.02, f"optical tilt {axis}: {got:.4f} vs truth {want:.4f} mrad"
    return err


@pytest.mark.parametrize("kind", ["dish", "gore", "heliostat"])
def test_noise_free_against_truth(repo_root, kind):
    rec = measure(repo_root, kind)
    assert rec["iterations"]["converged"] and rec["verdict"] in ("pass", "fail")
    err = check_against_truth(rec, long_focus=kind == "heliostat")
    worst = max(err, key=lambda k: abs(err[k]))
    print(f"{kind}: {rec['n_points']} points, worst {worst} {err[worst]:+.2e}; "
          + ", ".join(f"{k} {v:+.1e}" for k, v in err.items() if "focal" in k or "curv" in k))
    # the truth really differs from the design (the test would notice the design being echoed)
    true_rms = rec["truth"]["slope_rms_mrad"]
    assert true_rms["design"]["magnitude"] > true_rms["parabola"]["magnitude"]


def test_gore_misplaced_in_the_fixture(repo_root):
    """3 mm and 3 mrad of fixture error change nothing the boresight defines, and the corner pose reports it.

    What the corners can resolve (derived here, not tuned): a corner found to sigma_c = 0.05 px (the
    twin-measured accuracy of the sub-pixel corners on this station is ~0.03 px) moves a lateral
    position by sigma_c D / f_px = 0.05 * 11.5 / 5000 = 0.12 mm, and a rotation about z by
    sigma_c / (f_px * half-length / D) ~ 0.05 / 650 = 0.08 mrad. A tilt moves corners only through depth:
    by f_px r^2 theta / D^2 pixels for a corner r from the axis, so its resolution is sigma_c D^2 / (f_px r^2):
    0.6 mrad about y (r = 1.5 m, the gore's half-length) and 4.4 mrad about x (r = 0.55 m, half the wide end).
    Tolerances are twice these; the depth (z) follows the measured distance along the line of sight and is
    allowed the lateral tolerance plus the tilt's lever (half-length x tilt resolution about y).
    """
    applied_mm, applied_mrad = [3.0, -3.0, 3.0], [3.0, -3.0, 3.0]
    perfect = measure(repo_root, "gore")
    moved = measure(repo_root, "gore", placement_mm=applied_mm, placement_mrad=applied_mrad)
    for rec in (perfect, moved):
        check_against_truth(rec, long_focus=False)
    for k in ("focal_length_x_m", "focal_length_y_m"):
        assert abs(moved[k] / perfect[k] - 1) < 1e-3
    assert abs(moved["twist_mrad_per_m"] - perfect["twist_mrad_per_m"]) < 0.02
    for axis in ("x", "y", "magnitude"):
        assert abs(moved["slope_rms_mrad"]["parabola"][axis] - perfect["slope_rms_mrad"]["parabola"][axis]) < 0.02
    # A gore whose f differs from design has its corners elsewhere in depth than the design's, which the
    # corner pose reads as a small offset: compare against the same facet placed perfectly.
    d_mm = np.subtract(moved["placement"]["mm"], perfect["placement"]["mm"])
    d_mrad = np.subtract(moved["placement"]["mrad"], perfect["placement"]["mrad"])
    lateral_mm, rz_mrad, ry_mrad, rx_mrad = 2 * 0.12, 2 * 0.08, 2 * 0.6, 2 * 4.4
    print("placement found - applied:", np.round(d_mm - applied_mm, 3), "mm",
          np.round(d_mrad - applied_mrad, 3), "mrad")
    assert abs(d_mm[0] - applied_mm[0]) < lateral_mm and abs(d_mm[1] - applied_mm[1]) < lateral_mm
    assert abs(d_mm[2] - applied_mm[2]) < lateral_mm + 1.5 * ry_mrad
    assert abs(d_mrad[2] - applied_mrad[2]) < rz_mrad
    assert abs(d_mrad[1] - applied_mrad[1]) < ry_mrad
    assert abs(d_mrad[0] - applied_mrad[0]) < rx_mrad
    # the optical tilt, unlike the corner pose, follows the applied tilt to the slopes' precision
    tilt = {a: moved["optical_tilt_mrad"][a] - perfect["optical_tilt_mrad"][a] for a in "xy"}
    print(f"optical tilt moved by {tilt['x']:.4f}, {tilt['y']:.4f} mrad for 3, -3 mrad applied")
    assert abs(tilt["x"] - applied_mrad[0]) < 0.02 and abs(tilt["y"] - applied_mrad[1]) < 0.02
