"""The ray trace against first principles: the sun's image of a perfect paraboloid, energy, sun shapes.

Truth here never comes from the code under test: the image of a perfect paraboloid is computed from its
geometry (each point images the sun's disc at its distance to the focus, stretched by the tilt of the
focal plane), the Buie profile is integrated with scipy's quadrature from the published formula.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate

from sofast_station.facet import FacetDesign
from sofast_station.optics import (Aperture, OpticsSettings, SunShape, design_samples, design_trace, facet_optics,
                                   make_scene, trace_surface)
from sofast_station.optics.sun import buie_power_fraction_outside_disc

THETA_SUN = 4.65e-3
F = 5.33
HALF = 0.3            # the dish fixture's facet: 0.6 m square


def dish(f=F, half=HALF) -> FacetDesign:
    return FacetDesign(name="dish", kind="dish", focal_length_m=f,
                       outline_m=[[half, -half], [half, half], [-half, half], [-half, -half]],
                       measure_point_m=[0, 0], alignment_point_m=[0, 0])


def image_radius_bounds(f, rho_max):
    """Smallest and largest edge radius of the sun's image on the focal plane of a perfect paraboloid.

    A point at radius rho (height z = rho^2 / 4f) is D = f + z from the focus and sees it at an angle phi
    from the axis, sin(phi) = rho / D. A ray deviating by the sun's half-angle lands D theta from the focus
    across the radial plane and D theta / cos(phi) along it (the focal plane is tilted by phi against
    the ray). So every ray lands within f theta (1 + rho^2/4f^2) / cos(phi) of the focus, and the
    vertex images a disc of exactly f theta: the off-axis terms grow as rho^2 / f^2.
    """
    d = f + rho_max ** 2 / (4 * f)
    cos_phi = math.sqrt(1 - (rho_max / d) ** 2)
    return f * THETA_SUN, d * THETA_SUN / cos_phi


def test_perfect_paraboloid_images_the_sun_as_a_disc_of_radius_f_theta():
    design = dish()
    settings = OpticsSettings(sun=SunShape("pillbox"), design_points=60_000, grid_cells=121)
    scene = make_scene(design, settings)
    tr = design_trace(design, settings, scene)
    r_min, r_max = image_radius_bounds(F, HALF * math.sqrt(2))
    assert (r_max / r_min - 1) < 0.006                       # the off-axis terms for this facet: < 0.6 %
    r = np.hypot(tr.hits.x_m, tr.hits.y_m)
    assert r.max() <= r_max * 1.0005                          # nothing outside the largest disc
    assert np.quantile(r, 0.999) >= r_min * 0.995             # and the disc is filled to its edge
    # A uniform disc holds 90 % within sqrt(0.9) of its radius.
    assert tr.figures["spot_radius_m"] == pytest.approx(math.sqrt(0.9) * F * THETA_SUN, rel=0.006)
    # Centred on the aim point (the focus).
    assert abs(tr.figures["centroid_m"]["x"]) < 1e-4 and abs(tr.figures["centroid_m"]["y"]) < 1e-4
    # Uniform irradiance inside: power / (pi R^2) in the middle of the disc.
    cells = settings.grid_cells
    w = 2 * scene.grid_half_width_m / cells
    c = (np.arange(cells) + 0.5) * w - scene.grid_half_width_m
    xx, yy = np.meshgrid(c, c)
    middle = np.hypot(xx, yy) < 0.6 * r_min
    expected = 1000.0 * 0.94 * 0.36 / (math.pi * (F * THETA_SUN) ** 2)
    assert tr.flux_w_m2[middle].mean() == pytest.approx(expected, rel=0.02)


def test_intercept_is_one_for_an_aperture_just_larger_than_the_sun_image():
    design = dish()
    _, r_max = image_radius_bounds(F, HALF * math.sqrt(2))
    just_larger = OpticsSettings(aperture=Aperture("circle", radius_m=1.001 * r_max), design_points=40_000)
    assert design_trace(design, just_larger).figures["intercept"] == 1.0
    # Half the area of the disc holds half the power (less a little: the off-axis stretch).
    half = OpticsSettings(aperture=Aperture("circle", radius_m=F * THETA_SUN / math.sqrt(2)), design_points=40_000)
    assert design_trace(design, half).figures["intercept"] == pytest.approx(0.5, abs=0.006)
    square = OpticsSettings(aperture=Aperture("rectangle", width_m=2.002 * r_max, height_m=2.002 * r_max),
                            design_points=40_000)
    assert design_trace(design, square).figures["intercept"] == 1.0


@pytest.mark.parametrize("incidence_deg", [0.0, 30.0])
def test_energy_is_conserved(incidence_deg):
    """Power on the target (map plus what fell off it) = DNI x reflectivity x projected area x cos(incidence).

    For a paraboloid centred on its vertex, the integral of cos(theta_i) dA over the surface is the outline's
    area times cos(incidence): the normals' x components cancel between +x and -x.
    """
    design = dish()
    settings = OpticsSettings(incidence_angle_deg=incidence_deg, dni_w_m2=950.0, reflectivity=0.9,
                              design_points=30_000, grid_cells=101)
    scene = make_scene(design, settings)
    tr = design_trace(design, settings, scene)
    w = 2 * scene.grid_half_width_m / settings.grid_cells
    on_map = tr.flux_w_m2.sum() * w * w
    expected = 950.0 * 0.9 * 0.36 * math.cos(math.radians(incidence_deg))
    assert on_map + tr.off_grid_w == pytest.approx(expected, rel=1e-6)
    assert tr.figures["reflected_w"] == pytest.approx(expected, rel=1e-6)        # float32 cosines
    assert tr.figures["incident_w"] == pytest.approx(expected / 0.9, rel=1e-6)


def test_off_axis_incidence_spreads_the_tangential_image():
    """At incidence i a paraboloid of focal length f is astigmatic: its tangential and sagittal foci lie near
    f cos(i) and f / cos(i) (the mirror's local radius is 2f), so on the plane at L = f the 0.6 m facet's
    beam is about 0.3 m x (1 - cos 30 deg) = 40 mm wide on either side of the aim point, against the sun
    image's 25 mm: the 90 % radius must grow by more than half."""
    design = dish()
    on = design_trace(design, OpticsSettings(design_points=20_000)).figures["spot_radius_m"]
    off = design_trace(design, OpticsSettings(incidence_angle_deg=30.0, design_points=20_000)).figures["spot_radius_m"]
    assert off > 1.5 * on


def test_the_trace_is_deterministic_for_a_seed():
    design = dish()
    points, slopes, areas = design_samples(design, 5000)
    s1 = OpticsSettings(seed=3, design_points=5000)
    scene = make_scene(design, s1)
    a = trace_surface(points, slopes, areas, scene, s1)
    b = trace_surface(points, slopes, areas, scene, s1)
    c = trace_surface(points, slopes, areas, scene, OpticsSettings(seed=4, design_points=5000))
    assert np.array_equal(a.flux_w_m2, b.flux_w_m2) and a.figures == b.figures
    assert not np.array_equal(a.flux_w_m2, c.flux_w_m2)


def test_sun_shapes_have_their_published_radial_distributions():
    rng = np.random.default_rng(0)
    n = 400_000
    theta, _ = SunShape("pillbox").sample(n, rng)
    assert theta.max() <= THETA_SUN
    assert np.mean(theta < THETA_SUN / 2) == pytest.approx(0.25, abs=0.003)    # uniform over the disc
    theta, phi = SunShape("gaussian", sigma_mrad=3.0).sample(n, rng)
    dx = theta * np.cos(phi)
    assert np.std(dx) == pytest.approx(3e-3, rel=0.01)
    assert np.std(theta * np.sin(phi)) == pytest.approx(3e-3, rel=0.01)

    csr = 0.1
    k = 0.9 * math.log(13.5 * csr) * csr ** -0.3
    g = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1

    def radiance(t_mrad):       # Buie et al. 2003, written out here independently
        if t_mrad <= 4.65:
            return math.cos(0.326 * t_mrad) / math.cos(0.308 * t_mrad)
        return math.exp(k) * t_mrad ** g

    disc = integrate.quad(lambda t: radiance(t) * t, 0, 4.65)[0]
    aureole = integrate.quad(lambda t: radiance(t) * t, 4.65, 43.6, limit=200)[0]
    truth = aureole / (disc + aureole)
    theta, _ = SunShape("buie", csr=csr).sample(n, rng)
    assert np.mean(theta > THETA_SUN) == pytest.approx(truth, abs=0.002)
    assert buie_power_fraction_outside_disc(csr) == pytest.approx(truth, rel=0.01)
    assert theta.max() <= 43.6e-3
    # Limb darkening: inside the disc the radiance falls from the centre to the edge.
    inner = np.mean(theta < 2.325e-3) / np.mean(theta < THETA_SUN)
    assert inner > 0.25


def test_facet_optics_on_the_design_itself_gives_the_design_figures():
    design = dish()
    settings = OpticsSettings(design_points=20_000)
    points, slopes, _ = design_samples(design, 20_000)
    res = facet_optics(points, slopes, np.array([0.0, 0.0, 2 * F]), design, settings, slope_error_mrad=0.0,
                       focal_power_per_m=1 / F)
    f = res.figures
    assert f["power_ratio_vs_design"] == pytest.approx(1.0, abs=2e-3)
    assert f["spot_radius_m"] == pytest.approx(f["design"]["spot_radius_m"], rel=0.01)
    assert f["intercept"] == f["design"]["intercept"] == 1.0
    assert f["analytic_spot_radius_m"] == pytest.approx(math.sqrt(0.9) * F * math.tan(THETA_SUN), rel=1e-12)
