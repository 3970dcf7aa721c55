"""Slope-error maps for the process engineer (the method paper's Figs. 8-10).

For each model (design, fitted parabola, higher order) the colour is the magnitude of the slope error
sqrt(e_x^2 + e_y^2) in mrad on a fixed scale (0 to 5 mrad by default, blue to maroon as in the paper),
drawn in facet coordinates (x and y in metres, +y up), and white arrows show the error's direction and
size (e_x, e_y) at every Nth camera pixel in both image directions. The panel titles carry the RMS of
e_x, e_y and the magnitude, which are the reported figures. The map is a nearest-pixel resampling of the
per-pixel residuals onto a regular facet grid as fine as the camera's pixels on the facet, so every
coloured cell shows one measured pixel's value.

The module uses Matplotlib's object-oriented API with the Agg canvas (no pyplot, no display), so it runs
headless and in worker threads; every picture is written to a temporary file and renamed into place.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ._common import ReportError, savefig_atomic

log = logging.getLogger(__name__)

#: The three models of the paper's Figs. 8-10, in order, with their panel labels.
MODELS = ("design", "parabola", "higher_order")
MODEL_LABELS = {"design": "compared with the design", "parabola": "compared with the fitted parabola",
                "higher_order": "compared with the higher-order model (3rd order in z)"}

# -- slope-error maps -------------------------------------------------------------------------------------
@dataclass
class SlopeErrorMap:
    """One model's slope errors, ready to draw.

    Attributes
    ----------
    model : str
        ``design``, ``parabola`` or ``higher_order``.
    magnitude_mrad : (ny, nx) array
        sqrt(e_x^2 + e_y^2) of the nearest camera pixel on a regular facet grid, mrad; NaN off the facet.
    extent_m : (float, float, float, float)
        (x_min, x_max, y_min, y_max) of the grid's cell edges, facet frame, metres.
    arrow_x_m, arrow_y_m : (K,) arrays
        Facet-frame position of every Nth pixel, metres.
    arrow_ex_mrad, arrow_ey_mrad : (K,) arrays
        Its slope errors e_x, e_y, mrad.
    arrow_step_px : int
        N: the arrows sit on every Nth camera row and column.
    pixel_m : float
        Size of one camera pixel on the facet, metres.
    rms_mrad : dict
        RMS of e_x, of e_y and the magnitude RMS over every valid pixel, mrad.
    """

    model: str
    magnitude_mrad: np.ndarray
    extent_m: tuple
    arrow_x_m: np.ndarray
    arrow_y_m: np.ndarray
    arrow_ex_mrad: np.ndarray
    arrow_ey_mrad: np.ndarray
    arrow_step_px: int
    pixel_m: float
    rms_mrad: dict


def _poly_terms(u: np.ndarray, v: np.ndarray, degree: int = 3) -> np.ndarray:
    return np.stack([u ** i * v ** j for i in range(degree + 1) for j in range(degree + 1 - i)], axis=1)


def auto_arrow_step(pixels_across: int, most: int = 32) -> int:
    """Every 10th pixel, as in the paper, unless that puts more than *most* arrows across the facet (a
    1600 x 1200 camera sees the facet about 770 pixels wide: every 25th pixel)."""
    return max(10, int(math.ceil(pixels_across / most)))


def slope_error_maps(analysis, arrow_step_px: int | None = None, max_cells: int = 1500) -> dict[str, SlopeErrorMap]:
    """Resample an analysis's per-pixel residuals onto a facet grid, for each model.

    Parameters
    ----------
    analysis : sofast_station.measure.pipeline.Analysis
        ``valid`` (rows, columns), ``points_facet_m`` (3, N) and ``residuals_mrad`` {model: (e_x, e_y)}
        in the raster order of ``valid``.
    arrow_step_px : int, optional
        Arrows on every Nth camera row and column; :func:`auto_arrow_step` by default.
    max_cells : int
        Largest grid size along either axis (cells).

    Returns
    -------
    dict
        Model name -> :class:`SlopeErrorMap`.
    """
    rows, cols = np.nonzero(analysis.valid)          # raster order: the order of the per-point arrays
    x, y = analysis.points_facet_m[0], analysis.points_facet_m[1]
    if rows.size != x.size:
        raise ReportError(f"the analysis has {x.size} points but {rows.size} valid pixels: cannot map them")
    # the camera pixel's size on the facet, from the linear map (column, row) -> (x, y)
    a = np.column_stack([cols, rows, np.ones_like(cols)]).astype(np.float64)
    jx, *_ = np.linalg.lstsq(a, x, rcond=None)
    jy, *_ = np.linalg.lstsq(a, y, rcond=None)
    pixel_m = float(math.sqrt(abs(jx[0] * jy[1] - jx[1] * jy[0])))
    # the inverse map (x, y) -> (column, row), a cubic in centred and scaled coordinates
    x0, y0 = float(np.mean(x)), float(np.mean(y))
    s = float(max(np.ptp(x), np.ptp(y), 1e-9)) / 2.0
    terms = _poly_terms((x - x0) / s, (y - y0) / s)
    kc, *_ = np.linalg.lstsq(terms, cols.astype(np.float64), rcond=None)
    kr, *_ = np.linalg.lstsq(terms, rows.astype(np.float64), rcond=None)
    misfit = float(np.max(np.hypot(terms @ kc - cols, terms @ kr - rows)))
    if misfit > 0.5:
        log.warning("the facet-to-image map misses some pixels by %.2f px: the map may be slightly smeared", misfit)
    cell = max(pixel_m, float(max(np.ptp(x), np.ptp(y))) / max_cells)
    xmin, xmax = float(x.min()) - cell, float(x.max()) + cell
    ymin, ymax = float(y.min()) - cell, float(y.max()) + cell
    nx, ny = int(math.ceil((xmax - xmin) / cell)), int(math.ceil((ymax - ymin) / cell))
    gx = xmin + (np.arange(nx) + 0.5) * cell
    gy = ymin + (np.arange(ny) + 0.5) * cell
    gxx, gyy = np.meshgrid(gx, gy)
    gterms = _poly_terms((gxx.ravel() - x0) / s, (gyy.ravel() - y0) / s)
    gc = np.rint(gterms @ kc).astype(np.int64)
    gr = np.rint(gterms @ kr).astype(np.int64)
    h, w = analysis.valid.shape
    inside = (gc >= 0) & (gc < w) & (gr >= 0) & (gr < h)
    index = np.full(analysis.valid.shape, -1, dtype=np.int64)
    index[rows, cols] = np.arange(rows.size)
    cell_point = np.full(gc.size, -1, dtype=np.int64)
    cell_point[inside] = index[gr[inside], gc[inside]]
    on_facet = cell_point >= 0
    across = int(max(np.ptp(rows), np.ptp(cols))) + 1
    step = int(arrow_step_px) if arrow_step_px else auto_arrow_step(across)
    if step < 1:
        raise ValueError(f"arrow_step_px must be at least 1, got {arrow_step_px}")
    pick = (rows % step == 0) & (cols % step == 0)
    out = {}
    for model in MODELS:
        ex, ey = (np.asarray(e, dtype=np.float64) for e in analysis.residuals_mrad[model])
        mag = np.hypot(ex, ey)
        grid = np.full(gc.size, np.nan)
        grid[on_facet] = mag[cell_point[on_facet]]
        n = ex.size
        sx, sy = float(np.sum(ex * ex)) / n, float(np.sum(ey * ey)) / n
        out[model] = SlopeErrorMap(model, grid.reshape(ny, nx), (xmin, xmin + nx * cell, ymin, ymin + ny * cell),
                                   x[pick], y[pick], ex[pick], ey[pick], step, pixel_m,
                                   {"x": math.sqrt(sx), "y": math.sqrt(sy), "magnitude": math.sqrt(sx + sy)})
    return out


def _draw_map(fig, ax, m: SlopeErrorMap, title: str, vmax_mrad: float, cmap: str):
    image = ax.imshow(m.magnitude_mrad, extent=m.extent_m, origin="lower", cmap=cmap, vmin=0.0, vmax=vmax_mrad,
                      interpolation="nearest")
    spacing = m.arrow_step_px * m.pixel_m
    # an error of vmax_mrad is drawn 3 arrow spacings long (1 mrad: 0.6 spacings on the 5 mrad scale)
    q = ax.quiver(m.arrow_x_m, m.arrow_y_m, m.arrow_ex_mrad, m.arrow_ey_mrad, color="white", angles="xy",
                  scale_units="xy", scale=vmax_mrad / (3.0 * spacing), width=0.0025, headwidth=3.5,
                  headlength=4.0, pivot="tail")
    ax.set_xlabel("facet x (m)")
    ax.set_ylabel("facet y (m)")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9.5)
    return image, q


def _arrow_key(q, x: float) -> None:
    q.axes.quiverkey(q, x, 0.025, 1.0, "arrow of a 1 mrad error", labelpos="E", coordinates="figure",
                  color="black", fontproperties={"size": 8})


def _titles(result, maps: dict) -> dict:
    rec = result.record
    f_design = getattr(result.design, "focal_length_m", None)

    def fmt_f(v):
        return "inf" if v is None else f"{v:.4f}"

    head = {"design": MODEL_LABELS["design"] + (f" (f {f_design:g} m)" if f_design else ""),
            "parabola": MODEL_LABELS["parabola"] + f" (f_x {fmt_f(rec.get('focal_length_x_m'))} m, "
                                                   f"f_y {fmt_f(rec.get('focal_length_y_m'))} m)",
            "higher_order": MODEL_LABELS["higher_order"]}
    out = {}
    for model, m in maps.items():
        r = rec.get("slope_rms_mrad", {}).get(model) or m.rms_mrad
        out[model] = (f"{head[model]}\nslope error RMS x {r['x']:.3f}, y {r['y']:.3f}, "
                      f"magnitude {r['magnitude']:.3f} mrad")
    return out


def write_slope_error_maps(result, out_dir: str | Path, *, vmax_mrad: float = 5.0, arrow_step_px: int | None = None,
                           cmap: str = "jet", separate: bool = False, dpi: int = 110) -> list[Path]:
    """Draw a reprocessed dump's slope-error maps (the paper's Figs. 8-10) as PNG.

    Parameters
    ----------
    result : ReprocessResult
        From :func:`~sofast_station.reanalysis.reprocess.reprocess_dump` (it holds the analysis).
    out_dir : str or Path
        Folder for ``<dump stem>.png`` (three panels), or with *separate* ``<dump stem>-design.png``,
        ``-parabola.png`` and ``-higher_order.png``.
    vmax_mrad : float
        Top of the colour scale, mrad (the paper: 5); larger errors show in the top colour.
    arrow_step_px : int, optional
        Arrows on every Nth camera row and column (default: :func:`auto_arrow_step`).
    cmap : str
        Matplotlib colour map; ``jet`` runs blue to maroon like the paper's.
    separate : bool
        Three files instead of one with three panels.
    dpi : int

    Returns
    -------
    list of Path
        The files written.

    Raises
    ------
    ReportError
        When the analysis refused the capture (nothing to draw).
    """
    from matplotlib.figure import Figure

    if result.analysis is None:
        raise ReportError(f"cannot draw {result.path}: the analysis refused the capture "
                          f"({'; '.join(result.record.get('reasons', []))})")
    if not (math.isfinite(vmax_mrad) and vmax_mrad > 0):
        raise ValueError(f"vmax_mrad must be a positive number of mrad, got {vmax_mrad}")
    maps = slope_error_maps(result.analysis, arrow_step_px)
    titles = _titles(result, maps)
    rec = result.record
    step = maps["design"].arrow_step_px
    overrides = result.overrides.to_dict()
    lines = [f"Facet {rec.get('serial')} ({rec.get('facet')}), measured {rec.get('time')}",
             f"slope error, colour 0 to {vmax_mrad:g} mrad, arrows every {step}th pixel",
             f"reprocessed by sofast-station {__version__} from {Path(result.path).name}"
             + (" with " + ", ".join(f"{k} = {v}" for k, v in overrides.items()) if overrides else "")]
    out_dir = Path(out_dir)
    stem = Path(result.path).stem
    written = []
    if separate:
        for model in MODELS:
            fig = Figure(figsize=(7.0, 6.2), layout="constrained")
            ax = fig.subplots()
            image, q = _draw_map(fig, ax, maps[model], titles[model], vmax_mrad, cmap)
            fig.colorbar(image, ax=ax, label="slope error magnitude (mrad)", extend="max", shrink=0.85)
            _arrow_key(q, 0.6)
            fig.suptitle("\n".join(lines), fontsize=8.5)
            written.append(savefig_atomic(fig, out_dir / f"{stem}-{model}.png", dpi))
    else:
        fig = Figure(figsize=(18.0, 6.6), layout="constrained")
        axes = fig.subplots(1, 3)
        image = q = None
        for ax, model in zip(axes, MODELS):
            image, q = _draw_map(fig, ax, maps[model], titles[model], vmax_mrad, cmap)
        fig.colorbar(image, ax=list(axes), label="slope error magnitude (mrad)", extend="max", shrink=0.85)
        _arrow_key(q, 0.84)
        fig.suptitle(f"{lines[0]}: {lines[1]}\n{lines[2]}", fontsize=10)
        written.append(savefig_atomic(fig, out_dir / f"{stem}.png", dpi))
    log.info("slope-error maps of %s: %s", result.path, ", ".join(str(p) for p in written))
    return written
