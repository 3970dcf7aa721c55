"""A GenICam camera (GigE Vision, USB3 Vision) over a transport: pylon (``basler.py``) or Aravis (``aravis.py``).

:class:`GenICamCamera` is the camera protocol the station relies on, whichever library reaches the camera:
it checks the arguments, opens and configures the camera (features, pixel format, region, trigger), sets
exposure (seconds) and gain (the camera's unit) within the camera's range, grabs a fresh frame with a
timeout, tells a timeout from a camera that has gone, and closes. A :class:`GenICamTransport` holds only
what a library does its own way: finding and opening a camera, reading and writing a GenICam node,
exposure and gain, starting and stopping the acquisition, firing a software trigger, taking one buffer,
and telling which of its exceptions mean that the camera has gone.

Acquisition runs continuously from opening to closing. By default every ``grab`` fires a software trigger
and returns the frame that trigger produced: frames already waiting when ``grab`` is called are dropped,
and so is a frame that reached the host before the trigger was sent (a late frame of an earlier,
timed-out trigger), where the transport knows when a frame arrived. ``trigger="freerun"`` lets the camera
run free and returns the first frame completed after the call (its exposure may have begun before it: the
display's settle time must then cover one frame period); any other value names a hardware trigger line
("Line1") and ``grab`` waits for the next frame that line triggers.

Every error is a :class:`~sofast_station.errors.CameraError`; after any of them the camera can be closed
and a new one opened.
"""

from __future__ import annotations

import abc
import contextlib
import logging
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from ...errors import CameraDisconnectedError, CameraError, CameraTimeoutError
from ._common import (CameraFrameSizeError, CameraIncompleteFrameError, CameraSettingError, check_exposure,
                      check_frame_shape, check_gain, check_in_range, check_pixel_format, check_shape)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Delivery:
    """One buffer a transport took from the camera's stream.

    Attributes
    ----------
    frame : numpy.ndarray or None
        (rows, columns) uint8 counts, owning its data; None when the buffer was damaged.
    damage : str
        What was wrong with a damaged buffer (the library's status or error code), "" otherwise.
    arrived_ns : int or None
        Host wall-clock time (``time.time_ns()``) at which the frame began to arrive, nanoseconds; None
        where the library does not tell.
    """

    frame: np.ndarray | None
    damage: str = ""
    arrived_ns: int | None = None


class GenICamTransport(abc.ABC):
    """What one GenICam library does for :class:`GenICamCamera`: the base of ``PylonTransport`` and
    ``AravisTransport``.

    A transport is created without touching its library; :meth:`load` imports it (raising
    :class:`~sofast_station.devices.cameras._common.CameraBackendMissingError`) and :meth:`open` finds and
    opens the camera. The other methods may raise the library's own exceptions (``error_types``): the
    camera turns them into station errors with :meth:`failures`, whose verdict (camera gone, timed out,
    or a plain failure) is the transport's :meth:`_verdict`.

    Attributes
    ----------
    requested : str or None
        What the station asked for (a serial number, device id or address); None takes the first camera.
    vendor, model, serial : str
        The opened camera's identity ("" until opened).
    handle : object or None
        The library's camera object while open, None before opening and after closing.
    broken : bool
        The camera was seen to have gone: do not talk to it again, only release it.
    error_types : tuple of type
        The library's exception classes (set by :meth:`load`).
    """

    #: The end of the "no feature" message: where a user finds the feature names.
    feature_hint = "check the feature name"
    #: A trigger line name of this kind of camera, for the message on an empty trigger.
    trigger_line_example = "Line1"

    def __init__(self, requested: str | None):
        self.requested = requested
        self.vendor = ""
        self.model = ""
        self.serial = ""
        self.handle = None
        self.broken = False
        self.error_types: tuple[type[BaseException], ...] = ()

    # -- what every transport must do -----------------------------------------------------------

    @abc.abstractmethod
    def load(self) -> None:
        """Import the library; raise CameraBackendMissingError naming what to install."""

    @abc.abstractmethod
    def unopened_description(self) -> str:
        """The camera as named in messages before its identity is known."""

    @abc.abstractmethod
    def open(self) -> None:
        """Find the requested camera, open it and read its identity (CameraNotFoundError, CameraError)."""

    @abc.abstractmethod
    def feature_kind(self, name: str) -> str | None:
        """The kind of the available feature ``name``: "command" or "value"; None when the camera lacks it."""

    @abc.abstractmethod
    def read(self, name: str):
        """The value of feature ``name`` (int, float, bool or str), None when absent or unreadable."""

    @abc.abstractmethod
    def write(self, name: str, value, required: bool) -> None:
        """Write ``value`` to the value feature ``name`` (a CameraSettingError when it cannot and
        ``required``; a library exception when the write itself fails)."""

    @abc.abstractmethod
    def execute(self, name: str) -> None:
        """Execute the command feature ``name``."""

    @abc.abstractmethod
    def quantity(self, name: str) -> float:
        """The value the camera reports of ``name``: "exposure" (microseconds) or "gain" (its unit)."""

    @abc.abstractmethod
    def quantity_range(self, name: str) -> tuple[float, float]:
        """(lowest, highest) value of "exposure" or "gain"; CameraSettingError when the camera has none."""

    @abc.abstractmethod
    def set_quantity(self, name: str, value: float) -> None:
        """Write "exposure" (microseconds) or "gain" (the camera's unit)."""

    @abc.abstractmethod
    def prepare_acquisition(self) -> None:
        """Everything the library needs before the acquisition starts (buffers, stream, packet size)."""

    @abc.abstractmethod
    def start(self) -> None:
        """Start the continuous acquisition."""

    @abc.abstractmethod
    def drop_waiting(self) -> int:
        """At the start of a grab: drop every frame already waiting (exposed before the grab) and return
        how many; raise CameraDisconnectedError where the library already knows the camera has gone."""

    @abc.abstractmethod
    def software_trigger(self, timeout_s: float) -> bool:
        """Fire a software trigger; False when the camera was not ready for one within ``timeout_s``."""

    @abc.abstractmethod
    def next_frame(self, timeout_s: float, bits: int) -> Delivery | None:
        """Wait up to ``timeout_s`` seconds for the next buffer; None when none came.

        ``bits`` is the pixel format's significant bits per pixel; the frame is returned as uint8 counts.
        """

    @abc.abstractmethod
    def check_alive(self) -> None:
        """Raise CameraDisconnectedError (and set :attr:`broken`) when the camera has gone."""

    @abc.abstractmethod
    def release(self) -> None:
        """Stop the acquisition and release the camera; set :attr:`handle` to None; never raise."""

    @abc.abstractmethod
    def _verdict(self, exc: BaseException, setting: bool) -> str | None:
        """What one of the library's exceptions means: "gone" (the camera), "timeout", or None (a plain failure)."""

    def _detail(self, exc: BaseException) -> str:
        """The library's own words for an exception."""
        return str(exc)

    # -- what they share ------------------------------------------------------------------------

    @property
    def description(self) -> str:
        """The camera as named in messages, e.g. "Basler acA1600-20gm (serial 12345678)"."""
        if self.serial or self.model:
            return f"{self.vendor} {self.model} (serial {self.serial})".strip()
        return self.unopened_description()

    @property
    def loss(self) -> str:
        """How the camera was lost, for the message once it is :attr:`broken`."""
        return "was disconnected"

    def classify(self, exc: BaseException, action: str, setting: bool = False) -> CameraError:
        """Turn one of the library's exceptions, raised while ``action``, into the station's camera error.

        Parameters
        ----------
        exc : BaseException
            The library's exception.
        action : str
            What was being done, e.g. "grabbing a frame", for the message.
        setting : bool
            A setting was being written: a plain failure is a CameraSettingError.
        """
        verdict, detail, name = self._verdict(exc, setting), self._detail(exc), self.description
        if verdict == "gone":
            self.broken = True
            return CameraDisconnectedError(f"{name} does not answer while {action} ({detail}): check the cable, "
                                           "power and network, then close and reopen the camera")
        if verdict == "timeout":
            return CameraTimeoutError(f"{name} timed out while {action}: {detail}")
        if setting:
            return CameraSettingError(f"{name}: {action} failed: {detail}")
        return CameraError(f"{name} failed while {action}: {detail}")

    @contextlib.contextmanager
    def failures(self, action: str, setting: bool = False) -> Iterator[None]:
        """Context in which the library's exceptions become station errors (see :meth:`classify`)."""
        try:
            yield
        except self.error_types as exc:
            raise self.classify(exc, action, setting) from exc


class GenICamCamera:
    """A GenICam camera behind the station's Camera protocol, reached through a transport.

    Parameters
    ----------
    transport : GenICamTransport
        The library that reaches the camera, not yet loaded or opened (``PylonTransport``,
        ``AravisTransport``); the camera opens it.
    expected_shape : tuple of int
        (rows, columns) in pixels every frame must have (the camera's Width/Height, set with the
        vendor's viewer, a user set, or ``features``).
    pixel_format : str
        GenICam PixelFormat to set: "Mono8" (default), or an unpacked "Mono10", "Mono12", "Mono14",
        "Mono16", whose 8 most significant bits are returned.
    trigger : str
        "software" (default: each grab fires a software trigger), "freerun", or the name of a trigger
        source line such as "Line1" (hardware trigger, e.g. from the display's vertical sync).
    features : mapping of str to object, optional
        GenICam features to set after opening, in order, before anything else: e.g.
        ``{"Width": 1600, "Height": 1200}``. A command feature is executed when its value is True or None.
    exposure_s : float, optional
        Exposure time to set on opening, seconds.
    gain : float, optional
        Gain to set on opening, in the camera's unit (dB for ``Gain``, raw counts for ``GainRaw``).

    Attributes
    ----------
    shape : tuple of int
        (rows, columns) of the frames, pixels.
    exposure_s : float
        The exposure time the camera reports, seconds (after rounding to its steps).
    gain : float
        The gain the camera reports, in its unit.
    frames_grabbed, frames_dropped : int
        Frames returned by ``grab``, and frames dropped as stale (waiting before a grab, or arrived
        before its software trigger), since opening.

    Raises
    ------
    CameraBackendMissingError
        The transport's library is not installed.
    CameraNotFoundError
        No camera answers to the requested identity (the message lists the cameras found, where the
        library can list them without a network broadcast).
    CameraFrameSizeError
        The camera's Width/Height differ from ``expected_shape``.
    CameraSettingError
        A setting is not supported, not writable or out of range.
    CameraError
        The camera could not be opened or could not start its acquisition.
    """

    def __init__(self, transport: GenICamTransport, expected_shape: tuple[int, int], pixel_format: str = "Mono8",
                 *, trigger: str = "software", features: Mapping[str, object] | None = None,
                 exposure_s: float | None = None, gain: float | None = None):
        self._transport = transport
        self.shape = check_shape(expected_shape)
        self.pixel_format = str(pixel_format)
        self._bits = check_pixel_format(self.pixel_format)
        self.trigger = str(trigger).strip()
        if self.trigger.lower() in ("software", "freerun"):
            self.trigger = self.trigger.lower()
        if not self.trigger:
            raise CameraSettingError('trigger must be "software", "freerun" or a trigger line such as '
                                     f'"{transport.trigger_line_example}"')
        self.exposure_s = float("nan")
        self.gain = float("nan")
        self.frames_grabbed = 0
        self.frames_dropped = 0
        transport.load()
        try:
            # A library exception no step below expected must still reach the station as a CameraError.
            with transport.failures("opening the camera"):
                self._open(features or {})
                if exposure_s is not None:
                    self.set_exposure(exposure_s)
                if gain is not None:
                    self.set_gain(gain)
            with transport.failures("starting the acquisition"):
                transport.start()
        except BaseException:
            self.close()
            raise

    # -- identity --------------------------------------------------------------------------------

    @property
    def description(self) -> str:
        """The camera as named in messages, e.g. "Basler acA1600-20gm (serial 12345678)"."""
        return self._transport.description

    vendor = property(lambda self: self._transport.vendor, doc="The opened camera's vendor name.")
    model = property(lambda self: self._transport.model, doc="The opened camera's model name.")
    serial = property(lambda self: self._transport.serial, doc="The opened camera's serial number.")

    @property
    def _camera(self):
        # The library's own camera object (None once closed): for tests that reach past the protocol,
        # e.g. to make pylon's emulated camera fail.
        return self._transport.handle

    # -- opening ---------------------------------------------------------------------------------

    def _open(self, features: Mapping[str, object]) -> None:
        transport = self._transport
        transport.open()
        log.info("opened %s (asked for %r)", self.description, transport.requested)
        for name, value in features.items():
            self._set_feature(name, value)
        if transport.read("PixelFormat") != self.pixel_format:
            self._set_feature("PixelFormat", self.pixel_format)
        width, height = transport.read("Width"), transport.read("Height")
        if width is not None and height is not None and (int(height), int(width)) != self.shape:
            raise CameraFrameSizeError(
                f"{self.description} is set to frames of {height} x {width} pixels (rows x columns) but the "
                f"station expects {self.shape[0]} x {self.shape[1]}: make the camera's Width/Height (region "
                "of interest) and the station's camera size (station.toml [camera]) agree")
        self._configure_trigger()
        self._set_feature("AcquisitionMode", "Continuous", required=False)
        with transport.failures("creating the image stream"):
            transport.prepare_acquisition()
        self.exposure_s = self._quietly("exposure") * 1e-6
        self.gain = self._quietly("gain")

    def _configure_trigger(self) -> None:
        if self._transport.feature_kind("TriggerSelector") is not None:
            self._set_feature("TriggerSelector", "FrameStart")
        if self.trigger == "freerun":
            self._set_feature("TriggerMode", "Off", required=False)
        else:
            self._set_feature("TriggerMode", "On")
            self._set_feature("TriggerSource", "Software" if self.trigger == "software" else self.trigger)

    def _quietly(self, name: str) -> float:
        """The camera's "exposure" or "gain", NaN when it cannot tell."""
        try:
            return float(self._transport.quantity(name))
        except (CameraError, *self._transport.error_types):
            return float("nan")

    # -- GenICam features ------------------------------------------------------------------------

    def _set_feature(self, name: str, value, required: bool = True) -> None:
        """Set (or execute) one GenICam feature; raise CameraSettingError naming it on failure.

        A feature the camera lacks is skipped when not ``required``.
        """
        transport = self._transport
        kind = transport.feature_kind(name)
        if kind is None:
            if required:
                raise CameraSettingError(f"{self.description} has no feature {name!r}: {transport.feature_hint} "
                                         "or the camera model")
            log.debug("%s: no feature %s, skipped", self.description, name)
            return
        with transport.failures(f"setting {name} to {value!r}", setting=True):
            if kind == "command":
                if value not in (None, True):
                    raise CameraSettingError(f"{name} is a command: give it the value true to execute it")
                transport.execute(name)
            else:
                transport.write(name, value, required)
        log.debug("%s: %s = %r", self.description, name, value)

    # -- exposure and gain -----------------------------------------------------------------------

    def _range(self, name: str, scale: float) -> tuple[float, float]:
        self._require_open()
        try:
            low, high = self._transport.quantity_range(name)
        except (CameraError, *self._transport.error_types):
            return (float("nan"), float("nan"))
        return float(low) * scale, float(high) * scale

    @property
    def exposure_range_s(self) -> tuple[float, float]:
        """(shortest, longest) exposure time the camera accepts, seconds (NaN when it cannot tell)."""
        return self._range("exposure", 1e-6)

    @property
    def gain_range(self) -> tuple[float, float]:
        """(lowest, highest) gain the camera accepts, in its unit (NaN when it cannot tell)."""
        return self._range("gain", 1.0)

    def _set_quantity(self, name: str, value: float, action: str, unit: str, scale: float) -> float:
        """Write exposure or gain ``value`` (camera's unit) within the camera's range; return what it reports."""
        self._require_open()
        transport = self._transport
        with transport.failures(action, setting=True):
            low, high = transport.quantity_range(name)
            # An automatic exposure or gain would overwrite the value the station chose.
            self._set_feature("ExposureAuto" if name == "exposure" else "GainAuto", "Off", required=False)
            check_in_range(name, value, low, high, unit, scale=scale)
            transport.set_quantity(name, value)
            return float(transport.quantity(name))

    def set_exposure(self, seconds: float) -> None:
        """Set the exposure time.

        Parameters
        ----------
        seconds : float
            Exposure time, seconds (written in microseconds to ExposureTime or ExposureTimeAbs; the
            camera rounds to its step, and :attr:`exposure_s` holds the value it reports).

        Raises
        ------
        CameraSettingError
            Outside the camera's range, or the camera has no writable exposure time.
        CameraDisconnectedError
            The camera is gone.
        """
        seconds = check_exposure(seconds)
        us = self._set_quantity("exposure", seconds * 1e6, f"setting the exposure to {seconds:g} s", "s", 1e-6)
        self.exposure_s = us * 1e-6
        log.debug("%s: exposure %.6f s (asked %.6f s)", self.description, self.exposure_s, seconds)

    def set_gain(self, gain: float) -> None:
        """Set the gain.

        Parameters
        ----------
        gain : float
            In the camera's unit: dB for ``Gain``, raw counts for ``GainRaw`` (rounded to an integer).
            :attr:`gain` holds the value the camera reports.

        Raises
        ------
        CameraSettingError
            Outside the camera's range (:attr:`gain_range`), or the camera has no writable gain.
        CameraDisconnectedError
            The camera is gone.
        """
        gain = check_gain(gain)
        self.gain = self._set_quantity("gain", gain, f"setting the gain to {gain:g}", "(camera units)", 1.0)
        log.debug("%s: gain %g (asked %g)", self.description, self.gain, gain)

    # -- grabbing --------------------------------------------------------------------------------

    def _require_open(self) -> None:
        transport = self._transport
        if transport.handle is None:
            raise CameraError(f"{self.description} is closed; open a new camera")
        if transport.broken:
            raise CameraDisconnectedError(f"{self.description} {transport.loss}; check the cable, power and "
                                          "network, then close and reopen the camera")

    def _no_frame(self, message: str) -> CameraTimeoutError:
        """The timeout error, once the camera is known to be still there (else CameraDisconnectedError)."""
        self._transport.check_alive()
        self._require_open()
        return CameraTimeoutError(message)

    def grab(self, timeout_s: float = 2.0) -> np.ndarray:
        """Grab one frame.

        Parameters
        ----------
        timeout_s : float
            Longest wait for the frame, seconds. (Finding out that a camera has gone can take longer:
            Aravis retries a control command for about 2.5 s.)

        Returns
        -------
        numpy.ndarray
            (rows, columns) uint8 counts.

        Raises
        ------
        CameraTimeoutError
            No frame within ``timeout_s`` while the camera is still there.
        CameraDisconnectedError
            The camera was removed or stopped answering; close it and open a new one.
        CameraIncompleteFrameError
            The frame arrived damaged (lost packets: check the network card, packet size and delay).
        CameraFrameSizeError
            The frame's size differs from ``expected_shape``.
        CameraError
            The camera was closed, or its library failed otherwise.
        """
        self._require_open()
        transport = self._transport
        timeout_s = max(0.0, float(timeout_s))
        deadline = time.monotonic() + timeout_s
        with transport.failures("grabbing a frame"):
            dropped = transport.drop_waiting()
            if dropped:
                self.frames_dropped += dropped
                log.debug("%s: dropped %d stale frame(s)", self.description, dropped)
        sent_ns = time.time_ns()
        if self.trigger == "software":
            with transport.failures("sending a software trigger"):
                ready = transport.software_trigger(max(0.0, deadline - time.monotonic()))
            if not ready:
                raise self._no_frame(f"{self.description} was not ready for a software trigger within "
                                     f"{timeout_s:g} s; check the exposure time and frame rate")
        while True:
            with transport.failures("grabbing a frame"):
                got = transport.next_frame(max(0.0, deadline - time.monotonic()), self._bits)
            if got is None:
                source = {"software": "after a software trigger", "freerun": "in free run"}.get(
                    self.trigger, f"from trigger line {self.trigger}")
                raise self._no_frame(f"{self.description}: no frame {source} within {timeout_s:g} s; "
                                     "check the trigger, exposure time and frame rate")
            # A frame whose first packet reached the host before the trigger is a late, stale one.
            if self.trigger == "software" and got.arrived_ns is not None and got.arrived_ns < sent_ns:
                self.frames_dropped += 1
                continue
            break
        if got.frame is None:
            transport.check_alive()
            self._require_open()
            raise CameraIncompleteFrameError(
                f"{self.description} delivered a damaged frame ({got.damage}); check the network card, packet "
                "size and inter-packet delay, or the USB link")
        self.frames_grabbed += 1
        return check_frame_shape(got.frame, self.shape, self.description)

    # -- closing ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the acquisition and release the camera (idempotent, never raises)."""
        if self._transport.handle is None:
            return
        self._transport.release()
        log.info("closed %s", self.description)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        transport = self._transport
        state = "closed" if transport.handle is None else ("disconnected" if transport.broken else "open")
        return f"<{type(self).__name__} {self.description}, {self.shape[0]} x {self.shape[1]}, {state}>"


__all__ = ["GenICamCamera", "GenICamTransport", "Delivery"]
