"""The archiver: one pass drains journal and spool, reruns are no-ops, problems wait or are recorded."""

from __future__ import annotations

import errno
import os
import time

import numpy as np
import pytest

from sofast_station.archive import archiver as amod
from sofast_station.archive.archiver import Archiver, ArchiverSettings
from sofast_station.archive.dumps import dump_path_for, list_dumps, read_dump, write_dump
from sofast_station.archive.dumps import writer as dump_writer
from sofast_station.archive.journal import Journal
from sofast_station.archive.spool import spool_list, spool_path, spool_put
from sofast_station.archive.workbook import read_workbook, workbook_path

from .conftest import make_record, synthetic_content


@pytest.fixture
def setup(tmp_path):
    with Journal(tmp_path / "journal.sqlite") as j:
        yield j, tmp_path / "data"


def test_one_pass_writes_rows_and_dumps_and_a_second_pass_does_nothing(setup, small_config):
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    contents = [synthetic_content(small_config, f"c{i}", make_record(f"S{i}"), seed=i) for i in range(3)]
    arch.submit("c0", contents[0].record, contents[0])
    arch.submit("c1", contents[1].record)                     # no dump requested
    arch.submit("c2", contents[2].record, contents[2])
    assert len(spool_list(data / "spool")) == 2
    report = arch.run_once()
    assert report.workbook_rows == 3 and len(report.dumps_written) == 2 and report.spools_removed == 2
    book = workbook_path(data / "archive", "2026-03-02")
    assert [r["cycle_id"] for r in read_workbook(book)] == ["c0", "c1", "c2"]
    for c in (contents[0], contents[2]):
        row = journal.get(c.cycle_id)
        assert row.dump_status == "written"
        assert row.dump_path == str(dump_path_for(data / "dumps", c.serial, c.time, c.cycle_id))
        assert np.array_equal(read_dump(row.dump_path).frames_cropped, c.frames_cropped)
    assert journal.get("c1").dump_status == "not requested"
    assert spool_list(data / "spool") == []
    stamps = {p: p.stat().st_mtime_ns for p in [book, *list_dumps(data / "dumps")]}
    again = arch.run_once()
    assert again.workbook_rows == 0 and again.dumps_written == [] and again.dumps_failed == {}
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps


def test_a_dump_renamed_before_the_journal_mark_is_not_rewritten(setup, small_config):
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    c = synthetic_content(small_config, "c0")
    arch.submit("c0", c.record, c)
    final = dump_path_for(data / "dumps", c.serial, c.time, c.cycle_id)
    write_dump(final, c)                                      # as if the archiver died right after the rename
    before = final.stat().st_mtime_ns
    report = arch.run_once()
    assert report.dumps_written == [final] and final.stat().st_mtime_ns == before
    assert journal.get("c0").dump_path == str(final) and spool_list(data / "spool") == []


def test_a_spool_left_after_the_mark_is_removed(setup, small_config):
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    c = synthetic_content(small_config, "c0")
    arch.submit("c0", c.record, c)
    journal.mark_dump("c0", data / "somewhere.h5")            # as if the archiver died before deleting the spool
    report = arch.run_once()
    assert report.spools_removed == 1 and spool_list(data / "spool") == []


def test_missing_bad_and_orphaned_spools(setup, small_config):
    journal, data = setup
    settings = ArchiverSettings(min_free_gb=0.0, missing_spool_grace_s=3600, orphan_spool_age_s=3600)
    journal.append("lost", make_record("S-LOST"), dump_requested=True)       # the station died before spooling
    report = Archiver(journal, data, settings).run_once()
    assert report.dumps_waiting == 1 and journal.get("lost").dump_status == "pending"   # still within the grace
    settings = ArchiverSettings(min_free_gb=0.0, missing_spool_grace_s=0, orphan_spool_age_s=0)
    (data / "spool").mkdir(parents=True)
    bad = spool_path(data / "spool", "bad")
    bad.write_bytes(b"not an npz")
    journal.append("bad", make_record("S-BAD"), dump_requested=True)
    c = synthetic_content(small_config, "orphan")
    spool_put(data / "spool", "orphan", *c.to_spool())                       # spooled, never journaled
    report = Archiver(journal, data, settings).run_once()
    assert set(report.dumps_failed) == {"lost", "bad"}
    assert "no spool" in journal.get("lost").dump_error
    assert "unusable spool" in journal.get("bad").dump_error and "not an .npz" in journal.get("bad").dump_error
    assert (data / "spool" / "bad" / "bad.npz").exists()
    assert (data / "spool" / "orphaned" / "orphan.npz").exists()
    assert spool_list(data / "spool") == [] and journal.pending_dumps() == []


def test_dumps_wait_while_the_disk_is_short_or_full(setup, small_config, monkeypatch):
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=5.0))
    c = synthetic_content(small_config, "c0")
    arch.submit("c0", c.record, c)
    monkeypatch.setattr(amod, "disk_ok", lambda folder, min_free_gb: (False, 0.5))
    report = arch.run_once()
    assert report.dumps_waiting == 1 and report.dumps_written == [] and len(spool_list(data / "spool")) == 1
    monkeypatch.setattr(amod, "disk_ok", lambda folder, min_free_gb: (True, 50.0))

    def full(record):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(dump_writer, "_flat_figures", full)                            # fails while writing
        report = arch.run_once()
    assert report.dumps_waiting == 1 and journal.get("c0").dump_status == "pending"
    assert list_dumps(data / "dumps") == [] and not list((data / "dumps").rglob("*.tmp"))
    report = arch.run_once()
    assert len(report.dumps_written) == 1 and spool_list(data / "spool") == []


def test_background_thread_drains_and_stops(setup, small_config):
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0, poll_interval_s=0.05, workbook_interval_s=0.0))
    arch.start()
    try:
        assert arch.running
        for i in range(4):
            c = synthetic_content(small_config, f"c{i}", make_record(f"S{i}"), seed=i)
            arch.submit(c.cycle_id, c.record, c if i % 2 else None)
        deadline = time.monotonic() + 30
        while (journal.pending_workbook() or journal.pending_dumps()) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        t0 = time.monotonic()
        assert arch.stop(timeout_s=30)
    assert time.monotonic() - t0 < 10 and not arch.running
    assert journal.pending_workbook() == [] and journal.pending_dumps() == []
    assert len(read_workbook(workbook_path(data / "archive", "2026-03-02"))) == 4
    assert len(list_dumps(data / "dumps")) == 2


def test_stale_temp_files_of_dead_writers_are_removed(setup):
    journal, data = setup
    (data / "archive").mkdir(parents=True)
    dead = data / "archive" / ".results-2026-03-02.xlsx.999999999.0123abcd.tmp"   # no such process
    mine = data / "archive" / f".results-2026-03-02.xlsx.{os.getpid()}.0123abcd.tmp"
    dead.write_bytes(b"x")
    mine.write_bytes(b"x")
    Archiver(journal, data).run_once()
    assert not dead.exists() and mine.exists()


def test_thread_batches_workbook_saves_and_stop_can_drain(setup):
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0, poll_interval_s=0.02, workbook_interval_s=3600))
    arch.start()
    deadline = time.monotonic() + 60                          # wait for the first pass (workbook due) to run
    while arch._last_workbook == float("-inf") and time.monotonic() < deadline:
        time.sleep(0.01)
    assert arch._last_workbook > float("-inf"), "the archiver's first pass did not run within 60 s"
    arch.submit("c0", make_record("S0"))
    arch.submit("c1", make_record("S1"))
    time.sleep(0.3)
    assert len(journal.pending_workbook()) == 2               # not due for an hour: the rows wait, safely
    assert arch.stop(timeout_s=30, drain=True)
    assert journal.pending_workbook() == []
    assert [r["cycle_id"] for r in read_workbook(workbook_path(data / "archive", "2026-03-02"))] == ["c0", "c1"]


def test_long_workbook_saves_are_spaced_to_keep_their_share_of_a_core(setup, monkeypatch):
    """A save that took c s of CPU puts the next one c * (1/share - 1) s later (at least the interval)."""
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0, workbook_interval_s=30.0,
                                                    workbook_cpu_share=0.1))
    clock = [100.0]
    arch._cpu_clock = lambda: clock[0]                           # the test's CPU clock, not the machine's
    real = amod.write_pending

    def save_costing(cpu_s):
        def save(*args, **kwargs):
            clock[0] += cpu_s
            return real(*args, **kwargs)
        return save

    assert arch.workbook_gap_s == 30.0
    arch.submit("c0", make_record("S0"))
    monkeypatch.setattr(amod, "write_pending", save_costing(12.0))    # a nearly full part
    arch.run_once(dumps=False)
    assert arch.workbook_gap_s == pytest.approx(108.0)                          # 12 s in every 120 s: 10 %
    assert [r["cycle_id"] for r in read_workbook(workbook_path(data / "archive", "2026-03-02"))] == ["c0"]
    arch.submit("c1", make_record("S1"))
    monkeypatch.setattr(amod, "write_pending", save_costing(0.5))     # a short part: the interval
    arch.run_once(dumps=False)
    assert arch.workbook_gap_s == 30.0
    assert journal.pending_workbook() == []


def test_a_16_bit_capture_is_dumped_as_it_came(setup, small_config):
    """Issue 28: a faulted facet of a 16-bit camera was retried at every pass and never dumped (the writer
    took uint8 only). Its counts are dumped as they came, read back bit for bit."""
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    c = synthetic_content(small_config, "c16")
    rng = np.random.default_rng(5)
    c.frames_cropped = rng.integers(0, 4096, size=c.frames_cropped.shape, dtype=np.uint16)   # a 12-bit camera
    arch.submit("c16", c.record, c)
    report = arch.run_once()
    assert report.dumps_written and report.dumps_waiting == 0 and not report.dumps_failed
    back = read_dump(journal.get("c16").dump_path)
    assert back.frames_cropped.dtype == np.uint16 and np.array_equal(back.frames_cropped, c.frames_cropped)


def test_a_spool_that_cannot_make_a_dump_is_set_aside_not_retried(setup, small_config):
    """A content error (here frames of float counts) is no disk problem: the dump is marked failed with the
    reason after one pass and its spool kept aside in spool/bad/, instead of being retried at every pass."""
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    c = synthetic_content(small_config, "cf")
    c.frames_cropped = c.frames_cropped.astype(np.float32)
    arch.submit("cf", c.record, c)
    report = arch.run_once()
    assert list(report.dumps_failed) == ["cf"] and "8- or 16-bit" in report.dumps_failed["cf"]
    assert journal.get("cf").dump_status == "failed"
    assert [p.name for p in (data / "spool" / "bad").iterdir()] == [spool_path(data / "spool", "cf").name]
    assert arch.run_once().dumps_failed == {}


def test_a_dumps_folder_that_cannot_be_written_mid_run_is_said_once(setup, small_config, caplog):
    """Issue 28: with dumps/ unwritable mid-run the archiver printed a traceback every 2 s. The folder of
    the day is made impossible (a file stands where it belongs, which holds for root too): the dump waits
    in the spool, said once over many passes; when the folder is fixed the dump is written and that is said."""
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    c = synthetic_content(small_config, "cw")
    arch.submit("cw", c.record, c)
    day = dump_path_for(data / "dumps", c.serial, c.time, c.cycle_id).parent
    day.parent.mkdir(parents=True)
    day.write_text("in the way")
    with caplog.at_level("INFO", logger="sofast_station.archive"):
        for _ in range(5):
            report = arch.run_once()
            assert report.dumps_waiting == 1 and not report.dumps_written
        assert [r.levelname for r in caplog.records if "waits in the spool" in r.getMessage()] == ["WARNING"]
        assert not [r for r in caplog.records if r.exc_info]
        day.unlink()
        assert arch.run_once().dumps_written
    assert "dumps are written again" in caplog.text
    assert journal.get("cw").dump_status == "written"


def test_a_failing_pass_is_a_traceback_once_then_a_line_every_ten_minutes(setup, monkeypatch, caplog):
    """The background pass retries every couple of seconds; the same error is logged with its traceback
    once, then one line per REPEAT_LOG_S of the archiver's clock (a test clock here), not at every pass."""
    journal, data = setup
    arch = Archiver(journal, data, ArchiverSettings(min_free_gb=0.0))
    clock = [1000.0]
    monkeypatch.setattr(amod.time, "monotonic", lambda: clock[0])
    with caplog.at_level("INFO", logger="sofast_station.archive"):
        for _ in range(700):                            # 23 minutes of passes, one every 2 s
            arch._pass_failed(PermissionError(13, "Permission denied"))
            clock[0] += 2.0
    lines = [r for r in caplog.records if "pass" in r.getMessage()]
    assert len(lines) == 3 and lines[0].exc_info is not None and "still fail" in lines[1].getMessage()
