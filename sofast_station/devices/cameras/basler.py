"""Basler cameras (GigE, USB3 Vision, and pylon's camera emulation) through pypylon: the pylon transport of
:class:`~sofast_station.devices.cameras.genicam.GenICamCamera`.

pylon talks microseconds; the station talks seconds. Exposure goes to ``ExposureTime`` (SFNC 2, most current
models) or ``ExposureTimeAbs`` (older GigE models); gain to ``Gain`` (dB) or ``GainRaw`` (the camera's raw
units), whichever the model has, and ``set_gain`` takes that feature's own unit.

pylon tells when a camera is removed (``IsCameraDeviceRemoved``), and every grab asks. Its frames carry no
host arrival time, so a frame of a software trigger that timed out is kept away from the next grab by
restarting the acquisition after the timeout.

The emulated cameras appear when the environment variable ``PYLON_CAMEMU`` is set to their number before
pylon enumerates devices (pypylon reads it at enumeration, so setting it after ``import pypylon`` works).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

from ...errors import CameraDisconnectedError, CameraError
from ._common import CameraBackendMissingError, CameraNotFoundError, CameraSettingError, ms, to_uint8
from .genicam import Delivery, GenICamCamera, GenICamTransport

log = logging.getLogger(__name__)

#: The pip requirement that provides this backend.
PIP_REQUIREMENT = "pypylon==26.9"

#: The nodes that hold the exposure time (microseconds) and the gain, SFNC 2 name first, then the older
#: GigE models' name.
_QUANTITY_NODES = {"exposure": ("ExposureTime", "ExposureTimeAbs"), "gain": ("Gain", "GainRaw")}


def _import_pylon():
    """Return (pylon, genicam) from pypylon, or raise CameraBackendMissingError naming the package."""
    try:
        # optional: pypylon is the hardware extra
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


def _listed(pylon, genicam, device_class: str | None) -> list:
    try:
        return _enumerate(pylon, device_class)
    except genicam.GenericException as exc:
        raise CameraError(f"pylon could not list the cameras: {exc}") from exc


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
    return [{"serial": info.GetSerialNumber(), "model": info.GetModelName(), "vendor": info.GetVendorName(),
             "device_class": info.GetDeviceClass(), "friendly_name": info.GetFriendlyName()}
            for info in _listed(pylon, genicam, device_class)]


class PylonTransport(GenICamTransport):
    """pypylon's side of a Basler camera: an ``InstantCamera`` and its node map.

    Parameters
    ----------
    serial : str or None
        The camera's serial number; None takes the first camera pylon finds.
    device_class : str, optional
        Look for the camera only in this pylon transport layer.
    max_buffers : int
        Number of frame buffers pylon allocates (at least 2).
    """

    feature_hint = "check the feature name (pylon Viewer shows them)"
    trigger_line_example = "Line1"

    def __init__(self, serial: str | None, device_class: str | None = None, max_buffers: int = 10):
        super().__init__(serial)
        self.vendor = "Basler"
        self.device_class = device_class
        self.max_buffers = max(2, int(max_buffers))
        self._restart = False          # a grab timed out: restart acquisition to drop late frames
        self._pylon = self._genicam = None

    def load(self) -> None:
        self._pylon, self._genicam = _import_pylon()
        self.error_types = (self._genicam.GenericException,)

    def unopened_description(self) -> str:
        return f"Basler camera (serial {self.requested})" if self.requested else "Basler camera"

    def open(self) -> None:
        pylon, genicam = self._pylon, self._genicam
        devices = _listed(pylon, genicam, self.device_class)
        if self.requested is None:
            chosen = devices[0] if devices else None
        else:
            chosen = next((d for d in devices if d.GetSerialNumber() == str(self.requested)), None)
        if chosen is None:
            found = ", ".join(f"{d.GetModelName()} (serial {d.GetSerialNumber()})" for d in devices) or "none"
            wanted = f"with serial {self.requested}" if self.requested else "at all"
            raise CameraNotFoundError(
                f"no Basler camera found {wanted} (cameras found: {found}); check the camera's power and "
                "cable, its network settings (pylon IP Configurator) and that no other program uses it")
        try:
            self.handle = pylon.InstantCamera(pylon.TlFactory.GetInstance().CreateDevice(chosen))
            self.serial = self.handle.GetDeviceInfo().GetSerialNumber()
            self.model = self.handle.GetDeviceInfo().GetModelName()
            self.handle.Open()
        except genicam.GenericException as exc:
            raise CameraError(f"could not open {self.description}: {exc}; check that no other program "
                              "(pylon Viewer, another station) has it open, then retry") from exc

    # -- nodes -----------------------------------------------------------------------------------

    def _node(self, *names: str):
        """The first available pypylon parameter of ``names``, or None when the camera has none of them."""
        genicam = self._genicam
        for name in names:
            try:
                node = self.handle.GetNodeMap().GetNode(name)
                if node is not None and type(node).__name__ != "PlaceholderParameter" and genicam.IsAvailable(node):
                    return node
            except genicam.GenericException:
                continue
        return None

    def feature_kind(self, name: str) -> str | None:
        node = self._node(name)
        if node is None:
            return None
        return "command" if type(node).__name__ == "CommandParameter" else "value"

    def read(self, name: str):
        node = self._node(name)
        if node is None or not self._genicam.IsReadable(node):
            return None
        try:
            return node.Value
        except self._genicam.GenericException:
            return None

    def write(self, name: str, value, required: bool) -> None:
        genicam = self._genicam
        node = self._node(name)
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

    def execute(self, name: str) -> None:
        self._node(name).Execute()

    # -- exposure (microseconds) and gain, under the names this model has ---------------------------

    def _quantity_node(self, name: str):
        names = _QUANTITY_NODES[name]
        node = self._node(*names)
        if node is None:
            raise CameraSettingError(f"{self.description} has neither {names[0]} nor {names[1]}")
        return node

    def quantity(self, name: str) -> float:
        return float(self._quantity_node(name).Value)

    def quantity_range(self, name: str) -> tuple[float, float]:
        node = self._quantity_node(name)
        return float(node.Min), float(node.Max)

    def set_quantity(self, name: str, value: float) -> None:
        node = self._quantity_node(name)
        node.Value = int(round(value)) if type(node).__name__ == "IntegerParameter" else value

    # -- acquisition -----------------------------------------------------------------------------

    def prepare_acquisition(self) -> None:
        try:
            self.handle.MaxNumBuffer.Value = self.max_buffers
        except self._genicam.GenericException as exc:  # not fatal: pylon keeps its default
            log.debug("%s: MaxNumBuffer not set: %s", self.description, exc)

    def start(self) -> None:
        self.handle.StartGrabbing(self._pylon.GrabStrategy_OneByOne)
        self._restart = False

    def drop_waiting(self) -> int:
        if self._restart:       # a frame of a timed-out trigger may still come: start afresh
            self.handle.StopGrabbing()
            self.start()
        self.check_alive()
        dropped = 0
        while True:
            result = self.handle.RetrieveResult(0, self._pylon.TimeoutHandling_Return)
            with result:
                if not result.IsValid():
                    return dropped
                dropped += 1

    def software_trigger(self, timeout_s: float) -> bool:
        if not self.handle.WaitForFrameTriggerReady(ms(timeout_s), self._pylon.TimeoutHandling_Return):
            self._restart = True
            return False
        self.handle.ExecuteSoftwareTrigger()
        return True

    def next_frame(self, timeout_s: float, bits: int) -> Delivery | None:
        result = self.handle.RetrieveResult(ms(timeout_s), self._pylon.TimeoutHandling_Return)
        with result:
            if not result.IsValid():
                self._restart = True
                return None
            if not result.GrabSucceeded():
                return Delivery(None, f"error {result.GetErrorCode():#x}: {result.GetErrorDescription()}")
            return Delivery(to_uint8(result.GetArray(), bits))

    def check_alive(self) -> None:
        cam = self.handle
        try:
            removed = cam.IsCameraDeviceRemoved()
            attached = cam.IsPylonDeviceAttached() and cam.IsOpen()
            grabbing = cam.IsGrabbing()
        except self._genicam.GenericException as exc:
            self.broken = True
            raise CameraDisconnectedError(f"{self.description} does not answer ({exc}); check the cable and "
                                          "power, then close and reopen the camera") from exc
        if removed or not attached or not grabbing:
            self.broken = True
            what = ("was removed (unplugged, power or network lost)" if removed
                    else "was closed underneath the station" if not attached else "stopped grabbing")
            raise CameraDisconnectedError(f"{self.description} {what}; check the cable and power, then close "
                                          "and reopen the camera")

    def _verdict(self, exc: BaseException, setting: bool) -> str | None:
        genicam = self._genicam
        try:
            removed = self.handle is not None and self.handle.IsCameraDeviceRemoved()
        except genicam.GenericException:
            removed = True
        if removed or (not setting and isinstance(exc, genicam.RuntimeException)):
            return "gone"
        return "timeout" if isinstance(exc, genicam.TimeoutException) else None

    def release(self) -> None:
        cam, self.handle = self.handle, None
        for step in ("StopGrabbing", "Close", "DestroyDevice"):
            try:
                getattr(cam, step)()
            except self._genicam.GenericException as exc:
                log.debug("%s: %s failed while closing: %s", self.description, step, exc)
            except Exception as exc:  # closing must never raise
                log.warning("%s: %s failed while closing: %s", self.description, step, exc)


class BaslerCamera(GenICamCamera):
    """A Basler camera through pypylon: :class:`~.genicam.GenICamCamera` over a :class:`PylonTransport`.

    Parameters
    ----------
    serial : str or None
        The camera's serial number; None takes the first camera pylon finds.
    expected_shape, pixel_format, trigger, features, exposure_s, gain
        As for :class:`~.genicam.GenICamCamera`; the features can include transport settings, e.g.
        ``{"GevSCPSPacketSize": 8192}``, and a trigger line is e.g. "Line1".
    max_buffers : int
        Number of frame buffers pylon allocates.
    device_class : str, optional
        Look for the camera only in this pylon transport layer ("BaslerGigE", "BaslerUsb",
        "BaslerCamEmu"); by default every transport layer is searched, which broadcasts a GigE Vision
        discovery packet on every network interface.

    Attributes
    ----------
    requested_serial, device_class : str or None
        What was asked for.
    serial, model : str
        The opened camera's serial number and model name.

    The other attributes, and the errors raised, are :class:`~.genicam.GenICamCamera`'s.
    """

    def __init__(self, serial: str | None, expected_shape: tuple[int, int], pixel_format: str = "Mono8", *,
                 trigger: str = "software", features: Mapping[str, object] | None = None,
                 exposure_s: float | None = None, gain: float | None = None, max_buffers: int = 10,
                 device_class: str | None = None):
        self.requested_serial = serial
        self.device_class = device_class
        super().__init__(PylonTransport(serial, device_class, max_buffers), expected_shape, pixel_format,
                         trigger=trigger, features=features, exposure_s=exposure_s, gain=gain)


__all__ = ["BaslerCamera", "PylonTransport", "list_cameras"]
