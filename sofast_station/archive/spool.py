"""The spool: a facet's cropped frames and metadata, kept on disk until the archiver dumps them.

The station spools a facet *before* it releases the robot, so a crash of the station process later (in
the analysis of the next facet, in the archiver) cannot lose the data of a requested dump. Spooling
must be fast: one uncompressed ``.npz`` (the arrays, plus the metadata as UTF-8 JSON in the reserved
array ``__metadata__``), written under a temporary name and renamed. No fsync: the page cache survives
a process crash, and a power cut loses at most the spool of the facet being measured (whose journal row
then says the dump failed: no spool).
"""

from __future__ import annotations

import json
import logging
import os
import zipfile
from pathlib import Path

import numpy as np

from ..errors import ArchiveError
from ..files import is_temp_file, safe_name, temp_path_for, to_json

log = logging.getLogger(__name__)

_META = "__metadata__"
SUFFIX = ".npz"


def spool_path(spool_dir: str | Path, cycle_id: str) -> Path:
    """Where the spool of *cycle_id* lives."""
    return Path(spool_dir) / f"{safe_name(cycle_id, 120)}{SUFFIX}"


def spool_put(spool_dir: str | Path, cycle_id: str, arrays: dict, metadata: dict) -> Path:
    """Spool a cycle's arrays and metadata (fast, atomic against process crashes).

    Parameters
    ----------
    spool_dir : str or Path
        The spool folder (created when missing).
    cycle_id : str
    arrays : dict of str -> numpy array
        Stored uncompressed, exactly (dtype and shape kept).
    metadata : dict
        JSON-ready data (NaN and infinities become null); ``cycle_id`` is added.

    Returns
    -------
    Path
        The spool file.
    """
    if _META in arrays:
        raise ArchiveError(f"spool array name {_META!r} is reserved")
    folder = Path(spool_dir)
    folder.mkdir(parents=True, exist_ok=True)
    final = spool_path(folder, cycle_id)
    meta = dict(metadata)
    meta["cycle_id"] = cycle_id
    blob = np.frombuffer(to_json(meta).encode("utf-8"), dtype=np.uint8)
    tmp = temp_path_for(final)
    try:
        with open(tmp, "wb") as fh:
            np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()}, **{_META: blob})
        os.replace(tmp, final)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    log.debug("spooled cycle %s to %s", cycle_id, final)
    return final


def spool_get(path: str | Path) -> tuple[dict, dict]:
    """Read a spool file back: (arrays, metadata).

    Raises
    ------
    ArchiveError
        When the file is missing, truncated or not a spool.
    """
    path = Path(path)
    if path.exists() and not zipfile.is_zipfile(path):
        raise ArchiveError(f"spool {path} is not an .npz file (truncated, or not written by the station)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise ArchiveError(f"spool {path} does not exist") from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as exc:
        raise ArchiveError(f"spool {path} is unreadable ({type(exc).__name__}: {exc})") from exc
    blob = arrays.pop(_META, None)
    if blob is None:
        raise ArchiveError(f"spool {path} has no metadata; it is not a spool of this station")
    try:
        meta = json.loads(blob.tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ArchiveError(f"spool {path} has corrupt metadata ({exc})") from exc
    return arrays, meta


def spool_list(spool_dir: str | Path) -> list[Path]:
    """The spool files in *spool_dir* (temporary files excluded), oldest first."""
    folder = Path(spool_dir)
    if not folder.is_dir():
        return []
    files = [p for p in folder.glob(f"*{SUFFIX}") if p.is_file() and not is_temp_file(p)]
    return sorted(files, key=lambda p: (p.stat().st_mtime, p.name))
