"""Issue 26, item 6: a wall clock that steps backwards is logged as a warning and stated in the row, and
cycle ids stay unique and increasing (station/clock.py). The clock is controlled: a real clock's reading
plus an offset the test steps, against the real monotonic clock."""

from __future__ import annotations

import datetime as _dt
import logging
import time

from sofast_station.archive import Journal
from sofast_station.archive.workbook import period_key
from sofast_station.config import load_config
from sofast_station.station.clock import StationClock, cycle_id_ms, format_cycle_id
from sofast_station.station.service import Service


class SteppedClock:
    """The wall clock as the station would read it, with a step the test sets (``offset``)."""

    def __init__(self, start: _dt.datetime):
        self.start, self.t0 = start, time.monotonic()
        self.offset = _dt.timedelta(0)

    def __call__(self) -> _dt.datetime:
        return self.start + _dt.timedelta(seconds=time.monotonic() - self.t0) + self.offset


START = _dt.datetime(2026, 12, 3, 0, 30, tzinfo=_dt.timezone(_dt.timedelta(hours=1)))


def test_ids_increase_and_a_step_back_is_stated(caplog):
    wall = SteppedClock(START)
    clock = StationClock(wall=wall)
    first, note = clock.next_cycle()
    assert note is None
    wall.offset = -_dt.timedelta(hours=25)
    with caplog.at_level(logging.WARNING):
        second, note = clock.next_cycle()
    assert note and "stepped back by 25.0 h" in note and "check the station's time" in note
    assert any("stepped back by 25.0 h" in r.getMessage() for r in caplog.records)
    third, again = clock.next_cycle()
    assert again is None                                      # one step, stated once
    assert first < second < third and len({first, second, third}) == 3
    assert cycle_id_ms(second) == cycle_id_ms(first) + 1      # the id goes on from the last, not back
    # a forward step (a clock set right again, a suspend) is no fault; ids follow it
    wall.offset = _dt.timedelta(hours=2)
    fourth, note = clock.next_cycle()
    assert note is None and cycle_id_ms(fourth) > cycle_id_ms(third) + 3600_000


def test_a_clock_behind_the_journal_at_start_is_stated_and_ids_go_on_from_it():
    last = format_cycle_id(int(START.timestamp() * 1000), "0123abcd")
    clock = StationClock(wall=SteppedClock(START - _dt.timedelta(hours=25)), last_cycle_id=last, last_time=START)
    cycle_id, note = clock.next_cycle()
    assert cycle_id > last and note and "before the journal's newest row" in note


def test_the_loop_states_a_clock_step_in_the_row_and_keeps_ids_increasing(small_station_toml, caplog):
    """Three facets through the production loop; the wall clock steps back 25 h after the first. Before,
    the second row was filed under the previous day with nothing said, and its cycle id sorted before the
    first's."""
    small_station_toml.write_text(small_station_toml.read_text() + "\n[run]\ndeadline_s = 300\n")  # busy machines
    cfg = load_config(small_station_toml)
    service = Service(cfg, simulated_facets=3, console=lambda line: None, archiver_process=False)
    runner = service.runner
    wall = SteppedClock(START)
    runner.clock = StationClock(wall=wall)

    def step(outcome):
        if outcome.serial == "SIM-0001":
            wall.offset = -_dt.timedelta(hours=25)
    runner.hooks.append(step)
    try:
        with caplog.at_level(logging.WARNING):
            runner.run()
    finally:
        service.close()
    journal = Journal(cfg.data_dir / "journal.sqlite3")
    try:
        rows = sorted(journal.rows(), key=lambda r: r.seq)
    finally:
        journal.close()
    assert [r.serial for r in rows] == ["SIM-0001", "SIM-0002", "SIM-0003"]
    ids = [r.cycle_id for r in rows]
    assert ids == sorted(ids) and len(set(ids)) == 3
    assert "clock_warning" not in rows[0].record and "clock_warning" not in rows[2].record
    warning = rows[1].record["clock_warning"]
    assert "stepped back by 25.0 h" in warning
    # the row keeps the clock's date (the station cannot know which reading was right) and says so
    assert period_key(rows[1].time) == "2026-12-01" and period_key(rows[0].time) == "2026-12-03"
    assert any("stepped back" in r.getMessage() and r.levelno == logging.WARNING for r in caplog.records)
