"""Issue 44 item 1: every capture checks the geometry it relies on. The fixture's marks, located in each cycle's
white frame against their commissioned places, tell a moved camera (all marks shift) from a misplaced facet
(marks still); a moved camera withholds the facet's verdict, raises the station's alarm and holds the line until
the geometry is confirmed or recommissioned.

The physics is the twin's: it draws the marks from its own camera model and the true poses
(sofast_station/twin/marks.py), and the camera is moved in the twin (TrueAssembly), never in the check.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.devices.protocols import FAULT_CODES, WARNING_BITS

ROOT = Path(__file__).resolve().parents[2]
#: A hall warming by 5 K a facet (issue 44 item 4), the screen 1 K above it; commissioned at 20 degC.
TEMPERATURE_TABLE = """
[temperature]
source = "simulated"
commissioned_c = 20.0

[simulation.temperature]
start_c = 20.0
k_per_100 = 500.0
screen_above_k = 1.0
"""
MARKS_TABLE = '''
[marks]
centres_mm = [[-450, -380], [0, -380], [450, -380], [-450, 380], [0, 380], [450, 380], [-500, 0], [500, 0]]
diameter_mm = 20.0
'''


def test_good_cycles_raise_no_alarm_and_every_move_is_caught_on_the_next_facet(tmp_path):
    """Two drawn dish stations of the population (400 x 300: marks of 6 px, the hard case; the lens's k1 and the
    twin's optics and noise drawn as the population draws them), their marks commissioned by the routine; 25 good
    cycles each (the facet placed anew every fifth cycle within the fixture's tolerance, each white frame its own
    noise, room light and refresh phase): no facet withheld. With 0 false alarms in 50 cycles the rate is below
    5.8 % at 95 % confidence (1 - 0.05^(1/50)); benchmarks/marks.py runs 1000 (below 0.3 %). The margin is the
    claim that carries: the largest apparent turn of a good cycle stays under a quarter of max_turn_mrad (the
    benchmark's worst of 1000 is in docs/reliability.md).

    Each camera move of the issue (turned by 0.2 mrad about x, y or both; shifted 1 mm along x, y or both) is
    caught on the next frame of both stations, and the apparent turn is the true one: 0.2 mrad for a turn (the
    fixture's marks turn by as much in the camera's view), 1 mm / D for a shift (D = 10.66 m to the fixture:
    0.094 mrad), each within 0.01 mrad (the shift's noise, 0.003 px / 3409 px = 1e-6 rad, and the marks'
    perspective, under 1 %: 0.002 mrad)."""
    from sofast_station.station.marks_study import MUST_CATCH, run_study

    r = run_study(2, 25, seed=5, data_dir=tmp_path, place_every=5, which=MUST_CATCH)
    assert r["cycles"] == 50 and r["false_alarms"] == 0, [g["reason"] for g in r["good"] if g["withheld"]]
    assert r["false_alarm_upper_95"] == pytest.approx(1 - 0.05 ** (1 / 50))
    assert max(g["turn_fraction"] for g in r["good"]) < 0.25
    assert min(g["found"] for g in r["good"]) == 8
    distance = 10.66
    for name, per_station in r["moves"].items():
        assert all(m["caught"] for m in per_station), (name, per_station)
        assert all("the camera has moved by" in m["reason"] for m in per_station)
        want = 0.2 if name.startswith("turn") else 1.0 / distance
        for m in per_station:
            assert np.hypot(*m["turn_mrad"][:2]) == pytest.approx(want, abs=0.01), (name, m["turn_mrad"])
    # the commissioned places are the twin's marks (the routine's mean of 4 frames), to a hundredth of a pixel
    assert max(r["commissioned_vs_truth_px"]) < 0.03


@pytest.fixture
def marked_station(tmp_path) -> Path:
    """The small simulated dish station (400 x 300) with the shipped station file's marks."""
    from tests.conftest import SMALL_STATION

    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json")
                    + MARKS_TABLE + "\n[run]\ndeadline_s = 600.0\nwarmup = false\nstandby_worker = false\n"
                    + TEMPERATURE_TABLE)
    return path


def test_a_moved_camera_holds_the_line_until_the_marks_are_taken_again(marked_station):
    """`calibrate marks` commissions the marks. The first facet is judged (the marks where they were: the fixture
    pose their small shift leaves unknown widens the placement's and the optical tilt's U, by what the row says);
    the twin's camera is then turned by 0.2 mrad. The next two facets are withheld: the robot hears fault 7
    (calibration) with the reason and the line's warning bit; the page's alarm is raised (status line-geometry,
    which OPC UA's Alarms/Line follows); every row says what the marks showed. The hold outlives the line (a
    restart is held too), and a newer marks record (calibrate marks) ends it.

    The hall warms by 5 K a facet (item 4): every row, and every dump (the withheld facets' frames are dumped)
    holds the reading; `calibrate marks` took the commissioning's (20 / 21 degC, the simulated hall's first
    reading); the judged facet's budget has the thermal row: its placement's U grows by twice the structure's
    expansion, 12e-6 /K x the camera's 10.66 m to the fixture x sqrt(dT^2 + 0.5^2) along its line of sight."""
    from sofast_station.archive import Journal, read_dump
    from sofast_station.live.status import read_status
    from sofast_station.station.commissioning import run_marks
    from sofast_station.station.marks import MarkCheck
    from sofast_station.station.service import Service
    from sofast_station.web.opcua import values

    step = run_marks(load_config(marked_station))
    assert step.verdict == "pass", step.summary
    config = load_config(marked_station)
    lines: list[str] = []
    service = Service(config, simulated_facets=3, console=lines.append)
    robot = service.trigger

    def bump(outcome):
        if outcome.serial == "SIM-0001":
            service.station.move_camera(turn_mrad=(0.0, 0.2, 0.0))

    try:
        service.runner.run(on_outcome=bump)
        status = read_status(config.data_dir)
    finally:
        service.close()
    answers = [a for a in robot.answers if a.kind in ("done", "fault")]
    assert [a.kind for a in answers] == ["done", "fault", "fault"]
    assert not answers[0].warnings & WARNING_BITS["line"]
    assert all(a.code == FAULT_CODES["calibration"] and a.warnings & WARNING_BITS["line"] for a in answers[1:])
    assert "the camera has moved by 0.7 px (0.20 mrad" in answers[1].reason
    assert "calibrate confirm-geometry" in answers[1].reason
    assert "line-geometry" in status["alarms"]
    snap = {"status": status, "summary": type("S", (), {"total": 3, "yield_fraction": None, "cycle_median_s": None,
                                                         "cycle_worst_s": None, "counts": {}})(),
            "calibration": {}, "disk": {}, "station": "s", "shift_start": None,
            "alarms": sorted(status["alarms"].items())}
    assert values(snap)["Alarms/Line"] is True
    # the page shows the station's own health beside the facets' (item 5)
    from sofast_station.web.render import station_html

    page = station_html({**snap, "calibration": {}, "disk": {"workbook_backlog": 0, "dump_backlog": 0,
                                                              "spool_files": 0}})
    assert "geometry (fixture marks)" in page and "HOLD: the camera has moved by 0.7 px" in page
    assert "hall 30.0 degC, screen 31.0 degC: +10.0 K and +10.0 K from commissioning" in page
    assert any(line.startswith("LINE ALARM: geometry: the camera has moved") for line in lines)
    journal = Journal(config.data_dir / "journal.sqlite3")
    try:
        rows = {r.serial: r.record for r in journal.rows()}
    finally:
        journal.close()
    first = rows["SIM-0001"]["station_checks"]["marks"]
    assert first["withhold"] is None and first["found"] == 8
    hall = [rows[s]["station_checks"]["temperature"]["hall_c"] for s in ("SIM-0001", "SIM-0002", "SIM-0003")]
    assert hall == [20.0, 25.0, 30.0]
    temp = rows["SIM-0001"]["station_checks"]["temperature"]
    assert temp["commissioned"]["from"].startswith("marks record") and temp["screen_c"] == 21.0
    along = 12e-6 * 10.66e3 * 0.5                        # dT = 0: the reading's own 0.5 K
    assert sum(temp["u"]["fixture_translation_mm"]) == pytest.approx(along, rel=0.02)
    assert max(v for k, v in temp["widened_U"].items() if k.startswith("placement.mm")) == pytest.approx(
        2 * along, rel=0.02)
    dumps = sorted((config.data_dir / "dumps").rglob("*.h5"))
    assert dumps and all(read_dump(d, load_frames=False).record["station_checks"]["temperature"]["hall_c"] in
                         (25.0, 30.0) for d in dumps)
    assert first["widened_U"]["optical_tilt_mrad.x"] == pytest.approx(2 * first["pose_u"]["rotation_mrad"][0])
    assert first["widened_U"]["placement.mm.0"] == pytest.approx(2 * first["pose_u"]["translation_mm"][0])
    for serial in ("SIM-0002", "SIM-0003"):
        marks = rows[serial]["station_checks"]["marks"]
        assert marks["withhold"] and marks["found"] == 8
        assert abs(marks["turn_mrad"][1]) == pytest.approx(0.2, abs=0.01)
    # the hold outlives the line, and a new marks record ends it
    again = load_config(marked_station)
    assert MarkCheck.open(again).held
    hold = json.loads((config.data_dir / "calibration" / "marks" / "hold.json").read_text())
    assert hold["against"] == step.data["record_id"] and "0.20 mrad" in hold["reason"]
    step2 = run_marks(again)
    assert step2.verdict == "pass" and step2.data["hold_ended"]
    assert not MarkCheck.open(load_config(marked_station)).held


def test_marks_out_of_view_are_refused_at_commissioning_and_a_typo_at_load(marked_station, tmp_path):
    """A mark the camera cannot see is refused by `calibrate marks` (no record) naming the mark and what to
    check; [marks] with an unknown key stops the station at load naming the file, the section and the key."""
    from sofast_station.calibrate.store import list_records
    from sofast_station.errors import ConfigError
    from sofast_station.station.commissioning import run_marks

    off = tmp_path / "off.toml"
    off.write_text(marked_station.read_text().replace("[500, 0]]", "[500, 0], [2500, 0]]"))
    config = load_config(off)
    step = run_marks(config)
    assert step.verdict == "refused" and "mark 8" in step.summary and "not found" in step.summary
    assert not list_records(config.data_dir, "marks")
    typo = tmp_path / "typo.toml"
    typo.write_text(marked_station.read_text().replace("diameter_mm", "diametre_mm"))
    with pytest.raises(ConfigError, match=r"\[marks\] has unknown key\(s\) diametre_mm"):
        load_config(typo)
