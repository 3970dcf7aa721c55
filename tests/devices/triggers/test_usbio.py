"""The USB digital-I/O trigger on an emulated FTDI chip (virtual pyusb backend) with a test-side PLC."""

from __future__ import annotations

import re
import threading
import time
from datetime import datetime

import pytest

import usb  # noqa: F401  (a dependency: its absence must fail, not skip)

from sofast_station.devices.protocols import FAULT_CODES
from sofast_station.devices.triggers import _handshake, usbio
from sofast_station.devices.triggers.usbio import UsbTrigger
from sofast_station.errors import ConfigError, TriggerError

from .virtual_ftdi import VirtualFtdi, VirtualUsbBackend

ANSWERED = (usbio.DONE_PASS, usbio.DONE_FAIL, usbio.DONE_INVALID, usbio.STATUS_FAULT, usbio.DONE_INDETERMINATE)


@pytest.fixture(autouse=True)
def _fresh_serial_counters(monkeypatch):
    monkeypatch.setattr(_handshake, "_counters", {})


class DiscretePlc(threading.Thread):
    """The PLC on the other side of the wires: waits for READY, raises FACET_PRESENT with the recipe and
    dump bits, waits for an answer, records it and (if it acks) drops FACET_PRESENT."""

    def __init__(self, chip: VirtualFtdi, facets: list[dict], ack: bool = True):
        super().__init__(daemon=True)
        self.chip, self.facets, self.ack = chip, facets, ack
        self.answers: list[int] = []
        self.stop = threading.Event()

    def _until(self, cond) -> bool:
        while not self.stop.is_set():
            if cond():
                return True
            time.sleep(0.001)
        return False

    def run(self):
        self.chip.drive(facet_present=False, dump_request=False, recipe=0)
        for facet in self.facets:
            if not self._until(lambda: self.chip.status() == usbio.STATUS_READY):
                return
            self.chip.drive(recipe=facet.get("recipe", 0), dump_request=facet.get("dump", False),
                            facet_present=True)
            if not self._until(lambda: self.chip.status() in ANSWERED):
                return
            self.answers.append(self.chip.status())
            if self.ack:
                self.chip.drive(facet_present=False)


def _request(trigger: UsbTrigger, timeout_s: float = 5.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        request = trigger.wait_for_facet(0.1)
        if request is not None:
            return request
        trigger.heartbeat()
    raise AssertionError("no facet request")


def test_open_configures_async_bitbang():
    chip = VirtualFtdi()
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip))
    assert not chip.kernel_driver and chip.claimed == {0} and chip.configuration == 1
    assert chip.bitmode == usbio.BITMODE_BITBANG and chip.direction == 0x17
    assert chip.latency_ms == usbio.LATENCY_MS and chip.baud == (0x4138, 0)
    assert chip.status() == usbio.OFFLINE
    trigger.ready()
    assert chip.status() == usbio.STATUS_READY
    trigger.close()
    assert chip.status() == usbio.OFFLINE and chip.claimed == set()


def test_full_handshake_with_station_made_serials():
    chip = VirtualFtdi()
    facets = [{"recipe": 1}, {"recipe": 2, "dump": True}, {"recipe": 3}, {}, {}]
    plc = DiscretePlc(chip, facets)
    plc.start()
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip), recipes={1: "dish-5m33", 3: "gore"})
    answers = [("done", "pass"), ("done", "fail"), ("done", "invalid"), ("fault", FAULT_CODES["camera"]),
               ("done", "indeterminate")]
    requests = []
    for answer in answers:
        trigger.ready()
        requests.append(_request(trigger))
        trigger.busy()
        assert chip.status() == usbio.STATUS_BUSY
        if answer[0] == "done":
            trigger.done(answer[1])
        else:
            trigger.fault(answer[1], "camera gone")
    plc.join(5)
    assert plc.answers == [usbio.DONE_PASS, usbio.DONE_FAIL, usbio.DONE_INVALID, usbio.STATUS_FAULT,
                           usbio.DONE_INDETERMINATE]
    today = datetime.now().strftime("%Y%m%d")
    assert [r.serial for r in requests] == [f"USB-{today}-{n:04d}" for n in (1, 2, 3, 4, 5)]
    assert [r.recipe for r in requests] == ["dish-5m33", "2", "gore", "", ""]
    assert [r.dump for r in requests] == [False, True, False, False, False]
    assert [r.extra["recipe_code"] for r in requests] == [1, 2, 3, 0, 0]
    trigger.close()


def test_device_that_disappears_raises_and_a_new_trigger_finds_it_again():
    chip = VirtualFtdi()
    backend = VirtualUsbBackend(chip)
    plc = DiscretePlc(chip, [{}, {}])
    plc.start()
    trigger = UsbTrigger(backend=backend)
    trigger.ready()
    _request(trigger)
    trigger.busy()
    chip.unplug()
    t0 = time.monotonic()
    with pytest.raises(TriggerError, match="disappeared"):
        trigger.done("pass")
    assert time.monotonic() - t0 < 0.5
    trigger.close()  # no error on a device that is gone
    with pytest.raises(TriggerError, match="no FTDI FT232R/FT232H"):
        UsbTrigger(backend=backend)
    with pytest.raises(TriggerError, match="no FTDI FT232R/FT232H"):
        trigger.reopen()
    # Plugged in again (a new chip object: it re-enumerates, kernel driver bound again).
    chip2 = VirtualFtdi(address=6)
    backend.devices = [chip2]
    plc.stop.set()
    plc2 = DiscretePlc(chip2, [{}])
    plc2.start()
    assert trigger.reopen() is trigger
    assert "address 6" in trigger.name and not chip2.kernel_driver
    trigger.ready()
    _request(trigger)
    trigger.busy()
    trigger.done("pass")
    plc2.join(5)
    assert plc2.answers == [usbio.DONE_PASS]
    trigger.close()


def test_device_gone_while_waiting_for_a_facet():
    chip = VirtualFtdi()
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip))
    trigger.ready()
    chip.unplug()
    with pytest.raises(TriggerError, match="reading the pins failed"):
        trigger.wait_for_facet(1.0)


def test_plc_that_never_acknowledges():
    chip = VirtualFtdi()
    plc = DiscretePlc(chip, [{}], ack=False)
    plc.start()
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip), ack_timeout_s=0.4, heartbeat_interval_s=0.05)
    trigger.ready()
    _request(trigger)
    trigger.busy()
    toggles = chip.heartbeat_toggles()
    t0 = time.monotonic()
    with pytest.raises(TriggerError, match="PLC did not acknowledge the done-pass answer"):
        trigger.done("pass")
    assert 0.35 < time.monotonic() - t0 < 1.5
    assert chip.heartbeat_toggles() - toggles >= 4  # the heartbeat went on while it waited
    assert plc.answers == [usbio.DONE_PASS]
    trigger.close()
    # The reopened trigger does not take the still-raised FACET_PRESENT for a new facet.
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip))
    trigger.ready()
    assert trigger.wait_for_facet(0.1) is None
    chip.drive(facet_present=False)
    assert trigger.wait_for_facet(0.05) is None
    chip.drive(facet_present=True)
    assert trigger.wait_for_facet(0.5) is not None
    trigger.close()


def test_heartbeat_toggles_only_its_pin():
    chip = VirtualFtdi()
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip), heartbeat_interval_s=60)
    trigger.ready()
    start = chip.heartbeat_toggles()
    levels = []
    for _ in range(6):
        trigger.heartbeat()
        levels.append(bool(chip.pins() & usbio.OUT_HEARTBEAT))
        assert chip.status() == usbio.STATUS_READY
    assert chip.heartbeat_toggles() - start == 6
    assert levels == [levels[0], not levels[0]] * 3
    trigger.close()


def test_chip_is_chosen_by_serial_number_when_there_are_several():
    backend = VirtualUsbBackend(VirtualFtdi(serial="CABLE001", address=3),
                                VirtualFtdi(product_id=0x6014, serial="HANDSHK1", address=4))
    with pytest.raises(ConfigError, match="serial_number"):
        UsbTrigger(backend=backend)
    trigger = UsbTrigger(backend=backend, serial_number="HANDSHK1")
    assert "FT232H" in trigger.name
    chip = backend.devices[1]
    assert chip.bitmode == usbio.BITMODE_BITBANG and chip.baud == (0x4138, usbio.INTERFACE_A)
    assert backend.devices[0].bitmode == usbio.BITMODE_RESET  # the other one untouched
    trigger.close()
    with pytest.raises(TriggerError, match="with serial number NOPE"):
        UsbTrigger(backend=backend, serial_number="NOPE")


def test_inverting_interface_board():
    chip = VirtualFtdi()
    trigger = UsbTrigger(backend=VirtualUsbBackend(chip), invert_inputs=0xFF, invert_outputs=usbio.OUTPUT_MASK)
    chip.drive(facet_present=True)       # inverted: the station reads 0
    trigger.ready()
    assert usbio.pins_status(~chip.pins() & 0xFF) == usbio.STATUS_READY
    chip.drive(facet_present=False)      # inverted: a 1, a new request
    assert trigger.wait_for_facet(0.5) is not None
    trigger.close()


def test_serial_counter_restarts_daily_and_survives_a_restart_with_a_file(tmp_path):
    day = [datetime(2025, 6, 14, 10, 0)]
    path = tmp_path / "trigger" / "usb-serials.json"
    gen = _handshake.SerialGenerator("USB", path, clock=lambda: day[0])
    assert [gen.next() for _ in range(3)] == ["USB-20250614-0001", "USB-20250614-0002", "USB-20250614-0003"]
    _handshake._counters.clear()  # a restarted station: only the file remembers
    gen = _handshake.SerialGenerator("USB", path, clock=lambda: day[0])
    assert gen.next() == "USB-20250614-0004"
    day[0] = datetime(2025, 6, 15, 0, 1)
    assert gen.next() == "USB-20250615-0001"
    # Without a file the counter lives in the process, across trigger objects.
    other = _handshake.SerialGenerator("LINE2", clock=lambda: day[0])
    assert other.next() == "LINE2-20250615-0001"
    assert _handshake.SerialGenerator("LINE2", clock=lambda: day[0]).next() == "LINE2-20250615-0002"
    assert re.fullmatch(r"USB-\d{8}-\d{4}", _handshake.SerialGenerator().next())
