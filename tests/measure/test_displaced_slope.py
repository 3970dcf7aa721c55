"""The budget's rows measured about a displaced point (budget.displaced_slope_squared), on a synthetic population
whose truth is known: a figure's response to six inputs, each g z + q z^2 in its standard normal error z, the
sensitivities taken as the station takes them (central differences of one standard deviation about the
measured point, which the errors have moved from the truth), U = 2 sqrt(sum of the rows + 2 sum q^2 + (sum q)^2)
as budget.combine states it. 20,000 captures per case.

A figure any error raises (g = 0, a slope RMS with no true gradient) had U about 1.4 times its errors' root mean
square (RMS of error / (U / 2) 0.73); with the excess taken out of the rows' sum, 0.86 (its errors' distribution
is a sum of squares, so a U that follows each capture's own rows still reads high on it: the clip at 0 brings back
some of what it takes out); a linear figure (q = 0) is unchanged and covered 95 %."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.measure.uncertainty.budget import displaced_slope_squared


def _population(g, q, n=20_000, seed=0):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, g.size))
    error = (g * z + q * z * z).sum(axis=1)

    def response(x):
        return g * x + q * x * x

    # per capture and input: the central difference and the curvature part about the measured point z
    linear = (response(z + 1.0) - response(z - 1.0)) / 2.0
    curvature = 0.5 * (response(z + 1.0) + response(z - 1.0)) - response(z)
    return error, linear, curvature


def _ratio(error, rows2, curvature):
    half_u = np.sqrt(rows2 + 2.0 * np.sum(curvature ** 2, axis=1) + np.sum(curvature, axis=1) ** 2)
    r = error / half_u
    return float(np.sqrt(np.mean(r * r))), float(np.mean(np.abs(r) <= 2.0))


@pytest.mark.parametrize("g_scale", [0.0, 0.3])
def test_a_figure_any_error_raises_gets_the_u_of_its_spread(g_scale):
    q = np.array([1.0, 0.6, 1.4, 0.8, 1.2, 0.5])
    error, linear, curvature = _population(np.full(6, g_scale), q)
    own = np.ones(6, bool)
    rows = np.array([displaced_slope_squared(c[:, None], k[:, None], own)[:, 0].sum()
                     for c, k in zip(linear, curvature)])
    plain = np.sum(linear ** 2, axis=1)
    corrected, _ = _ratio(error, rows, curvature)
    before, _ = _ratio(error, plain, curvature)
    assert before < 0.78
    assert 0.82 <= corrected <= 1.0
    assert corrected > before + 0.08


def test_a_linear_figure_and_mixed_rows_are_left_alone():
    g = np.array([1.0, -0.5, 0.7, 0.2, 1.1, -0.9])
    error, linear, curvature = _population(g, np.zeros(6), n=4000)
    own = np.ones(6, bool)
    rows = np.array([displaced_slope_squared(c[:, None], k[:, None], own)[:, 0].sum()
                     for c, k in zip(linear, curvature)])
    np.testing.assert_allclose(rows, np.sum(linear ** 2, axis=1))
    ratio, cover = _ratio(error, rows, curvature)
    assert abs(ratio - 1.0) < 0.05 and abs(cover - 0.95) < 0.015
    # rows mixed by a covariance (own False) keep their squares whatever their curvature
    c, k = np.array([[2.0], [3.0]]), np.array([[1.0], [1.0]])
    out = displaced_slope_squared(c, k, np.array([False, True]))
    assert out[0, 0] == 4.0 and out[1, 0] == pytest.approx(9.0 - 4.0)
