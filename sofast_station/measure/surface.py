"""Ray/surface intersection and normals, in the facet frame.

The shape model is z = A x^2 + B y^2 + C x + D y + E xy + F, coefficients ``(A, B, C, D, E, F)``.
"""

from __future__ import annotations

import numpy as np


def surface_z(coeffs: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Height of the quadratic model, metres."""
    a, b, c, d, e, f = coeffs
    return a * x * x + b * y * y + c * x + d * y + e * x * y + f


def surface_slopes(coeffs: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slopes dz/dx, dz/dy of the quadratic model (dimensionless)."""
    a, b, c, d, e, _ = coeffs
    return 2.0 * a * x + c + e * y, 2.0 * b * y + d + e * x


def intersect_quadratic(coeffs: np.ndarray, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """First intersection of rays ``origin + t u`` (t > 0) with the quadratic surface.

    Substituting the ray gives a t^2 + b t + c = 0. The roots are formed as q = -(b + sign(b) sqrt(disc))/2,
    t = c/q and t = q/a, which loses no digits when a is tiny (a nearly flat model or a ray along the
    axis), where the textbook formula cancels catastrophically.

    Parameters
    ----------
    coeffs : (6,) array
    origin : (3,) array
        Ray origin (the camera centre), facet frame, metres.
    directions : (3, N) array
        Unit ray directions, facet frame (components in rows: fast for long arrays).

    Returns
    -------
    (3, N) array
        Intersection points, metres; NaN columns where a ray misses.
    """
    a_, b_, c_, d_, e_, f_ = (float(v) for v in coeffs)
    ox, oy, oz = (float(v) for v in origin)
    ux, uy, uz = directions
    qa = a_ * ux * ux + b_ * uy * uy + e_ * ux * uy
    qb = (2.0 * a_ * ox + c_ + e_ * oy) * ux + (2.0 * b_ * oy + d_ + e_ * ox) * uy - uz
    qc = a_ * ox * ox + b_ * oy * oy + c_ * ox + d_ * oy + e_ * ox * oy + f_ - oz
    disc = qb * qb - 4.0 * qa * qc
    miss = disc < 0
    root = np.sqrt(np.where(miss, 0.0, disc))
    q = -0.5 * (qb + np.copysign(root, qb))
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = qc / q
        t2 = q / qa
    t1 = np.where(t1 > 0, t1, np.inf)
    t2 = np.where(t2 > 0, t2, np.inf)
    t = np.minimum(t1, t2)
    t = np.where(miss | ~np.isfinite(t), np.nan, t)
    return np.stack([ox + t * ux, oy + t * uy, oz + t * uz])


def normal_slopes(points: np.ndarray, camera_m: np.ndarray, screen_points_m: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Surface slopes from the law of reflection.

    The unit normal at X bisects the unit vectors X->C (camera centre) and X->T (screen point); slopes
    are s_x = -n_x/n_z, s_y = -n_y/n_z (docs/conventions.md#slopes).

    Parameters
    ----------
    points : (3, N) array
        Surface points X, facet frame, metres.
    camera_m : (3,) array
        Camera centre C, facet frame, metres.
    screen_points_m : (3, N) array
        Screen points T seen at each X, facet frame, metres.
    """
    cx, cy, cz = (float(v) for v in camera_m)
    px, py, pz = points
    ax, ay, az = cx - px, cy - py, cz - pz
    la = np.sqrt(ax * ax + ay * ay + az * az)
    bx, by, bz = screen_points_m[0] - px, screen_points_m[1] - py, screen_points_m[2] - pz
    lb = np.sqrt(bx * bx + by * by + bz * bz)
    # n = a/|a| + b/|b|, scaled by |a||b| (its length does not matter for the slope ratios)
    nx, ny, nz = ax * lb + bx * la, ay * lb + by * la, az * lb + bz * la
    return -nx / nz, -ny / nz
