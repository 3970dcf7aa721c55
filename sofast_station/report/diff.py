"""The difference of two measurements of one facet type on their common grid (``report diff A B``).

Both measurements' slopes are averaged into the same cells (facet frame); the difference B - A is shown
as angles (mrad) in x and y, its magnitude, and the height difference integrated from it (µm). Each
measurement's own tilt (its boresight) is removed first: the mean slope difference is subtracted, so a
facet placed a little differently does not show as a shape change.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from ..errors import ReportError
from ..measure.heights import grid_slopes, integrate_slopes
from ..result.formatting import figure_decimals, figure_text, with_u
from ..result.record import figure_uncertainty, figure_value
from ._common import savefig_atomic
from .maps import draw_field


def common_grid_difference(a, b, cells_across: int = 120) -> dict:
    """B - A on the common grid: ``e_x_mrad``, ``e_y_mrad``, ``height_um``, ``extent_m``, ``cell_m``, ``n_cells``."""
    pa, pb = a.analysis.points_facet_m, b.analysis.points_facet_m
    x0 = max(float(pa[0].min()), float(pb[0].min()))
    x1 = min(float(pa[0].max()), float(pb[0].max()))
    y0 = max(float(pa[1].min()), float(pb[1].min()))
    y1 = min(float(pa[1].max()), float(pb[1].max()))
    if not (x1 > x0 and y1 > y0):
        raise ReportError("the two measurements do not overlap on the facet: are they the same facet type?")

    def spacing(p):
        return math.sqrt(max(float(np.ptp(p[0])) * float(np.ptp(p[1])), 1e-18) / p.shape[1])

    cell = max(max(x1 - x0, y1 - y0) / cells_across, 1.5 * spacing(pa), 1.5 * spacing(pb))
    ext = (x0, x1, y0, y1)
    # each cell's mean at its centre, not at its points' centroid: A's and B's pixels fall differently in the
    # cells, and a dish's slope changes by 0.1 mrad per mm (the same dish on two pixel lattices differed by
    # 0.07 mrad RMS and 0.45 at the rim uncentred, 0.01 and 0.27 centred)
    ga = grid_slopes(pa[0], pa[1], a.analysis.slopes[0], a.analysis.slopes[1], cell, extent_m=ext, centred=True)
    gb = grid_slopes(pb[0], pb[1], b.analysis.slopes[0], b.analysis.slopes[1], cell, extent_m=ext, centred=True)
    dx = np.arctan(gb["s_x"]) - np.arctan(ga["s_x"])
    dy = np.arctan(gb["s_y"]) - np.arctan(ga["s_y"])
    dx -= np.nanmean(dx)
    dy -= np.nanmean(dy)
    h = integrate_slopes(np.tan(dx), np.tan(dy), cell)
    return {"e_x_mrad": 1e3 * dx, "e_y_mrad": 1e3 * dy, "height_um": 1e6 * h, "extent_m": ga["extent_m"],
            "cell_m": cell, "n_cells": int(np.count_nonzero(np.isfinite(dx) & np.isfinite(dy)))}


def check_same_design(a, b) -> None:
    """ReportError unless A and B are measurements of one facet type (the same design name and focal
    length): a dish against a heliostat facet differs by their designs, which is no shape change."""
    da, db = getattr(a, "design", None), getattr(b, "design", None)
    name_a, name_b = (getattr(d, "name", None) or r.record.get("facet") for d, r in ((da, a), (db, b)))
    f_a, f_b = (getattr(d, "focal_length_m", None) for d in (da, db))
    same_f = f_a is None or f_b is None or math.isclose(f_a, f_b, rel_tol=1e-6)
    if name_a != name_b or not same_f:
        raise ReportError(f"A is a {name_a} facet (f {f_a:g} m) and B a {name_b} facet (f {f_b:g} m): their "
                          "difference is that of their designs, not a change of shape. Compare two measurements of "
                          "one facet type, or give --any-design to draw it anyway")


def _label(m) -> str:
    """A measurement in a title: its file (not its whole path), serial and time."""
    return f"{Path(m.path).name} ({m.record.get('serial')}, {str(m.record.get('time', ''))[:19].replace('T', ' ')})"


def diff_figures(a, b, d: dict) -> list[tuple[str, str, str, str, str]]:
    """Rows (figure, A, B, B - A, unit) of the two measurements' reported figures and of the map's
    difference, each ``value ± U`` where the records carry U, as every screen writes them
    (:func:`~sofast_station.result.formatting.figure_text`)."""
    rows = []
    for key, label, unit in (("focal_length_x_m", "focal length f_x", "m"),
                             ("focal_length_y_m", "focal length f_y", "m"),
                             ("twist_mrad_per_m", "twist", "mrad/m"),
                             ("slope_rms_mrad.design.magnitude", "slope error RMS vs design", "mrad"),
                             ("slope_rms_mrad.parabola.magnitude", "slope error RMS vs parabola", "mrad")):
        va, vb = figure_value(a.record, key), figure_value(b.record, key)
        if va is None and vb is None:
            continue
        ua, ub = figure_uncertainty(a.record, key), figure_uncertainty(b.record, key)
        u_diff = math.hypot(ua, ub) if ua is not None and ub is not None else None
        diff = None if va is None or vb is None else vb - va
        rows.append((label, figure_text(a.record, key), figure_text(b.record, key),
                     with_u(diff, u_diff, decimals=figure_decimals(key), sign=True), unit))
    rms = {k: float(np.sqrt(np.nanmean(d[k] ** 2))) for k in ("e_x_mrad", "e_y_mrad", "height_um")}
    rows += [("slope difference x, RMS over the common grid", "", "", f"{rms['e_x_mrad']:.3f}", "mrad"),
             ("slope difference y, RMS over the common grid", "", "", f"{rms['e_y_mrad']:.3f}", "mrad"),
             ("height difference, RMS over the common grid", "", "", f"{rms['height_um']:.2f}", "µm")]
    return rows


def diff_text(a, b, rows) -> str:
    """The figures of :func:`diff_figures` as an aligned table."""
    head = ("figure", "A", "B", "B - A", "unit")
    widths = [max(len(str(r[i])) for r in [head, *rows]) for i in range(5)]
    line = "  ".join
    out = [f"A: {_label(a)}", f"B: {_label(b)}",
           line([head[0].ljust(widths[0])] + [h.rjust(w) for h, w in zip(head[1:4], widths[1:4])] + [head[4]])]
    out += [line([r[0].ljust(widths[0])] + [str(v).rjust(w) for v, w in zip(r[1:4], widths[1:4])] + [r[4]])
            for r in rows]
    return "\n".join(out)


def write_diff(a, b, out_path: Path, dpi: int = 100, d: dict | None = None) -> Path:
    d = common_grid_difference(a, b) if d is None else d
    fig = Figure(figsize=(12.5, 10.5), layout="constrained")
    axes = fig.subplots(2, 2).ravel()
    rms = {k: float(np.sqrt(np.nanmean(d[k] ** 2))) for k in ("e_x_mrad", "e_y_mrad", "height_um")}
    for ax, axis in zip(axes[:2], "xy"):
        draw_field(fig, ax, d[f"e_{axis}_mrad"], d["extent_m"],
                   f"slope difference {axis}, B - A (RMS {rms[f'e_{axis}_mrad']:.3f} mrad)", "mrad", signed=True)
    draw_field(fig, axes[2], np.hypot(d["e_x_mrad"], d["e_y_mrad"]), d["extent_m"], "slope difference magnitude",
               "mrad", signed=False)
    draw_field(fig, axes[3], d["height_um"], d["extent_m"], f"height difference B - A (RMS {rms['height_um']:.2f} µm)",
               "µm", signed=True)
    fig.suptitle(f"B - A: {b.record.get('serial')} minus {a.record.get('serial')}, on a common grid of "
                 f"{d['n_cells']} cells of {1e3 * d['cell_m']:.1f} mm, mean tilt removed\n"
                 f"A: {_label(a)}\nB: {_label(b)}", fontsize=10)
    return savefig_atomic(fig, Path(out_path), dpi)
