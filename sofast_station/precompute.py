"""Per-camera data computed once per process and reused by every analysis (the station's steady state).

The analysis itself (:mod:`sofast_station.measure`) keeps no state; what depends only on the camera
calibration (the pixel rays) is kept here, per camera, so that the station's worker, ``reprocess`` and
``batch`` on many dumps of one station, and ``import-opencsp`` pay for it once. :func:`warm_up` fills it
before the first facet (the analysis worker calls it when it starts).
"""

from __future__ import annotations

import ctypes
import threading
import time
from collections import OrderedDict

import numpy as np

from .cache import load_rays, save_rays
from .geometry import CameraIntrinsics
from .measure.camera import RayTable
from .measure.kernels import warm_up as load_kernels

#: Ray tables kept (one per camera calibration; 25 bytes per pixel each: 48 MB for 1.9 MP).
MAX_CAMERAS = 2

_TABLES: "OrderedDict[tuple, RayTable]" = OrderedDict()
_LOCK = threading.Lock()
#: The station's cache on disk this process keeps its rays in (:func:`use_disk_cache`), and how many
#: pixels of each table were there when it was read or last written.
_DISK = None
_ON_DISK: dict = {}


def _camera_key(camera: CameraIntrinsics) -> tuple:
    return (int(camera.width_px), int(camera.height_px), np.asarray(camera.matrix, np.float64).tobytes(),
            np.asarray(camera.distortion, np.float64).tobytes())


def ray_table(camera: CameraIntrinsics) -> RayTable:
    """The process's :class:`~sofast_station.measure.camera.RayTable` for this camera calibration.

    Rays are computed for the pixels an analysis asks for the first time it asks; later analyses of the
    same camera reuse them (bit-identical to computing them afresh). The least recently used table is
    dropped beyond :data:`MAX_CAMERAS` calibrations.
    """
    key = _camera_key(camera)
    with _LOCK:
        table = _TABLES.get(key)
        if table is None:
            table = _TABLES[key] = RayTable(camera)
            if _DISK is not None:
                _ON_DISK[key] = load_rays(_DISK, table)
            while len(_TABLES) > MAX_CAMERAS:
                _ON_DISK.pop(_TABLES.popitem(last=False)[0], None)
        else:
            _TABLES.move_to_end(key)
        return table


def use_disk_cache(cache) -> None:
    """Keep this process's pixel rays in the station's cache on disk too (a
    :class:`~sofast_station.cache.DiskCache`, or None: not): a ray table is filled from it when first
    asked for, and :func:`keep_rays` writes back what the analyses added. For the commands that start a
    process per use (``reprocess``, ``import-opencsp``, ``inspect``); the rays are the same bits either way."""
    global _DISK
    with _LOCK:
        _DISK = cache


def keep_rays() -> int:
    """Write every ray table that gained pixels since it was read to the cache of :func:`use_disk_cache`;
    returns how many tables were written."""
    if _DISK is None:
        return 0

    written = 0
    with _LOCK:
        for key, table in _TABLES.items():
            n = table.n_known
            if n > _ON_DISK.get(key, 0) and save_rays(_DISK, table):
                _ON_DISK[key] = n
                written += 1
    return written


def keep_freed_memory() -> bool:
    """Have the C allocator keep the memory an analysis frees for the next one (glibc; elsewhere nothing).

    An analysis allocates and frees arrays of megabytes. By default glibc maps each one afresh (mmap) and
    unmaps it when it is freed, so every analysis pays a page fault per 4 kB page it touches again (several
    microseconds each in a virtual machine), and each mapping call takes the process's memory-map lock,
    which stalls the page faults of the other analysis thread: the two threads then run one after the
    other. With blocks up to 32 MB taken from the heap and the heap never trimmed, the process keeps the
    memory of its largest analysis (its peak resident size is unchanged) and reuses it: on the 2-core test
    machine the twin's analysis took about 15 % less wall and CPU time (2,000-5,000 page faults fewer).

    Returns
    -------
    bool
        Whether the allocator took the settings.
    """
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    m_trim_threshold, m_mmap_threshold = -1, -3          # glibc's malloc.h
    return bool(mallopt(m_mmap_threshold, 32 * 1024 * 1024)) and bool(mallopt(m_trim_threshold, 2 ** 31 - 1))


def prepare_analysis_process() -> float:
    """What a process that analyses capture after capture does when it starts (``reprocess``, ``batch``'s
    workers, ``import-opencsp``; the station's worker through :func:`warm_up`): keep freed memory
    (:func:`keep_freed_memory`) and load the analysis' compiled kernels (the build ``setup-env`` made of
    them, a millisecond; without one from numba's on-disk cache, about a second, or compiled, 10 to 20 s,
    the first time after an install or an update), so the first analysis costs what the others do.
    Returns the seconds it took."""
    t = time.perf_counter()
    keep_freed_memory()
    load_kernels()
    return time.perf_counter() - t


def warm_up(camera: CameraIntrinsics) -> float:
    """Fill the camera's ray table for every pixel and load the analysis' compiled kernels, so the first
    facet costs what every other does, and have the process keep the memory analyses free for the next
    (:func:`keep_freed_memory`).

    Returns
    -------
    float
        Seconds it took (about 2 s for 1.9 MP, plus the kernels: a millisecond from their build, about 1 s
        from numba's on-disk cache, 10 to 20 s the first time after an install or an update without a
        build, when they are compiled and cached).
    """
    t = time.perf_counter()
    prepare_analysis_process()
    ray_table(camera).fill()
    return time.perf_counter() - t
