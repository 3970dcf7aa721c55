"""The twin's Gaussian noise (Box-Muller on the generator's raw words) is standard normal: moments, tail
fractions against the normal's, no correlation between neighbours or between the two deviates of a pair."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sofast_station.twin.noise import standard_normal_f32

N = 2_000_001          # odd: the last pair gives one deviate


def test_deviates_are_standard_normal():
    z32 = standard_normal_f32(np.random.default_rng(5), N)
    assert z32.dtype == np.float32 and z32.size == N and np.all(np.isfinite(z32))
    z = z32.astype(np.float64)
    se = 1.0 / math.sqrt(N)
    assert abs(z.mean()) < 5 * se
    assert z.std() == pytest.approx(1.0, abs=5 * se)
    assert ((z - z.mean()) ** 4).mean() / z.var() ** 2 == pytest.approx(3.0, abs=5 * math.sqrt(96 / N))
    assert abs(np.mean(z ** 3)) < 5 * math.sqrt(15 / N)
    for k in (0.5, 1.0, 2.0, 3.0, 4.0):
        p = math.erfc(k / math.sqrt(2))           # P(|z| > k) of a standard normal
        observed = np.count_nonzero(np.abs(z) > k) / N
        assert abs(observed - p) < 5 * math.sqrt(p * (1 - p) / N) + 1e-6, k
    assert np.abs(z).max() <= math.sqrt(-2 * math.log(2.0 ** -33)) + 1e-4
    m = (N + 1) // 2
    # the cosine and sine deviates of one pair, and raster neighbours, are uncorrelated
    assert abs(np.corrcoef(z[:N - m], z[m:])[0, 1]) < 5 * se * math.sqrt(2)
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 5 * se


def test_same_state_same_deviates_and_sizes():
    a = standard_normal_f32(np.random.default_rng(9), 1001)
    assert a.dtype == np.float32 and a.shape == (1001,)
    assert np.array_equal(a, standard_normal_f32(np.random.default_rng(9), 1001))
    assert not np.array_equal(a, standard_normal_f32(np.random.default_rng(10), 1001))
    assert standard_normal_f32(np.random.default_rng(1), 0).size == 0
    assert standard_normal_f32(np.random.default_rng(1), 1).size == 1
