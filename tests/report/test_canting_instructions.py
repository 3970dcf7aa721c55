"""Issue 30, item 5: canting instructions an assembler can follow.

The forward model: a facet's design surface turned by a known canting error (scipy rotations); the
instructions' screw moves applied to the screw points of that turned facet must bring its normal back to
the design's (a plane through the three moved screw points), and the edges move as a rigid turn moves them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sofast_station.ensemble import Adjusters, load_ensemble
from sofast_station.report.canting import canting_instructions, instructions_text, screw_moves_mm
from tests.conftest import ROOT

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")


def turned_normal_after_screws(adjusters, rx, ry):
    """A flat facet turned by (rx, ry) mrad (R_y R_x), its screws then moved as instructed: its normal."""
    r = Rotation.from_euler("YX", [1e-3 * ry, 1e-3 * rx]).as_matrix()
    pts = np.column_stack([adjusters.points_m, np.zeros(len(adjusters.points_m))]) @ r.T
    pts[:, 2] += 1e-3 * np.array(screw_moves_mm(adjusters, rx, ry))
    n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    return n / n[2] if n[2] else n


@pytest.mark.parametrize("fixed", [None, 2])
def test_the_screw_moves_turn_the_facet_back(fixed):
    adj = Adjusters(points_m=ENSEMBLE.adjusters.points_m, names=ENSEMBLE.adjusters.names, thread_pitch_mm=1.25,
                    fixed=fixed)
    for rx, ry in ((0.8, 0.0), (0.0, -1.2), (1.5, 2.0)):
        n = turned_normal_after_screws(adj, rx, ry)
        # back to the design normal to second order in the angles (1e-6 rad per mrad^2)
        assert abs(n[0]) < 5e-6 and abs(n[1]) < 5e-6, (rx, ry, n)
        if fixed is not None:
            assert screw_moves_mm(adj, rx, ry)[fixed] == 0.0


def record():
    return {"serial": "H-7", "facets": [
        {"label": "R1C1", "status": "measured", "canting_mrad": {"x": 0.8, "y": 0.0},
         "canting_mrad_U": {"x": 0.05, "y": 0.05}},
        {"label": "R1C2", "status": "measured", "canting_mrad": {"x": 0.02, "y": -0.03},
         "canting_mrad_U": {"x": 0.05, "y": 0.05}},
        {"label": "R2C1", "status": "missing", "reason": "facet R2C1 is missing: nothing responds"},
        {"label": "R2C2", "status": "measured", "canting_mrad": {"x": -0.4, "y": 1.0},
         "canting_mrad_U": {"x": 0.05, "y": 0.06}}]}


def test_instructions_say_which_way_and_how_far():
    ins = canting_instructions(record(), ENSEMBLE, limit_mrad=0.1)
    by = {f["label"]: f for f in ins["facets"]}
    assert [by[k]["action"] for k in ("R1C1", "R1C2", "R2C1", "R2C2")] == ["turn", "leave", "not measured", "turn"]
    # R1C1 leans +0.8 mrad about x (its top edge 0.24 mm towards the viewer): back by -0.8, top edge away
    assert by["R1C1"]["turn_mrad"] == {"about_x": -0.8, "about_y": -0.0}
    assert by["R1C1"]["edges_mm"]["top"] == pytest.approx(-0.3 * 0.8)
    screws = {s["name"]: s for s in by["R1C1"]["screws"]}
    # the upper screw (y = +0.22 m) goes down by 0.22 x 0.8 = 0.176 mm = 0.14 turn, counterclockwise
    assert screws["upper right"]["raise_mm"] == pytest.approx(-0.176)
    assert screws["upper right"]["turns"] == pytest.approx(0.176 / 1.25)
    assert screws["upper right"]["direction"] == "counterclockwise"
    assert screws["left"]["direction"] == "leave"            # on the axis it turns about
    text = instructions_text(ins)
    for words in ("serial H-7", "Limit 0.1 mrad", "R1C1   canting x +0.800 ± 0.050", "TURN IT",
                  "screw upper right: lower 0.18 mm = 0.14 turn counterclockwise", "R1C2", "within the limit, leave it",
                  "R2C1   NOT MEASURED (missing)", "2 facet(s) to turn"):
        assert words in text, words


def test_without_adjusters_the_angles_and_edges_are_given():
    bare = type(ENSEMBLE)(name=ENSEMBLE.name, facets=ENSEMBLE.facets, measure_facet=ENSEMBLE.measure_facet)
    ins = canting_instructions(record(), bare)
    assert all("screws" not in f for f in ins["facets"])
    assert all(f["action"] in ("turn", "not measured") for f in ins["facets"])     # no limit: every one to turn
    assert "right edge 0.30 mm towards you" in instructions_text(ins)
    assert math.isclose(ins["facets"][3]["edges_mm"]["right"], 0.3)
