"""Reading and validating a dump: what the file is, its schema and version, every required object, the
frames' digests; a damaged or foreign file is a :class:`~sofast_station.errors.DumpError` that says what."""

from __future__ import annotations

import hashlib
import json
import logging
import zlib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ... import __version__
from ...errors import DumpError
from .content import DumpContent
from .schema import _JSON_ENCODING, _PLAIN_ENCODING, SCHEMA, SCHEMA_V1, SCHEMA_V2, SCHEMA_VERSION

log = logging.getLogger("sofast_station.archive.dumps")

_MAGIC = ((b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
          (b"PK\x03\x04", "a ZIP archive (an .xlsx, .npz or .zip file?)"), (b"II*\x00", "a TIFF image"),
          (b"MM\x00*", "a TIFF image"), (b"SQLite format 3", "an SQLite database"), (b"%PDF", "a PDF document"),
          (b"{", "JSON or other text"), (b"\x93NUMPY", "a NumPy .npy file"))


def _read_value(obj):
    # lazy: h5py costs ~30 ms CPU (80 ms wall); every user of the journal loads this module
    import h5py

    if isinstance(obj, h5py.Group):
        return {k: _read_value(obj[k]) for k in obj.keys()}
    encoding = obj.attrs.get("encoding", _PLAIN_ENCODING)
    if isinstance(encoding, bytes):
        encoding = encoding.decode()
    if obj.dtype.kind in "OS" or h5py.check_string_dtype(obj.dtype) is not None:
        value = obj.asstr()[()]
        if isinstance(value, np.ndarray):
            return [str(v) for v in value.tolist()]
        return json.loads(value) if encoding == _JSON_ENCODING else str(value)
    value = obj[()]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value.item() if hasattr(value, "item") else value


#: HDF5's filter numbers: what the writer compresses the frames with (shuffle, then deflate).
_H5Z_DEFLATE, _H5Z_SHUFFLE = 1, 2


def _read_frames(ds, path: Path) -> np.ndarray:
    """The frames of *ds*, the same bits as ``ds[()]`` in about half the time: the writer stores one frame
    per chunk, shuffled and deflated, and HDF5 inflates chunk after chunk on one thread (0.07 s of a
    full-resolution dump's 0.11 s of reading); here each chunk's bytes are read as stored and inflated on
    two threads (zlib releases the GIL). A dataset laid out otherwise (other filters or chunks, a chunk
    HDF5 marks as unfiltered) is read by HDF5."""
    n, h, w = ds.shape
    plist = ds.id.get_create_plist()
    filters = [plist.get_filter(i)[0] for i in range(plist.get_nfilters())]
    if ds.chunks != (1, h, w) or filters not in ([_H5Z_SHUFFLE, _H5Z_DEFLATE], [_H5Z_DEFLATE]):
        return ds[()]
    raw = [ds.id.read_direct_chunk((i, 0, 0)) for i in range(n)]
    if any(mask != 0 for mask, _ in raw):
        return ds[()]
    out = np.empty((n, h, w), dtype=ds.dtype)
    size = ds.dtype.itemsize

    def inflate(i: int) -> None:
        try:
            data = np.frombuffer(zlib.decompress(raw[i][1]), dtype=np.uint8)
        except zlib.error as exc:
            raise DumpError(f"dump {path} is corrupt: frame {i}'s compressed data cannot be inflated ({exc})") \
                from exc
        if data.size != h * w * size:
            raise DumpError(f"dump {path} is corrupt: frame {i} inflates to {data.size} bytes, not {h * w * size}")
        if size > 1 and filters[0] == _H5Z_SHUFFLE:     # byte k of every value stored together
            data = data.reshape(size, h * w).T
        out[i] = np.ascontiguousarray(data).view(ds.dtype).reshape(h, w)

    with ThreadPoolExecutor(2) as pool:
        list(pool.map(inflate, range(n)))
    return out


def _what_is(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return "unreadable"
    for magic, name in _MAGIC:
        if head.startswith(magic):
            return name
    return f"unknown content starting with {head[:8]!r}"


def _attr_str(attrs, key: str, where: str) -> str:
    if key not in attrs:
        raise DumpError(f"dump {where}: the root attribute {key!r} is missing; the file is damaged or not "
                        "written by sofast-station")
    v = attrs[key]
    return v.decode() if isinstance(v, bytes) else str(v)


def read_dump(path: str | Path, load_frames: bool = True, require_result: bool = True) -> DumpContent:
    """Open a data dump, check its schema, and return its content.

    The reader dispatches on the file's ``schema_version`` (:data:`_READERS`): every layout version up to
    :data:`SCHEMA_VERSION` keeps its own reader, so dumps of earlier versions stay readable.

    Parameters
    ----------
    path : str or Path
    load_frames : bool
        Read (and checksum-verify) the frames; False reads the metadata only (``frames_cropped`` None).
    require_result : bool
        Refuse a dump without its ``result`` group (the archived record). Re-analysis passes False: the
        result is an output of the analysis, not an input, so a dump that lost it can still be redone;
        its ``record`` is then ``{}``.

    Returns
    -------
    DumpContent

    Raises
    ------
    DumpError
        Naming the file and the problem: missing, empty, not HDF5 (e.g. a PNG renamed ``.h5``), truncated
        or corrupt, an HDF5 file that is not a dump, a dump of a newer schema version (upgrade), or a
        dump that lacks a dataset.
    """
    # lazy: h5py costs ~30 ms CPU (80 ms wall); every user of the journal loads this module
    import h5py

    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise DumpError(f"dump {path} does not exist") from None
    except OSError as exc:
        raise DumpError(f"dump {path} cannot be read: {exc}") from exc
    if path.is_dir():
        raise DumpError(f"dump {path} is a folder, not a file")
    if size == 0:
        raise DumpError(f"dump {path} is empty (0 bytes): its write was interrupted or it was truncated; "
                        "it holds no data")
    try:
        is_hdf5 = h5py.is_hdf5(str(path))
    except OSError as exc:
        raise DumpError(f"dump {path} cannot be read: {exc}") from exc
    if not is_hdf5:
        raise DumpError(f"dump {path} is not an HDF5 file (it looks like {_what_is(path)}); it is not a "
                        "sofast-station dump")
    try:
        f = h5py.File(path, "r", locking=False)      # readable on shares without file locking
    except OSError as exc:
        msg = str(exc)
        what = "is truncated (shorter than its header says: an interrupted copy?)" if "truncated" in msg else \
            "is corrupt"
        raise DumpError(f"dump {path} {what}; HDF5 says: {msg}") from exc
    try:
        with f:
            return _read_open(f, path, load_frames, require_result)
    except DumpError:
        raise
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
        raise DumpError(f"dump {path} is corrupt or truncated: reading it failed with {type(exc).__name__}: "
                        f"{exc}") from exc


def _read_open(f, path: Path, load_frames: bool, require_result: bool = True) -> DumpContent:
    schema = f.attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode()
    if schema is None:
        top = ", ".join(sorted(f.keys())[:8]) or "nothing"
        raise DumpError(f"{path} is an HDF5 file but not a sofast-station dump (no 'schema' attribute at its "
                        f"root; it holds {top})")
    if schema != SCHEMA:
        raise DumpError(f"{path} is an HDF5 file of schema {schema!r}, not a sofast-station dump ({SCHEMA!r})")
    try:
        version = int(f.attrs.get("schema_version"))
    except (TypeError, ValueError):
        raise DumpError(f"dump {path} has no valid 'schema_version' attribute ({f.attrs.get('schema_version')!r})")
    if version > SCHEMA_VERSION:
        sw = f.attrs.get("software_version", "?")
        sw = sw.decode() if isinstance(sw, bytes) else sw
        raise DumpError(f"dump {path} was written by a newer sofast-station ({sw}, dump schema version {version}); "
                        f"this software ({__version__}) reads schema versions up to {SCHEMA_VERSION}: upgrade "
                        "sofast-station to read it")
    if version < 1:
        raise DumpError(f"dump {path} has an invalid schema_version {version}")
    reader = _READERS.get(version)
    if reader is None:                       # a version this software wrote but no longer reads: a bug
        raise DumpError(f"dump {path} has schema version {version}, for which this software ({__version__}) "
                        f"has no reader (it knows {sorted(_READERS)}); report this as a bug")
    return reader(f, path, version, load_frames, require_result)


def _read_v1(f, path: Path, version: int, load_frames: bool, require_result: bool,
             table=SCHEMA_V1) -> DumpContent:
    """Reader of schema version 1 (docs/dump-schema.md, :data:`SCHEMA_V1`)."""
    # lazy: h5py costs ~30 ms CPU (80 ms wall); every user of the journal loads this module
    import h5py

    where = str(path)
    attrs = {k: _attr_str(f.attrs, k, where) for k in ("software_version", "cycle_id", "serial", "time",
                                                         "config_hash")}
    created = _attr_str(f.attrs, "created", where)
    optional = () if require_result else ("result", "result/record_json")
    missing = [p for p, kind, _, _, _, required in table
               if required and kind != "attribute" and "*" not in p and p not in f and p not in optional]
    if missing:
        raise DumpError(f"dump {path} lacks the dataset(s) {', '.join(missing)} required by schema version "
                        f"{version}; the file is damaged or incomplete")
    frames_ds = f["capture/frames"]
    if not isinstance(frames_ds, h5py.Dataset) or frames_ds.ndim != 3 or frames_ds.dtype not in (np.uint8, np.uint16):
        raise DumpError(f"dump {path}: capture/frames must be an (n, h, w) uint8 or uint16 dataset, got "
                        f"{getattr(frames_ds, 'shape', None)} {getattr(frames_ds, 'dtype', None)}")
    cap = f["capture"]
    frames = None
    if load_frames:
        digests = _read_value(cap["frames_sha256"])
        if len(digests) != frames_ds.shape[0]:
            raise DumpError(f"dump {path}: {len(digests)} frame digests for {frames_ds.shape[0]} frames")
        frames = _read_frames(frames_ds, path)
        with ThreadPoolExecutor(2) as pool:         # hashlib releases the GIL
            found = list(pool.map(lambda frame: hashlib.sha256(frame).hexdigest(), frames))
        for i, (digest, expected) in enumerate(zip(found, digests)):
            if digest != expected:
                raise DumpError(f"dump {path} is corrupt: frame {i} does not match its SHA-256 digest")
    crop_box = tuple(int(v) for v in _read_value(cap["crop_box"]))
    full_shape = tuple(int(v) for v in _read_value(cap["full_shape"]))
    n, h, w = frames_ds.shape
    if len(crop_box) != 2 or len(full_shape) != 2 or crop_box[0] < 0 or crop_box[1] < 0 \
            or crop_box[0] + h > full_shape[0] or crop_box[1] + w > full_shape[1]:
        raise DumpError(f"dump {path}: the crop {h} x {w} at {crop_box} does not fit the full frame {full_shape}")
    cfg = _read_value(f["config"])
    record = {}
    if "result/record_json" in f:
        try:
            record = json.loads(_read_value(f["result/record_json"]))
        except json.JSONDecodeError as exc:
            raise DumpError(f"dump {path}: result/record_json is not valid JSON ({exc})") from exc
    else:
        log.warning("dump %s holds no archived result (no result/record_json); reading it for re-analysis only",
                    path)
    sensitivities = None
    if "result/sensitivities_json" in f:          # optional: re-analysis recomputes them without it
        try:
            sensitivities = json.loads(_read_value(f["result/sensitivities_json"]))
        except (json.JSONDecodeError, TypeError) as exc:
            log.warning("dump %s: result/sensitivities_json is not valid JSON (%s); the re-analysis computes the "
                        "sensitivities afresh", path, exc)
    inputs = None
    if "result/uncertainty_inputs_json" in f:     # optional (0.4.0 on): re-analysis states the line's U with it
        try:
            inputs = json.loads(_read_value(f["result/uncertainty_inputs_json"]))
        except (json.JSONDecodeError, TypeError) as exc:
            log.warning("dump %s: result/uncertainty_inputs_json is not valid JSON (%s); the re-analysis takes the "
                        "input uncertainties from the dumped station.toml and radiometric record", path, exc)
    return DumpContent(
        cycle_id=attrs["cycle_id"], serial=attrs["serial"], time=attrs["time"],
        software_version=attrs["software_version"], config_hash=attrs["config_hash"], frames_cropped=frames,
        crop_box=crop_box, full_shape=full_shape,
        measured_distance_m=float(_read_value(cap["measured_distance_m"])),
        fringes=_read_value(f["fringes"]), radiometric=_read_value(f["calibration/radiometric"]),
        geometry=_read_value(f["geometry"]), design=_read_value(f["design"]), analysis=_read_value(f["analysis"]),
        station_toml=cfg["station_toml"], facet_toml=cfg["facet_toml"], station_path=cfg["station_path"],
        facet_path=cfg["facet_path"], station_name=cfg["station_name"], record=record, schema_version=version,
        created=created, path=path, sensitivities=sensitivities, uncertainty_inputs=inputs)


def _read_v2(f, path: Path, version: int, load_frames: bool, require_result: bool) -> DumpContent:
    """Reader of schema version 2 (:data:`SCHEMA_V2`): version 1's layout, the screen's pitch as ``pitch_m``
    (square pixels) or ``pitch_x_m`` and ``pitch_y_m``."""
    scr = f["geometry/screen"] if "geometry/screen" in f else {}
    if "pitch_m" not in scr and not ("pitch_x_m" in scr and "pitch_y_m" in scr):
        raise DumpError(f"dump {path} lacks geometry/screen/pitch_m (or pitch_x_m and pitch_y_m) required by schema "
                        f"version {version}; the file is damaged or incomplete")
    return _read_v1(f, path, version, load_frames, require_result, table=SCHEMA_V2)


def _read_v3(f, path: Path, version: int, load_frames: bool, require_result: bool) -> DumpContent:
    """Reader of schema version 3 (:data:`SCHEMA_V3`): version 2's layout and a fixed-pattern capture
    (``design/method`` "fixed" with its ``design/fixed``)."""
    method = _read_value(f["design/method"]) if "design/method" in f else "fringe"
    if method == "fixed" and "design/fixed" not in f:
        raise DumpError(f"dump {path} is a fixed-pattern capture (design/method \"fixed\") but lacks design/fixed "
                        "(the dot grid it showed); the file is damaged or incomplete")
    content = _read_v2(f, path, version, load_frames, require_result)
    n = f["capture/frames"].shape[0]
    if method == "fixed" and n != (3 if content.design["fixed"].get("white_frame") else 1):
        raise DumpError(f"dump {path} holds {n} frames for a fixed-pattern capture "
                        f"({'dark, white and dots' if content.design['fixed'].get('white_frame') else 'the dots'})")
    return content


#: The reader of each schema version this software reads (a new layout adds its version here and keeps
#: the readers of the older ones).
_READERS = {1: _read_v1, 2: _read_v2, 3: _read_v3}
