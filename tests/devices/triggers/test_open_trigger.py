"""open_trigger: the three kinds, lazy imports, and ConfigError for what a configuration can get wrong."""

from __future__ import annotations

import sys

import pytest

from sofast_station.devices.triggers import KINDS, open_trigger
from sofast_station.devices.triggers.simulated import SimulatedRobot
from sofast_station.errors import ConfigError, TriggerError


def test_simulated_is_opened_with_its_options():
    robot = open_trigger("simulated", requests=2, period_s=0.0)
    assert isinstance(robot, SimulatedRobot)
    assert [r.serial for r in robot.requests] == ["SIM-0001", "SIM-0002"]


def test_unknown_kind_names_the_known_ones():
    with pytest.raises(ConfigError, match="unknown trigger kind 'profibus'.*simulated, modbus, usb"):
        open_trigger("profibus")
    assert KINDS == ("simulated", "modbus", "usb")


def test_unknown_option_is_a_config_error():
    with pytest.raises(ConfigError, match="trigger 'simulated'.*requests, period_s"):
        open_trigger("simulated", requests=1, speed=3)


@pytest.mark.parametrize("kind, package, hint", [("modbus", "pymodbus", "pymodbus>=3.10,<4"),
                                                 ("usb", "usb", "pyusb>=1.2,<2")])
def test_missing_package_is_named(monkeypatch, kind, package, hint):
    monkeypatch.setitem(sys.modules, package, None)  # import of it fails as if not installed
    with pytest.raises(ConfigError, match=f"needs the Python package '{package}'") as err:
        open_trigger(kind, host="127.0.0.1") if kind == "modbus" else open_trigger(kind)
    assert hint in str(err.value)


def test_modbus_to_nothing_is_a_trigger_error():
    import pymodbus  # noqa: F401
    from .fake_plc import free_port

    with pytest.raises(TriggerError, match="cannot connect"):
        open_trigger("modbus", host="127.0.0.1", port=free_port(), timeout_s=0.5)


def test_usb_through_open_trigger_on_the_virtual_bus():
    import usb  # noqa: F401
    from .virtual_ftdi import VirtualFtdi, VirtualUsbBackend

    trigger = open_trigger("usb", backend=VirtualUsbBackend(VirtualFtdi()), ack_timeout_s=1.0)
    trigger.ready()
    trigger.heartbeat()
    trigger.close()
    with pytest.raises(TriggerError, match="no FTDI"):
        open_trigger("usb", backend=VirtualUsbBackend())
