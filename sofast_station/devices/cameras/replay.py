"""A camera that replays recorded frames: for re-running a capture, for tests, and for timing studies.

Each ``grab`` returns the next frame, in order, after waiting ``frame_delay_s`` (to model the display's
latency plus the exposure of a real capture). Exposure and gain are recorded but do not change the frames.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import numpy as np

from ...errors import CameraError, CameraTimeoutError, ConfigError
from ._common import check_exposure, check_gain

log = logging.getLogger(__name__)


class ReplayCamera:
    """Camera backend serving a fixed stack of frames in order.

    Parameters
    ----------
    frames : numpy.ndarray
        (n, rows, columns) uint8 frames, n >= 1. The camera keeps its own read-only copy.
    frame_delay_s : float
        Time each ``grab`` waits before returning its frame, seconds (>= 0).
    loop : bool
        Start again at the first frame after the last one; otherwise a ``grab`` after the last frame
        raises :class:`~sofast_station.errors.CameraTimeoutError`.

    Attributes
    ----------
    shape : tuple of int
        (rows, columns) of every frame, pixels.
    exposure_s : float or None
        The last exposure time set, seconds (None until set).
    gain : float or None
        The last gain set, in whatever unit the caller uses (None until set).
    index : int
        Index of the frame the next ``grab`` returns (counts on past the end when ``loop`` is set: the
        frame served is ``index % n``).

    Raises
    ------
    ConfigError
        ``frames`` is not a non-empty (n, rows, columns) uint8 array, or ``frame_delay_s`` is negative.
    """

    def __init__(self, frames: np.ndarray, frame_delay_s: float = 0.0, loop: bool = False):
        frames = np.asarray(frames)
        if frames.ndim != 3 or frames.shape[0] < 1 or frames.shape[1] < 1 or frames.shape[2] < 1:
            raise ConfigError(f"replay camera: frames must be an (n, rows, columns) array with n >= 1, "
                              f"got shape {frames.shape}")
        if frames.dtype != np.uint8:
            raise ConfigError(f"replay camera: frames must be uint8 counts, got {frames.dtype}; convert them "
                              "first (e.g. scale 16-bit frames to 8 bits)")
        delay = float(frame_delay_s)
        if not np.isfinite(delay) or delay < 0:
            raise ConfigError(f"replay camera: frame_delay_s must be >= 0 seconds, got {frame_delay_s!r}")
        self._frames = np.array(frames, copy=True)
        self._frames.setflags(write=False)
        self.frame_delay_s = delay
        self.loop = bool(loop)
        self.shape: tuple[int, int] = (int(frames.shape[1]), int(frames.shape[2]))
        self.exposure_s: float | None = None
        self.gain: float | None = None
        self.index = 0
        self._closed = False
        log.debug("replay camera: %d frames of %d x %d, delay %.3f s, loop %s", len(self._frames),
                  *self.shape, delay, self.loop)

    @classmethod
    def from_frames(cls, frames: np.ndarray | Sequence[np.ndarray], frame_delay_s: float = 0.0,
                    loop: bool = False) -> "ReplayCamera":
        """Make a replay camera from a stack or a sequence of frames.

        Parameters
        ----------
        frames : numpy.ndarray or sequence of numpy.ndarray
            An (n, rows, columns) uint8 array, or n (rows, columns) uint8 frames of one size.
        frame_delay_s : float
            Wait per grab, seconds.
        loop : bool
            Start again after the last frame.

        Returns
        -------
        ReplayCamera

        Raises
        ------
        ConfigError
            The frames differ in size, are not uint8, or there are none.
        """
        if isinstance(frames, np.ndarray):
            stack = frames
        else:
            frames = list(frames)
            if not frames:
                raise ConfigError("replay camera: no frames given")
            shapes = {np.shape(f) for f in frames}
            if len(shapes) != 1:
                raise ConfigError(f"replay camera: the frames differ in size ({sorted(shapes)}); give frames "
                                  "of one size")
            stack = np.stack([np.asarray(f) for f in frames])
        return cls(stack, frame_delay_s=frame_delay_s, loop=loop)

    @property
    def n_frames(self) -> int:
        """Number of frames in the recording."""
        return int(self._frames.shape[0])

    def set_exposure(self, seconds: float) -> None:
        """Record an exposure time (seconds); the frames do not change.

        Raises
        ------
        CameraSettingError
            Not a positive finite number of seconds.
        """
        self.exposure_s = check_exposure(seconds)

    def set_gain(self, gain: float) -> None:
        """Record a gain; the frames do not change.

        Raises
        ------
        CameraSettingError
            Not a finite number.
        """
        self.gain = check_gain(gain)

    def rewind(self) -> None:
        """Serve the first frame again on the next ``grab``."""
        self.index = 0

    def grab(self, timeout_s: float = 2.0) -> np.ndarray:
        """Return the next frame after waiting ``frame_delay_s``.

        Parameters
        ----------
        timeout_s : float
            Longest wait, seconds. When ``frame_delay_s`` exceeds it, the grab waits ``timeout_s``, then
            raises CameraTimeoutError without using up the frame (like a real camera whose frame comes
            too late).

        Returns
        -------
        numpy.ndarray
            (rows, columns) uint8, a fresh copy the caller may modify.

        Raises
        ------
        CameraTimeoutError
            The recording is exhausted (and ``loop`` is off), or ``frame_delay_s > timeout_s``.
        CameraError
            The camera was closed.
        """
        if self._closed:
            raise CameraError("replay camera: grab after close; open a new camera")
        n = self.n_frames
        if not self.loop and self.index >= n:
            raise CameraTimeoutError(f"replay camera: all {n} recorded frames have been served; rewind() "
                                     "or replay a longer recording (or set loop=True)")
        if self.frame_delay_s > timeout_s:
            time.sleep(max(0.0, float(timeout_s)))
            raise CameraTimeoutError(f"replay camera: the frame takes {self.frame_delay_s:g} s, longer than "
                                     f"the grab timeout of {timeout_s:g} s; raise the timeout")
        if self.frame_delay_s > 0:
            time.sleep(self.frame_delay_s)
        frame = self._frames[self.index % n].copy()
        self.index += 1
        return frame

    def close(self) -> None:
        """Close the camera (idempotent); further grabs raise CameraError."""
        self._closed = True

    def __enter__(self) -> "ReplayCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (f"ReplayCamera({self.n_frames} frames of {self.shape[0]} x {self.shape[1]}, "
                f"delay {self.frame_delay_s:g} s, loop={self.loop}, next={self.index})")
