"""Per-camera data computed once per process and reused by every analysis (the station's steady state).

The analysis itself (:mod:`sofast_station.measure`) keeps no state; what depends only on the camera
calibration (the pixel rays) is kept here, per camera, so that the station's worker, ``reprocess`` and
``batch`` on many dumps of one station, and ``import-opencsp`` pay for it once. :func:`warm_up` fills it
before the first facet (the analysis worker calls it when it starts).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict

import numpy as np

from .geometry import CameraIntrinsics
from .measure.camera import RayTable

#: Ray tables kept (one per camera calibration; 25 bytes per pixel each: 48 MB for 1.9 MP).
MAX_CAMERAS = 2

_TABLES: "OrderedDict[tuple, RayTable]" = OrderedDict()
_LOCK = threading.Lock()


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
            while len(_TABLES) > MAX_CAMERAS:
                _TABLES.popitem(last=False)
        else:
            _TABLES.move_to_end(key)
        return table


def warm_up(camera: CameraIntrinsics) -> float:
    """Fill the camera's ray table for every pixel, so the first facet costs what every other does.

    Returns
    -------
    float
        Seconds it took (about 2 s for 1.9 MP; nothing when the table is already full).
    """
    t = time.perf_counter()
    ray_table(camera).fill()
    return time.perf_counter() - t
