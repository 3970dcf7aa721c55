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


def surface_slopes_of_points(coeffs: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`surface_slopes` of point arrays, formed in place: the same operations in the same order
    (2A x + C + E y as (2A x + C) + E y), so the same bits, with two fresh arrays instead of eight."""
    a, b, c, d, e, _ = coeffs
    s_x = np.multiply(2.0 * a, x)
    s_x += c
    tmp = np.multiply(e, y)
    s_x += tmp
    s_y = np.multiply(2.0 * b, y)
    s_y += d
    s_y += np.multiply(e, x, out=tmp)
    return s_x, s_y


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
    # Written in place (a pass per operation, no temporaries beyond two), in exactly the order of
    # qa = a ux ux + b uy uy + e ux uy, qb = (2a ox + c + e oy) ux + (2b oy + d + e ox) uy - uz,
    # disc = qb qb - 4 qa qc: the same bits as the expressions written out.
    tmp = np.empty_like(ux)
    qa = np.multiply(ux, a_)
    qa *= ux
    np.multiply(uy, b_, out=tmp)
    tmp *= uy
    qa += tmp
    np.multiply(ux, e_, out=tmp)
    tmp *= uy
    qa += tmp
    qb = np.multiply(ux, 2.0 * a_ * ox + c_ + e_ * oy)
    qb += np.multiply(uy, 2.0 * b_ * oy + d_ + e_ * ox, out=tmp)
    qb -= uz
    qc = a_ * ox * ox + b_ * oy * oy + c_ * ox + d_ * oy + e_ * ox * oy + f_ - oz
    disc = np.multiply(qb, qb)
    np.multiply(qa, 4.0, out=tmp)
    tmp *= qc
    disc -= tmp
    miss = disc < 0
    root = np.maximum(disc, 0.0, out=disc)        # NaN stays NaN, as np.where(miss, 0, disc) leaves it
    np.sqrt(root, out=root)
    q = np.copysign(root, qb, out=root)
    q += qb
    q *= -0.5
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.divide(qc, q, out=tmp)
        t2 = np.divide(q, qa, out=qa)
    np.copyto(t1, np.inf, where=~(t1 > 0))
    np.copyto(t2, np.inf, where=~(t2 > 0))
    t = np.minimum(t1, t2, out=t1)
    np.copyto(t, np.nan, where=miss | ~np.isfinite(t))
    out = np.empty((3, t.size))
    for row, (o, u) in enumerate(((ox, ux), (oy, uy), (oz, uz))):
        np.multiply(t, u, out=out[row])
        out[row] += o
    return out


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
    # In place, in the order of la = |C - X|, lb = |T - X|, n = a lb + b la, s = -n_xy / n_z (the same bits).
    ax, ay, az = np.subtract(cx, px), np.subtract(cy, py), np.subtract(cz, pz)
    bx, by, bz = (np.subtract(screen_points_m[k], p) for k, p in enumerate((px, py, pz)))
    tmp = np.empty_like(ax)

    def length(x, y, z):
        n = np.multiply(x, x)
        n += np.multiply(y, y, out=tmp)
        n += np.multiply(z, z, out=tmp)
        return np.sqrt(n, out=n)

    la, lb = length(ax, ay, az), length(bx, by, bz)
    # n = a/|a| + b/|b|, scaled by |a||b| (its length does not matter for the slope ratios)
    for a, b in ((ax, bx), (ay, by), (az, bz)):
        a *= lb
        a += np.multiply(b, la, out=tmp)
    np.divide(ax, az, out=ax)
    np.divide(ay, az, out=ay)
    return np.negative(ax, out=ax), np.negative(ay, out=ay)
