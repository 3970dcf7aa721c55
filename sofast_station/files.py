"""The station's own files: read with errors that name the file and say what to do; written whole or not at
all (a temporary file beside the final one, renamed into place), as JSON that never holds NaN or Infinity;
and the temporary files a crashed writer leaves, recognised and removed."""

from __future__ import annotations

import json
import logging
import math
import os
import re
import secrets
import time
import tomllib
from pathlib import Path

from .errors import ConfigError

log = logging.getLogger(__name__)

#: Temporary files are ``.<final name>.<pid>.<random>.tmp`` in the final file's folder.
_TEMP_RE = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{8}\.tmp$")


def read_toml(path: Path, what: str, hint: str = "") -> dict:
    """Parse a TOML file; a missing or malformed file raises :class:`ConfigError` naming *what* and *path*."""
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist{'; ' + hint if hint else ''}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} {path} is not valid TOML: {exc}") from None


#: Where a station writes when its file names no ``data_dir``.
DEFAULT_DATA_DIR = "~/sofast-station-data"


def data_dir_of(station_table: dict, base: Path) -> Path:
    """The ``data_dir`` of a station file's ``[station]`` table: the environment variable ``SOFAST_DATA_DIR``
    when set, else the table's (``~`` expanded; relative to the file's folder *base*), else
    :data:`DEFAULT_DATA_DIR`."""
    return resolve_data_dir(os.environ.get("SOFAST_DATA_DIR") or station_table.get("data_dir", DEFAULT_DATA_DIR),
                            base)


def resolve_data_dir(value: str | Path, base: Path) -> Path:
    """A data folder as written (*value*: ``~`` expanded; relative to *base*) as a path. Every station's data
    folder is resolved here, once (the test suite watches this one place: tests/conftest.py)."""
    data_dir = Path(value).expanduser()
    return data_dir if data_dir.is_absolute() else Path(base) / data_dir


def station_data_dir(path: str | Path) -> Path | None:
    """The ``data_dir`` of the station file *path* from its ``[station]`` table alone (no validation, nothing
    loaded but the TOML), for a command that only keeps a cache there; None when the file cannot be read
    (the command then goes without)."""
    path = Path(path).expanduser()
    if os.environ.get("SOFAST_DATA_DIR"):
        return resolve_data_dir(os.environ["SOFAST_DATA_DIR"], Path.cwd())
    try:
        raw = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return None
    table = raw.get("station", {})
    if not isinstance(table, dict) or not isinstance(table.get("data_dir", ""), str):
        return None
    return data_dir_of(table, path.resolve().parent)


def safe_name(text: str, limit: int = 80) -> str:
    """*text* reduced to characters safe in file names on every platform (letters, digits, ``-_.``)."""
    out = re.sub(r"[^A-Za-z0-9._-]+", "_", str(text)).strip("._") or "x"
    return out[:limit]


# -- JSON ---------------------------------------------------------------------------------------------------
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


def write_json_atomic(path: Path, obj, replace: bool = True) -> Path:
    """Write *obj* as JSON (:func:`to_json`, one-space indent, a final newline) whole or not at all, flushed to
    the disk before it takes its name (:func:`write_file_atomic`; its folder made when missing). *replace*
    False: never overwrite (FileExistsError when the name is taken)."""
    text = to_json(obj, indent=1) + "\n"
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    return write_file_atomic(path, lambda fh: fh.write(text), mode="w", fsync=True, replace=replace)


# -- writing whole or not at all ----------------------------------------------------------------------------
def temp_path_for(final: Path) -> Path:
    """A fresh hidden temporary name in *final*'s folder, recognisable by :func:`is_temp_file`."""
    return final.parent / f".{final.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"


def write_file_atomic(path: Path, write, mode: str = "wb", fsync: bool = False, replace: bool = True) -> Path:
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
    replace : bool
        Replace a file of that name (an atomic rename); False: never overwrite (a hard link, which fails with
        FileExistsError when the name is taken; the temporary file is removed either way).

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
        if replace:
            os.replace(tmp, path)
        else:
            os.link(tmp, path)
            tmp.unlink()
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
