"""The journal: durable appends, idempotent on the cycle id, re-tests kept, time-range queries."""

from __future__ import annotations

import math
import signal
import sqlite3

import pytest

from sofast_station.archive.journal import Journal, new_cycle_id
from sofast_station.errors import ArchiveError

from .conftest import make_record, run_child

APPEND_THEN_DIE = """
import os, signal, sys, json
from sofast_station.archive.journal import Journal
from tests.archive.conftest import make_record
j = Journal(sys.argv[1])
j.append("cycle-durable", make_record("SER-DURABLE"), dump_requested=True)
print("appended", flush=True)
os.kill(os.getpid(), signal.SIGKILL)   # no close, no checkpoint, no atexit
"""


def test_append_is_durable_when_it_returns(tmp_path):
    path = tmp_path / "journal.sqlite"
    proc = run_child(APPEND_THEN_DIE, path)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert "appended" in proc.stdout
    with Journal(path) as j:
        row = j.get("cycle-durable")
        assert row is not None
        assert row.serial == "SER-DURABLE"
        assert row.record == make_record("SER-DURABLE")
        assert row.dump_status == "pending" and row.workbook_path is None
        assert j.integrity_ok()


def test_wal_mode_and_full_sync(tmp_path):
    with Journal(tmp_path / "j.sqlite") as j:
        assert j._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert j._db.execute("PRAGMA synchronous").fetchone()[0] == 2      # FULL


def test_duplicate_cycle_id_is_a_noop(tmp_path):
    with Journal(tmp_path / "j.sqlite") as j:
        assert j.append("c1", make_record("A"), dump_requested=False) is True
        assert j.append("c1", make_record("A-changed"), dump_requested=True) is False
        assert j.count() == 1
        row = j.get("c1")
        assert row.serial == "A" and not row.dump_requested
        assert [r.cycle_id for r in j.pending_workbook()] == ["c1"]


def test_retest_of_a_serial_keeps_both_rows(tmp_path):
    with Journal(tmp_path / "j.sqlite") as j:
        first, second = new_cycle_id(), new_cycle_id()
        assert first != second
        j.append(first, make_record("SER-7", "2026-03-02T10:00:00+01:00", verdict="fail"))
        j.append(second, make_record("SER-7", "2026-03-02T10:05:00+01:00", verdict="pass"))
        rows = j.rows(serial="SER-7")
        assert [r.cycle_id for r in rows] == [first, second]
        assert [r.verdict for r in rows] == ["fail", "pass"]


def test_time_range_queries_compare_instants(tmp_path):
    times = {"a": "2026-03-01T23:30:00.000+01:00",   # 22:30 UTC on the 1st
             "b": "2026-03-02T00:10:00.000+00:00",   # 00:10 UTC
             "c": "2026-03-01T20:00:00.000-05:00",   # 01:00 UTC on the 2nd
             "d": "2026-03-02T12:00:00.000+00:00"}
    with Journal(tmp_path / "j.sqlite") as j:
        for cid, t in times.items():
            j.append(cid, make_record(f"S-{cid}", t))
        assert [r.cycle_id for r in j.rows()] == ["a", "b", "c", "d"]               # time order, not append order
        assert [r.cycle_id for r in j.rows(since="2026-03-02T00:00:00+00:00")] == ["b", "c", "d"]
        assert [r.cycle_id for r in j.rows(until="2026-03-02T01:00:00Z")] == ["a", "b"]  # until is exclusive
        assert [r.cycle_id for r in j.rows("2026-03-02T00:10:00+00:00", "2026-03-02T12:00:00+00:00")] == ["b", "c"]
        assert j.rows(since="2027-01-01T00:00:00+00:00") == []
        # the newest rows by record time, oldest first, without reading the whole journal (drift priming)
        assert [r.cycle_id for r in j.recent(2)] == ["c", "d"] and [r.cycle_id for r in j.recent(9)] == list("abcd")


def test_pending_queries_and_marks(tmp_path):
    with Journal(tmp_path / "j.sqlite") as j:
        for i in range(4):
            j.append(f"c{i}", make_record(f"S{i}"), dump_requested=i % 2 == 0)
        assert [r.cycle_id for r in j.pending_workbook()] == ["c0", "c1", "c2", "c3"]
        assert [r.cycle_id for r in j.pending_workbook(limit=2)] == ["c0", "c1"]
        assert j.mark_workbook(["c0", "c2"], tmp_path / "book.xlsx") == 2
        assert [r.cycle_id for r in j.pending_workbook()] == ["c1", "c3"]
        assert [r.cycle_id for r in j.rows_in_workbook(tmp_path / "book.xlsx")] == ["c0", "c2"]
        assert [r.cycle_id for r in j.pending_dumps()] == ["c0", "c2"]
        j.mark_dump("c0", tmp_path / "c0.h5")
        j.mark_dump("c2", None, error="disk on fire")
        assert j.pending_dumps() == []
        assert j.get("c0").dump_status == "written" and j.get("c0").dump_path == str(tmp_path / "c0.h5")
        assert j.get("c2").dump_status == "failed" and j.get("c2").dump_error == "disk on fire"
        assert j.get("c1").dump_status == "not requested"
        j.mark_dump("c2", None)                      # neither: pending again
        assert [r.cycle_id for r in j.pending_dumps()] == ["c2"]
        with pytest.raises(ArchiveError, match="no cycle"):
            j.mark_dump("nope", tmp_path / "x.h5")


def test_infinite_and_nan_values_are_stored_as_null(tmp_path):
    rec = make_record("FLAT", focal_length_x_m=math.inf, curvature_x_per_m=float("nan"))
    with Journal(tmp_path / "j.sqlite") as j:
        j.append("flat", rec)
        stored = j.get("flat").record
    assert stored["focal_length_x_m"] is None and stored["curvature_x_per_m"] is None


def test_a_second_connection_reads_what_the_writer_appended(tmp_path):
    path = tmp_path / "j.sqlite"
    with Journal(path) as writer, Journal(path) as reader:
        writer.append("c1", make_record("A"))
        assert reader.get("c1").serial == "A"
        writer.append("c2", make_record("B"))
        assert [r.cycle_id for r in reader.rows()] == ["c1", "c2"]


def test_bad_records_and_files_name_the_problem(tmp_path):
    with Journal(tmp_path / "j.sqlite") as j:
        rec = make_record()
        del rec["time"]
        with pytest.raises(ArchiveError, match="has no 'time'"):
            j.append("c1", rec)
        with pytest.raises(ArchiveError, match="not ISO 8601"):
            j.append("c2", make_record(time="yesterday"))
        assert j.count() == 0
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not a database" * 100)
    with pytest.raises(ArchiveError, match="junk.sqlite"):
        Journal(junk)
    # and the journal's own table is what a plain sqlite3 client sees
    with sqlite3.connect(tmp_path / "j.sqlite") as db:
        assert db.execute("PRAGMA user_version").fetchone()[0] == 1
