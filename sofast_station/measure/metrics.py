"""Reported figures: slope-residual RMS values, focal lengths, principal axes (the residual angles
themselves come from :func:`~sofast_station.measure.kernels.model_residuals`).

Definitions: docs/conventions.md#residuals and #focal-power.
"""

from __future__ import annotations

import numpy as np

#: |kappa| below this (1/m) means an infinite focal length.
FLAT_CURVATURE_PER_M = 4e-9


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


def neighbour_difference_ms(values: np.ndarray, flat_idx: np.ndarray, width_px: int) -> float:
    """Mean square difference of *values* between side-by-side and stacked neighbouring pixels.

    Parameters
    ----------
    values : (N,) array
        One value per pixel (e.g. a slope residual, mrad).
    flat_idx : (N,) int array
        The pixels' flat indices (raster order, increasing) in an image *width_px* wide.
    width_px : int

    Returns
    -------
    float
        Mean of (v(p) - v(q))^2 over the pairs of neighbours that both have a value, in the values' unit
        squared; 0 when there is no pair. For a smooth field it is half the mean square gradient per pixel,
        plus twice the per-pixel noise variance.
    """
    values = np.asarray(values, dtype=np.float64)
    flat_idx = np.asarray(flat_idx)
    total, count = 0.0, 0
    for step in (1, int(width_px)):
        nxt = np.searchsorted(flat_idx, flat_idx + step)
        nxt = np.minimum(nxt, flat_idx.size - 1)
        pair = flat_idx[nxt] == flat_idx + step
        if step == 1:
            pair &= (flat_idx % width_px) != width_px - 1        # not across a row's end
        d = values[nxt[pair]] - values[pair]
        total += float(np.einsum("i,i->", d, d, optimize=False))      # einsum's own loop: the same bits always
        count += int(d.size)
    return total / count if count else 0.0
