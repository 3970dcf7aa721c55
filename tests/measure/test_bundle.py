"""The bundle adjustment: analytic derivatives against finite differences, recovery of known parameters with
a covariance that matches the scatter, the noise estimated from the residuals, undetermined parameters named.

All synthetic (projections of known points through known poses with known noise): the forward model is the
oracle."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.geometry import CameraIntrinsics, Pose
from sofast_station.measure import bundle
from sofast_station.measure import commission as C
from sofast_station.measure.screen_shape import ScreenShape

CAM = CameraIntrinsics(640, 480, [[600.0, 0, 319.5], [0, 610.0, 239.5], [0, 0, 1]], [0.02, -0.05, 1e-3, 2e-3, 0.01])


def _finite_difference_check(blocks, groups, tol=1e-4):
    """Every group's analytic derivative against central differences (relative to the column's size): a
    wrong derivative is wrong by its own size; central differences with steps of 1e-6 are good to ~1e-5."""
    values = {b.name: b.x0 for b in blocks}
    worst = 0.0
    for g in groups:
        _, jac = g.function(values, True)
        for name in g.blocks:
            b = next(bb for bb in blocks if bb.name == name)
            for i in range(b.size):
                h = 1e-6 if b.is_pose else 1e-6 * max(1.0, abs(b.x0[i]))
                d = np.zeros(b.size)
                d[i] = h
                vp, vm = dict(values), dict(values)
                vp[name] = bundle.moved(values[name], d) if b.is_pose else values[name] + d
                vm[name] = bundle.moved(values[name], -d) if b.is_pose else values[name] - d
                fd = (g.function(vp, False) - g.function(vm, False)) / (2 * h)
                scale = max(np.max(np.abs(fd)), np.max(np.abs(jac[name][:, i])), 1e-3)
                worst = max(worst, float(np.max(np.abs(fd - jac[name][:, i]))) / scale)
    assert worst < tol, worst


def test_projection_derivatives_match_finite_differences():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.3, -0.2, 0.8], [0.3, 0.2, 1.2], (20, 3))
    cam = bundle.camera_vector(CAM)
    pix, d_pt, d_cam = bundle.project(cam, pts, True)
    for i in range(3):
        e = np.zeros(3)
        e[i] = 1e-7
        fd = (bundle.project(cam, pts + e) - bundle.project(cam, pts - e)) / 2e-7
        assert np.allclose(fd, d_pt[:, :, i], rtol=1e-6, atol=1e-4)
    for i in range(9):
        e = np.zeros(9)
        e[i] = 1e-7 * max(1.0, abs(cam[i]))
        fd = (bundle.project(cam + e, pts) - bundle.project(cam - e, pts)) / (2 * e[i])
        assert np.allclose(fd, d_cam[:, :, i], rtol=1e-6, atol=1e-4)


def test_screen_view_groups_have_exact_derivatives():
    """The screen fit's groups (fiducials, fringes, the scale board with its scale) at a bowed screen."""
    rng = np.random.default_rng(1)
    pose = Pose(bundle.rotation_from_vector([3.0, 0.1, -0.05]), np.array([0.05, -0.02, 0.9]))
    uv = rng.uniform([0.02, 0.02], [0.5, 0.28], (15, 2))
    view = C.ScreenView("v", bundle.project(bundle.camera_vector(CAM), pose.apply(np.column_stack(
        [uv[:, 0] - 0.264, uv[:, 1] - 0.1485, np.zeros(15)]))), uv, rng.uniform(0, 400, (8, 2)),
        rng.uniform(0, 0.2, (8, 2)), rng.uniform(0, 400, (10, 2)), rng.uniform(0, 0.5, (10, 2)), np.full((10, 2), 1e-4))
    starts = {"views": [pose], "fringe_sigma": [np.full(20, 0.1)],
              "board_to_screen": Pose(np.diag([1.0, -1.0, -1.0]), np.array([0.3, 0.1, 0.004])),
              "shape": {"a_x": 0.01, "x:P3,0": 1e-4, "y:P2,1": -2e-4, "z:2,0": 1e-3, "z:1,1": 3e-4}}
    blocks, groups = C._screen_problem([view], CAM, [1.0] * 9, "distorted3d", 0.528, 0.297, 5e-5, starts)
    _finite_difference_check(blocks, groups)


def test_mirror_distance_and_border_groups_have_exact_derivatives():
    rng = np.random.default_rng(2)
    cam = bundle.camera_vector(CameraIntrinsics(400, 300, [[3409, 0, 199.5], [0, 3409, 149.5], [0, 0, 1]],
                                                [-0.05, 0.1, 2e-4, -1e-4, 0.0]))
    shape = ScreenShape("distorted3d", 0.528, 0.297, np.r_[0.01, 0.002, rng.normal(0, 1e-4, 27)])
    screen = Pose(bundle.rotation_from_vector([0.01, 3.1, 0.02]), np.array([-0.34, 0.01, 0.02]))
    target = Pose(bundle.rotation_from_vector([3.1, 0.0, 0.01]), np.array([-0.5, -0.4, 10.6]))
    uv = rng.uniform(0, 0.3, (15, 2))
    base, design = shape.basis(uv[:, 0], uv[:, 1])
    blocks = [bundle.Block("screen", screen), bundle.Block("camera", cam), bundle.Block("pitch", shape.params[:2]),
              bundle.Block("scale", [1.0]), bundle.Block("target 0", target)]
    border = rng.uniform(0, 1, (12, 3))
    border[:, 2] = 0.0
    normals = rng.normal(size=(12, 2))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    groups = [bundle.Group("f", ["screen", "target 0", "pitch", "camera"],
                           C._mirror_group("target 0", rng.uniform(0, 300, (15, 2)), base,
                                           design[:, :, 2:] @ shape.params[2:], design[:, :, :2]), 1.0),
              bundle.Group("d", ["screen", "target 0", "scale"],
                           C._distance_group("target 0", np.array([0.5, 0.4, 0.0]), 10.7), 1.0),
              bundle.Group("b", ["target 0", "scale", "camera"],
                           C._border_group("target 0", border, rng.uniform(0, 300, (12, 2)), normals), 1.0)]
    _finite_difference_check(blocks, groups)


def _pnp_problem(rng, noise_px, n_points=40):
    """A camera pose from noisy projections of known points: the smallest bundle adjustment."""
    truth = Pose(bundle.rotation_from_vector([0.1, -0.2, 0.05]), np.array([0.02, -0.01, 1.0]))
    pts = rng.uniform([-0.3, -0.2, -0.05], [0.3, 0.2, 0.05], (n_points, 3))
    obs = bundle.project(bundle.camera_vector(CAM), truth.apply(pts)) + rng.normal(0, noise_px, (n_points, 2))

    def f(values, der):
        pose, cam = values["pose"], values["camera"]
        if not der:
            return (bundle.project(cam, pose.apply(pts)) - obs).ravel()
        pix, d_pix, _ = bundle.project(cam, pose.apply(pts), True)
        return (pix - obs).ravel(), {"pose": np.einsum("nij,njk->nik", d_pix,
                                                       bundle.pose_derivative(pose, pts)).reshape(-1, 6)}

    start = bundle.moved(truth, rng.normal(0, [0.01] * 3 + [0.005] * 3))
    blocks = [bundle.Block("pose", start), bundle.Block("camera", bundle.camera_vector(CAM), fixed=True)]
    return truth, blocks, [bundle.Group("points", ["pose"], f, 1.0)]


def test_solve_recovers_the_pose_and_its_covariance_matches_the_scatter():
    """40 noisy projections (0.1 px), the noise unknown to the solver (its guess is 1 px): over 60 draws the
    errors scatter as the stated covariance says (the normalised squared errors average 6, one per
    parameter; between 4.5 and 7.5 for 60 draws), and the estimated noise is the true 0.1 px to 10 %."""
    rng = np.random.default_rng(3)
    chi, sig = [], []
    for _ in range(60):
        truth, blocks, groups = _pnp_problem(rng, 0.1)
        sol = bundle.solve(blocks, groups)
        err = bundle.motion_between(truth, sol.values["pose"])
        chi.append(float(err @ np.linalg.solve(sol.covariance["pose"], err)))
        sig.append(sol.sigma["points"])
    print(f"\nmean normalised squared error {np.mean(chi):.2f} (6 expected); noise {np.mean(sig):.4f} px (0.1)")
    assert 4.5 < np.mean(chi) < 7.5
    assert abs(np.mean(sig) / 0.1 - 1.0) < 0.1


def test_an_outlier_is_dropped_and_counted():
    rng = np.random.default_rng(4)
    truth, blocks, groups = _pnp_problem(rng, 0.05)
    f0 = groups[0].function

    def spoiled(values, der):                  # one misdetected point, 5 px off
        out = f0(values, der)
        r = out[0] if der else out
        r = r.copy()
        r[7] += 5.0
        return (r, out[1]) if der else r

    groups[0].function = spoiled
    sol = bundle.solve(blocks, groups)
    assert sol.dropped["points"] == 1
    assert np.max(np.abs(bundle.motion_between(truth, sol.values["pose"]))) < 1e-3


def test_an_undetermined_parameter_is_named():
    """A scale that no observation sees (its column is zero) and two parameters that only appear as a sum
    are not determined: the solver says which."""
    x = np.linspace(0, 1, 20)
    obs = 2.0 * x + 1.0

    def f(values, der):
        a, b = values["ab"]
        r = (a + b) * x + 1.0 - obs
        return (r, {"ab": np.column_stack([x, x])}) if der else r

    sol = bundle.solve([bundle.Block("ab", [0.5, 0.5], names=["a", "b"])], [bundle.Group("y", ["ab"], f, 0.01)],
                       estimate_noise=False, outlier_sigmas=0.0)
    assert set(sol.undetermined) == {"a", "b"}


def test_the_nested_model_test_needs_the_richer_model_only_when_it_earns_it():
    assert not bundle.nested_model_test(1010.0, 1000.0, 5, 1000)["needed"]      # 2 per extra parameter: noise
    assert bundle.nested_model_test(1100.0, 1000.0, 5, 1000)["needed"]          # 20 each: structure


@pytest.mark.parametrize("omega", [[0.0, 0.0, 0.0], [1e-9, 0, 0], [0.3, -0.2, 0.1], [0.0, 3.1, 0.0]])
def test_rotation_vectors_round_trip(omega):
    r = bundle.rotation_from_vector(omega)
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.allclose(bundle.vector_from_rotation(r), omega, atol=1e-9)
