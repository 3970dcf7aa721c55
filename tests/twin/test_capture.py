"""Image formation: analytic DN, display sampling convention, noise statistics, determinism, knee."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from sofast_station.errors import DisplayError
from sofast_station.twin import TwinOptics, TwinStation

from .conftest import RICH_FACET


def _vignetting(station) -> np.ndarray:
    """The vignetting model computed in the test: 1 - v (r / r_corner)^2 about the principal point."""
    cam = station.geometry.camera
    cx, cy = cam.matrix[0, 2], cam.matrix[1, 2]
    v, u = np.mgrid[0:cam.height_px, 0:cam.width_px]
    r2 = (u - cx) ** 2 + (v - cy) ** 2
    r2_corner = max((a - cx) ** 2 + (b - cy) ** 2 for a in (0, cam.width_px - 1) for b in (0, cam.height_px - 1))
    return 1 - station.optics.vignetting * r2 / r2_corner


def _gain(station, vignetting) -> float:
    """DN per unit radiance: white_dn at the brightest facet pixel under full white (nominal ambient)."""
    o = station.optics
    return (o.white_dn - o.camera_offset_dn) / ((o.reflectance + o.ambient) * vignetting[station.coverage >= 1].max())


def _display(station, value) -> np.ndarray:
    screen = station.geometry.screen
    return np.full((screen.height_px, screen.width_px), value, np.uint8)


@pytest.mark.parametrize("command", [0, 90, 180, 255])
def test_noise_free_uniform_capture_equals_analytic_dn(parabola_station, command):
    station = parabola_station
    o = station.optics
    frame = station.capture(_display(station, command))
    assert frame.dtype == np.uint8 and frame.shape == station.geometry.camera.shape
    vig = _vignetting(station)
    gain = _gain(station, vig)
    luminance = o.display_floor + (1 - o.display_floor) * (command / 255) ** o.display_gamma
    rows, cols = np.nonzero(station.coverage >= 1)
    pick = np.random.default_rng(0).choice(rows.size, 12, replace=False)
    r, c = rows[pick], cols[pick]
    expected = o.camera_offset_dn + gain * vig[r, c] * (o.reflectance * luminance + o.ambient)
    assert np.all(np.abs(frame[r, c] - expected) <= 0.5 + 1e-3)
    for r, c in [(5, 5), (1190, 1590), (600, 60)]:            # background, no facet
        assert abs(frame[r, c] - (o.camera_offset_dn + gain * vig[r, c] * o.background)) <= 0.5 + 1e-3


def test_white_reads_white_dn_at_the_brightest_facet_pixel(parabola_station):
    frame = parabola_station.capture(_display(parabola_station, 255))
    assert frame[parabola_station.coverage >= 1].max() == round(parabola_station.optics.white_dn)


def test_capture_samples_the_display_bilinearly_at_the_traced_screen_points(rich_station):
    """A random display image: every facet pixel must read the bilinear sample at its screen point."""
    station = rich_station
    o = station.optics
    screen = station.geometry.screen
    display = np.random.default_rng(5).integers(0, 256, (screen.height_px, screen.width_px), dtype=np.uint8)
    frame = station.capture(display)
    lum_display = o.display_floor + (1 - o.display_floor) * (display / 255.0) ** o.display_gamma
    rows, cols = np.nonzero(station.coverage >= 1)
    u_scr = station.screen_position_m[rows, cols]
    col = u_scr[:, 0] / screen.pitch_m - 0.5
    row = (screen.height_m - u_scr[:, 1]) / screen.pitch_m - 0.5
    lum = map_coordinates(lum_display, [row, col], order=1, mode="grid-constant", cval=0.0)
    vig = _vignetting(station)
    expected = o.camera_offset_dn + _gain(station, vig) * vig[rows, cols] * (o.reflectance * lum + o.ambient)
    error = frame[rows, cols] - expected
    assert np.max(np.abs(error)) <= 0.5 + 1e-3
    assert np.std(expected) > 20                                  # the pattern really varies


def test_partial_pixels_mix_facet_and_background(rich_station):
    station = rich_station
    o = station.optics
    frame = station.capture(_display(station, 255)).astype(float)
    rows, cols = np.nonzero((station.coverage > 0.2) & (station.coverage < 0.8))
    cov = station.coverage[rows, cols]
    vig = _vignetting(station)[rows, cols]
    gain = _gain(station, _vignetting(station))
    screen_ok = station.on_screen[rows, cols]
    expected = o.camera_offset_dn + gain * vig * (cov * (o.reflectance + o.ambient) + (1 - cov) * o.background)
    assert np.max(np.abs(frame[rows, cols] - expected)[screen_ok]) <= 0.5 + 1e-3


def test_noise_matches_the_noise_model(parabola_station):
    optics = TwinOptics(ambient_jitter=0.0)
    station = parabola_station.with_optics(optics)
    command = 200
    frames = np.stack([station.capture(_display(station, command), np.random.default_rng(12 + k))
                       for k in range(32)]).astype(float)
    vig = _vignetting(station)
    gain = _gain(station, vig)
    luminance = optics.display_floor + (1 - optics.display_floor) * (command / 255) ** optics.display_gamma
    pick = np.random.default_rng(1).choice(station.coverage.size, 40000, replace=False)
    r, c = np.unravel_index(pick, station.coverage.shape)
    for where, radiance in ((station.coverage[r, c] >= 1, optics.reflectance * luminance + optics.ambient),
                            (station.coverage[r, c] == 0, optics.background)):
        rr, cc = r[where], c[where]
        signal = gain * vig[rr, cc] * radiance                  # DN above the black level
        observed = np.mean(np.var(frames[:, rr, cc], axis=0, ddof=1))
        model = np.mean(optics.read_noise_dn ** 2 + signal / optics.electrons_per_dn + 1 / 12)   # + rounding
        assert np.sqrt(observed) == pytest.approx(np.sqrt(model), rel=0.15)
        assert np.mean(frames[:, rr, cc]) == pytest.approx(np.mean(optics.camera_offset_dn + signal), abs=0.05)


def test_same_seed_gives_the_same_frame(parabola_station):
    station = parabola_station.with_optics(TwinOptics())
    display = _display(station, 128)
    a = station.capture(display, np.random.default_rng(7))
    b = station.capture(display, np.random.default_rng(7))
    c = station.capture(display, np.random.default_rng(8))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.array_equal(station.capture(display), station.capture(display))


@pytest.mark.parametrize("optics", [TwinOptics(), TwinOptics(electrons_per_dn=0.0, read_noise_dn=2.0, knee_dn=60.0)])
def test_a_kept_pattern_renders_the_same_frame_as_a_fresh_image(rich_station, optics):
    # A read-only pattern's light is kept on the box of seen pixels and added there, and a noisy frame is
    # formed on that box only (the dark level and its noise deviation outside it); a writable image is
    # sampled and scattered onto the seen pixels of a whole frame each time: the same frames, bit for bit.
    station = rich_station.with_optics(optics)
    screen = station.geometry.screen
    rows, cols = np.mgrid[0:screen.height_px, 0:screen.width_px]
    pattern = (127.5 + 120 * np.cos(2 * np.pi * (cols / 37.0 + rows / 53.0))).astype(np.uint8)
    kept = pattern.copy()
    kept.setflags(write=False)
    for seed in (3, None):
        fresh = station.capture(pattern.copy(), None if seed is None else np.random.default_rng(seed))
        first = station.capture(kept, None if seed is None else np.random.default_rng(seed))
        again = station.capture(kept, None if seed is None else np.random.default_rng(seed))
        assert np.array_equal(fresh, first) and np.array_equal(first, again)
    assert station.renderer.cached_light(kept) is not None and station.renderer.cached_light(pattern) is None
    r0, r1, c0, c1, _ = station.renderer.seen_box   # the box leaves dark pixels on every side to check
    height, width = station.geometry.camera.shape
    assert r0 > 0 and c0 > 0 and r1 < height and c1 < width


def test_knee_is_monotone_and_saturates_at_255(parabola_station):
    station = parabola_station.with_optics(TwinOptics(read_noise_dn=0.0, electrons_per_dn=0.0, ambient_jitter=0.0,
                                                      white_dn=300.0, knee_dn=200.0))
    mask = station.coverage >= 1
    levels = [np.sort(station.capture(_display(station, v))[mask]) for v in range(0, 256, 15)]
    means = [lv.mean() for lv in levels]
    assert all(b >= a for a, b in zip(means, means[1:]))
    assert 240 < levels[-1].max() < 255                       # 300 DN linear, bent below 255
    linear = station.with_optics(dataclasses.replace(station.optics, knee_dn=None)).capture(_display(station, 30))[mask]
    assert np.array_equal(np.sort(linear), levels[2])        # below the knee nothing changes


def test_display_image_must_match_the_screen(parabola_station):
    with pytest.raises(DisplayError, match="uint8"):
        parabola_station.capture(np.zeros((1080, 1920), np.float32))
    with pytest.raises(DisplayError):
        parabola_station.capture(np.zeros((1920, 1080), np.uint8))


def test_full_resolution_sensor_noise_is_fresh_and_zero_mean(geometry, design):
    """The full-resolution twin with its default (noisy) optics and the rich facet (random surface, dents,
    cubic term): at the nominal ambient, each capture is the noise-free frame plus sensor noise drawn
    afresh and of zero mean. Over 10 captures the mean difference on the facet's pixels lies within five
    standard errors of zero (the differences' own scatter, about 2 DN per pixel over some 6 10^6 samples:
    6 10^-4 DN; a bias of a hundredth of a rounding step fails), and two captures differ at most facet
    pixels. The display shows random commands 20..200, so that the noise-free frame's own rounding
    (0.29 DN per pixel) averages out over the facet (under a uniform screen the facet's pixels share their
    fractional DN, and its mean rounding error is 0.008 DN) and no pixel meets the clipping at 0 or 255.
    (The trace's and a capture's time: benchmarks/twin_render.py.)"""
    station = TwinStation(geometry, design, RICH_FACET)
    assert station.optics.read_noise_dn > 0 and station.optics.electrons_per_dn > 0
    screen = station.geometry.screen
    display = np.random.default_rng(7).integers(20, 201, (screen.height_px, screen.width_px), dtype=np.uint8)
    facet = station.coverage >= 1
    exact = station.capture(display)[facet].astype(np.float64)        # no generator: the noise-free frame
    rng = np.random.default_rng(0)
    frames = [station.capture(display, rng, ambient_z=0.0)[facet] for _ in range(10)]
    diff = np.stack([f.astype(np.float64) - exact for f in frames])
    standard_error = diff.std() / np.sqrt(diff.size)
    assert abs(diff.mean()) < 5 * standard_error, (diff.mean(), standard_error)
    assert 1.0 < diff.std() < 4.0                                   # the noise is there, of its model's size
    assert np.mean(frames[0] != frames[1]) > 0.5
