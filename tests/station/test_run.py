"""Issue 5: the production loop on the simulated station.

Twenty facets on the full-resolution default station with three injected faults (a dark capture, a camera
timeout, a misplaced facet) and a hung analysis worker: twenty answers to the robot, every good facet (the
hung worker's one by its rerun on the standby) within the core's tolerances of the twin's truth, every
fault with its reason and the next facet measured, twenty rows
in the journal and the workbook, the requested dumps present, and a dump that reprocesses to exactly its
archived figures.
"""

from __future__ import annotations

import dataclasses
import json
import signal
import subprocess
import sys

import pytest

from sofast_station.archive import Journal, read_dump, read_workbook
from sofast_station.result.record import FIGURE_KEYS
from sofast_station.station.service import Service
from tests.station.test_facets import FACETS, check_against_truth
from tests.conftest import load_station

FAULTS = {"SIM-0004": "dark", "SIM-0008": "camera-timeout", "SIM-0012": "misplaced"}
#: The analysis worker hangs on this facet: the facet is measured all the same, by its rerun on the standby.
HUNG = "SIM-0016"


@pytest.fixture(scope="module")
def twenty(repo_root, tmp_path_factory):
    data = tmp_path_factory.mktemp("run")
    cfg = load_station(repo_root / "station.toml", data)
    # Time is controlled, not raced: the deadline is far beyond a facet's time on a loaded machine (the
    # worker is warmed up before the first facet), and the hung analysis never ends, so it is run again on
    # the standby (after 3 times the usual analysis time) and its first worker killed. On a machine made
    # very busy (load 14 on two cores a facet took up to 80 s) a good facet may pass the deadline too: the
    # grace lets its analysis finish, and it is then checked as a late result (_late_by_load).
    raw = dict(cfg.raw, run={"deadline_s": 40.0, "late_grace_s": 60.0, "dump_every_n": 5},
               archive={"workbook_interval_s": 1.0})
    faults = {**FAULTS, HUNG: "hung-analysis"}
    cfg = dataclasses.replace(cfg, data_dir=data, raw=raw,
                              simulation={"seed": 3, "facet": FACETS["dish"][1], "faults": faults, "hang_s": 3600.0})
    lines: list[str] = []
    service = Service(cfg, simulated_facets=20, console=lines.append)
    robot = service.trigger
    try:
        outcomes = service.runner.run()
    finally:
        service.close()                      # waits for the archiver to drain
    return cfg, robot, outcomes, lines


def test_twenty_answers_and_the_line_goes_on(twenty):
    cfg, robot, outcomes, lines = twenty
    finals = [a for a in robot.answers if a.kind in ("done", "fault")]
    assert [a.serial for a in finals] == [f"SIM-{i:04d}" for i in range(1, 21)]
    assert len(lines) == 20
    late = _late_by_load(outcomes)
    for a in finals:
        if a.serial in FAULTS:
            assert a.kind == "fault" and a.reason, a
        elif a.serial in late:                       # a machine so busy the deadline passed: measured late
            assert a.kind == "fault" and a.reason.startswith("timeout"), a
        else:
            assert a.kind == "done" and a.verdict in ("pass", "fail", "invalid"), a
    by_serial = {a.serial: a for a in finals}
    assert "dark everywhere" in by_serial["SIM-0004"].reason
    assert "camera" in by_serial["SIM-0008"].reason
    assert "cut off" in by_serial["SIM-0012"].reason or "misplaced" in by_serial["SIM-0012"].reason
    # the facet whose worker hung is measured by its rerun on the standby, and says so (in time, or late on
    # a very busy machine); so is the facet after it
    assert by_serial[HUNG].kind == "done" or HUNG in late
    hung = next(o for o in outcomes if o.serial == HUNG)
    assert any("run again on the standby worker" in n for n in hung.record["capture_notes"]), hung.record
    assert by_serial["SIM-0017"].kind == "done" or "SIM-0017" in late


def _late_by_load(outcomes) -> set:
    """Serials of facets without an injected fault whose analysis ended after the deadline.

    The deadline (40 s) is far beyond a facet's time on a loaded machine, but a machine made busy enough
    can pass it (in a run at load 14 on two cores SIM-0013 and SIM-0017 took 44 and 83 s): the station
    then does what it must, answers the robot "timeout" and journals the late result with its figures and
    verdict (``late_verdict``). Such a facet is checked
    like any other: its figures against the truth, its row, its dump. A facet that timed out without a
    late result is not in this set, so the tests fail on it."""
    return {o.serial for o in outcomes if o.serial not in FAULTS and o.answer == "fault"
            and o.record.get("late") and o.record.get("late_verdict")}


def test_good_facets_meet_the_core_tolerances(twenty):
    _, _, outcomes, _ = twenty
    late = _late_by_load(outcomes)
    good = [o for o in outcomes if o.answer != "fault" or o.serial in late]
    assert len(good) == 17                           # SIM-0016's by its rerun
    for o in good:
        check_against_truth(o.record, long_focus=False)
        assert o.record.get("late_verdict", o.record["verdict"]) == "pass", o.record["reasons"]


def test_journal_workbook_and_dumps(twenty):
    cfg, _, outcomes, _ = twenty
    journal = Journal(cfg.data_dir / "journal.sqlite3")
    try:
        rows = journal.rows()
        assert [r.serial for r in rows] == [f"SIM-{i:04d}" for i in range(1, 21)]
        assert all(r.workbook_path for r in rows), "every row reached a workbook"
        books = sorted((cfg.data_dir / "archive").glob("*.xlsx"))
        assert books and sum(len(read_workbook(b)) for b in books) == 20
        # dumps: every 5th facet, and every faulted one that has frames (dark, misplaced, and a facet measured
        # late on a very busy machine)
        wanted = {"SIM-0005", "SIM-0010", "SIM-0015", "SIM-0020", "SIM-0004", "SIM-0012"}
        wanted |= _late_by_load(outcomes)
        dumped = {r.serial for r in rows if r.dump_status == "written"}
        assert dumped == wanted
        for r in rows:
            if r.dump_status == "written":
                assert read_dump(r.dump_path, load_frames=False).cycle_id == r.cycle_id
    finally:
        journal.close()


def test_a_dump_reprocesses_to_exactly_its_archived_figures(twenty):
    cfg, _, outcomes, _ = twenty
    journal = Journal(cfg.data_dir / "journal.sqlite3")
    try:
        row = next(r for r in journal.rows() if r.serial == "SIM-0010")
    finally:
        journal.close()
    archived = json.loads(json.dumps(row.record))
    again = read_dump(row.dump_path).analyse().figures
    for k in FIGURE_KEYS + ("coefficients", "placement", "valid_fraction", "iterations", "higher_order"):
        got = json.loads(json.dumps(again[k]))
        assert got == archived[k], k


def test_sigterm_finishes_the_current_facet(small_station_toml, tmp_path):
    """`sofast-station run` stops on SIGTERM after the facet in progress; its row is journaled."""
    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "run", "--config", str(small_station_toml),
                             "--facets", "200"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first = proc.stdout.readline()                  # the header
    second = proc.stdout.readline()                 # the first facet's line
    assert first.split()[:2] == ["n", "serial"] and second.split()[:2] == ["1/200", "SIM-0001"], (first, second)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    facet_lines = [ln for ln in (second + out).splitlines() if ln.split()[1:2] and ln.split()[1].startswith("SIM-")]
    summary = next(ln for ln in out.splitlines() if "facet(s):" in ln)
    assert summary.startswith(f"{len(facet_lines)} facet(s)")
    assert len(facet_lines) < 200
    journal = Journal(tmp_path / "station-data" / "journal.sqlite3")
    try:
        assert journal.count() == len(facet_lines)
    finally:
        journal.close()
