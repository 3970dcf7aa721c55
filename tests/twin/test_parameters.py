"""TrueFacet and TwinOptics: validation, unknown keys, round trips."""

from __future__ import annotations

import math

import pytest

from sofast_station.errors import ConfigError
from sofast_station.twin import TrueFacet, TwinOptics

from .conftest import RICH_FACET


def test_true_facet_round_trip_and_infinite_focal_length():
    assert TrueFacet.from_dict(RICH_FACET.to_dict()) == RICH_FACET
    flat = TrueFacet.from_dict({"focal_length_x_m": "inf", "focal_length_y_m": math.inf})
    assert flat.focal_length_x_m == math.inf and flat.focal_length_y_m == math.inf
    assert TrueFacet.from_dict(flat.to_dict()) == flat


@pytest.mark.parametrize("cls, data, key", [
    (TrueFacet, {"focal_lenght_x_m": 5.0}, "focal_lenght_x_m"),
    (TwinOptics, {"gama": 2.2}, "gama"),
    (TrueFacet, {"dents": [{"x_m": 0, "y_m": 0, "depth_m": 1e-5, "radius_m": 0.01, "sigma": 1}]}, "sigma"),
])
def test_unknown_keys_are_named(cls, data, key):
    with pytest.raises(ConfigError, match=key):
        cls.from_dict(data)


@pytest.mark.parametrize("cls, data", [
    (TrueFacet, {"focal_length_x_m": 0.0}),
    (TrueFacet, {"placement_mm": [1, 2]}),
    (TrueFacet, {"dents": [{"x_m": 0, "y_m": 0, "depth_m": 1e-5, "radius_m": -0.01}]}),
    (TrueFacet, {"slope_error_rms_mrad": -1}),
    (TwinOptics, {"white_dn": 3.0}),
    (TwinOptics, {"knee_dn": 300.0}),
    (TwinOptics, {"reflectance": "high"}),
    (TwinOptics, {"screen_grid": 0}),
    (TwinOptics, {"screen_grid": 9}),
    (TwinOptics, {"screen_grid": 2.5}),
])
def test_invalid_values_raise_config_error(cls, data):
    with pytest.raises(ConfigError, match=next(iter(data)) if "screen_grid" in data else None):
        cls.from_dict(data)


def test_optics_round_trip_and_noise_free():
    optics = TwinOptics(knee_dn=220.0, read_noise_dn=1.5)
    assert TwinOptics.from_dict(optics.to_dict()) == optics
    quiet = optics.noise_free()
    assert quiet.knee_dn == 220.0 and not quiet.has_noise
    assert quiet.read_noise_dn == quiet.electrons_per_dn == quiet.ambient_jitter == 0.0
    assert TwinOptics.noise_free() == TwinOptics(read_noise_dn=0.0, electrons_per_dn=0.0, ambient_jitter=0.0)
    assert TwinOptics().has_noise
