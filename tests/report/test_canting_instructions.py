"""Canting instructions a crew follows without guessing (issue 30, item 5; issue 43, item 6).

The forward model: a facet's screw points turned by a known canting error (scipy rotations, R_y(ry) R_x(rx) as
the placement reads angles); the moves the *sheet's words* say ("screw A: 1/4 turn clockwise", a thread of
known pitch, clockwise seen from behind raising the facet) are applied to those points, and the plane through
them must be the design's to within what the rounding to whole steps allows. The bound is derived here from
the screws' geometry alone: each screw off its exact move by at most half a step (pitch x step / 2), the
plane's tilt a linear map of those errors (worked out below by moving one screw at a time), so the tilt left is
at most the sum of that map's absolute columns times half a step, per axis. The code chooses among the roundings
up or down of each screw the one leaving the least tilt, which is never worse than rounding each to the nearest.
"""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sofast_station.ensemble import Adjusters, load_ensemble
from sofast_station.report.canting import canting_instructions, facet_places, instructions_text, screw_moves_mm
from sofast_station.result.heliostat import canting_resolution
from tests.conftest import ROOT

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")
ENSEMBLE_5X5 = load_ensemble(ROOT / "fixtures/facets/heliostat_5x5.toml")


def tilt_after(adjusters, rx, ry, moves_mm):
    """The canting (rx, ry), mrad, left on a flat facet turned by (rx, ry) mrad whose screws then moved by
    *moves_mm* along its design normal (+: towards the mirror side): the normal of the plane through them."""
    r = Rotation.from_euler("YX", [1e-3 * ry, 1e-3 * rx]).as_matrix()          # R_y(ry) R_x(rx), intrinsic
    pts = np.column_stack([adjusters.points_m, np.zeros(len(adjusters.points_m))]) @ r.T
    pts[:, 2] += 1e-3 * np.asarray(moves_mm, dtype=float)
    n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    n = n / np.linalg.norm(n) * np.sign(n[2])
    # the normal R_y(ry) R_x(rx) z gives: (sin ry cos rx, -sin rx, cos ry cos rx)
    return 1e3 * math.asin(-n[1]), 1e3 * math.atan2(n[0], n[2])


def rounding_bound_mrad(adjusters) -> float:
    """The most tilt whole steps can leave (see the module docstring), mrad."""
    columns = []
    for k in range(len(adjusters.points_m)):
        if k == adjusters.fixed:                                    # never turned: no rounding there
            continue
        unit = np.zeros(len(adjusters.points_m))
        unit[k] = 1.0                                               # 1 mm at screw k alone
        columns.append(tilt_after(adjusters, 0.0, 0.0, unit))
    half_step_mm = 0.5 * adjusters.thread_pitch_mm * adjusters.turn_step
    per_axis = np.abs(np.array(columns)).sum(axis=0) * half_step_mm
    return float(np.hypot(*per_axis))


_SCREW = re.compile(r"^    screw (\w+): (?:leave it|(?:(\d+) )?(?:(\d+)/(\d+) )?turns? (clockwise|counterclockwise))$")


def moves_the_sheet_says(text: str, label: str) -> dict[str, float]:
    """What a crew does reading the sheet for facet *label*: each screw's move, mm (+: towards the mirror
    side), from its words alone and the sheet's own statement of pitch and which way raises."""
    lines = text.split(f"\n{label}, ")[1].splitlines()
    block = [lines[0]] + list(itertools.takewhile(lambda line: line.startswith("    "), lines[1:]))
    flat = " ".join(text.split())                 # the header's lines are wrapped
    pitch = float(re.search(r"; ([\d.]+) mm per turn", flat).group(1))
    raises = re.search(r"Turning a screw (\w+) pushes the facet away from you", flat).group(1)
    moves = {}
    for line in block:
        m = _SCREW.match(line)
        if m is None:
            continue
        name, whole, num, den, way = m.groups()
        turns = (int(whole) if whole else 0) + (int(num) / int(den) if num else 0.0)
        moves[name] = 0.0 if way is None else turns * pitch * (1.0 if way == raises else -1.0)
    return moves


@pytest.mark.parametrize("fixed", [None, 2])
def test_the_exact_screw_moves_turn_the_facet_back(fixed):
    adj = Adjusters(points_m=ENSEMBLE.adjusters.points_m, names=ENSEMBLE.adjusters.names, thread_pitch_mm=1.25,
                    fixed=fixed)
    for rx, ry in ((0.8, 0.0), (0.0, -1.2), (1.5, 2.0)):
        left = tilt_after(adj, rx, ry, screw_moves_mm(adj, rx, ry))
        # back to the design normal to second order in the angles (1e-6 rad per mrad^2)
        assert abs(left[0]) < 5e-3 and abs(left[1]) < 5e-3, (rx, ry, left)
        if fixed is not None:
            assert screw_moves_mm(adj, rx, ry)[fixed] == 0.0


@pytest.mark.parametrize("ensemble, fixed", [(ENSEMBLE, None), (ENSEMBLE, 2), (ENSEMBLE_5X5, None)])
def test_the_sheets_turns_bring_every_facet_back_within_the_rounding(ensemble, fixed):
    """200 heliostats per case (3 cases: the two shipped screw layouts, 1.25 mm and 1 mm threads, one with a
    fixed pivot), each facet given a canting error drawn up to 3 mrad: the turns the sheet's words give, in
    1/8 turns, bring every facet over the limit back within the rounding bound (0.50 and 0.59 mrad for
    three turning screws, less with a fixed one; the worst left over the 672 facets turned of each case: 0.22
    and 0.26 mrad),
    and the "within ... mrad" the sheet states is what the forward model finds (to its 0.01 mrad print)."""
    import dataclasses

    adj = dataclasses.replace(ensemble.adjusters, fixed=fixed)
    helio = dataclasses.replace(ensemble, adjusters=adj)
    bound = rounding_bound_mrad(adj)
    rng = np.random.default_rng(43)
    worst, checked = 0.0, 0
    labels = [f.label for f in helio.facets][:4]
    for _ in range(200):
        errors = {label: rng.uniform(0.0, 3.0) * np.array([math.cos(a), math.sin(a)])
                  for label, a in zip(labels, rng.uniform(0, 2 * math.pi, len(labels)))}
        record = {"facets": [{"label": f.label, "status": "measured",
                              "canting_mrad": {"x": float(errors.get(f.label, (0.0, 0.0))[0]),
                                               "y": float(errors.get(f.label, (0.0, 0.0))[1])},
                              "canting_mrad_U": {"x": 0.05, "y": 0.05}} for f in helio.facets]}
        ins = canting_instructions(record, helio, limit_mrad=0.5)
        text = instructions_text(ins)
        for f in ins["facets"]:
            if f["action"] != "turn":
                continue
            said = moves_the_sheet_says(text, f["label"])
            assert list(said) == list(adj.names)
            left = math.hypot(*tilt_after(adj, f["canting_mrad"]["x"], f["canting_mrad"]["y"],
                                          [said[n] for n in adj.names]))
            assert left <= bound + 0.01, (f["label"], f["canting_mrad"], said, left, bound)
            stated = float(re.search(rf"\n{f['label']}, .*?then it is within ([\d.]+) mrad", text, re.S).group(1))
            assert abs(stated - left) < 0.015, (stated, left)
            worst, checked = max(worst, left), checked + 1
    assert checked > 150 and 0.2 < bound < 0.7
    print(f"\n{checked} facets turned; worst tilt left {worst:.3f} mrad, bound {bound:.3f} mrad")


def record():
    return {"serial": "H-7", "facets": [
        {"label": "R1C1", "status": "measured", "canting_mrad": {"x": 0.8, "y": 0.0},
         "canting_mrad_U": {"x": 0.05, "y": 0.05}},
        {"label": "R1C2", "status": "measured", "canting_mrad": {"x": 0.02, "y": -0.03},
         "canting_mrad_U": {"x": 0.05, "y": 0.05}},
        {"label": "R2C1", "status": "missing", "reason": "facet R2C1 is missing: nothing responds"},
        {"label": "R2C2", "status": "measured", "canting_mrad": {"x": -0.4, "y": 1.0},
         "canting_mrad_U": {"x": 0.05, "y": 0.06}}]}


def test_the_sheet_says_where_to_stand_which_facet_which_screw_and_how_far():
    """One viewpoint, stated: behind the heliostat, at the screws. There the heliostat's +x is on the crew's
    left, so R1C2 (top right seen from the mirrors) is the top row's first from the left. Screws by the
    heliostat file's labels, turns in eighths, the direction as seen from behind."""
    ins = canting_instructions(record(), ENSEMBLE, limit_mrad=0.1)
    assert facet_places(ENSEMBLE) == {"R1C2": "top row, 1st from the left", "R1C1": "top row, 2nd from the left",
                                      "R2C2": "bottom row, 1st from the left", "R2C1": "bottom row, 2nd from the left"}
    by = {f["label"]: f for f in ins["facets"]}
    assert [by[k]["action"] for k in ("R1C1", "R1C2", "R2C1", "R2C2")] == ["turn", "leave", "not measured", "turn"]
    assert by["R1C1"]["turn_mrad"] == {"about_x": -0.8, "about_y": -0.0}
    # R1C1 leans +0.8 mrad about x: its lower screw A (y = -0.22 m) goes up by 0.176 mm (1.13 eighths of a
    # 1.25 mm turn), the upper B down by as much; one eighth each leaves 0.09 mrad, the least of the choices
    screws = {s["name"]: s for s in by["R1C1"]["screws"]}
    assert screws["A"]["raise_mm"] == pytest.approx(0.176) and screws["B"]["raise_mm"] == pytest.approx(-0.176)
    assert (screws["A"]["steps"], screws["B"]["steps"], screws["C"]["steps"]) == (1, -1, 0)
    assert by["R1C1"]["after_mrad"] == pytest.approx(0.8 - 2 * 0.15625 / 0.44, abs=1e-9)
    text = instructions_text(ins)
    flat = " ".join(text.split())
    for words in ("serial H-7", "Seen from behind the heliostat, at its adjusting screws", "Limit: 0.1 mrad",
                  "Screws A, B, C on each facet", "1.25 mm per turn", "Turning a screw clockwise pushes the facet "
                  "away from you there", "steps of 1/8 turn",
                  "R1C1, top row, 2nd from the left: off by 0.800 ± 0.050 mrad, over the limit: ADJUST IT",
                  "    screw A: 1/8 turn clockwise", "    screw B: 1/8 turn counterclockwise", "    screw C: leave it",
                  "then it is within 0.09 mrad of its design", "R1C2, top row, 1st from the left: off by",
                  "within the limit: leave it", "R2C1, bottom row, 2nd from the left: NOT MEASURED (missing)",
                  "2 facets to adjust"):
        assert words in (text if words.startswith("    ") else flat), words
    assert "{" not in text and "'" not in text.replace("facet's", "").replace("heliostat's", "")


def test_the_measurement_is_stated_against_the_limit_and_a_coarse_one_is_warned_about():
    """The test uncertainty ratio (the limit over the largest U) is on the sheet; the 5x5's case (U 0.40 mrad
    against 0.5) is warned about in plain words, a U of a tenth of the limit is not."""
    coarse = record()
    coarse["facets"][3]["canting_mrad_U"] = {"x": 0.25, "y": 0.40}
    res = canting_resolution(coarse["facets"], 0.5)
    assert res["U_mrad"] == 0.40 and res["facet"] == "R2C2" and res["ratio"] == pytest.approx(1.25)
    assert res["coarse_facets"] == ["R2C2"] and "more than a third of the 0.5 mrad limit" in res["warning"]
    text = " ".join(instructions_text(canting_instructions(coarse, ENSEMBLE, 0.5)).split())
    assert "test uncertainty ratio 1.2 against the limit (3 or more is wanted)" in text
    assert "WARNING: the measurement barely tells the canting limit apart: facet R2C2's canting is known only to " \
           "0.40 mrad (U, k = 2; at worst, R2C2)" in text
    fine = canting_resolution(record()["facets"], 0.5)
    assert fine["warning"] is None and fine["ratio"] == pytest.approx(0.5 / 0.06)
    assert "WARNING" not in instructions_text(canting_instructions(record(), ENSEMBLE, 0.5))
    assert canting_resolution(record()["facets"], None) is None


def test_without_screws_the_edges_turn_the_facet_back():
    """No [heliostat.adjusters]: the sheet says how far the top edge and the crew's right edge move; moved so,
    about the facet's centre, the facet is back on its design (forward model, second order)."""
    import dataclasses

    bare = dataclasses.replace(ENSEMBLE, adjusters=None)
    ins = canting_instructions(record(), bare)
    assert all("screws" not in f for f in ins["facets"])
    assert all(f["action"] in ("turn", "not measured") for f in ins["facets"])     # no limit: every one to turn
    text = instructions_text(ins)
    # R2C2 (-0.4, +1.0): its top edge (y = 0.3 m) 0.12 mm away from the crew, their right edge (x = -0.3 m)
    # 0.30 mm towards them
    assert "turning it about its centre: top edge 0.12 mm away from you, right edge 0.30 mm towards you" in text
    for f in ins["facets"]:
        if "edges_mm" not in f:
            continue
        outline = ENSEMBLE.facets[0].design.outline_m
        top, right = outline[:, 1].max(), outline[:, 0].min()
        pts = Adjusters(points_m=[[0.0, 0.0], [0.0, top], [right, 0.0]], names=("o", "t", "r"), thread_pitch_mm=1.0)
        towards_you = [0.0, f["edges_mm"]["top"], f["edges_mm"]["right"]]
        left = tilt_after(pts, f["canting_mrad"]["x"], f["canting_mrad"]["y"], [-m for m in towards_you])
        assert math.hypot(*left) < 5e-3, (f["label"], left)


def test_turns_are_said_as_a_wrench_sets_them():
    from sofast_station.report.canting import turns_text

    assert [turns_text(t, 0.125) for t in (0.125, 0.25, 0.375, 1.0, 1.25, 2.0)] == \
        ["1/8 turn", "1/4 turn", "3/8 turn", "1 turn", "1 1/4 turns", "2 turns"]
    assert turns_text(0.5, 0.5) == "1/2 turn"
