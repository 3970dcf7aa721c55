"""The shape figures' part from the corner pose, by Monte Carlo over its draws: the capture's residual fields
and figures moved by each draw's error of the corner pose, through the pipeline's own response to it.

The corner pose places the frame the shape is measured in; the electronic boresight then turns that frame
until the fitted parabola's normal at the alignment point is the design's. A nearly frontal facet's four
corners leave the pose's rotation uncertain by several mrad and, with point-sampled edges on a
quarter-resolution camera, by tens of mrad and its place by tens of mm; the boresight takes out the tilt,
not the rest: the surface is reconstructed along each pixel's ray at the depth the misplaced frame gives
it, so the slopes change across the facet, and on an off-axis facet (a gore) the frame's error changes
which parabola fits it best. That reaches the twist, the curvatures and above all the slope RMS against
the design, which any such change raises whatever its sign: far from linear at that scale (on a
population gore the design's slope RMS y was 0.061 mrad high for a pose 70 mrad and 96 mm off, 0.001
with the twin's true pose, against a U of 0.009 from the finite differences at one corner standard
deviation).

The pipeline's response to the frame is smooth: the shape stage rerun with the corner pose moved by
+-2 mrad about, or +-2 mm along, each facet axis gives per parameter the change of every point's slope
residual (against the design and the parabola) and of the fitted figures (:func:`pose_fields`); with
those, the residual field with the true pose taken out predicted that gore's design slope RMS y to
0.004 mrad (0.809 against the truth's 0.805, measured 0.866). Every draw of the corners' noise
(:func:`~.corner_pose.pose_monte_carlo`'s own draws, as frame errors) then moves the capture's fields
and figures by the linear fields (the RMS recomputed from the moved field, exactly quadratic) and the
figures by their linear and quadratic parts: :func:`shape_monte_carlo`. Its mean square change stands for
the budget's corner rows of :data:`SHAPE_PATHS`.

The camera's draws are carried the same way, draw by draw with the pose the same camera gives: a wrong camera
moves the corner pose and every pixel's ray together, and the two partly cancel in the design residual (a Monte
Carlo of the pose alone, tried before this one, stated the design's slope RMS x four times its errors' spread).
:func:`pose_fields` also takes each camera input's field with the corner pose held (the rays alone), and
:func:`shape_monte_carlo` moves the fields by the draw's frame error and its camera together, so the budget's
camera rows (:data:`~.budget.SHAPE_GROUPS`) are the Monte Carlo's too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ...errors import StationError
from ..boresight import Motion, ShapeSolution
from ..camera import moved_rays
from ..pipeline import (NOT_FITTED_BY_A_PLANE, default_screen, parabola_figures, pose_from_corners,
                        quadratic_residuals, screen_points_and_rays, shape_and_boresight)
from .corner_pose import CAMERA_DRAWN, rotation_vectors
from .inputs import RMS_AXES, get_path, small_motion
from .systematic import decimated

#: The figures whose corner rows this Monte Carlo replaces.
SHAPE_PATHS: tuple[tuple, ...] = (
    ("focal_length_x_m",), ("focal_length_y_m",), ("curvature_x_per_m",), ("curvature_y_per_m",),
    ("twist_mrad_per_m",), ("twist_e1_mrad_per_m",), ("twist_e2_mrad_per_m",),
    ("principal_focal_lengths_m", 0), ("principal_focal_lengths_m", 1), ("principal_curvatures_per_m", 0),
    ("principal_curvatures_per_m", 1), *[("slope_rms_mrad", m, a) for m in ("design", "parabola") for a in RMS_AXES])
#: The curvatures' difference kappa_x - kappa_y (1/m), carried beside the figures for the axis angle's bound.
DIFFERENCE_PATH = ("curvature_difference_per_m",)
#: Slope-RMS models whose residual fields are moved (the others' figures by their own responses).
FIELD_MODELS = ("design", "parabola")
#: Points of the capture the reruns use (every n-th valid pixel, n the nearest whole step): the fields are smooth
#: over the facet. 2000 rather than 4000 (2026-12-06): OpenCSP's fixed capture's fields from every second of its
#: 3,537 dots and its fringe capture's from every 178th pixel instead of every 89th moved no U by more than
#: 0.6 %, and the reruns' CPU by about 40 % (25 ms per capture).
FIELD_POINTS = 2000
#: The corner pose's moves the fields are taken from: about each facet axis (mrad), along it (mm).
FIELD_STEP = (2.0, 2.0)
#: Where each rerun's iteration stops (:func:`~..boresight.close_on_all_points`): the relative change of kappa
#: between two steps and of the surface's height at the measure point (metres), ten times the analysis's own
#: (1e-6, 1e-8). A field is a difference over a step that moves the figures by far more than that, and the
#: reruns need not reach the reported figure's last digits: on OpenCSP's fixed and fringe captures
#: (2026-12-07) no U moved by more than 0.03 %, and the iteration took 45 steps instead of 58 (fixed: 44-47
#: ms of CPU instead of 61-70). A hundred times the analysis's (1e-4, 1e-6) moved the fringe's twist U by 2.6 %.
FIELD_TOLERANCE = (1e-5, 1e-7)


@dataclasses.dataclass
class PoseFields:
    """The pipeline's response to the corner pose and to the camera's rays at one capture (:func:`pose_fields`).

    Attributes
    ----------
    residuals : dict
        ``{model: (2, m) array}`` the capture's slope residuals (x, y; mrad) at the decimated points.
    fields : dict
        ``{model: (6 + 9, 2, m) array}`` their change per mrad of turn about, then per mm along, the facet's
        x, y, z (the corner pose moved), then per standard deviation of each camera input of
        :data:`~.corner_pose.CAMERA_DRAWN` with the corner pose held (the rays alone).
    linear, curvature : dict
        ``{path: (15,) array}`` each figure's change per unit of each of those (c) and its curvature part
        ``(f(+h) + f(-h)) / 2 - f(0)`` per unit squared.
    """

    residuals: dict
    fields: dict
    linear: dict
    curvature: dict


def pose_fields(reduction, *, fringes, geometry, design, measured_distance_m: float, settings, inputs, screen=None,
                max_points: int = FIELD_POINTS, step: tuple = FIELD_STEP) -> PoseFields | None:
    """The shape stage rerun on a decimated copy of *reduction* with its corner pose moved by +-*step* about
    and along each facet axis (the facet frame composed with the move: the pose Monte Carlo's frame errors),
    and with each camera input of *inputs* moved by +1 standard deviation (a forward difference; the moved
    camera's rays to first order, :func:`~..camera.moved_rays`), the corner pose held: the residual fields' and
    figures' response. 21 reruns of the shape stage alone on about *max_points* points, each started where its
    frame converges (:func:`carried_start`, :func:`mirrored_start`): on OpenCSP's fixed capture (all its 3,537
    points, 2026-12-06) 59 steps of the boresight's iteration and 70-76 ms of CPU, against 89 steps and
    180-205 ms for full reruns from the capture's own solution, every U within 0.03 %; on every second point
    (:data:`FIELD_POINTS`) 27-40 ms; each iteration stopped at :data:`FIELD_TOLERANCE`, 45 steps instead of 58
    and a quarter less CPU. None when a rerun fails."""

    if getattr(reduction, "shape", None) is None or reduction.shape.points_m is None:
        return None
    settings = dataclasses.replace(settings, max_range_shift_m=float("inf"), max_corner_rms_px=float("inf"),
                                   robust_fit=False)
    paths = [p for p in SHAPE_PATHS if p[0] != "slope_rms_mrad" or p[1] not in FIELD_MODELS]
    u_cam = np.array([inputs.camera_focal_px] * 2 + [inputs.camera_principal_px] * 2 + list(inputs.camera_distortion))

    def response(rays, pose, start):
        # the shape stage alone, from *start*: the residuals of FIELD_MODELS and the parabola's figures are all
        # the fields read (no cubic, no report_figures: a third of a full rerun's cost)
        shape = shape_and_boresight(rays, pose, design, measured_distance_m, settings, start=start,
                                    kappa_tolerance=FIELD_TOLERANCE[0], height_tolerance_m=FIELD_TOLERANCE[1])
        figures = (parabola_figures(shape.fit) if settings.surface == "parabolic"
                   else dict.fromkeys(NOT_FITTED_BY_A_PLANE))
        return shape.solution, quadratic_residuals(shape, design), figures

    try:
        screen = screen if screen is not None else default_screen(geometry)
        # the decimated capture from its rays on (pipeline.rerun's stages from "rays", the shape stage lean)
        dec = decimated(reduction, max_points, nearest=True)
        rays0 = screen_points_and_rays(dec.region, dec.phases, geometry.camera, screen,
                                       min_valid_px=settings.min_valid_px)
        pose0 = pose_from_corners(reduction.pose.corners_px, dec.region, rays0, geometry, design, measured_distance_m,
                                  settings, agreement=reduction.pose.outline_agreement)
        sol0, res0, fig0 = response(rays0, pose0, reduction.shape.solution)
        n = 6 + len(CAMERA_DRAWN)
        fields = {m: np.zeros((n,) + res0[m].shape) for m in FIELD_MODELS}
        linear = {p: np.zeros(n) for p in paths}
        curvature = {p: np.zeros(n) for p in paths}
        camera_rays = moved_rays(geometry.camera, rays0.rays, u_cam)

        def moved(k, sign, plus=None):
            if k < 6:
                v = np.zeros(6)
                v[k] = sign * (step[0] if k < 3 else step[1])
                move = small_motion(rotation_mrad=v[:3], translation_mm=v[3:])
                pose = dataclasses.replace(pose0, facet_to_camera=pose0.facet_to_camera.compose(move))
                return response(rays0, pose, carried_start(sol0, move) if plus is None else mirrored_start(sol0, plus))
            # the camera moved by +1 standard deviation of input k - 6, its rays with it, the corner pose held
            return response(dataclasses.replace(rays0, rays=camera_rays[k - 6]), pose0, sol0)

        for k in range(n):
            h = (step[0] if k < 3 else step[1]) if k < 6 else 1.0
            if k >= 6 and u_cam[k - 6] <= 0:
                continue
            # The camera inputs' fields by forward differences at +1 standard deviation (their curvature part
            # 0), not central ones: a camera's standard deviation moves the rays far less than the corner pose's
            # step, and the response is linear there. On OpenCSP's fixed capture (2026-12-06) every U within
            # 0.3 % of the central differences' (f x 2.4245 -> 2.4189 m), 7 of its 28 reruns left out.
            one_sided = k >= 6
            plus = moved(k, 1.0)
            minus = (sol0, res0, fig0) if one_sided else moved(k, -1.0, plus[0])
            span = h if one_sided else 2.0 * h
            for m in FIELD_MODELS:
                fields[m][k] = (np.asarray(plus[1][m]) - np.asarray(minus[1][m])) / span
            for p in paths:
                fp, fm = get_path(plus[2], p), get_path(minus[2], p)
                if None in (fp, fm, get_path(fig0, p)):
                    linear[p][k] = curvature[p][k] = np.nan
                    continue
                linear[p][k] = (fp - fm) / span
                curvature[p][k] = 0.0 if one_sided else (0.5 * (fp + fm) - get_path(fig0, p)) / (h * h)
    except (StationError, ValueError, np.linalg.LinAlgError):
        return None
    return PoseFields(res0, fields, linear, curvature)


def carried_start(solution: ShapeSolution, move) -> ShapeSolution:
    """Where the shape stage's iteration starts for the facet frame moved by *move* (a Pose composed after the
    corner pose's facet-to-camera): *solution*'s boresight motion carried along, so that the boresighted frame
    stays where *solution* left it as far as the motion can (its turn about x and y and its shift along z; the
    rest of *move* is what the rerun measures). The iteration's own convergence tests decide where it ends: a
    turn about a facet axis through the pivot converges at once (the boresight takes it out, the fields are
    0), where from *solution*'s motion it took five steps."""
    carried = solution.motion.as_pose().compose(move)
    r = carried.rotation
    alpha, beta = float(np.arctan2(r[2, 1], r[2, 2])), -float(np.arcsin(np.clip(r[2, 0], -1.0, 1.0)))
    pivot = solution.motion.pivot_m
    turned = Motion(alpha, beta, 0.0, pivot).as_pose()
    t_z = float(carried.translation[2] - turned.translation[2])
    return dataclasses.replace(solution, motion=Motion(alpha, beta, t_z, pivot))


def mirrored_start(solution: ShapeSolution, plus: ShapeSolution) -> ShapeSolution:
    """Where the shape stage's iteration starts for the move opposite to the one that converged at *plus*:
    *solution* (the unmoved capture's) moved back by as much as *plus* moved it (its boresight motion, model
    and surface height), the linear response the central differences assume."""
    m0, m1 = solution.motion, plus.motion
    return dataclasses.replace(
        solution, motion=Motion(2.0 * m0.alpha_rad - m1.alpha_rad, 2.0 * m0.beta_rad - m1.beta_rad,
                                2.0 * m0.t_z_m - m1.t_z_m, m0.pivot_m),
        coefficients=2.0 * np.asarray(solution.coefficients, float) - np.asarray(plus.coefficients, float),
        surface_height_m=2.0 * solution.surface_height_m - plus.surface_height_m)


def beyond_linear(frames: dict, step: tuple = FIELD_STEP) -> bool:
    """Whether the corner pose's draws (:func:`~.corner_pose.pose_monte_carlo`'s *frames*) move the facet's
    frame beyond the fields' own step: an RMS turn about the facet's x or y above ``step[0]`` mrad, or an
    RMS shift along any axis above ``step[1]`` mm. Within it the pipeline's response to the frame is the
    linear one the budget's finite differences (at one standard deviation of the corners and the camera)
    carry already, and :func:`shape_monte_carlo` adds its cost and nothing else.

    Measured (2026-12-06): on seed 0's first eight population stations (400 x 300 cameras) the draws moved
    the dish's frame by 3-6 mrad and 3 mm RMS, and the Monte Carlo changed none of its U in the third
    digit; the gore's by 10-23 mrad and 10-30 mm, and its design slope RMS y's U went from 0.014 to 0.048
    mrad (error 0.061). On the shipped dish station (1600 x 1200) they move it by 0.6 / 1.1 mrad and
    0.8 mm, the Monte Carlo's mean square change of the design's slope RMS y is 3e-12 mrad^2, and it cost
    0.32 s of CPU per facet (0.60 against 0.92 s, ``benchmarks/analysis.py``): skipped there."""
    rot = frames.get("rotation")
    if rot is None or len(rot) == 0:
        return False
    turn = 1e3 * np.sqrt(np.mean(rotation_vectors(np.asarray(rot, np.float64))[:, :2] ** 2, axis=0))
    shift = 1e3 * np.sqrt(np.mean(np.asarray(frames["translation"], np.float64) ** 2, axis=0))
    return bool(np.any(turn > step[0]) or np.any(shift > step[1]))


def _draws(frames: dict) -> np.ndarray:
    """The draws as the fields' parameters (n, 15): the frame's turn (mrad) about and shift (mm) along the
    facet's axes, then the analysis's camera error in standard deviations (a true input of +z is an
    analysis input of -z)."""
    rot = np.asarray(frames["rotation"], np.float64)
    d = np.column_stack([1e3 * rotation_vectors(rot), 1e3 * np.asarray(frames["translation"], np.float64)])
    z = frames.get("camera_z")
    z = np.zeros((len(d), 9)) if z is None else -np.asarray(z, np.float64)
    return np.column_stack([d, z])


def displaced_gradient_factor(change: np.ndarray, linear: np.ndarray, h: np.ndarray, second: np.ndarray) -> float:
    """The factor (at most 1) that takes out of a mean square residual's Monte Carlo what the measured frame's
    own error adds to it: the draws are taken about the measured frame, which the corner pose's error has moved
    from the true one by a draw of the same spread.

    The mean square residual is exactly quadratic in the draw d: ms(d) = ms(0) + 2 g.d + d' H d (*change* the
    draws' ms(d) - ms(0), *linear* their 2 g.d, *h* H, *second* the draws' second moments S). Measured at the
    error d_t from the truth, the gradient is g_t + H d_t: its linear part's mean square 4 E[(g.d)^2] is too
    large by 4 tr(H S H S) on average, which the true error's mean square (4 g_t' S g_t + 2 tr((HS)^2) +
    tr(HS)^2) does not hold. Without a true gradient (the design residual x of a round facet, whose slope
    RMS any frame error raises) the Monte Carlo stated 7/3 of the error's mean square (RMS of error / (U / 2)
    about 0.65; 0.38-0.55 on the population's heliostat, issue 47). The factor is the mean square of *change*
    with the linear part's mean square less that excess (never below 0), over its own; the slope RMS's mean
    square change is scaled by it (its square root's change is the mean square's over 2 RMS, to first order)."""
    total = float(np.mean(change ** 2))
    if not total > 0:
        return 1.0
    lin_ms = float(np.mean(linear ** 2))
    excess = 4.0 * float(np.trace(h @ second @ h @ second))
    return max(total - lin_ms + max(lin_ms - excess, 0.0), 0.0) / total


def shape_monte_carlo(fields: PoseFields | None, frames: dict) -> dict:
    """Mean square change of the shape figures (:data:`SHAPE_PATHS`) over the draws of the corner pose's Monte
    Carlo: each draw's error of the frame and its camera (through the rays, the pose held) move the
    capture's residual fields, whose RMS is taken again, and its figures by their linear and quadratic parts.

    Parameters
    ----------
    fields : PoseFields
        The capture's response (:func:`pose_fields`).
    frames : dict
        :func:`~.corner_pose.pose_monte_carlo`'s *frames*: ``rotation`` (n, 3, 3) and ``translation`` (n, 3)
        of each draw's frame error (radians, metres), ``camera_z`` (n, 9), and ``corners`` (the corners'
        noise alone: its ``rotation`` and ``translation``).

    Returns
    -------
    dict
        ``{path: (mean square change, mean square change from the corners alone)}`` in the figures' units
        squared; {} without fields or draws.
    """
    if fields is None or frames.get("rotation") is None or len(frames["rotation"]) == 0:
        return {}
    runs = [_draws(frames), _draws(frames["corners"])]
    out: dict = {}
    for m in FIELD_MODELS:
        r0, f = fields.residuals[m], fields.fields[m]
        n = r0.shape[1]
        ms0 = np.mean(r0 ** 2, axis=1)                                      # (2,)
        g = np.einsum("kam,am->ka", f, r0) / n                              # (k, 2): <r0, F_k>
        h = np.einsum("kam,lam->kla", f, f) / n                             # (k, k, 2): <F_k, F_l>
        for a in RMS_AXES:
            out[("slope_rms_mrad", m, a)] = []
        for d in runs:
            lin = 2.0 * d @ g                                               # (n, 2)
            ms = np.clip(ms0[None] + lin + np.einsum("dk,kla,dl->da", d, h, d), 0.0, None)
            second = d.T @ d / len(d)                                       # the draws' second moments
            for a, v, base, lin_a, h_a in (
                    ("x", ms[:, 0], ms0[0], lin[:, 0], h[:, :, 0]), ("y", ms[:, 1], ms0[1], lin[:, 1], h[:, :, 1]),
                    ("magnitude", ms.sum(axis=1), ms0.sum(), lin.sum(axis=1), h.sum(axis=2))):
                change = float(np.mean((np.sqrt(v) - np.sqrt(base)) ** 2))
                out[("slope_rms_mrad", m, a)].append(change * displaced_gradient_factor(v - base, lin_a, h_a, second))
    responses = dict(fields.linear)
    curvatures = dict(fields.curvature)
    kx, ky = ("curvature_x_per_m",), ("curvature_y_per_m",)
    if kx in responses and ky in responses:
        # their difference, which fixes the axis angle: a common change (a camera's focal length, the range)
        # moves both curvatures alike and leaves it
        responses[DIFFERENCE_PATH] = responses[kx] - responses[ky]
        curvatures[DIFFERENCE_PATH] = curvatures[kx] - curvatures[ky]
    for p, c in responses.items():
        q = curvatures[p]
        if not (np.all(np.isfinite(c)) and np.all(np.isfinite(q))):
            continue
        out[p] = [float(np.mean((d @ c + (d * d) @ q) ** 2)) for d in runs]
    return {p: tuple(v) for p, v in out.items()}
