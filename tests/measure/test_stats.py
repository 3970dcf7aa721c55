"""The fast order statistics give numpy's numbers bit for bit (measure/stats.py)."""

import numpy as np
import pytest

from sofast_station.measure.stats import median, quantile


@pytest.mark.parametrize("kind", ["normal", "ties", "float32", "positive"])
def test_median_and_quantile_are_numpys_bits(kind):
    rng = np.random.default_rng(7)
    for _ in range(60):
        n = int(rng.integers(60, 3000))
        x = rng.normal(size=n)
        if kind == "ties":
            x = np.round(3 * x)
        elif kind == "float32":
            x = x.astype(np.float32)
        elif kind == "positive":
            x = np.abs(x)
        assert median(x) == float(np.median(x))
        if x.dtype == np.float64:
            for q in (0.0, 0.01, 0.5, 0.6827, 0.99, 1.0, float(rng.random())):
                assert quantile(x, q) == float(np.quantile(x, q)), (n, q)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int16, np.int32])
def test_integer_quantiles_by_counting_are_numpys(dtype):
    rng = np.random.default_rng(3)
    low = -40 if np.issubdtype(dtype, np.signedinteger) else 0
    for n in (70, 1001, 200_000):
        x = rng.integers(low, 250, size=n).astype(dtype)
        for q in (0.0, 0.01, 0.5, 0.6827, 0.99, 1.0):
            assert quantile(x, q) == float(np.quantile(x, q)), (dtype, n, q)


def test_nan_gives_nan_as_numpy():
    x = np.random.default_rng(1).normal(size=501)
    x[3] = np.nan
    assert np.isnan(median(x)) and np.isnan(np.median(x))
    assert np.isnan(quantile(x, 0.2)) and np.isnan(np.quantile(x, 0.2))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_camera_count_quantiles_from_the_histogram_are_numpys(dtype, monkeypatch):
    """Unsigned counts over the whole range, with heavy ties at both ends (clipped black and saturated
    pixels), counted in several histogram chunks."""
    from sofast_station.measure import stats

    monkeypatch.setattr(stats, "_HIST_CHUNK", 4096)
    rng = np.random.default_rng(5)
    top = np.iinfo(dtype).max
    for n in (65, 5000, 30_001):
        x = rng.integers(0, top + 1, size=n).astype(dtype)
        x[: n // 4] = 0
        x[n // 4: n // 3] = top
        rng.shuffle(x)
        for q in (0.0, 0.01, 0.25, 0.2501, 0.5, 0.6827, 0.99, 1.0, float(rng.random())):
            assert quantile(x, q) == float(np.quantile(x, q)), (dtype, n, q)
        strided = x[: n - n % 5].reshape(5, -1)[:, ::2]      # not contiguous
        assert quantile(strided, 0.3) == float(np.quantile(strided, 0.3))


def _neighbour_ms_by_image(values, flat_idx, width_px, height_px):
    """The definition, written out on the image: every pair of valid neighbours, right then below."""
    img = np.full(width_px * height_px, np.nan)
    img[flat_idx] = values
    img = img.reshape(height_px, width_px)
    right = (img[:, 1:] - img[:, :-1]).ravel()
    below = (img[1:, :] - img[:-1, :]).ravel()
    d = np.concatenate([right[np.isfinite(right)], below[np.isfinite(below)]])
    return float(np.mean(d * d)) if d.size else 0.0


@pytest.mark.parametrize("seed", range(5))
def test_neighbour_difference_from_the_pairs_is_the_image_definition(seed):
    from sofast_station.measure.metrics import neighbour_difference_ms, neighbour_pairs

    rng = np.random.default_rng(seed)
    w, h = int(rng.integers(3, 40)), int(rng.integers(3, 40))
    keep = rng.random(w * h) < rng.uniform(0.3, 0.95)
    flat = np.flatnonzero(keep)
    pairs = neighbour_pairs(flat, w)
    for _ in range(3):                  # one set of pairs serves any number of value arrays
        v = rng.normal(size=flat.size)
        assert neighbour_difference_ms(v, pairs) == pytest.approx(_neighbour_ms_by_image(v, flat, w, h), rel=1e-12)
    assert neighbour_difference_ms(np.ones(1), neighbour_pairs(np.array([5]), w)) == 0.0
    assert neighbour_difference_ms(np.ones(0), neighbour_pairs(np.array([], dtype=int), w)) == 0.0
