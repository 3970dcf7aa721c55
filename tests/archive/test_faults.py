"""SIGKILL at every named fault-injection point, then a rerun: nothing lost, nothing doubled, nothing half-written.

Each test runs the appender or the archiver in a child process with SOFAST_FAULT set, checks that the
child really died at that point (SIGKILL, and the trace it leaves), checks the state on disk, reruns
without the fault, and checks the end state: every journaled cycle exactly once in the journal and the
workbook, every requested dump readable under its final name, no spool or temporary file left.
"""

from __future__ import annotations

import signal

import numpy as np
from openpyxl import load_workbook

from sofast_station.archive.archiver import Archiver
from sofast_station.archive.dumps import list_dumps, read_dump
from sofast_station.archive.journal import Journal
from sofast_station.archive.spool import spool_list
from sofast_station.archive.workbook import read_workbook, workbook_path

from .conftest import make_record, run_child, synthetic_content

APPEND = """
import sys
from sofast_station.archive.journal import Journal
from tests.archive.conftest import make_record
Journal(sys.argv[1]).append(sys.argv[2], make_record(sys.argv[3]))
print("appended")
"""

ARCHIVE = """
import sys, logging
logging.basicConfig(level=logging.INFO)
from sofast_station.archive.archiver import Archiver, ArchiverSettings
from sofast_station.archive.journal import Journal
r = Archiver(Journal(sys.argv[1]), sys.argv[2], ArchiverSettings(min_free_gb=0.0)).run_once()
print("rows", r.workbook_rows, "dumps", len(r.dumps_written))
"""


def temp_files(folder):
    return sorted(p for p in folder.rglob("*.tmp"))


def check_end_state(journal_path, data_dir, expected_ids, dump_ids=()):
    """Every cycle once in the journal and once in the workbook; dumps complete; nothing left over."""
    with Journal(journal_path) as j:
        assert j.integrity_ok()
        rows = j.rows()
        assert sorted(r.cycle_id for r in rows) == sorted(expected_ids)
        assert j.pending_workbook() == [] and j.pending_dumps() == []
        book = workbook_path(data_dir / "archive", "2026-03-02")
        load_workbook(book)                                       # opens with openpyxl
        ids = [r["cycle_id"] for r in read_workbook(book)]
        assert sorted(ids) == sorted(expected_ids)                # no row lost, none doubled
        assert {r.workbook_path for r in rows} == {str(book)}
        for cid in dump_ids:
            row = j.get(cid)
            assert row.dump_status == "written"
            assert read_dump(row.dump_path).cycle_id == cid
    assert spool_list(data_dir / "spool") == []
    assert temp_files(data_dir) == []


def test_kill_inside_the_journal_append(tmp_path):
    jp, data = tmp_path / "journal.sqlite", tmp_path / "data"
    with Journal(jp) as j:
        for i in range(3):
            j.append(f"c{i}", make_record(f"S{i}"))
    proc = run_child(APPEND, jp, "c3", "S3", fault="journal-append")
    assert proc.returncode == -signal.SIGKILL and "appended" not in proc.stdout, proc.stderr
    with Journal(jp) as j:                      # the transaction died with the process: no row, no damage
        assert j.integrity_ok() and j.count() == 3 and j.get("c3") is None
    for _ in range(2):                          # the station retries; a second retry is a no-op
        proc = run_child(APPEND, jp, "c3", "S3")
        assert proc.returncode == 0, proc.stderr
    with Journal(jp) as j:
        assert j.count() == 4
        Archiver(j, data).run_once()
    check_end_state(jp, data, ["c0", "c1", "c2", "c3"])


def _book_with_three_then_two_pending(jp, data):
    with Journal(jp) as j:
        for i in range(3):
            j.append(f"c{i}", make_record(f"S{i}"))
        Archiver(j, data).run_once()
        for i in (3, 4):
            j.append(f"c{i}", make_record(f"S{i}"))
    return workbook_path(data / "archive", "2026-03-02")


def test_kill_after_the_workbook_temp_file_is_written(tmp_path):
    jp, data = tmp_path / "journal.sqlite", tmp_path / "data"
    book = _book_with_three_then_two_pending(jp, data)
    proc = run_child(ARCHIVE, jp, data, fault="workbook-temp-written")
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert len(temp_files(data / "archive")) == 1                  # died with the full temp file written
    assert [r["cycle_id"] for r in read_workbook(book)] == ["c0", "c1", "c2"]   # the book is the old one
    with Journal(jp) as j:
        assert [r.cycle_id for r in j.pending_workbook()] == ["c3", "c4"]
    proc = run_child(ARCHIVE, jp, data)
    assert proc.returncode == 0, proc.stderr
    check_end_state(jp, data, [f"c{i}" for i in range(5)])


def test_kill_after_the_workbook_rename_before_the_journal_mark(tmp_path):
    jp, data = tmp_path / "journal.sqlite", tmp_path / "data"
    book = _book_with_three_then_two_pending(jp, data)
    proc = run_child(ARCHIVE, jp, data, fault="workbook-renamed")
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert [r["cycle_id"] for r in read_workbook(book)] == [f"c{i}" for i in range(5)]   # renamed in place
    with Journal(jp) as j:
        assert [r.cycle_id for r in j.pending_workbook()] == ["c3", "c4"]              # but not marked
    proc = run_child(ARCHIVE, jp, data)
    assert proc.returncode == 0, proc.stderr
    assert "rows 0" in proc.stdout                                   # found in the book, marked, not rewritten
    check_end_state(jp, data, [f"c{i}" for i in range(5)])


def test_kill_in_the_middle_of_a_dump(tmp_path, small_config):
    jp, data = tmp_path / "journal.sqlite", tmp_path / "data"
    contents = {}
    with Journal(jp) as j:
        arch = Archiver(j, data)
        for i in range(2):
            c = synthetic_content(small_config, cycle_id=f"d{i}", record=make_record(f"S{i}"), seed=i)
            contents[c.cycle_id] = c
            arch.submit(c.cycle_id, c.record, c)
    proc = run_child(ARCHIVE, jp, data, fault="dump-mid-write")
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert list_dumps(data / "dumps") == []                           # no dump under a final name
    assert len(temp_files(data / "dumps")) == 1                       # only the hidden temporary file
    assert len(spool_list(data / "spool")) == 2                       # the frames are still safe
    with Journal(jp) as j:
        assert [r.cycle_id for r in j.pending_dumps()] == ["d0", "d1"]
    proc = run_child(ARCHIVE, jp, data)
    assert proc.returncode == 0, proc.stderr
    check_end_state(jp, data, ["d0", "d1"], dump_ids=["d0", "d1"])
    with Journal(jp) as j:
        for cid, c in contents.items():
            back = read_dump(j.get(cid).dump_path)
            assert np.array_equal(back.frames_cropped, c.frames_cropped) and back.record == c.record
