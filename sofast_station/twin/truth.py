"""Ground truth: the SPEC's fit definitions applied to the exact true surface at the kept pixels.

Part-1 version: the fit frame is the true facet frame (:func:`truth_frame_samples`); a later version puts
the samples in the boresight frame instead, and nothing else here changes.
"""

from __future__ import annotations

import numpy as np

from ..errors import AnalysisError
from .station import TwinStation

#: Focal power below which a focal length is reported as infinite (None), 1/m.
INFINITE_FOCUS_KAPPA_PER_M = 4e-9


def truth_frame_samples(station: TwinStation, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact surface points and slopes at the kept pixels, in the frame the ground truth is fitted in.

    This is the only place that chooses the frame: here the true facet frame.

    Parameters
    ----------
    station : TwinStation
    kept : (H, W) bool array
        Pixels the pipeline kept. Pixels that do not see the facet (coverage 0) carry no truth and are
        skipped.

    Returns
    -------
    points_xy_m : (n, 2) array
        (x, y) of the true surface points, metres.
    slopes : (n, 2) array
        Exact (s_x, s_y) = (dz/dx, dz/dy) there.
    """
    kept = np.asarray(kept)
    shape = station.geometry.camera.shape
    if kept.shape != shape or kept.dtype != bool:
        raise AnalysisError(f"kept must be a bool array of the camera's shape {shape}, got {kept.dtype} {kept.shape}")
    use = kept & (station.coverage > 0)
    return station.surface_point_facet_m[use][:, :2], station.slope_true[use]


def _focal_length(kappa_per_m: float) -> float | None:
    """Focal length 1/kappa, metres; None (infinite) when |kappa| < 4e-9 /m."""
    return None if abs(kappa_per_m) < INFINITE_FOCUS_KAPPA_PER_M else 1.0 / kappa_per_m


def _residual_rms_mrad(slopes: np.ndarray, model: np.ndarray) -> dict:
    """RMS of angular residuals atan(s) - atan(s_model) per axis and in magnitude, mrad."""
    e = 1e3 * (np.arctan(slopes) - np.arctan(model))
    return {"x": float(np.sqrt(np.mean(e[:, 0] ** 2))), "y": float(np.sqrt(np.mean(e[:, 1] ** 2))),
            "magnitude": float(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))}


def ground_truth(station: TwinStation, kept: np.ndarray) -> dict:
    """Fit the SPEC's parabola to the exact true slopes at the kept pixels; report the SPEC's figures.

    The two slope equations are fitted separately by linear least squares,
    ``s_x = 2A x + C + E1 y`` and ``s_y = 2B y + D + E2 x``, with E = (E1 + E2)/2; the assembled parabola
    (slopes ``2A x + C + E y``, ``2B y + D + E x``) defines the residuals. Residuals are angles
    ``atan(s) - atan(s_model)``, mrad.

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
        ``axis_angle_rad`` (0.5 atan2(E, A - B)), ``coefficients`` ([A, B, C, D, E]),
        ``slope_rms_mrad`` ({"design": {"x", "y", "magnitude"}, "parabola": {...}}) and ``n_points``.

    Raises
    ------
    AnalysisError
        If fewer than 3 kept pixels see the facet.
    """
    xy, slopes = truth_frame_samples(station, kept)
    n = xy.shape[0]
    if n < 3:
        raise AnalysisError(f"ground truth needs at least 3 kept pixels on the facet, got {n}")
    x, y = xy[:, 0], xy[:, 1]
    ones = np.ones(n)
    (two_a, c, e1), *_ = np.linalg.lstsq(np.column_stack([x, ones, y]), slopes[:, 0], rcond=None)
    (two_b, d, e2), *_ = np.linalg.lstsq(np.column_stack([y, ones, x]), slopes[:, 1], rcond=None)
    a, b = 0.5 * float(two_a), 0.5 * float(two_b)
    c, d, e1, e2 = float(c), float(d), float(e1), float(e2)
    e = 0.5 * (e1 + e2)

    parabola = np.column_stack([2 * a * x + c + e * y, 2 * b * y + d + e * x])
    f_design = station.design.focal_length_m
    design = np.column_stack([x / (2 * f_design), y / (2 * f_design)])

    eigenvalues = np.linalg.eigvalsh(np.array([[a, 0.5 * e], [0.5 * e, b]]))[::-1]
    return {
        "focal_length_x_m": _focal_length(4 * a),
        "focal_length_y_m": _focal_length(4 * b),
        "curvature_x_per_m": 4 * a,
        "curvature_y_per_m": 4 * b,
        "twist_mrad_per_m": 1e3 * e,
        "twist_e1_mrad_per_m": 1e3 * e1,
        "twist_e2_mrad_per_m": 1e3 * e2,
        "principal_focal_lengths_m": [_focal_length(4 * float(lam)) for lam in eigenvalues],
        "axis_angle_rad": 0.5 * float(np.arctan2(e, a - b)),
        "coefficients": [a, b, c, d, e],
        "slope_rms_mrad": {"design": _residual_rms_mrad(slopes, design),
                           "parabola": _residual_rms_mrad(slopes, parabola)},
        "n_points": int(n),
    }
