"""What the camera backends share: their error classes, pixel-format handling and argument checks.

Every error here derives from :class:`~sofast_station.errors.CameraError`, so the station loop, which
closes and reopens the camera after any ``CameraError``, handles them all.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ...errors import CameraDisconnectedError, CameraError

log = logging.getLogger(__name__)

#: Monochrome pixel formats a backend can turn into uint8 frames: name -> bits per pixel. Frames of more
#: than 8 bits (unpacked, little-endian 16-bit words) are shifted right to their 8 most significant bits.
MONO_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}


class CameraBackendMissingError(CameraError):
    """A camera backend's library is not installed (the message names the package to install)."""


class CameraNotFoundError(CameraDisconnectedError):
    """No camera answers to the requested serial number or device id (not plugged in, not powered, other
    subnet, or opened by another program)."""


class CameraSettingError(CameraError):
    """A setting (exposure, gain, pixel format, trigger, a named feature) is not supported by the camera,
    not writable, or outside the camera's range."""


class CameraFrameSizeError(CameraError):
    """The camera delivers frames of another size than the station expects."""


class CameraIncompleteFrameError(CameraError):
    """A frame arrived damaged or incomplete (lost packets, buffer underrun, cancelled transfer)."""


def check_shape(expected_shape) -> tuple[int, int]:
    """Validate an expected frame shape.

    Parameters
    ----------
    expected_shape : tuple of int
        (rows, columns) in pixels.

    Returns
    -------
    tuple of int
        The shape as a tuple of two positive Python ints.

    Raises
    ------
    CameraSettingError
        The shape is not two positive integers.
    """
    try:
        rows, cols = (int(v) for v in expected_shape)
    except (TypeError, ValueError) as exc:
        raise CameraSettingError(
            f"expected_shape must be (rows, columns) in pixels, got {expected_shape!r}") from exc
    if rows <= 0 or cols <= 0:
        raise CameraSettingError(
            f"expected_shape must be positive (rows, columns) in pixels, got {expected_shape!r}")
    return rows, cols


def check_pixel_format(pixel_format: str) -> int:
    """Bits per pixel of a supported monochrome pixel format.

    Parameters
    ----------
    pixel_format : str
        GenICam PixelFormat name, e.g. "Mono8".

    Returns
    -------
    int
        Bits per pixel (8 to 16).

    Raises
    ------
    CameraSettingError
        The format is not one the station can turn into 8-bit frames.
    """
    bits = MONO_BITS.get(pixel_format)
    if bits is None:
        raise CameraSettingError(
            f"pixel format {pixel_format!r} is not supported: use one of {', '.join(MONO_BITS)} "
            "(unpacked monochrome; set it in the camera options)")
    return bits


def check_exposure(seconds: float) -> float:
    """Validate an exposure time.

    Parameters
    ----------
    seconds : float
        Exposure time, seconds.

    Returns
    -------
    float
        The exposure time in seconds.

    Raises
    ------
    CameraSettingError
        Not a finite positive number.
    """
    try:
        value = float(seconds)
    except (TypeError, ValueError) as exc:
        raise CameraSettingError(f"exposure must be a number of seconds, got {seconds!r}") from exc
    if not math.isfinite(value) or value <= 0:
        raise CameraSettingError(f"exposure must be a positive number of seconds, got {seconds!r}")
    return value


def check_gain(gain: float) -> float:
    """Validate a gain value (finite number, in the camera's own unit).

    Raises
    ------
    CameraSettingError
        Not a finite number.
    """
    try:
        value = float(gain)
    except (TypeError, ValueError) as exc:
        raise CameraSettingError(f"gain must be a number, got {gain!r}") from exc
    if not math.isfinite(value):
        raise CameraSettingError(f"gain must be a finite number, got {gain!r}")
    return value


def check_in_range(what: str, value: float, low: float, high: float, unit: str, scale: float = 1.0) -> None:
    """Raise :class:`CameraSettingError` unless ``low <= value <= high`` (all in the camera's unit).

    Parameters
    ----------
    what : str
        The setting's name, for the message.
    value, low, high : float
        The requested value and the camera's limits, in the camera's unit.
    unit : str
        The unit used in the message.
    scale : float
        Factor from the camera's unit to the message's unit (1e-6 to show microseconds as seconds).
    """
    # A relative tolerance: limits read back as floats may differ from a typed-in limit in the last digit.
    tol = 1e-9 * max(abs(low), abs(high), 1.0)
    if not (low - tol <= value <= high + tol):
        raise CameraSettingError(
            f"{what} {value * scale:g} {unit} is outside the camera's range "
            f"[{low * scale:g}, {high * scale:g}] {unit}: choose a value inside it")


def to_uint8(image: np.ndarray, bits: int) -> np.ndarray:
    """Turn a monochrome frame of ``bits`` bits per pixel into uint8 counts.

    Parameters
    ----------
    image : numpy.ndarray
        (rows, columns) frame, uint8 for 8 bits, uint16 otherwise.
    bits : int
        Significant bits per pixel (8 to 16).

    Returns
    -------
    numpy.ndarray
        (rows, columns) uint8, C-contiguous, owning its data: the 8 most significant bits.
    """
    if bits == 8:
        return np.array(image, dtype=np.uint8, copy=True, order="C")
    return np.right_shift(np.asarray(image, dtype=np.uint16), bits - 8).astype(np.uint8, order="C")


def check_frame_shape(frame: np.ndarray, expected: tuple[int, int], source: str) -> np.ndarray:
    """Return ``frame`` if it is (rows, columns) = ``expected``, else raise :class:`CameraFrameSizeError`.

    Parameters
    ----------
    frame : numpy.ndarray
        The grabbed frame.
    expected : tuple of int
        (rows, columns) in pixels the station expects.
    source : str
        The camera's description, for the message.
    """
    if frame.ndim != 2 or tuple(frame.shape) != tuple(expected):
        got = " x ".join(str(n) for n in frame.shape)
        raise CameraFrameSizeError(
            f"{source} delivered a frame of {got} pixels (rows x columns) but the station expects "
            f"{expected[0]} x {expected[1]}: make the camera's region of interest (Width/Height) and the "
            "station's camera size (station.toml [camera] width_px/height_px) agree")
    return frame


def ms(seconds: float) -> int:
    """Seconds -> whole milliseconds, at least 0 (pylon timeouts)."""
    return max(0, int(math.ceil(seconds * 1000.0)))
