"""Writing a dump: every object labelled from the schema, frames compressed on all cores, written under a
temporary name, fsynced and renamed."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ArchiveError, DumpError
from ...files import fsync_dir, fsync_file, temp_path_for, to_json
from ...times import now_iso
from .._common import fault_point
from .content import DumpContent
from .schema import (
    _JSON_ENCODING,
    _PLAIN_ENCODING,
    COMPRESSION_LEVEL,
    FRINGE_SCHEMA_VERSION,
    KEY_FIGURES,
    SCHEMA,
    SCHEMA_VERSION,
    _describe,
)

log = logging.getLogger("sofast_station.archive.dumps")


@dataclass(frozen=True)
class DumpStats:
    """What writing a dump cost.

    Attributes
    ----------
    path : Path
    size_bytes : int
        File size, bytes.
    raw_bytes : int
        Uncompressed size of the cropped frames, bytes.
    seconds : float
        Wall time of the write including fsync and rename, seconds.
    """

    path: Path
    size_bytes: int
    raw_bytes: int
    seconds: float


def _set_description(obj, path: str) -> None:
    desc, units = _describe(path)
    obj.attrs["description"] = desc
    obj.attrs["units"] = units


def _write_value(group, name: str, value, path: str) -> None:
    # lazy: h5py costs ~30 ms CPU (80 ms wall); every user of the journal loads this module
    import h5py

    if isinstance(value, dict):
        sub = group.create_group(name, track_order=True)
        _set_description(sub, path)
        for k, v in value.items():
            if "/" in str(k) or not str(k):
                raise DumpError(f"cannot store the key {k!r} of {path} in a dump")
            _write_value(sub, str(k), v, f"{path}/{k}")
        return
    encoding = _PLAIN_ENCODING
    if isinstance(value, str):
        ds = group.create_dataset(name, data=value, dtype=h5py.string_dtype("utf-8"))
    elif isinstance(value, bool):
        ds = group.create_dataset(name, data=np.bool_(value))
    elif isinstance(value, int):
        ds = group.create_dataset(name, data=np.int64(value))
    elif isinstance(value, float):
        ds = group.create_dataset(name, data=np.float64(value))
    else:
        arr = None
        if isinstance(value, (list, tuple)):
            try:
                arr = np.asarray(value)
            except ValueError:            # ragged
                arr = None
        if arr is not None and arr.dtype.kind in "biuf" and (arr.size or arr.ndim == 1):
            ds = group.create_dataset(name, data=arr.astype(np.int64 if arr.dtype.kind in "iu" else arr.dtype))
        elif arr is not None and arr.dtype.kind == "U" and arr.ndim == 1 and arr.size:
            ds = group.create_dataset(name, data=[str(v) for v in value], dtype=h5py.string_dtype("utf-8"))
        else:                              # None, ragged or mixed lists: JSON text
            ds = group.create_dataset(name, data=json.dumps(value), dtype=h5py.string_dtype("utf-8"))
            encoding = _JSON_ENCODING
    _set_description(ds, path)
    ds.attrs["encoding"] = encoding


#: The camera counts a dump holds: 8-bit, or 16-bit (a camera of more than 8 bits); little-endian on disk.
FRAME_DTYPES = (np.dtype(np.uint8), np.dtype("<u2"))


def _shuffled(frame: np.ndarray) -> np.ndarray:
    """The frame's bytes as HDF5's shuffle filter arranges them: every element's first byte, then every
    second byte (the identity on 1-byte data)."""
    if frame.dtype.itemsize == 1:
        return frame
    return np.ascontiguousarray(frame.reshape(-1).view(np.uint8).reshape(-1, frame.dtype.itemsize).T)


def _frame_job(frame: np.ndarray, level: int) -> tuple[bytes, str]:
    # zlib and hashlib release the GIL on large buffers: frames compress in parallel, and the station's
    # own threads keep running meanwhile
    return zlib.compress(_shuffled(frame), level), hashlib.sha256(frame).hexdigest()


def _write_frames(ds, frames: np.ndarray, level: int) -> list[str]:
    """Compress each frame (the shuffle filter's byte order, then a zlib stream: HDF5's deflate filter) on
    all cores and write it as the frame's chunk; return the frames' SHA-256 digests."""
    n = frames.shape[0]
    digests = []
    workers = max(1, min(n, os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dump-zlib") as pool:
        for i, (blob, digest) in enumerate(pool.map(_frame_job, frames, [level] * n)):
            ds.id.write_direct_chunk((i, 0, 0), blob, 0)
            digests.append(digest)
            if i + 1 == n // 2:
                fault_point("dump-mid-write")
    return digests


def _flat_figures(record: dict) -> dict:
    out = {}
    for key in KEY_FIGURES:
        v = record
        for part in key.split("."):
            v = v.get(part) if isinstance(v, dict) else None
        if isinstance(v, (str, int, float, bool)):
            out[key] = v
    return out


def write_dump(path: str | Path, content: DumpContent, compression_level: int = COMPRESSION_LEVEL) -> DumpStats:
    """Write a data dump atomically.

    The file is written as ``.<name>.<pid>.<random>.tmp`` in the target folder, closed, fsynced and
    renamed to *path*; the folder is fsynced. On failure the temporary file is removed.

    Parameters
    ----------
    path : str or Path
        The final ``.h5`` file (replaced when it exists).
    content : DumpContent
    compression_level : int
        gzip level of the frames, 0..9.

    Returns
    -------
    DumpStats

    Raises
    ------
    DumpError
        When the content cannot make a dump (frames of the wrong kind, a crop that does not fit, a value a
        dump cannot hold): writing it again will not help.
    ArchiveError
        When the file cannot be written now (disk full, permissions, a folder in the way); the cause is
        chained.
    """
    # lazy: h5py costs ~30 ms CPU (80 ms wall); every user of the journal loads this module
    import h5py

    t0 = time.perf_counter()
    path = Path(path)
    level = int(compression_level)
    if not 0 <= level <= 9:
        raise DumpError(f"dump {path}: compression level must be 0..9, got {compression_level}")
    frames = content.frames_cropped
    if (frames is None or frames.ndim != 3 or frames.dtype.kind != "u" or frames.dtype.itemsize not in (1, 2)
            or min(frames.shape) < 1):
        raise DumpError(f"dump {path}: frames_cropped must be a non-empty (n, h, w) array of 8- or 16-bit camera "
                        f"counts (uint8, uint16), got {None if frames is None else (frames.shape, frames.dtype)}")
    frames = np.ascontiguousarray(frames, dtype=FRAME_DTYPES[frames.dtype.itemsize - 1])
    n, h, w = frames.shape
    restore_check = (content.crop_box[0] >= 0 and content.crop_box[1] >= 0
                     and content.crop_box[0] + h <= content.full_shape[0]
                     and content.crop_box[1] + w <= content.full_shape[1])
    if not restore_check:
        raise DumpError(f"dump {path}: the crop {h} x {w} at {tuple(content.crop_box)} does not fit the full "
                        f"frame {tuple(content.full_shape)}")
    try:
        patterns = content.patterns
    except Exception as exc:                 # an unusable fringe definition still gets dumped
        log.warning("dump %s: the fringe definition gives no pattern names (%s: %s); its frames are named "
                    "frame 0..%d", path, type(exc).__name__, exc, n - 1)
        patterns = None
    if patterns is not None and len(patterns) != n:
        log.warning("dump %s: the fringe definition names %d patterns for %d frames; the frames are named "
                    "frame 0..%d", path, len(patterns), n, n - 1)
        patterns = None
    if patterns is None:
        patterns = [f"frame {i}" for i in range(n)]
    tmp = temp_path_for(path)
    created = now_iso()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)      # in the try: a folder it cannot make is an ArchiveError
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["schema"] = SCHEMA
            fixed = isinstance(content.design, dict) and content.design.get("method") == "fixed"
            # a fringe capture stays version 2, which every reader since reads; a fixed one needs 3's reader
            f.attrs["schema_version"] = np.int64(SCHEMA_VERSION if fixed else FRINGE_SCHEMA_VERSION)
            f.attrs["description"] = (f"sofast-station data dump of facet {content.serial}, cycle {content.cycle_id}: "
                                      "raw frames and everything needed to redo the analysis; layout: "
                                      "docs/dump-schema.md")
            f.attrs["software_version"] = content.software_version
            f.attrs["created"] = created
            f.attrs["cycle_id"] = content.cycle_id
            f.attrs["serial"] = content.serial
            f.attrs["time"] = content.time
            f.attrs["config_hash"] = content.config_hash
            f.attrs["station"] = content.station_name
            f.attrs["facet"] = str(content.design.get("name", ""))

            cap = f.create_group("capture", track_order=True)
            _set_description(cap, "capture")
            ds = cap.create_dataset("frames", shape=frames.shape, dtype=frames.dtype, chunks=(1, h, w),
                                    compression="gzip", compression_opts=level, shuffle=True)
            _set_description(ds, "capture/frames")
            digests = _write_frames(ds, frames, level)
            _write_value(cap, "frames_sha256", digests, "capture/frames_sha256")
            _write_value(cap, "crop_box", [int(v) for v in content.crop_box], "capture/crop_box")
            _write_value(cap, "full_shape", [int(v) for v in content.full_shape], "capture/full_shape")
            _write_value(cap, "patterns", patterns, "capture/patterns")
            _write_value(cap, "measured_distance_m", float(content.measured_distance_m), "capture/measured_distance_m")

            _write_value(f, "fringes", content.fringes, "fringes")
            cal = f.create_group("calibration", track_order=True)
            _set_description(cal, "calibration")
            _write_value(cal, "radiometric", content.radiometric, "calibration/radiometric")
            _write_value(f, "geometry", content.geometry, "geometry")
            _write_value(f, "design", content.design, "design")
            _write_value(f, "analysis", content.analysis, "analysis")
            _write_value(f, "config", {"station_toml": content.station_toml, "facet_toml": content.facet_toml,
                                       "station_path": content.station_path, "facet_path": content.facet_path,
                                       "config_hash": content.config_hash, "station_name": content.station_name},
                         "config")
            res = f.create_group("result", track_order=True)
            _set_description(res, "result")
            _write_value(res, "record_json", to_json(content.record), "result/record_json")
            if content.sensitivities is not None:
                _write_value(res, "sensitivities_json", to_json(content.sensitivities), "result/sensitivities_json")
            if content.uncertainty_inputs is not None:
                _write_value(res, "uncertainty_inputs_json", to_json(content.uncertainty_inputs),
                             "result/uncertainty_inputs_json")
            for k, v in _flat_figures(content.record).items():
                res.attrs[k] = v
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError as exc2:
            log.warning("could not remove the temporary dump %s: %s", tmp, exc2)
        if isinstance(exc, (ValueError, TypeError)):       # what the content holds, not the disk
            raise DumpError(f"could not write the dump {path}: {type(exc).__name__}: {exc}") from exc
        if isinstance(exc, (OSError, RuntimeError)) and not isinstance(exc, ArchiveError):
            raise ArchiveError(f"could not write the dump {path}: {type(exc).__name__}: {exc}") from exc
        raise
    fsync_dir(path.parent)
    stats = DumpStats(path, path.stat().st_size, int(frames.nbytes), time.perf_counter() - t0)
    log.info("wrote dump %s: %.1f MB (frames %.1f MB raw) in %.2f s", path, stats.size_bytes / 1e6,
             stats.raw_bytes / 1e6, stats.seconds)
    return stats
