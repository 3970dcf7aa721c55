"""The log files under ``data_dir/logs``: one per process (the station, the archiver, the monitor), rotated.
"""

from __future__ import annotations

import logging
import logging.handlers
from pathlib import Path

from ..errors import StationError


def setup_logging(data_dir: Path, verbose: bool = False, name: str = "station.log") -> Path:
    """Console (stderr) plus a rotating log file under data_dir/logs."""
    log_dir = data_dir / "logs"
    path = log_dir / name
    try:
        log_dir.mkdir(parents=True, exist_ok=True)
        handler = logging.handlers.RotatingFileHandler(path, maxBytes=10_000_000, backupCount=10)
    except OSError as exc:
        raise StationError(f"cannot write the log {path} ({exc.strerror or exc}): make {log_dir} writable "
                           f"(permissions, a read-only mount, a full disk) or give the station another data_dir "
                           f"(station.toml [station] data_dir, or SOFAST_DATA_DIR), then start again") from None
    handler.setFormatter(logging.Formatter("%(asctime)s %(process)d %(name)s %(levelname)s %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    # On a full disk the file handler fails on every line: without this each failure prints a logging
    # traceback on the console (seen on a 30 MB tmpfs data folder); the console handler still says it all.
    logging.raiseExceptions = False
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    return path
