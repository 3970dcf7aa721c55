"""Canting instructions a crew follows without guessing: per facet, leave it, or which screw to turn, which way
and by how much.

From a heliostat's measured canting errors (docs/conventions.md#canting): a facet turned by rx about its x
axis and ry about its y axis from its design canting is turned back by -rx and -ry.

**One viewpoint.** Everything on the sheet, and the facet map (:mod:`sofast_station.report.heliostat`), is as
the crew sees it standing *behind* the heliostat, at the adjusting screws: left and right, clockwise and
"towards you" are theirs. Seen from behind, the heliostat frame's +x (to the right seen from the mirrors)
runs to the crew's left; each facet is located by its row from the top and its place from the crew's left.

**Screws by their labels.** With ``[heliostat.adjusters]`` each screw is named by the label the heliostat file
gives it (``names``: the marks on the frame, "A", "B", "C"), which the map draws where the screw is. A screw
move ``dz = x ry - y rx`` (mm; about the facet's origin, or about the fixed screw) pushes the facet away from
the crew (towards the mirror side) when positive; it is said in turns of the thread, rounded to what a
wrench sets (``turn_step``, 1/8 turn by default), choosing among the roundings up or down of each screw the
one that leaves the least tilt, and the tilt those whole steps leave is stated (``after_mrad``). Without
screws the sheet says how far the top edge and the crew's right edge move.

**The measurement against the limit.** The sheet states how well the canting is known against the limit
(:func:`~sofast_station.result.heliostat.canting_resolution`: the test uncertainty ratio, the limit over the
largest U) and warns, in plain words, when U is more than a third of the limit.

A facet whose canting error is within the limit (``[limits] max_canting_mrad``) is left alone; one that was
not measured is named with why. Pure functions: a record in, a dict (JSON-ready) and text out.
"""

from __future__ import annotations

import itertools
import math
import textwrap
from fractions import Fraction

import numpy as np

from ..ensemble import EnsembleDesign
from ..result.formatting import with_u
from ..result.heliostat import canting_resolution

#: Screw motions below this are "leave" when a facet is turned exactly (a hundredth of a millimetre), mm.
MIN_SCREW_MM = 0.01
#: The sheet's header lines are wrapped to this many characters (the console's, a printed page's).
WIDTH = 100
#: Where the crew stands: every direction on the sheet and the map is seen from there.
VIEWPOINT = ("behind the heliostat, at its adjusting screws: left, right, clockwise and \"towards you\" are as you "
             "see them standing there")


def screw_moves_mm(adjusters, rx_mrad: float, ry_mrad: float) -> list[float]:
    """How far each screw raises the facet (towards the mirror side, away from a crew behind it; mm) to turn it
    back by (-rx, -ry): ``dz = x ry - y rx`` about the facet's origin, or about the fixed screw when there is
    one."""
    px, py = (0.0, 0.0) if adjusters.fixed is None else (float(v) for v in adjusters.points_m[adjusters.fixed])
    return [float((x - px) * ry_mrad - (y - py) * rx_mrad) for x, y in adjusters.points_m]


def _plane_fit(points_m: np.ndarray) -> np.ndarray:
    """The (3, K) least-squares map from heights at *points_m* to the plane's (constant, d/dx, d/dy)."""
    return np.linalg.pinv(np.column_stack([np.ones(len(points_m)), points_m[:, 0], points_m[:, 1]]))


def rounded_turns(adjusters, rx_mrad: float, ry_mrad: float) -> tuple[list[int], tuple[float, float]]:
    """Each screw's turn in whole steps of ``turn_step`` (signed: + raises the facet) and the canting left
    after them (rx, ry), mrad: of the roundings down or up of each screw's exact turn, the one leaving the least
    tilt (then the fewest steps). A fixed screw never turns.

    The canting left: the screws' heights on the facet turned by (rx, ry), ``z = y rx - x ry``, plus their
    moves, fitted by a plane (least squares: exact for three screws), whose slopes are the tilt left (small
    angles: second order, 1e-6 mrad per mrad^2)."""
    exact = np.array(screw_moves_mm(adjusters, rx_mrad, ry_mrad)) / (adjusters.thread_pitch_mm * adjusters.turn_step)
    choices = [(0,) if k == adjusters.fixed else tuple(sorted({math.floor(s), math.ceil(s)}))
               for k, s in enumerate(exact)]
    pts = np.asarray(adjusters.points_m, dtype=np.float64)
    fit = _plane_fit(pts)[1:]
    tilted = pts[:, 1] * rx_mrad - pts[:, 0] * ry_mrad
    best = None
    for steps in itertools.product(*choices):
        along_x, along_y = fit @ (tilted + np.array(steps, dtype=np.float64) * adjusters.thread_pitch_mm
                                  * adjusters.turn_step)
        left = (float(along_y), float(-along_x))
        key = (round(math.hypot(*left), 9), sum(abs(s) for s in steps))
        if best is None or key < best[0]:
            best = (key, list(steps), left)
    return best[1], best[2]


def turns_text(turns: float, step: float) -> str:
    """A number of turns as a wrench sets it: "1/8 turn", "3/4 turn", "1 1/4 turns" (in steps of *step*)."""
    frac = Fraction(turns).limit_denominator(max(1, round(1.0 / step)) * 4)
    whole, part = divmod(frac, 1)
    words = ([str(int(whole))] if whole else []) + ([f"{part.numerator}/{part.denominator}"] if part else [])
    return " ".join(words or ["0"]) + (" turns" if frac > 1 else " turn")


def facet_places(ensemble: EnsembleDesign) -> dict[str, str]:
    """Where each facet is, seen from behind: "top row, 2nd from the left" (rows by the height of the facet's
    centre, from the top; within a row, from the crew's left, which is the heliostat's +x side)."""
    centres = {ef.label: np.asarray(ef.position_m[:2], dtype=np.float64) for ef in ensemble.facets}
    size = min(float(np.ptp(ef.design.outline_m[:, 1])) for ef in ensemble.facets)
    rows: list[list[str]] = []
    for label in sorted(centres, key=lambda k: -centres[k][1]):
        if rows and abs(centres[rows[-1][0]][1] - centres[label][1]) < 0.5 * size:
            rows[-1].append(label)
        else:
            rows.append([label])
    out = {}
    for r, row in enumerate(rows):
        which = ("top row" if r == 0 else "bottom row" if r == len(rows) - 1 else f"row {r + 1} from the top") \
            if len(rows) > 1 else "the row"
        for k, label in enumerate(sorted(row, key=lambda lb: -centres[lb][0])):      # behind: +x is on the left
            out[label] = f"{which}, {_ordinal(k + 1)} from the left" if len(row) > 1 else which
    return out


def _ordinal(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def canting_instructions(record: dict, ensemble: EnsembleDesign, limit_mrad: float | None = None) -> dict:
    """The instructions for a heliostat's record (``facets`` entries with ``label``, ``status``,
    ``canting_mrad`` and ``canting_mrad_U``).

    Returns
    -------
    dict
        ``heliostat``, ``serial``, ``viewpoint`` ("behind"), ``limit_mrad``, ``resolution_U`` (how well the
        canting is known against the limit, with a ``warning`` when U is more than a third of it; named as an
        uncertainty, ``_U``: a reprocess recomputes the U's, so it is shown, not compared bit for bit),
        ``thread_pitch_mm``, ``raise_turn``, ``turn_step``, ``screw_labels`` and ``facets``: per facet
        ``label``, ``place`` (seen from behind), ``status``, ``action`` (``"turn"``, ``"leave"`` or
        ``"not measured"``), ``canting_mrad`` and ``canting_mrad_U``, ``size_mrad``, ``turn_mrad``
        {about_x, about_y} (the facet's own axes), ``edges_mm`` {top, right} (towards the crew behind it;
        right is theirs) and, on a facet to turn when the heliostat has adjusters, ``screws`` (label,
        ``raise_mm`` exact, ``steps`` of ``turn_step`` signed, ``turns``, ``turns_text``, ``direction`` seen from
        behind or "leave") and ``after_mrad`` / ``after_canting_mrad``, the canting those whole steps leave.
    """
    adjusters = ensemble.adjusters
    by_label = {f["label"]: f for f in record.get("facets", [])}
    places = facet_places(ensemble)
    out = {"heliostat": ensemble.name, "serial": record.get("serial"), "viewpoint": "behind", "limit_mrad": limit_mrad,
           "resolution_U": canting_resolution(list(by_label.values()), limit_mrad),
           "thread_pitch_mm": None if adjusters is None else adjusters.thread_pitch_mm,
           "raise_turn": None if adjusters is None else adjusters.raise_turn,
           "turn_step": None if adjusters is None else adjusters.turn_step,
           "screw_labels": None if adjusters is None else list(adjusters.names), "facets": []}
    for ef in ensemble.facets:
        f = by_label.get(ef.label, {"status": "missing"})
        entry = {"label": ef.label, "place": places[ef.label], "status": f.get("status", "missing")}
        if "canting_mrad" not in f:
            entry["action"] = "not measured"
            entry["reason"] = f.get("reason", f"facet {ef.label} was not measured")
            out["facets"].append(entry)
            continue
        rx, ry = float(f["canting_mrad"]["x"]), float(f["canting_mrad"]["y"])
        entry["canting_mrad"] = {"x": rx, "y": ry}
        entry["canting_mrad_U"] = f.get("canting_mrad_U")
        size = math.hypot(rx, ry)
        entry["size_mrad"] = size
        entry["action"] = "leave" if limit_mrad is not None and size <= limit_mrad else "turn"
        entry["turn_mrad"] = {"about_x": -rx, "about_y": -ry}
        outline = ef.design.outline_m
        top, crew_right = float(outline[:, 1].max()), float(outline[:, 0].min())   # behind: -x is on the right
        # turning by -rx about x moves a point at height y by -y rx towards the mirror side, by -ry about y a
        # point at x by x ry; towards the crew behind is the other way
        entry["edges_mm"] = {"top": top * rx, "right": -crew_right * ry}
        if adjusters is not None and entry["action"] == "turn":
            steps, left = rounded_turns(adjusters, rx, ry)
            other = "counterclockwise" if adjusters.raise_turn == "clockwise" else "clockwise"
            exact = screw_moves_mm(adjusters, rx, ry)
            entry["screws"] = [
                {"name": name, "raise_mm": dz, "steps": n, "turns": abs(n) * adjusters.turn_step,
                 "turns_text": turns_text(abs(n) * adjusters.turn_step, adjusters.turn_step),
                 "direction": "leave" if n == 0 else adjusters.raise_turn if n > 0 else other}
                for name, dz, n in zip(adjusters.names, exact, steps)]
            entry["after_canting_mrad"] = {"x": left[0], "y": left[1]}
            entry["after_mrad"] = math.hypot(*left)
        out["facets"].append(entry)
    return out


def _pm(v: float, u) -> str:
    return with_u(v, u, "", 3)


def size_u(entry: dict) -> float | None:
    """The U of a facet's canting size sqrt(x^2 + y^2), along the error's direction (as the guarded decision
    rule takes it); None without U."""
    u = entry.get("canting_mrad_U") or {}
    if u.get("x") is None or u.get("y") is None:
        return None
    c, size = entry["canting_mrad"], math.hypot(entry["canting_mrad"]["x"], entry["canting_mrad"]["y"])
    return math.hypot(c["x"] * u["x"], c["y"] * u["y"]) / size if size > 0 else max(u["x"], u["y"])


def instructions_text(instructions: dict) -> str:
    """The instructions as text for the crew (one block per facet), every direction seen from behind."""
    ins = instructions
    limit = ins.get("limit_mrad")
    serial = f", serial {ins['serial']}" if ins.get("serial") else ""
    lines = [f"Canting instructions for {ins['heliostat']}{serial}",
             f"Seen from {VIEWPOINT}; the facet map is drawn the same way."]
    if limit is not None:
        lines.append(f"Limit: {limit:g} mrad of canting error per facet.")
    res = ins.get("resolution_U")
    if res:
        lines.append(f"Measurement: each facet's canting is known to {res['U_mrad']:.2f} mrad or better (its "
                     f"uncertainty U, k = 2; least well {res['facet']}): test uncertainty ratio {res['ratio']:.1f} "
                     f"against the limit ({res['wanted_ratio']:g} or more is wanted).")
        if res.get("warning"):
            lines.append(f"WARNING: {res['warning']}")
    if ins.get("thread_pitch_mm"):
        raise_turn = ins["raise_turn"]
        other = "counterclockwise" if raise_turn == "clockwise" else "clockwise"
        step = ins.get("turn_step") or 0.125
        lines.append(f"Screws {', '.join(ins.get('screw_labels') or [])} on each facet (where each is: the facet "
                     f"map); {ins['thread_pitch_mm']:g} mm per turn. Turning a screw {raise_turn} pushes the facet "
                     f"away from you there, {other} pulls it towards you. Turns are in steps of "
                     f"{turns_text(step, step)}.")
    lines = [textwrap.fill(line, WIDTH, subsequent_indent="  ", break_on_hyphens=False) for line in lines]
    lines.append("")
    todo = 0
    for f in ins["facets"]:
        where = f"{f['label']}, {f['place']}" if f.get("place") else f["label"]
        if f["action"] == "not measured":
            lines.append(f"{where}: NOT MEASURED ({f['status']}): {f.get('reason', '')}")
            continue
        size = f.get("size_mrad", math.hypot(f["canting_mrad"]["x"], f["canting_mrad"]["y"]))
        head = f"{where}: off by {_pm(size, size_u(f))} mrad"
        if f["action"] == "leave":
            lines.append(f"{head}, within the limit: leave it")
            continue
        todo += 1
        lines.append(f"{head}" + (", over the limit" if limit is not None else "") + ": ADJUST IT")
        if "screws" in f:
            for s in f["screws"]:
                lines.append(f"    screw {s['name']}: " + ("leave it" if s["direction"] == "leave"
                                                           else f"{s['turns_text']} {s['direction']}"))
            after = f["after_mrad"]
            lines.append(f"    then it is within {after:.2f} mrad of its design (the nearest whole steps)")
            if limit is not None and after > limit:
                exact = ", ".join(f"{s['name']} {abs(s['raise_mm']) / ins['thread_pitch_mm']:.2f} turn "
                                  f"{_way(s['raise_mm'], ins['raise_turn'])}" for s in f["screws"])
                lines.append(f"    STILL OVER THE LIMIT: whole steps cannot set it closer; the exact turns are {exact}")
        else:
            e = f["edges_mm"]
            lines.append(f"    turning it about its centre: top edge {_edge(e['top'])}, right edge {_edge(e['right'])}")
    lines.append("")
    lines.append(f"{todo} facet{'' if todo == 1 else 's'} to adjust."
                 + (" Measure the heliostat again afterwards." if todo else ""))
    return "\n".join(lines) + "\n"


def _way(raise_mm: float, raise_turn: str) -> str:
    return raise_turn if raise_mm > 0 else "counterclockwise" if raise_turn == "clockwise" else "clockwise"


def _edge(mm: float) -> str:
    return f"{abs(mm):.2f} mm {'towards you' if mm > 0 else 'away from you'}"
