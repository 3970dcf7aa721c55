"""The blur's first-order shift of the decoded positions (measure/deblur.py) against an independent image model:
a fringe set's complex signal A exp(i phi) on a pixel grid, blurred by scipy's Gaussian filter (the light's
blur, as a lens blurs it), its phase read back with numpy. The position field is a facet's projection with a
curvature that varies across the image, the amplitude falls off as a lens's vignetting does. Drawn over 24
cases (blur 0.4-1.2 px, fringe gradients 0.15-0.45 rad/px, vignetting and curvature drawn): what the blur
adds to the positions' linear part across the image (what a nearly flat facet reads as focal power) is cut to
a twentieth or less, and so is its whole RMS (measured 2026-12-07: at most 1/160 and 1/110 of it). The
blur is the filter's own spread (a sampled Gaussian's, below its sigma under a pixel: with the nominal sigma
the correction missed 16-29 % at 0.5 px)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from sofast_station.measure.deblur import blur_shift_m, roughness_shift_m


def _case(rng):
    h, w = 150, 200
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / w, (v - h / 2) / w                        # about -0.5..0.5 across the image
    sigma = rng.uniform(0.4, 1.2)
    gradient = rng.uniform(0.15, 0.45)                              # the fringes' phase per pixel, rad
    period_m = 0.3
    # positions (metres): a linear map, a curvature and its change across the image (a cubic)
    slope = gradient * period_m / (2 * np.pi) * w                   # metres per unit of x
    s = slope * (x + rng.uniform(-0.05, 0.05) * x * x + rng.uniform(-0.03, 0.03) * x * y
                 + rng.uniform(-0.02, 0.02) * x ** 3)
    amplitude = 100.0 * np.exp(-rng.uniform(0.5, 2.0) * ((x - rng.uniform(-0.2, 0.2)) ** 2 + y ** 2))
    phi = 2 * np.pi * s / period_m
    z = amplitude * np.exp(1j * phi)
    blurred = gaussian_filter(z.real, sigma, mode="nearest") + 1j * gaussian_filter(z.imag, sigma, mode="nearest")
    seen = s + np.angle(blurred * np.exp(-1j * phi)) * period_m / (2 * np.pi)
    inner = np.zeros((h, w), bool)
    inner[8:-8, 8:-8] = True                                        # clear of the image's border by 5+ sigma
    # the filter's own spread: a sampled Gaussian's variance is below sigma^2 when sigma is under a pixel
    k = np.arange(-int(4.0 * sigma + 0.5), int(4.0 * sigma + 0.5) + 1)
    weights = np.exp(-0.5 * (k / sigma) ** 2)
    spread = float(np.sqrt(np.sum(k * k * weights) / np.sum(weights)))
    return u, v, inner, s, seen, np.abs(blurred), spread


def _linear_part(e, u, v):
    a = np.column_stack([np.ones(e.size), u, v])
    c, *_ = np.linalg.lstsq(a, e, rcond=None)
    return np.hypot(c[1], c[2])


@pytest.mark.parametrize("seed", range(24))
def test_the_blur_shift_takes_the_blurs_displacement_off_the_positions(seed):
    rng = np.random.default_rng(seed)
    u, v, inner, s, seen, amplitude, sigma = _case(rng)
    uu, vv, ok = u[inner], v[inner], np.ones(int(inner.sum()), bool)
    shift = blur_shift_m(uu, vv, ok, seen[inner], amplitude[inner], sigma)
    before = seen[inner] - s[inner]
    after = before - shift
    assert _linear_part(after, uu, vv) <= 0.05 * _linear_part(before, uu, vv)
    assert np.sqrt(np.mean(after ** 2)) <= 0.05 * np.sqrt(np.mean(before ** 2))


def test_no_blur_or_too_few_pixels_move_nothing():
    u, v = np.meshgrid(np.arange(10.0), np.arange(4.0))
    u, v = u.ravel(), v.ravel()
    s, a, ok = 1e-3 * u, np.full(u.size, 50.0), np.ones(u.size, bool)
    assert np.all(blur_shift_m(u, v, ok, s, a, 0.0) == 0)
    assert np.all(blur_shift_m(u, v, np.zeros(u.size, bool), s, a, 0.8) == 0)
    with pytest.raises(ValueError, match="one shape"):
        blur_shift_m(u, v, ok, s[:-1], a, 0.8)


def _rough_case(rng):
    """A position field with a smooth part and a rough one (white noise smoothed to a correlation of 2.5-6 px:
    a facet's slope errors of 2-6 cm seen by pixels of 5-10 mm), its fringes blurred as in :func:`_case`."""
    h, w = 150, 200
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / w, (v - h / 2) / w
    sigma = rng.uniform(0.5, 1.0)
    period_m = 0.3
    slope = rng.uniform(0.15, 0.45) * period_m / (2 * np.pi) * w
    smooth = slope * (x + rng.uniform(-0.05, 0.05) * x * x + rng.uniform(-0.03, 0.03) * x * y)
    length = rng.uniform(2.5, 6.0)
    rough = gaussian_filter(rng.standard_normal((h, w)), length)
    rough *= 0.05 * period_m / (2 * np.pi) / np.std(np.gradient(rough)[1])      # 0.05 rad/px of phase gradient
    s = smooth + rough
    amplitude = 100.0 * np.exp(-rng.uniform(0.5, 2.0) * (x ** 2 + y ** 2))
    z = amplitude * np.exp(2j * np.pi * s / period_m)
    blurred = gaussian_filter(z.real, sigma, mode="nearest") + 1j * gaussian_filter(z.imag, sigma, mode="nearest")
    seen = s + np.angle(blurred * np.exp(-2j * np.pi * s / period_m)) * period_m / (2 * np.pi)
    inner = np.zeros((h, w), bool)
    inner[8:-8, 8:-8] = True
    k = np.arange(-int(4.0 * sigma + 0.5), int(4.0 * sigma + 0.5) + 1)
    weights = np.exp(-0.5 * (k / sigma) ** 2)
    spread = float(np.sqrt(np.sum(k * k * weights) / np.sum(weights)))
    return u, v, inner, s, seen, np.abs(blurred), spread


def test_the_roughness_shift_takes_most_of_the_blurs_smoothing_off_what_a_fit_sees():
    """24 drawn rough fields (blur 0.5-1.0 px, roughness correlated over 2.5-6 px, an independent image model).
    What a fit reads of the error the smooth shift leaves (its linear part across the image, what a nearly flat
    facet reads as focal power) falls to at most 0.35 of its RMS over the cases and its largest to at most half,
    and each field's whole error to at most half its RMS (measured 2026-12-07: RMS 0.206 -> 0.047 um per px,
    largest 0.501 -> 0.129; the whole error to at most 0.20). Without the roughness shift the test fails."""
    ratios, fine = [], []
    for seed in range(24):
        rng = np.random.default_rng(100 + seed)
        u, v, inner, s, seen, amplitude, sigma = _rough_case(rng)
        uu, vv, ok = u[inner], v[inner], np.ones(int(inner.sum()), bool)
        smooth_off = seen[inner] - blur_shift_m(uu, vv, ok, seen[inner], amplitude[inner], sigma)
        sharpened = smooth_off - roughness_shift_m(uu, vv, ok, smooth_off, sigma)
        before, after = smooth_off - s[inner], sharpened - s[inner]
        ratios.append((_linear_part(before, uu, vv), _linear_part(after, uu, vv)))
        fine.append(np.sqrt(np.mean(after ** 2) / np.mean(before ** 2)))
        assert fine[-1] <= 0.5, seed
    before, after = np.array(ratios).T
    print(f"linear part: RMS {1e6 * np.sqrt(np.mean(before ** 2)):.3f} -> {1e6 * np.sqrt(np.mean(after ** 2)):.3f}, "
          f"largest {1e6 * before.max():.3f} -> {1e6 * after.max():.3f} um per px; "
          f"fine RMS at most {max(fine):.2f} of it")
    assert np.sqrt(np.mean(after ** 2)) <= 0.35 * np.sqrt(np.mean(before ** 2))
    assert after.max() <= 0.5 * before.max()


def test_the_roughness_shift_leaves_the_rim_and_a_smooth_field_alone():
    u, v = np.meshgrid(np.arange(30.0), np.arange(20.0))
    u, v = u.ravel(), v.ravel()
    ok = np.ones(u.size, bool)
    cubic = 1e-3 * u + 2e-6 * u * v - 1e-7 * u ** 3
    assert np.max(np.abs(roughness_shift_m(u, v, ok, cubic, 0.8))) < 1e-15
    bump = cubic + 1e-5 * ((u == 10) & (v == 10))
    shift = roughness_shift_m(u, v, ok, bump, 0.8)
    rim = (u == 0) | (u == 29) | (v == 0) | (v == 19)
    assert np.all(shift[rim] == 0)
    assert shift[(u == 10) & (v == 10)][0] < 0 < shift[(u == 11) & (v == 10)][0]
    assert np.all(roughness_shift_m(u, v, ok, bump, 0.0) == 0)
    with pytest.raises(ValueError, match="one shape"):
        roughness_shift_m(u, v, ok, bump[:-1], 0.8)
