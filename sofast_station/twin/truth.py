"""Ground truth: the conventions' fit definitions applied to the exact true surface at the kept pixels.

The exact surface points and normals at the kept pixels start in the true facet frame, so x, y and the
rotation about z are the facet's true placement (docs/conventions.md#ground-truth). They are then put
in the frame the electronic boresight defines for the parabola fitted to those exact normals: a rotation
R = R_y(beta) R_x(alpha) about the alignment point P_a = (x_a, y_a, z_design(x_a, y_a)) chosen so that the
fitted parabola's slopes at (x_a, y_a) are the design's (:func:`boresight_frame`). The boresight's
translation along z and the model's constant change neither slopes nor x, y, so they are left out.

Everything here is written from the definitions of ``docs/conventions.md``; nothing is shared with
``sofast_station.measure``.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import AnalysisError
from ..facet import FacetDesign
from .station import TwinStation
from .trace import rotation_zyx

#: Focal power below which a focal length is reported as infinite (None), 1/m.
INFINITE_FOCUS_KAPPA_PER_M = 4e-9

#: The boresight iteration stops when both angle updates are below this, radians.
BORESIGHT_TOLERANCE_RAD = 1e-10

#: Boresight iterations before giving up.
BORESIGHT_MAX_ITERATIONS = 50

#: Exponents (i, j) of the higher-order model's terms x^i y^j, 1 <= i + j <= 3 (9 terms).
HIGHER_ORDER_TERMS = tuple((i, n - i) for n in (1, 2, 3) for i in range(n, -1, -1))


def exact_samples(station: TwinStation, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact surface points and unit normals at the kept pixels, in the true facet frame.

    Parameters
    ----------
    station : TwinStation
    kept : (H, W) bool array
        Pixels the pipeline kept. Pixels that do not see the facet (coverage 0) carry no truth and are
        skipped.

    Returns
    -------
    points_facet_m : (n, 3) array
        True surface points, metres.
    normals_facet : (n, 3) array
        Exact unit normals there, n_z > 0 (n proportional to (-s_x, -s_y, 1)).
    """
    kept = np.asarray(kept)
    shape = station.geometry.camera.shape
    if kept.shape != shape or kept.dtype != bool:
        raise AnalysisError(f"kept must be a bool array of the camera's shape {shape}, got {kept.dtype} {kept.shape}")
    use = kept & (station.coverage > 0)
    points = np.array(station.surface_point_facet_m[use], dtype=np.float64)
    slopes = station.slope_true[use]
    normals = np.column_stack([-slopes[:, 0], -slopes[:, 1], np.ones(len(slopes))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals


def rotate_about_pivot(points_m: np.ndarray, normals: np.ndarray, pivot_m: np.ndarray,
                       alpha_rad: float, beta_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Rotate samples by R = R_y(beta) R_x(alpha) about *pivot_m*; return their (x, y) and slopes.

    ``X' = R (X - P) + P``, ``n' = R n``, ``s' = (-n'_x / n'_z, -n'_y / n'_z)``.

    Parameters
    ----------
    points_m : (n, 3) array
        Surface points, metres.
    normals : (n, 3) array
        Unit normals, n_z > 0.
    pivot_m : (3,) array
        Rotation centre P, metres.
    alpha_rad, beta_rad : float
        Rotation angles about x and y, radians.

    Returns
    -------
    points_xy_m : (n, 2) array
        (x, y) of the rotated points, metres.
    slopes : (n, 2) array
        (s_x, s_y) of the rotated normals.
    """
    r = rotation_zyx(alpha_rad, beta_rad, 0.0)          # R_z(0) R_y(beta) R_x(alpha)
    xy = (points_m - pivot_m) @ r[:2].T + pivot_m[:2]
    n = normals @ r.T
    return xy, -n[:, :2] / n[:, 2:3]


def boresight_frame(points_m: np.ndarray, normals: np.ndarray, design: FacetDesign) -> dict:
    """The electronic boresight applied to exact samples: rotate until the fitted parabola meets the design.

    Finds (alpha, beta) such that, after :func:`rotate_about_pivot` about
    P_a = (x_a, y_a, z_design(x_a, y_a)), the assembled fitted parabola's slopes at (x_a, y_a) equal the
    design's (x_a / 2f, y_a / 2f). Rotating by R_y(beta) lowers atan(s_x) by about beta and R_x(alpha)
    raises atan(s_y) by about alpha, so the iteration is ::

        beta  += atan(s_fit,x(a)) - atan(s_design,x(a))
        alpha -= atan(s_fit,y(a)) - atan(s_design,y(a))

    until both updates are below 1e-10 rad. The returned frame is the one at the returned angles (the last,
    sub-tolerance update is not applied), so the condition holds there to 1e-10 rad.

    Parameters
    ----------
    points_m : (n, 3) array
        Exact surface points in the starting (true facet) frame, metres.
    normals : (n, 3) array
        Exact unit normals there.
    design : FacetDesign

    Returns
    -------
    dict
        ``alpha_rad``, ``beta_rad``, ``xy_m`` ((n, 2) points in the boresight frame), ``slopes``
        ((n, 2) exact slopes there), ``parabola`` (the fit there, see :func:`fit_parabola`) and
        ``iterations``.

    Raises
    ------
    RuntimeError
        If the iteration has not converged after 50 steps.
    """
    x_a, y_a = (float(c) for c in design.alignment_point_m)
    pivot_m = np.array([x_a, y_a, float(design.z(x_a, y_a))])
    f = design.focal_length_m
    design_angle_x, design_angle_y = math.atan(x_a / (2 * f)), math.atan(y_a / (2 * f))
    alpha = beta = 0.0
    for iteration in range(1, BORESIGHT_MAX_ITERATIONS + 1):
        xy, slopes = rotate_about_pivot(points_m, normals, pivot_m, alpha, beta)
        parabola = fit_parabola(xy, slopes)
        fit_x, fit_y = parabola_slopes(parabola, x_a, y_a)
        d_beta = math.atan(fit_x) - design_angle_x
        d_alpha = -(math.atan(fit_y) - design_angle_y)
        if abs(d_alpha) < BORESIGHT_TOLERANCE_RAD and abs(d_beta) < BORESIGHT_TOLERANCE_RAD:
            return {"alpha_rad": alpha, "beta_rad": beta, "xy_m": xy, "slopes": slopes, "parabola": parabola,
                    "iterations": iteration}
        alpha += d_alpha
        beta += d_beta
    raise RuntimeError(f"ground-truth boresight did not converge in {BORESIGHT_MAX_ITERATIONS} iterations "
                       f"(last updates {d_alpha:.3e}, {d_beta:.3e} rad): the exact slopes are inconsistent "
                       "with a parabola near the design")


def optical_tilt_mrad(placement_mrad, alpha_rad: float, beta_rad: float) -> dict:
    """The boresight frame's tilt in the fixture, mrad: the (rx, ry) of its orientation there.

    Boresight coordinates are X_b = R_b (X_t - P) + P with R_b = R_y(beta) R_x(alpha) (as in
    :func:`rotate_about_pivot`), so the boresight frame's axes are R_b^T in the true facet frame, and
    R_p R_b^T in the fixture, R_p = R_z(rz) R_y(ry) R_x(rx) being the true placement. Its angles are read
    in the placement's own convention: ry = -asin(R[2, 0]), rx = atan2(R[2, 1], R[2, 2]).
    """
    rx, ry, rz = (1e-3 * float(v) for v in placement_mrad)
    r = rotation_zyx(rx, ry, rz) @ rotation_zyx(alpha_rad, beta_rad, 0.0).T
    return {"x": 1e3 * math.atan2(r[2, 1], r[2, 2]), "y": -1e3 * math.asin(max(-1.0, min(1.0, r[2, 0])))}


def fit_parabola(xy_m: np.ndarray, slopes: np.ndarray) -> dict:
    """The parabola fit: ``s_x = 2A x + C + E1 y`` and ``s_y = 2B y + D + E2 x``, separately.

    Definition: docs/conventions.md#twist.

    Returns
    -------
    dict
        ``a``, ``b``, ``c``, ``d``, ``e1``, ``e2`` and ``e`` = (E1 + E2)/2 (1/m for A, B, E; slope units
        for C, D).
    """
    x, y = xy_m[:, 0], xy_m[:, 1]
    ones = np.ones(len(x))
    (two_a, c, e1), *_ = np.linalg.lstsq(np.column_stack([x, ones, y]), slopes[:, 0], rcond=None)
    (two_b, d, e2), *_ = np.linalg.lstsq(np.column_stack([y, ones, x]), slopes[:, 1], rcond=None)
    e1, e2 = float(e1), float(e2)
    return {"a": 0.5 * float(two_a), "b": 0.5 * float(two_b), "c": float(c), "d": float(d),
            "e1": e1, "e2": e2, "e": 0.5 * (e1 + e2)}


def parabola_slopes(p: dict, x, y):
    """Slopes of the assembled parabola: ``(2A x + C + E y, 2B y + D + E x)``."""
    return 2 * p["a"] * x + p["c"] + p["e"] * y, 2 * p["b"] * y + p["d"] + p["e"] * x


def higher_order_slopes(xy_m: np.ndarray, slopes: np.ndarray) -> np.ndarray:
    """Fit the higher-order model to the slopes; return its slopes at the same points.

    Model: ``z = sum c_ij x^i y^j`` over 1 <= i + j <= 3 (9 coefficients; a constant does not matter).
    Both slope equations, dz/dx = s_x and dz/dy = s_y, are stacked with shared coefficients and solved by
    one linear least-squares fit with equal weights. For conditioning the monomials are taken in centred,
    scaled coordinates u = (x - x0)/h_x, v = (y - y0)/h_y: the polynomials of degree <= 3 in (u, v) are
    those in (x, y), so the fitted surface is the same; slopes stay in physical units
    (dz/dx = (dz/du)/h_x).

    Parameters
    ----------
    xy_m : (n, 2) array
        Points, metres.
    slopes : (n, 2) array
        (s_x, s_y) there.

    Returns
    -------
    (n, 2) array
        The fitted model's (dz/dx, dz/dy) at the points.
    """
    centre = 0.5 * (xy_m.min(axis=0) + xy_m.max(axis=0))
    half = 0.5 * (xy_m.max(axis=0) - xy_m.min(axis=0))
    half = np.where(half > 0, half, 1.0)
    u, v = ((xy_m - centre) / half).T
    n = len(u)
    design = np.empty((2 * n, len(HIGHER_ORDER_TERMS)))
    for k, (i, j) in enumerate(HIGHER_ORDER_TERMS):
        design[:n, k] = i * u ** max(i - 1, 0) * v ** j / half[0] if i else 0.0
        design[n:, k] = j * u ** i * v ** max(j - 1, 0) / half[1] if j else 0.0
    coefficients, *_ = np.linalg.lstsq(design, np.concatenate([slopes[:, 0], slopes[:, 1]]), rcond=None)
    model = design @ coefficients
    return np.column_stack([model[:n], model[n:]])


def _focal_length(kappa_per_m: float) -> float | None:
    """Focal length 1/kappa, metres; None (infinite) when |kappa| < 4e-9 /m."""
    return None if abs(kappa_per_m) < INFINITE_FOCUS_KAPPA_PER_M else 1.0 / kappa_per_m


def _residual_rms_mrad(slopes: np.ndarray, model: np.ndarray) -> dict:
    """RMS of angular residuals atan(s) - atan(s_model) per axis and in magnitude, mrad."""
    e = 1e3 * (np.arctan(slopes) - np.arctan(model))
    return {"x": float(np.sqrt(np.mean(e[:, 0] ** 2))), "y": float(np.sqrt(np.mean(e[:, 1] ** 2))),
            "magnitude": float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))}


def ground_truth(station: TwinStation, kept: np.ndarray) -> dict:
    """The reported figures from the exact true slopes at the kept pixels, in the boresight frame.

    Definitions: docs/conventions.md#reported-figures.

    The exact samples (:func:`exact_samples`, true facet frame) are rotated into the frame the electronic
    boresight gives the parabola fitted to them (:func:`boresight_frame`). There the two slope equations
    are fitted separately by linear least squares, ``s_x = 2A x + C + E1 y`` and
    ``s_y = 2B y + D + E2 x``, with E = (E1 + E2)/2; the assembled parabola (slopes ``2A x + C + E y``,
    ``2B y + D + E x``) defines the parabola residuals; the higher-order model is fitted as in
    :func:`higher_order_slopes`; the design's slopes are ``(x, y) / 2f`` at the same points. Residuals are
    angles ``atan(s) - atan(s_model)``, mrad.

    Parameters
    ----------
    station : TwinStation
    kept : (H, W) bool array
        Pixels the pipeline kept (pixels that do not see the facet are skipped).

    Returns
    -------
    dict
        ``focal_length_x_m``, ``focal_length_y_m`` (metres, None if infinite), ``curvature_x_per_m`` (4A),
        ``curvature_y_per_m`` (4B), ``twist_mrad_per_m`` (1000 E), ``twist_e1_mrad_per_m``,
        ``twist_e2_mrad_per_m``, ``principal_focal_lengths_m`` ([f1, f2], from the eigenvalues of
        [[A, E/2], [E/2, B]] in decreasing order, i.e. the shorter first for a concave facet),
        ``principal_curvatures_per_m`` ([4 lambda1, 4 lambda2], the same eigenvalues, larger first),
        ``axis_angle_rad`` (0.5 atan2(E, A - B)), ``coefficients`` ([A, B, C, D, E]),
        ``slope_rms_mrad`` ({"design" | "parabola" | "higher_order": {"x", "y", "magnitude"}}),
        ``boresight_mrad`` ({"x": 1000 alpha, "y": 1000 beta}: the rotation R_y(beta) R_x(alpha) about the
        alignment point from the true facet frame to the boresight frame), ``placement`` (the true
        placement, echoed: {"mm": [dx, dy, dz], "mrad": [rx, ry, rz]}) and ``n_points``.

    Raises
    ------
    AnalysisError
        If fewer than 9 kept pixels see the facet (the higher-order model has 9 coefficients).
    RuntimeError
        If the boresight iteration does not converge.
    """
    points_m, normals = exact_samples(station, kept)
    return truth_from_samples(points_m, normals, station.design, station.facet)


def truth_from_samples(points_m: np.ndarray, normals: np.ndarray, design: FacetDesign, facet) -> dict:
    """:func:`ground_truth` of exact samples: *points_m* (n, 3) and unit *normals* (n, 3) in the true facet
    frame of the true facet *facet* (a :class:`~sofast_station.twin.parameters.TrueFacet`: its placement)."""
    n = points_m.shape[0]
    if n < len(HIGHER_ORDER_TERMS):
        raise AnalysisError(f"ground truth needs at least {len(HIGHER_ORDER_TERMS)} kept pixels on the facet, "
                            f"got {n}")
    frame = boresight_frame(points_m, normals, design)
    xy, slopes, p = frame["xy_m"], frame["slopes"], frame["parabola"]
    x, y = xy[:, 0], xy[:, 1]
    a, b, e = p["a"], p["b"], p["e"]

    parabola = np.column_stack(parabola_slopes(p, x, y))
    f_design = design.focal_length_m
    design = np.column_stack([x / (2 * f_design), y / (2 * f_design)])

    eigenvalues = np.linalg.eigvalsh(np.array([[a, 0.5 * e], [0.5 * e, b]]))[::-1]
    return {
        "focal_length_x_m": _focal_length(4 * a),
        "focal_length_y_m": _focal_length(4 * b),
        "curvature_x_per_m": 4 * a,
        "curvature_y_per_m": 4 * b,
        "twist_mrad_per_m": 1e3 * e,
        "twist_e1_mrad_per_m": 1e3 * p["e1"],
        "twist_e2_mrad_per_m": 1e3 * p["e2"],
        "principal_focal_lengths_m": [_focal_length(4 * float(lam)) for lam in eigenvalues],
        "principal_curvatures_per_m": [4 * float(lam) for lam in eigenvalues],
        "axis_angle_rad": 0.5 * float(np.arctan2(e, a - b)),
        "coefficients": [a, b, p["c"], p["d"], e],
        "slope_rms_mrad": {"design": _residual_rms_mrad(slopes, design),
                           "parabola": _residual_rms_mrad(slopes, parabola),
                           "higher_order": _residual_rms_mrad(slopes, higher_order_slopes(xy, slopes))},
        "boresight_mrad": {"x": 1e3 * frame["alpha_rad"], "y": 1e3 * frame["beta_rad"]},
        "optical_tilt_mrad": optical_tilt_mrad(facet.placement_mrad, frame["alpha_rad"], frame["beta_rad"]),
        "placement": {"mm": list(facet.placement_mm), "mrad": list(facet.placement_mrad)},
        "n_points": int(n),
    }
