"""GigE Vision (and USB3 Vision) cameras through Aravis 0.8, via GObject introspection.

Acquisition runs continuously from ``open`` to ``close`` into a small pool of buffers. By default every
``grab`` fires a software trigger and returns the frame that trigger produced: frames that reached the
host before the trigger was sent (stale ones, or a late frame of an earlier, timed-out trigger) are
recycled, judged by the host time at which the frame's first packet arrived. ``trigger="freerun"``
returns the first frame arriving after the call (its exposure may have begun before it); any other value
names a hardware trigger line ("Line0", "Line1") and ``grab`` waits for the next frame.

Disconnects: Aravis reports a lost camera through the device's ``control-lost`` signal (heartbeat), and a
control command to a camera that has gone away fails after Aravis's retries (5 x 0.5 s on Aravis 0.8.26).
When a grab times out without a command failing, the camera is probed with a register read: if that fails
too, the grab raises CameraDisconnectedError, else CameraTimeoutError.

Needs, on Debian 12: ``gir1.2-aravis-0.8`` (the typelib, pulling in ``libaravis-0.8-0``), and PyGObject in
the Python environment: ``python3-gi`` for the system Python, or ``pip install 'PyGObject<3.51'`` in a
virtual environment (newer releases need a newer GLib than Debian 12's), which builds from source and
needs ``libgirepository1.0-dev libcairo2-dev pkg-config python3-dev gcc``.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import time
from collections.abc import Mapping

import numpy as np

from ...errors import CameraDisconnectedError, CameraError, CameraTimeoutError
from ._common import (CameraBackendMissingError, CameraFrameSizeError, CameraIncompleteFrameError,
                      CameraNotFoundError, CameraSettingError, check_exposure, check_frame_shape, check_gain,
                      check_in_range, check_pixel_format, check_shape, to_uint8)

log = logging.getLogger(__name__)

#: What this backend needs installed, named in the error raised when it is missing.
PIP_REQUIREMENT = "PyGObject<3.51"
DEBIAN_PACKAGES = "gir1.2-aravis-0.8"
BUILD_PREREQUISITES = "libgirepository1.0-dev libcairo2-dev pkg-config python3-dev gcc"


def _import_aravis():
    """Return (Aravis, GLib) or raise CameraBackendMissingError naming what to install."""
    try:
        import gi
    except ImportError as exc:
        raise CameraBackendMissingError(
            f"the Aravis camera backend needs PyGObject, which is not installed ({exc}): install the build "
            f"prerequisites (apt-get install {BUILD_PREREQUISITES}), then pip install '{PIP_REQUIREMENT}'; "
            f"Aravis itself comes with apt-get install {DEBIAN_PACKAGES}") from exc
    try:
        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis, GLib
    except (ValueError, ImportError) as exc:
        raise CameraBackendMissingError(
            f"the Aravis camera backend needs the Aravis 0.8 introspection data, which is not installed "
            f"({exc}): apt-get install {DEBIAN_PACKAGES}") from exc
    return Aravis, GLib


def list_cameras() -> list[dict[str, str]]:
    """The cameras Aravis finds now (GigE Vision discovery on every interface, and USB3 Vision).

    Returns
    -------
    list of dict
        One dict per camera: device_id, address, serial, model, vendor, protocol.

    Raises
    ------
    CameraBackendMissingError
        PyGObject or the Aravis typelib is not installed.
    """
    Aravis, _ = _import_aravis()
    Aravis.update_device_list()
    return [{"device_id": Aravis.get_device_id(i) or "", "address": Aravis.get_device_address(i) or "",
             "serial": Aravis.get_device_serial_nbr(i) or "", "model": Aravis.get_device_model(i) or "",
             "vendor": Aravis.get_device_vendor(i) or "", "protocol": Aravis.get_device_protocol(i) or ""}
            for i in range(Aravis.get_n_devices())]


def _is_ip_address(text) -> bool:
    try:
        ipaddress.ip_address(str(text))
    except ValueError:
        return False
    return True


def _release(held: list, description: str) -> None:
    """Drop Aravis objects in order (their finalizers may block on a camera that has gone)."""
    t0 = time.monotonic()
    while held:
        held.pop(0)
    log.debug("%s: released in %.2f s", description, time.monotonic() - t0)


class AravisCamera:
    """Camera backend for GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8.

    Parameters
    ----------
    device_id : str or None
        What Aravis opens: the camera's IP address (opened directly, no discovery broadcast), or a device
        id ("<vendor>-<model>-<serial>", as ``arv-tool-0.8`` lists them) or serial number, found by a
        GigE Vision discovery broadcast on every network interface; None takes the first camera found.
    expected_shape : tuple of int
        (rows, columns) in pixels every frame must have.
    pixel_format : str
        GenICam PixelFormat to set: "Mono8" (default) or an unpacked "Mono10", "Mono12", "Mono16", whose
        8 most significant bits are returned.
    trigger : str
        "software" (default: each grab fires a software trigger), "freerun", or a trigger source line
        such as "Line0" (hardware trigger).
    features : mapping of str to object, optional
        GenICam features to set after opening, in order, before anything else, e.g. ``{"Width": 1600,
        "Height": 1200}``. A command feature is executed when its value is True or None.
    exposure_s : float, optional
        Exposure time to set on opening, seconds.
    gain : float, optional
        Gain to set on opening, in the camera's unit (usually dB).
    n_buffers : int
        Frame buffers in the stream's pool.
    auto_packet_size : bool
        On GigE Vision, let Aravis find the largest packet size the network path carries.

    Attributes
    ----------
    shape : tuple of int
        (rows, columns) of the frames, pixels.
    device_id, vendor, model, serial : str
        The opened camera's identity (``device_id`` is "<vendor>-<model>-<serial>", as Aravis lists it).
    exposure_s : float
        The exposure time the camera reports, seconds.
    gain : float
        The gain the camera reports, in its unit.
    frames_grabbed, frames_dropped : int
        Frames returned by ``grab``, and stale frames recycled, since opening.

    Raises
    ------
    CameraBackendMissingError
        PyGObject or the Aravis typelib is not installed.
    CameraNotFoundError
        No camera answers to ``device_id`` (the message lists the cameras found).
    CameraFrameSizeError
        The camera's region differs from ``expected_shape``.
    CameraSettingError
        A setting is not supported, not writable or out of range.
    CameraError
        The camera could not be opened or could not start streaming.
    """

    def __init__(self, device_id: str | None, expected_shape: tuple[int, int], pixel_format: str = "Mono8", *,
                 trigger: str = "software", features: Mapping[str, object] | None = None,
                 exposure_s: float | None = None, gain: float | None = None, n_buffers: int = 4,
                 auto_packet_size: bool = True):
        self.shape = check_shape(expected_shape)
        self.pixel_format = str(pixel_format)
        self._bits = check_pixel_format(self.pixel_format)
        self.trigger = str(trigger).strip()
        if self.trigger.lower() in ("software", "freerun"):
            self.trigger = self.trigger.lower()
        if not self.trigger:
            raise CameraSettingError('trigger must be "software", "freerun" or a trigger line such as "Line0"')
        self.requested_id = device_id
        self.device_id = ""
        self.vendor = ""
        self.model = ""
        self.serial = ""
        self.exposure_s = float("nan")
        self.gain = float("nan")
        self.frames_grabbed = 0
        self.frames_dropped = 0
        self._camera = None
        self._device = None
        self._stream = None
        self._lost_handler = None
        self._lost = threading.Event()   # set from Aravis's heartbeat thread on "control-lost"
        self._broken = False             # a disconnect was seen: do not talk to the camera when closing
        self._acquiring = False
        self._release_thread: threading.Thread | None = None
        self._Aravis, self._GLib = _import_aravis()
        try:
            self._open(features or {}, max(2, int(n_buffers)), bool(auto_packet_size))
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
        """The camera as named in messages, e.g. "Aravis Fake (serial GV01)"."""
        if self.serial or self.model:
            return f"{self.vendor} {self.model} (serial {self.serial})".strip()
        return f"camera {self.requested_id}" if self.requested_id else "Aravis camera"

    def _open(self, features: Mapping[str, object], n_buffers: int, auto_packet_size: bool) -> None:
        Aravis, GLib = self._Aravis, self._GLib
        try:
            self._camera = Aravis.Camera.new(self.requested_id)
        except GLib.Error as exc:
            wanted = repr(self.requested_id) if self.requested_id else "any camera"
            if _is_ip_address(self.requested_id):
                found = ""          # addressed directly: no discovery broadcast just for the message
            else:
                try:
                    cams = list_cameras()
                    found = "; cameras found: " + (", ".join(f"{c['device_id']} at {c['address']}"
                                                             for c in cams) or "none")
                except GLib.Error:
                    found = ""
            raise CameraNotFoundError(
                f"Aravis could not open {wanted} ({exc.message}{found}); check the camera's power and cable, "
                "that it is on this computer's subnet (arv-tool-0.8 lists the cameras), and that no other "
                "program controls it") from exc
        if self._camera is None:
            raise CameraNotFoundError(f"Aravis found no camera {self.requested_id or ''}; check power and cable")
        self._device = self._camera.get_device()
        lost = self._lost
        self._lost_handler = self._device.connect("control-lost", lambda *_: lost.set())
        try:
            self.vendor = self._camera.get_vendor_name() or ""
            self.model = self._camera.get_model_name() or ""
            self.serial = self._camera.get_device_serial_number() or ""
            self.device_id = f"{self.vendor}-{self.model}-{self.serial}"
        except GLib.Error as exc:
            raise self._classify(exc, "reading the camera's identity") from exc
        log.info("opened %s as %r", self.description, self.requested_id)

        for name, value in features.items():
            self._set_feature(name, value)
        try:
            if self._camera.get_pixel_format_as_string() != self.pixel_format:
                self._camera.set_pixel_format_from_string(self.pixel_format)
            _, _, width, height = self._camera.get_region()
        except GLib.Error as exc:
            raise self._classify(exc, f"setting the pixel format {self.pixel_format}", setting=True) from exc
        if (int(height), int(width)) != self.shape:
            raise CameraFrameSizeError(
                f"{self.description} is set to frames of {height} x {width} pixels (rows x columns) but the "
                f"station expects {self.shape[0]} x {self.shape[1]}: make the camera's Width/Height (region "
                "of interest) and the station's camera size (station.toml [camera]) agree")
        self._configure_trigger()
        if auto_packet_size and self._camera.is_gv_device():
            try:
                size = self._camera.gv_auto_packet_size()
                log.debug("%s: GigE Vision packet size %d bytes", self.description, size)
            except GLib.Error as exc:   # not fatal: the camera keeps its packet size
                log.warning("%s: finding the packet size failed (%s); keeping the camera's",
                            self.description, exc.message)
        try:
            self._camera.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
            payload = self._camera.get_payload()
            self._stream = self._camera.create_stream(None, None)
        except GLib.Error as exc:
            raise self._classify(exc, "creating the image stream") from exc
        if self._stream is None:
            raise CameraError(f"{self.description}: Aravis could not create an image stream (a firewall "
                              "blocking UDP, or no free port?)")
        for _ in range(n_buffers):
            self._stream.push_buffer(Aravis.Buffer.new_allocate(payload))
        self.exposure_s = self._read_exposure_s()
        self.gain = self._read_gain()

    def _configure_trigger(self) -> None:
        if self._has("TriggerSelector"):
            self._set_feature("TriggerSelector", "FrameStart")
        if self.trigger == "freerun":
            if self._has("TriggerMode"):
                self._set_feature("TriggerMode", "Off")
        else:
            self._set_feature("TriggerMode", "On")
            self._set_feature("TriggerSource", "Software" if self.trigger == "software" else self.trigger)

    def _start(self) -> None:
        try:
            self._camera.start_acquisition()
        except self._GLib.Error as exc:
            raise self._classify(exc, "starting the acquisition") from exc
        self._acquiring = True

    # -- GenICam features ------------------------------------------------------------------------

    def _has(self, name: str) -> bool:
        try:
            return bool(self._camera.is_feature_available(name))
        except self._GLib.Error:
            return False

    def _set_feature(self, name: str, value) -> None:
        """Set (or execute) one GenICam feature; raise CameraSettingError naming it on failure."""
        GLib = self._GLib
        node = self._device.get_feature(name)
        if node is None or not self._has(name):
            raise CameraSettingError(f"{self.description} has no feature {name!r}: check the name "
                                     "(arv-tool-0.8 features lists them) or the camera model")
        try:
            if type(node).__name__ == "GcCommand":
                if value not in (None, True):
                    raise CameraSettingError(f"{name} is a command: give it the value true to execute it")
                node.execute()
            else:
                if isinstance(value, bool):
                    value = "true" if value else "false"
                node.set_value_from_string(str(value))
        except GLib.Error as exc:
            raise self._classify(exc, f"setting {name} to {value!r}", setting=True) from exc
        log.debug("%s: %s = %r", self.description, name, value)

    # -- exposure and gain -----------------------------------------------------------------------

    def _read_exposure_s(self) -> float:
        try:
            return float(self._camera.get_exposure_time()) * 1e-6
        except self._GLib.Error:
            return float("nan")

    def _read_gain(self) -> float:
        try:
            return float(self._camera.get_gain())
        except self._GLib.Error:
            return float("nan")

    @property
    def exposure_range_s(self) -> tuple[float, float]:
        """(shortest, longest) exposure time the camera accepts, seconds."""
        low, high = self._camera.get_exposure_time_bounds()
        return low * 1e-6, high * 1e-6

    @property
    def gain_range(self) -> tuple[float, float]:
        """(lowest, highest) gain the camera accepts, in its unit."""
        low, high = self._camera.get_gain_bounds()
        return float(low), float(high)

    def set_exposure(self, seconds: float) -> None:
        """Set the exposure time.

        Parameters
        ----------
        seconds : float
            Exposure time, seconds (Aravis writes microseconds to ExposureTime or ExposureTimeAbs;
            :attr:`exposure_s` holds the value the camera reports).

        Raises
        ------
        CameraSettingError
            Outside the camera's range, or not writable.
        CameraDisconnectedError
            The camera does not answer.
        """
        seconds = check_exposure(seconds)
        cam = self._require_open()
        GLib = self._GLib
        us = seconds * 1e6
        try:
            if cam.is_exposure_auto_available():
                cam.set_exposure_time_auto(self._Aravis.Auto.OFF)
            low, high = cam.get_exposure_time_bounds()
            check_in_range("exposure", us, low, high, "s", scale=1e-6)
            cam.set_exposure_time(us)
            self.exposure_s = float(cam.get_exposure_time()) * 1e-6
        except GLib.Error as exc:
            raise self._classify(exc, f"setting the exposure to {seconds:g} s", setting=True) from exc
        log.debug("%s: exposure %.6f s (asked %.6f s)", self.description, self.exposure_s, seconds)

    def set_gain(self, gain: float) -> None:
        """Set the gain.

        Parameters
        ----------
        gain : float
            In the camera's unit (dB for SFNC ``Gain``; raw counts where the camera only has
            ``GainRaw``). :attr:`gain` holds the value the camera reports.

        Raises
        ------
        CameraSettingError
            Outside the camera's range (:attr:`gain_range`), or no writable gain.
        CameraDisconnectedError
            The camera does not answer.
        """
        gain = check_gain(gain)
        cam = self._require_open()
        GLib = self._GLib
        try:
            if not cam.is_gain_available():
                raise CameraSettingError(f"{self.description} has no gain setting")
            if cam.is_gain_auto_available():
                cam.set_gain_auto(self._Aravis.Auto.OFF)
            low, high = cam.get_gain_bounds()
            check_in_range("gain", gain, low, high, "(camera units)")
            cam.set_gain(gain)
            self.gain = float(cam.get_gain())
        except GLib.Error as exc:
            raise self._classify(exc, f"setting the gain to {gain:g}", setting=True) from exc
        log.debug("%s: gain %g (asked %g)", self.description, self.gain, gain)

    # -- grabbing --------------------------------------------------------------------------------

    def _require_open(self):
        if self._camera is None:
            raise CameraError(f"{self.description} is closed; open a new camera")
        if self._broken or self._lost.is_set():
            self._broken = True
            raise CameraDisconnectedError(f"{self.description} lost contact (no heartbeat answer); check the "
                                          "cable, power and network, then close and reopen the camera")
        return self._camera

    def _classify(self, exc, action: str, setting: bool = False) -> CameraError:
        """Turn a GLib.Error from Aravis into the station's camera error."""
        Aravis = self._Aravis
        timeout_codes = {int(Aravis.DeviceError.TIMEOUT), int(Aravis.DeviceError.TRANSFER_ERROR),
                         int(Aravis.DeviceError.NOT_CONNECTED)}
        is_device_error = exc.domain == "arv-device-error-quark"
        if self._lost.is_set() or (is_device_error and exc.code in timeout_codes):
            self._broken = True
            return CameraDisconnectedError(f"{self.description} does not answer while {action} ({exc.message}): "
                                           "check the cable, power and network, then close and reopen the camera")
        if setting:
            return CameraSettingError(f"{self.description}: {action} failed: {exc.message}")
        return CameraError(f"{self.description} failed while {action}: {exc.message}")

    def _probe(self) -> None:
        """Read a register; raise CameraDisconnectedError when the camera does not answer."""
        if self._lost.is_set():
            self._require_open()
        try:
            # Address 0 is a bootstrap register of every GigE Vision (and USB3 Vision) device: one
            # read, never served from a feature cache.
            answer = self._device.read_register(0)
        except self._GLib.Error as exc:
            raise self._classify(exc, "checking whether it still answers") from exc
        if answer is False or (isinstance(answer, tuple) and answer and answer[0] is False):
            self._broken = True
            raise CameraDisconnectedError(f"{self.description} does not answer a register read; check the "
                                          "cable, power and network, then close and reopen the camera")

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
            No frame within ``timeout_s`` while the camera still answers.
        CameraDisconnectedError
            The camera stopped answering; close it and open a new one.
        CameraIncompleteFrameError
            The frame arrived damaged (lost packets: check the network card, packet size, packet delay).
        CameraFrameSizeError
            The frame's size differs from ``expected_shape``.
        CameraError
            The camera was closed, or Aravis failed otherwise.
        """
        Aravis, GLib = self._Aravis, self._GLib
        cam = self._require_open()
        stream = self._stream
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        # Recycle frames that are already waiting: they were exposed before this call.
        while (buf := stream.try_pop_buffer()) is not None:
            stream.push_buffer(buf)
            self.frames_dropped += 1
        sent_ns = time.time_ns()
        if self.trigger == "software":
            try:
                cam.software_trigger()
            except GLib.Error as exc:
                raise self._classify(exc, "sending a software trigger") from exc
        while True:
            remaining_us = int(max(0.0, deadline - time.monotonic()) * 1e6)
            buf = stream.timeout_pop_buffer(remaining_us) if remaining_us > 0 else stream.try_pop_buffer()
            if buf is None:
                self._probe()
                self._require_open()
                source = {"software": "after a software trigger", "freerun": "in free run"}.get(
                    self.trigger, f"from trigger line {self.trigger}")
                raise CameraTimeoutError(f"{self.description}: no frame {source} within {timeout_s:g} s; "
                                         "check the trigger, exposure time and frame rate")
            try:
                # A frame whose first packet reached the host before the trigger is a late, stale one.
                if self.trigger == "software" and buf.get_system_timestamp() < sent_ns:
                    self.frames_dropped += 1
                    continue
                status = buf.get_status()
                if status != Aravis.BufferStatus.SUCCESS:
                    self._require_open()
                    raise CameraIncompleteFrameError(
                        f"{self.description} delivered a damaged frame ({status.value_nick}); check the "
                        "network card, packet size and inter-packet delay (or the USB link)")
                frame = self._to_array(buf)
            finally:
                stream.push_buffer(buf)
            break
        self.frames_grabbed += 1
        return check_frame_shape(frame, self.shape, self.description)

    def _to_array(self, buf) -> np.ndarray:
        width, height = buf.get_image_width(), buf.get_image_height()
        data = buf.get_image_data() if hasattr(buf, "get_image_data") else buf.get_data()
        itemsize = 1 if self._bits == 8 else 2
        if len(data) < width * height * itemsize:
            raise CameraIncompleteFrameError(f"{self.description} delivered {len(data)} bytes for a frame of "
                                             f"{height} x {width} pixels; check the pixel format")
        dtype = np.uint8 if itemsize == 1 else np.dtype("<u2")
        image = np.frombuffer(data, dtype=dtype, count=width * height).reshape(height, width)
        return to_uint8(image, self._bits)

    # -- closing ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the acquisition and release the camera (idempotent, never raises, returns at once).

        A camera that has gone away is released in a background thread: Aravis's clean-up still sends it
        a few control commands and waits for their retries (about 7.5 s on Aravis 0.8.26).
        """
        cam, self._camera = self._camera, None
        if cam is None:
            return
        GLib = self._GLib
        if self._acquiring and not (self._broken or self._lost.is_set()):
            try:
                cam.stop_acquisition()
            except GLib.Error as exc:
                self._broken = self._broken or exc.domain == "arv-device-error-quark"
                log.debug("%s: stopping the acquisition failed while closing: %s", self.description, exc.message)
        self._acquiring = False
        if self._device is not None and self._lost_handler is not None:
            try:
                self._device.disconnect(self._lost_handler)
            except Exception as exc:  # closing must never raise
                log.debug("%s: disconnecting the control-lost handler failed: %s", self.description, exc)
        # Dropping the last references stops the stream thread and releases the device (stream first).
        held = [self._stream, self._device, cam]
        self._lost_handler = self._stream = self._device = None
        del cam
        if self._broken or self._lost.is_set():
            thread = threading.Thread(target=_release, args=(held, self.description), daemon=True,
                                      name="aravis-release")
            thread.start()
            self._release_thread = thread
        else:
            _release(held, self.description)
        log.info("closed %s", self.description)

    def __enter__(self) -> "AravisCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._camera is None else ("disconnected" if self._broken else "open")
        return f"<AravisCamera {self.description}, {self.shape[0]} x {self.shape[1]}, {state}>"


__all__ = ["AravisCamera", "list_cameras"]
