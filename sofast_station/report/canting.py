"""Canting instructions an assembler can follow: per facet, which way and how far to turn it.

From a heliostat's measured canting errors (docs/conventions.md#canting): a facet turned by rx about its x
axis and ry about its y axis from its design canting is turned back by -rx and -ry. Said three ways:

* the angles, mrad (about the facet's own x, to the right, and y, up, seen from the mirrors);
* the edges: how far its top edge and its right edge move towards the viewer (mm), turning about its centre;
* its adjusting screws, when the heliostat file gives them (``[heliostat.adjusters]``): how far each
  raises or lowers the facet (``dz = x ry - y rx``, or about a fixed pivot), in mm and in turns of the
  thread, and which way to turn (seen from the back of the frame).

A facet whose canting error is within the limit (``[limits] max_canting_mrad``) is left alone; one that was
not measured is named with why. Pure functions: a record in, a dict (JSON-ready) and text out.
"""

from __future__ import annotations

import math

from ..ensemble import EnsembleDesign

#: Screw motions below this are "leave" (a hundredth of a millimetre: no thread is set finer), mm.
MIN_SCREW_MM = 0.01


def screw_moves_mm(adjusters, rx_mrad: float, ry_mrad: float) -> list[float]:
    """How far each screw raises the facet (towards the mirror side, mm) to turn it back by (-rx, -ry):
    ``dz = x ry - y rx`` about the facet's origin, or about the fixed screw when there is one."""
    px, py = (0.0, 0.0) if adjusters.fixed is None else (float(v) for v in adjusters.points_m[adjusters.fixed])
    return [float((x - px) * ry_mrad - (y - py) * rx_mrad) for x, y in adjusters.points_m]


def canting_instructions(record: dict, ensemble: EnsembleDesign, limit_mrad: float | None = None) -> dict:
    """The instructions for a heliostat's record (``facets`` entries with ``label``, ``status``,
    ``canting_mrad`` and ``canting_mrad_U``).

    Returns
    -------
    dict
        ``heliostat``, ``serial``, ``limit_mrad``, ``thread_pitch_mm``, ``raise_turn`` and ``facets``: per facet
        ``label``, ``status``, ``action`` (``"turn"``, ``"leave"`` or ``"not measured"``), ``canting_mrad`` and
        ``canting_mrad_U``, ``turn_mrad`` {about_x, about_y}, ``edges_mm`` {top, right} (towards the viewer)
        and ``screws`` (name, raise_mm, turns, direction) when the heliostat has adjusters.
    """
    adjusters = ensemble.adjusters
    by_label = {f["label"]: f for f in record.get("facets", [])}
    out = {"heliostat": ensemble.name, "serial": record.get("serial"), "limit_mrad": limit_mrad,
           "thread_pitch_mm": None if adjusters is None else adjusters.thread_pitch_mm,
           "raise_turn": None if adjusters is None else adjusters.raise_turn, "facets": []}
    for ef in ensemble.facets:
        f = by_label.get(ef.label, {"status": "missing"})
        entry = {"label": ef.label, "status": f.get("status", "missing")}
        if "canting_mrad" not in f:
            entry["action"] = "not measured"
            entry["reason"] = f.get("reason", f"facet {ef.label} was not measured")
            out["facets"].append(entry)
            continue
        rx, ry = float(f["canting_mrad"]["x"]), float(f["canting_mrad"]["y"])
        entry["canting_mrad"] = {"x": rx, "y": ry}
        entry["canting_mrad_U"] = f.get("canting_mrad_U")
        size = math.hypot(rx, ry)
        entry["action"] = "leave" if limit_mrad is not None and size <= limit_mrad else "turn"
        entry["turn_mrad"] = {"about_x": -rx, "about_y": -ry}
        outline = ef.design.outline_m
        top, right = float(outline[:, 1].max()), float(outline[:, 0].max())
        # turning by -rx about x moves a point at height y by -y rx towards the viewer; by -ry about y, x ry
        entry["edges_mm"] = {"top": -top * rx, "right": right * ry}
        if adjusters is not None:
            screws = []
            for name, dz in zip(adjusters.names, screw_moves_mm(adjusters, rx, ry)):
                turns = dz / adjusters.thread_pitch_mm
                other = "counterclockwise" if adjusters.raise_turn == "clockwise" else "clockwise"
                screws.append({"name": name, "raise_mm": dz, "turns": abs(turns),
                               "direction": (adjusters.raise_turn if dz > 0 else other)
                               if abs(dz) >= MIN_SCREW_MM else "leave"})
            entry["screws"] = screws
        out["facets"].append(entry)
    return out


def _pm(v: float, u) -> str:
    from ..result.formatting import with_u
    return with_u(v, u, "", 3, sign=True)


def instructions_text(instructions: dict) -> str:
    """The instructions as text for the assembler (one block per facet)."""
    ins = instructions
    lines = [f"Canting instructions: {ins['heliostat']}" + (f", serial {ins['serial']}" if ins.get("serial") else ""),
             "Seen from the mirrors: x to the right, y up; each facet turns about its own centre."
             + (f" Limit {ins['limit_mrad']:g} mrad." if ins.get("limit_mrad") is not None else "")]
    if ins.get("thread_pitch_mm"):
        lines.append(f"Screws: {ins['thread_pitch_mm']:g} mm per turn; turning {ins['raise_turn']} (seen from the "
                     "back of the frame) raises the facet towards the mirror side.")
    lines.append("")
    todo = 0
    for f in ins["facets"]:
        if f["action"] == "not measured":
            lines.append(f"{f['label']:6s} NOT MEASURED ({f['status']}): {f.get('reason', '')}")
            continue
        c, u = f["canting_mrad"], f.get("canting_mrad_U") or {}
        size = math.hypot(c["x"], c["y"])
        head = (f"{f['label']:6s} canting x {_pm(c['x'], u.get('x'))}, y {_pm(c['y'], u.get('y'))} mrad "
                f"({size:.3f} mrad)")
        if f["action"] == "leave":
            lines.append(f"{head}: within the limit, leave it")
            continue
        todo += 1
        lines.append(f"{head}: TURN IT")
        t, e = f["turn_mrad"], f["edges_mm"]
        lines.append(f"       about its horizontal axis by {t['about_x']:+.3f} mrad: top edge "
                     f"{abs(e['top']):.2f} mm {'towards you' if e['top'] > 0 else 'away from you'}")
        lines.append(f"       about its vertical axis by {t['about_y']:+.3f} mrad: right edge "
                     f"{abs(e['right']):.2f} mm {'towards you' if e['right'] > 0 else 'away from you'}")
        for s in f.get("screws", []):
            if s["direction"] == "leave":
                lines.append(f"       screw {s['name']}: leave")
            else:
                verb = "raise" if s["raise_mm"] > 0 else "lower"
                lines.append(f"       screw {s['name']}: {verb} {abs(s['raise_mm']):.2f} mm = {s['turns']:.2f} turn "
                             f"{s['direction']}")
    lines.append("")
    lines.append(f"{todo} facet(s) to turn." + (" Measure the heliostat again afterwards." if todo else ""))
    return "\n".join(lines) + "\n"
