"""Pictures of a heliostat: its flux maps (design, as measured, re-canted) and the map of its facets.

``draw_heliostat_flux`` puts the three traces of :func:`~sofast_station.optics.heliostat.heliostat_optics`
side by side on one colour scale, each with the aperture, the aim point, the beam's centroid and where each
facet's own beam lands (its label), and each panel's intercept and 90 % radius with their U.

``draw_facet_map`` draws the heliostat as seen from the mirrors (x right, y up, the heliostat frame): each
facet where it sits, coloured by its canting error's size against the limit, with an arrow the way its
optical axis leans (exaggerated) and its canting ``x ± U, y ± U`` in mrad; a facet missing, hidden or not
measured is drawn hatched with its status.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ._common import savefig_atomic


def _pm(value, u, fmt: str = "{:.3f}") -> str:
    """*value* with `` ± U`` when its expanded uncertainty *u* is known (the one formatter, GUM's rounding),
    else in *fmt* (its decimals and sign)."""
    from ..result.formatting import with_u

    decimals = int(fmt.split(".")[1][0])
    return with_u(value, u, "", decimals, sign="+" in fmt)


def draw_heliostat_flux(optics, title: str = "") -> "Figure":  # noqa: F821
    """A Matplotlib figure (Agg) of a heliostat's design, measured and re-canted flux maps."""
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    scene = optics.scene
    half = scene.grid_half_width_m
    scale, unit = (1.0, "m") if half > 1.0 else (1000.0, "mm")
    extent = [-half * scale, half * scale, -half * scale, half * scale]
    vmax = float(max(optics.flux_w_m2[k].max() for k in optics.flux_w_m2)) or 1.0
    fig = Figure(figsize=(17.0, 6.8), layout="constrained")
    axes = fig.subplots(1, 3, sharex=True, sharey=True)
    f = optics.figures
    cond = f["conditions"]
    ms_to_m = cond["slant_range_m"] / 1000.0 * scale
    fig.suptitle(f"{title}\n{cond['sun']} sun, DNI {cond['dni_w_m2']:g} W/m², reflectivity {cond['reflectivity']:g}, "
                 f"incidence {cond['incidence_angle_deg']:g}°, target at {cond['slant_range_m']:.1f} m; "
                 f"{len(cond['facets_traced'])} facets traced".strip())
    names = (("design", "design (every facet at its design canting)"),
             ("measured", "as measured"),
             ("corrected", "canting errors corrected (shapes as measured)"))
    image = None
    for ax, (key, label) in zip(axes, names):
        g = f[key]
        image = ax.imshow(optics.flux_w_m2[key], origin="lower", extent=extent, cmap="inferno", vmin=0.0, vmax=vmax,
                          interpolation="nearest")
        ap = scene.aperture
        if ap.shape == "circle":
            ax.add_patch(Circle((0, 0), ap.radius_m * scale, fill=False, ec="white", lw=1.4))
        else:
            ax.add_patch(Rectangle((-ap.width_m / 2 * scale, -ap.height_m / 2 * scale), ap.width_m * scale,
                                   ap.height_m * scale, fill=False, ec="white", lw=1.4))
        ax.plot([0], [0], "+", color="cyan", ms=12, mew=1.5)
        c = g["centroid_offset_mrad"]
        ax.plot([c["x"] * ms_to_m], [c["y"] * ms_to_m], "x", color="lime", ms=10, mew=2)
        for lab, p in g["facet_centroids_mrad"].items():
            if p["x"] is None:
                continue
            x, y = p["x"] * ms_to_m, p["y"] * ms_to_m
            ax.plot([x], [y], "o", ms=4, color="deepskyblue", mec="black", mew=0.5)
            if key == "measured":        # elsewhere the facets' beams lie on one another
                ax.annotate(lab, (x, y), xytext=(3, 3), textcoords="offset points", fontsize=7, color="deepskyblue")
        text = (f"{label}\nintercept {_pm(g['intercept'], g.get('intercept_U'), '{:.4f}')}, "
                f"r90 {_pm(g['spot_radius_mrad'], g.get('spot_radius_mrad_U'), '{:.2f}')} mrad\n"
                f"centroid {c['magnitude']:.3f} mrad off aim")
        if key != "design" and g.get("power_ratio_vs_design") is not None:
            text += f", power / design's {g['power_ratio_vs_design']:.4f}"
        ax.set_title(text, fontsize=10)
        ax.set_xlabel(f"target x, {unit} from the aim point")
    axes[0].set_ylabel(f"target y, {unit}")
    gain = f["recanting_gain"]["intercept"]
    fig.text(0.5, 0.005, f"Re-canting would change the intercept by {gain:+.4f}. White: aperture; +: aim point; "
             "x: the heliostat's beam centroid; blue dots: each facet's own beam centroid.",
             ha="center", va="bottom", fontsize=9)
    fig.colorbar(image, ax=list(axes), shrink=0.85, label="flux, W/m²")
    return fig


def save_heliostat_flux(optics, path: Path, title: str = "", dpi: int = 110) -> Path:
    return savefig_atomic(draw_heliostat_flux(optics, title), Path(path), dpi)


def draw_facet_map(record: dict, ensemble, limit_mrad: float | None = None, title: str = "") -> "Figure":  # noqa: F821
    """A Matplotlib figure (Agg): the heliostat's facets as seen from the mirrors, each with its canting error.

    *record* is a heliostat record (``facets`` entries with ``label``, ``status``, ``canting_mrad`` and
    ``canting_mrad_U``); *limit_mrad* (``[limits] max_canting_mrad``) sets the colour scale's end (red)."""
    from matplotlib.figure import Figure

    n = ensemble.n_facets
    fig = Figure(figsize=(9.0, 8.5) if n <= 9 else (12.0, 11.0), layout="constrained")
    ax = fig.subplots()
    norm, cmap = draw_facet_map_on(ax, record, ensemble, limit_mrad, fontsize=9 if n <= 9 else 7)
    from matplotlib.cm import ScalarMappable
    bar = fig.colorbar(ScalarMappable(norm, cmap), ax=ax, shrink=0.8, extend="max" if limit_mrad else "neither",
                       label="canting error, mrad" + (f" (the line: the limit, {limit_mrad:g})" if limit_mrad else ""))
    if limit_mrad:
        bar.ax.axhline(limit_mrad, color="black", lw=2.0)
    h = record.get("heliostat", {})
    sub = ""
    if "canting_rms_mrad" in h:
        sub = (f"canting RMS {h['canting_rms_mrad']:.3f} mrad, largest {h['canting_max_mrad']:.3f} mrad "
               f"({h.get('canting_max_facet', '')}); arrows: where each facet's optical axis leans")
    ax.set_title(f"{title}\n{sub}".strip(), fontsize=11)
    return fig


def draw_facet_map_on(ax, record: dict, ensemble, limit_mrad: float | None = None, fontsize: int = 9):
    """Draw the map of the facets (:func:`draw_facet_map`) into the Matplotlib axes *ax*; returns its colour
    scale (norm, colour map)."""
    from matplotlib import colormaps
    from matplotlib.colors import Normalize
    from matplotlib.patches import FancyArrow, Polygon

    facets = {f["label"]: f for f in record["facets"]}
    mags = [math.hypot(f["canting_mrad"]["x"], f["canting_mrad"]["y"]) for f in facets.values() if "canting_mrad" in f]
    # the colour scale runs to 1.5 times the limit: green well within it, orange near it, red beyond
    top = 1.5 * limit_mrad if limit_mrad else (max(mags) if mags else 1.0) or 1.0
    norm = Normalize(0.0, top)
    cmap = colormaps["RdYlGn_r"]
    xy = ensemble.corners_m()[:, :2]
    span = float(np.max(xy.max(axis=0) - xy.min(axis=0)))
    n = ensemble.n_facets
    pitch = span / max(1.0, math.sqrt(n))
    # the arrow in the facet's lower half, its text in the upper: an error at the scale's end (or beyond)
    # draws an arrow a fifth of a facet long, so it stays on its facet and off its text
    arrow_scale = 0.2 * pitch / max(top, 1e-9)
    font = fontsize
    for ef in ensemble.facets:
        corners = ef.corners_m()[:, :2]
        f = facets.get(ef.label, {"status": "missing"})
        centre = corners.mean(axis=0)
        if "canting_mrad" in f:
            c = f["canting_mrad"]
            mag = math.hypot(c["x"], c["y"])
            ax.add_patch(Polygon(corners, closed=True, fc=cmap(norm(min(mag, top))), ec="black", lw=1.0))
            # the optical axis leans towards (ry, -rx) in the facet's frame
            stretch = arrow_scale * min(1.0, top / mag) if mag > 0 else 0.0
            dx, dy = c["y"] * stretch, -c["x"] * stretch
            if math.hypot(dx, dy) > 1e-9:
                ax.add_patch(FancyArrow(centre[0], centre[1] - 0.2 * pitch, dx, dy, width=0.012 * pitch,
                                        head_width=0.05 * pitch, length_includes_head=True, color="black"))
            u = f.get("canting_mrad_U") or {}
            over = limit_mrad is not None and mag > limit_mrad
            ax.text(centre[0], centre[1] + 0.4 * pitch,
                    f"{ef.label}{'  OVER' if over else ''}\nx {_pm(c['x'], u.get('x'), '{:+.3f}')}\n"
                    f"y {_pm(c['y'], u.get('y'), '{:+.3f}')} mrad", ha="center", va="top", fontsize=font,
                    fontweight="bold" if over else "normal")
        else:
            ax.add_patch(Polygon(corners, closed=True, fc="lightgrey", ec="black", lw=1.0, hatch="//"))
            ax.text(centre[0], centre[1], f"{ef.label}\n{f.get('status', 'missing')}", ha="center", va="center",
                    fontsize=font)
    pad = 0.05 * span
    ax.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
    ax.set_ylim(xy[:, 1].min() - pad, xy[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("heliostat x, m (seen from the mirrors)")
    ax.set_ylabel("heliostat y, m")
    return norm, cmap


def save_facet_map(record: dict, ensemble, path: Path, limit_mrad: float | None = None, title: str = "",
                   dpi: int = 110) -> Path:
    return savefig_atomic(draw_facet_map(record, ensemble, limit_mrad, title), Path(path), dpi)
