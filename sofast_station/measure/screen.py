"""Screen models: fractional screen coordinates -> 3-D points in the camera frame.

A screen model answers one question: where, in the camera's frame, is the screen point at position
(u_x, u_y) metres from the active area's left and bottom edges? The flat model uses the screen's size
and its pose (the camera/screen assembly); a measured distortion map (projection screens) plugs in
behind the same method.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..geometry import Pose


class ScreenModel(Protocol):
    width_m: float
    height_m: float

    def points_camera(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        """(3, N) camera-frame points, metres, of screen positions u_x (from left), u_y (from bottom)."""


@dataclass(frozen=True)
class FlatScreen:
    """A flat screen of known size at a known pose.

    Attributes
    ----------
    width_m, height_m : float
        Active area W and H, metres.
    screen_to_camera : Pose
        Maps screen-frame points (origin at the active area's centre) into the camera frame.
    """

    width_m: float
    height_m: float
    screen_to_camera: Pose

    def points_camera(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        u_x_m = np.asarray(u_x_m, dtype=np.float64)
        u_y_m = np.asarray(u_y_m, dtype=np.float64)
        r = self.screen_to_camera.rotation
        t = self.screen_to_camera.translation
        x = u_x_m - 0.5 * self.width_m
        y = u_y_m - 0.5 * self.height_m
        return np.stack([r[i, 0] * x + r[i, 1] * y + t[i] for i in range(3)])

    def centre_camera(self) -> np.ndarray:
        """The screen centre in the camera frame, metres."""
        return self.screen_to_camera.translation.copy()
