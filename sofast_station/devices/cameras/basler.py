"""Basler cameras (GigE, USB3 Vision, and pylon's camera emulation) through pypylon.

Acquisition runs continuously from ``open`` to ``close``. By default every ``grab`` fires a software
trigger and waits for that frame, so a frame is always exposed after ``grab`` was called (after the display
showed its image), never a stale one from a queue. ``trigger="freerun"`` lets the camera run free and
returns the first frame completed after the call (its exposure may have begun before it: the display's
settle time must then cover one frame period); any other value names a hardware trigger line ("Line1")
and ``grab`` waits for the next frame that line triggers.

pylon talks microseconds; this module talks seconds. Exposure goes to ``ExposureTime`` (SFNC 2, most
current models) or ``ExposureTimeAbs`` (older GigE models); gain to ``Gain`` (dB) or ``GainRaw`` (the
camera's raw units), whichever the model has, and ``set_gain`` takes that feature's own unit.

The emulated cameras appear when the environment variable ``PYLON_CAMEMU`` is set to their number before
pylon enumerates devices (pypylon reads it at enumeration, so setting it after ``import pypylon`` works).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping

import numpy as np

from ...errors import CameraDisconnectedError, CameraError, CameraTimeoutError
from ._common import (CameraBackendMissingError, CameraFrameSizeError, CameraIncompleteFrameError,
                      CameraNotFoundError, CameraSettingError, check_exposure, check_frame_shape, check_gain,
                      check_in_range, check_pixel_format, check_shape, ms, to_uint8)

log = logging.getLogger(__name__)

#: The pip requirement that provides this backend.
PIP_REQUIREMENT = "pypylon==26.9"


def _import_pylon():
    """Return (pylon, genicam) from pypylon, or raise CameraBackendMissingError naming the package."""
    try:
        from pypylon import genicam, pylon
    except ImportError as exc:
        raise CameraBackendMissingError(
            f"the Basler camera backend needs pypylon, which is not installed or does not load ({exc}); "
            f"install it into the station's environment: pip install '{PIP_REQUIREMENT}'") from exc
    return pylon, genicam


def _enumerate(pylon, device_class: str | None) -> list:
    """Device infos of every transport layer, or only of ``device_class``'s (no network discovery of
    GigE cameras unless that transport layer is enumerated)."""
    factory = pylon.TlFactory.GetInstance()
    if not device_class:
        return list(factory.EnumerateDevices())
    tl = factory.CreateTl(str(device_class))
    if tl is None:
        raise CameraSettingError(f"pylon has no transport layer {device_class!r}: use BaslerGigE, BaslerUsb, "
                                 "BaslerGTC/Basler/CXP or BaslerCamEmu, or leave device_class unset")
    return list(tl.EnumerateDevices())


def list_cameras(device_class: str | None = None) -> list[dict[str, str]]:
    """The Basler cameras pylon can see now (real ones, and emulated ones when PYLON_CAMEMU is set).

    Parameters
    ----------
    device_class : str, optional
        Only this transport layer's cameras, e.g. "BaslerUsb", "BaslerGigE", "BaslerCamEmu".
        Enumerating GigE cameras broadcasts a discovery packet on every network interface.

    Returns
    -------
    list of dict
        One dict per camera: serial, model, vendor, device_class, friendly_name.

    Raises
    ------
    CameraBackendMissingError
        pypylon is not installed.
    """
    pylon, genicam = _import_pylon()
    out = []
    try:
        infos = _enumerate(pylon, device_class)
    except genicam.GenericException as exc:
        raise CameraError(f"pylon could not list the cameras: {exc}") from exc
    for info in infos:
        out.append({"serial": info.GetSerialNumber(), "model": info.GetModelName(),
                    "vendor": info.GetVendorName(), "device_class": info.GetDeviceClass(),
                    "friendly_name": info.GetFriendlyName()})
    return out


class BaslerCamera:
    """Camera backend for Basler cameras through pypylon.

    Parameters
    ----------
    serial : str or None
        The camera's serial number; None takes the first camera pylon finds.
    expected_shape : tuple of int
        (rows, columns) in pixels every frame must have (the camera's Width/Height, set with the
        pylon Viewer, a user set, or ``features``).
    pixel_format : str
        GenICam PixelFormat to set: "Mono8" (default), or an unpacked "Mono10", "Mono12", "Mono16",
        whose 8 most significant bits are returned.
    trigger : str
        "software" (default: each grab fires a software trigger), "freerun", or the name of a trigger
        source line such as "Line1" (hardware trigger, e.g. from the display's vertical sync).
    features : mapping of str to object, optional
        GenICam features to set after opening, in order, before anything else: e.g.
        ``{"Width": 1600, "Height": 1200, "GevSCPSPacketSize": 8192}``. A command feature is executed when
        its value is True or None.
    exposure_s : float, optional
        Exposure time to set on opening, seconds.
    gain : float, optional
        Gain to set on opening, in the camera's unit (dB for ``Gain``, raw counts for ``GainRaw``).
    max_buffers : int
        Number of frame buffers pylon allocates.
    device_class : str, optional
        Look for the camera only in this pylon transport layer ("BaslerGigE", "BaslerUsb",
        "BaslerCamEmu"); by default every transport layer is searched, which broadcasts a GigE Vision
        discovery packet on every network interface.

    Attributes
    ----------
    shape : tuple of int
        (rows, columns) of the frames, pixels.
    serial, model : str
        The opened camera's serial number and model name.
    exposure_s : float
        The exposure time the camera reports, seconds (after rounding to its steps).
    gain : float
        The gain the camera reports, in its unit.
    frames_grabbed : int
        Frames returned by ``grab`` since opening.

    Raises
    ------
    CameraBackendMissingError
        pypylon is not installed.
    CameraNotFoundError
        No camera with that serial number (the message lists the cameras found).
    CameraFrameSizeError
        The camera's Width/Height differ from ``expected_shape``.
    CameraSettingError
        A setting is not supported, not writable or out of range.
    CameraError
        The camera could not be opened (e.g. another program holds it).
    """

    def __init__(self, serial: str | None, expected_shape: tuple[int, int], pixel_format: str = "Mono8", *,
                 trigger: str = "software", features: Mapping[str, object] | None = None,
                 exposure_s: float | None = None, gain: float | None = None, max_buffers: int = 10,
                 device_class: str | None = None):
        self.shape = check_shape(expected_shape)
        self.pixel_format = str(pixel_format)
        self._bits = check_pixel_format(self.pixel_format)
        self.trigger = str(trigger).strip()
        if self.trigger.lower() in ("software", "freerun"):
            self.trigger = self.trigger.lower()
        if not self.trigger:
            raise CameraSettingError('trigger must be "software", "freerun" or a trigger line such as "Line1"')
        self.requested_serial = serial
        self.device_class = device_class
        self.serial = ""
        self.model = ""
        self.exposure_s = float("nan")
        self.gain = float("nan")
        self.frames_grabbed = 0
        self._camera = None
        self._broken = False           # a disconnect was seen: do not talk to the device when closing
        self._restart = False          # a grab timed out: restart acquisition to drop late frames
        self._pylon, self._genicam = _import_pylon()
        try:
            self._open(features or {}, int(max_buffers))
            if exposure_s is not None:
                self.set_exposure(exposure_s)
            if gain is not None:
                self.set_gain(gain)
            self._start()
        except BaseException:
            self.close()
            raise

    # -- opening ---------------------------------------------------------------------------------

    @property
    def description(self) -> str:
        """The camera as named in messages, e.g. "Basler acA1600-20gm (serial 12345678)"."""
        if self.serial:
            return f"Basler {self.model} (serial {self.serial})"
        return f"Basler camera (serial {self.requested_serial})" if self.requested_serial else "Basler camera"

    def _open(self, features: Mapping[str, object], max_buffers: int) -> None:
        pylon, genicam = self._pylon, self._genicam
        factory = pylon.TlFactory.GetInstance()
        try:
            devices = _enumerate(pylon, self.device_class)
        except genicam.GenericException as exc:
            raise CameraError(f"pylon could not list the cameras: {exc}") from exc
        if self.requested_serial is None:
            chosen = devices[0] if devices else None
        else:
            chosen = next((d for d in devices if d.GetSerialNumber() == str(self.requested_serial)), None)
        if chosen is None:
            found = ", ".join(f"{d.GetModelName()} (serial {d.GetSerialNumber()})" for d in devices) or "none"
            wanted = f"with serial {self.requested_serial}" if self.requested_serial else "at all"
            raise CameraNotFoundError(
                f"no Basler camera found {wanted} (cameras found: {found}); check the camera's power and "
                "cable, its network settings (pylon IP Configurator) and that no other program uses it")
        try:
            self._camera = pylon.InstantCamera(factory.CreateDevice(chosen))
            self.serial = self._camera.GetDeviceInfo().GetSerialNumber()
            self.model = self._camera.GetDeviceInfo().GetModelName()
            self._camera.Open()
        except genicam.GenericException as exc:
            raise CameraError(f"could not open {self.description}: {exc}; check that no other program "
                              "(pylon Viewer, another station) has it open, then retry") from exc
        log.info("opened %s", self.description)

        for name, value in features.items():
            self._set_feature(name, value)
        if self._read("PixelFormat") != self.pixel_format:
            self._set_feature("PixelFormat", self.pixel_format)
        width, height = self._read("Width"), self._read("Height")
        if width is not None and height is not None and (int(height), int(width)) != self.shape:
            raise CameraFrameSizeError(
                f"{self.description} is set to frames of {height} x {width} pixels (rows x columns) but the "
                f"station expects {self.shape[0]} x {self.shape[1]}: make the camera's Width/Height (region "
                "of interest) and the station's camera size (station.toml [camera]) agree")
        self._configure_trigger()
        self._set_feature("AcquisitionMode", "Continuous", required=False)
        try:
            self._camera.MaxNumBuffer.Value = max(2, max_buffers)
        except genicam.GenericException as exc:  # not fatal: pylon keeps its default
            log.debug("%s: MaxNumBuffer not set: %s", self.description, exc)
        self.exposure_s = self._read_exposure_s()
        self.gain = self._read_gain()

    def _configure_trigger(self) -> None:
        if self._node("TriggerSelector") is not None:
            self._set_feature("TriggerSelector", "FrameStart")
        if self.trigger == "freerun":
            self._set_feature("TriggerMode", "Off", required=False)
        else:
            self._set_feature("TriggerMode", "On")
            source = "Software" if self.trigger == "software" else self.trigger
            self._set_feature("TriggerSource", source)

    def _start(self) -> None:
        pylon, genicam = self._pylon, self._genicam
        try:
            self._camera.StartGrabbing(pylon.GrabStrategy_OneByOne)
        except genicam.GenericException as exc:
            raise self._classify(exc, "starting the acquisition") from exc
        self._restart = False

    # -- GenICam features ------------------------------------------------------------------------

    def _node(self, name: str):
        """The pypylon parameter ``name``, or None when the camera has no such (available) feature."""
        genicam = self._genicam
        try:
            node = self._camera.GetNodeMap().GetNode(name)
        except genicam.GenericException:
            return None
        if node is None or type(node).__name__ == "PlaceholderParameter":
            return None
        try:
            return node if genicam.IsAvailable(node) else None
        except genicam.GenericException:
            return None

    def _read(self, name: str):
        node = self._node(name)
        if node is None or not self._genicam.IsReadable(node):
            return None
        try:
            return node.Value
        except self._genicam.GenericException:
            return None

    def _set_feature(self, name: str, value, required: bool = True) -> None:
        """Set (or execute) one GenICam feature; raise CameraSettingError naming it on failure."""
        genicam = self._genicam
        node = self._node(name)
        if node is None:
            if required:
                raise CameraSettingError(f"{self.description} has no feature {name!r}: check the feature "
                                         "name (pylon Viewer shows them) or the camera model")
            log.debug("%s: no feature %s, skipped", self.description, name)
            return
        try:
            if type(node).__name__ == "CommandParameter":
                if value not in (None, True):
                    raise CameraSettingError(f"{name} is a command: give it the value true to execute it")
                node.Execute()
                return
            if not genicam.IsWritable(node):
                if genicam.IsReadable(node) and str(node.ToString()) == str(value):
                    return          # already set, e.g. a read-only feature at the wanted value
                if required:
                    raise CameraSettingError(f"{self.description}: feature {name} is not writable now "
                                             "(locked while grabbing, or by another setting)")
                return
            if isinstance(value, str) or type(node).__name__ in ("EnumParameter", "StringParameter"):
                node.FromString(str(value))
            else:
                node.Value = value
        except genicam.GenericException as exc:
            raise CameraSettingError(f"{self.description}: could not set {name} to {value!r}: {exc}") from exc
        log.debug("%s: %s = %r", self.description, name, value)

    # -- exposure and gain -----------------------------------------------------------------------

    def _exposure_node(self):
        for name in ("ExposureTime", "ExposureTimeAbs"):
            node = self._node(name)
            if node is not None:
                return node
        return None

    def _read_exposure_s(self) -> float:
        node = self._exposure_node()
        try:
            return float(node.Value) * 1e-6 if node is not None else float("nan")
        except self._genicam.GenericException:
            return float("nan")

    def _gain_node(self):
        for name in ("Gain", "GainRaw"):
            node = self._node(name)
            if node is not None:
                return node
        return None

    def _read_gain(self) -> float:
        node = self._gain_node()
        try:
            return float(node.Value) if node is not None else float("nan")
        except self._genicam.GenericException:
            return float("nan")

    @property
    def exposure_range_s(self) -> tuple[float, float]:
        """(shortest, longest) exposure time the camera accepts, seconds."""
        node = self._exposure_node()
        if node is None:
            return (float("nan"), float("nan"))
        return float(node.Min) * 1e-6, float(node.Max) * 1e-6

    @property
    def gain_range(self) -> tuple[float, float]:
        """(lowest, highest) gain the camera accepts, in its unit."""
        node = self._gain_node()
        if node is None:
            return (float("nan"), float("nan"))
        return float(node.Min), float(node.Max)

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
        self._require_open()
        node = self._exposure_node()
        if node is None:
            raise CameraSettingError(f"{self.description} has neither ExposureTime nor ExposureTimeAbs")
        self._set_feature("ExposureAuto", "Off", required=False)
        us = seconds * 1e6
        try:
            check_in_range("exposure", us, float(node.Min), float(node.Max), "s", scale=1e-6)
            node.Value = us
            self.exposure_s = float(node.Value) * 1e-6
        except self._genicam.GenericException as exc:
            raise self._classify(exc, f"setting the exposure to {seconds:g} s", setting=True) from exc
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
        self._require_open()
        node = self._gain_node()
        if node is None:
            raise CameraSettingError(f"{self.description} has neither Gain nor GainRaw")
        self._set_feature("GainAuto", "Off", required=False)
        try:
            check_in_range("gain", gain, float(node.Min), float(node.Max), "(camera units)")
            node.Value = int(round(gain)) if type(node).__name__ == "IntegerParameter" else gain
            self.gain = float(node.Value)
        except self._genicam.GenericException as exc:
            raise self._classify(exc, f"setting the gain to {gain:g}", setting=True) from exc
        log.debug("%s: gain %g (asked %g)", self.description, self.gain, gain)

    # -- grabbing --------------------------------------------------------------------------------

    def _require_open(self):
        if self._camera is None:
            raise CameraError(f"{self.description} is closed; open a new camera")
        if self._broken:
            raise CameraDisconnectedError(f"{self.description} was disconnected; close it and open it again")
        return self._camera

    def _check_alive(self) -> None:
        """Raise CameraDisconnectedError when pylon reports the device removed or no longer grabbing."""
        cam = self._camera
        try:
            removed = cam.IsCameraDeviceRemoved()
            attached = cam.IsPylonDeviceAttached() and cam.IsOpen()
            grabbing = cam.IsGrabbing()
        except self._genicam.GenericException as exc:
            self._broken = True
            raise CameraDisconnectedError(f"{self.description} does not answer ({exc}); check the cable and "
                                          "power, then close and reopen the camera") from exc
        if removed or not attached or not grabbing:
            self._broken = True
            what = ("was removed (unplugged, power or network lost)" if removed
                    else "was closed underneath the station" if not attached else "stopped grabbing")
            raise CameraDisconnectedError(f"{self.description} {what}; check the cable and power, then close "
                                          "and reopen the camera")

    def _classify(self, exc: Exception, action: str, setting: bool = False) -> CameraError:
        """Turn a pylon exception into the station's camera error."""
        genicam = self._genicam
        try:
            removed = self._camera is not None and self._camera.IsCameraDeviceRemoved()
        except genicam.GenericException:
            removed = True
        if removed or (not setting and isinstance(exc, genicam.RuntimeException)):
            self._broken = True
            return CameraDisconnectedError(f"{self.description} failed while {action} ({exc}); the camera is "
                                           "gone or not answering: check cable and power, then close and reopen")
        if isinstance(exc, genicam.TimeoutException):
            return CameraTimeoutError(f"{self.description} timed out while {action}: {exc}")
        if setting:
            return CameraSettingError(f"{self.description}: {action} failed: {exc}")
        return CameraError(f"{self.description} failed while {action}: {exc}")

    def _drain(self) -> int:
        """Drop frames that are already waiting, so the next one is fresh. Returns the number dropped."""
        pylon = self._pylon
        dropped = 0
        while True:
            result = self._camera.RetrieveResult(0, pylon.TimeoutHandling_Return)
            with result:
                if not result.IsValid():
                    return dropped
                dropped += 1

    def grab(self, timeout_s: float = 2.0) -> np.ndarray:
        """Grab one frame.

        Parameters
        ----------
        timeout_s : float
            Longest wait for the frame, seconds.

        Returns
        -------
        numpy.ndarray
            (rows, columns) uint8 counts.

        Raises
        ------
        CameraTimeoutError
            No frame within ``timeout_s`` (the camera is still there).
        CameraDisconnectedError
            The camera was removed or stopped answering; close it and open a new one.
        CameraIncompleteFrameError
            The frame arrived damaged (lost packets: check the network card, packet size and delay).
        CameraFrameSizeError
            The frame's size differs from ``expected_shape``.
        CameraError
            The camera was closed, or pylon failed otherwise.
        """
        pylon, genicam = self._pylon, self._genicam
        cam = self._require_open()
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        try:
            if self._restart:       # a frame of a timed-out trigger may still come: start afresh
                cam.StopGrabbing()
                self._start()
            self._check_alive()
            dropped = self._drain()
            if dropped:
                log.debug("%s: dropped %d stale frame(s)", self.description, dropped)
            if self.trigger == "software":
                if not cam.WaitForFrameTriggerReady(ms(deadline - time.monotonic()), pylon.TimeoutHandling_Return):
                    self._check_alive()
                    self._restart = True
                    raise CameraTimeoutError(f"{self.description} was not ready for a software trigger within "
                                             f"{timeout_s:g} s; check the exposure time and frame rate")
                cam.ExecuteSoftwareTrigger()
            result = cam.RetrieveResult(ms(deadline - time.monotonic()), pylon.TimeoutHandling_Return)
            with result:
                if not result.IsValid():
                    self._check_alive()
                    self._restart = True
                    source = {"software": "after a software trigger", "freerun": "in free run"}.get(
                        self.trigger, f"from trigger line {self.trigger}")
                    raise CameraTimeoutError(f"{self.description}: no frame {source} within {timeout_s:g} s; "
                                             "check the trigger, exposure time and frame rate")
                if not result.GrabSucceeded():
                    self._check_alive()
                    raise CameraIncompleteFrameError(
                        f"{self.description} delivered a damaged frame (error {result.GetErrorCode():#x}: "
                        f"{result.GetErrorDescription()}); check the network card, packet size and "
                        "inter-packet delay, or the USB link")
                frame = to_uint8(result.GetArray(), self._bits)
        except genicam.GenericException as exc:
            raise self._classify(exc, "grabbing a frame") from exc
        self.frames_grabbed += 1
        return check_frame_shape(frame, self.shape, self.description)

    # -- closing ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop grabbing and release the camera (idempotent, never raises)."""
        cam, self._camera = self._camera, None
        if cam is None:
            return
        genicam = self._genicam
        for step in ("StopGrabbing", "Close", "DestroyDevice"):
            try:
                getattr(cam, step)()
            except genicam.GenericException as exc:
                log.debug("%s: %s failed while closing: %s", self.description, step, exc)
            except Exception as exc:  # closing must never raise
                log.warning("%s: %s failed while closing: %s", self.description, step, exc)
        log.info("closed %s", self.description)

    def __enter__(self) -> "BaslerCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._camera is None else ("disconnected" if self._broken else "open")
        return f"<BaslerCamera {self.description}, {self.shape[0]} x {self.shape[1]}, {state}>"
