"""The true surface: random slope error statistics, analytic shape terms, exact slopes, ray intersection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sofast_station.twin import TrueFacet, TrueSurface
from sofast_station.twin.outline import inside_outline

from .conftest import RICH_FACET


def _points_in_outline(design, spacing_m=0.002):
    g = np.arange(-0.3 + spacing_m / 2, 0.3, spacing_m)
    x, y = (a.ravel() for a in np.meshgrid(g, g))
    keep = inside_outline(x, y, design.outline_m)
    return x[keep], y[keep]


@pytest.mark.parametrize("rms_mrad, corr_m, seed", [(0.5, 0.02, 3), (1.5, 0.01, 7), (0.8, 0.03, 0)])
def test_random_surface_has_configured_slope_rms(design, rms_mrad, corr_m, seed):
    x, y = _points_in_outline(design)
    smooth = TrueSurface(TrueFacet(), design)
    rough = TrueSurface(TrueFacet(slope_error_rms_mrad=rms_mrad, slope_error_correlation_m=corr_m,
                                  surface_seed=seed), design)
    sx0, sy0 = smooth.slopes(x, y)
    sx1, sy1 = rough.slopes(x, y)
    for component in (sx1 - sx0, sy1 - sy0):
        rms = 1e3 * np.sqrt(np.mean(component ** 2))
        assert rms == pytest.approx(rms_mrad, rel=0.10)


def test_random_surface_is_reproducible_per_seed(design):
    x, y = _points_in_outline(design, 0.01)

    def make(seed):
        return TrueSurface(TrueFacet(slope_error_rms_mrad=1.0, surface_seed=seed), design)
    z_0 = TrueSurface(TrueFacet(), design).height(x, y)
    z_a, z_b, z_c = (make(seed).height(x, y) - z_0 for seed in (5, 5, 6))
    assert np.array_equal(z_a, z_b)
    assert np.sqrt(np.mean((z_a - z_c) ** 2)) > 0.5 * np.sqrt(np.mean(z_a ** 2))


def test_random_field_fast_evaluation_equals_scipy_spline(design):
    field = TrueSurface(TrueFacet(slope_error_rms_mrad=1.0, slope_error_correlation_m=0.01), design).random_field
    x0, x1, y0, y1 = field.domain_m
    rng = np.random.default_rng(1)
    x, y = rng.uniform(x0, x1, 50000), rng.uniform(y0, y1, 50000)
    z, zx, zy = field.evaluate(x, y)
    spline = field._spline
    for ours, ref in ((z, spline.ev(x, y)), (zx, spline.ev(x, y, dx=1)), (zy, spline.ev(x, y, dy=1))):
        ref = field._scale * ref
        assert np.max(np.abs(ours - ref)) < 1e-12 * np.max(np.abs(ref))


def test_dents_and_cubic_terms_change_slopes_by_their_analytic_derivative(design):
    x, y = _points_in_outline(design, 0.01)
    cubic = (3e-4, -2e-4, 1e-4, 2.5e-4)
    dents = ({"x_m": 0.1, "y_m": -0.05, "depth_m": -3e-5, "radius_m": 0.02},
             {"x_m": -0.2, "y_m": 0.15, "depth_m": 2e-5, "radius_m": 0.04})
    base = TrueSurface(TrueFacet(focal_length_x_m=5.4, twist_mrad_per_m=0.2), design)
    shaped = TrueSurface(TrueFacet(focal_length_x_m=5.4, twist_mrad_per_m=0.2, cubic_per_m2=cubic, dents=dents),
                         design)
    u, v = x - design.centroid_m[0], y - design.centroid_m[1]
    c30, c21, c12, c03 = cubic
    dz = c30 * u ** 3 + c21 * u ** 2 * v + c12 * u * v ** 2 + c03 * v ** 3
    dzx = 3 * c30 * u ** 2 + 2 * c21 * u * v + c12 * v ** 2
    dzy = c21 * u ** 2 + 2 * c12 * u * v + 3 * c03 * v ** 2
    for d in dents:
        g = d["depth_m"] * np.exp(-((x - d["x_m"]) ** 2 + (y - d["y_m"]) ** 2) / (2 * d["radius_m"] ** 2))
        dz += g
        dzx += -g * (x - d["x_m"]) / d["radius_m"] ** 2
        dzy += -g * (y - d["y_m"]) / d["radius_m"] ** 2
    z0, sx0, sy0 = base.height_and_slopes(x, y)
    z1, sx1, sy1 = shaped.height_and_slopes(x, y)
    assert np.max(np.abs((z1 - z0) - dz)) < 1e-15
    assert np.max(np.abs((sx1 - sx0) - dzx)) < 1e-15
    assert np.max(np.abs((sy1 - sy0) - dzy)) < 1e-15
    assert np.max(np.abs(dzx)) > 1e-4                     # the terms are not negligible


def test_quadratic_part_and_twist(design):
    x, y = _points_in_outline(design, 0.05)
    surface = TrueSurface(TrueFacet(focal_length_x_m=5.42, focal_length_y_m=math.inf, twist_mrad_per_m=0.7), design)
    z, sx, sy = surface.height_and_slopes(x, y)
    e = 0.7e-3
    assert np.allclose(z, x ** 2 / (4 * 5.42) + e * x * y, rtol=0, atol=1e-16)
    assert np.allclose(sx, x / (2 * 5.42) + e * y, rtol=0, atol=1e-16)
    assert np.allclose(sy, e * x, rtol=0, atol=1e-16)


def test_slopes_are_the_derivatives_of_the_height(design):
    surface = TrueSurface(RICH_FACET, design)
    x, y = _points_in_outline(design, 0.013)
    h = 1e-5
    fd_x = (surface.height(x + h, y) - surface.height(x - h, y)) / (2 * h)
    fd_y = (surface.height(x, y + h) - surface.height(x, y - h)) / (2 * h)
    sx, sy = surface.slopes(x, y)
    assert np.max(np.abs(fd_x - sx)) < 2e-9
    assert np.max(np.abs(fd_y - sy)) < 2e-9


def test_intersection_lies_on_the_surface_and_is_the_first_hit(design):
    surface = TrueSurface(RICH_FACET, design)
    origin = np.array([0.17, 0.02, 10.66])
    rng = np.random.default_rng(2)
    targets = np.column_stack([rng.uniform(-0.32, 0.32, 3000), rng.uniform(-0.32, 0.32, 3000), np.zeros(3000)])
    d = targets - origin
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = surface.intersect(origin, d)
    hit = origin + t[:, None] * d
    assert np.max(np.abs(hit[:, 2] - surface.height(hit[:, 0], hit[:, 1]))) < 1e-12
    # no earlier crossing: the ray stays above the surface before the hit
    for frac in (0.5, 0.9, 0.999):
        p = origin + frac * t[:, None] * d
        assert np.all(p[:, 2] > surface.height(p[:, 0], p[:, 1]))


def test_nearly_flat_surface_uses_the_stable_root(design):
    origin = np.array([0.17, 0.0, 10.66])
    d = np.array([[-0.017, 0.01, -1.0]])
    d /= np.linalg.norm(d)
    t_flat = TrueSurface(TrueFacet(focal_length_x_m=math.inf, focal_length_y_m=math.inf), design).intersect(origin, d)
    t_long = TrueSurface(TrueFacet(focal_length_x_m=1e12, focal_length_y_m=1e12), design).intersect(origin, d)
    assert t_flat[0] == pytest.approx(-origin[2] / d[0, 2], rel=1e-15)
    assert abs(t_long[0] - t_flat[0]) < 1e-12
