"""Slope-error maps for the process engineer (the method paper's Figs. 8-10).

For each model (design, fitted parabola, higher order) the colour is the magnitude of the slope error
sqrt(e_x^2 + e_y^2) in mrad on one sequential, perceptually ordered scale (viridis) from 0 to the 99th
percentile of the data rounded up (a fixed top such as the paper's 5 mrad on request), drawn in facet
coordinates (x and y in metres, +y up); arrows show the error's direction and size, averaged on a regular
grid of about 22 cells across and scaled so they never overlap, with a round-valued length key.

The detail page of one model (:func:`write_detail_maps`) adds e_x and e_y on a diverging scale centred on
zero (cool-warm), the height error in micrometres integrated from the residual slopes by least squares
(:mod:`sofast_station.measure.heights`) and the local focal power minus the design's. The panel titles carry the RMS of
e_x, e_y and the magnitude, which are the reported figures. The map is a nearest-pixel resampling of the
per-pixel residuals onto a regular facet grid as fine as the camera's pixels on the facet, so every
coloured cell shows one measured pixel's value.

The module uses Matplotlib's object-oriented API with the Agg canvas (no pyplot, no display), so it runs
headless and in worker threads; every picture is written to a temporary file and renamed into place.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import ReportError
from ..measure.fit import monomials
from ..measure.heights import curvature_map, grid_slopes, integrate_slopes, slope_differences
from ..result.formatting import figure_text
from ._common import savefig_atomic
from .summary import MODELS, figure_lines

log = logging.getLogger(__name__)

#: The three models of the paper's Figs. 8-10 (:data:`MODELS`, in order) with their panel labels.
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
    terms = monomials((x - x0) / s, (y - y0) / s, 3)
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
    gterms = monomials((gxx.ravel() - x0) / s, (gyy.ravel() - y0) / s, 3)
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


#: Colour maps: sequential for a magnitude, diverging (light at zero) for a signed value. Both are
#: perceptually ordered (viridis; Moreland's cool-warm); never jet, whose bright bands invent edges.
SEQUENTIAL_CMAP = "viridis"
DIVERGING_CMAP = "coolwarm"

#: Robust colour scales: this percentile of the data (|value| for a signed map) tops the scale.
ROBUST_PERCENTILE = 99.0

#: Arrows across the facet's longer side on the drawn (decimated) grid.
ARROWS_ACROSS = 22


def nice_ceil(v: float) -> float:
    """The smallest of 1, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k not below *v* (a readable scale top)."""
    if not (math.isfinite(v) and v > 0):
        return 1.0
    k = math.floor(math.log10(v))
    for m in (1, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10):
        if m * 10 ** k >= v * (1 - 1e-12):
            return m * 10 ** k
    return 10 ** (k + 1)


def nice_round(v: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above *v* (a length key)."""
    if not (math.isfinite(v) and v > 0):
        return 1.0
    k = math.floor(math.log10(v))
    for m in (5, 2, 1):
        if m * 10 ** k <= v * (1 + 1e-12):
            return m * 10 ** k
    return 10 ** k


def robust_top(values, signed: bool = False, percentile: float = ROBUST_PERCENTILE) -> float:
    """Top of a colour scale: the *percentile* of the finite values (of |values| when *signed*), rounded
    up to a readable number, so a few wild pixels do not flatten the picture."""
    a = np.asarray(values, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size == 0:
        return 1.0
    return nice_ceil(float(np.percentile(np.abs(a) if signed else a, percentile)))


def decimated_arrows(x_m, y_m, u, v, across: int = ARROWS_ACROSS):
    """Mean of (u, v) in a regular grid of about *across* cells along the longer side: arrow positions
    (cell centres with data), vectors and the cell size (metres)."""
    x = np.asarray(x_m, float)
    y = np.asarray(y_m, float)
    cell = max(float(np.ptp(x)), float(np.ptp(y)), 1e-9) / max(int(across), 1)
    g = grid_slopes(x, y, u, v, cell, extent_m=(float(x.min()) - 0.5 * cell, float(x.min()) + cell * (across + 1),
                                                float(y.min()) - 0.5 * cell, float(y.min()) + cell * (across + 1)))
    gx, gy = np.meshgrid(g["x_m"], g["y_m"])
    ok = np.isfinite(g["s_x"])
    return gx[ok], gy[ok], g["s_x"][ok], g["s_y"][ok], cell


def scaled_arrows(x_m, y_m, u, v):
    """:func:`decimated_arrows` ready to draw: positions, vectors, the cell size (metres) and the reference
    length *ref* (the 95th-percentile magnitude) that is drawn 0.9 cell long. The few longest (beyond
    2 x *ref*) are shortened to 2 x *ref*, so they cannot tangle."""
    ax_, ay_, au, av, cell = decimated_arrows(x_m, y_m, u, v)
    mags = np.hypot(au, av)
    ref = float(np.percentile(mags, 95)) if mags.size else 1.0
    ref = ref if ref > 0 else 1.0
    long = mags > 2 * ref
    au, av = (np.where(long, w * 2 * ref / np.where(long, mags, 1.0), w) for w in (au, av))
    return ax_, ay_, au, av, cell, ref


def draw_arrows(ax, x_m, y_m, u, v, unit: str = "mrad", key_value: float | None = None, color: str = "black"):
    """Arrows of (u, v) on a decimated grid, scaled so the 95th-percentile arrow is 0.9 cell long (they
    never tangle), with a length key of a round value inside the map's corner."""
    # lazy: matplotlib costs ~650 ms CPU; the monitor imports this module for the maps' data (drawn with OpenCV)
    from matplotlib import patheffects

    ax_, ay_, au, av, cell, ref = scaled_arrows(x_m, y_m, u, v)
    scale = ref / (0.9 * cell)                           # data units per metre of arrow
    q = ax.quiver(ax_, ay_, au, av, color=color, angles="xy", scale_units="xy", scale=scale, width=0.005,
                  headwidth=3.5, headlength=4.0, headaxislength=3.5, pivot="middle", zorder=3)
    q.set_path_effects([patheffects.withStroke(linewidth=1.5, foreground="white")])
    key = key_value or nice_round(ref)
    # The key inside the map's own corner, on a white box: under the axes it was cut off by the page's edge
    # or ran into the x label.
    qk = ax.quiverkey(q, 0.05, 0.05, key, f"arrow: {key:g} {unit}", labelpos="E", coordinates="axes", color=color,
                      fontproperties={"size": 9}, zorder=5)
    qk.text.set_bbox({"facecolor": "white", "alpha": 0.85, "edgecolor": "0.6", "boxstyle": "round,pad=0.2"})
    return q


def draw_field(fig, ax, image, extent, title: str, label: str, *, signed: bool, top: float | None = None,
               cmap: str | None = None, centre: float = 0.0):
    """One map: a signed value on a diverging scale centred on *centre* (+- the robust top), or a
    magnitude on a sequential scale from 0; a colour bar with *label*."""
    data = np.asarray(image, float)
    if top is None:
        top = robust_top(data - centre if signed else data, signed=signed)
    if signed:
        vmin, vmax, cmap = centre - top, centre + top, cmap or DIVERGING_CMAP
    else:
        vmin, vmax, cmap = 0.0, top, cmap or SEQUENTIAL_CMAP
    im = ax.imshow(data, extent=extent, origin="lower", cmap=cmap, vmin=vmin, vmax=vmax, interpolation="nearest")
    ax.set_xlabel("facet x (m)")
    ax.set_ylabel("facet y (m)")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9.5)
    finite = data[np.isfinite(data)]
    over = finite.size and (np.max(np.abs(finite - centre)) > top if signed else np.max(finite) > top)
    fig.colorbar(im, ax=ax, label=label, shrink=0.85, extend=("both" if signed else "max") if over else "neither")
    return im


def _draw_map(fig, ax, m: SlopeErrorMap, title: str, vmax_mrad: float, cmap: str):
    image = ax.imshow(m.magnitude_mrad, extent=m.extent_m, origin="lower", cmap=cmap, vmin=0.0, vmax=vmax_mrad,
                      interpolation="nearest")
    q = draw_arrows(ax, m.arrow_x_m, m.arrow_y_m, m.arrow_ex_mrad, m.arrow_ey_mrad)
    ax.set_xlabel("facet x (m)")
    ax.set_ylabel("facet y (m)")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=9.5)
    return image, q


# -- the engineer's maps of one model -----------------------------------------------------------------
@dataclass
class DetailMaps:
    """Gridded maps of one model's residuals, ready to draw (facet frame, +y up).

    Attributes
    ----------
    model : str
    extent_m : tuple
        Grid edges (x_min, x_max, y_min, y_max), metres.
    cell_m : float
    e_x_mrad, e_y_mrad, magnitude_mrad : (ny, nx) arrays
        Mean residual angles per cell, mrad (NaN off the facet).
    height_um : (ny, nx) array
        Height error against the model, integrated from the residual slopes, micrometres, zero mean.
    kappa_dev_per_m : (ny, nx) array
        Local focal power (mean of kappa_x and kappa_y from the measured slopes) minus the design's, 1/m.
    points : tuple
        (x_m, y_m, e_x_mrad, e_y_mrad) per measured point, for arrows.
    """

    model: str
    extent_m: tuple
    cell_m: float
    e_x_mrad: np.ndarray
    e_y_mrad: np.ndarray
    magnitude_mrad: np.ndarray
    height_um: np.ndarray
    kappa_dev_per_m: np.ndarray
    points: tuple

    @property
    def height_rms_um(self) -> float:
        return float(np.sqrt(np.nanmean(self.height_um ** 2)))


def detail_maps(x_m, y_m, slopes, residuals_mrad: dict, model: str = "parabola", design_focal_length_m=None,
                cells_across: int = 160) -> DetailMaps:
    """Residual, height-error and curvature maps of one model on a regular grid (pure arrays in).

    Parameters
    ----------
    x_m, y_m : (N,) arrays
        Facet-frame point positions, metres.
    slopes : (2, N) array
        Measured slopes.
    residuals_mrad : dict
        Model -> (e_x, e_y) angle residuals, mrad.
    model : str
    design_focal_length_m : float, optional
        For the curvature map's reference (kappa_design = 1 / f); 0 when None.
    cells_across : int
        Grid cells along the facet's longer side.
    """
    if model not in residuals_mrad:
        raise ReportError(f"no residuals for model {model!r} (have {', '.join(residuals_mrad)})")
    x = np.asarray(x_m, float)
    y = np.asarray(y_m, float)
    ex, ey = (np.asarray(e, float) for e in residuals_mrad[model])
    # no finer than 1.5 measured points' spacing, so every cell holds a point (no holes between cells)
    spacing = math.sqrt(max(float(np.ptp(x)) * float(np.ptp(y)), 1e-18) / max(x.size, 1))
    cell = max(max(float(np.ptp(x)), float(np.ptp(y)), 1e-9) / max(int(cells_across), 8), 1.5 * spacing)
    g = grid_slopes(x, y, ex, ey, cell)
    extent = g["extent_m"]
    dsx, dsy = slope_differences(slopes, (ex, ey))
    # each cell's mean at its centre, not its points' centroid (heights.centred_slopes): the height and the
    # curvature are differences between cells, and uncentred means beat with the pixel lattice
    d = grid_slopes(x, y, dsx, dsy, cell, extent_m=extent, centred=True)
    h = integrate_slopes(d["s_x"], d["s_y"], cell)
    s = np.asarray(slopes, float)
    m = grid_slopes(x, y, s[0], s[1], cell, extent_m=extent, centred=True)
    k = curvature_map(m["s_x"], m["s_y"], cell)["mean"]
    k_design = 0.0 if not design_focal_length_m else 1.0 / float(design_focal_length_m)
    return DetailMaps(model, extent, cell, g["s_x"], g["s_y"], np.hypot(g["s_x"], g["s_y"]), 1e6 * h,
                      k - k_design, (x, y, ex, ey))


def draw_detail(fig, axes, dm: DetailMaps, *, which=("e_x", "e_y", "magnitude", "height", "curvature")) -> None:
    """Draw the chosen maps of *dm* into *axes* (one axis each, in the order of *which*)."""
    label = MODEL_LABELS.get(dm.model, dm.model).replace("compared with the ", "vs ")
    for ax, name in zip(axes, which):
        if name == "e_x":
            draw_field(fig, ax, dm.e_x_mrad, dm.extent_m, f"slope error x, {label}", "e_x (mrad)", signed=True)
        elif name == "e_y":
            draw_field(fig, ax, dm.e_y_mrad, dm.extent_m, f"slope error y, {label}", "e_y (mrad)", signed=True)
        elif name == "magnitude":
            draw_field(fig, ax, dm.magnitude_mrad, dm.extent_m, f"slope error magnitude, {label}",
                       "|e| (mrad)", signed=False)
            x, y, ex, ey = dm.points
            draw_arrows(ax, x, y, ex, ey)
        elif name == "height":
            draw_field(fig, ax, dm.height_um, dm.extent_m,
                       f"height error, {label}\nRMS {dm.height_rms_um:.2f} µm (from slopes, least squares)",
                       "height error (µm)", signed=True)
        elif name == "curvature":
            draw_field(fig, ax, dm.kappa_dev_per_m, dm.extent_m, "local focal power minus design\n"
                       "(kappa_x + kappa_y) / 2 - 1/f", "(1/m)", signed=True)
        else:
            raise ValueError(f"unknown map {name!r}")


def write_detail_maps(result, out_path: str | Path, model: str = "parabola", dpi: int = 100) -> Path:
    """The engineer's page of one model: e_x and e_y (diverging), magnitude with arrows, height error
    (µm) and local focal power, for a reprocessed dump or an OpenCSP import (anything with ``analysis``,
    ``record`` and optionally ``design``)."""
    # lazy: matplotlib costs ~650 ms CPU; the monitor imports this module for the maps' data (drawn with OpenCV)
    from matplotlib.figure import Figure

    a = getattr(result, "analysis", None)
    if a is None:
        raise ReportError(f"cannot draw {getattr(result, 'path', '')}: the analysis refused the capture")
    f_design = getattr(getattr(result, "design", None), "focal_length_m", None)
    dm = detail_maps(a.points_facet_m[0], a.points_facet_m[1], a.slopes, a.residuals_mrad, model, f_design)
    fig = Figure(figsize=(16.5, 10.0), layout="constrained")
    axes = fig.subplots(2, 3).ravel()
    draw_detail(fig, axes[:5], dm)
    rec = getattr(result, "record", {}) or {}
    axes[5].axis("off")
    axes[5].text(0.0, 1.0, figure_lines(rec), va="top", ha="left", family="monospace", fontsize=9,
                 transform=axes[5].transAxes)
    fig.suptitle(f"Facet {rec.get('serial', '?')} ({rec.get('facet', '?')}), measured {rec.get('time', '?')}: "
                 f"maps {MODEL_LABELS.get(model, model)}", fontsize=11)
    return savefig_atomic(fig, Path(out_path), dpi)


def _titles(result, maps: dict) -> dict:
    """Each model map's title: the model, its focal lengths and slope RMS, each ``± U`` (expanded, k = 2,
    said in the page's title) where the record carries it: every figure shown is a measurement result."""
    rec = result.record
    f_design = getattr(result.design, "focal_length_m", None)

    def fmt_f(key):
        return figure_text(rec, key, missing="inf")

    head = {"design": MODEL_LABELS["design"] + (f" (f {f_design:g} m)" if f_design else ""),
            "parabola": MODEL_LABELS["parabola"] + f"\nf_x {fmt_f('focal_length_x_m')} m, "
                                                   f"f_y {fmt_f('focal_length_y_m')} m",
            "higher_order": MODEL_LABELS["higher_order"]}
    out = {}
    for model, m in maps.items():
        shown = rec if (rec.get("slope_rms_mrad") or {}).get(model) else {"slope_rms_mrad": {model: m.rms_mrad}}
        x, y, mag = (figure_text(shown, f"slope_rms_mrad.{model}.{a}") for a in ("x", "y", "magnitude"))
        out[model] = f"{head[model]}\nslope error RMS (mrad) x {x}, y {y},\nmagnitude {mag}"
    return out


def write_slope_error_maps(result, out_dir: str | Path, *, vmax_mrad: float | None = None,
                           arrow_step_px: int | None = None, cmap: str = SEQUENTIAL_CMAP, separate: bool = False,
                           dpi: int = 110) -> list[Path]:
    """Draw a reprocessed dump's slope-error maps (the paper's Figs. 8-10) as PNG.

    Parameters
    ----------
    result : ReprocessResult
        From :func:`~sofast_station.reanalysis.reprocess.reprocess_dump` (it holds the analysis).
    out_dir : str or Path
        Folder for ``<dump stem>.png`` (three panels), or with *separate* ``<dump stem>-design.png``,
        ``-parabola.png`` and ``-higher_order.png``.
    vmax_mrad : float, optional
        Top of the colour scale, mrad (the paper: 5); larger errors show in the top colour. By default
        the 99th percentile of the three panels' magnitudes, rounded up (one scale for all three).
    arrow_step_px : int, optional
        Arrows on every Nth camera row and column (default: :func:`auto_arrow_step`).
    cmap : str
        Matplotlib colour map (sequential, perceptually ordered: viridis by default).
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
    # lazy: matplotlib costs ~650 ms CPU; the monitor imports this module for the maps' data (drawn with OpenCV)
    from matplotlib.figure import Figure

    if result.analysis is None:
        raise ReportError(f"cannot draw {result.path}: the analysis refused the capture "
                          f"({'; '.join(result.record.get('reasons', []))})")
    if vmax_mrad is not None and not (math.isfinite(vmax_mrad) and vmax_mrad > 0):
        raise ValueError(f"vmax_mrad must be a positive number of mrad, got {vmax_mrad}")
    maps = slope_error_maps(result.analysis, arrow_step_px)
    if vmax_mrad is None:
        vmax_mrad = robust_top(np.concatenate([m.magnitude_mrad.ravel() for m in maps.values()]))
    titles = _titles(result, maps)
    rec = result.record
    overrides = result.overrides.to_dict()
    lines = [f"Facet {rec.get('serial')} ({rec.get('facet')}), measured {rec.get('time')}",
             f"slope error, colour 0 to {vmax_mrad:g} mrad (99th percentile), arrows: mean error on a "
             f"{ARROWS_ACROSS}-cell grid" + (f"; ± U: expanded uncertainty, k = {rec['coverage_factor']}"
                                             if rec.get("coverage_factor") else ""),
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
            fig.suptitle("\n".join(lines), fontsize=8.5)
            written.append(savefig_atomic(fig, out_dir / f"{stem}-{model}.png", dpi))
    else:
        fig = Figure(figsize=(18.0, 6.6), layout="constrained")
        axes = fig.subplots(1, 3)
        image = q = None
        for ax, model in zip(axes, MODELS):
            image, q = _draw_map(fig, ax, maps[model], titles[model], vmax_mrad, cmap)
        fig.colorbar(image, ax=list(axes), label="slope error magnitude (mrad)", extend="max", shrink=0.85)
        fig.suptitle(f"{lines[0]}: {lines[1]}\n{lines[2]}", fontsize=10)
        written.append(savefig_atomic(fig, out_dir / f"{stem}.png", dpi))
    log.info("slope-error maps of %s: %s", result.path, ", ".join(str(p) for p in written))
    return written
