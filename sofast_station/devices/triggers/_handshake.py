"""The station's side of the robot/PLC handshake, shared by every trigger backend.

:class:`Handshake` keeps the call order of the :class:`~sofast_station.devices.protocols.Trigger`
protocol (``ready`` -> ``wait_for_facet`` -> ``busy`` -> ``done`` | ``fault``) and turns a call out of
order into a :class:`~sofast_station.errors.TriggerError`, so that the station's usual recovery (close and
reopen the trigger) also resets a handshake left in an unknown state. Backends implement the I/O.

It also holds the helpers the hardware backends share: verdict and status codes, recipe decoding,
station-generated serial numbers.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from datetime import datetime
from pathlib import Path

from ...errors import TriggerError

log = logging.getLogger(__name__)

#: The verdicts ``done`` accepts.
VERDICTS = ("pass", "fail", "invalid", "indeterminate")

#: Handshake states of the station side.
IDLE, READY, REQUESTED, BUSY, ANSWERED, CLOSED = "idle", "ready", "requested", "busy", "answered", "closed"


class Handshake:
    """Call-order bookkeeping for a trigger backend.

    Subclasses call :meth:`_enter` at the start of each protocol method with the states it is allowed
    from, and set ``self._state`` when the call has succeeded.
    """

    name = "trigger"

    def __init__(self) -> None:
        self._state = IDLE

    @property
    def state(self) -> str:
        """The handshake state: "idle", "ready", "requested", "busy", "answered" or "closed"."""
        return self._state

    def _enter(self, call: str, allowed: tuple[str, ...]) -> None:
        if self._state == CLOSED:
            raise TriggerError(f"{self.name}: {call}() on a closed trigger; open a new one")
        if self._state not in allowed:
            raise TriggerError(
                f"{self.name}: protocol violation: {call}() in state '{self._state}' (the order is "
                "ready, wait_for_facet until a request, busy, then done or fault); the station closes "
                "and reopens the trigger to reset the handshake")

    @staticmethod
    def _check_verdict(verdict: str) -> None:
        if verdict not in VERDICTS:
            raise ValueError(f"verdict must be one of {VERDICTS}, not {verdict!r}")

    @staticmethod
    def _check_fault_code(code: int) -> int:
        code = int(code)
        if not 1 <= code <= 0xFFFF:
            raise ValueError(f"fault code must be 1..65535, not {code}")
        return code


class PolledHandshake(Handshake):
    """A handshake the station drives by polling the PLC's signals (Modbus registers, USB pins).

    Subclasses provide ``_beat()``, and set ``ack_timeout_s``, ``poll_interval_s``,
    ``heartbeat_interval_s``, ``_last_beat``, ``_request`` and ``_armed``.
    """

    def _maybe_beat(self) -> None:
        if time.monotonic() - self._last_beat >= self.heartbeat_interval_s:
            self._beat()

    def _await_ack(self, poll, what: str, unchanged: str, check: str) -> None:
        """Poll until the PLC acknowledges an answer, beating the heartbeat meanwhile.

        Parameters
        ----------
        poll : callable
            Returns None while unacknowledged, else whether the station is armed for the next request
            (FACET_PRESENT already dropped).
        what : str
            The answer, for the message ("done-pass", "fault (3)").
        unchanged : str
            The signal that did not change, for the message.
        check : str
            What the operator should check besides the PLC program.
        """
        deadline = time.monotonic() + self.ack_timeout_s
        while True:
            armed = poll()
            if armed is not None:
                if armed:
                    self._armed = True
                return
            if time.monotonic() >= deadline:
                raise TriggerError(
                    f"{self.name}: PLC did not acknowledge the {what} answer for facet {self._request.serial} "
                    f"within {self.ack_timeout_s:g} s ({unchanged}); the station reports it and goes on: check "
                    f"the PLC program's handshake (docs/plc.md) and {check}")
            self._maybe_beat()
            pace(deadline, self.poll_interval_s)


def recipe_name(code: int, name: str = "", recipes: dict[int, str] | None = None) -> str:
    """The recipe of a facet request from the PLC's recipe code and (optional) recipe name.

    Parameters
    ----------
    code : int
        Recipe code the PLC sent (0 = none).
    name : str
        Recipe name the PLC sent ("" = none); wins over the code when given.
    recipes : dict of int to str, optional
        The station's table of recipe codes to names.

    Returns
    -------
    str
        ``name`` if not blank, else ``recipes[code]`` if listed, else "" for code 0, else the code in
        decimal (so that an unlisted code reaches the station's recipe lookup and is reported there,
        never silently replaced by the default).
    """
    name = name.strip()
    if name:
        return name
    if recipes and code in recipes:
        return recipes[code]
    return "" if code == 0 else str(code)


def pace(deadline: float, poll_interval_s: float) -> None:
    """Sleep one poll interval (seconds), but never past ``deadline`` (time.monotonic seconds)."""
    time.sleep(max(0.0, min(poll_interval_s, deadline - time.monotonic())))


# Station-generated serial numbers (for backends whose PLC cannot send one). -------------------------

_counters: dict[str, tuple[str, int]] = {}
_counters_lock = threading.Lock()


class SerialGenerator:
    """Serial numbers "<prefix>-<YYYYMMDD>-<NNNN>" made by the station, the counter restarting daily.

    The counter continues across trigger objects of the same prefix in one process (the station reopens
    its trigger after every handshake error) and, when ``counter_file`` is given, across restarts: the
    file holds ``{"date": "YYYYMMDD", "counter": N}`` and is replaced atomically after every serial.

    Parameters
    ----------
    prefix : str
        First part of every serial, e.g. "USB".
    counter_file : str or Path, optional
        Where the last counter is kept (under the station's data_dir). Without it a restarted station
        counts again from 0001 on the same day.
    clock : callable, optional
        Returns the local date and time (datetime); tests pass a fixed one.
    """

    def __init__(self, prefix: str = "USB", counter_file: str | os.PathLike | None = None,
                 clock=datetime.now):
        self.prefix = prefix
        self.counter_file = Path(counter_file) if counter_file is not None else None
        self.clock = clock

    def _load(self) -> tuple[str, int]:
        if self.counter_file is not None and self.counter_file.exists():
            try:
                data = json.loads(self.counter_file.read_text())
                return str(data["date"]), int(data["counter"])
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.warning("serial counter file %s unreadable (%s): counting from the process's "
                            "own counter", self.counter_file, exc)
        return _counters.get(self.prefix, ("", 0))

    def _store(self, date: str, counter: int) -> None:
        _counters[self.prefix] = (date, counter)
        if self.counter_file is None:
            return
        try:
            self.counter_file.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.counter_file.with_name(self.counter_file.name + ".tmp")
            tmp.write_text(json.dumps({"date": date, "counter": counter}))
            os.replace(tmp, self.counter_file)
        except OSError as exc:  # never stop the line for this: the process counter still counts
            log.warning("cannot write serial counter file %s: %s", self.counter_file, exc)

    def next(self) -> str:
        """The next serial number, e.g. "USB-20250614-0007"."""
        with _counters_lock:
            today = self.clock().strftime("%Y%m%d")
            date, counter = self._load()
            mem_date, mem_counter = _counters.get(self.prefix, ("", 0))
            if mem_date == date:  # the file may lag the process (unwritable disk)
                counter = max(counter, mem_counter)
            counter = counter + 1 if date == today else 1
            self._store(today, counter)
            return f"{self.prefix}-{today}-{counter:04d}"
