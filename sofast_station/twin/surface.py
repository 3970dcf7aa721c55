"""The true facet surface: height z(x, y) and its exact slopes, in the true facet frame.

The surface is ``z = a x^2 + b y^2 + E x y + l_x x + l_y y + c + cubic(u, v) + dents(x, y) + random(x, y)``
with ``a = 1/(4 f_x)``, ``b = 1/(4 f_y)``, ``(u, v) = (x - cx, y - cy)`` and (cx, cy) the design outline's
centroid (see :class:`~sofast_station.twin.parameters.TrueFacet`); l_x, l_y and c make the quadratic part
touch the design at (cx, cy), so an off-axis facet's focal-length error does not also tilt it. Every term has an
analytic derivative; the random term is a bicubic spline, differentiated exactly.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import RectBivariateSpline
from scipy.ndimage import gaussian_filter

from ..errors import ConfigError, GeometryError
from ..facet import FacetDesign
from .parameters import TrueFacet
from .outline import inside_outline

#: Newton stops when the step along the ray is below this, metres.
NEWTON_TOLERANCE_M = 1e-12

#: Largest random-field grid (nodes) the twin builds (about 80 MB per copy).
MAX_RANDOM_FIELD_NODES = 10_000_000


class RandomHeightField:
    """Gaussian-filtered white noise on a grid, interpolated by a bicubic spline.

    The grid spacing is a quarter of the correlation length (the Gaussian filter's standard deviation);
    the grid covers the outline's bounding box widened by ``max(4 correlation, 2 cm)``, and the field is
    zero outside that domain (the twin never looks there). The field is scaled so that the quadratic mean
    of the two slope components' RMS over the outline equals the target; each component then matches it
    up to the field's sampling anisotropy (a few per cent for a facet many correlation lengths wide), see
    :attr:`slope_rms_mrad`.

    Parameters
    ----------
    outline_m : (N, 2) array
        Facet outline in the facet frame, metres.
    slope_rms_mrad : float
        Target RMS slope per component, mrad (> 0).
    correlation_m : float
        Gaussian filter standard deviation, metres.
    seed : int
        Seed of the white noise.
    """

    def __init__(self, outline_m: np.ndarray, slope_rms_mrad: float, correlation_m: float, seed: int):
        spacing_m = correlation_m / 4.0
        margin_m = max(4.0 * correlation_m, 0.02)
        lo = outline_m.min(axis=0) - margin_m
        hi = outline_m.max(axis=0) + margin_m
        n_x = int(math.ceil((hi[0] - lo[0]) / spacing_m)) + 1
        n_y = int(math.ceil((hi[1] - lo[1]) / spacing_m)) + 1
        if n_x * n_y > MAX_RANDOM_FIELD_NODES:
            smallest_m = 4.0 * math.sqrt((hi[0] - lo[0]) * (hi[1] - lo[1]) / MAX_RANDOM_FIELD_NODES)
            raise ConfigError(f"slope_error_correlation_m = {correlation_m} m needs a {n_x} x {n_y} random-field "
                              f"grid for this facet, more than {MAX_RANDOM_FIELD_NODES} nodes: use at least "
                              f"{smallest_m:.2g} m")
        sigma_nodes = correlation_m / spacing_m
        pad = int(math.ceil(4.0 * sigma_nodes)) + 1
        rng = np.random.default_rng(seed)
        white = rng.standard_normal((n_x + 2 * pad, n_y + 2 * pad))
        field = gaussian_filter(white, sigma=sigma_nodes, truncate=4.0, mode="constant")[pad:-pad, pad:-pad]
        self._x_nodes_m = lo[0] + spacing_m * np.arange(n_x)
        self._y_nodes_m = lo[1] + spacing_m * np.arange(n_y)
        self.domain_m = (float(self._x_nodes_m[0]), float(self._x_nodes_m[-1]),
                         float(self._y_nodes_m[0]), float(self._y_nodes_m[-1]))
        self._spline = RectBivariateSpline(self._x_nodes_m, self._y_nodes_m, field, kx=3, ky=3, s=0)
        self._scale = 1.0

        # Scale on a sampling grid midway between the nodes, inside the outline.
        gx = np.arange(outline_m[:, 0].min() + spacing_m / 2.0, outline_m[:, 0].max(), spacing_m)
        gy = np.arange(outline_m[:, 1].min() + spacing_m / 2.0, outline_m[:, 1].max(), spacing_m)
        sx, sy = (a.ravel() for a in np.meshgrid(gx, gy, indexing="ij"))
        keep = inside_outline(sx, sy, outline_m)
        _, zx, zy = self.evaluate(sx[keep], sy[keep])
        rms_x, rms_y = np.sqrt(np.mean(zx ** 2)), np.sqrt(np.mean(zy ** 2))
        self._scale = 1e-3 * slope_rms_mrad / math.sqrt(0.5 * (rms_x ** 2 + rms_y ** 2))
        #: Achieved RMS of (dz/dx, dz/dy) over the outline's sampling grid, mrad.
        self.slope_rms_mrad = (1e3 * self._scale * rms_x, 1e3 * self._scale * rms_y)

    def evaluate(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height (m) and exact slopes dz/dx, dz/dy at facet-frame points; zero outside the domain."""
        x_m = np.asarray(x_m, dtype=np.float64)
        y_m = np.asarray(y_m, dtype=np.float64)
        z = np.zeros(x_m.shape)
        zx = np.zeros(x_m.shape)
        zy = np.zeros(x_m.shape)
        x0, x1, y0, y1 = self.domain_m
        inside = (x_m >= x0) & (x_m <= x1) & (y_m >= y0) & (y_m <= y1)
        xi, yi = x_m[inside], y_m[inside]
        fast, values = self._evaluate_uniform(xi, yi)
        slow = ~fast
        zi, zxi, zyi = values
        if np.any(slow):
            xs, ys = xi[slow], yi[slow]
            zi[slow] = self._spline.ev(xs, ys)
            zxi[slow] = self._spline.ev(xs, ys, dx=1)
            zyi[slow] = self._spline.ev(xs, ys, dy=1)
        z[inside], zx[inside], zy[inside] = self._scale * zi, self._scale * zxi, self._scale * zyi
        return z, zx, zy

    def _evaluate_uniform(self, x_m: np.ndarray, y_m: np.ndarray):
        """The same spline, evaluated where its knots are uniform (all but the outer few nodes).

        FITPACK's interpolating spline has interior knots at the nodes x_2 .. x_(n-3); a point whose four
        B-splines all have uniformly spaced knots is evaluated here with the cardinal cubic B-spline
        (value and first derivatives in one pass, a few times faster than ``ev``); the others are flagged
        for ``RectBivariateSpline.ev``. The two agree to rounding (tested).

        Returns
        -------
        fast : bool array
            Points evaluated here.
        (z, dz/dx, dz/dy) : arrays
            Unscaled values; zero where not *fast*.
        """
        t_x, t_y, coeffs = self._spline.tck
        n_cy = t_y.size - 4
        h_x = (t_x[-5] - t_x[4]) / (t_x.size - 9)
        h_y = (t_y[-5] - t_y[4]) / (t_y.size - 9)
        f_x = (x_m - t_x[4]) / h_x
        f_y = (y_m - t_y[4]) / h_y
        i_x = np.floor(f_x)
        i_y = np.floor(f_y)
        fast = (i_x >= 3) & (i_x <= t_x.size - 13) & (i_y >= 3) & (i_y <= t_y.size - 13)
        i_x = np.where(fast, i_x, 3.0)
        i_y = np.where(fast, i_y, 3.0)
        w_x, dw_x = _cardinal_cubic(f_x - i_x, h_x)
        w_y, dw_y = _cardinal_cubic(f_y - i_y, h_y)
        # Point in knot interval k = 4 + i uses B-splines (and coefficients) k-3 .. k.
        base = (i_x.astype(np.intp) + 1) * n_cy + (i_y.astype(np.intp) + 1)
        z = np.zeros(x_m.shape)
        zx = np.zeros(x_m.shape)
        zy = np.zeros(x_m.shape)
        for a in range(4):
            row = np.zeros(x_m.shape)
            d_row = np.zeros(x_m.shape)
            for b in range(4):
                c = coeffs[base + (a * n_cy + b)]
                row += c * w_y[b]
                d_row += c * dw_y[b]
            z += row * w_x[a]
            zx += row * dw_x[a]
            zy += d_row * w_x[a]
        return fast, (np.where(fast, z, 0.0), np.where(fast, zx, 0.0), np.where(fast, zy, 0.0))


def _cardinal_cubic(s: np.ndarray, h: float) -> tuple[list, list]:
    """Weights of the 4 uniform cubic B-splines at local coordinate s in [0, 1), and d/dx (spacing h)."""
    s2 = s * s
    s3 = s2 * s
    m = 1.0 - s
    weights = [m * m * m / 6.0, (3.0 * s3 - 6.0 * s2 + 4.0) / 6.0, (-3.0 * s3 + 3.0 * s2 + 3.0 * s + 1.0) / 6.0,
               s3 / 6.0]
    derivs = [-m * m / (2.0 * h), (3.0 * s2 - 4.0 * s) / (2.0 * h), (-3.0 * s2 + 2.0 * s + 1.0) / (2.0 * h),
              s2 / (2.0 * h)]
    return weights, derivs


class TrueSurface:
    """The true facet surface in the true facet frame.

    Parameters
    ----------
    facet : TrueFacet
        True shape parameters.
    design : FacetDesign
        The design (its focal length is the default, its centroid the cubic terms' origin, its outline
        the random field's support).
    """

    def __init__(self, facet: TrueFacet, design: FacetDesign):
        self.facet = facet
        self.design = design
        f_x = design.focal_length_m if facet.focal_length_x_m is None else facet.focal_length_x_m
        f_y = design.focal_length_m if facet.focal_length_y_m is None else facet.focal_length_y_m
        #: Coefficients of the quadratic part a x^2 + b y^2 + e x y (1/m); 0 for an infinite focal length.
        self.a_per_m = 1.0 / (4.0 * f_x)
        self.b_per_m = 1.0 / (4.0 * f_y)
        self.e_per_m = 1e-3 * facet.twist_mrad_per_m
        self.centroid_m = np.array(design.centroid_m, dtype=np.float64)
        # Linear and constant terms that make the quadratic part touch the design surface at the facet's
        # middle (same height and normal): a facet made with another focal length or with twist sits in
        # the fixture on its middle, and its shape error grows away from there. For an on-axis facet (middle
        # at the vertex) they are zero.
        cx, cy = (float(c) for c in self.centroid_m)
        a_d = 1.0 / (4.0 * design.focal_length_m)
        a, b, e = self.a_per_m, self.b_per_m, self.e_per_m
        self.lin_x = 2.0 * (a_d - a) * cx - e * cy
        self.lin_y = 2.0 * (a_d - b) * cy - e * cx
        self.const_m = a_d * (cx * cx + cy * cy) - (a * cx * cx + b * cy * cy + e * cx * cy
                                                     + self.lin_x * cx + self.lin_y * cy)
        self._cubic = np.array(facet.cubic_per_m2, dtype=np.float64)
        self._dents = np.array([[d["x_m"], d["y_m"], d["depth_m"], d["radius_m"]] for d in facet.dents],
                               dtype=np.float64).reshape(-1, 4)
        self.random_field = None
        if facet.slope_error_rms_mrad > 0:
            self.random_field = RandomHeightField(design.outline_m, facet.slope_error_rms_mrad,
                                                  facet.slope_error_correlation_m, facet.surface_seed)

    def height_and_slopes(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height z (m) and exact slopes dz/dx, dz/dy at facet-frame (x, y) metres."""
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        a, b, e = self.a_per_m, self.b_per_m, self.e_per_m
        z = a * x * x + b * y * y + e * x * y + self.lin_x * x + self.lin_y * y + self.const_m
        zx = 2.0 * a * x + e * y + self.lin_x
        zy = 2.0 * b * y + e * x + self.lin_y
        c30, c21, c12, c03 = self._cubic
        if np.any(self._cubic != 0):
            u = x - self.centroid_m[0]
            v = y - self.centroid_m[1]
            z = z + ((c30 * u + c21 * v) * u + c12 * v * v) * u + c03 * v * v * v
            zx = zx + 3.0 * c30 * u * u + 2.0 * c21 * u * v + c12 * v * v
            zy = zy + c21 * u * u + 2.0 * c12 * u * v + 3.0 * c03 * v * v
        for x0, y0, depth, radius in self._dents:
            dx, dy = x - x0, y - y0
            bump = depth * np.exp(-(dx * dx + dy * dy) / (2.0 * radius * radius))
            z = z + bump
            zx = zx - bump * dx / (radius * radius)
            zy = zy - bump * dy / (radius * radius)
        if self.random_field is not None:
            zr, zrx, zry = self.random_field.evaluate(x, y)
            z, zx, zy = z + zr, zx + zrx, zy + zry
        return z, zx, zy

    def height(self, x_m, y_m) -> np.ndarray:
        """Height z (m) at facet-frame (x, y) metres."""
        return self.height_and_slopes(x_m, y_m)[0]

    def slopes(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
        """Exact slopes (dz/dx, dz/dy) at facet-frame (x, y) metres."""
        return self.height_and_slopes(x_m, y_m)[1:]

    def normals(self, x_m, y_m) -> np.ndarray:
        """Unit normals (..., 3) with n_z > 0 at facet-frame (x, y) metres."""
        _, zx, zy = self.height_and_slopes(x_m, y_m)
        n = np.stack([-zx, -zy, np.ones_like(zx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def paraboloid_hits(self, origin_m: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Ray parameter of the first hit of the quadratic part ``a x^2 + b y^2 + e x y + l_x x + l_y y + c``.

        Uses the numerically stable roots of the ray/quadric quadratic and keeps the smallest positive.

        Parameters
        ----------
        origin_m : (3,) array
            Common ray origin, facet frame, metres.
        directions : (n, 3) array
            Ray directions (unit), facet frame.

        Returns
        -------
        (n,) array
            Distance along each ray, metres; NaN where the ray misses.
        """
        a, b, e = self.a_per_m, self.b_per_m, self.e_per_m
        ox, oy, oz = (float(c) for c in origin_m)
        dx, dy, dz = directions[:, 0], directions[:, 1], directions[:, 2]
        alpha = a * dx * dx + b * dy * dy + e * dx * dy
        lx, ly = self.lin_x, self.lin_y
        beta = 2.0 * a * ox * dx + 2.0 * b * oy * dy + e * (ox * dy + oy * dx) + lx * dx + ly * dy - dz
        gamma = a * ox * ox + b * oy * oy + e * ox * oy + lx * ox + ly * oy + self.const_m - oz
        disc = beta * beta - 4.0 * alpha * gamma
        with np.errstate(invalid="ignore", divide="ignore"):
            q = -0.5 * (beta + np.copysign(np.sqrt(disc), beta))
            root_1 = np.where(alpha != 0.0, q / alpha, np.inf)
            root_2 = np.where(q != 0.0, gamma / q, np.inf)
        root_1 = np.where(root_1 > 0, root_1, np.inf)
        root_2 = np.where(root_2 > 0, root_2, np.inf)
        t = np.minimum(root_1, root_2)
        return np.where(np.isfinite(t) & (disc >= 0), t, np.nan)

    def intersect(self, origin_m: np.ndarray, directions: np.ndarray, max_iterations: int = 50,
                  start_m: np.ndarray | None = None) -> np.ndarray:
        """First intersection of rays with the full true surface.

        Starts at the quadratic part's stable root (:meth:`paraboloid_hits`), or at *start_m* when given
        (the hits on a surface a few micrometres away), then Newton on
        ``g(t) = z_surface(x(t), y(t)) - z(t)`` until the step is below 1e-12 m.

        Parameters
        ----------
        origin_m : (3,) array
            Common ray origin, facet frame, metres.
        directions : (n, 3) array
            Unit ray directions, facet frame.
        max_iterations : int
            Newton iterations before giving up.
        start_m : (n,) array, optional
            Distances along the rays to start from, metres (NaN: a ray that misses).

        Returns
        -------
        (n,) array
            Distance along each ray, metres; NaN where the ray misses the quadric.

        Raises
        ------
        GeometryError
            If Newton does not converge for some ray (a surface too rough for its quadratic start).
        """
        origin_m = np.asarray(origin_m, dtype=np.float64)
        t = self.paraboloid_hits(origin_m, directions) if start_m is None else np.array(start_m, dtype=np.float64)
        active = np.flatnonzero(np.isfinite(t))
        for _ in range(max_iterations):
            if active.size == 0:
                break
            d = directions[active]
            p = origin_m + t[active, None] * d
            z, zx, zy = self.height_and_slopes(p[:, 0], p[:, 1])
            g = z - p[:, 2]
            dg = zx * d[:, 0] + zy * d[:, 1] - d[:, 2]
            step = g / dg
            t[active] -= step
            active = active[~(np.abs(step) < NEWTON_TOLERANCE_M)]
        if active.size:
            raise GeometryError(f"ray/surface intersection did not converge for {active.size} rays within "
                                f"{max_iterations} Newton steps: the true surface's shape terms (dents, cubic, "
                                "random) are too large for the paraboloid start; reduce them")
        return t
