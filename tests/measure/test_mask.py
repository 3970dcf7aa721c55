"""The facet region and the frames' gathering by OpenCV and slice copies give the plain numpy results."""

import cv2
import numpy as np
import pytest

from sofast_station.measure import checks
from sofast_station.measure.mask import facet_region
from sofast_station.measure.pipeline import _gather_runs, _runs


def numpy_region(dark, white, threshold_dn, max_hole_px=2000):
    """The region by the definition: white - dark > threshold in exact integers, the largest 8-connected
    set, its enclosed 4-connected holes up to max_hole_px filled."""
    responsive = (white.astype(np.int64) - dark.astype(np.int64)) > threshold_dn
    n, labels, stats, _ = cv2.connectedComponentsWithStats(responsive.view(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros(responsive.shape, dtype=bool)
    region = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    padded = np.pad(~region, 1, constant_values=True)
    n_h, labels_h, stats_h, _ = cv2.connectedComponentsWithStats(padded.view(np.uint8), connectivity=4)
    outside = labels_h[0, 0]
    holes = (labels_h != outside) & (labels_h > 0) & (stats_h[labels_h, cv2.CC_STAT_AREA] <= max_hole_px)
    return region | holes[1:-1, 1:-1]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_region_from_clipped_differences_is_the_exact_integer_region(dtype):
    rng = np.random.default_rng(4)
    top = np.iinfo(dtype).max
    for threshold in (0.0, 0.5, 20.0, 20.7, 19.9999999, 254.5, 255.0, 300.0, 65534.5):
        dark = rng.integers(0, top + 1, (90, 120)).astype(dtype)
        white = np.clip(dark.astype(np.int64) + rng.integers(-40, 60, dark.shape), 0, top)
        lit = int(min(threshold, top))
        noise = rng.integers(-2, 3, (50, 70))
        white[20:70, 30:100] = np.clip(dark[20:70, 30:100].astype(np.int64) + lit + noise, 0, top)
        white[40:44, 50:53] = dark[40:44, 50:53]                  # a hole
        white = white.astype(dtype)
        assert np.array_equal(facet_region(dark, white, threshold), numpy_region(dark, white, threshold)), threshold


def test_masked_means_and_run_gathering_are_numpys():
    rng = np.random.default_rng(8)
    for dtype in (np.uint8, np.uint16, np.int16):
        sample = rng.integers(0, 200, (6, 5001)).astype(dtype)
        mask = rng.random(5001) < 0.3
        assert np.array_equal(checks._masked_means(sample, mask, int(mask.sum())),
                              sample[:, mask].mean(axis=1, dtype=np.float64))
    frames = rng.integers(0, 255, (5, 40, 50)).astype(np.uint8)
    region = np.zeros((40, 50), bool)
    region[5:30, 10:45] = True
    region[12:15, 20:22] = False
    region[:, 44:] = True                                     # runs that wrap from row to row
    for r in (region, np.zeros_like(region)):
        idx = np.flatnonzero(r)
        out = np.empty((5, idx.size), np.uint8)
        _gather_runs(frames.reshape(5, -1), idx, _runs(idx), out)
        assert np.array_equal(out, frames.reshape(5, -1)[:, idx])
