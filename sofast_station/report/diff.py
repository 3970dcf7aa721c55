"""The difference of two measurements of one facet type on their common grid (``report diff A B``).

Both measurements' slopes are averaged into the same cells (facet frame); the difference B - A is shown
as angles (mrad) in x and y, its magnitude, and the height difference integrated from it (um). Each
measurement's own tilt (its boresight) is removed first: the mean slope difference is subtracted, so a
facet placed a little differently does not show as a shape change.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..errors import ReportError
from ._common import savefig_atomic
from .maps import draw_field


def common_grid_difference(a, b, cells_across: int = 120) -> dict:
    """B - A on the common grid: ``e_x_mrad``, ``e_y_mrad``, ``height_um``, ``extent_m``, ``cell_m``, ``n_cells``."""
    from ..measure.heights import grid_slopes, integrate_slopes

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
    ga = grid_slopes(pa[0], pa[1], a.analysis.slopes[0], a.analysis.slopes[1], cell, extent_m=ext)
    gb = grid_slopes(pb[0], pb[1], b.analysis.slopes[0], b.analysis.slopes[1], cell, extent_m=ext)
    dx = np.arctan(gb["s_x"]) - np.arctan(ga["s_x"])
    dy = np.arctan(gb["s_y"]) - np.arctan(ga["s_y"])
    dx -= np.nanmean(dx)
    dy -= np.nanmean(dy)
    h = integrate_slopes(np.tan(dx), np.tan(dy), cell)
    return {"e_x_mrad": 1e3 * dx, "e_y_mrad": 1e3 * dy, "height_um": 1e6 * h, "extent_m": ga["extent_m"],
            "cell_m": cell, "n_cells": int(np.count_nonzero(np.isfinite(dx) & np.isfinite(dy)))}


def write_diff(a, b, out_path: Path, dpi: int = 100) -> Path:
    from matplotlib.figure import Figure

    d = common_grid_difference(a, b)
    fig = Figure(figsize=(16.0, 9.5), layout="constrained")
    axes = fig.subplots(2, 2).ravel()
    rms = {k: float(np.sqrt(np.nanmean(d[k] ** 2))) for k in ("e_x_mrad", "e_y_mrad", "height_um")}
    for ax, axis in zip(axes[:2], "xy"):
        draw_field(fig, ax, d[f"e_{axis}_mrad"], d["extent_m"],
                   f"slope difference {axis}, B - A (RMS {rms[f'e_{axis}_mrad']:.3f} mrad)", "mrad", signed=True)
    draw_field(fig, axes[2], np.hypot(d["e_x_mrad"], d["e_y_mrad"]), d["extent_m"], "slope difference magnitude",
               "mrad", signed=False)
    draw_field(fig, axes[3], d["height_um"], d["extent_m"], f"height difference B - A (RMS {rms['height_um']:.2f} um)",
               "um", signed=True)
    fig.suptitle(f"A: {a.path} ({a.record.get('serial')}, {a.record.get('time')})\n"
                 f"B: {b.path} ({b.record.get('serial')}, {b.record.get('time')}); common grid of {d['n_cells']} cells "
                 f"of {1e3 * d['cell_m']:.1f} mm, mean tilt removed", fontsize=10)
    return savefig_atomic(fig, Path(out_path), dpi)
