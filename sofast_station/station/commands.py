"""Operator commands to the running loop: files in ``data_dir/commands/``, taken between facets.

Anything that wants the line to do something (the web page's guarded actions, the command line) posts a
command here; the station's loop takes the waiting commands between two facets, oldest first, and
deletes each as it takes it. A command is a small JSON file written under a temporary name and renamed,
so the loop never reads half of one. Nothing here touches the devices: :class:`~.runner.StationRunner`
acts on what it takes.

Commands
--------
``dump-next``
    Dump the next facet measured (the same flag file ``sofast-station dump-next`` touches).
``pause`` / ``resume``
    Stop taking facets from the robot/PLC after the one in progress / take them again.
``remeasure``
    Measure the facet in the fixture again, under the last facet's serial and recipe, as a new cycle
    (journaled with ``request.operator = "remeasure"``; the robot is not answered, it did not ask).
``serial``
    The next facet gets this serial (the barcode could not be read); the record keeps what the robot
    said as ``request.serial_read``.
"""

from __future__ import annotations

import json
import logging
import os
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from ..errors import CommandError

log = logging.getLogger(__name__)

COMMANDS = ("dump-next", "pause", "resume", "remeasure", "serial")
#: The flag file of ``dump-next`` in data_dir (its presence means: dump the next facet).
DUMP_NEXT_FLAG = "dump-next"
#: Longest serial an operator may enter, characters.
MAX_MANUAL_SERIAL = 64


@dataclass(frozen=True)
class Command:
    """One operator command, as taken by the loop."""

    name: str
    serial: str | None = None
    source: str = ""
    posted: str = ""


def commands_dir(data_dir: str | Path) -> Path:
    return Path(data_dir) / "commands"


def check_manual_serial(serial: str) -> str:
    """A serial typed by an operator, stripped; CommandError when empty, too long or not printable."""
    serial = str(serial).strip()
    if not serial:
        raise CommandError("the serial is empty: type the serial printed on the facet")
    if len(serial) > MAX_MANUAL_SERIAL:
        raise CommandError(f"the serial is {len(serial)} characters long; at most {MAX_MANUAL_SERIAL} are allowed")
    if not serial.isprintable():
        raise CommandError("the serial holds control characters; type only the characters printed on the facet")
    return serial


def post_command(data_dir: str | Path, name: str, serial: str | None = None, source: str = "") -> Path:
    """Queue a command for the loop; returns its file. ``dump-next`` touches the flag file instead."""
    if name not in COMMANDS:
        raise CommandError(f"unknown command {name!r}; known: {', '.join(COMMANDS)}")
    if name == "dump-next":
        return request_dump_next(data_dir)
    if name == "serial":
        serial = check_manual_serial(serial or "")
    folder = commands_dir(data_dir)
    folder.mkdir(parents=True, exist_ok=True)
    stamp = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}"
    final = folder / f"{stamp}.json"
    tmp = folder / f".{stamp}.tmp"
    tmp.write_text(json.dumps({"command": name, "serial": serial, "source": source,
                               "posted": time.strftime("%Y-%m-%dT%H:%M:%S%z")}), encoding="utf-8")
    os.replace(tmp, final)
    log.info("command %s posted (%s)", name, source or "no source given")
    return final


def request_dump_next(data_dir: str | Path) -> Path:
    """Ask the loop to dump the next facet it measures."""
    flag = Path(data_dir) / DUMP_NEXT_FLAG
    flag.parent.mkdir(parents=True, exist_ok=True)
    flag.touch()
    return flag


def take_dump_next(data_dir: str | Path) -> bool:
    """True (once) when a dump of the next facet was asked for."""
    flag = Path(data_dir) / DUMP_NEXT_FLAG
    if flag.exists():
        flag.unlink(missing_ok=True)
        return True
    return False


def take_commands(data_dir: str | Path) -> list[Command]:
    """The waiting commands, oldest first, each deleted as it is taken; unreadable files are dropped with
    a log line."""
    folder = commands_dir(data_dir)
    try:
        names = sorted(e.name for e in os.scandir(folder) if e.name.endswith(".json"))
    except FileNotFoundError:
        return []
    out = []
    for name in names:
        path = folder / name
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            cmd = Command(str(data["command"]), data.get("serial"), str(data.get("source", "")),
                          str(data.get("posted", "")))
            if cmd.name not in COMMANDS:
                raise ValueError(f"unknown command {cmd.name!r}")
            out.append(cmd)
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.error("dropping the unreadable command file %s: %s", path, exc)
        path.unlink(missing_ok=True)
    return out
