"""The response fit, floor and top, and the lookup table, on synthetic responses (no devices)."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.calibrate.errors import CalibrationError
from sofast_station.calibrate.radiometric import (build_lut, find_top_and_floor, fit_monotone_response,
                                                  isotonic_increasing)
from sofast_station.calibrate.settings import RadiometricSettings
from sofast_station.errors import ConfigError


def response(v, gamma=2.5, floor=0.03, offset=6.0, gain=240.0):
    return offset + gain * (floor + (1 - floor) * (np.asarray(v, float) / 255) ** gamma)


def test_isotonic_regression_pools_violators():
    assert np.allclose(isotonic_increasing([1, 3, 2, 4]), [1, 2.5, 2.5, 4])
    assert np.allclose(isotonic_increasing([5, 4, 3]), [4, 4, 4])
    y = np.random.default_rng(0).normal(size=50).cumsum()
    iso = isotonic_increasing(y)
    assert np.all(np.diff(iso) >= 0) and iso.mean() == pytest.approx(y.mean())


def test_smooth_response_gets_the_plain_seventh_order_polynomial():
    v = np.arange(10, 256, 5, dtype=float)
    fit = fit_monotone_response(v, response(v), 7)
    assert fit.method == "polynomial" and fit.order == 7
    grid = np.linspace(10, 255, 500)
    assert np.max(np.abs(fit(grid) - response(grid))) < 0.05          # DN, of a 230 DN range


def test_a_wiggling_fit_is_constrained_or_replaced_to_stay_increasing():
    """Nearly flat data with a bump: the unconstrained polynomial turns down somewhere; the result may not."""
    v = np.arange(0, 256, 15, dtype=float)
    r = 10 + 0.02 * v + np.where((v > 100) & (v < 140), 3.0, 0.0)      # a step that a polynomial overshoots
    free = np.polynomial.Chebyshev.fit(v, r, 7, domain=[v[0], v[-1]])
    assert np.any(np.diff(free(np.linspace(0, 255, 2000))) <= 0)
    fit = fit_monotone_response(v, r, 7)
    assert fit.method in ("polynomial-constrained", "pchip-isotonic")
    assert np.all(np.diff(fit(np.linspace(0, 255, 4096))) > 0)
    # and a decreasing stretch in the data itself
    r2 = r.copy()
    r2[5] += 4.0
    fit2 = fit_monotone_response(v, r2, 7)
    assert np.all(np.diff(fit2(np.linspace(0, 255, 4096))) > 0)


def test_floor_is_the_lowest_command_from_which_the_response_rises():
    v = np.arange(0, 256, 5, dtype=float)
    r = response(v)
    sat = np.zeros(v.size)
    top, floor, rise_min = find_top_and_floor(v, r, sat, 0.001, 0.02)
    assert top == v.size - 1
    # the slope at the floor is at least 2 % of the mean slope, and just below it is not
    slope = np.diff(r)
    assert slope[floor] > 0.02 * slope.mean() >= slope[floor - 1] * 0.999
    # noise raises the floor: a step must rise by more than three times its noise
    _, floor_noisy, _ = find_top_and_floor(v, r, sat, 0.001, 0.02, step_noise_dn=0.5)
    assert floor_noisy > floor and slope[floor_noisy] > 1.5


def test_top_stops_below_saturation_and_a_flat_ramp_is_refused():
    v = np.arange(0, 256, 5, dtype=float)
    r = np.minimum(response(v, gain=300), 255.0)
    sat = (r >= 255).astype(float)
    top, floor, _ = find_top_and_floor(v, r, sat, 0.001, 0.02)
    assert r[top] < 255 and sat[top] == 0 and top < v.size - 1
    with pytest.raises(CalibrationError, match="rises over only"):
        find_top_and_floor(v, np.full(v.size, 12.0), np.zeros(v.size), 0.001, 0.02)
    with pytest.raises(CalibrationError, match="saturated"):
        find_top_and_floor(v, r, np.ones(v.size), 0.001, 0.02)


def test_lookup_table_inverts_the_response_between_floor_and_top():
    v = np.arange(0, 256, 5, dtype=float)
    r = response(v)
    fit = fit_monotone_response(v[3:], r[3:], 7)
    lut, floor_level, max_level = build_lut(fit, r[0], 15.0, 255.0, 1024)
    assert max_level == 1.0 and 0 < floor_level < 0.01
    assert np.all(np.diff(lut) >= 0) and lut[0] == 0.0 and lut[-1] == pytest.approx(1.0, abs=1e-6)
    levels = np.linspace(floor_level, 1.0, 200)
    commands = 255 * np.interp(levels, np.linspace(0, 1, lut.size), lut)
    observed = (response(commands) - r[0]) / (response(255.0) - r[0])
    assert np.max(np.abs(observed - levels)) < 2e-4


def test_routine_settings_are_validated_with_the_key_named():
    with pytest.raises(ConfigError, match="ramp_step"):
        RadiometricSettings(ramp_step=0)
    with pytest.raises(ConfigError, match="gain_max"):
        RadiometricSettings(gain_min=2.0, gain_max=1.0)
    with pytest.raises(ConfigError, match="fit_order"):
        RadiometricSettings(fit_order=2.5)
