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


def principal_curvatures(a: float, b: float, e: float) -> list[float]:
    """The principal focal powers (1/m), larger first: 4 lambda for the eigenvalues lambda of
    [[A, E/2], [E/2, B]] (the larger power is the shorter positive focal length)."""
    mean = 0.5 * (a + b)
    half = float(np.hypot(0.5 * (a - b), 0.5 * e))
    return [4.0 * (mean + half), 4.0 * (mean - half)]


def principal_axes(a: float, b: float, e: float) -> tuple[list, float]:
    """Principal focal lengths (shorter first, metres or None) and the axis angle of the shorter, radians.

    f = 1 / kappa of :func:`principal_curvatures`; the angle (1/2) atan2(E, A - B) is measured from +x
    toward +y.
    """
    return [focal_length_m(k) for k in principal_curvatures(a, b, e)], float(0.5 * np.arctan2(e, a - b))


def neighbour_pairs(flat_idx: np.ndarray, width_px: int) -> tuple:
    """The pairs of side-by-side and of stacked neighbouring pixels among *flat_idx*.

    Parameters
    ----------
    flat_idx : (N,) int array
        The pixels' flat indices (raster order, strictly increasing) in an image *width_px* wide.
    width_px : int

    Returns
    -------
    tuple of two (first, second) pairs of int arrays
        For side-by-side neighbours, then stacked ones: positions in *flat_idx* of each pair's first pixel
        (raster order) and of its neighbour to the right (below). Pairs do not run across a row's end.
    """
    flat_idx = np.asarray(flat_idx, dtype=np.int64)
    width_px = int(width_px)
    pos = np.arange(flat_idx.size)
    if flat_idx.size == 0:
        return (pos, pos), (pos, pos)
    # side by side: in a strictly increasing list, p + 1 can only be the next entry
    right = (flat_idx[1:] == flat_idx[:-1] + 1) & ((flat_idx[:-1] % width_px) != width_px - 1)
    # stacked: each pixel's position in the list looked up on the image (-1: not in the list)
    lookup = np.full(int(flat_idx[-1]) + 1 + width_px, -1, dtype=np.int64)
    lookup[flat_idx] = pos
    below_at = lookup[flat_idx + width_px]
    below = below_at >= 0
    return (pos[:-1][right], pos[1:][right]), (pos[below], below_at[below])


def neighbour_difference_ms(values: np.ndarray, pairs: tuple) -> float:
    """Mean square difference of *values* between side-by-side and stacked neighbouring pixels.

    Parameters
    ----------
    values : (N,) array
        One value per pixel (e.g. a slope residual, mrad).
    pairs : tuple
        The pixels' neighbour pairs, :func:`neighbour_pairs` of their flat indices (computed once for any
        number of value arrays on the same pixels).

    Returns
    -------
    float
        Mean of (v(p) - v(q))^2 over the pairs of neighbours that both have a value, in the values' unit
        squared; 0 when there is no pair. For a smooth field it is half the mean square gradient per pixel,
        plus twice the per-pixel noise variance.
    """
    values = np.asarray(values, dtype=np.float64)
    total, count = 0.0, 0
    for first, second in pairs:
        d = values[second] - values[first]
        total += float(np.einsum("i,i->", d, d, optimize=False))      # einsum's own loop: the same bits always
        count += int(d.size)
    return total / count if count else 0.0
