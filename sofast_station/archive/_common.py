"""Small helpers shared by the journal, the workbooks and the dumps.

Atomic files, JSON that never holds NaN or Infinity, ISO 8601 times, and the named fault-injection
points the crash tests use.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import os
import re
import secrets
import signal
import time
from pathlib import Path

from ..files import safe_name  # noqa: F401  (the archive's names use it; its home is files.py)

log = logging.getLogger(__name__)

#: Environment variable naming the fault-injection point at which the process SIGKILLs itself.
FAULT_ENV = "SOFAST_FAULT"

#: The named fault-injection points (see :func:`fault_point`).
FAULT_POINTS = ("journal-append", "workbook-temp-written", "workbook-renamed", "dump-mid-write")

#: Temporary files are ``.<final name>.<pid>.<random>.tmp`` in the final file's folder.
_TEMP_RE = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{8}\.tmp$")


def fault_point(name: str) -> None:
    """Kill this process with SIGKILL when ``SOFAST_FAULT`` names this point (crash tests only).

    Parameters
    ----------
    name : str
        One of :data:`FAULT_POINTS`.
    """
    if os.environ.get(FAULT_ENV) == name:
        log.critical("fault injection: %s=%s, killing process %d", FAULT_ENV, name, os.getpid())
        sig = getattr(signal, "SIGKILL", None)
        if sig is None:      # Windows: no SIGKILL; an immediate exit is the nearest equivalent
            os._exit(137)
        os.kill(os.getpid(), sig)


def json_ready(obj):
    """A copy of *obj* that :func:`json.dumps` accepts with ``allow_nan=False``.

    NaN and infinities become ``None`` (an infinite focal length is JSON null:
    docs/conventions.md#focal-power), numpy scalars and arrays become Python numbers and lists, tuples become lists,
    paths become strings.
    """
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, int):
        return obj
    if isinstance(obj, dict):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):          # numpy scalar or array
        return json_ready(obj.tolist())
    raise TypeError(f"cannot store a {type(obj).__name__} in a result record: {obj!r}")


def to_json(obj, indent: int | None = None) -> str:
    """JSON text of *obj* after :func:`json_ready` (no NaN, no Infinity)."""
    return json.dumps(json_ready(obj), allow_nan=False, indent=indent, ensure_ascii=False)


def parse_time(value) -> _dt.datetime:
    """A time-zone-aware datetime from an ISO 8601 string or a datetime.

    A value without a UTC offset is taken as the machine's local time.

    Raises
    ------
    ValueError
        When *value* is not an ISO 8601 date or date and time.
    """
    if isinstance(value, _dt.datetime):
        dt = value
    elif isinstance(value, _dt.date):
        dt = _dt.datetime(value.year, value.month, value.day)
    else:
        dt = _dt.datetime.fromisoformat(str(value))
    if dt.tzinfo is None:
        dt = dt.astimezone()
    return dt


def utc_key(value) -> str:
    """A string that sorts like the instant *value* denotes: UTC, ``YYYY-MM-DDTHH:MM:SS.ffffffZ``."""
    return parse_time(value).astimezone(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def parse_bound(text, what: str = "--from/--to") -> str | None:
    """A period bound from the command line: an ISO date (local midnight at its start), an ISO date and
    time, or ``today`` / ``yesterday`` / ``tomorrow`` (local midnight); None stays None.

    Raises
    ------
    ConfigError
        Naming *what* and the accepted forms, when *text* is none of them.
    """
    from ..errors import ConfigError

    if text is None:
        return None
    t = str(text).strip()
    words = {"today": 0, "yesterday": -1, "tomorrow": 1}
    if t.lower() in words:
        return (_dt.date.today() + _dt.timedelta(days=words[t.lower()])).isoformat()
    try:
        if len(t) == 10:
            return _dt.date.fromisoformat(t).isoformat()
        _dt.datetime.fromisoformat(t)
        return t
    except ValueError:
        raise ConfigError(f"{what} {text!r} is not a date: give an ISO date (2026-11-25), a date and time "
                          f"(2026-11-25T06:00), 'today' or 'yesterday'") from None


def check_period(since, until, what: str = "--from/--to") -> None:
    """Refuse an empty or reversed period ``[since, until)`` with a message that says so."""
    from ..errors import ConfigError

    if since is not None and until is not None and utc_key(since) >= utc_key(until):
        raise ConfigError(f"{what}: the period from {since} to {until} is empty or reversed (the end is "
                          f"exclusive): the start must come before the end")


def now_iso() -> str:
    """Local date and time with its UTC offset, ISO 8601, to the millisecond."""
    return _dt.datetime.now().astimezone().isoformat(timespec="milliseconds")


def release_memory() -> None:
    """Give the memory a large piece of work freed back to the system (a full garbage collection, then
    glibc's ``malloc_trim``; nothing where that does not exist).

    A workbook save (a part streamed from the journal), a dump (a facet's frames) allocate and free a few
    MB; freed, that memory would otherwise stay with the long-lived archiver process at its high-water
    mark.
    """
    import gc

    gc.collect()
    trim_heap()


def trim_heap() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``; nothing elsewhere).

    A long-lived process that frees hundreds of MB per cycle (the analysis worker's per-pixel arrays)
    otherwise keeps them at its high-water mark and, with several threads' arenas, lets that mark creep
    up (the full-resolution soak: about 30 MB per 100 facets). An analysis loop at full resolution rose
    from 558 to 585 MB over 30 facets without it and stayed between 454 and 485 MB over 60 with it.
    Costs about a millisecond.
    """
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


#: Allocations of at least this many bytes get a mapping of their own (glibc), see :func:`map_large_blocks`.
LARGE_BLOCK_BYTES = 4 << 20


def map_large_blocks(threshold_bytes: int = LARGE_BLOCK_BYTES) -> bool:
    """Make glibc serve every allocation of at least *threshold_bytes* from a mapping of its own, handed
    back to the system when freed (``mallopt(M_MMAP_THRESHOLD)``; False where that does not exist).

    By default glibc raises that threshold to the size of the largest block freed so far (up to 32 MB):
    after the first facet's frames (12.5 MB at full resolution) a process serves such blocks from its
    heaps, where they fragment and stay. The archiver reads a spool and writes a dump per faulted or
    scheduled facet: with the default it rose by 9 MB per 100 full-resolution cycles in steps (a
    320-cycle soak); in a loop of 240 dumps, run with and without, its memory was 24 MB lower and flat
    (72.8 -> 75.3 MB against 96.8 -> 103.1 MB) with this threshold. Call once, early in the process.
    Not in the station or the analysis worker: they allocate and free dozens of such blocks per facet (the
    twin's renders, the per-pixel arrays), and a fresh mapping is zeroed page by page each time (the
    simulated line's cycle took 48 % longer with it in the station); the worker trims its heap instead.
    """
    import ctypes

    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(-3, int(threshold_bytes)))   # -3: M_MMAP_THRESHOLD
    except (OSError, AttributeError):
        return False


def temp_path_for(final: Path) -> Path:
    """A fresh hidden temporary name in *final*'s folder, recognisable by :func:`is_temp_file`."""
    return final.parent / f".{final.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"


def write_file_atomic(path: Path, write, mode: str = "wb", fsync: bool = False) -> Path:
    """Write *path* whole or not at all: ``write(fh)`` fills a temporary file of :func:`temp_path_for` in the
    same folder, which is then renamed into place.

    On any failure (a full disk, a folder gone) the temporary file is removed before the error is raised,
    so nothing is left behind; a process killed meanwhile leaves a name :func:`remove_stale_temp_files`
    recognises. Without *fsync* the data may still be in the system's cache when it returns: for files that
    say what is happening now (live status, pictures, commands); results are written with *fsync*.

    Parameters
    ----------
    path : Path
        The final file.
    write : callable
        Called with the open temporary file.
    mode : str
        ``"wb"`` or ``"w"`` (UTF-8 text).
    fsync : bool
        Flush the data to the disk before the rename.

    Returns
    -------
    Path
        *path*.
    """
    path = Path(path)
    tmp = temp_path_for(path)
    try:
        with open(tmp, mode, **({"encoding": "utf-8"} if "b" not in mode else {})) as fh:
            write(fh)
            if fsync:
                fh.flush()
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise
    return path


def is_temp_file(path: Path) -> bool:
    """Whether *path* is named like a temporary file of :func:`temp_path_for`."""
    return _TEMP_RE.match(Path(path).name) is not None


def fsync_file(path: Path) -> None:
    """Flush a closed file's data to the disk."""
    fd = os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(folder: Path) -> None:
    """Make a rename in *folder* durable (POSIX; Windows has no directory handles to flush)."""
    if os.name != "posix":
        return
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    except OSError as exc:       # some network file systems refuse; the rename itself has happened
        log.debug("could not fsync folder %s: %s", folder, exc)
    finally:
        os.close(fd)


def pid_alive(pid: int) -> bool:
    """Whether process *pid* exists (on POSIX; elsewhere assumed alive: files are then judged by age)."""
    if os.name != "posix":
        return True              # no safe liveness probe (os.kill terminates on Windows): go by age
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temp_files(folder: Path, max_age_s: float = 3600.0, recursive: bool = False) -> list[Path]:
    """Remove temporary files left by a crashed writer.

    A temporary file is stale when the process that made it no longer runs, or when it is older than
    *max_age_s* seconds. Temporary files of this process are never touched.

    Parameters
    ----------
    folder : Path
    max_age_s : float
        Age, seconds, beyond which any temporary file is stale.
    recursive : bool
        Also look into sub-folders.

    Returns
    -------
    list of Path
        The files removed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    now = time.time()
    for path in (folder.rglob(".*.tmp") if recursive else folder.glob(".*.tmp")):
        m = _TEMP_RE.match(path.name)
        if not m:
            continue
        pid = int(m.group(1))
        if pid == os.getpid():
            continue
        try:
            age = now - path.stat().st_mtime
            if not pid_alive(pid) or age > max_age_s:
                path.unlink()
                removed.append(path)
                log.info("removed the temporary file %s left by a stopped writer (process %d)", path, pid)
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("could not remove the stale temporary file %s: %s", path, exc)
    return removed
