"""Issue 28: a hung or crashed analysis costs the line at most one facet.

A warm standby worker takes over at once after a timeout or a crash, while the abandoned worker may still
bring a late result; a worker killed while it starts is started again. Small (400 x 300) simulated station.
No timing is asserted: a hung analysis never ends, so it meets any deadline; the test deadline is the suite's
scaled one, and what is checked is the order of events (the next facet answered while the abandoned
analysis is still within its grace), which a loop that waited out the grace could not produce.
"""

from __future__ import annotations

import dataclasses
import logging
import threading

from sofast_station.archive import Journal, read_dump
from sofast_station.config import load_config
from sofast_station.devices.protocols import FAULT_CODES
from sofast_station.station import worker as worker_module
from sofast_station.station.service import Service, run_settings

from .worker_faults import DIE_ONCE_ENV, alive, ping_dies_once


def _config(path, data, faults=None, run=None, **sim):
    cfg = load_config(path)
    raw = dict(cfg.raw, run={**(run or {})}, archive={"workbook_interval_s": 0.5})
    simulation = {**cfg.simulation, "faults": faults or {}, **sim}
    return dataclasses.replace(cfg, data_dir=data, raw=raw, simulation=simulation)


def _rows(data):
    with Journal(data / "journal.sqlite3") as journal:
        return {r.serial: r for r in journal.rows()}


def test_the_facet_after_a_hung_analysis_is_measured_while_the_hung_one_is_still_in_its_grace(
        small_station_toml, tmp_path):
    """SIM-0002 hangs every worker it is given. At the deadline the robot hears "timeout", the standby
    takes over at once and SIM-0003 is measured on it, while SIM-0002's abandoned analysis is still within
    its (hour-long) grace: the loop no longer waits out the grace and a restart. Stopped, the abandoned
    worker is killed and the facet's row says so, its frames dumped. The deadline, 30 s, is about a hundred
    times this station's analysis (0.3 s) on a quiet machine."""
    cfg = _config(small_station_toml, tmp_path / "d", faults={"SIM-0002": "hung-facet"},
                  run={"late_grace_s": 3600.0, "deadline_s": 30.0}, hang_s=7200.0)
    assert run_settings(cfg).deadline_s == 30.0
    service = Service(cfg, simulated_facets=3, console=lambda line: None)
    robot, worker = service.trigger, service.runner.worker
    seen: dict = {}
    ids: dict[str, str] = {}

    def on_outcome(outcome):
        ids[outcome.serial] = outcome.cycle_id
        seen[outcome.serial] = outcome.answer
        if outcome.serial == "SIM-0003":             # SIM-0002's row as SIM-0003 is answered
            with Journal(cfg.data_dir / "journal.sqlite3") as journal:
                seen["SIM-0002 then"] = journal.get(ids["SIM-0002"]).record
    runner = threading.Thread(target=service.runner.run, kwargs={"on_outcome": on_outcome}, daemon=True)
    try:
        runner.start()
        runner.join(1200)                                # a loop waiting out the grace would still be in it
        assert not runner.is_alive(), f"the loop is stuck after the hung analysis: {seen}"
        worker.close(late_wait_s=0)                      # stop now: the abandoned analysis is given up
    finally:
        service.close()
    finals = {a.serial: a for a in robot.answers if a.kind in ("done", "fault")}
    assert finals["SIM-0002"].kind == "fault" and finals["SIM-0002"].code == FAULT_CODES["timeout"]
    assert finals["SIM-0001"].kind == finals["SIM-0003"].kind == "done", finals
    # SIM-0003 was answered (by the standby) while SIM-0002's row was still the bare timeout: its abandoned
    # analysis was still within its grace
    assert seen["SIM-0003"] == "pass" and seen["SIM-0002 then"]["verdict"] == "fault", seen
    assert "late" not in seen["SIM-0002 then"]
    # the takeover at the deadline, and one more when SIM-0002's stalled analysis was rerun (the start's timed
    # analysis, the warm-up and SIM-0001 make its usual time known)
    assert worker.takeovers == 1 + worker.reruns
    rows = _rows(cfg.data_dir)
    late = rows["SIM-0002"].record
    assert late["verdict"] == "fault" and late["late"] is True and late["fault_code"] == FAULT_CODES["timeout"]
    assert any("no result within the late grace" in r for r in late["reasons"]), late["reasons"]
    assert rows["SIM-0002"].dump_status == "written"
    assert read_dump(rows["SIM-0002"].dump_path, load_frames=True).frames_cropped.shape[0] == 18
    assert rows["SIM-0003"].verdict == "pass" and abs(rows["SIM-0003"].record["focal_length_x_m"] - 5.42) < 0.05


def test_a_hung_worker_costs_its_facet_a_rerun_on_the_standby_not_a_timeout(small_station_toml, tmp_path):
    """The worker hangs on SIM-0004 (its analysis would sleep two hours). After three times the recipe's
    usual analysis time (at least 1 s) the facet is analysed again on the warm standby, which answers: the
    robot hears SIM-0004's verdict, not "timeout", the record says it was rerun, the hung worker is killed,
    and SIM-0005 is measured too. No time is asserted: the deadline is the suite's (120 s), which a hang
    would reach; only the order of events is checked."""
    cfg = _config(small_station_toml, tmp_path / "d", faults={"SIM-0004": "hung-analysis"}, hang_s=7200.0)
    service = Service(cfg, simulated_facets=5, console=lambda line: None)
    robot, worker = service.trigger, service.runner.worker
    hung_pids: list[int] = []
    outcomes = []

    def on_outcome(outcome):
        outcomes.append(outcome)
        if outcome.serial == "SIM-0003":
            hung_pids.extend(worker.pids())             # the worker that will hang on SIM-0004
    try:
        service.runner.run(on_outcome=on_outcome)
    finally:
        service.close()
    finals = {a.serial: a for a in robot.answers if a.kind in ("done", "fault")}
    assert [finals[f"SIM-{i:04d}"].kind for i in range(1, 6)] == ["done"] * 5, finals
    by = {o.serial: o for o in outcomes}
    notes = by["SIM-0004"].record["capture_notes"]
    assert any("run again on the standby worker" in n and "the rerun analysis's result" in n for n in notes), notes
    assert by["SIM-0004"].answer == "pass" and abs(by["SIM-0004"].record["focal_length_x_m"] - 5.42) < 0.05
    assert worker.reruns >= 1 and worker.takeovers >= 1
    assert hung_pids and not any(alive(pid) for pid in hung_pids), hung_pids
    rows = _rows(cfg.data_dir)
    assert rows["SIM-0004"].verdict == "pass" and "late" not in rows["SIM-0004"].record


def test_a_worker_killed_while_it_starts_is_started_again(small_station_toml, tmp_path, monkeypatch, caplog):
    """Killed in the first seconds of `run`, before "analysis worker ready", the worker ended the run (exit
    2, "could not start (BrokenProcessPool ...)", no facet answered). It is started again and the line runs."""
    flag = tmp_path / "die-once"
    flag.touch()
    monkeypatch.setenv(DIE_ONCE_ENV, str(flag))
    monkeypatch.setattr(worker_module, "_ping", ping_dies_once)
    cfg = _config(small_station_toml, tmp_path / "d")
    with caplog.at_level(logging.WARNING, logger="sofast_station.station.worker"):
        service = Service(cfg, simulated_facets=2, console=lambda line: None, archiver_process=False)
        try:
            outcomes = service.runner.run()
        finally:
            service.close()
    assert not flag.exists()                             # a worker did die while starting
    assert "died while starting" in caplog.text
    assert [o.answer for o in outcomes] == ["pass", "pass"]


def test_a_worker_closed_on_two_threads_at_once_frees_its_frames_once(monkeypatch):
    """A retired worker's waiter thread and the stopping station may close the same worker at once; the
    second close once found the shared frames half-freed (AttributeError in the thread 'analysis-retired',
    seen in a CI run). Both closes now return quietly and the buffer is unlinked once."""
    import time
    from multiprocessing import shared_memory

    proc = worker_module._Process((2, 4, 4))
    name = proc.shm.name
    real_close = proc.shm.close

    def slow_close():                    # holds the first close inside the buffer's close for a while
        time.sleep(0.3)
        real_close()

    monkeypatch.setattr(proc.shm, "close", slow_close)
    start = threading.Barrier(2)
    errors = []

    def close():
        start.wait()
        try:
            proc.close()
        except Exception as exc:         # any error is the failure this test looks for
            errors.append(exc)

    threads = [threading.Thread(target=close) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert errors == [] and proc.shm is None and proc.frames is None
    try:
        shared_memory.SharedMemory(name=name).close()
        still_there = True
    except FileNotFoundError:
        still_there = False
    assert not still_there, "the worker's frame buffer was not unlinked"
