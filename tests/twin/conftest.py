"""Shared fixtures for the digital-twin tests: the default dish facet and station geometry, traced stations.

Tracing a full-resolution station takes one to three seconds, so the traced stations are session-scoped.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sofast_station.facet import load_facet
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.twin import TrueFacet, TwinOptics, TwinStation

REPO = Path(__file__).resolve().parents[2]

RICH_FACET = TrueFacet(
    focal_length_x_m=5.40, focal_length_y_m=5.30, twist_mrad_per_m=0.3,
    placement_mm=(1.5, -2.0, 3.0), placement_mrad=(1.0, -0.8, 2.0),
    cubic_per_m2=(2e-4, -1e-4, 5e-5, 1.5e-4),
    dents=({"x_m": 0.1, "y_m": -0.12, "depth_m": -2e-5, "radius_m": 0.02},
           {"x_m": -0.15, "y_m": 0.05, "depth_m": 1e-5, "radius_m": 0.03}),
    slope_error_rms_mrad=0.5, slope_error_correlation_m=0.02, surface_seed=11)


@pytest.fixture(scope="session")
def design():
    return load_facet(REPO / "fixtures" / "facets" / "dish_5m33.toml")


@pytest.fixture(scope="session")
def camera_intrinsics():
    return CameraIntrinsics(1600, 1200, [[13636, 0, 799.5], [0, 13636, 599.5], [0, 0, 1]],
                            [-0.05, 0.1, 0.0002, -0.0001, 0.0])


@pytest.fixture(scope="session")
def geometry(design, camera_intrinsics):
    return layout_station(design, camera_intrinsics, ScreenSpec(1920, 1080, 0.000275), separation_m=0.34)


@pytest.fixture(scope="session")
def rich_station(geometry, design):
    """Every shape term and a placement error: the geometry tests' station."""
    return TwinStation(geometry, design, RICH_FACET, TwinOptics.noise_free())


@pytest.fixture(scope="session")
def parabola_station(geometry, design):
    """A pure paraboloid with known focal lengths and twist, slightly misplaced."""
    facet = TrueFacet(focal_length_x_m=5.42, focal_length_y_m=5.35, twist_mrad_per_m=0.1,
                      placement_mm=(0.5, -0.3, 1.0), placement_mrad=(0.4, -0.2, 0.3))
    return TwinStation(geometry, design, facet, TwinOptics.noise_free())


@pytest.fixture(scope="session")
def flat_station(geometry, design):
    """A flat mirror (infinite focal length) at a known tilt and offset."""
    facet = TrueFacet(focal_length_x_m=math.inf, focal_length_y_m=math.inf,
                      placement_mm=(2.0, -1.0, 5.0), placement_mrad=(4.0, -3.0, 2.0))
    return TwinStation(geometry, design, facet, TwinOptics.noise_free())
