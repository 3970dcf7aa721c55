"""The field's frames and the sun: round trips, the twin's independent writing of the same conventions,
and the commanded normal against the law of reflection."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sofast_station.errors import ConfigError, GeometryError
from sofast_station.field.geometry import (azimuth_elevation, direction, heliostat_angles, heliostat_rotation, look_at,
                                           pointing_error_mrad)
from sofast_station.field.sun import commanded_normal, parse_time, sun_direction, sun_position
from sofast_station.twin.field import camera_rotation, heliostat_to_field


def test_directions_and_heliostat_frames_round_trip():
    """Exact inverses (to 1e-12 rad), and a heliostat's x axis level before its spin (docs/field.md#frames)."""
    rng = np.random.default_rng(0)
    for _ in range(20):
        az, el, spin = rng.uniform(0, 2 * math.pi), rng.uniform(-1.2, 1.5), rng.uniform(-0.1, 0.1)
        assert np.allclose(azimuth_elevation(direction(az, el)), (az, el), atol=1e-12)
        r = heliostat_rotation(az, el, spin)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12) and np.linalg.det(r) > 0
        assert np.allclose(heliostat_angles(r), (az, el, spin), atol=1e-12)
        assert abs(heliostat_rotation(az, el)[2, 0]) < 1e-12          # x level without spin


def test_the_twin_writes_the_same_frames_independently():
    """The twin's heliostat and camera frames (its own code) equal the field package's for the same angles:
    the documented convention is one, written twice."""
    rng = np.random.default_rng(1)
    for _ in range(10):
        az, el, spin = rng.uniform(0, 2 * math.pi), rng.uniform(0.1, 1.4), rng.uniform(-0.05, 0.05)
        assert np.allclose(heliostat_rotation(az, el, spin), heliostat_to_field(az, el, spin), atol=1e-12)
        cam, target, roll = rng.normal(0, 10, 3) + [0, 0, 50], rng.normal(0, 50, 3), rng.uniform(-0.01, 0.01)
        assert np.allclose(look_at(cam, target, roll), camera_rotation(cam, target, roll), atol=1e-12)
    # a level camera looking north: image columns run east, rows down
    r = look_at([0, 0, 0], [0, 10, 0])
    assert np.allclose(r[0], [1, 0, 0]) and np.allclose(r[1], [0, 0, -1])


def test_pointing_error_components():
    """A normal moved by 2 mrad up and 3 mrad east on the sky reads (3, 2) mrad, angle sqrt(13)."""
    az, el = 3.0, 0.6
    moved = direction(az + 3e-3 / math.cos(el), el + 2e-3)
    e = pointing_error_mrad(moved, direction(az, el))
    assert e["azimuth_mrad"] == pytest.approx(3.0, abs=0.01) and e["elevation_mrad"] == pytest.approx(2.0, abs=1e-9)
    assert e["angle_mrad"] == pytest.approx(math.sqrt(13.0), abs=0.01)


def test_sun_at_equinox_noon_stands_at_the_colatitude():
    """At solar noon of the March equinox the sun stands due south at 90 deg less the latitude (declination
    about 0.1 deg that day, refraction under 0.02 deg at that height): pvlib within 0.3 deg of it."""
    lat, lon = 37.094, -2.359
    # solar noon: 12:00 UTC less the longitude (4 min per degree) less the equation of time (+7.5 min on 21 March)
    noon = f"2027-03-21T12:{int(round(-lon * 4 + 7.5)):02d}:00+00:00"
    az, el = np.degrees(sun_position([noon], lat, lon, 500.0)[0])
    assert az == pytest.approx(180.0, abs=1.0) and el == pytest.approx(90.0 - lat, abs=0.3)
    assert np.allclose(sun_direction(noon, lat, lon, 500.0), direction(*np.radians([az, el])), atol=1e-12)


def test_commanded_normal_reflects_the_sun_onto_the_aim_point():
    """The law of reflection: the sun's direction mirrored in the commanded normal points at the aim point."""
    rng = np.random.default_rng(2)
    for _ in range(10):
        sun = direction(rng.uniform(0, 2 * math.pi), rng.uniform(0.2, 1.4))
        helio, aim = np.append(rng.uniform(-200, 200, 2), 2.0), np.array([0.0, 0.0, 60.0])
        n = commanded_normal(sun, helio, aim)
        out = 2 * (sun @ n) * n - sun
        assert np.allclose(out, (aim - helio) / np.linalg.norm(aim - helio), atol=1e-12)


def test_times_without_a_zone_and_a_sun_below_the_horizon_are_refused():
    with pytest.raises(ConfigError, match="no time zone"):
        parse_time("2027-03-21T10:00:00")
    with pytest.raises(ConfigError, match="ISO 8601"):
        parse_time("yesterday")
    with pytest.raises(GeometryError, match="below the horizon"):
        sun_direction("2027-03-21T00:00:00+00:00", 37.0, -2.4)
