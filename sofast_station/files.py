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
