"""Reading the station's own files, with errors that name the file and say what to do."""

from __future__ import annotations

import tomllib
from pathlib import Path

from .errors import ConfigError


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
    import os

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
    import os

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
