"""The twin's sensor and display timing: exposure and gain act like a sensor, flicker for exposures that
are not whole refresh periods, display latency, and the reference settings reproduce the old frames."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sofast_station.devices.renderer import FringeRenderer
from sofast_station.devices.simulated import SimulatedCamera, SimulatedDisplay
from sofast_station.fringes import Pattern
from sofast_station.twin import TwinOptics


def _display(station, value) -> np.ndarray:
    screen = station.geometry.screen
    return np.full((screen.height_px, screen.width_px), value, np.uint8)


def test_reference_exposure_and_gain_give_the_frames_the_twin_always_gave(parabola_station):
    """At the reference exposure (one refresh period) and gain 1, any refresh phase: bit for bit."""
    station = parabola_station.with_optics(TwinOptics())
    screen = station.geometry.screen
    display = np.random.default_rng(2).integers(0, 256, (screen.height_px, screen.width_px), dtype=np.uint8)
    plain = station.capture(display, np.random.default_rng(4))
    explicit = station.capture(display, np.random.default_rng(4), exposure_s=1 / 60, gain=1.0, flicker_phase=0.37)
    assert np.array_equal(plain, explicit)
    assert station.sensor_scale() == 1.0 and station.flicker_factor(1 / 60, 0.37) == 1.0


@pytest.mark.parametrize("exposure_s, gain", [(2 / 60, 1.0), (1 / 60, 1.7), (3 / 60, 0.6)])
def test_signal_is_proportional_to_exposure_times_gain(parabola_station, exposure_s, gain):
    station = parabola_station
    offset = station.optics.camera_offset_dn
    display = _display(station, 200)
    ref = station.linear_dn(display) - offset
    got = station.linear_dn(display, exposure_s=exposure_s, gain=gain) - offset
    scale = exposure_s / station.optics.reference_exposure_s * gain
    assert np.allclose(got, scale * ref, rtol=1e-5, atol=1e-3)
    frame = station.capture(display, exposure_s=exposure_s, gain=gain)
    facet = station.coverage >= 1
    expected = np.clip(np.rint(offset + scale * ref), 0, 255)
    assert np.max(np.abs(frame[facet] - expected[facet])) <= 1


def test_read_noise_scales_with_the_gain_and_counts_clip_at_255(parabola_station):
    # a black level well above 0, so that the noise is not clipped
    station = parabola_station.with_optics(TwinOptics(read_noise_dn=1.0, electrons_per_dn=0.0, ambient_jitter=0.0,
                                                      camera_offset_dn=40.0, white_dn=240.0))
    dark = _display(station, 0)
    background = station.coverage == 0
    stds = {}
    for gain in (1.0, 4.0):
        frames = np.stack([station.capture(dark, np.random.default_rng(k), gain=gain) for k in range(3)]).astype(float)
        stds[gain] = math.sqrt(float(np.mean(np.var(frames[:, background], axis=0, ddof=1))))
    # observed variance = (read noise x gain)^2 + 1/12 (rounding)
    assert stds[1.0] == pytest.approx(math.sqrt(1.0 + 1 / 12), rel=0.05)
    assert stds[4.0] == pytest.approx(math.sqrt(16.0 + 1 / 12), rel=0.05)
    bright = station.capture(_display(station, 255), gain=3.0)
    assert bright.max() == 255 and np.mean(bright[station.coverage >= 1] == 255) > 0.99


def test_flicker_only_for_exposures_that_are_not_whole_refresh_periods(parabola_station):
    station = parabola_station.with_optics(TwinOptics.noise_free())
    m, f = station.optics.flicker_depth, station.optics.refresh_hz
    white = _display(station, 255)
    facet = station.coverage >= 1
    for periods in (1, 2, 3):
        frames = [station.capture(white, exposure_s=periods / f, flicker_phase=p) for p in (0.0, 0.3, 0.71)]
        assert all(np.array_equal(frames[0], other) for other in frames[1:])
    exposure = 1.5 / f
    means = []
    for phase in np.linspace(0, 1, 8, endpoint=False):
        expected = 1 + m * (math.sin(2 * math.pi * (phase + 1.5)) - math.sin(2 * math.pi * phase)) / (2 * math.pi * 1.5)
        assert station.flicker_factor(exposure, phase) == pytest.approx(expected, abs=1e-12)
        means.append(station.linear_dn(white, exposure_s=exposure, flicker_phase=phase)[facet].mean())
    spread = (max(means) - min(means)) / np.mean(means)
    assert spread > 0.05                  # +-m / (pi * 1.5) of the display light: ~ +-5 %


def test_simulated_camera_settings_act_on_the_twin_and_each_grab_has_its_own_phase(parabola_station):
    station = parabola_station.with_optics(TwinOptics.noise_free())
    screen = station.geometry.screen
    renderer = FringeRenderer(screen.width_px, screen.height_px)
    try:
        display = SimulatedDisplay(renderer)
        camera = SimulatedCamera(station, display, rng=None, flicker_rng=np.random.default_rng(3))
        display.show(Pattern("uniform", command=255))
        facet = station.coverage >= 1
        base = camera.grab()[facet].astype(float).mean()
        camera.set_gain(0.5)
        half = camera.grab()[facet].astype(float).mean()
        offset = station.optics.camera_offset_dn
        assert (half - offset) == pytest.approx(0.5 * (base - offset), rel=0.01)
        camera.set_gain(0.4)                   # longer exposures below saturation
        camera.set_exposure(1.5 / 60)          # not a whole number of refresh periods: flicker
        grabs = [camera.grab()[facet].astype(float).mean() for _ in range(6)]
        assert np.std(grabs) / np.mean(grabs) > 0.005
        camera.set_exposure(2 / 60)            # two whole periods: none
        grabs = [camera.grab()[facet].astype(float).mean() for _ in range(4)]
        assert np.ptp(grabs) == 0
    finally:
        renderer.release()


@pytest.mark.parametrize("settle_s, exposure_s, stale_grabs", [(0.0, 1 / 60, 3), (0.0, 2 / 60, 2), (0.05, 1 / 60, 0),
                                                              (0.02, 1 / 60, 2)])
def test_display_latency_shows_the_previous_image_until_the_settle_covers_it(parabola_station, settle_s, exposure_s,
                                                                             stale_grabs):
    """Latency 40 ms: a grab takes max(exposure, 1/60 s) of the display's time, so with no settle 40 ms are
    three 16.7-ms frames or two 33.3-ms frames; a settle of 50 ms covers it, one of 20 ms leaves 2 frames."""
    station = parabola_station.with_optics(dataclasses.replace(TwinOptics.noise_free(), display_latency_s=0.04))
    screen = station.geometry.screen
    renderer = FringeRenderer(screen.width_px, screen.height_px)
    try:
        display = SimulatedDisplay(renderer, latency_s=station.optics.display_latency_s, settle_s=settle_s)
        camera = SimulatedCamera(station, display)
        camera.set_exposure(exposure_s)
        facet = station.coverage >= 1
        display.show(Pattern("uniform", command=0))
        display.advance(1.0)                                    # long settled
        dark = camera.grab()[facet].mean()
        display.show(Pattern("uniform", command=255))
        seen = [camera.grab()[facet].mean() > dark + 50 for _ in range(stale_grabs + 2)]
        assert seen == [False] * stale_grabs + [True, True]
    finally:
        renderer.release()


def test_new_optics_are_validated():
    from sofast_station.errors import ConfigError
    for bad in ({"refresh_hz": 0.0}, {"flicker_depth": 1.0}, {"display_latency_s": -0.01},
                {"reference_exposure_s": 0.0}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            TwinOptics.from_dict(bad)
