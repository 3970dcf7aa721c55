"""Issue 27: the reports leave nothing out without saying so (a result file that cannot be read, a record
whose time cannot be read)."""

from __future__ import annotations

import json
import logging

from sofast_station.report.control_charts import select_records
from sofast_station.report.trend import trend_records_from_results


def test_a_batch_result_that_cannot_be_read_is_named_when_the_trend_leaves_it_out(tmp_path, caplog):
    results = tmp_path / "batch" / "results"
    results.mkdir(parents=True)
    good = {"status": "ok", "serial": "S-1", "time": "2026-03-02T10:15:00.000+01:00", "focal_length_x_m": 5.42}
    (results / "a.json").write_text(json.dumps(good))
    (results / "b.json").write_text('{"status": "ok", "serial": "S-2", "ti')          # cut off mid-write
    (results / "c.json").write_bytes(b"\xff\xfe not text")
    with caplog.at_level(logging.WARNING, logger="sofast_station.report.trend"):
        got = trend_records_from_results(tmp_path / "batch")
    assert [r["serial"] for r in got] == ["S-1"]
    text = caplog.text
    assert "leaves out 2 unreadable result file(s)" in text and "b.json" in text and "c.json" in text


def test_a_record_whose_time_cannot_be_read_is_named_when_the_charts_leave_it_out(caplog):
    records = [{"serial": "S-1", "cycle_id": "c1", "time": "2026-03-02T10:15:00.000+01:00", "verdict": "pass"},
               {"serial": "S-2", "cycle_id": "c2", "time": "not a time", "verdict": "pass"},
               {"serial": "S-3", "cycle_id": "c3", "verdict": "pass"}]
    with caplog.at_level(logging.WARNING, logger="sofast_station.report.control_charts"):
        got = select_records(records)
    assert [r["serial"] for r in got] == ["S-1"]
    assert "2 record(s) left out: their time cannot be read" in caplog.text
    assert "S-2 (cycle c2" in caplog.text and "S-3 (cycle c3" in caplog.text
