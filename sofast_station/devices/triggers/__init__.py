"""Robot/PLC handshake backends of the :class:`~sofast_station.devices.protocols.Trigger` protocol.

=============  ==============================================  ===================================
kind           backend                                         needs
=============  ==============================================  ===================================
"simulated"    :class:`.simulated.SimulatedRobot`              nothing
"modbus"       :class:`.modbus.ModbusTrigger` (Modbus TCP)     pymodbus >= 3.10, < 4
"usb"          :class:`.usbio.UsbTrigger` (FTDI bit-bang)      pyusb >= 1.2, and libusb 1.0
=============  ==============================================  ===================================

Open one with :func:`open_trigger`; docs/plc.md has the register map, the pin map and the handshake.
"""

from __future__ import annotations

import importlib
import inspect

from ...errors import ConfigError

#: kind -> (module, class, the package its import needs, how to install it)
_KINDS = {
    "simulated": ("simulated", "SimulatedRobot", None, None),
    "modbus": ("modbus", "ModbusTrigger", "pymodbus", "pip install 'pymodbus>=3.10,<4'"),
    "usb": ("usbio", "UsbTrigger", "usb", "pip install 'pyusb>=1.2,<2' (and apt-get install libusb-1.0-0)"),
}

#: The trigger kinds :func:`open_trigger` knows.
KINDS = tuple(_KINDS)


def trigger_class(kind: str):
    """The backend class of ``kind``, imported on first use.

    Raises
    ------
    ConfigError
        For an unknown kind, or when the backend's package is not installed (naming it).
    """
    try:
        module_name, class_name, package, install = _KINDS[kind]
    except (KeyError, TypeError):
        raise ConfigError(f"unknown trigger kind {kind!r}: use one of {', '.join(KINDS)}") from None
    try:
        module = importlib.import_module(f".{module_name}", __name__)
        if package is not None:
            importlib.import_module(package)  # the backends import it lazily, on construction
    except ImportError as exc:
        missing = exc.name or package
        raise ConfigError(f"trigger kind {kind!r} needs the Python package '{missing}', which is not "
                          f"installed ({exc}): {install}") from exc
    return getattr(module, class_name)


def open_trigger(kind: str, **options):
    """Open the robot/PLC handshake of ``kind`` ("simulated", "modbus" or "usb").

    Parameters
    ----------
    kind : str
        Backend name.
    **options
        The backend's constructor arguments (station.toml's ``[trigger]`` table less ``kind``), e.g.
        ``requests=5`` for "simulated", ``host="192.168.0.10", port=502, ack_timeout_s=5.0`` for
        "modbus", ``serial_number="A50285BI"`` for "usb".

    Returns
    -------
    Trigger
        The opened backend.

    Raises
    ------
    ConfigError
        Unknown kind, missing package, or an option the backend does not take.
    TriggerError
        The device could not be reached (the station retries later).
    """
    cls = trigger_class(kind)
    try:
        inspect.signature(cls).bind(**options)
    except TypeError as exc:
        params = [p for p in inspect.signature(cls).parameters if p != "self"]
        raise ConfigError(f"trigger {kind!r}: {exc}; its options are {', '.join(params)}") from None
    return cls(**options)


__all__ = ["KINDS", "open_trigger", "trigger_class"]
