"""The optical figures' uncertainty parts: the trace's own Monte Carlo error and the re-trace sensitivities."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.facet import FacetDesign
from sofast_station.optics import Aperture, OpticsSettings, design_samples, make_scene, trace_surface
from sofast_station.optics.uncertainty import optics_sensitivities, sampling_u

DISH = FacetDesign.from_dict({"name": "dish", "kind": "dish", "focal_length_m": 5.33,
                              "outline_m": [[0.3, -0.3], [0.3, 0.3], [-0.3, 0.3], [-0.3, -0.3]]})


@pytest.fixture(scope="module")
def rough_dish():
    """The design dish with 1 mrad of random slope error (fixed), under a 24 mm aperture that clips its spot."""
    settings = OpticsSettings(aperture=Aperture("circle", radius_m=0.024), design_points=20_000)
    points, slopes, areas = design_samples(DISH, 20_000)
    slopes = slopes + np.random.default_rng(3).normal(0.0, 1e-3, slopes.shape)
    return settings, make_scene(DISH, settings), points, slopes, areas


def test_sampling_error_matches_the_spread_over_seeds(rough_dish):
    """The delta-method sampling error of one trace agrees with the spread of 12 traces with other seeds."""
    settings, scene, points, slopes, areas = rough_dish
    figs, predicted = [], []
    for seed in range(12):
        s = OpticsSettings(aperture=settings.aperture, seed=100 + seed)
        tr = trace_surface(points, slopes, areas, scene, s, rays_per_point=2.0)
        figs.append(tr.figures)
        predicted.append(sampling_u(tr.hits, tr.figures, scene.aperture, scene.target.slant_range_m))
    for key, get in (("intercept", lambda f: f["intercept"]), ("spot_radius_m", lambda f: f["spot_radius_m"]),
                     ("centroid_x_m", lambda f: f["centroid_m"]["x"])):
        spread = np.std([get(f) for f in figs], ddof=1)
        u = np.median([p[key] for p in predicted])
        assert 0.0 < u and 0.5 < spread / u < 1.6, (key, spread, u)


def test_sensitivities_have_the_signs_physics_gives(rough_dish):
    """More slope error widens the spot and spills power; a focal power step changes the spot's size but
    hardly moves a centred dish's centroid (the curvature turns the slopes about the alignment point)."""
    settings, scene, points, slopes, areas = rough_dish
    design = trace_surface(*design_samples(DISH, 20_000), scene, settings, seed_offset=1, rays_per_point=1.0)
    sens = optics_sensitivities(points, slopes, areas, DISH, settings, scene, design.figures, 1.0)
    c_r, _ = sens["slope RMS"]["spot_radius_m"]
    c_i, _ = sens["slope RMS"]["intercept"]
    assert c_r > 0 and c_i < 0
    spot_mrad = 1000.0 / 5.33 * sens["curvature x"]["spot_radius_m"][0]
    centroid_mrad = sens["curvature x"]["centroid_offset_mrad.x"][0]
    assert spot_mrad != 0.0 and abs(centroid_mrad) < 0.05 * abs(spot_mrad), (spot_mrad, centroid_mrad)
