"""Camera backends behind the :class:`~sofast_station.devices.protocols.Camera` protocol.

========  ============================================  ==========================================
kind      class                                         needs
========  ============================================  ==========================================
basler    :class:`.basler.BaslerCamera` (pypylon)       ``pip install pypylon==26.9``
aravis    :class:`.aravis.AravisCamera` (Aravis 0.8)    Debian ``gir1.2-aravis-0.8``, ``PyGObject<3.51``
replay    :class:`.replay.ReplayCamera`                 nothing
========  ============================================  ==========================================

The two GenICam backends are one camera, :class:`.genicam.GenICamCamera`, over a transport
(:class:`.basler.PylonTransport`, :class:`.aravis.AravisTransport`) that holds only what its library does
its own way. Backends are imported only when asked for, so a station without pypylon or Aravis can still
use the others; asking for one whose library is missing raises
:class:`~sofast_station.devices.cameras._common.CameraBackendMissingError` naming what to install.

Every error a backend raises is a :class:`~sofast_station.errors.CameraError`:
:class:`~sofast_station.errors.CameraTimeoutError` (no frame in time),
:class:`~sofast_station.errors.CameraDisconnectedError` (the camera went away; also
:class:`CameraNotFoundError` when opening), :class:`CameraFrameSizeError`, :class:`CameraSettingError`,
:class:`CameraIncompleteFrameError`. After any of them the camera can be closed and a new one opened.
"""

from __future__ import annotations

import importlib
import inspect
import logging

from ...errors import ConfigError
from ._common import (CameraBackendMissingError, CameraFrameSizeError, CameraIncompleteFrameError,
                      CameraNotFoundError, CameraSettingError)

log = logging.getLogger(__name__)

#: kind -> (module, class name) of each backend.
BACKENDS: dict[str, tuple[str, str]] = {
    "basler": ("basler", "BaslerCamera"),
    "aravis": ("aravis", "AravisCamera"),
    "replay": ("replay", "ReplayCamera"),
}


def _backend_class(kind: str):
    try:
        module_name, class_name = BACKENDS[kind]
    except KeyError:
        raise ConfigError(f"unknown camera kind {kind!r}: use one of {', '.join(sorted(BACKENDS))}") from None
    module = importlib.import_module(f"{__name__}.{module_name}")
    return getattr(module, class_name)


def open_camera(kind: str, **options):
    """Open a camera of the given kind.

    Parameters
    ----------
    kind : str
        "basler", "aravis" or "replay" (case-insensitive).
    **options
        The backend's constructor arguments, e.g. ``serial="12345678", expected_shape=(1200, 1600)``
        for "basler", ``device_id="192.168.3.10", expected_shape=(1200, 1600)`` for "aravis",
        ``frames=stack`` for "replay". Times are in seconds.

    Returns
    -------
    Camera
        An open camera implementing the Camera protocol.

    Raises
    ------
    ConfigError
        Unknown kind, or options the backend does not take (the message lists the ones it takes).
    CameraBackendMissingError
        The backend's library is not installed (the message names the package).
    CameraError
        The camera could not be opened.
    """
    key = str(kind).strip().lower()
    cls = _backend_class(key)
    try:
        inspect.signature(cls).bind(**options)
    except TypeError as exc:
        accepted = ", ".join(name for name in inspect.signature(cls).parameters)
        raise ConfigError(f"camera kind {key!r}: {exc}; it takes: {accepted}") from None
    log.debug("opening a %s camera with %s", key, sorted(options))
    return cls(**options)


def __getattr__(name: str):
    # Lazy access to the backend classes: sofast_station.devices.cameras.BaslerCamera imports basler.py
    # (which itself imports pypylon only when a camera is opened).
    for kind, (_, class_name) in BACKENDS.items():
        if name == class_name:
            return _backend_class(kind)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["open_camera", "BACKENDS", "BaslerCamera", "AravisCamera", "ReplayCamera",
           "CameraBackendMissingError", "CameraNotFoundError", "CameraSettingError", "CameraFrameSizeError",
           "CameraIncompleteFrameError"]
