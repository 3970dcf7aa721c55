"""End to end on the full-resolution simulated dish station: frames from a facet of known shape, through
the real renderer and the twin's camera, analysed by the pipeline, compared with the twin's ground truth.

Tolerances (issue 3): f within 0.1 % of truth, twist within 0.02 mrad/m, parabola residual RMS within
0.02 mrad of truth; with noise, over ten repeats, sample standard deviations below 0.05 % in f and
0.01 mrad in each RMS, and a median per-pixel slope standard deviation of at most 0.05 mrad.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.measure.pipeline import analyse
from sofast_station.station.inspect import FIGURE_KEYS, capture, inspect, open_station
from sofast_station.twin.truth import ground_truth

# The paper's ADDS facet: f 5.42 m / 5.35 m against a design of 5.33 m, a little twist, 0.5 mrad of
# small-scale slope error with a 20 mm correlation length.
TRUE_FACET = {"focal_length_x_m": 5.42, "focal_length_y_m": 5.35, "twist_mrad_per_m": 0.1,
              "slope_error_rms_mrad": 0.5, "slope_error_correlation_m": 0.02, "surface_seed": 11}


def dish_config(repo_root, **optics):
    cfg = load_config(repo_root / "station.toml")
    sim = {"seed": 1, "facet": dict(TRUE_FACET), "optics": dict(optics)}
    return dataclasses.replace(cfg, simulation=sim)


def check_against_truth(fig: dict, truth: dict) -> dict:
    """Assert the issue's tolerances; return the errors for the report."""
    err = {}
    for k in ("focal_length_x_m", "focal_length_y_m"):
        err[k] = fig[k] / truth[k] - 1
        assert abs(err[k]) < 1e-3, f"{k}: {fig[k]:.5f} m against truth {truth[k]:.5f} m"
    err["twist"] = fig["twist_mrad_per_m"] - truth["twist_mrad_per_m"]
    assert abs(err["twist"]) < 0.02, f"twist {fig['twist_mrad_per_m']:.4f} vs {truth['twist_mrad_per_m']:.4f}"
    for axis in ("x", "y", "magnitude"):
        got, want = fig["slope_rms_mrad"]["parabola"][axis], truth["slope_rms_mrad"]["parabola"][axis]
        err[f"rms_{axis}"] = got - want
        assert abs(got - want) < 0.02, f"parabola residual RMS {axis}: {got:.4f} vs truth {want:.4f} mrad"
    return err


@pytest.fixture(scope="module")
def noisy_station(repo_root):
    station = open_station(dish_config(repo_root), seed=1, noise=True)
    yield station
    station.close()


def test_noise_free_dish_facet_matches_truth(repo_root):
    station = open_station(dish_config(repo_root), noise=False)
    try:
        rec = inspect(station, "NOISE-FREE")
    finally:
        station.close()
    assert station.config.geometry.camera.shape == (1200, 1600)
    assert rec["n_points"] >= 400_000
    assert rec["iterations"]["converged"]
    assert set(FIGURE_KEYS) <= set(rec["truth"]) | {"n_points"}
    err = check_against_truth(rec, rec["truth"])
    print("noise-free errors:", {k: f"{v:.2e}" for k, v in err.items()})
    # the design really differs from the truth, so the test would notice a pipeline returning the design
    assert abs(rec["truth"]["focal_length_x_m"] - 5.33) > 0.05


def test_ten_noisy_repeats(noisy_station):
    figs, slopes, valids = [], [], []
    for seed in range(10):
        noisy_station.camera.rng = np.random.default_rng(100 + seed)
        frames, distance = capture(noisy_station)
        cfg = noisy_station.config
        a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis,
                    rays_cam=noisy_station.rays_cam)
        check_against_truth(a.figures, ground_truth(noisy_station.twin, a.valid))
        figs.append(a.figures)
        # Per-pixel angles relative to this repeat's fitted parabola: the corner pose leaves each repeat's
        # frame tilted by ~0.3 mrad (four corners of a 0.6 m facet seen from 10.7 m resolve tilt poorly),
        # which the electronic boresight (part 2) removes; relative to the fit, only measurement noise is left.
        full = np.full((2, a.valid.size), np.nan)
        full[:, np.flatnonzero(a.valid)] = np.stack(a.residuals_mrad["parabola"])
        slopes.append(full)
        valids.append(a.valid.ravel())
    for k in ("focal_length_x_m", "focal_length_y_m"):
        v = np.array([f[k] for f in figs])
        assert np.std(v, ddof=1) / np.mean(v) < 5e-4, f"{k} repeatability {np.std(v, ddof=1):.2e} m"
    # (the design residual depends on the frame, which the corner pose sets to ~0.3 mrad: it is proven
    # after the electronic boresight, in part 2)
    for model in ("parabola",):
        for axis in ("x", "y", "magnitude"):
            v = np.array([f["slope_rms_mrad"][model][axis] for f in figs])
            assert np.std(v, ddof=1) < 0.01, f"{model} RMS {axis} repeatability {np.std(v, ddof=1):.4f} mrad"
    kept = np.logical_and.reduce(valids)
    s = np.stack(slopes)[:, :, kept]                     # (repeat, axis, pixel), mrad
    per_pixel_mrad = np.std(s, axis=0, ddof=1)
    median = np.median(per_pixel_mrad, axis=1)
    print(f"per-pixel slope std, median: x {median[0]:.4f} mrad, y {median[1]:.4f} mrad over {kept.sum()} pixels")
    assert kept.sum() > 400_000
    assert np.all(median <= 0.05)
