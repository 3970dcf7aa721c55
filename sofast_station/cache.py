"""The station's cache on disk (``data_dir/cache``): results that take seconds to compute, that depend only on
what their key names, and that are the same bits whoever computes them, kept across processes so that a
fresh ``reprocess``, ``import-opencsp`` or ``inspect`` does not pay for them again.

Two kinds are kept:

* the uncertainty's **sensitivities** (:func:`~sofast_station.measure.uncertainty.sensitivities`, 0.4 to
  3.5 s for a full-resolution capture), keyed by the station's geometry, recipe and input uncertainties
  (:func:`~sofast_station.measure.uncertainty.sensitivity_key`), the capture they are computed from (a
  SHA-256 of its frames, its measured distance and pixel mask: they are finite differences of that
  capture's reduction) and the analysis code (:func:`code_fingerprint`);
* the camera's **pixel rays** (:class:`~sofast_station.measure.camera.RayTable`: undistorting 600,000
  pixels takes 0.4 s of CPU), keyed by the camera calibration, OpenCV's version and the analysis code.

A value is stored under a hash of its whole key (a JSON object) together with that key, and a read compares
the key it finds with the one it asked for: a changed input, another capture, an updated install or a
hash collision reads as a miss, never as another key's value. So a value read from the cache is the value
computing it afresh gives, and a command's figures do not depend on whether the cache was warm
(tests/reanalysis/test_sensitivity_cache.py runs ``reprocess`` cold and warm and compares every figure).

Any number of processes may read and write at once: the store is diskcache's (SQLite in WAL mode; a large
value is written to its own file before the row naming it is committed). Least recently stored values are
evicted beyond :data:`SIZE_LIMIT_BYTES`. A cache that cannot be opened or written (a read-only or full
``data_dir``) is skipped with a warning: the command computes what it needs, as without a cache.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sqlite3
from pathlib import Path

import cv2
import diskcache
import numpy as np

from . import __version__
from .measure.camera import UNDISTORT_CRITERIA
from .measure.compiled import installed_version
from .measure.sensitivity_record import from_record, to_record
from .measure.uncertainty import Sensitivities

log = logging.getLogger(__name__)

#: The cache's folder under the station's ``data_dir``.
FOLDER = "cache"
#: Beyond this the least recently stored values are dropped (a full-resolution camera's rays are 15 to
#: 46 MB, a set of sensitivities 20 kB).
SIZE_LIMIT_BYTES = 1 << 30
#: Version of the stored layouts (part of every key: a new layout misses the old values).
LAYOUT = 1

_CODE: str | None = None


def code_fingerprint() -> str:
    """A hash of what computes the cached values: the source of the analysis package
    (``sofast_station/measure``) and the versions of the libraries it computes with. An update of either
    misses every value computed before it."""
    global _CODE
    if _CODE is None:
        h = hashlib.sha256()
        root = Path(__file__).resolve().parent
        for path in sorted((root / "measure").rglob("*.py")):
            h.update(path.relative_to(root).as_posix().encode())
            h.update(path.read_bytes())
        # scipy's and numba's versions from their metadata: importing them only for it cost every command
        # 0.01 s (scipy) and 0.3 s (numba)
        h.update(json.dumps([__version__, np.__version__, installed_version("scipy"), cv2.__version__,
                             installed_version("numba")]).encode())
        _CODE = h.hexdigest()[:32]
    return _CODE


def array_digest(a: np.ndarray | None) -> str | None:
    """SHA-256 of an array's shape, type and values (None for None)."""
    if a is None:
        return None
    a = np.ascontiguousarray(a)
    h = hashlib.sha256(json.dumps([list(a.shape), a.dtype.str]).encode())
    h.update(a.data)
    return h.hexdigest()


def capture_basis(frames: np.ndarray, measured_distance_m: float, pixel_mask: np.ndarray | None = None,
                  **extra) -> dict:
    """What a capture's sensitivities are computed from besides their key: its frames, the measured
    distance and the pixel mask (and *extra*, e.g. a dump's crop box when *frames* are the cropped ones)."""
    return {"frames": array_digest(frames), "measured_distance_m": repr(float(measured_distance_m)),
            "pixel_mask": array_digest(None if pixel_mask is None else np.asarray(pixel_mask, bool)), **extra}


class DiskCache:
    """The cache folder of one station (:func:`open_cache`): bytes stored under JSON keys.

    Parameters
    ----------
    directory : Path
        Created when missing.
    """

    def __init__(self, directory: Path):
        self.directory = Path(directory)
        self._store = diskcache.Cache(str(self.directory), size_limit=SIZE_LIMIT_BYTES,
                                      eviction_policy="least-recently-stored")
        self._warned = False

    def close(self) -> None:
        self._store.close()

    @staticmethod
    def _name(kind: str, key: dict) -> tuple[str, bytes]:
        text = json.dumps({"kind": kind, "layout": LAYOUT, **key}, sort_keys=True, separators=(",", ":"))
        return f"{kind}-{hashlib.sha256(text.encode()).hexdigest()}", text.encode()

    def _failed(self, what: str, exc: Exception) -> None:
        if not self._warned:
            log.warning("the cache in %s could not be %s (%s): going on without it", self.directory, what, exc)
            self._warned = True

    def get(self, kind: str, key: dict) -> bytes | None:
        """The bytes stored for *key* of *kind*, or None (absent, or stored for another key)."""
        name, text = self._name(kind, key)
        try:
            value = self._store.get(name)
        except (OSError, sqlite3.Error, diskcache.Timeout) as exc:
            self._failed("read", exc)
            return None
        if not isinstance(value, bytes):
            return None
        stored, sep, payload = value.partition(b"\0")
        return payload if sep and stored == text else None

    def put(self, kind: str, key: dict, payload: bytes) -> bool:
        """Store *payload* for *key* of *kind* (with the key itself); False when the cache could not take it."""
        name, text = self._name(kind, key)
        try:
            return bool(self._store.set(name, text + b"\0" + payload))
        except (OSError, sqlite3.Error, diskcache.Timeout) as exc:
            self._failed("written", exc)
            return False


def open_cache(data_dir: Path | None) -> DiskCache | None:
    """The cache under *data_dir* (created when missing), or None when there is none or it cannot be opened
    (warned: the command goes on without it)."""
    if data_dir is None:
        return None
    directory = Path(data_dir) / FOLDER
    try:
        return DiskCache(directory)
    except (OSError, sqlite3.Error) as exc:
        log.warning("no cache in %s (%s): what it would keep is computed afresh", directory, exc)
        return None


# -- the uncertainty's sensitivities ------------------------------------------------------------------------
class SensitivityStore(dict):
    """The ``sensitivity_cache`` an analysis takes (a dict, :func:`~sofast_station.measure.analysis.analyse`)
    that also reads and writes the sensitivities of one capture in the cache on disk.

    Sensitivities (under the string keys of ``sensitivity_key``) missing from the dict are looked for on
    disk under that key and *basis* (:func:`capture_basis`; a callable is called the first time it is
    needed, so a capture whose sensitivities are at hand is never hashed); computed ones are written
    there. Anything else the analysis keeps in it (the frame-brightness pool) stays in this process.

    Parameters
    ----------
    cache : DiskCache or None
        None: a plain dict.
    basis : dict or callable returning one
        The capture the sensitivities are computed from.
    initial : dict, optional
        Sensitivities at hand (a dump's own): used before anything on disk, and not written there.
    pool : bool
        Whether the analysis may keep its frame-brightness pool here (as in any cache it is given); False
        gives what an analysis without a cache does (its capture's own frame brightness only).
    """

    def __init__(self, cache: DiskCache | None, basis, initial: dict | None = None, pool: bool = True):
        super().__init__(initial or {})
        self._cache = cache
        self._basis = basis
        self._pool = pool
        self.hits = 0          # read from disk (for the command's log and the tests)

    def setdefault(self, key, default=None):
        if not self._pool and not isinstance(key, str):
            return None
        return super().setdefault(key, default)

    def basis(self) -> dict:
        if callable(self._basis):
            self._basis = self._basis()
        return self._basis

    def _key(self, key: str) -> dict:
        return {"sensitivity_key": key, "basis": self.basis(), "code": code_fingerprint()}

    def get(self, key, default=None):
        if dict.__contains__(self, key):
            return dict.__getitem__(self, key)
        if self._cache is None or not isinstance(key, str):
            return default
        payload = self._cache.get("sensitivities", self._key(key))
        found = None
        if payload is not None:
            try:
                found = from_record(json.loads(payload))
            except (ValueError, UnicodeDecodeError):
                found = None
        if found is None or found[0] != key:
            return default
        self.hits += 1
        dict.__setitem__(self, key, found[1])
        return found[1]

    def __setitem__(self, key, value) -> None:
        dict.__setitem__(self, key, value)
        if self._cache is not None and isinstance(key, str) and isinstance(value, Sensitivities):
            record = to_record(key, value)
            self._cache.put("sensitivities", self._key(key), json.dumps(record).encode())


# -- the camera's pixel rays --------------------------------------------------------------------------------
def _ray_key(camera) -> dict:
    return {"camera": [int(camera.width_px), int(camera.height_px),
                       np.asarray(camera.matrix, np.float64).tobytes().hex(),
                       np.asarray(camera.distortion, np.float64).tobytes().hex()],
            "undistort": list(UNDISTORT_CRITERIA), "opencv": cv2.__version__, "code": code_fingerprint()}


def load_rays(cache: DiskCache | None, table) -> int:
    """Fill the :class:`~sofast_station.measure.camera.RayTable` *table* with the rays kept for its camera;
    returns how many pixels it took."""
    if cache is None:
        return 0
    payload = cache.get("rays", _ray_key(table.camera))
    if payload is None:
        return 0
    n = table.camera.width_px * table.camera.height_px
    packed = (n + 7) // 8
    try:
        known = np.unpackbits(np.frombuffer(payload, np.uint8, packed, 0), count=n).astype(bool)
        idx = np.flatnonzero(known)
        rays = np.frombuffer(payload, np.float64, 3 * idx.size, packed).reshape(3, idx.size)
    except ValueError:
        return 0
    table.add_known(idx, rays)
    return int(idx.size)


def save_rays(cache: DiskCache | None, table) -> bool:
    """Keep every ray *table* knows for its camera (replacing what was kept)."""
    if cache is None:
        return False
    idx, rays = table.known()
    n = table.camera.width_px * table.camera.height_px
    known = np.zeros(n, dtype=bool)
    known[idx] = True
    return cache.put("rays", _ray_key(table.camera), np.packbits(known).tobytes() + rays.tobytes())


# -- a measured screen's grid split ------------------------------------------------------------------------
def _split_key(nodes_uv: np.ndarray) -> dict:
    return {"nodes_uv": array_digest(np.ascontiguousarray(nodes_uv, np.float64)), "code": code_fingerprint()}


def load_screen_split(cache: DiskCache | None, nodes_uv: np.ndarray) -> np.ndarray | None:
    """The grid split (:attr:`~sofast_station.measure.screen.InterpolatedScreen.split`) kept for a measured
    screen's grid positions *nodes_uv*, or None."""
    if cache is None:
        return None
    payload = cache.get("screen_split", _split_key(nodes_uv))
    if payload is None or len(payload) < 8:
        return None
    rows, cols = (int(v) for v in np.frombuffer(payload, np.int32, 2))
    try:
        return np.unpackbits(np.frombuffer(payload, np.uint8, offset=8), count=rows * cols).astype(bool).reshape(
            rows, cols)
    except ValueError:
        return None


def save_screen_split(cache: DiskCache | None, nodes_uv: np.ndarray, split: np.ndarray | None) -> bool:
    """Keep the grid split of a measured screen on the grid positions *nodes_uv* (the triangulation scipy
    made: the key's code fingerprint holds scipy's version)."""
    if cache is None or split is None:
        return False
    split = np.asarray(split, dtype=bool)
    return cache.put("screen_split", _split_key(nodes_uv),
                     np.array(split.shape, np.int32).tobytes() + np.packbits(split).tobytes())
