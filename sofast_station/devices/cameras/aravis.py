"""GigE Vision (and USB3 Vision) cameras through Aravis 0.8, via GObject introspection: the Aravis transport
of :class:`~sofast_station.devices.cameras.genicam.GenICamCamera`.

Acquisition streams into a small pool of buffers. Each buffer carries the host time at which its first
packet arrived, so a frame that reached the host before a software trigger was sent (a stale one, or a
late frame of an earlier, timed-out trigger) is recognised and recycled.

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

from ...errors import CameraDisconnectedError, CameraError
from ._common import (CameraBackendMissingError, CameraIncompleteFrameError, CameraNotFoundError, CameraSettingError,
                      to_uint8)
from .genicam import Delivery, GenICamCamera, GenICamTransport

log = logging.getLogger(__name__)

#: What this backend needs installed, named in the error raised when it is missing.
PIP_REQUIREMENT = "PyGObject<3.51"
DEBIAN_PACKAGES = "gir1.2-aravis-0.8"
BUILD_PREREQUISITES = "libgirepository1.0-dev libcairo2-dev pkg-config python3-dev gcc"

#: ArvCamera's calls for exposure and gain: get_NAME, get_NAME_bounds, set_NAME.
_QUANTITY_CALLS = {"exposure": "exposure_time", "gain": "gain"}


def _import_aravis():
    """Return (Aravis, GLib) or raise CameraBackendMissingError naming what to install."""
    try:
        # optional: PyGObject and Aravis are the hardware extra
        import gi
    except ImportError as exc:
        raise CameraBackendMissingError(
            f"the Aravis camera backend needs PyGObject, which is not installed ({exc}): install the build "
            f"prerequisites (apt-get install {BUILD_PREREQUISITES}), then pip install '{PIP_REQUIREMENT}'; "
            f"Aravis itself comes with apt-get install {DEBIAN_PACKAGES}") from exc
    try:
        gi.require_version("Aravis", "0.8")
        # optional: PyGObject and Aravis are the hardware extra
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


class AravisTransport(GenICamTransport):
    """Aravis's side of a GenICam camera: an ``ArvCamera``, its device's nodes and an ``ArvStream``.

    Parameters
    ----------
    device_id : str or None
        The camera's IP address (opened directly), a device id or serial number (found by discovery),
        or None for the first camera found.
    n_buffers : int
        Frame buffers in the stream's pool (at least 2).
    auto_packet_size : bool
        On GigE Vision, let Aravis find the largest packet size the network path carries.
    """

    feature_hint = "check the name (arv-tool-0.8 features lists them)"
    trigger_line_example = "Line0"

    def __init__(self, device_id: str | None, n_buffers: int = 4, auto_packet_size: bool = True):
        super().__init__(device_id)
        self.n_buffers = max(2, int(n_buffers))
        self.auto_packet_size = bool(auto_packet_size)
        self.device_id = ""
        self._device = None
        self._stream = None
        self._lost_handler = None
        self._lost = threading.Event()   # set from Aravis's heartbeat thread on "control-lost"
        self._acquiring = False
        self._release_thread: threading.Thread | None = None
        self._Aravis = self._GLib = None

    # A disconnect seen here, or Aravis's heartbeat reporting the camera lost.
    broken = property(lambda self: self._broken or self._lost.is_set(),
                      lambda self, value: setattr(self, "_broken", bool(value)))

    @property
    def loss(self) -> str:
        return "lost contact (no heartbeat answer)" if self._lost.is_set() else "was disconnected"

    def load(self) -> None:
        self._Aravis, self._GLib = _import_aravis()
        self.error_types = (self._GLib.Error,)

    def unopened_description(self) -> str:
        return f"camera {self.requested}" if self.requested else "Aravis camera"

    def _detail(self, exc) -> str:
        return exc.message

    def open(self) -> None:
        Aravis, GLib = self._Aravis, self._GLib
        try:
            self.handle = Aravis.Camera.new(self.requested)
        except GLib.Error as exc:
            wanted = repr(self.requested) if self.requested else "any camera"
            if _is_ip_address(self.requested):
                found = ""          # addressed directly: no discovery broadcast just for the message
            else:
                try:
                    found = "; cameras found: " + (", ".join(f"{c['device_id']} at {c['address']}"
                                                             for c in list_cameras()) or "none")
                except GLib.Error:
                    found = ""
            raise CameraNotFoundError(
                f"Aravis could not open {wanted} ({exc.message}{found}); check the camera's power and cable, "
                "that it is on this computer's subnet (arv-tool-0.8 lists the cameras), and that no other "
                "program controls it") from exc
        if self.handle is None:
            raise CameraNotFoundError(f"Aravis found no camera {self.requested or ''}; check power and cable")
        self._device = self.handle.get_device()
        lost = self._lost
        self._lost_handler = self._device.connect("control-lost", lambda *_: lost.set())
        with self.failures("reading the camera's identity"):
            self.vendor = self.handle.get_vendor_name() or ""
            self.model = self.handle.get_model_name() or ""
            self.serial = self.handle.get_device_serial_number() or ""
        self.device_id = f"{self.vendor}-{self.model}-{self.serial}"

    # -- nodes -----------------------------------------------------------------------------------

    def _node(self, name: str):
        try:
            node = self._device.get_feature(name)
            return node if node is not None and self.handle.is_feature_available(name) else None
        except self._GLib.Error:
            return None

    def feature_kind(self, name: str) -> str | None:
        node = self._node(name)
        if node is None:
            return None
        return "command" if isinstance(node, self._Aravis.GcCommand) else "value"

    def read(self, name: str):
        Aravis, device, node = self._Aravis, self._device, self._node(name)
        try:
            if node is None:
                return None
            if isinstance(node, Aravis.GcString):          # strings and enumerations, by entry name
                return device.get_string_feature_value(name)
            if isinstance(node, Aravis.GcInteger):
                return device.get_integer_feature_value(name)
            if isinstance(node, Aravis.GcFloat):
                return device.get_float_feature_value(name)
            return node.get_value_as_string()
        except self._GLib.Error:
            return None

    def write(self, name: str, value, required: bool) -> None:
        if isinstance(value, bool):
            value = "true" if value else "false"
        self._node(name).set_value_from_string(str(value))

    def execute(self, name: str) -> None:
        self._node(name).execute()

    # -- exposure (microseconds) and gain: Aravis's camera calls, which know the vendors' feature names --

    def quantity(self, name: str) -> float:
        return float(getattr(self.handle, f"get_{_QUANTITY_CALLS[name]}")())

    def quantity_range(self, name: str) -> tuple[float, float]:
        if name == "gain" and not self.handle.is_gain_available():
            raise CameraSettingError(f"{self.description} has no gain setting")
        return tuple(getattr(self.handle, f"get_{_QUANTITY_CALLS[name]}_bounds")())

    def set_quantity(self, name: str, value: float) -> None:
        getattr(self.handle, f"set_{_QUANTITY_CALLS[name]}")(value)

    # -- acquisition -----------------------------------------------------------------------------

    def prepare_acquisition(self) -> None:
        cam = self.handle
        if self.auto_packet_size and cam.is_gv_device():
            try:
                log.debug("%s: GigE Vision packet size %d bytes", self.description, cam.gv_auto_packet_size())
            except self._GLib.Error as exc:   # not fatal: the camera keeps its packet size
                log.warning("%s: finding the packet size failed (%s); keeping the camera's",
                            self.description, exc.message)
        payload = cam.get_payload()
        self._stream = cam.create_stream(None, None)
        if self._stream is None:
            raise CameraError(f"{self.description}: Aravis could not create an image stream (a firewall "
                              "blocking UDP, or no free port?)")
        for _ in range(self.n_buffers):
            self._stream.push_buffer(self._Aravis.Buffer.new_allocate(payload))

    def start(self) -> None:
        self.handle.start_acquisition()
        self._acquiring = True

    def drop_waiting(self) -> int:
        dropped = 0
        while (buf := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(buf)
            dropped += 1
        return dropped

    def software_trigger(self, timeout_s: float) -> bool:
        self.handle.software_trigger()
        return True

    def next_frame(self, timeout_s: float, bits: int) -> Delivery | None:
        stream = self._stream
        timeout_us = int(timeout_s * 1e6)
        buf = stream.timeout_pop_buffer(timeout_us) if timeout_us > 0 else stream.try_pop_buffer()
        if buf is None:
            return None
        try:
            arrived_ns = buf.get_system_timestamp()
            status = buf.get_status()
            if status != self._Aravis.BufferStatus.SUCCESS:
                return Delivery(None, status.value_nick, arrived_ns)
            return Delivery(self._to_array(buf, bits), "", arrived_ns)
        finally:
            stream.push_buffer(buf)

    def _to_array(self, buf, bits: int) -> np.ndarray:
        width, height = buf.get_image_width(), buf.get_image_height()
        data = buf.get_image_data() if hasattr(buf, "get_image_data") else buf.get_data()
        itemsize = 1 if bits == 8 else 2
        if len(data) < width * height * itemsize:
            raise CameraIncompleteFrameError(f"{self.description} delivered {len(data)} bytes for a frame of "
                                             f"{height} x {width} pixels; check the pixel format")
        dtype = np.uint8 if itemsize == 1 else np.dtype("<u2")
        return to_uint8(np.frombuffer(data, dtype=dtype, count=width * height).reshape(height, width), bits)

    def check_alive(self) -> None:
        """Read a register; raise CameraDisconnectedError when the camera does not answer."""
        if self.broken:
            return          # already known: the camera's next check says so
        with self.failures("checking whether it still answers"):
            # Address 0 is a bootstrap register of every GigE Vision (and USB3 Vision) device: one
            # read, never served from a feature cache.
            answer = self._device.read_register(0)
        if answer is False or (isinstance(answer, tuple) and answer and answer[0] is False):
            self.broken = True
            raise CameraDisconnectedError(f"{self.description} does not answer a register read; check the "
                                          "cable, power and network, then close and reopen the camera")

    def _verdict(self, exc, setting: bool) -> str | None:
        device_error = self._Aravis.DeviceError
        lost_codes = {int(device_error.TIMEOUT), int(device_error.TRANSFER_ERROR), int(device_error.NOT_CONNECTED)}
        if self._lost.is_set() or (exc.domain == "arv-device-error-quark" and exc.code in lost_codes):
            return "gone"
        return None

    def release(self) -> None:
        """Stop the acquisition and drop the camera; returns at once.

        A camera that has gone away is released in a background thread: Aravis's clean-up still sends it
        a few control commands and waits for their retries (about 7.5 s on Aravis 0.8.26).
        """
        cam, self.handle = self.handle, None
        if self._acquiring and not self.broken:
            try:
                cam.stop_acquisition()
            except self._GLib.Error as exc:
                self.broken = self.broken or exc.domain == "arv-device-error-quark"
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
        if self.broken:
            thread = threading.Thread(target=_release, args=(held, self.description), daemon=True,
                                      name="aravis-release")
            thread.start()
            self._release_thread = thread
        else:
            _release(held, self.description)


class AravisCamera(GenICamCamera):
    """A GenICam camera (GigE Vision, USB3 Vision) through Aravis 0.8: :class:`~.genicam.GenICamCamera`
    over an :class:`AravisTransport`.

    Parameters
    ----------
    device_id : str or None
        What Aravis opens: the camera's IP address (opened directly, no discovery broadcast), or a device
        id ("<vendor>-<model>-<serial>", as ``arv-tool-0.8`` lists them) or serial number, found by a
        GigE Vision discovery broadcast on every network interface; None takes the first camera found.
    expected_shape, pixel_format, trigger, features, exposure_s, gain
        As for :class:`~.genicam.GenICamCamera` (a trigger line is e.g. "Line0"; the gain is usually dB).
    n_buffers : int
        Frame buffers in the stream's pool.
    auto_packet_size : bool
        On GigE Vision, let Aravis find the largest packet size the network path carries.

    Attributes
    ----------
    requested_id : str or None
        What was asked for.
    device_id, vendor, model, serial : str
        The opened camera's identity (``device_id`` is "<vendor>-<model>-<serial>", as Aravis lists it).

    The other attributes, and the errors raised, are :class:`~.genicam.GenICamCamera`'s.
    """

    def __init__(self, device_id: str | None, expected_shape: tuple[int, int], pixel_format: str = "Mono8", *,
                 trigger: str = "software", features: Mapping[str, object] | None = None,
                 exposure_s: float | None = None, gain: float | None = None, n_buffers: int = 4,
                 auto_packet_size: bool = True):
        self.requested_id = device_id
        super().__init__(AravisTransport(device_id, n_buffers, auto_packet_size), expected_shape, pixel_format,
                         trigger=trigger, features=features, exposure_s=exposure_s, gain=gain)

    @property
    def device_id(self) -> str:
        """The opened camera's "<vendor>-<model>-<serial>"."""
        return self._transport.device_id


__all__ = ["AravisCamera", "AravisTransport", "list_cameras"]
