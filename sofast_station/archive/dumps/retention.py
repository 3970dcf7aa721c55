"""Where dumps go and how long they stay: names, listing, pruning by age and total size, free disk."""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

from ...files import is_temp_file, safe_name
from ...times import parse_time

log = logging.getLogger("sofast_station.archive.dumps")


def list_dumps(folder: str | Path) -> list[Path]:
    """Every dump (``*.h5``, temporary files excluded) under *folder*, oldest first (by modification time)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    out = []
    for p in folder.rglob("*.h5"):
        if is_temp_file(p) or p.name.startswith("."):
            continue
        try:
            out.append((p.stat().st_mtime, p))
        except FileNotFoundError:
            continue
    return [p for _, p in sorted(out, key=lambda t: (t[0], str(t[1])))]


def prune_dumps(folder: str | Path, keep_days: float | None, max_total_gb: float | None) -> list[Path]:
    """Apply the retention rule: remove dumps older than *keep_days*, then the oldest until the total is at
    most *max_total_gb*.

    Parameters
    ----------
    folder : str or Path
        The dump folder (searched recursively; emptied day folders are removed).
    keep_days : float or None
        Largest age of a dump, days (by file modification time); None: no age limit.
    max_total_gb : float or None
        Largest total size of the dumps, GB (10^9 bytes); None: no size limit.

    Returns
    -------
    list of Path
        The dumps removed, oldest first.
    """
    folder = Path(folder)
    dumps = list_dumps(folder)
    sizes = {}
    for p in dumps:
        try:
            sizes[p] = p.stat().st_size
        except FileNotFoundError:
            sizes[p] = 0
    total = sum(sizes.values())
    cutoff = None if keep_days is None else time.time() - float(keep_days) * 86400.0
    limit = None if max_total_gb is None else float(max_total_gb) * 1e9
    removed = []
    for p in dumps:                          # oldest first
        try:
            mtime = p.stat().st_mtime
        except FileNotFoundError:
            continue
        too_old = cutoff is not None and mtime < cutoff
        too_big = limit is not None and total > limit
        if not (too_old or too_big):
            break                            # the rest are younger, and the total fits
        try:
            p.unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("retention: could not remove %s: %s", p, exc)
            continue
        total -= sizes[p]
        removed.append(p)
    for d in sorted({p.parent for p in removed}, key=lambda d: len(d.parts), reverse=True):
        if d != folder:
            try:
                d.rmdir()                    # only when empty
            except OSError:
                pass
    if removed:
        log.info("retention: removed %d dump(s) from %s (%s days, %s GB); %.2f GB remain", len(removed), folder,
                 keep_days, max_total_gb, total / 1e9)
    return removed


def disk_ok(folder: str | Path, min_free_gb: float) -> tuple[bool, float]:
    """Whether the disk holding *folder* has at least *min_free_gb* free.

    Parameters
    ----------
    folder : str or Path
        Any path on the disk (the nearest existing parent is measured).
    min_free_gb : float
        Required free space, GB (10^9 bytes).

    Returns
    -------
    (bool, float)
        Whether the free space suffices, and the free space in GB.
    """
    p = Path(folder).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    free_gb = shutil.disk_usage(p).free / 1e9
    return free_gb >= float(min_free_gb), free_gb


def dump_name(serial: str, time_iso: str, cycle_id: str) -> str:
    """File name of a cycle's dump: ``<serial>_<local time YYYYMMDDTHHMMSS>_<cycle id>.h5`` (file-name safe)."""
    t = parse_time(time_iso)
    return f"{safe_name(serial, 60)}_{t.strftime('%Y%m%dT%H%M%S')}_{safe_name(cycle_id, 80)}.h5"


def dump_path_for(folder: str | Path, serial: str, time_iso: str, cycle_id: str) -> Path:
    """Where the archiver puts a cycle's dump: ``<folder>/<local date>/<dump_name>``."""
    return Path(folder) / parse_time(time_iso).date().isoformat() / dump_name(serial, time_iso, cycle_id)
