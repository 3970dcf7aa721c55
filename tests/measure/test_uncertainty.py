"""Expanded uncertainties (k = 2) on a small twin station: every reported scalar carries one, of the
figure's shape; the noise explained matches the slope noise two captures of the same facet show; the
sensitivities are cached. Whether the errors against the twin's truth lie within U as often as claimed is
checked on a drawn population of stations (tests/station/test_population.py; the full runs:
benchmarks/population.py and benchmarks/uncertainty_coverage.py)."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.measure.analysis import analyse
from sofast_station.measure.uncertainty import SCALAR_PATHS, InputUncertainties, Sensitivities, get_path, path_name
from sofast_station.station.study import TwinRig
from tests.conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
from uncertainty_coverage import small_station


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    cfg = load_config(small_station(tmp_path_factory.mktemp("unc")))
    return TwinRig(cfg)


@pytest.fixture(scope="module")
def two_captures(rig):
    cfg = rig.config
    twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
    cache: dict = {}
    out = []
    for seed in (1, 2):
        frames = rig.capture(twin, np.random.default_rng(seed))
        out.append(analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                           uncertainty=cfg.uncertainty, sensitivity_cache=cache))
    return out, cache


def _same_shape(a, b):
    if isinstance(a, dict):
        return isinstance(b, dict) and set(a) == set(b) and all(_same_shape(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(_same_shape(x, y) for x, y in zip(a, b))
    return (a is None) == (b is None)


def test_every_reported_scalar_has_an_expanded_uncertainty(two_captures):
    (a, _), _ = two_captures
    fig = a.figures
    assert fig["coverage_factor"] == 2
    for path in SCALAR_PATHS:
        u = get_path({k[:-2]: v for k, v in fig.items() if k.endswith("_U")}, path)
        assert u is not None and np.isfinite(u) and u > 0, path_name(path)
        ur = get_path({k[:-9]: v for k, v in fig.items() if k.endswith("_U_random")}, path)
        assert 0 < ur <= u + 1e-15, path_name(path)
    for top in {p[0] for p in SCALAR_PATHS}:
        assert _same_shape(fig[top], fig[f"{top}_U"]), top
    # The noise floor: corrected <= measured, with the noise explained removed in quadrature.
    for model, rms in fig["slope_rms_mrad"].items():
        for axis in ("x", "y", "magnitude"):
            c, n = fig["slope_rms_corrected_mrad"][model][axis], fig["slope_rms_noise_mrad"][model][axis]
            assert c == pytest.approx(np.sqrt(rms[axis] ** 2 - n ** 2), rel=1e-12)
            # the measured value's U covers its uncorrected noise bias in quadrature (k = 2), not added linearly;
            # the corrected value's U is the rest magnified by r / c (test_noise_corrected.py), never smaller
            u_c, u_m = fig["slope_rms_corrected_mrad_U"][model][axis], fig["slope_rms_mrad_U"][model][axis]
            rest = np.sqrt(u_m ** 2 - (2 * (rms[axis] - c)) ** 2)
            assert rest <= u_c * (1 + 1e-9)
            assert u_c <= 2 * rest * rms[axis] / c + 1e-12        # c - sqrt(c^2 - 2 r U) <= 2 (r / c) U
    budget = fig["uncertainty_budget"]
    groups = {r["group"] for r in budget["rows"]}
    assert {"measured distance", "camera focal length", "camera distortion", "camera-to-screen rotation",
            "camera-to-screen translation", "screen pitch", "display response", "fixture pose", "corner location",
            "intensity noise"} <= groups
    f = budget["figures"].index("focal_length_x_m")
    assert budget["combined_standard"][f] == pytest.approx(fig["focal_length_x_m_U"] / 2, rel=1e-2)


def test_a_focal_lengths_u_is_its_focal_powers(two_captures):
    """Issue 47: f = 1 / kappa, and f's U (total, random, every budget row) is kappa's mapped linearly, U(kappa)
    / kappa^2, for f_x, f_y and both principal focal lengths: the rows of f itself (differences over an input's
    step) are noise on a nearly flat facet, where the step moves kappa by as much as kappa. Whether kappa's U is
    right is the population's test (tests/station/test_population.py)."""
    (a, _), _ = two_captures
    fig = a.figures
    u = {k[:-2]: v for k, v in fig.items() if k.endswith("_U")}
    ur = {k[:-9]: v for k, v in fig.items() if k.endswith("_U_random")}
    budget = fig["uncertainty_budget"]
    pairs = [(("focal_length_x_m",), ("curvature_x_per_m",)), (("focal_length_y_m",), ("curvature_y_per_m",)),
             *[(("principal_focal_lengths_m", i), ("principal_curvatures_per_m", i)) for i in (0, 1)]]
    for f_path, k_path in pairs:
        f, kappa = get_path(fig, f_path), get_path(fig, k_path)
        assert f == pytest.approx(1.0 / kappa, rel=1e-12), path_name(f_path)
        assert get_path(u, f_path) == pytest.approx(get_path(u, k_path) * f * f, rel=1e-9), path_name(f_path)
        assert get_path(ur, f_path) == pytest.approx(get_path(ur, k_path) * f * f, rel=1e-9), path_name(f_path)
        jf, jk = (budget["figures"].index(path_name(p)) for p in (f_path, k_path))
        for row in budget["rows"]:
            cf, ck = row["contributions"][jf], row["contributions"][jk]
            assert (cf is None) == (ck is None) and (cf is None or cf == pytest.approx(ck * f * f, rel=2e-2, abs=0))


def test_noise_explained_matches_the_scatter_between_two_captures(two_captures):
    (a, b), _ = two_captures
    both = np.flatnonzero((a.valid & b.valid).ravel())
    ia, ib = np.isin(np.flatnonzero(a.valid.ravel()), both), np.isin(np.flatnonzero(b.valid.ravel()), both)
    d = 1000.0 * (np.arctan(a.slopes[:, ia]) - np.arctan(b.slopes[:, ib]))
    # The pixel-to-pixel scatter between the two captures, over sqrt(2).
    for axis, row in (("x", 0), ("y", 1)):
        seen = float(np.std(d[row] - np.median(d[row]))) / np.sqrt(2.0)
        stated = a.figures["slope_rms_noise_mrad"]["design"][axis]
        assert 0.7 < stated / seen < 1.5, (axis, stated, seen)


def test_sensitivities_are_computed_once_per_geometry_and_recipe(two_captures):
    (a, b), cache = two_captures
    assert sum(isinstance(v, Sensitivities) for v in cache.values()) == 1     # (and the frame-brightness pool)
    assert a.timings_s["uncertainty_sensitivities"] > 0 and "uncertainty_sensitivities" not in b.timings_s
    assert a.timings_s["uncertainty"] > 0 and b.timings_s["uncertainty"] > 0


def test_uncertainty_table_is_validated():
    with pytest.raises(ConfigError, match="distance_mm"):
        InputUncertainties.from_table({"distance_mm": -1})
    with pytest.raises(ConfigError, match="screen_rotation_mrad"):
        InputUncertainties.from_table({"screen_rotation_mrad": [0.1, 0.2]})
    with pytest.raises(ConfigError, match="unknown"):
        InputUncertainties.from_table({"distance": 1})
    with pytest.raises(ConfigError, match="unknown"):      # set from the radiometric record, not by hand
        InputUncertainties.from_table({"response_record_rad": 1e-4})
    # ... but it travels to the analysis worker with the rest (to_dict / from_dict).
    w = InputUncertainties(distance_mm=0.7, response_record_rad=4e-4)
    assert InputUncertainties.from_dict(w.to_dict()) == w
    u = InputUncertainties.from_table({"distance_mm": 2, "camera_distortion": [0, 0, 0, 0, 0]})
    assert u.distance_mm == 2.0 and u.camera_distortion == (0.0,) * 5
    rec = {"std": {"fx": 0.4, "fy": 0.6, "cx": 0.3, "cy": 0.2, "distortion": [1e-3, 2e-3, 0, 0, 0]}}
    v = u.with_camera_record(rec)
    assert v.camera_focal_px == 0.6 and v.camera_principal_px == 0.3 and v.camera_distortion[1] == 2e-3


def test_study_repeatability_command(rig, tmp_path, capsys):
    """Three placements through the CLI: a table, its JSON and a PNG; the measurement's own spread (error
    against truth) is of the order of the stated random U (the 30-placement figures are in the notes).

    Both sides of that: the spread's standard deviation over 3 placements (2 degrees of freedom) is
    s sqrt(chi2(2) / 2) for a true one of s, and a right U_random (k = 2) is 2 s, so std / U_random lies in
    0.5 x 0.7 x sqrt(chi2_0.0005(2) / 2) .. 0.5 x 1.3 x sqrt(chi2_0.9995(2) / 2) = 0.008 .. 1.79 for a
    U_random within 0.7-1.3 of right (probability 0.999 each side): wide with three placements, but a
    U_random ten times too large or too small fails it."""
    import json

    from sofast_station.cli import main

    assert main(["study", "repeatability", "--config", str(rig.config.path), "--facets", "3",
                 "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    from sofast_station.result.specs import figure_name

    assert figure_name("focal_length_x_m")[0] in out and "%GRR" in out      # the table names figures for people
    table = json.loads(next(tmp_path.glob("repeatability-*.json")).read_text())
    png = next(tmp_path.glob("repeatability-*.png"))
    assert png.stat().st_size > 10_000
    rows = {r["figure"]: r for r in table["rows"]}
    from scipy.stats import chi2

    low, high = 0.5 * 0.7 * np.sqrt(chi2.ppf(0.0005, 2) / 2), 0.5 * 1.3 * np.sqrt(chi2.isf(0.0005, 2) / 2)
    for name in ("focal_length_x_m", "twist_mrad_per_m", "slope_rms_mrad.design.magnitude", "placement.mm.0"):
        assert low <= rows[name]["std_over_U_random"] <= high, (rows[name], low, high)
    assert rows["focal_length_x_m"]["grr_class"] == "acceptable"


def test_frame_brightness_is_pooled_over_captures_and_widened_for_few_values():
    """A capture's four fringe sets give its frame-brightness noise with 4 degrees of freedom only: alone,
    it is widened by sqrt(4 / 2) (the t distribution's standard deviation); pooled over the recent captures
    it converges on the true value; a capture far above the pool (the room light changed) keeps its own."""
    from collections import deque

    from sofast_station.measure.uncertainty import pooled_frame_brightness, small_sample_factor

    assert small_sample_factor(4) == pytest.approx(np.sqrt(2.0)) and small_sample_factor(1000) < 1.002
    alone = pooled_frame_brightness(0.8, 4, None)
    assert alone["source"] == "own" and alone["sigma_dn"] == pytest.approx(0.8 * np.sqrt(2.0))
    rng = np.random.default_rng(0)
    pool = deque(maxlen=50)
    used = []
    for _ in range(60):
        own = float(np.sqrt(np.mean(rng.normal(0.0, 1.0, 4) ** 2)))      # true sigma 1 DN, 4 values
        used.append(pooled_frame_brightness(own, 4, pool))
    pooled = [u for u in used[20:] if u["source"] == "pooled"]
    assert len(pool) == 50 and len(pooled) >= 36 and pooled[-1]["dof"] == 200     # (the F test's 1 % aside)
    assert abs(pooled[-1]["sigma_dn"] - 1.0) < 0.15
    spread_own = np.std([u["own_dn"] for u in used[20:]])
    spread_used = np.std([u["sigma_dn"] for u in pooled])
    assert spread_used < 0.3 * spread_own                # a stable U instead of one that jumps by 35 %
    disturbed = pooled_frame_brightness(4.0, 4, pool)
    assert disturbed["source"] == "own" and disturbed["sigma_dn"] > 4.0


def _true_four_step_error_rad(rig, gamma: float) -> float:
    """The twin's own four-step phase error of its finest fringes, its cos/sin(4 phase) amplitude (rad):
    the commands it was sent (the rendered images, through the record's lookup table) seen through the
    twin's display (luminance floor + (1 - floor) (v / 255)^gamma), along the middle screen line; the
    larger of the two axes."""
    pats = rig.config.fringes.patterns()
    lum = rig.optics.display_floor + (1.0 - rig.optics.display_floor) * (np.arange(256) / 255.0) ** gamma
    out = []
    for axis in "xy":
        p = max(q.periods for q in pats if q.kind == "fringe" and q.axis == axis)
        ks = [i for i, q in enumerate(pats) if q.kind == "fringe" and q.axis == axis and q.periods == p]
        img = rig.images[ks]
        line = lum[img[:, img.shape[1] // 2, :] if axis == "x" else img[:, :, img.shape[2] // 2]]
        phi = np.unwrap(np.arctan2(line[1] - line[3], line[0] - line[2]))
        t = np.arange(phi.size)
        err = phi - np.polyval(np.polyfit(t, phi, 1), t)
        coef = np.linalg.lstsq(np.column_stack([np.cos(4 * phi), np.sin(4 * phi), np.ones_like(phi)]), err,
                               rcond=None)[0]
        out.append(float(np.hypot(coef[0], coef[1])))
    return max(out)


def test_display_response_uncertainty_comes_from_the_evidence(rig, two_captures):
    """The display response's standard uncertainty is the capture's own estimate of the phase error (from the
    second harmonic of its four-step residuals) with the rounding to 8-bit commands the radiometric record
    leaves, not the fixed 0.003 rad default: on the twin with its display linearised by the record, the
    record's part matches the twin's true 4-times-phase error and the result stays far below the default;
    with the twin's display at gamma 2.45 (the table inverts 2.2) the capture's estimate follows the twin's
    true error and the budget's display-response row grows with it."""
    import dataclasses

    (a, _), cache = two_captures
    cfg = rig.config
    assert cfg.uncertainty.response_phase_rad == 0.003
    dr = a.figures["uncertainty_budget"]["display_response"]
    truth = _true_four_step_error_rad(rig, rig.optics.display_gamma)
    assert dr["source"] == "capture and record"
    assert dr["record_rad"] == pytest.approx(truth, rel=0.1)
    assert truth <= dr["u_rad"] < 0.003 / 4

    optics = rig.optics
    try:
        rig.optics = dataclasses.replace(optics, display_gamma=2.45)
        twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
        frames = rig.capture(twin, np.random.default_rng(3))
        truth_bent = _true_four_step_error_rad(rig, 2.45)
    finally:
        rig.optics = optics
    b = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                uncertainty=cfg.uncertainty, sensitivity_cache=cache)
    bent = b.figures["uncertainty_budget"]["display_response"]
    assert truth_bent > 10 * truth
    assert bent["estimate_rad"] == pytest.approx(truth_bent, rel=0.15)
    assert bent["u_rad"] == pytest.approx(np.hypot(bent["estimate_rad"], bent["record_rad"]), rel=1e-3)
    # The budget's row scales with it (same cached sensitivities).
    rows = {r["group"]: r["contributions"] for r in a.figures["uncertainty_budget"]["rows"]}
    rows_b = {r["group"]: r["contributions"] for r in b.figures["uncertainty_budget"]["rows"]}
    j = a.figures["uncertainty_budget"]["figures"].index("twist_e1_mrad_per_m")
    assert rows_b["display response"][j] / rows["display response"][j] == pytest.approx(
        bent["u_rad"] / dr["u_rad"], rel=0.1)
    # Without the capture's evidence: the record's part, else the stated default; 0 there: left out.
    from types import SimpleNamespace

    from sofast_station.measure.uncertainty import display_response_u
    quiet = SimpleNamespace(phases=SimpleNamespace(noise=None))        # phases that say nothing about it
    assert display_response_u(quiet, cfg.uncertainty)["source"] == "record"
    assert display_response_u(quiet, dataclasses.replace(cfg.uncertainty, response_record_rad=None)) == {
        "u_rad": 0.003, "source": "default"}
    assert display_response_u(a, dataclasses.replace(cfg.uncertainty, response_phase_rad=0.0))["u_rad"] == 0.0


def _expected_corners(cfg):
    from sofast_station.measure.camera import project

    return project(cfg.geometry.camera, cfg.geometry.fixture_to_camera, cfg.design.corners_3d())


def test_batched_pose_solver_finds_opencvs_poses(rig):
    """The Monte Carlo's all-draws-at-once pose solver against OpenCV's solvePnP (one draw at a time), on
    corners and cameras drawn about the small station's expected pose: the same projection to 1e-9 px, a
    reprojection error never above OpenCV's, and the same poses for most draws (OpenCV stops earlier in the
    nearly frontal facet's flat valley, a few draws far from the minimum)."""
    import cv2

    from sofast_station.measure.uncertainty.corner_pose import _project_batch, solve_poses_batch

    cfg = rig.config
    cam, fix = cfg.geometry.camera, cfg.geometry.fixture_to_camera
    pts = np.asarray(cfg.design.corners_3d(), float)
    rng = np.random.default_rng(5)
    n = 60
    obs = _expected_corners(cfg)[None] + rng.normal(0, 0.1, (n, 4, 2))
    k = np.repeat(cam.matrix[None], n, axis=0)
    k[:, (0, 1, 0, 1), (0, 1, 2, 2)] += rng.normal(0, 1.0, (n, 4))
    dist = cam.distortion[None] + rng.normal(0, 1, (n, 5)) * np.array([2e-3, 1e-2, 5e-5, 5e-5, 1e-3])
    rvec0 = cv2.Rodrigues(fix.rotation)[0]
    moved = np.repeat(fix.rotation[None], n, axis=0) @ cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))[0]
    proj = _project_batch(moved, np.repeat(fix.translation[None], n, axis=0) + 0.01, pts, k, dist)
    ref = np.array([cv2.projectPoints(pts.reshape(-1, 1, 3), cv2.Rodrigues(moved[i])[0], fix.translation + 0.01,
                                      k[i], dist[i])[0].reshape(-1, 2) for i in range(n)])
    assert np.abs(proj - ref).max() < 1e-9
    rot, t, converged = solve_poses_batch(obs, pts, k, dist, fix.rotation, fix.translation)
    assert converged.all()
    cost = np.sum((_project_batch(rot, t, pts, k, dist) - obs) ** 2, axis=(1, 2))
    angle = []
    for i in range(n):
        ok, rvec, tvec = cv2.solvePnP(pts.reshape(-1, 1, 3), obs[i].reshape(-1, 1, 2), k[i], dist[i],
                                      rvec=rvec0.copy(), tvec=fix.translation.reshape(3, 1).copy(),
                                      useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        r_cv = cv2.Rodrigues(rvec)[0]
        cost_cv = np.sum((_project_batch(r_cv[None], tvec.reshape(1, 3), pts, k[i:i + 1], dist[i:i + 1])
                          - obs[i]) ** 2)
        assert cost[i] <= cost_cv + 1e-9
        angle.append(np.linalg.norm(cv2.Rodrigues(r_cv.T @ rot[i])[0]))
    assert np.median(angle) < 2e-4


def test_pose_monte_carlo_matches_the_stations_own_corner_pose(rig):
    """The Monte Carlo's arithmetic on arrays against the station's own corner pose (the twin's projection
    of the facet through the drawn camera, then solve_corner_pose, fix_range and placement with the nominal
    one: OpenCV, Pose objects) on the same draws: the root mean square errors of the boresight and placement
    (their standard uncertainties) agree to 2.5 %, and the rotation about y keeps the offset the curvature
    of its response to f_x - f_y gives (about -0.6 mrad on the twin, -0.67 in the coverage study)."""
    from types import SimpleNamespace

    from sofast_station.geometry import Pose
    from sofast_station.measure.pipeline import default_screen
    from sofast_station.measure.pose import fix_range, placement, solve_corner_pose
    from sofast_station.measure.uncertainty import POSE_PATHS, pose_draws, pose_monte_carlo
    from sofast_station.twin.camera import TwinCamera

    cfg = rig.config
    g, design = cfg.geometry, cfg.design
    corners = _expected_corners(cfg)
    a = np.random.default_rng(3).normal(0, 0.03, (8, 8))
    cov = a @ a.T + 0.002 * np.eye(8)                    # correlated corners, about 0.1 px each
    centre = default_screen(g).centre_camera()
    red = SimpleNamespace(pose=SimpleNamespace(corners_px=corners, corner_cov_px2=cov),
                          rays=SimpleNamespace(screen_centre_cam_m=centre))
    draws = 120
    mc = pose_monte_carlo(red, geometry=g, design=design, inputs=cfg.uncertainty, draws=draws, seed=4)
    w, v = np.linalg.eigh(cov)
    dr = pose_draws(corners, v * np.sqrt(w)[None, :], g, cfg.uncertainty, draws, seed=4)
    measure = np.array([*design.measure_point_m, float(design.z(*design.measure_point_m))])
    errors = []
    for i in range(draws):
        # The facet as designed at the expected pose in the drawn fixture, seen by the drawn camera (the twin's
        # own camera model), its distance read with the drawn error.
        camera = TwinCamera(dataclasses.replace(g.camera, matrix=dr["matrix"][i], distortion=dr["distortion"][i]))
        true = Pose(dr["fixture_rotation"][i], dr["fixture_translation"][i])
        seen = camera.project(true.apply(design.corners_3d())) + dr["corner_noise_px"][i]
        distance = float(np.linalg.norm(true.apply(measure) - centre)) + dr["distance_m"][i]
        pose = solve_corner_pose(g.camera, seen, design.corners_3d(), g.fixture_to_camera).facet_to_camera
        pose, _ = fix_range(pose, measure, centre, distance, 1.0)
        p = placement(g.fixture_to_camera, pose, design)
        d = true.rotation.T @ pose.rotation
        errors.append([-1000.0 * d[2, 1], -1000.0 * d[0, 2], *p["mm"], *p["mrad"]])
    errors = np.array(errors)
    ref = np.sqrt(np.mean(errors ** 2, axis=0))
    got = np.sqrt([mc[p][0] for p in POSE_PATHS])
    assert ref[0] > 0.3 and ref[1] > 0.3                  # the boresight's spread is real (mrad)
    np.testing.assert_allclose(got, ref, rtol=0.025)
    assert -1.0 < errors[:, 6].mean() < -0.3               # placement rotation about y, mrad


def test_boresight_carries_the_principal_points_turn_of_the_rays(rig, two_captures):
    """The boresight is the rotation from the corner pose to the frame the measured surface defines; the
    camera's principal point turns that frame too (every ray by 1 / f per pixel), which the corner pose's
    Monte Carlo does not draw. On the twin, a camera whose principal point is 3 px off moves the boresight
    about x by 3 / f more than the placement's rotation (the corner pose's noise is common to both), and the
    budget adds that path (u / f for u = 1 px) to the boresight's U."""
    cfg = rig.config
    analyses, cache = two_captures
    first = analyses[0].figures
    f_px = cfg.geometry.camera.matrix[1, 1]
    rays = first["uncertainty_budget"]["pose_monte_carlo"]["boresight_camera_rays"]
    expected = 1000.0 * cfg.uncertainty.camera_principal_px / f_px
    assert rays["boresight_mrad.x"] == pytest.approx(expected, rel=0.05)
    assert rays["boresight_mrad.y"] == pytest.approx(expected, rel=0.05)

    k = cfg.geometry.camera.matrix.copy()
    k[1, 2] += 3.0
    true = dataclasses.replace(cfg.geometry, camera=dataclasses.replace(cfg.geometry.camera, matrix=k))
    twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4), geometry=true)
    frames = rig.capture(twin, np.random.default_rng(1))
    moved = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                    uncertainty=cfg.uncertainty, sensitivity_cache=cache).figures

    def gap(fig):
        return fig["boresight_mrad"]["x"] - fig["placement"]["mrad"][0]

    assert gap(moved) - gap(first) == pytest.approx(3000.0 / f_px, abs=0.1)


def test_twin_capture_with_the_ambient_given_draws_the_same_frames(rig):
    """``TwinRig.capture(..., steady=True)``: the frames are the ones drawn without it, and the steady ones
    have the same sensor noise with the ambient light at its nominal level in every frame, so the two differ
    by the ambient's change alone (what the frame-to-frame brightness leaves in a figure)."""
    twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
    plain = rig.capture(twin, np.random.default_rng(5))
    frames, steady = rig.capture(twin, np.random.default_rng(5), steady=True)
    assert np.array_equal(frames, plain)
    # The ambient of frame k is nominal x (1 + jitter z_k), z_k the first draw of each frame from the stream.
    rng = np.random.default_rng(5)
    z0 = float(rng.standard_normal())
    seen = twin.linear_dn(rig.images[1]) > twin.linear_dn(rig.images[0]) + 50      # the lit facet
    step = np.mean(frames[0][seen].astype(float) - steady[0][seen])
    nominal = twin.linear_dn(rig.images[0])
    twin.optics = dataclasses.replace(rig.optics, ambient=rig.optics.ambient * (1 + rig.optics.ambient_jitter * z0))
    expect = float(np.mean((twin.linear_dn(rig.images[0]) - nominal)[seen]))
    twin.optics = rig.optics
    assert abs(expect) > 0.05 and step == pytest.approx(expect, abs=0.03)
    assert not np.array_equal(frames, steady)
    # Without the ambient's jitter the steady frames are the frames.
    still = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
    still.optics = dataclasses.replace(still.optics, ambient_jitter=0.0)
    a, b = rig.capture(still, np.random.default_rng(5), steady=True)
    assert np.array_equal(a, b)


def test_frame_brightness_rows_state_what_a_known_brightness_change_does(rig):
    """The budget's frame-to-frame brightness rows against the figures' response to known brightness changes
    (issue 12: the x figures' U / std of 2.05-2.17 on some seeds). Noise-free twin; each frame of the finest
    x and y sets in turn brighter and darker by 2 ambient jitter deviations (D DN on the facet, measured as
    the mean change of the frame). A brightness noise sigma_f per frame then gives each figure the standard
    deviation sigma_f sqrt(sum_k (dF_k / D)^2); the budget's row states sigma_f times the same, per DN of
    the sigma_f it used. The x rows and the y rows are each right to a few per cent (on the coverage twin
    with the seeds' drawn ambients: 1.00-1.01 with the per-pixel ratio of the ambient to the modulation).

    The rows are checked on the decoding they model in full: without the correction of the display's 8-bit
    rounding (``FringeSet.drawn``, issue 47). With it, the twist e1's response to the x frames is 0.00165 per
    DN against 0.00157 without: the drawn part's gain (1 - e'(phi)) the rows now carry
    (:func:`~sofast_station.measure.phase.drawn_gain`) makes the row 0.00159; the rest, and 0.00020 per DN from
    the y frames, is the period sets' measured phase error refitted with a brighter frame (fitted over both
    axes' pixels), which the rows do not model yet (docs/uncertainty.md)."""
    from sofast_station.measure.analysis import analyse as run

    cfg = rig.config
    cfg = dataclasses.replace(cfg, fringes=dataclasses.replace(cfg.fringes, drawn=()))
    twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
    twin.optics = dataclasses.replace(twin.optics, read_noise_dn=0.0, electrons_per_dn=0.0)
    n = len(rig.images)
    cache: dict = {}

    def analysed(z):
        frames = np.stack([twin.capture(img, None, exposure_s=rig.exposure_s, gain=rig.gain, ambient_z=float(z[k]))
                           for k, img in enumerate(rig.images)])
        return frames, run(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                           uncertainty=cfg.uncertainty, sensitivity_cache=cache)

    frames0, a0 = analysed(np.zeros(n))
    budget = a0.figures["uncertainty_budget"]
    row = dict(zip(budget["figures"], next(r["contributions"] for r in budget["rows"]
                                           if r["group"] == "frame-to-frame brightness")))
    per_dn = {k: v / budget["frame_brightness"]["sigma_dn"] for k, v in row.items()}
    reach = {"x": ("focal_length_x_m", "slope_rms_mrad.design.x", "twist_e1_mrad_per_m"),
             "y": ("focal_length_y_m", "slope_rms_mrad.design.y", "twist_e2_mrad_per_m")}
    names = reach["x"] + reach["y"]
    slices = cfg.fringes.slices()
    seen = a0.valid
    for axis in "xy":
        response = {name: 0.0 for name in names}
        for k in range(slices[axis][-1].start, slices[axis][-1].stop):
            out = []
            for sign in (1.0, -1.0):
                z = np.zeros(n)
                z[k] = 2.0 * sign
                frames, a = analysed(z)
                d_dn = float(np.mean(frames[k][seen].astype(float) - frames0[k][seen]))
                out.append((a.figures, d_dn))
            for name in names:
                path = next(p for p in SCALAR_PATHS if path_name(p) == name)
                df = 0.5 * (get_path(out[0][0], path) - get_path(out[1][0], path))
                d = 0.5 * (out[0][1] - out[1][1])
                response[name] += (df / d) ** 2
        for name in names:
            if name in reach[axis]:
                assert np.sqrt(response[name]) == pytest.approx(per_dn[name], rel=0.04), (axis, name)
            else:                           # the other axis's frames leave these figures alone
                assert np.sqrt(response[name]) < 0.1 * per_dn[name], (axis, name)


def _flat_screen_as_grid(geometry, nx: int = 9, ny: int = 7):
    """The station's flat screen as a measured one (OpenCSP's kind): positions in fractions of the screen,
    each grid node's screen-frame point from the flat screen's size. Returns the screen and a geometry whose
    own screen is 1 x 1 m, as the OpenCSP import's, so nothing can fall back to the flat screen unnoticed."""
    from sofast_station.geometry import ScreenSpec
    from sofast_station.measure.pipeline import default_screen
    from sofast_station.measure.screen import InterpolatedScreen

    flat = default_screen(geometry)
    fx, fy = np.meshgrid(np.linspace(0.0, 1.0, nx), np.linspace(0.0, 1.0, ny))
    uv = np.column_stack([fx.ravel(), fy.ravel()])
    pts = np.column_stack([(uv[:, 0] - 0.5) * flat.width_m, (uv[:, 1] - 0.5) * flat.height_m, np.zeros(len(uv))])
    screen = InterpolatedScreen(1.0, 1.0, uv, pts, geometry.screen_to_camera)
    return screen, dataclasses.replace(geometry, screen=ScreenSpec(1000, 1000, 0.001))


def test_a_measured_screen_is_perturbed_as_itself(rig):
    """The flat screen's own grid as an InterpolatedScreen (fractional positions, the geometry's screen
    1 x 1 m as in the OpenCSP import) gives the flat screen's sensitivities and noise propagation.

    Tolerance: linear interpolation of a linear map is that map, so both reductions see the same screen
    points up to rounding (1e-16 relative); the reruns at +-u then differ by rounding only, and a
    contribution by a few 1e-16 of the figure, which is at most ~1e-11 of the column's largest
    contribution (found: 8e-12). 1e-6 leaves room and is six orders of magnitude below what a screen
    replaced by another one does: before the screen models had moved() and stretched(), the camera-to-screen
    and pitch rows of the measured screen fell back to a flat 1 x 1 m screen, 1270 times the column's
    largest contribution. The noise propagation's finite difference (1e-4 of the position unit) straddles
    no kink of a linear map: 1e-6 relative (found 2e-8)."""
    from sofast_station.measure.pipeline import reduce_stages
    from sofast_station.measure.uncertainty import noise_propagation, sensitivities

    cfg = rig.config
    twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
    frames = rig.capture(twin, np.random.default_rng(1))
    d = twin.measured_distance_m()
    grid, g_grid = _flat_screen_as_grid(cfg.geometry)
    out = {}
    for name, geometry, screen in (("flat", cfg.geometry, None), ("grid", g_grid, grid)):
        red, _ = reduce_stages(frames, cfg.fringes, geometry, cfg.design, d, cfg.analysis, screen)
        kw = dict(fringes=cfg.fringes, geometry=geometry, design=cfg.design, settings=cfg.analysis, screen=screen)
        out[name] = (sensitivities(red, measured_distance_m=d, inputs=cfg.uncertainty, **kw),
                     noise_propagation(red, **kw))
    (s_flat, n_flat), (s_grid, n_grid) = out["flat"], out["grid"]
    assert [i.name for i in s_flat.inputs] == [i.name for i in s_grid.inputs]
    column = np.nanmax(np.abs(s_flat.contributions), axis=0)
    rel = np.abs(s_grid.contributions - s_flat.contributions) / column
    worst = {inp.name: float(np.nanmax(rel[i])) for i, inp in enumerate(s_flat.inputs)}
    assert max(worst.values()) < 1e-6, {k: v for k, v in worst.items() if v >= 1e-6}
    assert any(inp.group == "screen pitch" for inp in s_grid.inputs)
    for path, sigma in n_flat.sigma.items():
        assert n_grid.sigma[path] == pytest.approx(sigma, rel=1e-6, abs=1e-300), path


def test_screen_models_move_and_stretch_alike(rig):
    """moved() and stretched() of the flat screen and of its own grid give the same points; a stretch keeps
    the centre, and doubles as the pitch error it stands for; the arguments are checked."""
    from sofast_station.measure.pipeline import default_screen
    from sofast_station.measure.uncertainty import small_motion

    flat = default_screen(rig.config.geometry)
    grid, _ = _flat_screen_as_grid(rig.config.geometry)
    rng = np.random.default_rng(3)
    fx, fy = rng.uniform(0.0, 1.0, 500), rng.uniform(0.0, 1.0, 500)
    w, h = flat.width_m, flat.height_m
    delta = small_motion((0.5, -0.3, 0.2), (0.4, 0.1, -0.6))
    for f, g in ((flat.moved(delta), grid.moved(delta)), (flat.stretched("x", 1.001), grid.stretched("x", 1.001)),
                 (flat.stretched("y", 0.999), grid.stretched("y", 0.999))):
        assert np.abs(f.points_camera(fx * w, fy * h) - g.points_camera(fx, fy)).max() < 1e-12
        assert np.allclose(f.centre_camera(), g.centre_camera(), rtol=0, atol=1e-12)
    assert np.allclose(flat.moved(delta).centre_camera(), flat.screen_to_camera.compose(delta).translation)
    assert np.array_equal(flat.stretched("x", 1.001).centre_camera(), flat.centre_camera())
    # the right edge moves out by half the width's change, in the screen's plane
    edge = flat.stretched("x", 1.001).points_camera(np.array([w]), np.array([0.5 * h]))[:, 0]
    assert np.linalg.norm(edge - flat.points_camera(np.array([w]), np.array([0.5 * h]))[:, 0]) == pytest.approx(
        0.0005 * w, rel=1e-9)
    # a measured screen whose centre is not its frame's origin turns about that centre: a pure rotation
    # leaves the centre where it was, and a stretch keeps it too
    from sofast_station.measure.screen import InterpolatedScreen
    off = InterpolatedScreen(1.0, 1.0, grid._nodes_uv, grid._nodes_screen, grid.screen_to_camera, (0.1, -0.05, 0.0))
    turn = small_motion((2.0, -1.0, 3.0))
    assert np.allclose(off.moved(turn).centre_camera(), off.centre_camera(), rtol=0, atol=1e-12)
    assert np.allclose(off.stretched("y", 1.01).centre_camera(), off.centre_camera(), rtol=0, atol=1e-15)
    # the unstretched screen and the flat screen at pitch scale 1 are the same bits
    assert np.array_equal(flat.stretched("x", 1.0).points_camera(fx * w, fy * h), flat.points_camera(fx * w, fy * h))
    for bad in (("z", 1.0), ("x", 0.0), ("y", float("nan"))):
        with pytest.raises(ValueError, match="axis|factor"):
            grid.stretched(*bad)
        with pytest.raises(ValueError, match="axis|factor"):
            flat.stretched(*bad)


def test_each_pixels_noise_follows_its_brightness_as_the_twins_camera_makes_it(rig):
    """The twin's camera adds read noise and shot noise (variance in proportion to the signal). Where the
    facet's edges cut through pixels, those pixels gather less light and are quieter: the noise the
    uncertainty gives each pixel of the facet's region (from the capture's noise-against-brightness line) is
    what two captures of the same scene show, for the dim edge pixels and for the rest, where the capture's
    one noise figure is far too high for the dim ones. (The shape no longer uses the edge pixels, which the
    lens's blur reaches, but the noise model is the capture's, for every pixel.)"""
    from sofast_station.measure.pipeline import reduce_stages
    from sofast_station.measure.uncertainty import pixel_noise_dn

    cfg = rig.config
    twin = rig.twin((0.5, -0.5, 0.2), (0.5, 0.3, -0.4))
    (_, one), (_, two) = (rig.capture(twin, np.random.default_rng(s), steady=True) for s in (3, 4))
    red, _ = reduce_stages(one, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis)
    take = np.flatnonzero(red.phases.min_modulation_dn >= cfg.analysis.min_modulation_dn)
    pix = red.region.idx[take]
    finest = cfg.fringes.slices()["x"][-1]
    # Each pixel's frame noise over the finest set's four frames, rounding included: var(f1 - f2) / 2.
    diff = (one[finest].reshape(4, -1)[:, pix].astype(float) - two[finest].reshape(4, -1)[:, pix]) ** 2 / 2.0
    seen = diff.mean(axis=0)
    got = np.broadcast_to(pixel_noise_dn(red, take), take.shape)
    level = np.subtract(red.region.stack[1][take], red.region.stack[0][take], dtype=float)
    dim = level < 0.8 * np.median(level)
    assert dim.sum() > 100
    for sel in (dim, ~dim):
        assert np.sqrt(np.mean(got[sel] ** 2)) == pytest.approx(np.sqrt(np.mean(seen[sel])), rel=0.06)
    assert red.phases.noise_dn > 1.2 * np.sqrt(np.mean(seen[dim]))


@pytest.mark.parametrize("inputs", [{"distance_mm": 300.0}, {"camera_focal_px": 500.0}],
                         ids=["distance_300_mm", "camera_focal_500_px"])
def test_sensitivity_reruns_never_trip_the_captures_checks(rig, inputs):
    """Issue 26: the uncertainty's reruns move the station's inputs, not the capture. A sensitivity study
    with [uncertainty] distance_mm = 300 moved the rerun's distance 0.3 m from the corner pose's range,
    beyond the 0.25 m a capture may differ, and the facet was refused with "re-measure the distance"
    (the distance was fine); camera_focal_px = 500 (15 % of the 3409 px lens) put the rerun's corners
    off the outline and refused it as "partly lit or obstructed". Both analyse, with a U that grows
    with the input's."""
    cfg = rig.config
    twin = rig.twin((0.3, -0.2, 0.1), (0.2, -0.3, 0.4))
    frames = rig.capture(twin, np.random.default_rng(3))
    base = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                   uncertainty=cfg.uncertainty)
    a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis,
                uncertainty=dataclasses.replace(cfg.uncertainty, **inputs))
    assert a.figures["focal_length_x_m"] == base.figures["focal_length_x_m"]
    assert a.figures["focal_length_x_m_U"] > 3 * base.figures["focal_length_x_m_U"]


def test_the_written_axis_angle_table_is_the_quantile_computed_afresh():
    """budget._AXIS_U_95 is written into the source (computing it cost every command 0.08 s): it must be
    what _projected_normal_quantile gives at each of its points (to rounding: numpy's exp and cos may
    differ in the last bit between CPUs), and the quantile itself right where it is known in closed form."""
    from sofast_station.measure.uncertainty import budget

    fresh = np.array([0.5 * budget._projected_normal_quantile(1.0 / (2.0 * u)) for u in budget._AXIS_U_LIN])
    assert budget._AXIS_U_95.shape == fresh.shape
    np.testing.assert_allclose(budget._AXIS_U_95, fresh, rtol=1e-12, atol=0)
    # d = 0: the direction is uniform on (-pi, pi], so the 95 % quantile of |theta| is 0.95 pi
    assert budget._projected_normal_quantile(0.0) == pytest.approx(0.95 * np.pi, rel=1e-3)
    # d large: theta ~ N(0, 1 / d^2), the quantile 1.96 / d (to the grid and the 1 / d^2 terms)
    assert budget._projected_normal_quantile(20.0) == pytest.approx(1.959964 / 20.0, rel=1e-2)
