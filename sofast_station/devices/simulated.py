"""Simulated backends: the fringe renderer drawing offscreen, and the digital twin's camera.

The simulated display draws every image with the same renderer (and shader) as the LCD window; the
simulated camera looks at whatever the display currently shows through the twin's optics.
"""

from __future__ import annotations

import dataclasses

import math
import threading

import numpy as np

from ..errors import CameraDisconnectedError, CameraTimeoutError, DisplayError
from .cameras._common import CameraSettingError, check_exposure, check_gain
from ..fringes import Pattern
from .renderer import FringeRenderer

#: The "lights-off" fault: counts of room light, present at calibration, that every pixel loses, DN.
LIGHTS_OFF_DN = 6


class SimulatedDisplay:
    """Display backend that renders offscreen and keeps the image "on screen" for the simulated camera.

    Time is virtual: the display keeps the station's clock (seconds). An image asked for at time t reaches
    the panel at ``t + latency_s`` (the twin's ``display_latency_s``); until then the panel shows the
    previous one. :meth:`show` then "waits" ``settle_s`` (advances the clock), as the LCD's ``show`` waits
    its settle time; each camera grab advances the clock by its frame period. So a grab right after
    ``show`` sees the previous image unless the settle time covers the latency.

    Parameters
    ----------
    renderer : FringeRenderer
    latency_s : float
        Time from ``show`` to the image being on the panel, seconds.
    settle_s : float
        Time ``show`` waits after drawing, seconds (the display-latency calibration's value).
    """

    def __init__(self, renderer: FringeRenderer, latency_s: float = 0.0, settle_s: float = 0.0):
        self.renderer = renderer
        self.latency_s = float(latency_s)
        self.settle_s = float(settle_s)
        if not (math.isfinite(self.latency_s) and self.latency_s >= 0):
            raise DisplayError(f"display latency must be a finite number of seconds >= 0, got {latency_s}")
        if not (math.isfinite(self.settle_s) and self.settle_s >= 0):
            raise DisplayError(f"the display settle time must be a finite number of seconds >= 0, got {settle_s}")
        #: Virtual time, seconds.
        self.clock_s = 0.0
        self._current = np.zeros((renderer.height_px, renderer.width_px), dtype=np.uint8)
        self._pending: list[tuple[float, np.ndarray]] = []      # (on the panel from, image), in show order
        self._cache: dict[Pattern, np.ndarray] = {}

    def show(self, pattern: Pattern) -> None:
        # The images of a fringe set never change between facets: render each once.
        img = self._cache.get(pattern)
        if img is None:
            img = self._cache[pattern] = self.renderer.render(pattern)
            img.setflags(write=False)        # the twin may keep what it derives from an image that never changes
        self._pending.append((self.clock_s + self.latency_s, img))
        self.clock_s += max(self.settle_s, 0.0)

    def image_at(self, t_s: float) -> np.ndarray:
        """The image on the panel at virtual time *t_s* (not earlier than any time asked before)."""
        while self._pending and self._pending[0][0] <= t_s:
            self._current = self._pending.pop(0)[1]
        return self._current

    @property
    def image(self) -> np.ndarray:
        """The image on the panel now."""
        return self.image_at(self.clock_s)

    def advance(self, seconds: float) -> None:
        """Let *seconds* of virtual time pass (a camera frame)."""
        self.clock_s += float(seconds)

    def close(self) -> None:
        self.renderer.release()
        self._cache.clear()


class SimulatedCamera:
    """Camera backend that images the simulated display through the twin.

    Exposure and gain act on the twin's sensor model (signal proportional to exposure x gain, read noise
    scaled by the gain). Each grab starts at a random phase of the display's refresh cycle (from
    *flicker_rng*), which matters only for exposures that are not a whole number of refresh periods, and
    takes ``max(exposure, one refresh period)`` of the display's virtual time.

    Parameters
    ----------
    twin : TwinStation
    display : SimulatedDisplay
    rng : numpy Generator or None
        Sensor noise and ambient jitter; None for noise-free frames.
    flicker_rng : numpy Generator or None
        Phase of the refresh cycle at each grab; None starts every grab at phase 0.
    """

    def __init__(self, twin, display: SimulatedDisplay, rng: np.random.Generator | None = None,
                 flicker_rng: np.random.Generator | None = None):
        self.twin = twin
        self.display = display
        self.rng = rng
        self.flicker_rng = flicker_rng
        self.shape = (twin.geometry.camera.height_px, twin.geometry.camera.width_px)
        self.exposure_s = twin.optics.reference_exposure_s
        self.gain = 1.0
        #: Injected fault for the current facet (tests of the production loop), see SimulatedStation.
        self.fault: str | None = None
        self._unhang = threading.Event()

    def set_exposure(self, seconds: float) -> None:
        self.exposure_s = check_exposure(seconds)

    def set_gain(self, gain: float) -> None:
        gain = check_gain(gain)
        if gain <= 0:
            raise CameraSettingError(f"gain must be a positive factor, got {gain!r}")
        self.gain = gain

    def grab(self, timeout_s: float = 2.0) -> np.ndarray:
        fault = self.fault
        if fault == "camera-timeout":
            raise CameraTimeoutError(f"no frame from the simulated camera within {timeout_s:g} s (injected fault)")
        if fault == "camera-disconnect":
            raise CameraDisconnectedError("the simulated camera went away (injected fault); reopen it")
        if fault == "hung-capture":
            self.fault = None
            self._unhang.clear()
            self._unhang.wait(60.0)               # a driver that blocks far past any timeout
        phase = float(self.flicker_rng.random()) if self.flicker_rng is not None else None
        settings = {"exposure_s": self.exposure_s, "gain": self.gain, "flicker_phase": phase}
        shown = self.display.image
        self.display.advance(max(self.exposure_s, 1.0 / self.twin.optics.refresh_hz))
        if fault == "dark":
            return self._unlit().capture(np.zeros_like(shown), self.rng, **settings)
        frame = self.twin.capture(shown, self.rng, **settings)
        if fault == "misplaced":
            frame = np.roll(frame, 220, axis=1)   # the facet far from where the fixture should hold it
        if fault == "lights-off":                 # the room light seen at calibration is gone
            frame = np.maximum(frame.astype(np.int16) - LIGHTS_OFF_DN, 0).astype(np.uint8)
        return frame

    def _unlit(self):
        """The twin with nothing in view lit (the dark fault: a covered lens, no light), the fixture's marks,
        which the hall lights, dark too."""
        if getattr(self, "_unlit_of", None) is not self.twin:
            twin = self.twin
            if getattr(twin, "mark_coverage", None) is not None:
                twin = twin.with_optics(dataclasses.replace(twin.optics, mark_radiance=0.0))
            self._unlit_of, self._unlit_twin = self.twin, twin
        return self._unlit_twin

    def release_hang(self) -> None:
        """Let a hung grab return (the station reopening the camera)."""
        self._unhang.set()

    def close(self) -> None:
        pass


class SimulatedRangeFinder:
    """The twin's exact distance, plus an optional fixed error (metres) to study its effect."""

    def __init__(self, twin, error_m: float = 0.0):
        self.twin = twin
        self.error_m = float(error_m)

    def measure(self) -> float:
        return self.twin.measured_distance_m() + self.error_m
