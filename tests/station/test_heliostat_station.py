"""Issue 30, item 6: a heliostat station on the line. ``inspect`` of the shipped 2x2 station (its camera at a
quarter of the resolution: 400 x 300) answers with one entry per facet (serial, figures with U, canting with
U, the twin's truth), verdicts per facet and for the heliostat, canting instructions and pictures; the
verdict rules are checked on their own.

The shipped station's twin has R1C2 canted 0.9 mrad about x on the frame (0.69 mrad from the facets' mean:
beyond its 0.5 mrad limit) and the other three within 0.45 mrad, so the heliostat fails on R1C2 alone.
"""

from __future__ import annotations

import json
import math
import re

import pytest

from sofast_station.ensemble import load_ensemble
from sofast_station.result.heliostat import judge_canting, judge_heliostat
from sofast_station.result.verdict import Limits, Quality
from tests.conftest import ROOT

SHIPPED = ROOT / "fixtures/stations/heliostat-ensemble.toml"


def small_heliostat_station(tmp_path, extra: str = "") -> str:
    """The shipped 2x2 heliostat station with a 400 x 300 camera (the same field of view), in *tmp_path*."""
    text = SHIPPED.read_text()
    text = text.replace('facet = "../facets/heliostat_2x2.toml"',
                        f'facet = "{ROOT / "fixtures/facets/heliostat_2x2.toml"}"')
    text = text.replace('radiometric = "../../calibration/simulated_radiometric.json"',
                        f'radiometric = "{ROOT / "calibration/simulated_radiometric.json"}"')
    text = text.replace('data_dir = "~/sofast-station-data/sim-heliostat-2x2"', f'data_dir = "{tmp_path / "data"}"')
    text = re.sub(r"width_px = 1600\nheight_px = 1200\nfocal_length_px = 3000.0\nprincipal_point_px = \[799.5, 599.5\]",
                  "width_px = 400\nheight_px = 300\nfocal_length_px = 750.0\nprincipal_point_px = [199.5, 149.5]", text)
    text += "\n[analysis]\nedge_window_px = 3\n" + extra
    path = tmp_path / "heliostat.toml"
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    import os
    import subprocess
    import sys

    tmp = tmp_path_factory.mktemp("heliostat")
    env = dict(os.environ, SOFAST_DATA_DIR=str(tmp / "data"))
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "inspect", "--config", small_heliostat_station(tmp),
                           "--json", "--serial", "H-0042"], capture_output=True, text=True, env=env, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_inspect_answers_every_facet_with_its_canting_and_truth(record):
    assert record["facet"] == "heliostat-2x2" and [f["label"] for f in record["facets"]] == ["R1C1", "R1C2", "R2C1",
                                                                                             "R2C2"]
    for f in record["facets"]:
        assert f["serial"] == f"H-0042-{f['label']}" and f["status"] == "measured"
        for key in ("curvature_x_per_m", "curvature_x_per_m_U", "slope_rms_mrad", "optical_tilt_mrad_U",
                    "n_points", "verdict"):
            assert key in f, key
        assert set(f["canting_mrad"]) == set(f["canting_mrad_U"]) == {"x", "y"}
        truth = f["truth"]["canting_mrad"]
        for ax in "xy":
            # the quarter-resolution camera's canting: within 0.05 mrad of truth and covered by its U
            err = f["canting_mrad"][ax] - truth[ax]
            assert abs(err) < 0.05 and abs(err) <= f["canting_mrad_U"][ax], (f["label"], ax, err)
        assert abs(f["curvature_x_per_m"] - f["truth"]["curvature_x_per_m"]) < 1e-3
    h = record["heliostat"]
    assert h["n_measured"] == 4 and h["canting_max_facet"] == "R1C2" and "placement_U" in h
    assert record["truth"]["heliostat"]["placement"]["mm"] == [1.0, -0.6, 0.8]


def test_its_summary_says_the_aperture_in_words_and_each_figure_with_its_u(record):
    """Issue 43: the heliostat's summary printed "aperture {'shape': ...}" (a Python dict); it is the one record
    summary now (report/summary.py), each figure written as every screen writes it."""
    from sofast_station.report.summary import record_text
    from sofast_station.result.formatting import figure_text

    text = record_text(record)
    assert "{'shape'" not in text and "aperture a circle of " in text, text
    assert text.startswith("Heliostat H-0042 (heliostat-2x2)") and "canting RMS" in text
    for f in record["facets"]:
        line = next(ln for ln in text.splitlines() if ln.strip().startswith(f["label"] + " "))
        for key in ("canting_mrad.x", "curvature_x_per_m", "slope_rms_mrad.parabola.magnitude"):
            assert figure_text(f, key, sign=key.startswith("canting")) in line, (key, line)
        assert " ± " in line


def test_the_verdict_is_each_facets_and_the_heliostats(record):
    by = {f["label"]: f for f in record["facets"]}
    assert by["R1C2"]["verdict"] == "fail"
    assert any(r.startswith("canting error") for r in by["R1C2"]["reasons"])
    assert record["verdict"] == "fail" and any(r.startswith("R1C2: canting error") for r in record["reasons"])
    # the station holds its facets' curvature to 1e-3 /m (their U at this resolution is a few 1e-4): the
    # twin's facets are within it, so R1C2 fails on its canting alone and the others pass
    assert [by[k]["verdict"] for k in ("R1C1", "R1C2", "R2C1", "R2C2")] == ["pass", "fail", "pass", "pass"]
    assert len(by["R1C2"]["reasons"]) == 1 and len(record["reasons"]) == 1


def test_the_record_carries_optics_instructions_and_pictures(record):
    o = record["optics"]
    assert o["corrected"]["intercept"] >= o["measured"]["intercept"] and "intercept_U" in o["measured"]
    ins = {f["label"]: f for f in record["canting_instructions"]["facets"]}
    assert ins["R1C2"]["action"] == "turn" and len(ins["R1C2"]["screws"]) == 3
    for kind in ("facet_map", "flux_maps"):
        assert open(record["pictures"][kind], "rb").read(4) == b"\x89PNG"


def test_the_instructions_turns_bring_the_twins_facets_back(record):
    """Issue 43: the twin's heliostat has known canting errors (R1C2 canted 0.8 mrad on purpose). The turns the
    record's instructions give (whole 1/8 turns of its screws), applied to each facet turned by its *true*
    canting, leave it within the rounding bound (tests/report/test_canting_instructions.py) plus what the
    measurement got wrong (under 0.05 mrad per axis here, checked above); every facet it says to leave is
    within the limit in truth, and the resolution against the limit is stated (under resolution_U: from the
    U's, which a reprocess recomputes, so it is not compared bit for bit)."""
    from tests.report.test_canting_instructions import rounding_bound_mrad, tilt_after

    adj = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml").adjusters
    ins = record["canting_instructions"]
    assert ins["serial"] == record["serial"]             # made before the record had one: named after
    assert ins["viewpoint"] == "behind" and ins["screw_labels"] == ["A", "B", "C"] and ins["turn_step"] == 0.125
    res = ins["resolution_U"]
    assert res["limit_mrad"] == 0.5 and res["ratio"] == pytest.approx(0.5 / res["U_mrad"])
    assert (res["warning"] is None) == (res["ratio"] >= 3.0)
    truth = {f["label"]: f["truth"]["canting_mrad"] for f in record["facets"]}
    measured = {f["label"]: f["canting_mrad"] for f in record["facets"]}
    turned = [f for f in ins["facets"] if f["action"] == "turn"]
    assert [f["label"] for f in turned] == ["R1C2"]
    for f in ins["facets"]:
        t = truth[f["label"]]
        if f["action"] == "leave":
            assert math.hypot(t["x"], t["y"]) <= 0.5, f["label"]
            continue
        moves = [s["steps"] * ins["turn_step"] * ins["thread_pitch_mm"] for s in f["screws"]]
        assert [s["direction"] for s in f["screws"]] == [
            "leave" if m == 0 else "clockwise" if m > 0 else "counterclockwise" for m in moves]
        left = math.hypot(*tilt_after(adj, t["x"], t["y"], moves))
        wrong = math.hypot(measured[f["label"]]["x"] - t["x"], measured[f["label"]]["y"] - t["y"])
        assert left <= rounding_bound_mrad(adj) + wrong + 0.01, (f["label"], left, wrong)
        assert math.hypot(t["x"], t["y"]) > 0.5 and left < 0.5
        print(f"\n{f['label']}: true canting {math.hypot(t['x'], t['y']):.3f} mrad, after the turns "
              f"{left:.3f} mrad (the sheet says {f['after_mrad']:.3f}; measured off truth by {wrong:.3f})")


LIMITS = Limits(max_canting_mrad=0.5)
DESIGNS = {f.label: f.design for f in load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml").facets}


def test_canting_against_its_limit_with_either_decision_rule():
    entry = {"canting_mrad": {"x": 0.45, "y": 0.1}, "canting_mrad_U": {"x": 0.1, "y": 0.1}}
    assert judge_canting(entry, LIMITS) == ([], [])
    guarded = Limits(max_canting_mrad=0.5, decision_rule="guarded")
    fail, unsure = judge_canting(entry, guarded)
    assert not fail and "within its U" in unsure[0]
    entry["canting_mrad"] = {"x": 0.7, "y": 0.1}
    assert judge_canting(entry, guarded)[0] and judge_canting(entry, LIMITS)[0]


def test_a_missing_facet_fails_the_heliostat_and_a_hidden_one_makes_it_invalid():
    facets = [{"label": "R1C1", "status": "missing", "reason": "facet R1C1 is missing"},
              {"label": "R1C2", "status": "hidden", "reason": "facet R1C2 is partly hidden"}]
    v = judge_heliostat(facets, DESIGNS, LIMITS, Quality())
    assert v["verdict"] == "invalid" and facets[0]["verdict"] == "fail" and facets[1]["verdict"] == "invalid"
    assert v["reasons"][0] == "R1C2: facet R1C2 is partly hidden"
    assert judge_heliostat(facets[:1], DESIGNS, LIMITS, Quality())["verdict"] == "fail"


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    """Two heliostats through the production loop (the simulated robot), every one dumped."""
    import dataclasses

    from sofast_station.config import load_config
    from sofast_station.station.service import Service

    tmp = tmp_path_factory.mktemp("line")
    cfg = load_config(small_heliostat_station(tmp))
    raw = dict(cfg.raw, run={"deadline_s": 120.0, "late_grace_s": 60.0, "dump_every_n": 1},
               archive={"workbook_interval_s": 1.0})
    cfg = dataclasses.replace(cfg, data_dir=tmp / "data", raw=raw)
    service = Service(cfg, simulated_facets=2, console=lambda line: None)
    try:
        outcomes = service.runner.run()
    finally:
        service.close()                      # waits for the archiver to drain
    return cfg, outcomes


def test_the_line_journals_a_row_per_facet_and_dumps_that_reprocess_exactly(line):
    from sofast_station.archive import Journal, read_workbook
    from sofast_station.reanalysis.reprocess import reprocess_dump

    cfg, outcomes = line
    assert [o.answer for o in outcomes] == ["fail", "fail"]           # R1C2's canting, as inspect found
    journal = Journal(cfg.data_dir / "journal.sqlite3")
    try:
        rows = journal.rows()
    finally:
        journal.close()
    assert len(rows) == 2 and all(r.dump_status == "written" for r in rows)
    books = sorted((cfg.data_dir / "archive").glob("*.xlsx"))
    sheet = [row for b in books for row in read_workbook(b)]
    assert [r["serial"] for r in sheet] == [f"SIM-000{i}-{lab}" for i in (1, 2) for lab in ("R1C1", "R1C2", "R2C1",
                                                                                             "R2C2")]
    for r in sheet:
        assert r["heliostat_serial"] in ("SIM-0001", "SIM-0002") and r["heliostat_verdict"] == "fail"
        assert "canting_mrad.x" in r and "canting_mrad_U.x" in r and "heliostat.canting_max_mrad" in r
    res = reprocess_dump(rows[0].dump_path)
    assert res.exact, res.differences
    assert res.n_compared > 400
    assert res.record["facets"][1]["canting_mrad"] == rows[0].record["facets"][1]["canting_mrad"]


def test_the_certificate_and_the_page_show_the_heliostat_as_a_map_of_its_facets(line, tmp_path):
    import subprocess
    import sys

    from sofast_station.web.data import LineData
    from sofast_station.web.images import FacetImages
    from sofast_station.web.render import last_html
    from sofast_station.web.settings import web_settings

    cfg, outcomes = line
    out = tmp_path / "certificate.pdf"
    import os
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "report", "certificate", "SIM-0002", "--config",
                           str(cfg.path), "--out", str(out)], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ, SOFAST_DATA_DIR=str(cfg.data_dir)))
    assert proc.returncode == 0, proc.stderr
    data = out.read_bytes()
    assert data.startswith(b"%PDF") and b"/Count 1" in data           # one page
    from sofast_station.archive import Journal
    from sofast_station.report.certificate import draw_heliostat_certificate
    with Journal(cfg.data_dir / "journal.sqlite3") as j:
        rec = j.rows(serial="SIM-0002")[-1].record
    fig = draw_heliostat_certificate(rec, ensemble=cfg.ensemble, limit_mrad=0.5)
    text = "\n".join([t.get_text() for t in fig.texts] + [t.get_text() for ax in fig.axes for t in ax.texts]
                     + [c.get_text().get_text() for ax in fig.axes for tb in ax.tables
                        for c in tb.get_celld().values()])
    for words in ("Heliostat inspection certificate", "SIM-0002", "OVER: ADJUST", "canting RMS", "FAIL",
                  "Data dump", "fail"):
        assert words in text, words
    snap = LineData(cfg, web_settings(cfg)).snapshot()
    labels = [f.label for f in snap["figures"]]
    assert labels[:2] == ["R1C1 canting (pass)", "R1C2 canting (fail)"] and snap["figures"][1].ok is False
    html = last_html(snap)
    assert f"/facet/{outcomes[-1].cycle_id}/facets.png" in html and "/map.png" not in html
    png = FacetImages(cfg.data_dir, config=cfg).get(outcomes[-1].cycle_id, "facets")
    assert png[:4] == b"\x89PNG"
