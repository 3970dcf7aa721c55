"""The corner pose's figures (boresight, placement) by Monte Carlo (GUM Supplement 1): the corners' noise,
the camera intrinsics, the fixture pose and the measured distance drawn together, every draw's 4-point pose
solved at once (:func:`solve_poses_batch`), because that pose is far from linear in its inputs.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..kernels import solve_poses
from .inputs import InputUncertainties, pose_covariance_mrad_mm

#: Figures the corner pose decides (their U comes from :func:`pose_monte_carlo`).
POSE_PATHS: tuple[tuple, ...] = (("boresight_mrad", "x"), ("boresight_mrad", "y"),
                                 *[("placement", "mm", i) for i in range(3)],
                                 *[("placement", "mrad", i) for i in range(3)])
#: Budget groups the Monte Carlo of the corner pose draws (the other groups' contributions are added to it).
POSE_GROUPS = ("measured distance", "camera focal length", "camera principal point", "camera distortion",
               "fixture pose", "corner location")
#: Budget groups it draws as well where the pose record's joint covariance correlates the screen's pose with the
#: fixture's (:func:`pose_draws`, :func:`pose_monte_carlo`'s *screen_paths*).
SCREEN_GROUPS = ("camera-to-screen rotation", "camera-to-screen translation")
#: Draws of the Monte Carlo (each solves the 4-corner pose twice: all inputs, corners alone).
POSE_DRAWS = 200


def _rotation_batch(angles: np.ndarray) -> np.ndarray:
    """:func:`_rotation` of each row (rx, ry, rz) of *angles* (n, 3), radians: (n, 3, 3)."""
    c, s = np.cos(angles), np.sin(angles)
    one, zero = np.ones(len(angles)), np.zeros(len(angles))
    r_x = np.stack([one, zero, zero, zero, c[:, 0], -s[:, 0], zero, s[:, 0], c[:, 0]], -1).reshape(-1, 3, 3)
    r_y = np.stack([c[:, 1], zero, s[:, 1], zero, one, zero, -s[:, 1], zero, c[:, 1]], -1).reshape(-1, 3, 3)
    r_z = np.stack([c[:, 2], -s[:, 2], zero, s[:, 2], c[:, 2], zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return r_z @ r_y @ r_x


def _rotations(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors *w* (n, 3), radians (Rodrigues' formula)."""
    theta = np.sqrt(np.sum(w * w, axis=1))
    k = w / np.where(theta < 1e-300, 1.0, theta)[:, None]
    kx = np.zeros((w.shape[0], 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    return np.eye(3) + np.sin(theta)[:, None, None] * kx + (1.0 - np.cos(theta))[:, None, None] * (kx @ kx)


def rotation_vectors(rotation: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3), radians, of rotation matrices *rotation* (n, 3, 3): the inverse of
    :func:`_rotations` for angles below pi."""
    skew = np.stack([rotation[:, 2, 1] - rotation[:, 1, 2], rotation[:, 0, 2] - rotation[:, 2, 0],
                     rotation[:, 1, 0] - rotation[:, 0, 1]], axis=1)
    cos = np.clip(0.5 * (np.trace(rotation, axis1=1, axis2=2) - 1.0), -1.0, 1.0)
    sin = 0.5 * np.linalg.norm(skew, axis=1)
    theta = np.arctan2(sin, cos)
    # theta / sin(theta) -> 1 for a small turn
    scale = np.where(sin > 1e-12, theta / np.where(sin > 1e-12, sin, 1.0), 1.0)
    return 0.5 * skew * scale[:, None]


def _project_batch(rotation, translation, points, matrix, distortion, jacobian: bool = False):
    """Image positions (n, m, 2) of *points* (m, 3) under n poses (*rotation* (n, 3, 3), *translation*
    (n, 3)) and n cameras (*matrix* (n, 3, 3), *distortion* (n, 5): k1, k2, p1, p2, k3): the arithmetic of
    OpenCV's projectPoints for the 5-coefficient model. With *jacobian*, also their derivatives (n, m, 2, 6)
    with respect to a rotation w applied on the left (R <- exp(w) R) and to the translation."""
    rp = rotation @ points.T                                        # (n, 3, m): R X
    xc = rp + translation[:, :, None]
    iz = 1.0 / xc[:, 2]
    x, y = xc[:, 0] * iz, xc[:, 1] * iz
    k1, k2, p1, p2, k3 = (distortion[:, i, None] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    fx, s, cx = matrix[:, 0, 0, None], matrix[:, 0, 1, None], matrix[:, 0, 2, None]
    fy, cy = matrix[:, 1, 1, None], matrix[:, 1, 2, None]
    uv = np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=-1)
    if not jacobian:
        return uv
    d_rad = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))          # d radial / dx = d_rad x
    dxd_dx = radial + d_rad * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = d_rad * x * y + 2.0 * p1 * x + 2.0 * p2 * y            # = d yd / dx
    dyd_dy = radial + d_rad * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    jac = np.empty(x.shape + (2, 6))
    rpt = np.moveaxis(rp, 1, -1)                                    # (n, m, 3): R X
    for row, (dx, dy) in enumerate(((fx * dxd_dx + s * dxd_dy, fx * dxd_dy + s * dyd_dy),
                                    (fy * dxd_dy, fy * dyd_dy))):
        # d/dXc of x = X/Z, y = Y/Z; then d(exp(w) R X)/dw at w = 0 is -[R X]x, so d/dw = (R X) x d/dXc.
        g = np.stack([dx * iz, dy * iz, -(dx * x + dy * y) * iz], axis=-1)
        jac[..., row, 3:] = g
        jac[..., row, :3] = np.cross(rpt, g)
    return uv, jac


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """The left Jacobian of SO(3) at rotation vectors *phi* (n, 3): exp(phi + d) = exp(J d) exp(phi)."""
    theta = np.sqrt(np.sum(phi * phi, axis=1))[:, None, None]
    k = np.zeros((phi.shape[0], 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(t)) / t ** 2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t ** 3)
    return np.eye(3) + a * k + b * (k @ k)


#: Levenberg-Marquardt of :func:`solve_poses_batch`: at most this many accepted steps, stopping at a relative
#: parameter change below FLT_EPSILON (the criterion of OpenCV's solvePnP refinement, whose 20 steps stop short
#: of the minimum for some draws; this one goes on to it).
PNP_MAX_ITER = 200
PNP_EPSILON = float(np.finfo(np.float32).eps)


def solve_poses_batch(corners_px: np.ndarray, points: np.ndarray, matrix: np.ndarray, distortion: np.ndarray,
                      rotation0: np.ndarray, translation0: np.ndarray, max_iter: int = PNP_MAX_ITER,
                      epsilon: float = PNP_EPSILON) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n camera-from-object poses, each refined from (*rotation0* (3, 3), *translation0* (3,)) so that *points*
    (m, 3) project onto its *corners_px* (n, m, 2) with the least squared reprojection error in pixels: the
    algorithm of :func:`_solve_poses_batch_numpy` (which documents it, and stays as its reference), in one
    compiled pass over the draws (:func:`~sofast_station.measure.kernels.solve_poses`): on numpy the draws'
    tiny arrays cost a call's overhead each, 9 ms of CPU per capture's Monte Carlo. A draw whose step cannot be
    solved (a singular 6 x 6 system, its corners leaving the pose undetermined) comes back NaN and not
    converged, which the Monte Carlo drops, where the numpy version takes a pseudo-inverse step.

    Returns
    -------
    (rotation (n, 3, 3), translation (n, 3), converged (n,) bool: stopped by *epsilon* within *max_iter*)
    """
    rvec0 = cv2.Rodrigues(np.asarray(rotation0, np.float64))[0].ravel()
    start = np.concatenate([rvec0, np.asarray(translation0, np.float64).ravel()])
    return solve_poses(corners_px, points, matrix, distortion, start, max_iter, epsilon)


def _solve_poses_batch_numpy(corners_px: np.ndarray, points: np.ndarray, matrix: np.ndarray,
                             distortion: np.ndarray, rotation0: np.ndarray, translation0: np.ndarray,
                             max_iter: int = PNP_MAX_ITER,
                             epsilon: float = PNP_EPSILON) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n camera-from-object poses at once, each refined from (*rotation0* (3, 3), *translation0* (3,)) so
    that *points* (m, 3) project onto its *corners_px* (n, m, 2) with the least squared reprojection error in
    pixels: what the station's own corner pose (:func:`~sofast_station.measure.pose.solve_corner_pose`,
    OpenCV's ``solvePnP(SOLVEPNP_ITERATIVE)`` from the fixture's nominal pose) minimises, on all n problems
    as arrays (a Monte Carlo's hundreds of 4-point solves then cost one solve's Python overhead).

    Levenberg-Marquardt as in OpenCV's refinement: parameters (Rodrigues vector, translation), the analytic
    Jacobian of the projection (the rotation's through the left Jacobian of SO(3)), Marquardt's damping
    (``J^T J`` with its diagonal times ``1 + 10^l``, l from -3, up by one and the step redone from the same
    point while the error grows, down by one after each accepted step), stopping at a relative parameter
    change below *epsilon*. Not after OpenCV's 20 steps: the four corners of a nearly frontal facet leave
    its pose a long, flat, curved valley of the reprojection error, along which the steps shrink slowly
    (each about 0.6 of the last), and OpenCV stops typically 0.03 mrad (at most 0.3) short of the minimum
    for one capture's corner noise, 1-20 mrad for a draw that lands far along the valley. On the 400 x 300
    twin this solver reaches the minimum (the error at most OpenCV's) and the Monte Carlo's U are 0.3-1.9 %
    above those with OpenCV's stops (20 captures).

    Returns
    -------
    (rotation (n, 3, 3), translation (n, 3), converged (n,) bool: stopped by *epsilon* within *max_iter*)
    """
    n = corners_px.shape[0]
    points = np.asarray(points, np.float64)
    obs = np.asarray(corners_px, np.float64).reshape(n, -1)
    rvec0 = cv2.Rodrigues(np.asarray(rotation0, np.float64))[0].ravel()
    param = np.tile(np.concatenate([rvec0, np.asarray(translation0, np.float64).ravel()]), (n, 1))

    def evaluate(idx, p):
        uv, jac = _project_batch(_rotations(p[:, :3]), p[:, 3:], points, matrix[idx], distortion[idx], jacobian=True)
        jac = jac.reshape(len(idx), -1, 6)
        jac[..., :3] = jac[..., :3] @ _left_jacobian(p[:, :3])
        err = uv.reshape(len(idx), -1) - obs[idx]
        jt = np.swapaxes(jac, 1, 2)
        return np.sqrt(np.sum(err * err, axis=1)), jt @ jac, (jt @ err[..., None])[..., 0]

    everyone = np.arange(n)
    prev_norm, jtj, jte = evaluate(everyone, param)
    prev = param.copy()
    lam_lg = np.full(n, -3)
    iters = np.zeros(n, int)
    active = np.ones(n, bool)
    converged = np.zeros(n, bool)
    eye6 = np.eye(6)
    while active.any():
        idx = np.flatnonzero(active)
        a = jtj[idx] * (1.0 + eye6 * 10.0 ** lam_lg[idx, None, None])
        try:
            step = np.linalg.solve(a, jte[idx][..., None])[..., 0]
        except np.linalg.LinAlgError:       # a draw whose corners leave the pose undetermined
            step = (np.linalg.pinv(a) @ jte[idx][..., None])[..., 0]
        new = prev[idx] - step
        norm, jtj_new, jte_new = evaluate(idx, new)
        worse = ~(norm <= prev_norm[idx])
        lam_lg[idx[worse]] += 1
        take = ~(worse & (lam_lg[idx] <= 16))        # a worse step is redone with more damping, up to 16
        ia = idx[take]
        lam_lg[ia] = np.maximum(lam_lg[ia] - 1, -16)
        iters[ia] += 1
        param[ia] = new[take]
        change = np.linalg.norm(new[take] - prev[ia], axis=1) / np.maximum(np.linalg.norm(prev[ia], axis=1), 1e-300)
        small = change < epsilon
        stop = small | (iters[ia] >= max_iter)
        active[ia[stop]] = False
        converged[ia[small]] = True
        go = ~stop
        on = ia[go]
        prev_norm[on], prev[on] = norm[take][go], new[take][go]
        jtj[on], jte[on] = jtj_new[take][go], jte_new[take][go]
    return _rotations(param[:, :3]), param[:, 3:].copy(), converged


def pose_draws(corners_px: np.ndarray, corner_factor: np.ndarray, geometry, inputs: InputUncertainties,
               draws: int = POSE_DRAWS, seed: int = 12, with_screen: bool = False) -> dict:
    """The inputs :func:`pose_monte_carlo` draws: the noise of the *corners_px* (n, 2), ``corner_factor @ z``
    (C = M M^T, the corners' covariance in pixels squared), the camera's focal lengths, principal point and
    distortion, the fixture pose and the measured distance's error from *inputs*.

    Standard normal draws, each input's column moment-matched (mean 0, standard deviation 1 exactly): the
    same draws serve every capture (fixed *seed*), so their sampling error would otherwise be one common
    bias of every U (a few per cent with 200 draws); matched, the linear part is exact.

    Returns
    -------
    dict of arrays over the draws
        ``camera_z`` (draws, 9): the camera's draws in standard deviations (f_x, f_y, c_x, c_y, then
        k1, k2, p1, p2, k3), ``corner_noise_px`` (draws, n, 2), the camera's ``matrix`` (draws, 3, 3) and ``distortion``
        (draws, 5), ``fixture_rotation`` (draws, 3, 3) and ``fixture_translation`` (draws, 3) of the
        fixture-to-camera pose, ``distance_m`` (draws,): the measured distance's error, metres. With
        *with_screen* and a joint covariance of the screen's and the fixture's poses in *inputs*
        (:func:`~.inputs.pose_covariance_mrad_mm`), also ``screen_motion`` (draws, 6): the screen's true small
        motion from the stated one, mrad and mm, drawn jointly with the fixture's (six more standard normals
        after the others, so that the draws without it stay as they were).
    """
    rng = np.random.default_rng(seed)
    corners = np.asarray(corners_px, np.float64)
    cam, fix0 = geometry.camera, geometry.fixture_to_camera
    z = rng.standard_normal((draws, corners.size + 4 + 5 + 6 + 1))
    z = (z - z.mean(axis=0)) / z.std(axis=0)
    z_c, z_k, z_d, z_f, z_r = np.split(z, np.cumsum([corners.size, 4, 5, 6]), axis=1)
    u_k = np.array([inputs.camera_focal_px, inputs.camera_focal_px, inputs.camera_principal_px,
                    inputs.camera_principal_px])
    k = np.repeat(cam.matrix[None], draws, axis=0)
    k[:, (0, 1, 0, 1), (0, 1, 2, 2)] += z_k * u_k
    fixture = z_f * np.concatenate([inputs.fixture_rotation_mrad, inputs.fixture_translation_mm])
    joint = pose_covariance_mrad_mm(inputs) if with_screen else None
    screen = None
    if joint is not None:
        z_s = rng.standard_normal((draws, 6))
        z_s = (z_s - z_s.mean(axis=0)) / z_s.std(axis=0)
        # fixture first: its draws are L_ff z_f, the screen's L_sf z_f + L_ss z_s (C = L L^T, fixture then screen)
        order = np.r_[6:12, 0:6]
        low = np.linalg.cholesky(joint[np.ix_(order, order)] + 1e-12 * np.eye(12) * np.trace(joint) / 12)
        drawn = np.column_stack([z_f, z_s]) @ low.T
        fixture, screen = drawn[:, :6], drawn[:, 6:]
    # The fixture moved by a small motion (fixture_to_camera.compose(small_motion(...))), on arrays.
    d_rot = _rotation_batch(1e-3 * fixture[:, :3])
    out = {"camera_z": np.column_stack([z_k, z_d]),
           "corner_noise_px": (z_c @ np.asarray(corner_factor).T).reshape(draws, *corners.shape),
           "matrix": k, "distortion": cam.distortion[None] + z_d * np.asarray(inputs.camera_distortion)[None],
           "fixture_rotation": fix0.rotation @ d_rot,
           "fixture_translation": (fix0.rotation @ (1e-3 * fixture[:, 3:]).T).T + fix0.translation,
           "distance_m": 1e-3 * inputs.distance_mm * z_r[:, 0]}
    if screen is not None:
        out["screen_motion"] = screen
    return out


#: The camera inputs of :func:`pose_draws`' ``camera_z`` columns, as the budget names them.
CAMERA_DRAWN = ("camera fx", "camera fy", "camera cx", "camera cy", "camera k1", "camera k2", "camera p1",
                "camera p2", "camera k3")


def pose_monte_carlo(reduction, *, geometry, design, inputs: InputUncertainties, draws: int = POSE_DRAWS,
                     seed: int = 12, ray_paths: dict | None = None, frames: dict | None = None,
                     screen_paths: dict | None = None) -> dict:
    """Mean squared error of the corner-pose figures (boresight, placement) when the inputs the corner
    pose depends on are drawn from their distributions (GUM Supplement 1): the corners' noise from their
    covariance (``corner_cov_px2``), the camera's focal lengths, principal point and distortion, the
    fixture pose and the measured distance's error from ``[uncertainty]``.

    Why not the finite differences of :func:`sensitivities`: the pose of a nearly frontal facet from its
    corners is far from linear at the scale of these uncertainties (on the 400 x 300 twin its rotation
    about y moves by -3.2 mrad for f_x - f_y = +1 px and +2.5 mrad for -1 px, and the slope itself shifts
    with the corners' own noise), so a sensitivity taken at one point, once per geometry, made U of the
    rotation about y cover 91 % of the errors instead of 95 %. All draws' 4-point poses are solved at once
    (:func:`solve_poses_batch`: 34-36 ms of CPU per facet as numpy arrays against 95-100 ms for OpenCV's
    solvePnP one at a time, on a quiet machine; compiled since 2026-12-06, the whole Monte Carlo 2 ms for
    OpenCSP's fixed capture against 6-10 ms), so it is drawn for every capture, with its own corner covariance, at the
    expected pose (the facet where the fixture's nominal pose puts it; GUM 5.1.3). Not at the capture's found
    corners: their own noise moves that point towards the near-frontal pose's two-fold ambiguity, where
    the pose turns fastest, and U then scattered from 3 to 13 mrad between captures of the same facet and
    covered 88-91 %. A fixed seed keeps the result the same for the same capture, and moment-matched draws
    make its linear part exact; the curved, heavy-tailed rest keeps a sampling error of 5-7 % of U with 200
    draws, common to every capture through the seed (docs/uncertainty.md).

    Each draw is the measurement itself: the facet at the expected pose in the drawn fixture, photographed
    by the drawn camera (its corners projected through the drawn intrinsics and distortion, plus the drawn
    corner noise), its distance read with the drawn error; the analysis's corner pose from those corners
    with the nominal camera, range-fixed with that distance, and its placement in the nominal fixture;
    the error is against the draw's truth. (Until 2026-12-02 the draws perturbed the analysis instead:
    nominal corners solved with the drawn camera. To first order that is the same spread, but the pose's
    curvature in f_x - f_y then has the opposite sign, so its offset of the rotation about y, -0.6 mrad
    on the twin, came out as +0.6 mrad; its U changed by 1-3 %.) Drawing the facet's placement in the
    fixture as well (uniform +-1 mm, +-1 mrad on the twin) changes these U by less than 0.5 %: the pose's
    nonlinearity is in the camera and the corners, not in where within that tolerance the facet sits.

    The boresight is the rotation from the corner pose to the frame the measured surface defines, which
    does not depend on the corner pose: its error is the corner pose's rotation error (about the facet's
    x and y), with the opposite sign, and the turn of the surface's frame the drawn camera gives every
    pixel's ray. *ray_paths* ``{boresight path: (9,) coefficients}`` is that turn per standard deviation of
    each camera input (:data:`CAMERA_DRAWN`; the camera rows of the optical tilt's finite differences,
    :func:`~.budget.boresight_ray_coefficients`), carried draw by draw with the pose the same camera gives:
    the two are not independent. A principal point off by 1 px turns a heliostat station's corner pose by
    0.75 mrad (its facet's corners are not all at one depth, so the shift is partly read as a turn) and its
    rays by 1.37 mrad the same way (quarter-resolution camera, f 750 px): the boresight moves by their
    difference, 0.6 mrad. Added in quadrature, the two made its U 2.6 times its errors' spread there.

    *screen_paths* ``{path: (6,) coefficients}``: each figure's change per mrad and mm of the screen's pose
    (:data:`~.inputs.POSE_ROWS`' first six; the linear parts of their finite differences,
    :func:`~.budget.screen_pose_coefficients`). Where *inputs* holds the pose record's joint covariance of the
    screen's and the fixture's poses, the screen's error is drawn with the fixture's (:func:`pose_draws`) and
    its turn of the figures added draw by draw, as the rays' above: the pose calibration finds the fixture
    through the mirror seated in it, seen through the screen pose it finds, so the two are not independent.
    The result then names the budget groups it stands for, :data:`SCREEN_GROUPS` included (``"groups"``).

    *frames*, a dict, receives the draws as errors of the facet's frame, for the shape figures' Monte Carlo
    (:func:`~.shape_pose.shape_monte_carlo`): ``rotation`` (n, 3, 3) and ``translation`` (n, 3, metres) of
    every input drawn, the estimated frame being the true one moved by them (facet axes), the camera's
    draws ``camera_z`` (n, 9), and ``corners``: the same two of the corners' noise alone.

    Returns
    -------
    dict
        ``{path: (mean square error, mean square error from the corners alone)}`` for :data:`POSE_PATHS`,
        in the figures' units squared, and ``"groups"``: the budget groups the draws stand for
        (:data:`POSE_GROUPS`, with :data:`SCREEN_GROUPS` where the screen was drawn); {} when the corners have
        no covariance.
    """
    if not getattr(design, "outline_known", True):
        return {}           # a mirror of unknown outline reports none of the corner pose's figures
    pose0 = reduction.pose
    cov = getattr(pose0, "corner_cov_px2", None)
    n_corners = np.asarray(pose0.corners_px, float).size
    if cov is None or np.shape(cov) != (n_corners, n_corners) or not np.all(np.isfinite(cov)):
        return {}
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    m = v * np.sqrt(np.clip(w, 0.0, None))[None, :]
    # The arithmetic of pose.solve_corner_pose, pose.fix_range and pose.placement on arrays, all draws at once.
    corners_3d = np.asarray(design.corners_3d(), np.float64)
    measure = np.array([*design.measure_point_m, float(design.z(*design.measure_point_m))])
    cx, cy = (float(c) for c in design.centroid_m)
    p_mid = np.array([cx, cy, float(design.z(cx, cy))])
    centre = np.asarray(reduction.rays.screen_centre_cam_m, np.float64)
    fix0 = geometry.fixture_to_camera
    cam = geometry.camera

    def nominal(x, n):
        return np.repeat(np.asarray(x, np.float64)[None], n, axis=0)

    def measured(true_r, true_t, k, dist, noise, distance_error):
        """The analysis's corner pose (range-fixed, NaN where it has none) of a facet at (true_r, true_t)
        photographed by camera (k, dist) with corner noise, its distance read with distance_error."""
        n = true_r.shape[0]
        corner_px = _project_batch(true_r, true_t, corners_3d, k, dist) + noise
        distance = np.linalg.norm(true_r @ measure + true_t - centre, axis=1) + distance_error
        r, t, _ = solve_poses_batch(corner_px, corners_3d, nominal(cam.matrix, n), nominal(cam.distortion, n),
                                    fix0.rotation, fix0.translation)
        q = r @ measure + t                         # range fixed along the line of sight to the measure point
        u = q / np.linalg.norm(q, axis=1)[:, None]
        wv = centre - q
        uw = np.sum(u * wv, axis=1)
        disc = uw * uw - np.sum(wv * wv, axis=1) + distance * distance
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        mu = np.where(np.abs(uw - root) <= np.abs(uw + root), uw - root, uw + root)
        return r, t + mu[:, None] * u

    def errors(true_r, est):
        r, t = est
        d = np.swapaxes(true_r, -1, -2) @ r         # the pose's rotation error, facet axes
        rf = fix0.rotation.T @ r                    # facet -> nominal fixture: the placement reported
        tf = (fix0.rotation.T @ (r @ p_mid + t - fix0.translation).T).T - p_mid
        # The facet sits at the expected pose in the (drawn) fixture: its true placement is zero.
        return np.column_stack([-1000.0 * d[:, 2, 1], -1000.0 * d[:, 0, 2], 1000.0 * tf,
                                1000.0 * np.arctan2(rf[:, 2, 1], rf[:, 2, 2]),
                                -1000.0 * np.arcsin(np.clip(rf[:, 2, 0], -1.0, 1.0)),
                                1000.0 * np.arctan2(rf[:, 1, 0], rf[:, 0, 0])])

    dr = pose_draws(np.zeros((n_corners // 2, 2)), m, geometry, inputs, draws, seed,
                    with_screen=screen_paths is not None)
    # In one batch of poses: all inputs drawn, then the corners alone.
    true_r = np.concatenate([dr["fixture_rotation"], nominal(fix0.rotation, draws)])
    true_t = np.concatenate([dr["fixture_translation"], nominal(fix0.translation, draws)])
    est = measured(true_r, true_t, np.concatenate([dr["matrix"], nominal(cam.matrix, draws)]),
                   np.concatenate([dr["distortion"], nominal(cam.distortion, draws)]),
                   np.concatenate([dr["corner_noise_px"], dr["corner_noise_px"]]),
                   np.concatenate([dr["distance_m"], np.zeros(draws)]))
    err = errors(true_r, est)
    d_all, d_corners = err[:draws], err[draws:]
    for j, p in enumerate(POSE_PATHS):
        coef = None if ray_paths is None else ray_paths.get(p)
        if coef is not None:
            # the drawn camera's turn of the rays, on the analysis's side (a true input of +z u is an
            # analysis input of -z u): the column's sign is the pose's rotation error's opposite
            d_all[:, j] = d_all[:, j] - dr["camera_z"] @ np.asarray(coef, float)
        coef = None if "screen_motion" not in dr else screen_paths.get(p)
        if coef is not None:
            # the true screen moved by +w is the analysis's screen moved by -w, as the fixture's draws
            d_all[:, j] = d_all[:, j] - dr["screen_motion"] @ np.nan_to_num(np.asarray(coef, float))
    # A draw whose pose cannot be solved says nothing about the others.
    good = np.all(np.isfinite(d_all), axis=1) & np.all(np.isfinite(d_corners), axis=1)
    n = int(good.sum())
    if n < draws // 2:
        return {}
    if frames is not None:
        # the estimated frame is the true one moved by (R, t): R = R_true^T R_est, t = R_true^T (t_est - t_true)
        rt = np.swapaxes(true_r, 1, 2)
        rot, trans = rt @ est[0], (rt @ (est[1] - true_t)[..., None])[..., 0]
        frames.update({"rotation": rot[:draws][good], "translation": trans[:draws][good],
                       "camera_z": dr["camera_z"][good],
                       "corners": {"rotation": rot[draws:][good], "translation": trans[draws:][good]}})
    sq_all = np.mean(d_all[good] ** 2, axis=0)
    sq_corners = np.mean(d_corners[good] ** 2, axis=0)
    groups = POSE_GROUPS + (SCREEN_GROUPS if "screen_motion" in dr else ())
    return {"groups": groups, **{p: (float(sq_all[j]), float(sq_corners[j])) for j, p in enumerate(POSE_PATHS)}}
