"""Reported figures: slope residuals as angles, focal lengths, principal axes.

Definitions: docs/conventions.md#residuals and #focal-power.
"""

from __future__ import annotations

import numpy as np

#: |kappa| below this (1/m) means an infinite focal length.
FLAT_CURVATURE_PER_M = 4e-9


def arctan(x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Arctangent, radians: the compiled :func:`~.kernels.atan` for 1-D float64 arrays, numpy's otherwise."""
    x = np.asarray(x)
    if x.ndim == 1 and x.dtype == np.float64 and (out is None or (out.dtype == np.float64 and out.ndim == 1
                                                                    and out.flags.c_contiguous)):
        from .kernels import atan
        return atan(x, out=out)
    return np.arctan(x, out=out)


def slope_residuals_mrad(s_x: np.ndarray, s_y: np.ndarray, model_x: np.ndarray, model_y: np.ndarray,
                         measured_angles: tuple[np.ndarray, np.ndarray] | None = None,
                         overwrite_model: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Residual angles e = atan(s_measured) - atan(s_model), mrad, per axis.

    Slope units and angles differ by up to 15 % at the slopes of a gore facet, so residuals are never
    taken as slope differences. ``measured_angles`` may pass atan(s_x), atan(s_y) computed once for
    several models. With *overwrite_model* the residuals are formed in the (float64) model arrays, which
    the caller no longer needs: the same operations, the same bits, no fresh arrays. The arctangents are
    :func:`~.kernels.atan` (numpy's to 3 units in the last place, four times faster) on 1-D arrays.
    """
    ax, ay = measured_angles if measured_angles is not None else (arctan(s_x), arctan(s_y))
    if not overwrite_model:
        return 1000.0 * (ax - arctan(model_x)), 1000.0 * (ay - arctan(model_y))
    out = []
    for angle, model in ((ax, model_x), (ay, model_y)):
        e = arctan(model, out=model)
        np.subtract(angle, e, out=e)
        e *= 1000.0
        out.append(e)
    return out[0], out[1]


def rms_summary(e_x_mrad: np.ndarray, e_y_mrad: np.ndarray) -> dict:
    """RMS of e_x, of e_y, and the magnitude RMS sqrt(mean(e_x^2 + e_y^2)), mrad."""
    n = e_x_mrad.size
    if n == 0:
        return {"x": None, "y": None, "magnitude": None}
    # sums of squares by einsum's own loops: one pass, no squared copy (BLAS never sees the points)
    sx = float(np.einsum("i,i->", e_x_mrad, e_x_mrad, optimize=False)) / n
    sy = float(np.einsum("i,i->", e_y_mrad, e_y_mrad, optimize=False)) / n
    return {"x": float(np.sqrt(sx)), "y": float(np.sqrt(sy)), "magnitude": float(np.sqrt(sx + sy))}


def focal_length_m(curvature_per_m: float) -> float | None:
    """f = 1/kappa, metres; None (JSON null) when |kappa| < 4e-9 /m. Negative for a convex facet."""
    if abs(curvature_per_m) < FLAT_CURVATURE_PER_M:
        return None
    return 1.0 / curvature_per_m


def principal_axes(a: float, b: float, e: float) -> tuple[list, float]:
    """Principal focal lengths (shorter first, metres or None) and the axis angle of the shorter, radians.

    From the eigenvalues lambda of [[A, E/2], [E/2, B]], f = 1/(4 lambda); the angle
    (1/2) atan2(E, A - B) is measured from +x toward +y.
    """
    mean = 0.5 * (a + b)
    half = np.hypot(0.5 * (a - b), 0.5 * e)
    lambdas = (mean + half, mean - half)      # larger lambda = shorter positive focal length
    return [focal_length_m(4.0 * lam) for lam in lambdas], float(0.5 * np.arctan2(e, a - b))
