"""Operator commands to the running loop: files in ``data_dir/commands/``, taken between facets.

Anything that wants the line to do something (the web page's guarded actions, the command line) posts a
command here; the station's loop takes the waiting commands between two facets, oldest first, and
deletes each as it takes it. A command is a small JSON file written under a temporary name and renamed,
so the loop never reads half of one. Nothing here touches the devices:
:class:`~sofast_station.station.runner.StationRunner` acts on what it takes.

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

from ..files import write_file_atomic
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


def check_manual_serial(serial) -> str:
    """A serial typed by an operator, stripped; CommandError when not text, empty, too long or not printable.

    This only tells the operator at once what cannot be a serial; the loop makes every serial safe, from
    wherever it comes, with :func:`sofast_station.serials.clean_serial` (the record keeps the original as
    ``serial_raw`` when that changed it).
    """
    if not isinstance(serial, str):
        raise CommandError(f"the serial must be text, e.g. \"F-123\", not {type(serial).__name__} "
                           f"{_shown(serial)}")
    serial = serial.strip()
    if not serial:
        raise CommandError("the serial is empty: type the serial printed on the facet")
    if len(serial) > MAX_MANUAL_SERIAL:
        raise CommandError(f"the serial is {len(serial)} characters long; at most {MAX_MANUAL_SERIAL} are allowed")
    if not serial.isprintable():
        raise CommandError("the serial holds control characters; type only the characters printed on the facet")
    return serial


def _shown(value, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def post_command(data_dir: str | Path, name: str, serial: str | None = None, source: str = "") -> Path:
    """Queue a command for the loop; returns its file. ``dump-next`` touches the flag file instead.

    Raises
    ------
    CommandError
        An unknown command, a bad serial, or a commands folder that cannot be written (saying why).
    """
    if name not in COMMANDS:
        raise CommandError(f"unknown command {name!r}; known: {', '.join(COMMANDS)}")
    try:
        if name == "dump-next":
            return request_dump_next(data_dir)
        if name == "serial":
            serial = check_manual_serial("" if serial is None else serial)
        folder = commands_dir(data_dir)
        folder.mkdir(parents=True, exist_ok=True)
        stamp = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}"
        text = json.dumps({"command": name, "serial": serial, "source": source,
                           "posted": time.strftime("%Y-%m-%dT%H:%M:%S%z")})
        final = write_file_atomic(folder / f"{stamp}.json", lambda fh: fh.write(text), mode="w")
    except OSError as exc:
        raise CommandError(f"the command {name} could not be posted to {commands_dir(data_dir)} "
                           f"({exc.strerror or exc}): that must be a writable folder of the station's data_dir "
                           "(a file of that name, a full disk or a read-only mount?)") from None
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
    try:
        flag.unlink()
        return True
    except FileNotFoundError:
        return False
    except OSError as exc:                      # a folder of that name, a read-only disk: never stop the line
        _once(f"flag:{exc.errno}", logging.ERROR, "the dump-next flag %s cannot be taken (%s); remove it",
              flag, exc.strerror or exc)
        return False


#: Largest command file taken, bytes (a command is a few hundred bytes; anything far larger is not one).
MAX_COMMAND_BYTES = 65536
#: Where entries of the commands folder that are not command files are moved (never deleted).
REJECTED = "rejected"

#: Problems with the commands folder already logged by this process (each is logged once, not at every
#: look between facets).
_reported: set = set()


def _once(key: str, level: int, message: str, *args) -> None:
    if key not in _reported:
        _reported.add(key)
        log.log(level, message, *args)


def take_commands(data_dir: str | Path) -> list[Command]:
    """The waiting commands, oldest first, each deleted as it is taken.

    Never raises: the loop looks here between every two facets, and nothing found here may stop it. A
    command file that cannot be read or is not a command is dropped with a log line saying why; an entry
    that is not a file (a folder named ``x.json``) is moved to ``commands/rejected/``; a ``commands`` that is
    not a folder is reported once and ignored.
    """
    folder = commands_dir(data_dir)
    try:
        entries = sorted((e for e in os.scandir(folder) if e.name.endswith(".json")), key=lambda e: e.name)
    except FileNotFoundError:
        return []
    except OSError as exc:
        _once(f"folder:{exc.errno}", logging.ERROR, "operator commands cannot be taken: %s is not a readable "
              "folder (%s); remove or rename it, the station makes the folder again", folder, exc.strerror or exc)
        return []
    out = []
    for entry in entries:
        path = folder / entry.name
        try:
            if not entry.is_file(follow_symlinks=False):
                _set_aside(folder, entry.name, "is not a command file (a folder or a link)")
                continue
            if entry.stat(follow_symlinks=False).st_size > MAX_COMMAND_BYTES:
                raise ValueError(f"larger than {MAX_COMMAND_BYTES} bytes: not a command")
            out.append(_parse(json.loads(path.read_text(encoding="utf-8"))))
        except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
            log.error("dropping the command file %s: %s", path, exc)
        try:
            path.unlink(missing_ok=True)
        except OSError as exc:
            _once(f"unlink:{entry.name}", logging.ERROR, "could not delete the command file %s (%s); it is "
                  "taken again at every look until it is removed", path, exc.strerror or exc)
    return out


def _parse(data) -> Command:
    """A command file's JSON as a :class:`Command`; ValueError naming what is wrong."""
    if not isinstance(data, dict):
        raise ValueError(f"a command file holds a JSON object, not {type(data).__name__}")
    name = data.get("command")
    if not isinstance(name, str) or name not in COMMANDS:
        raise ValueError(f"unknown command {_shown(name)}; known: {', '.join(COMMANDS)}")
    serial = data.get("serial")
    if name == "serial":
        try:
            serial = check_manual_serial(serial)
        except CommandError as exc:
            raise ValueError(str(exc)) from None
    else:
        serial = None
    return Command(name, serial, str(data.get("source", ""))[:200], str(data.get("posted", ""))[:40])


def _set_aside(folder: Path, name: str, why: str) -> None:
    """Move an entry that is not a command file out of the loop's way (into ``rejected/``); logged once."""
    target = folder / REJECTED / f"{name}.{time.time_ns()}"
    try:
        target.parent.mkdir(exist_ok=True)
        os.rename(folder / name, target)
        log.error("%s %s: moved to %s", folder / name, why, target)
    except OSError as exc:
        _once(f"aside:{name}", logging.ERROR, "%s %s, and could not be moved aside (%s): remove it",
              folder / name, why, exc.strerror or exc)
