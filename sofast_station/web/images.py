"""PNG pictures of one facet for the page, from its small picture file (station/pictures.py).

- the camera's white frame with the outline the station found (the edge of the analysis's valid pixels,
  green) and the corners it found (red), drawn with OpenCV;
- the slope-error map against the design, drawn by the report package's map code (the same resampling and
  colours as ``sofast-station report``) from the thinned per-pixel results.

Files are looked up by cycle id only (:func:`~sofast_station.station.pictures.picture_path`), never by a
serial or any other text from a request.
"""

from __future__ import annotations

import io
import logging
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from ..station.pictures import picture_path

log = logging.getLogger(__name__)


class _Thinned:
    """The attributes of an Analysis that the map code reads, from a picture file's thinned arrays."""

    def __init__(self, pic):
        step = int(pic["map_step_px"])
        rows, cols = pic["map_rows"] // step, pic["map_cols"] // step
        h, w = (int(v) for v in pic["camera_shape"])
        self.valid = np.zeros((h // step + 1, w // step + 1), dtype=bool)
        self.valid[rows, cols] = True
        xy = pic["map_points_xy_m"].astype(np.float64)
        self.points_facet_m = np.vstack([xy, np.zeros((1, xy.shape[1]))])
        self.residuals_mrad = {}
        for key in pic.files:
            if key.startswith("map_residuals_"):
                e = pic[key].astype(np.float64)
                self.residuals_mrad[key[len("map_residuals_"):]] = (e[0], e[1])


def white_png(pic) -> bytes:
    """The white frame (grey) with the found outline (green) and corners (red), PNG bytes."""
    import cv2

    white = pic["white"]
    img = cv2.cvtColor(white, cv2.COLOR_GRAY2BGR)
    scale = max(1, int(np.ceil(360 / max(white.shape))))      # small crops are enlarged for the page
    if scale > 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    if "mask" in pic.files and pic["mask"].any():
        contours, _ = cv2.findContours(pic["mask"].astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        contours = [(c * scale + scale // 2).astype(np.int32) for c in contours]
        cv2.drawContours(img, contours, -1, (60, 220, 60), 2)
    if "corners_px" in pic.files and pic["corners_px"].size:
        r0, c0 = (int(v) for v in pic["crop_box"][:2])
        step = int(pic["step_px"])
        for u, v in np.asarray(pic["corners_px"], dtype=np.float64).reshape(-1, 2):
            p = (int(round((u - c0) / step * scale)), int(round((v - r0) / step * scale)))
            cv2.drawMarker(img, p, (40, 40, 235), cv2.MARKER_CROSS, 14, 2)
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes()


def map_png(pic, model: str = "design") -> bytes | None:
    """The slope-error map of *model* (PNG bytes), or None when the file has no per-pixel results.

    Drawn like ``sofast-station report``'s maps (report/maps.py): magnitude on a perceptually ordered scale
    topped at the 99th percentile, arrows of the mean error on a coarse grid."""
    from matplotlib.figure import Figure

    from ..report.maps import SEQUENTIAL_CMAP, _draw_map, robust_top, slope_error_maps

    if "map_rows" not in pic.files or pic["map_rows"].size < 10:
        return None
    m = slope_error_maps(_Thinned(pic), max_cells=300)[model]
    top = robust_top(m.magnitude_mrad)
    fig = Figure(figsize=(5.0, 4.5), layout="constrained")
    ax = fig.subplots()
    r = m.rms_mrad
    image, _ = _draw_map(fig, ax, m, f"slope error vs {model}: RMS x {r['x']:.2f}, y {r['y']:.2f}, "
                                     f"magnitude {r['magnitude']:.2f} mrad\n(one camera pixel in "
                                     f"{int(pic['map_step_px'])} per axis)", top, SEQUENTIAL_CMAP)
    fig.colorbar(image, ax=ax, label="slope error magnitude (mrad)", extend="max", shrink=0.85)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return buf.getvalue()


class FacetImages:
    """Renders and caches the PNGs of recent facets (a handful, in memory)."""

    def __init__(self, data_dir: str | Path, cache: int = 16):
        self.data_dir = Path(data_dir)
        self._cache: OrderedDict = OrderedDict()
        self._size = cache
        self._lock = threading.Lock()                # requests are served from a thread pool

    def get(self, cycle_id: str, kind: str) -> bytes | None:
        """The PNG *kind* ("white" or "map") of *cycle_id*; None when there is none (or no such cycle)."""
        if kind not in ("white", "map"):
            return None
        path = picture_path(self.data_dir, cycle_id)
        if path is None or not path.is_file():
            return None
        key = (cycle_id, kind)
        with self._lock:
            if key in self._cache:
                self._cache.move_to_end(key)
                return self._cache[key]
        try:
            with np.load(path, allow_pickle=False) as pic:
                png = white_png(pic) if kind == "white" else map_png(pic)
        except Exception as exc:            # a half-pruned or damaged file: no picture, not a broken page
            log.warning("cannot draw the %s picture of cycle %s: %s", kind, cycle_id, exc)
            return None
        if png is not None:
            with self._lock:
                self._cache[key] = png
                while len(self._cache) > self._size:
                    self._cache.popitem(last=False)
        return png
