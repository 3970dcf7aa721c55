"""The small interfaces the station talks to. Real and simulated backends implement the same ones."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..fringes import Pattern


class Display(Protocol):
    """Shows one display image at a time; ``show`` returns once the image is on screen."""

    def show(self, pattern: Pattern) -> None: ...

    def close(self) -> None: ...


class Camera(Protocol):
    """Grabs monochrome frames (rows, columns) of integer counts."""

    shape: tuple[int, int]

    def set_exposure(self, seconds: float) -> None: ...

    def set_gain(self, gain: float) -> None: ...

    def grab(self) -> np.ndarray: ...

    def close(self) -> None: ...


class RangeFinder(Protocol):
    """Distance from the screen centre to the facet's measure point, metres."""

    def measure(self) -> float: ...
