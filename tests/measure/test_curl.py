"""The slope-curl check (measure/checks.py slope_curl) on a lattice of centres is the every-pixel check."""

import numpy as np
import pytest

from sofast_station.measure.checks import slope_curl


def every_pixel_curl(valid, points_m, slopes, step_m=0.01):
    """The check written out on NaN-filled images, at every pixel (what the lattice must reproduce)."""
    def image(v):
        g = np.full(valid.shape, np.nan)
        g[valid] = v
        return g

    x, y, sx, sy = image(points_m[0]), image(points_m[1]), image(slopes[0]), image(slopes[1])
    spacing = np.concatenate([np.abs(np.diff(x, axis=1)).ravel(), np.abs(np.diff(y, axis=0)).ravel()])
    k = max(1, int(round(step_m / np.median(spacing[np.isfinite(spacing)]))))

    def d_col(f):
        return f[k:-k, 2 * k:] - f[k:-k, :-2 * k]

    def d_row(f):
        return f[2 * k:, k:-k] - f[:-2 * k, k:-k]

    xc, xr, yc, yr = d_col(x), d_row(x), d_col(y), d_row(y)
    with np.errstate(invalid="ignore", divide="ignore"):
        det = xc * yr - xr * yc
        i00, i01, i10, i11 = yr / det, -xr / det, -yc / det, xc / det
        sc, sr, tc, tr = d_col(sx), d_row(sx), d_col(sy), d_row(sy)
        g01, g00 = sc * i01 + sr * i11, sc * i00 + sr * i10
        g10, g11 = tc * i00 + tr * i10, tc * i01 + tr * i11
    ok = np.isfinite(g00) & np.isfinite(g01) & np.isfinite(g10) & np.isfinite(g11)

    def rms(v):
        v = v - np.median(v)
        return float(np.sqrt(np.mean(v * v)))

    a, s, d = (0.5 * (g01 - g10))[ok], (0.5 * (g01 + g10))[ok], (0.5 * (g00 - g11))[ok]
    return {"antisymmetric_rms_per_m": rms(a), "symmetric_rms_per_m": float(np.hypot(rms(s), rms(d)) / np.sqrt(2.0)),
            "step_px": k, "n": int(np.count_nonzero(ok))}


def facet(swapped=False, seed=2, size=360):
    """A round facet seen by a camera (pixel size on the facet changing across the image), slopes of a
    dish with a random smooth height error, and slope noise; *swapped* exchanges and rescales the slope
    components as fringe sets captured in the wrong order do."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    valid = (rows - 0.52 * size) ** 2 + (cols - 0.47 * size) ** 2 < (0.42 * size) ** 2
    valid[100:104, 150:170] = False                      # a scratch
    r, c = rows[valid], cols[valid]
    pitch = 1.2e-3 * (1.0 + 0.15 * c / size)             # metres per pixel, growing along the rows
    x = (c - size / 2) * pitch
    y = (r - size / 2) * 1.25e-3 + 2e-6 * (c - size / 2) ** 2
    # z = dish + sum of a few bumps; slopes are its exact gradient
    sx, sy = x / (2 * 5.4), y / (2 * 5.3)
    for _ in range(12):
        x0, y0 = rng.uniform(-0.18, 0.18), rng.uniform(-0.18, 0.18)
        w, amp = rng.uniform(0.02, 0.06), rng.normal(0, 5e-5)
        bump = amp * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * w * w))
        sx, sy = sx - bump * (x - x0) / (w * w), sy - bump * (y - y0) / (w * w)
    sx, sy = sx + rng.normal(0, 1e-5, sx.size), sy + rng.normal(0, 1e-5, sy.size)
    if swapped:
        sx, sy = 0.9 * sy, 1.1 * sx
    return valid, np.stack([x, y, 1e-3 * x * x]), np.stack([sx, sy])


@pytest.mark.parametrize("swapped", [False, True])
def test_lattice_of_one_pixel_is_the_every_pixel_check_bit_for_bit(swapped):
    valid, points, slopes = facet(swapped)
    got = slope_curl(valid, points, slopes, stride=1)
    want = every_pixel_curl(valid, points, slopes)
    assert got["stride_px"] == 1
    assert {k: got[k] for k in want} == want


def test_lattice_samples_the_same_field_and_tells_swapped_sets():
    results = {}
    for swapped in (False, True):
        valid, points, slopes = facet(swapped)
        full, lattice = slope_curl(valid, points, slopes, stride=1), slope_curl(valid, points, slopes)
        assert lattice["step_px"] == full["step_px"] >= 6
        assert lattice["stride_px"] == full["step_px"] // 2
        assert lattice["n"] < full["n"] / 8
        for key in ("antisymmetric_rms_per_m", "symmetric_rms_per_m"):
            assert lattice[key] == pytest.approx(full[key], rel=0.03), (swapped, key)
        results[swapped] = lattice["antisymmetric_rms_per_m"] / lattice["symmetric_rms_per_m"]
    print(results)
    assert results[False] < 0.2 < 0.5 < results[True], results
