"""The station's live state for the monitor (web page, OPC UA): ``data_dir/live/status.json``.

The loop writes it on every change of state (a facet starts, ends, the line pauses, an alarm is raised or
cleared): a few hundred bytes, written under a temporary name and renamed, no fsync (the journal is the
durable record; this file only says what the station is doing now). Readers treat a status whose
process is gone as ``offline``.

States: ``idle`` (waiting for a facet), ``measuring``, ``fault`` (the last facet faulted; until the next
one starts), ``paused`` (an operator paused the line), ``offline`` (no station process).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import os
from pathlib import Path

from ..files import pid_alive, write_file_atomic

log = logging.getLogger(__name__)

STATES = ("idle", "measuring", "fault", "paused", "offline")
#: Alarms the loop raises itself (the monitor adds calibration, drift and disk from the journal).
LOOP_ALARMS = ("camera", "plc")


def status_path(data_dir: str | Path) -> Path:
    return Path(data_dir) / "live" / "status.json"


class StatusFile:
    """Writer of the live status (the station process only)."""

    def __init__(self, data_dir: str | Path):
        self.path = status_path(data_dir)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.data: dict = {"state": "idle", "pid": os.getpid(), "serial": None, "cycle_id": None,
                           "alarms": {}, "manual_serial": None, "since": _now()}

    def update(self, **fields) -> None:
        """Change fields (``state``, ``serial``...) and write the file; an I/O error is only logged."""
        if "state" in fields and fields["state"] != self.data.get("state"):
            fields.setdefault("since", _now())
        self.data.update(fields)
        self.data["updated"] = _now()
        try:
            text = json.dumps(self.data)
            write_file_atomic(self.path, lambda fh: fh.write(text), mode="w")
        except OSError as exc:
            log.warning("could not write the live status %s: %s", self.path, exc)

    def alarm(self, name: str, text: str | None) -> None:
        """Raise (*text*) or clear (None) an alarm; writes only when it changes."""
        alarms = dict(self.data.get("alarms") or {})
        if alarms.get(name) == text or (text is None and name not in alarms):
            return
        if text is None:
            alarms.pop(name, None)
        else:
            alarms[name] = text
        self.update(alarms=alarms)

    def close(self) -> None:
        self.update(state="offline", pid=None)


def read_status(data_dir: str | Path) -> dict:
    """The live status; ``offline`` when the file is missing or its process is gone."""
    try:
        data = json.loads(status_path(data_dir).read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError("not an object")
    except (OSError, ValueError):
        return {"state": "offline", "alarms": {}}
    pid = data.get("pid")
    if data.get("state") != "offline" and not (isinstance(pid, int) and pid_alive(pid)):
        data["state"] = "offline"
    return data


def _now() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="milliseconds")
