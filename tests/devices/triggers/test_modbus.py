"""The Modbus TCP trigger against a scripted PLC (pymodbus server) in a separate process on 127.0.0.1."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import signal
import time

import pytest

import pymodbus  # noqa: F401  (a dependency: its absence must fail, not skip)

from pymodbus.client import ModbusTcpClient

from sofast_station.devices.protocols import FAULT_CODES, WARNING_BITS
from sofast_station.devices.triggers import modbus
from sofast_station.devices.triggers.modbus import ModbusTrigger, RegisterMap, decode_ascii, encode_ascii
from sofast_station.errors import TriggerError

from .fake_plc import MAP, free_port, plc_block, run_plc

SPAWN = mp.get_context("spawn")


class Plc:
    """A scripted PLC process; ``events`` is what it reported."""

    def __init__(self, script: dict, port: int | None = None):
        self.port = port or free_port()
        self.events = SPAWN.Queue()
        self.proc = SPAWN.Process(target=run_plc, args=(self.port, script, self.events), daemon=True)
        self.proc.start()
        kind, _ = self.next("listening", timeout=20)

    def next(self, kind: str, timeout: float = 5.0):
        """The next event of ``kind`` (earlier events of other kinds are kept in ``seen``)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                event = self.events.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"the PLC reported no {kind!r} within {timeout} s") from None
            if event[0] == kind:
                return event
            if event[0] == "error":
                raise AssertionError(f"PLC error: {event[1]}")

    def kill(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(5)


@pytest.fixture
def plcs():
    """Start scripted PLCs with ``plcs(script)``; every one is killed at the end."""
    started: list[Plc] = []

    def start(script: dict, port: int | None = None) -> Plc:
        plc = Plc(script, port)
        started.append(plc)
        return plc

    yield start
    for plc in started:
        if plc.proc.is_alive():
            os.kill(plc.proc.pid, signal.SIGCONT)  # a frozen one must run to die
        plc.kill()
        plc.events.close()
        plc.events.join_thread()


class Observer:
    """An HMI-like second client: reads and writes the PLC's registers directly."""

    def __init__(self, port: int):
        self.client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        assert self.client.connect()

    def station(self) -> list[int]:
        return self.client.read_holding_registers(MAP.station_base, count=modbus.STATION_REGISTERS,
                                                  device_id=1).registers

    def write_plc(self, block: list[int]) -> None:
        assert not self.client.write_registers(MAP.plc_base, block, device_id=1).isError()

    def close(self):
        self.client.close()


def _wait_request(trigger: ModbusTrigger, timeout_s: float = 5.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        request = trigger.wait_for_facet(0.2)
        if request is not None:
            return request
        trigger.heartbeat()
    raise AssertionError("no facet request")


def test_register_map_is_the_documented_one():
    m = RegisterMap()
    assert (m.station_base, m.plc_base, m.serial_registers, m.recipe_name_registers) == (0, 100, 10, 8)
    assert (modbus.STATUS, modbus.VERDICT, modbus.FAULT_CODE, modbus.HEARTBEAT, modbus.CYCLE,
            modbus.SEQUENCE_ECHO, modbus.WARNINGS, modbus.STATION_REGISTERS) == (0, 1, 2, 3, 4, 5, 6, 7)
    assert (modbus.FACET_PRESENT, modbus.ACK, modbus.DUMP_REQUEST, modbus.RECIPE_CODE, modbus.SEQUENCE,
            modbus.SERIAL, m.recipe_name_offset, m.plc_registers) == (0, 1, 2, 3, 4, 5, 15, 23)
    with pytest.raises(ValueError, match="overlaps"):
        RegisterMap(station_base=100, plc_base=95)


def test_ascii_packing_high_byte_first():
    regs = encode_ascii("AB-12345", 5)
    assert regs[:4] == [0x4142, 0x2D31, 0x3233, 0x3435] and regs[4] == 0
    assert decode_ascii(regs) == "AB-12345"
    assert decode_ascii([0x4120, 0x2020]) == "A"           # space padding
    assert decode_ascii([0x41FF, 0x0042]) == "A?"          # not ASCII -> "?", NUL ends it
    with pytest.raises(ValueError):
        encode_ascii("X" * 21, 10)


def test_full_multi_facet_handshake(plcs):
    facets = [{"serial": "MF-2024-0001", "recipe_code": 2},
              {"serial": "MF-2024-0002", "recipe_name": "gore-inner", "dump": True},
              {"serial": "MF-2024-0003", "recipe_code": 7},
              {"serial": "MF-2024-0004"}, {"serial": "MF-2024-0005"}]
    plc = plcs({"facets": facets, "ack_delay_s": 0.02})
    trigger = ModbusTrigger("127.0.0.1", plc.port, recipes={2: "dish-5m33"})
    answers = [("done", "pass"), ("done", "fail"), ("fault", FAULT_CODES["capture"]), ("done", "invalid"),
               ("done", "indeterminate")]
    # a drift alarm rides with the first answer, the line alarm with the fault (and the answer after it)
    warnings = [WARNING_BITS["drift"], 0, WARNING_BITS["line"], WARNING_BITS["line"] | WARNING_BITS["drift"], 0]
    requests = []
    for answer, warn in zip(answers, warnings):
        trigger.ready()
        request = _wait_request(trigger)
        requests.append(request)
        trigger.busy()
        t0 = time.monotonic()
        if answer[0] == "done":
            trigger.done(answer[1], warnings=warn)
        else:
            trigger.fault(answer[1], "dark frame", warnings=warn)
        assert 0.015 < time.monotonic() - t0 < 2.0  # returned on the PLC's (delayed) acknowledgement
    assert [r.serial for r in requests] == [f["serial"] for f in facets]
    assert [r.recipe for r in requests] == ["dish-5m33", "gore-inner", "7", "", ""]
    assert [r.dump for r in requests] == [False, True, False, False, False]
    assert [r.extra["sequence"] for r in requests] == [1000, 1001, 1002, 1003, 1004]
    reported = [plc.next("answer")[1] for _ in facets]
    assert [a["warnings"] for a in reported] == warnings
    assert [(a["status"], a["verdict"], a["fault_code"]) for a in reported] == [
        (modbus.STATUS_DONE, 1, 0), (modbus.STATUS_DONE, 2, 0), (modbus.STATUS_FAULT, 0, 3),
        (modbus.STATUS_DONE, 3, 0), (modbus.STATUS_DONE, 4, 0)]
    assert [a["echo"] for a in reported] == [a["sequence"] for a in reported]
    assert [a["cycle"] for a in reported] == [1, 2, 3, 4, 5]
    trigger.ready()  # the PLC clears ACK once the station is ready again, then it has no more facets
    plc.next("finished")
    assert trigger.wait_for_facet(0.1) is None
    trigger.close()
    obs = Observer(plc.port)
    assert obs.station()[modbus.STATUS] == modbus.OFFLINE
    obs.close()


def test_plc_killed_mid_cycle_raises_quickly_and_a_new_trigger_reconnects(plcs):
    plc = plcs({"facets": [{"serial": "K-1"}]})
    trigger = ModbusTrigger("127.0.0.1", plc.port, timeout_s=2.0)
    trigger.ready()
    assert _wait_request(trigger).serial == "K-1"
    trigger.busy()
    plc.kill()  # SIGKILL: the PLC's sockets close under the station
    t0 = time.monotonic()
    with pytest.raises(TriggerError, match="failed") as err:
        trigger.done("pass")
    assert time.monotonic() - t0 < 1.0
    assert "reconnects" in str(err.value)
    with pytest.raises(TriggerError, match="closed"):
        trigger.heartbeat()
    trigger.close()  # no error on a dead connection
    t0 = time.monotonic()
    with pytest.raises(TriggerError, match="cannot connect"):
        trigger.reopen()  # the station's recovery, while the PLC is still down
    with pytest.raises(TriggerError, match="cannot connect"):
        ModbusTrigger("127.0.0.1", plc.port, timeout_s=1.0)
    assert time.monotonic() - t0 < 1.5
    # The PLC comes back on the same port: the same trigger reconnects and works.
    plcs({"facets": [{"serial": "K-2"}]}, port=plc.port)
    assert trigger.reopen() is trigger
    trigger.ready()
    assert _wait_request(trigger).serial == "K-2"
    trigger.busy()
    trigger.done("pass")
    trigger.close()


def test_frozen_plc_raises_after_the_request_timeout(plcs):
    plc = plcs({"facets": []})
    trigger = ModbusTrigger("127.0.0.1", plc.port, timeout_s=0.3)
    trigger.ready()
    os.kill(plc.proc.pid, signal.SIGSTOP)  # connection open, nobody answers
    t0 = time.monotonic()
    with pytest.raises(TriggerError):
        trigger.wait_for_facet(5.0)
    assert time.monotonic() - t0 < 2.0
    trigger.close()


def test_plc_that_never_acknowledges(plcs):
    plc = plcs({"facets": [{"serial": "NA-1"}], "ack": False})
    trigger = ModbusTrigger("127.0.0.1", plc.port, ack_timeout_s=0.6, heartbeat_interval_s=0.1)
    obs = Observer(plc.port)
    trigger.ready()
    assert _wait_request(trigger).serial == "NA-1"
    trigger.busy()
    beat0 = obs.station()[modbus.HEARTBEAT]
    t0 = time.monotonic()
    with pytest.raises(TriggerError, match="PLC did not acknowledge the done \\(fail\\) answer for facet NA-1"):
        trigger.done("fail")
    assert 0.55 < time.monotonic() - t0 < 2.0
    answer = plc.next("answer")[1]
    assert (answer["status"], answer["verdict"]) == (modbus.STATUS_DONE, 2)
    # The trigger kept the heartbeat going while it waited.
    assert (obs.station()[modbus.HEARTBEAT] - beat0) % 65536 >= 3
    # The station's recovery: close (STATUS offline) and open a new trigger.
    trigger.close()
    assert obs.station()[modbus.STATUS] == modbus.OFFLINE
    trigger = ModbusTrigger("127.0.0.1", plc.port)
    trigger.ready()
    # FACET_PRESENT is still 1 from the unacknowledged cycle: not a new request.
    assert trigger.wait_for_facet(0.2) is None
    trigger.close()
    obs.close()


def test_heartbeat_counter_increments_and_continues_across_reconnects(plcs):
    plc = plcs({"facets": []})
    obs = Observer(plc.port)
    trigger = ModbusTrigger("127.0.0.1", plc.port, heartbeat_interval_s=60)
    seen = [obs.station()[modbus.HEARTBEAT]]
    for _ in range(5):
        trigger.heartbeat()
        seen.append(obs.station()[modbus.HEARTBEAT])
    assert [b - a for a, b in zip(seen, seen[1:])] == [1] * 5
    trigger._regs[modbus.HEARTBEAT] = 0xFFFF  # wraps at 16 bits
    trigger.heartbeat()
    assert obs.station()[modbus.HEARTBEAT] == 0
    trigger.heartbeat()
    trigger.close()
    trigger = ModbusTrigger("127.0.0.1", plc.port, heartbeat_interval_s=60)
    trigger.heartbeat()
    assert obs.station()[modbus.HEARTBEAT] == 2  # the new connection counts on
    trigger.close()
    obs.close()


def test_stale_request_waits_for_a_new_rising_edge(plcs):
    plc = plcs({"facets": []})  # the test drives the PLC block itself
    obs = Observer(plc.port)
    obs.write_plc(plc_block({"serial": "OLD-1"}, 1))  # left over from an interrupted cycle
    trigger = ModbusTrigger("127.0.0.1", plc.port)
    trigger.ready()
    assert trigger.wait_for_facet(0.15) is None
    obs.write_plc(plc_block({"serial": "OLD-1"}, 1, present=0))
    assert trigger.wait_for_facet(0.1) is None
    obs.write_plc(plc_block({"serial": "NEW-2"}, 2))
    request = trigger.wait_for_facet(1.0)
    assert request is not None and request.serial == "NEW-2"
    trigger.busy()
    assert obs.station()[modbus.STATUS] == modbus.STATUS_BUSY
    assert obs.station()[modbus.SEQUENCE_ECHO] == 2
    trigger.close()
    obs.close()


def test_register_map_the_plc_does_not_serve_is_reported(plcs):
    plc = plcs({"facets": []})
    with pytest.raises(TriggerError, match="check the register map"):
        ModbusTrigger("127.0.0.1", plc.port, register_map=RegisterMap(plc_base=190))


def test_empty_serial_gets_a_station_made_one(plcs, caplog):
    plc = plcs({"facets": []})
    obs = Observer(plc.port)
    trigger = ModbusTrigger("127.0.0.1", plc.port)
    trigger.ready()
    obs.write_plc(plc_block({"serial": "", "recipe_code": 1}, 42))
    request = trigger.wait_for_facet(1.0)
    assert request is not None and request.serial.startswith("PLC-NOSERIAL-") and request.serial.endswith("-00042")
    assert request.extra["serial_missing"] and request.recipe == "1"
    assert "empty SERIAL" in caplog.text
    trigger.close()
    obs.close()


@pytest.mark.parametrize("ack_seen", [True, False], ids=["ack-and-request-together", "ack-pulse-missed"])
def test_a_request_raised_right_after_the_acknowledgement_is_taken(plcs, ack_seen):
    """Issue 11: the PLC acknowledges late and raises the next facet before the station's next poll. The
    station never sees FACET_PRESENT at 0; the new SEQUENCE tells it that this is a new request."""
    import threading

    plc = plcs({"facets": []})
    obs = Observer(plc.port)
    trigger = ModbusTrigger("127.0.0.1", plc.port, ack_timeout_s=20.0)
    obs.write_plc(plc_block({"serial": "FIRST-1"}, 1, present=0))
    trigger.ready()
    obs.write_plc(plc_block({"serial": "FIRST-1"}, 1))
    assert _wait_request(trigger).serial == "FIRST-1"
    trigger.busy()
    answered = threading.Thread(target=trigger.done, args=("pass",))
    answered.start()
    deadline = time.monotonic() + 10
    while obs.station()[modbus.STATUS] != modbus.STATUS_DONE:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    time.sleep(0.3)                                    # a late acknowledgement ...
    # ... written in one go with the next facet: ACK = 1 with the new request, or ACK already back at 0
    obs.write_plc(plc_block({"serial": "NEXT-2"}, 2, present=1, ack=1 if ack_seen else 0))
    answered.join(10)
    assert not answered.is_alive()
    trigger.ready()
    if ack_seen:
        assert trigger.wait_for_facet(0.1) is None     # ACK still 1: not yet
        obs.write_plc(plc_block({"serial": "NEXT-2"}, 2, present=1, ack=0))   # the PLC clears ACK on READY
    request = trigger.wait_for_facet(2.0)
    assert request is not None and request.serial == "NEXT-2" and request.extra["sequence"] == 2
    trigger.busy()
    assert obs.station()[modbus.SEQUENCE_ECHO] == 2
    trigger.close()
    obs.close()


def test_a_plc_down_at_start_is_retried_until_it_answers(plcs, caplog):
    """Issue 11: the station starting before its PLC waits for it, as its message says, instead of exiting."""
    import threading
    from types import SimpleNamespace

    from sofast_station.station.service import open_trigger_from_config

    port = free_port()
    config = SimpleNamespace(path="station.toml", raw={"devices": {"trigger": "modbus", "trigger_options": {
        "host": "127.0.0.1", "port": port, "timeout_s": 0.5}}})
    opened = []
    thread = threading.Thread(target=lambda: opened.append(open_trigger_from_config(config, None, retry_s=0.2)),
                              daemon=True)
    with caplog.at_level("ERROR"):
        thread.start()
        time.sleep(1.5)                                # several attempts fail meanwhile
        assert not opened and thread.is_alive()
        plcs({"facets": []}, port=port)
        thread.join(20)
    assert opened and isinstance(opened[0], ModbusTrigger)
    assert "retrying every 0.2 s" in caplog.text
    opened[0].close()


def _answer_not_acknowledged_in_time(plcs):
    """A trigger whose answer to FIRST-1 (SEQUENCE 7) the PLC did not acknowledge within ``ack_timeout_s``
    (the test is the PLC program: every write in order), and the observer that plays the PLC."""
    plc = plcs({"facets": []})
    obs = Observer(plc.port)
    trigger = ModbusTrigger("127.0.0.1", plc.port, ack_timeout_s=0.3, heartbeat_interval_s=0.1)
    obs.write_plc(plc_block({"serial": "FIRST-1"}, 7, present=0))
    trigger.ready()
    obs.write_plc(plc_block({"serial": "FIRST-1"}, 7))
    assert _wait_request(trigger).serial == "FIRST-1"
    trigger.busy()
    with pytest.raises(TriggerError, match="did not acknowledge"):
        trigger.done("pass")                           # the PLC is late: the station gives up waiting
    return trigger, obs


@pytest.mark.parametrize("moment", ["before-reopen", "after-reopen", "after-ready"])
def test_a_late_acknowledgement_followed_at_once_by_the_next_request_is_taken(plcs, moment):
    """Issue 28: the PLC acknowledges after ``ack_timeout_s`` (the station has reported it and reconnected),
    drops FACET_PRESENT for under a millisecond and raises the next facet with a new SEQUENCE. Whenever
    those two writes land in the station's recovery (before its reconnect, between reconnect and READY,
    or after READY), the next facet is taken, as docs/plc.md promises; the request of the interrupted
    cycle itself (its SEQUENCE) still is not."""
    trigger, obs = _answer_not_acknowledged_in_time(plcs)

    def late_ack_then_next_facet():
        obs.write_plc(plc_block({"serial": "FIRST-1"}, 7, present=0, ack=1))      # the late acknowledgement
        obs.write_plc(plc_block({"serial": "NEXT-2"}, 8, present=1, ack=0))       # the next facet at once

    if moment == "before-reopen":
        late_ack_then_next_facet()
    trigger.reopen()                                   # the station's recovery (runner._reopen_trigger)
    if moment == "after-reopen":
        late_ack_then_next_facet()
    trigger.ready()
    if moment == "after-ready":
        late_ack_then_next_facet()
    request = trigger.wait_for_facet(1.0)
    assert request is not None and request.serial == "NEXT-2" and request.extra["sequence"] == 8
    trigger.busy()
    assert obs.station()[modbus.SEQUENCE_ECHO] == 8
    trigger.close()
    obs.close()


def test_after_a_reconnect_the_interrupted_cycles_own_request_stays_stale(plcs):
    """The other side of the SEQUENCE rule: the station reconnects while the unacknowledged request is still
    up with the SEQUENCE it answered; that is not a new facet until the PLC drops it and raises it again."""
    trigger, obs = _answer_not_acknowledged_in_time(plcs)
    trigger.reopen()
    trigger.ready()
    assert trigger.wait_for_facet(0.3) is None         # SEQUENCE 7 again: the interrupted cycle's request
    obs.write_plc(plc_block({"serial": "FIRST-1"}, 7, present=0))
    assert trigger.wait_for_facet(0.1) is None
    obs.write_plc(plc_block({"serial": "FIRST-1"}, 7))  # placed again (a rising edge): taken
    request = trigger.wait_for_facet(1.0)
    assert request is not None and request.serial == "FIRST-1"
    trigger.close()
    obs.close()


def test_a_plc_outage_is_said_once_then_once_a_minute(caplog):
    """Issue 28: a PLC outage wrote about five log lines a second (the loop's failure, its failed reconnect,
    the heartbeat's, pymodbus's own). The loop's link watch says it once, then once a minute, and once when
    the link is back; reconnects are tried after a pause doubling up to MAX_PAUSE_S. On a test clock: a
    ten-minute outage of a PLC that refuses every reconnect (the real ModbusTrigger against a closed port)."""
    from sofast_station.station.link import MAX_PAUSE_S, LinkWatch

    now = [1000.0]
    watch = LinkWatch(first_pause_s=0.5, clock=lambda: now[0])
    port = free_port()                                  # nobody listens there: the PLC is off
    pauses = []
    with caplog.at_level(logging.DEBUG):
        while now[0] < 1000.0 + 600.0:
            try:
                ModbusTrigger("127.0.0.1", port, timeout_s=0.2)
            except TriggerError as exc:
                pauses.append(watch.failed(exc))
                now[0] += pauses[-1]
        watch.ok()
    lines = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(pauses) > 100                          # a reconnect every few seconds, all along
    assert pauses[:4] == [0.5, 1.0, 2.0, 4.0] and max(pauses) == MAX_PAUSE_S
    assert 10 <= len(lines) <= 13, [r.getMessage() for r in lines]   # the first, ~10 reminders, the recovery
    assert "handshake failed" in lines[0].getMessage() and "back after 6" in lines[-1].getMessage()
    assert not [r for r in caplog.records if r.name.startswith("pymodbus")]
