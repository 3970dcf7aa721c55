"""PNG pictures of one facet for the page, from its small picture file (live/pictures.py).

- the camera's white frame with the outline the station found (the edge of the analysis's valid pixels,
  green) and the corners it found (red), drawn with OpenCV;
- the slope-error map against the design, from the thinned per-pixel results: the report package's
  resampling, colours and arrows (as ``sofast-station report``), drawn with OpenCV (cheap enough for every
  facet).

Files are looked up by cycle id only (:func:`~sofast_station.live.pictures.picture_path`), never by a
serial or any other text from a request.
"""

from __future__ import annotations

import functools
import io
import json
import logging
import sqlite3
import threading
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from ..live.pictures import picture_path
from ..recipes import recipes_from_config

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


#: Size of the page's map picture, pixels (width x height), and its plot box inside it.
MAP_SIZE_PX = (440, 428)
_MAP_BOX_PX = (12, 46, 352, 352)                  # left, top, width, height of the map's square area
_FONT = 0                                         # cv2.FONT_HERSHEY_SIMPLEX


@functools.lru_cache(maxsize=4)
def _colour_table(name: str) -> np.ndarray:
    """256 x 3 BGR uint8 table of the matplotlib colour map *name* (the report's colours)."""
    # lazy: the page serves first; warm() loads these (~300 ms CPU) in a thread at start
    import matplotlib

    rgba = matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))
    return np.ascontiguousarray((rgba[:, 2::-1] * 255.0 + 0.5).astype(np.uint8))


def _text(img, text: str, org, scale: float = 0.42, colour=(30, 30, 30), thick: int = 1) -> None:
    cv2.putText(img, text, (int(org[0]), int(org[1])), _FONT, scale, colour, thick, cv2.LINE_AA)


def map_png(pic, model: str = "design") -> bytes | None:
    """The slope-error map of *model* (PNG bytes), or None when the file has no per-pixel results.

    The same map as ``sofast-station report`` draws (report/maps.py: the same resampling onto the facet
    grid, the magnitude on the same perceptually ordered scale topped at the 99th percentile, arrows of
    the mean error on the same coarse grid, scaled so the 95th-percentile arrow is 0.9 cell long), drawn
    with OpenCV instead of matplotlib: the monitor draws one per facet while the line runs, and
    matplotlib's layout and text took 0.4-0.6 s of CPU a map against 30-50 ms here. Facet +x to the
    right, +y up; a scale bar stands in for the axes."""
    # lazy: the page serves first; warm() loads these (~300 ms CPU) in a thread at start
    from ..report.maps import SEQUENTIAL_CMAP, nice_round, robust_top, scaled_arrows, slope_error_maps

    if "map_rows" not in pic.files or pic["map_rows"].size < 10:
        return None
    m = slope_error_maps(_Thinned(pic), max_cells=300)[model]
    top = robust_top(m.magnitude_mrad)
    width, height = MAP_SIZE_PX
    img = np.full((height, width, 3), 255, np.uint8)
    bx, by, bw, bh = _MAP_BOX_PX
    x0, x1, y0, y1 = m.extent_m
    span = max(x1 - x0, y1 - y0)
    px_per_m = min(bw, bh) / span
    w, h = max(1, int(round((x1 - x0) * px_per_m))), max(1, int(round((y1 - y0) * px_per_m)))
    left, top_px = bx + (bw - w) // 2, by + (bh - h) // 2
    # the magnitude grid: row 0 is the lowest y, so flip it to draw +y up
    mag = np.flipud(m.magnitude_mrad)
    on = np.isfinite(mag)
    level = np.zeros(mag.shape, np.uint8)
    level[on] = np.clip(np.rint(mag[on] / top * 255.0), 0, 255).astype(np.uint8)
    colours = _colour_table(SEQUENTIAL_CMAP)[level]
    colours[~on] = 235                                   # off the facet: light grey
    img[top_px:top_px + h, left:left + w] = cv2.resize(colours, (w, h), interpolation=cv2.INTER_NEAREST)
    # arrows: the report's decimated grid and scaling
    ax_, ay_, au, av, cell, ref = scaled_arrows(m.arrow_x_m, m.arrow_y_m, m.arrow_ex_mrad, m.arrow_ey_mrad)
    length_px = 0.9 * cell * px_per_m / ref             # pixels per mrad
    for xm, ym, u, v in zip(ax_, ay_, au, av):
        cx, cy = left + (xm - x0) * px_per_m, top_px + (y1 - ym) * px_per_m
        dx, dy = 0.5 * u * length_px, -0.5 * v * length_px
        p, q = (int(round(cx - dx)), int(round(cy - dy))), (int(round(cx + dx)), int(round(cy + dy)))
        cv2.arrowedLine(img, p, q, (255, 255, 255), 3, cv2.LINE_AA, tipLength=0.3)
        cv2.arrowedLine(img, p, q, (0, 0, 0), 1, cv2.LINE_AA, tipLength=0.3)
    # title: the RMS figures of this map
    r = m.rms_mrad
    _text(img, f"slope error vs {model}, mrad", (8, 16), 0.46, thick=1)
    _text(img, f"RMS x {r['x']:.2f}  y {r['y']:.2f}  magnitude {r['magnitude']:.2f}", (8, 35), 0.42)
    # colour bar with five labels, and "+" when values lie above the top
    cbx, cby, cbw, cbh = bx + bw + 14, by + 10, 14, bh - 20
    bar = _colour_table(SEQUENTIAL_CMAP)[np.linspace(255, 0, cbh).astype(np.uint8)][:, None, :]
    img[cby:cby + cbh, cbx:cbx + cbw] = np.repeat(bar, cbw, axis=1)
    cv2.rectangle(img, (cbx - 1, cby - 1), (cbx + cbw, cby + cbh), (60, 60, 60), 1)
    over = bool(on.any() and np.nanmax(mag) > top)
    for i in range(5):
        frac = i / 4
        yy = int(round(cby + cbh - 1 - frac * (cbh - 1)))
        cv2.line(img, (cbx + cbw, yy), (cbx + cbw + 3, yy), (60, 60, 60), 1)
        label = f"{top * frac:.3g}" + ("+" if over and i == 4 else "")
        _text(img, label, (cbx + cbw + 6, yy + 4), 0.38)
    # keys under the map: a round arrow length and a scale bar of a round length
    key = nice_round(ref)
    ky = by + bh + (height - by - bh) // 2 + 4
    kl = int(round(key * length_px))
    cv2.arrowedLine(img, (bx + 4, ky - 4), (bx + 4 + kl, ky - 4), (0, 0, 0), 1, cv2.LINE_AA, tipLength=0.3)
    _text(img, f"{key:g} mrad", (bx + 10 + kl, ky), 0.4)
    bar_m = nice_round(0.3 * span)
    bl = int(round(bar_m * px_per_m))
    sx = bx + bw - bl
    cv2.line(img, (sx, ky - 4), (sx + bl, ky - 4), (0, 0, 0), 2)
    _text(img, f"{bar_m:g} m", (sx - 44, ky), 0.4)
    ok, buf = cv2.imencode(".png", img)
    return buf.tobytes() if ok else None


def facet_map_png(record: dict, ensemble, limit_mrad: float | None) -> bytes:
    """The map of a heliostat's facets (:func:`~sofast_station.report.heliostat.draw_facet_map`), PNG bytes."""
    # lazy: report/heliostat.py brings matplotlib.figure (~750 ms CPU), needed only for a heliostat's map
    from ..report.heliostat import draw_facet_map

    buf = io.BytesIO()
    draw_facet_map(record, ensemble, limit_mrad, title=f"{record.get('serial')}: "
                   f"{str(record.get('verdict')).upper()}").savefig(buf, format="png", dpi=70)
    return buf.getvalue()


class FacetImages:
    """Renders and caches the PNGs of recent facets (a handful, in memory)."""

    def __init__(self, data_dir: str | Path, cache: int = 16, config=None):
        self.data_dir = Path(data_dir)
        #: The station's configuration: its recipes' heliostats, for the map of a heliostat's facets.
        self.config = config
        self._cache: OrderedDict = OrderedDict()
        self._size = cache
        self._lock = threading.Lock()                # requests are served from a thread pool

    def _facets(self, cycle_id: str) -> bytes | None:
        """The map of the heliostat measured in *cycle_id* (its record from the journal, its heliostat from
        its recipe); None for anything else."""
        if self.config is None:
            return None
        key = (cycle_id, "facets")
        with self._lock:
            if key in self._cache:
                return self._cache[key]
        try:
            con = sqlite3.connect(f"file:{self.data_dir / 'journal.sqlite3'}?mode=ro", uri=True, timeout=2.0)
            try:
                row = con.execute("SELECT record FROM cycles WHERE cycle_id = ?", (cycle_id,)).fetchone()
            finally:
                con.close()
            record = json.loads(row[0]) if row else None
            if not record or not isinstance(record.get("facets"), list):
                return None
            recipes = recipes_from_config(self.config)
            recipe = recipes.get(record.get("recipe") or "default", recipes["default"])
            if recipe.ensemble is None:
                return None
            png = facet_map_png(record, recipe.ensemble, recipe.limits.max_canting_mrad)
        except Exception as exc:          # a picture, never a broken page
            log.warning("cannot draw the map of the facets of cycle %s: %s", cycle_id, exc)
            return None
        with self._lock:
            self._cache[key] = png
            while len(self._cache) > self._size:
                self._cache.popitem(last=False)
        return png

    def warm(self) -> None:
        """Import what drawing needs (the report's maps, matplotlib's colour table): about 0.3 s of CPU, at start."""
        # lazy: the page serves first; warm() loads these (~300 ms CPU) in a thread at start
        from ..report.maps import SEQUENTIAL_CMAP
        _colour_table(SEQUENTIAL_CMAP)

    def get(self, cycle_id: str, kind: str) -> bytes | None:
        """The PNG *kind* ("white", "map", or a heliostat's "facets") of *cycle_id*; None when there is none (or
        no such cycle)."""
        if kind == "facets":
            return self._facets(cycle_id)
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
