"""Pictures of a heliostat: its flux maps (design, as measured, re-canted) and the map of its facets.

``draw_heliostat_flux`` puts the three traces of :func:`~sofast_station.optics.heliostat.heliostat_optics`
side by side on one colour scale, each with the aperture, the aim point, the beam's centroid and where each
facet's own beam lands (its label), and each panel's intercept and 90 % radius with their U.

``draw_facet_map`` draws the heliostat as the crew sees it from behind, at its adjusting screws (the canting
instructions' one viewpoint, :mod:`sofast_station.report.canting`: the heliostat frame's +x runs to the left):
each facet where it sits, coloured by its canting error's size against the limit, with its label, its error
``size ± U`` in mrad and what to do; each adjusting screw where it is, with the label the heliostat file gives
it and, on a facet to adjust, its turn (a curved arrow the way it turns, seen from behind, and how far: the
words of the instructions); a facet missing, hidden or not measured is drawn hatched with its status.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon, Rectangle

from ..result.formatting import with_u
from ._common import savefig_atomic
from .canting import canting_instructions, size_u


def _pm(value, u, fmt: str = "{:.3f}") -> str:
    """*value* with `` ± U`` when its expanded uncertainty *u* is known (the one formatter, GUM's rounding),
    else in *fmt* (its decimals and sign)."""
    decimals = int(fmt.split(".")[1][0])
    return with_u(value, u, "", decimals, sign="+" in fmt)


def draw_heliostat_flux(optics, title: str = "") -> "Figure":
    """A Matplotlib figure (Agg) of a heliostat's design, measured and re-canted flux maps."""
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


def draw_facet_map(record: dict, ensemble, limit_mrad: float | None = None, title: str = "") -> "Figure":
    """A Matplotlib figure (Agg): the heliostat's facets seen from behind, each with its canting error and, where
    there are screws, what to turn (module docstring).

    *record* is a heliostat record (``facets`` entries with ``label``, ``status``, ``canting_mrad`` and
    ``canting_mrad_U``; its ``canting_instructions`` when it has them, else they are made here); *limit_mrad*
    (``[limits] max_canting_mrad``) sets the colour scale's end (red)."""
    n = ensemble.n_facets
    fig = Figure(figsize=(9.0, 8.5) if n <= 9 else (12.0, 11.0), layout="constrained")
    ax = fig.subplots()
    norm, cmap = draw_facet_map_on(ax, record, ensemble, limit_mrad, fontsize=9 if n <= 9 else 7)
    bar = fig.colorbar(ScalarMappable(norm, cmap), ax=ax, shrink=0.8, extend="max" if limit_mrad else "neither",
                       label="canting error, mrad" + (f" (the line: the limit, {limit_mrad:g})" if limit_mrad else ""))
    if limit_mrad:
        bar.ax.axhline(limit_mrad, color="black", lw=2.0)
    h = record.get("heliostat", {})
    sub = "seen from behind, at the adjusting screws"
    if "canting_rms_mrad" in h:
        sub = (f"canting RMS {h['canting_rms_mrad']:.3f} mrad, largest {h['canting_max_mrad']:.3f} mrad "
               f"({h.get('canting_max_facet', '')}); {sub}")
    ax.set_title(f"{title}\n{sub}".strip(), fontsize=11)
    return fig


#: The curved arrows of a screw's turn, seen from behind (the map's and the sheet's viewpoint).
_TURN_GLYPH = {"clockwise": "\u21bb", "counterclockwise": "\u21ba"}


def draw_facet_map_on(ax, record: dict, ensemble, limit_mrad: float | None = None, fontsize: int = 9):
    """Draw the map of the facets (:func:`draw_facet_map`) into the Matplotlib axes *ax*; returns its colour
    scale (norm, colour map)."""
    instructions = record.get("canting_instructions") or canting_instructions(record, ensemble, limit_mrad)
    todo = {f["label"]: f for f in instructions["facets"]}
    facets = {f["label"]: f for f in record["facets"]}
    mags = [math.hypot(f["canting_mrad"]["x"], f["canting_mrad"]["y"]) for f in facets.values() if "canting_mrad" in f]
    # the colour scale runs to 1.5 times the limit: green well within it, orange near it, red beyond
    top = 1.5 * limit_mrad if limit_mrad else (max(mags) if mags else 1.0) or 1.0
    norm = Normalize(0.0, top)
    cmap = colormaps["RdYlGn_r"]
    # seen from behind: the heliostat's +x runs to the left, so every x is drawn mirrored
    behind = np.array([-1.0, 1.0])
    xy = ensemble.corners_m()[:, :2] * behind
    span = float(np.max(xy.max(axis=0) - xy.min(axis=0)))
    pitch = span / max(1.0, math.sqrt(ensemble.n_facets))
    adjusters = ensemble.adjusters
    font = fontsize
    for ef in ensemble.facets:
        corners = ef.corners_m()[:, :2] * behind
        f = facets.get(ef.label, {"status": "missing"})
        centre = corners.mean(axis=0)
        if "canting_mrad" not in f:
            ax.add_patch(Polygon(corners, closed=True, fc="lightgrey", ec="black", lw=1.0, hatch="//"))
            ax.text(centre[0], centre[1], f"{ef.label}\n{f.get('status', 'missing')}", ha="center", va="center",
                    fontsize=font)
            continue
        c = f["canting_mrad"]
        mag = math.hypot(c["x"], c["y"])
        ax.add_patch(Polygon(corners, closed=True, fc=cmap(norm(min(mag, top))), ec="black", lw=1.0))
        entry = todo.get(ef.label, {})
        adjust = entry.get("action") == "turn"
        what = ("ADJUST" if limit_mrad is None else "OVER: ADJUST") if adjust else "leave it"
        ax.text(centre[0], centre[1], f"{ef.label}\n{_pm(mag, size_u(f))} mrad\n{what}", ha="center",
                va="center", fontsize=font, fontweight="bold" if adjust else "normal")
        if adjusters is None:
            continue
        screws = {s["name"]: s for s in entry.get("screws", [])}
        origin = np.asarray(ef.position_m[:2], dtype=np.float64)
        for name, point in zip(adjusters.names, adjusters.points_m):
            # the screw where it sits on the frame (the design canting's few mrad do not move it on the map)
            at = (origin + ef.rotation[:2, :2] @ point) * behind
            ax.add_patch(Circle(at, 0.045 * pitch, fc="white", ec="black", lw=0.8))
            ax.text(at[0], at[1], name, ha="center", va="center", fontsize=font - 1, fontweight="bold")
            s = screws.get(name)
            if adjust and s is not None:
                said = "leave" if s["direction"] == "leave" else \
                    f"{_TURN_GLYPH[s['direction']]} {s['turns_text'].split(' turn')[0]}"
                # inside the facet: above a screw in its lower part, below one in its upper part or middle
                up = at[1] < centre[1] - 0.1 * pitch
                ax.text(at[0], at[1] + (0.06 if up else -0.06) * pitch, said, ha="center",
                        va="bottom" if up else "top", fontsize=font + (0 if said == "leave" else 2), fontweight="bold")
    pad = 0.05 * span
    ax.set_xlim(xy[:, 0].min() - pad, xy[:, 0].max() + pad)
    ax.set_ylim(xy[:, 1].min() - pad, xy[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    turns = "" if adjusters is None else (
        f"\nscrews {', '.join(adjusters.names)} as marked on the frame; turn {_TURN_GLYPH['clockwise']} clockwise, "
        f"{_TURN_GLYPH['counterclockwise']} counterclockwise")
    ax.set_xlabel(f"as seen standing behind the heliostat, at its screws{turns}")
    return norm, cmap


def save_facet_map(record: dict, ensemble, path: Path, limit_mrad: float | None = None, title: str = "",
                   dpi: int = 110) -> Path:
    return savefig_atomic(draw_facet_map(record, ensemble, limit_mrad, title), Path(path), dpi)
