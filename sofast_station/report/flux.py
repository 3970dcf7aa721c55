"""Flux maps: the irradiance a measured facet puts on the target plane, beside its design's.

Two panels on one colour scale (W/m^2, at the stated DNI and reflectivity): the measured facet's flux map
and the design facet's, each with the receiver aperture drawn (white), the aim point (+), the beam's
centroid (x) and the circle holding 90 % of the power about it (dashed). The title carries the sun
shape, DNI, reflectivity, incidence angle and slant range; each panel's title its intercept factor and
90 % radius, and the measured panel also the centroid offset and the power ratio against the design.

Axes are the target plane's (docs/conventions.md, "Optics"): x is the facet's x made perpendicular to the
central reflected ray, in millimetres (metres for spots larger than a metre) from the aim point.
"""

from __future__ import annotations

import logging
from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from ..errors import ReportError
from ..result.formatting import with_u
from ._common import savefig_atomic

log = logging.getLogger(__name__)


def _fmt(value, fmt: str, u=None) -> str:
    """*value* with `` ± U`` (k = 2) by GUM's rule (:func:`~sofast_station.result.formatting.with_u`) when its
    uncertainty *u* is known, else to the decimals of *fmt* (``"{:.4f}"``)."""
    return with_u(value, u, decimals=int(fmt.split(".")[1].rstrip("f}")))


def draw_flux_maps(res, title: str = "") -> Figure:
    """A Matplotlib figure (Agg) of the measured and the design flux maps of a FacetOptics result."""
    scene = res.scene
    half = scene.grid_half_width_m
    scale, unit, lf = (1.0, "m", "{:.3f}") if half > 1.0 else (1000.0, "mm", "{:.1f}")
    extent = [-half * scale, half * scale, -half * scale, half * scale]
    vmax = float(max(res.measured.flux_w_m2.max(), res.design.flux_w_m2.max())) or 1.0
    fig = Figure(figsize=(13.0, 7.0), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True, sharey=True)
    cond = res.figures["conditions"]
    sun = cond["sun"]
    sun_text = {"pillbox": lambda s: f"pillbox sun {s['half_angle_mrad']:.2f} mrad",
                "gaussian": lambda s: f"Gaussian sun sigma {s['sigma_mrad']:.2f} mrad",
                "buie": lambda s: f"Buie sun CSR {s['csr']:.3f}"}[sun["shape"]](sun)
    fig.suptitle(f"{title}\n{sun_text}, DNI {cond['dni_w_m2']:g} W/m², reflectivity {cond['reflectivity']:g}, "
                 f"incidence {cond['incidence_angle_deg']:g}°, target at {cond['slant_range_m']:.3f} m "
                 f"({cond['rays']:,} rays)".strip())
    f = res.figures
    u_r90 = None if f.get("spot_radius_m_U") is None else f["spot_radius_m_U"] * scale   # ± U (k = 2) if known
    u_off = (f.get("centroid_offset_mrad_U") or {}).get("magnitude")
    panels = ((res.measured, "measured facet",
               f"intercept {_fmt(f['intercept'], '{:.4f}', f.get('intercept_U'))}, r90 "
               f"{_fmt(None if f['spot_radius_m'] is None else f['spot_radius_m'] * scale, lf, u_r90)} {unit} "
               f"({_fmt(f['spot_radius_mrad'], '{:.2f}', f.get('spot_radius_mrad_U'))} mrad),\n"
               f"centroid {_fmt(f['centroid_offset_mrad']['magnitude'], '{:.3f}', u_off)} mrad off aim, "
               f"power / design's {_fmt(f['power_ratio_vs_design'], '{:.4f}', f.get('power_ratio_vs_design_U'))};\n"
               f"analytic r90 "
               f"{_fmt(f['analytic_spot_radius_m'] * scale, lf)} {unit}"),
              (res.design, "design facet",
               f"intercept {_fmt(f['design']['intercept'], '{:.4f}')}, r90 "
               f"{_fmt(None if f['design']['spot_radius_m'] is None else f['design']['spot_radius_m'] * scale, lf)}"
               f" {unit}\nanalytic r90 {_fmt(f['design']['analytic_spot_radius_m'] * scale, lf)} {unit}"))
    image = None
    for ax, (trace, label, text) in zip(axes, panels):
        image = ax.imshow(trace.flux_w_m2, origin="lower", extent=extent, cmap="inferno", vmin=0.0, vmax=vmax,
                          interpolation="nearest")
        ap = scene.aperture
        if ap.shape == "circle":
            ax.add_patch(Circle((0, 0), ap.radius_m * scale, fill=False, ec="white", lw=1.4, label="aperture"))
        else:
            ax.add_patch(Rectangle((-ap.width_m / 2 * scale, -ap.height_m / 2 * scale), ap.width_m * scale,
                                   ap.height_m * scale, fill=False, ec="white", lw=1.4, label="aperture"))
        fg = trace.figures
        cx, cy = fg["centroid_m"]["x"] * scale, fg["centroid_m"]["y"] * scale
        ax.plot([0], [0], "+", color="cyan", ms=12, mew=1.5, label="aim point")
        ax.plot([cx], [cy], "x", color="lime", ms=9, mew=1.5, label="centroid")
        if fg["spot_radius_m"] is not None:
            ax.add_patch(Circle((cx, cy), fg["spot_radius_m"] * scale, fill=False, ec="lime", lw=1.0, ls="--",
                                label="90 % of the power"))
        ax.set_title(f"{label}: {text}", fontsize=9.5)
        ax.set_xlabel(f"target x ({unit})")
        ax.set_aspect("equal")
    axes[0].set_ylabel(f"target y ({unit})")
    axes[0].legend(loc="upper left", fontsize=8, framealpha=0.5)
    fig.colorbar(image, ax=list(axes), shrink=0.85, label="irradiance (W/m²)")
    return fig


def write_flux_map(res, path: str | Path, title: str = "", dpi: int = 110) -> Path:
    """Draw :func:`draw_flux_maps` into a PNG at *path* (atomically); returns the path."""
    if res is None:
        raise ReportError("no optical figures to draw: the analysis produced none ([optics] enabled = false?)")
    return savefig_atomic(draw_flux_maps(res, title), Path(path), dpi)
