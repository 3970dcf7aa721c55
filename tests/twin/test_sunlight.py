"""The twin's own trace of its facet in sunlight (twin/sunlight.py), against closed forms and rays traced one by
one: the optical truth the station's optical figures are checked against must not come from optics/."""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest
from scipy.integrate import cumulative_trapezoid, quad
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from sofast_station.errors import ConfigError
from sofast_station.facet import load_facet
from sofast_station.twin.parameters import TrueFacet
from sofast_station.twin.surface import TrueSurface
from sofast_station.twin.sunlight import Sunlight, facet_in_sunlight, sun_share_within, sunlit_plan
from tests.conftest import ROOT

DISH = load_facet(ROOT / "fixtures/facets/dish_5m33.toml")
HELIOSTAT = load_facet(ROOT / "fixtures/facets/heliostat_100m.toml")
SUN_RAD = 4.65e-3


def _figures(facet: TrueFacet, design, sunlight: Sunlight, rotation=None, pivot=None) -> dict:
    return facet_in_sunlight(TrueSurface(facet, design), sunlit_plan(design, sunlight), sunlight, rotation, pivot)


# ------------------------------------------------------------------------------------------- closed form
def _ellipse_share_in_circle(a, b, radius):
    """The share of a uniform ellipse (semi-axes a <= b) inside a concentric circle: the circle's part near the
    major axis and the ellipse's elsewhere, from the ellipse's polar radius r^2 = a^2 b^2 / (a^2 cos^2 + b^2 sin^2),
    whose sector area from 0 to psi is (a b / 2) atan((b / a) tan psi)."""
    share = np.where(radius <= a, radius * radius / (a * b), 1.0)
    between = (radius > a) & (radius < b)
    sin2 = np.clip(a * a * (b * b - radius * radius) / (radius * radius * (b * b - a * a)), 0.0, 1.0)
    psi = np.arcsin(np.sqrt(sin2))             # where the ellipse crosses the circle, from the major axis
    quadrant = 0.5 * radius * radius * psi + 0.5 * a * b * (0.5 * np.pi - np.arctan((b / a) * np.tan(psi)))
    return np.where(between, 4.0 * quadrant / (np.pi * a * b), share)


def _perfect_at_focus(design, n=500):
    """The power within radius R of the focus of a perfect paraboloid, sun on its axis (pillbox), target at the
    focal plane: F(R), by a midpoint rule over the square facet (one quadrant, by symmetry).

    A point at radius rho lies D = f + rho^2 / 4f from the focus (the parabola's focal property) and sees it at
    phi from the axis, sin(phi) = rho / D. Its image of the sun (a cone of half-angle theta about the ray to the
    focus) on the focal plane is an ellipse about the focus, D theta across and D theta / cos(phi) along the
    radial direction (to first order in theta); a pillbox fills it uniformly. Each point reflects the same power
    per projected area (normal incidence)."""
    f = design.focal_length_m
    half = float(design.outline_m[:, 0].max())
    centres = (np.arange(n) + 0.5) * (half / n)
    x, y = np.meshgrid(centres, centres)
    rho2 = x * x + y * y
    d = f + rho2 / (4.0 * f)
    cos_phi = np.sqrt(1.0 - rho2 / (d * d))
    a, b = d * SUN_RAD, d * SUN_RAD / cos_phi
    return lambda radius: float(np.mean(_ellipse_share_in_circle(a, b, radius)))


@pytest.mark.parametrize("design", [DISH, HELIOSTAT], ids=["dish 0.6 m, f 5.33 m", "heliostat 1.2 m, f 100 m"])
def test_a_perfect_paraboloid_at_its_focus_gives_the_closed_form(design):
    """Intercept at three aperture radii, the 90 % radius and the reflected power of a perfect paraboloid, on its
    axis, at its focus, against :func:`_perfect_at_focus` (2 designs x 3 apertures).

    Tolerances: the closed form's midpoint rule over 500 x 500 cells (its integrand has kinks where the image's
    axes cross R) changes by under 2e-6 from 250 x 250 cells; the trace's own scatter on a perfect surface is
    5e-8 (16 scramblings). Both within 1e-5 in the intercept and 1e-5 relative in the radius. The reflected
    power is DNI x reflectivity x the projected area exactly (normal incidence: cos(theta_i) dA = dA_projected).
    """
    f = design.focal_length_m
    closed = _perfect_at_focus(design)
    r90 = brentq(lambda r: closed(r) - 0.9, 0.5 * f * SUN_RAD, 1.5 * f * SUN_RAD, xtol=1e-12)
    perfect = TrueFacet(focal_length_x_m=f, focal_length_y_m=f)
    area = float(np.ptp(design.outline_m[:, 0]) * np.ptp(design.outline_m[:, 1]))
    for scale in (0.85, 0.95, 1.0):
        radius = scale * f * SUN_RAD
        got = _figures(perfect, design, Sunlight(aperture=("circle", radius)))
        assert got["intercept"] == pytest.approx(closed(radius), abs=1e-5), scale
        assert got["spot_radius_m"] == pytest.approx(r90, rel=1e-5)
        assert got["reflected_w"] == pytest.approx(1000.0 * 0.94 * area, rel=1e-12)
        assert got["centroid_offset_mrad"]["magnitude"] < 1e-9
        assert got["power_ratio_vs_design"] == pytest.approx(1.0, abs=1e-12)
    # sqrt(0.9) f theta if every image were the centre's: the off-axis points' larger images widen it
    assert r90 > math.sqrt(0.9) * f * SUN_RAD


def test_the_power_reflected_at_an_incidence_is_the_cosine_law():
    """At 30 degrees the facet reflects DNI x reflectivity x area x cos(30 deg): the symmetric facet's slopes
    cancel in the integral of (cos i - sin i s_x) over the outline."""
    got = _figures(TrueFacet(focal_length_x_m=5.33, focal_length_y_m=5.33), DISH,
                   Sunlight(incidence_angle_deg=30.0, aperture=("circle", 0.2)))
    assert got["reflected_w"] == pytest.approx(1000.0 * 0.94 * 0.36 * math.cos(math.radians(30.0)), rel=1e-9)


# -------------------------------------------------------------------------------------- rays one by one
def _buie_inverse_cdf(csr: float):
    """Buie's radial distribution, integrated here on a fine trapezoid grid (theta in mrad)."""
    kappa = 0.9 * math.log(13.5 * csr) * csr ** -0.3
    gamma = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1
    t = np.concatenate([np.linspace(0.0, 4.65, 20001), np.geomspace(4.65 + 1e-9, 43.6, 20001)])
    radiance = np.where(t <= 4.65, np.cos(0.326 * t) / np.cos(0.308 * t),
                        math.exp(kappa) * np.maximum(t, 1e-9) ** gamma)
    cdf = cumulative_trapezoid(radiance * t, t, initial=0.0)
    cdf[20001:] -= cdf[20001] - cdf[20000]             # no power across the jump at the disc's edge
    return lambda u: 1e-3 * np.interp(u, cdf / cdf[-1], t)


def _rays_one_by_one(facet: TrueFacet, design, sun: str, aperture, rotation_mrad, n: int, seed: int) -> dict:
    """Intercept, 90 % radius and centroid of *n* rays traced one by one, each from a random point of the outline
    (uniform in x, y) in a random direction of the sun shape: the definitions of docs/optics.md written here
    with scipy's rotations, nothing of twin/sunlight.py."""
    rng = np.random.default_rng(seed)
    surface = TrueSurface(facet, design)
    lo, hi = design.outline_m.min(axis=0), design.outline_m.max(axis=0)
    x, y = rng.uniform(lo[0], hi[0], n), rng.uniform(lo[1], hi[1], n)
    z, sx, sy = surface.height_and_slopes(x, y)
    turn = Rotation.from_euler("YX", [rotation_mrad[1] * 1e-3, rotation_mrad[0] * 1e-3]).as_matrix()
    pivot = np.array([*design.alignment_point_m, float(design.z(*design.alignment_point_m))])
    points = (np.column_stack([x, y, z]) - pivot) @ turn.T + pivot
    normals = np.column_stack([-sx, -sy, np.ones(n)])
    normals = (normals / np.linalg.norm(normals, axis=1, keepdims=True)) @ turn.T
    # the sun: along -z, each ray turned by theta about a random axis across it
    u = rng.random(n)
    theta = {"pillbox": lambda: SUN_RAD * np.sqrt(u), "gaussian": lambda: 2.51e-3 * np.sqrt(-2.0 * np.log1p(-u)),
             "buie": lambda: _buie_inverse_cdf(0.05)(u)}[sun]()
    azimuth = rng.uniform(0.0, 2.0 * np.pi, n)
    incoming = np.column_stack([np.sin(theta) * np.cos(azimuth), np.sin(theta) * np.sin(azimuth), -np.cos(theta)])
    cos_i = np.maximum(normals[:, 2], 0.0)                      # -u_sun . n with u_sun = -z
    power = cos_i * np.sqrt(1.0 + sx * sx + sy * sy)           # per unit projected area, up to a constant
    reflected = incoming - 2.0 * np.sum(incoming * normals, axis=1, keepdims=True) * normals
    # the target: the design normal at the outline's centroid reflects the sun's centre into its normal
    cx, cy = design.centroid_m
    centre = np.array([cx, cy, float(design.z(cx, cy))])
    n_c = np.array([-cx / (2 * design.focal_length_m), -cy / (2 * design.focal_length_m), 1.0])
    n_c /= np.linalg.norm(n_c)
    r_c = np.array([0.0, 0.0, -1.0]) - 2.0 * (-n_c[2]) * n_c
    aim = centre + (design.focal_length_m + centre[2]) * r_c
    axis_x = np.array([1.0, 0.0, 0.0]) - r_c[0] * r_c
    axis_x /= np.linalg.norm(axis_x)
    axis_y = np.cross(r_c, axis_x)
    t = ((aim - points) @ r_c) / (reflected @ r_c)
    ahead = t > 0
    hits = points[ahead] + t[ahead, None] * reflected[ahead] - aim
    px, py, p = hits @ axis_x, hits @ axis_y, power[ahead]
    inside = (np.hypot(px, py) <= aperture[1]) if aperture[0] == "circle" else \
        (np.abs(px) <= aperture[1] / 2) & (np.abs(py) <= aperture[2] / 2)
    total = power.sum()
    mx, my = np.sum(p * px) / p.sum(), np.sum(p * py) / p.sum()
    r = np.hypot(px - mx, py - my)
    order = np.argsort(r)
    radius = float(np.interp(0.9 * total, np.cumsum(p[order]), r[order]))
    return {"intercept": float(p[inside].sum() / total), "spot_radius_m": radius, "x": mx, "y": my}


#: (facet, sun, aperture, boresight rotation (x, y) mrad): a small drawn population of rough facets.
CASES = [
    (TrueFacet(focal_length_x_m=5.42, focal_length_y_m=5.35, twist_mrad_per_m=0.12, slope_error_rms_mrad=0.5,
               slope_error_correlation_m=0.02, surface_seed=7), "pillbox", ("circle", 0.026), (0.0, 0.0)),
    (TrueFacet(focal_length_x_m=5.25, focal_length_y_m=5.40, slope_error_rms_mrad=1.5, slope_error_correlation_m=0.03,
               surface_seed=3, dents=({"x_m": 0.1, "y_m": -0.1, "depth_m": -3e-5, "radius_m": 0.04},)),
     "gaussian", ("rectangle", 0.07, 0.05), (0.3, -0.2)),
    (TrueFacet(focal_length_x_m=5.33, focal_length_y_m=5.30, twist_mrad_per_m=0.4, slope_error_rms_mrad=1.0,
               slope_error_correlation_m=0.05, surface_seed=11), "buie", ("circle", 0.03), (-0.5, 0.4)),
]


@pytest.mark.parametrize("case", range(len(CASES)), ids=["pillbox-circle", "gaussian-rectangle-dent", "buie-circle"])
def test_the_trace_agrees_with_rays_traced_one_by_one(case):
    """Three rough facets (slope errors 0.5-1.5 mrad, focal errors, twist, a dent; turned about the alignment
    point as a boresight would), three sun shapes, both aperture shapes: the twin's trace against 2^18 rays
    traced one by one in this test.

    Tolerances: the rays' own standard errors, from 8 batches of 2^15 (1.5e-4 to 1e-3 in the intercept and 1e-3
    relative in the radius; their spread over the batches divided by sqrt(8)), four and a half times, plus the
    trace's first-order neglect (micrometres on the plane, under 1e-4 of either figure).
    """
    facet, sun, aperture, turned = CASES[case]
    rotation = Rotation.from_euler("YX", [turned[1] * 1e-3, turned[0] * 1e-3]).as_matrix()
    pivot = np.array([*DISH.alignment_point_m, float(DISH.z(*DISH.alignment_point_m))])
    got = _figures(facet, DISH, Sunlight(sun=sun, aperture=aperture), rotation, pivot)
    batches = [_rays_one_by_one(facet, DISH, sun, aperture, turned, 2 ** 15, seed) for seed in range(8)]
    for key, floor in (("intercept", 1e-4), ("spot_radius_m", 1e-4 * got["spot_radius_m"])):
        values = np.array([b[key] for b in batches])
        error = values.std(ddof=1) / math.sqrt(len(values))
        assert abs(got[key] - values.mean()) <= 4.5 * error + floor, (key, got[key], values.mean(), error)
    for axis in ("x", "y"):
        values = np.array([b[axis] for b in batches])
        error = values.std(ddof=1) / math.sqrt(len(values))
        assert abs(got["centroid_m"][axis] - values.mean()) <= 4.5 * error + 1e-6, (axis, error)


# ------------------------------------------------------------------------------------------- the sun
@pytest.mark.parametrize("sun", ["pillbox", "gaussian", "buie"])
def test_the_suns_power_within_an_angle_follows_its_shape(sun):
    """The share of the sun's power within theta against its radiance integrated here by adaptive quadrature
    (scipy's quad, 1e-10): within 2e-5 (the trace's Buie table is linear between 9-urad cells of its disc)."""
    sunlight = Sunlight(sun=sun, sigma_mrad=2.0, csr=0.1)
    kappa = 0.9 * math.log(13.5 * 0.1) * 0.1 ** -0.3
    gamma = 2.2 * math.log(0.52 * 0.1) * 0.1 ** 0.43 - 0.1
    radiance = {"pillbox": lambda t: 1.0 if t <= 4.65 else 0.0,
                "gaussian": lambda t: math.exp(-0.5 * (t / 2.0) ** 2),
                "buie": lambda t: (math.cos(0.326 * t) / math.cos(0.308 * t) if t <= 4.65
                                   else math.exp(kappa) * t ** gamma if t <= 43.6 else 0.0)}[sun]
    breaks = [0.0, 4.65, 43.6, 60.0]

    def within(t_mrad):
        return sum(quad(lambda t: radiance(t) * t, a, min(b, t_mrad), epsabs=1e-12, epsrel=1e-10)[0]
                   for a, b in zip(breaks, breaks[1:]) if a < t_mrad)

    total = within(60.0)
    for t_mrad in (0.5, 2.0, 4.0, 4.6, 5.0, 8.0, 20.0, 43.0):
        assert float(sun_share_within(sunlight, 1e-3 * t_mrad)) == pytest.approx(within(t_mrad) / total, abs=2e-5)


# ------------------------------------------------------------------------------------------- the record
def test_the_same_facet_gives_the_same_bits():
    facet = CASES[0][0]
    a, b = (_figures(facet, DISH, Sunlight(aperture=("circle", 0.026))) for _ in range(2))
    assert a == b
    assert _figures(facet, DISH, Sunlight(aperture=("circle", 0.026), seed=2)) != a


@pytest.mark.parametrize("change, message", [
    ({"sun": "square"}, "sun must be one of"),
    ({"csr": 1.5}, "csr must lie between 0 and 1"),
    ({"reflectivity": 0.0}, "reflectivity must lie in (0, 1]"),
    ({"incidence_angle_deg": 95.0}, "incidence_angle_deg must lie in [0, 90)"),
    ({"aperture": ("circle", -1.0)}, "aperture must be"),
    ({"samples": 10}, "samples must be a whole number of at least 256"),
])
def test_bad_sunlight_is_refused_naming_what(change, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        dataclasses.replace(Sunlight(), **change)
