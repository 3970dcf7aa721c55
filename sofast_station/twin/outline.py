"""Point-in-polygon and signed distance to a facet outline (facet-frame x, y, metres)."""

from __future__ import annotations

import numpy as np


def inside_outline(x: np.ndarray, y: np.ndarray, outline_m: np.ndarray) -> np.ndarray:
    """Whether points lie inside a simple polygon (crossing-number rule).

    Parameters
    ----------
    x, y : arrays of the same shape
        Point coordinates, metres.
    outline_m : (N, 2) array
        Polygon corners, metres (either orientation).

    Returns
    -------
    bool array, shape of *x*
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    inside = np.zeros(x.shape, dtype=bool)
    corners = np.asarray(outline_m, dtype=np.float64)
    for (x0, y0), (x1, y1) in zip(corners, np.roll(corners, -1, axis=0)):
        if y0 == y1:
            continue
        straddles = (y0 > y) != (y1 > y)
        x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= straddles & (x < x_cross)
    return inside


def signed_distance_to_outline(x: np.ndarray, y: np.ndarray, outline_m: np.ndarray) -> np.ndarray:
    """Euclidean distance to the polygon's boundary, negative inside, metres.

    Parameters
    ----------
    x, y : arrays of the same shape
        Point coordinates, metres.
    outline_m : (N, 2) array
        Polygon corners, metres.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    best = np.full(x.shape, np.inf)
    corners = np.asarray(outline_m, dtype=np.float64)
    for (x0, y0), (x1, y1) in zip(corners, np.roll(corners, -1, axis=0)):
        ex, ey = x1 - x0, y1 - y0
        length2 = ex * ex + ey * ey
        s = np.clip(((x - x0) * ex + (y - y0) * ey) / length2, 0.0, 1.0)
        best = np.minimum(best, np.hypot(x - x0 - s * ex, y - y0 - s * ey))
    return np.where(inside_outline(x, y, corners), -best, best)
