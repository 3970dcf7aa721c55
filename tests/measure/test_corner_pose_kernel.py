"""The corner pose Monte Carlo's compiled 4-point pose solver (kernels.solve_poses, behind
corner_pose.solve_poses_batch) against its numpy version (corner_pose._solve_poses_batch_numpy), which stays
as the reference: the same Levenberg-Marquardt, step by step, to the same minimum."""

from __future__ import annotations

import cv2
import numpy as np

from sofast_station.measure.uncertainty.corner_pose import (PNP_EPSILON, _project_batch, _solve_poses_batch_numpy,
                                                            solve_poses_batch)


def _problem(seed: int, m: int, n: int, far: bool = False):
    """n draws of one random but realistic station: a camera (f 700-3000 px, skew, principal point off centre,
    radial and tangential distortion) drawn about its calibration per draw, a facet's m corners (4, or 8: its
    corners and four inside) on a paraboloid 3-12 m away, seen with corner noise of 0.05-2 px, and the solver's
    start a few mrad and mm off the truth (*far*: about 0.1 rad and 0.1 m, where undamped steps overshoot)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(700, 3000)
    k = np.array([[f * rng.uniform(0.98, 1.02), rng.normal(0, 0.5), f * rng.uniform(0.5, 0.6)],
                  [0.0, f, f * rng.uniform(0.35, 0.45)], [0.0, 0.0, 1.0]])
    dist = rng.normal(0, 1, 5) * [0.1, 0.1, 1e-3, 1e-3, 0.02]
    xy = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * rng.uniform(0.3, 0.8, 2)
    if m == 8:
        xy = np.vstack([xy, 0.5 * xy + rng.normal(0, 0.05, (4, 2))])
    pts = np.column_stack([xy, np.sum(xy ** 2, axis=1) / (4 * rng.uniform(10, 200))])
    rot = cv2.Rodrigues(np.array([np.pi, 0, 0]) + rng.normal(0, 0.2, 3))[0]
    tr = np.array([rng.normal(0, 0.2), rng.normal(0, 0.2), rng.uniform(3, 12)])
    seen = _project_batch(rot[None], tr[None], pts, k[None], dist[None])
    obs = seen + rng.uniform(0.05, 2.0) * rng.normal(size=(n, m, 2))
    kk = np.repeat(k[None], n, axis=0)
    kk[:, (0, 1, 0, 1), (0, 1, 2, 2)] += rng.normal(0, 1, (n, 4))
    dd = dist + rng.normal(0, 1, (n, 5)) * [2e-3, 1e-2, 5e-5, 5e-5, 1e-3]
    off = 0.1 if far else 3e-3
    return obs, pts, kk, dd, rot @ cv2.Rodrigues(rng.normal(0, off, 3))[0], tr + rng.normal(0, off, 3)


def _cost(rotation, translation, obs, pts, k, dist):
    return np.sum((_project_batch(rotation, translation, pts, k, dist) - obs) ** 2, axis=(1, 2))


def test_the_compiled_solver_takes_the_numpy_solvers_steps():
    """After one, two and three accepted steps (no stop by the parameter change) the compiled solver's poses
    are the numpy version's to 1e-12 (rotation elements; translation relative): the same Jacobian, damping
    schedule and step, in another order of rounding (measured: at most 2e-15 over these draws). 6 problems
    (3 stations x 4 and 8 corners) x 40 draws, half started far off so that some first steps grow the error and
    are redone with more damping. A wrong sign or factor in the Jacobian, or another damping (l from -2 instead
    of -3, or down by 2 after an accepted step), moves the first or second step by 1e-4 relative or more."""
    for seed in range(3):
        for m in (4, 8):
            for far in (False, True):
                args = _problem(seed, m, 20, far)
                for steps in (1, 2, 3):
                    r_k, t_k, _ = solve_poses_batch(*args, max_iter=steps, epsilon=0.0)
                    r_n, t_n, _ = _solve_poses_batch_numpy(*args, max_iter=steps, epsilon=0.0)
                    assert np.abs(r_k - r_n).max() < 1e-12, (seed, m, far, steps)
                    assert np.max(np.linalg.norm(t_k - t_n, axis=1) / np.linalg.norm(t_n, axis=1)) < 1e-12


def test_the_compiled_solver_reaches_the_numpy_solvers_minimum():
    """Run to their stop (relative parameter change below FLT_EPSILON), the two solvers stop on the same draws
    and at the same minimum: reprojection errors equal to 1e-9 relative, rotation elements within FLT_EPSILON
    (1.2e-7) and translations within FLT_EPSILON relative. Why not closer: near the minimum a step is a few
    1e-9 and the gradient J^T e is rounding noise along the nearly frontal facet's flat valley, so the two
    orders of rounding settle a few 1e-9 apart there, where both stop (over 12,000 draws of 60 such
    problems: 11,997 converged in both, 99.9 % agreeing to 1e-12, the worst 5.9e-8 in a rotation element and
    1.4e-9 in translation). 12 problems x 100 draws, half started far off."""
    for seed in range(3, 9):
        for m in (4, 8):
            obs, pts, k, dist, r0, t0 = args = _problem(seed, m, 100, far=seed % 2 == 0)
            r_k, t_k, c_k = solve_poses_batch(*args)
            r_n, t_n, c_n = _solve_poses_batch_numpy(*args)
            assert np.array_equal(c_k, c_n) and c_n.mean() > 0.95
            assert np.abs(r_k - r_n).max() < PNP_EPSILON
            assert np.max(np.linalg.norm(t_k - t_n, axis=1) / np.linalg.norm(t_n, axis=1)) < PNP_EPSILON
            cost_k, cost_n = _cost(r_k, t_k, obs, pts, k, dist), _cost(r_n, t_n, obs, pts, k, dist)
            assert np.max(np.abs(cost_k - cost_n) / cost_n) < 1e-9
            # and that minimum is the reprojection error's: no pose a little off it is better
            for d in (np.array([1e-5, 0, 0]), np.array([0, 1e-5, 0]), np.array([0, 0, 1e-5])):
                moved = r_k @ cv2.Rodrigues(d)[0]
                assert np.all(_cost(moved, t_k, obs, pts, k, dist) >= cost_k * (1 - 1e-12))
                assert np.all(_cost(r_k, t_k + 1e-2 * d, obs, pts, k, dist) >= cost_k * (1 - 1e-12))


def test_a_draw_whose_step_cannot_be_solved_is_marked_and_the_others_are_not_touched():
    """A draw whose 6 x 6 system is singular (a camera of zero focal length: every derivative zero) comes back
    NaN and not converged, as the kernel's docstring says (the numpy version steps by the pseudo-inverse
    instead); the draws around it get the poses they get alone."""
    obs, pts, k, dist, r0, t0 = _problem(11, 4, 5)
    k[2, :2] = 0.0
    rot, tr, conv = solve_poses_batch(obs, pts, k, dist, r0, t0)
    assert np.all(np.isnan(rot[2])) and np.all(np.isnan(tr[2])) and not conv[2]
    keep = [0, 1, 3, 4]
    alone = solve_poses_batch(obs[keep], pts, k[keep], dist[keep], r0, t0)
    assert np.array_equal(rot[keep], alone[0]) and np.array_equal(tr[keep], alone[1]) and conv[keep].all()
