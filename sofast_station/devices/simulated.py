"""Simulated backends: the fringe renderer drawing offscreen, and the digital twin's camera.

The simulated display draws every image with the same renderer (and shader) as the LCD window; the
simulated camera looks at whatever the display currently shows through the twin's optics.
"""

from __future__ import annotations

import threading

import numpy as np

from ..errors import CameraDisconnectedError, CameraTimeoutError
from ..fringes import Pattern
from .renderer import FringeRenderer


class SimulatedDisplay:
    """Display backend that renders offscreen and keeps the image "on screen" for the simulated camera."""

    def __init__(self, renderer: FringeRenderer):
        self.renderer = renderer
        self.image = np.zeros((renderer.height_px, renderer.width_px), dtype=np.uint8)
        self._cache: dict[Pattern, np.ndarray] = {}

    def show(self, pattern: Pattern) -> None:
        # The images of a fringe set never change between facets: render each once.
        img = self._cache.get(pattern)
        if img is None:
            img = self._cache[pattern] = self.renderer.render(pattern)
        self.image = img

    def close(self) -> None:
        self.renderer.release()
        self._cache.clear()


class SimulatedCamera:
    """Camera backend that images the simulated display through the twin."""

    def __init__(self, twin, display: SimulatedDisplay, rng: np.random.Generator | None = None):
        self.twin = twin
        self.display = display
        self.rng = rng
        self.shape = (twin.geometry.camera.height_px, twin.geometry.camera.width_px)
        self.exposure_s = 1 / 60
        self.gain = 1.0
        #: Injected fault for the current facet (tests of the production loop), see SimulatedStation.
        self.fault: str | None = None
        self._unhang = threading.Event()

    def set_exposure(self, seconds: float) -> None:
        self.exposure_s = float(seconds)

    def set_gain(self, gain: float) -> None:
        self.gain = float(gain)

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
        if fault == "dark":
            return self.twin.capture(np.zeros_like(self.display.image), self.rng)
        frame = self.twin.capture(self.display.image, self.rng)
        if fault == "misplaced":
            frame = np.roll(frame, 220, axis=1)   # the facet far from where the fixture should hold it
        return frame

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
