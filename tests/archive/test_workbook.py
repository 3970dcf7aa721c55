"""Excel workbooks: every figure flattened, one book per period, atomic saves, rows never lost or doubled."""

from __future__ import annotations

import datetime as dt
import errno
import os
import tempfile

import pytest
from openpyxl import load_workbook

from sofast_station.archive import workbook as wbmod
from sofast_station.files import is_temp_file
from sofast_station.archive.journal import Journal
from sofast_station.archive.workbook import (FIRST_COLUMNS, WorkbookSettings, export_workbook, period_key,
                                             read_workbook, workbook_path, write_pending)

from .conftest import SAMPLE_RECORD, make_record


def leaves(prefix, value, out):
    """Independent flattening: dotted names of every non-dict leaf."""
    if isinstance(value, dict):
        for k, v in value.items():
            leaves(f"{prefix}.{k}" if prefix else k, v, out)
    else:
        out[prefix] = value
    return out


def temp_files(folder):
    return [p for p in folder.iterdir() if p.name.endswith(".tmp")]


@pytest.fixture
def journal(tmp_path):
    with Journal(tmp_path / "journal.sqlite") as j:
        yield j


def test_a_row_holds_every_figure_of_the_record(journal, tmp_path):
    folder = tmp_path / "archive"
    journal.append("cycle-1", SAMPLE_RECORD)
    report = write_pending(journal, folder)
    book = workbook_path(folder, "2026-11-25")
    assert report.written == {str(book): 1} and journal.pending_workbook() == []
    assert journal.get("cycle-1").workbook_path == str(book)
    header = [c.value for c in load_workbook(book)["results"][1]]
    assert tuple(header[:6]) == FIRST_COLUMNS
    (row,) = read_workbook(book)
    expected = leaves("", SAMPLE_RECORD, {})
    assert "slope_rms_mrad.design.x" in expected and "truth.slope_rms_mrad.parabola.magnitude" in expected
    assert row["cycle_id"] == "cycle-1"
    for name, value in expected.items():
        assert name in header, name
        if name == "time":        # an Excel date and time: the record's local wall clock, offset beside it
            assert row[name] == dt.datetime(2026, 11, 25, 14, 40, 35, 89000) and row["utc_offset"] == "+00:00"
        elif isinstance(value, list):                             # lists as readable text
            assert row.get(name, "") == "; ".join(f"{v:.10g}" if isinstance(v, float) else str(v) for v in value), name
        elif isinstance(value, float):
            assert row[name] == float("%.16g" % value), name     # openpyxl writes 16 significant digits
        else:
            assert row[name] == value, name
    assert len(header) == len(expected) + 3                       # + cycle_id, dump_file, utc_offset
    assert "dump_file" not in row                                 # no dump requested: an empty cell
    units = dict(load_workbook(book)["units"].iter_rows(min_row=2, values_only=True))
    assert units["focal_length_x_m"] == "m" and units["slope_rms_mrad.design.x"] == "mrad"
    assert units["twist_mrad_per_m"] == "mrad/m" and units["curvature_x_per_m"] == "1/m"


def test_the_plant_reads_dates_as_dates_numbers_as_numbers_and_the_dump_name(journal, tmp_path):
    journal.append("cycle-7", SAMPLE_RECORD, dump_requested=True)
    out = tmp_path / "export.xlsx"
    export_workbook(journal, None, None, out)
    ws = load_workbook(out)["results"]
    cols = {c.value: c.column for c in ws[1]}
    t = ws.cell(2, cols["time"])
    assert t.is_date and isinstance(t.value, dt.datetime) and t.number_format == "yyyy-mm-dd hh:mm:ss"
    f = ws.cell(2, cols["focal_length_x_m"])
    assert f.data_type == "n" and isinstance(f.value, float)
    assert ws.cell(2, cols["n_points"]).data_type == "n"
    assert ws.cell(2, cols["reasons"]).value is None                        # no reasons: an empty cell
    assert ws.cell(2, cols["dump_file"]).value.startswith("SIM-0001_20261125T144035_cycle-7")
    # a hardware station's record has no truth: no truth.* column
    hw = {k: v for k, v in SAMPLE_RECORD.items() if k != "truth"}
    journal.append("cycle-8", dict(hw, serial="HW-1"))
    export_workbook(journal, "2026-11-25", "2026-11-26", out)
    header = [c.value for c in load_workbook(out)["results"][1]]
    assert any(h.startswith("truth.") for h in header)                      # the simulated row has them
    journal2 = Journal(tmp_path / "hw.sqlite")
    journal2.append("cycle-9", hw)
    export_workbook(journal2, None, None, tmp_path / "hw.xlsx")
    journal2.close()
    assert not any(c.value.startswith("truth.") for c in load_workbook(tmp_path / "hw.xlsx")["results"][1])


def test_number_formats_and_header(journal, tmp_path):
    journal.append("c1", make_record())
    write_pending(journal, tmp_path)
    ws = load_workbook(workbook_path(tmp_path, "2026-03-02"))["results"]
    cols = {c.value: c.column for c in ws[1]}
    assert ws.cell(1, 1).font.b and ws.freeze_panes == "B2"
    assert ws.cell(2, cols["slope_rms_mrad.design.x"]).number_format == "0.0000"
    assert ws.cell(2, cols["focal_length_x_m"]).number_format == "0.000000"
    assert ws.cell(2, cols["n_points"]).number_format == "0"
    assert ws.cell(2, cols["coefficients.C"]).number_format == "0.000000E+00"


def test_a_figure_with_its_u_shows_the_decimals_every_screen_writes_it_with(journal, tmp_path):
    """Issue 43: f_x read 5.420522 (0.000969) in the workbook and 5.42052 ± 0.00097 on the console. A figure's
    cell and its U's show U's two significant digits' place (GUM 7.2.6), the values kept whole; nested figures
    (slope RMS) and a U of tens too; a figure without U keeps its column's format."""
    rec = make_record(focal_length_x_m=5.420521550041019, focal_length_x_m_U=0.000969132939163216,
                      twist_mrad_per_m=-1.0, twist_mrad_per_m_U=63.2)
    rec["slope_rms_mrad_U"] = {"design": {"x": 0.0049, "y": 0.0034, "magnitude": 0.00431}}
    journal.append("c1", rec)
    write_pending(journal, tmp_path)
    ws = load_workbook(workbook_path(tmp_path, "2026-03-02"))["results"]
    cols = {c.value: c.column for c in ws[1]}
    for column, fmt in (("focal_length_x_m", "0.00000"), ("focal_length_x_m_U", "0.00000"),
                        ("slope_rms_mrad.design.magnitude", "0.0000"), ("slope_rms_mrad_U.design.magnitude", "0.0000"),
                        ("twist_mrad_per_m", "0"), ("twist_mrad_per_m_U", "0"),
                        ("focal_length_y_m", "0.000000"), ("slope_rms_mrad.parabola.x", "0.0000")):
        assert ws.cell(2, cols[column]).number_format == fmt, column
    assert ws.cell(2, cols["focal_length_x_m"]).value == 5.420521550041019          # every digit kept


def test_one_book_per_local_day_and_per_shift(journal, tmp_path):
    late = make_record("A", "2026-03-01T23:30:00.000+01:00")       # 22:30 UTC, but the 1st locally
    early = make_record("B", "2026-03-02T00:10:00.000+01:00")      # 23:10 UTC on the 1st, the 2nd locally
    journal.append("late", late)
    journal.append("early", early)
    write_pending(journal, tmp_path / "day")
    assert [r["serial"] for r in read_workbook(workbook_path(tmp_path / "day", "2026-03-01"))] == ["A"]
    assert [r["serial"] for r in read_workbook(workbook_path(tmp_path / "day", "2026-03-02"))] == ["B"]
    shifts = WorkbookSettings(period="shift")
    assert period_key("2026-03-02T05:59:00+01:00", shifts) == "2026-03-01-shift2200"   # night shift of the 1st
    assert period_key("2026-03-02T06:00:00+01:00", shifts) == "2026-03-02-shift0600"
    assert period_key("2026-03-02T21:59:59+01:00", shifts) == "2026-03-02-shift1400"
    assert period_key("2026-03-02T23:00:00+01:00", shifts) == "2026-03-02-shift2200"


def test_rows_already_in_the_book_are_not_written_twice(journal, tmp_path):
    for i in range(3):
        journal.append(f"c{i}", make_record(f"S{i}"))
    write_pending(journal, tmp_path)
    # a crash after the rename, before the journal mark: the journal still says pending
    journal._db.execute("UPDATE cycles SET workbook_path = NULL WHERE cycle_id IN ('c1', 'c2')")
    journal.append("c3", make_record("S3"))
    report = write_pending(journal, tmp_path)
    assert report.already_present == 2 and report.rows_written == 1
    rows = read_workbook(workbook_path(tmp_path, "2026-03-02"))
    assert [r["cycle_id"] for r in rows] == ["c0", "c1", "c2", "c3"]
    assert journal.pending_workbook() == []
    assert {r.workbook_path for r in journal.rows()} == {str(workbook_path(tmp_path, "2026-03-02"))}


def _two_then_blocked(journal, tmp_path, monkeypatch, fail):
    """Write two rows, then two more under a failing save; return the book."""
    journal.append("c0", make_record("S0"))
    journal.append("c1", make_record("S1"))
    write_pending(journal, tmp_path)
    book = workbook_path(tmp_path, "2026-03-02")
    before = book.read_bytes()
    journal.append("c2", make_record("S2"))
    journal.append("c3", make_record("S3"))
    with monkeypatch.context() as m:
        fail(m)
        report = write_pending(journal, tmp_path)
        assert report.rows_written == 0 and report.waiting == 2 and str(book) in report.errors
        assert [r.cycle_id for r in journal.pending_workbook()] == ["c2", "c3"]
        report = write_pending(journal, tmp_path)          # still failing: still waiting, nothing lost
        assert report.waiting == 2
    assert book.read_bytes() == before                      # the old book untouched
    assert temp_files(tmp_path) == []                       # no temporary file left behind
    assert [r["cycle_id"] for r in read_workbook(book)] == ["c0", "c1"]
    report = write_pending(journal, tmp_path)                # the condition is gone: the rows land
    assert report.rows_written == 2 and journal.pending_workbook() == []
    assert [r["cycle_id"] for r in read_workbook(book)] == ["c0", "c1", "c2", "c3"]
    assert temp_files(tmp_path) == []
    return book


def test_a_book_open_in_excel_keeps_rows_pending(journal, tmp_path, monkeypatch):
    real_replace = os.replace

    def locked(src, dst, *a, **k):
        if str(dst).endswith(".xlsx"):
            raise PermissionError(13, "The process cannot access the file because it is being used by another "
                                      "process", str(dst))
        return real_replace(src, dst, *a, **k)

    _two_then_blocked(journal, tmp_path, monkeypatch, lambda m: m.setattr(os, "replace", locked))


def test_a_full_disk_keeps_rows_pending(journal, tmp_path, monkeypatch):
    def disk_full(wb, fh):
        fh.write(b"PK\x03\x04 half a zip file")
        raise OSError(errno.ENOSPC, "No space left on device")

    _two_then_blocked(journal, tmp_path, monkeypatch, lambda m: m.setattr(wbmod, "_save_to", disk_full))


def test_rollover_to_a_new_part_before_the_row_limit(journal, tmp_path, monkeypatch):
    monkeypatch.setattr(wbmod, "EXCEL_MAX_ROWS", 4)          # header + 3 rows per part
    for i in range(8):
        journal.append(f"c{i}", make_record(f"S{i}"))
    report = write_pending(journal, tmp_path)
    parts = [workbook_path(tmp_path, "2026-03-02", p) for p in (1, 2, 3)]
    assert parts[1].name == "results-2026-03-02-part2.xlsx"
    assert report.written == {str(parts[0]): 3, str(parts[1]): 3, str(parts[2]): 2}
    assert [[r["cycle_id"] for r in read_workbook(p)] for p in parts] == \
        [["c0", "c1", "c2"], ["c3", "c4", "c5"], ["c6", "c7"]]
    assert journal.get("c4").workbook_path == str(parts[1])
    journal._db.execute("UPDATE cycles SET workbook_path = NULL WHERE cycle_id = 'c1'")   # crash before a mark
    for i in (8, 9):
        journal.append(f"c{i}", make_record(f"S{i}"))
    write_pending(journal, tmp_path)
    part4 = workbook_path(tmp_path, "2026-03-02", 4)
    assert [r["cycle_id"] for r in read_workbook(parts[2])] == ["c6", "c7", "c8"]
    assert [r["cycle_id"] for r in read_workbook(part4)] == ["c9"]
    assert [r["cycle_id"] for r in read_workbook(parts[0])] == ["c0", "c1", "c2"]          # c1 not doubled
    assert journal.get("c1").workbook_path == str(parts[0]) and journal.pending_workbook() == []
    assert all(load_workbook(p)["results"].max_row <= 4 for p in [*parts, part4])


def test_export_of_a_period(journal, tmp_path):
    for day in (1, 2, 3):
        for k in range(3):
            journal.append(f"d{day}-{k}", make_record(f"S{day}{k}", f"2026-03-0{day}T1{k}:00:00.000+01:00"))
    out = export_workbook(journal, "2026-03-02T00:00:00+01:00", "2026-03-03T00:00:00+01:00", tmp_path / "x.xlsx")
    assert out == [tmp_path / "x.xlsx"]
    assert [r["cycle_id"] for r in read_workbook(out[0])] == ["d2-0", "d2-1", "d2-2"]
    out = export_workbook(journal, None, "2026-03-03T11:00:00+01:00", tmp_path / "y.xlsx", max_rows=4)
    assert [p.name for p in out] == ["y.xlsx", "y-part2.xlsx"]
    assert sum(len(read_workbook(p)) for p in out) == 7
    assert journal.pending_workbook() != []                  # exporting marks nothing
    empty = export_workbook(journal, "2030-01-01", "2030-01-02", tmp_path / "empty.xlsx")
    assert read_workbook(empty[0]) == []


def test_a_new_figure_adds_a_column(journal, tmp_path):
    journal.append("c0", make_record("S0"))
    write_pending(journal, tmp_path)
    journal.append("c1", make_record("S1", new_figure_mrad=1.25))
    write_pending(journal, tmp_path)
    book = workbook_path(tmp_path, "2026-03-02")
    header = [c.value for c in load_workbook(book)["results"][1]]
    assert header[-1] == "new_figure_mrad"
    rows = read_workbook(book)
    assert "new_figure_mrad" not in rows[0] and rows[1]["new_figure_mrad"] == 1.25


def test_a_book_damaged_elsewhere_is_set_aside_and_rebuilt_from_the_journal(journal, tmp_path):
    journal.append("c0", make_record("S0"))
    journal.append("c1", make_record("S1"))
    write_pending(journal, tmp_path)
    book = workbook_path(tmp_path, "2026-03-02")
    book.write_bytes(b"someone saved garbage here")
    journal.append("c2", make_record("S2"))
    write_pending(journal, tmp_path)
    assert [r["cycle_id"] for r in read_workbook(book)] == ["c0", "c1", "c2"]
    aside = list(tmp_path.glob("results-2026-03-02.corrupt-*.xlsx"))
    assert len(aside) == 1 and aside[0].read_bytes() == b"someone saved garbage here"


def test_archive_export_takes_words_and_iso_dates_and_refuses_a_reversed_range(small_station_toml, caplog, capsys):
    import datetime as _dt

    from sofast_station.cli import main
    from sofast_station.config import load_config

    data = load_config(small_station_toml).data_dir
    now = _dt.datetime.now().astimezone()
    with Journal(data / "journal.sqlite3") as j:
        j.append("today-1", dict(SAMPLE_RECORD, time=now.isoformat(timespec="milliseconds")))
        j.append("old-1", dict(SAMPLE_RECORD, time="2026-01-05T10:00:00+00:00"))
    out = data / "x.xlsx"
    assert main(["archive", "export", "--config", str(small_station_toml), "--from", "yesterday",
                 "--out", str(out)]) == 0
    assert [r["cycle_id"] for r in read_workbook(out)] == ["today-1"]
    assert main(["archive", "export", "--config", str(small_station_toml), "--from", "2026-01-05", "--to",
                 "2026-01-06", "--out", str(out)]) == 0
    assert [r["cycle_id"] for r in read_workbook(out)] == ["old-1"]
    assert main(["archive", "export", "--config", str(small_station_toml), "--from", "today", "--to",
                 "yesterday", "--out", str(out)]) == 2
    assert "empty or reversed" in caplog.text
    assert main(["archive", "export", "--config", str(small_station_toml), "--from", "last tuesday"]) == 2
    assert "'today' or 'yesterday'" in caplog.text


def test_the_memory_of_a_save_does_not_grow_with_the_rows_of_its_part(journal, tmp_path):
    """A part is streamed from the journal, a few rows at a time: adding rows to a part of 200 rows needs
    hardly more memory than adding them to one of 20 (about 3 kB a row of the part: its cycle ids and
    strings). Loading the part to append to it (openpyxl's normal mode, the archiver before) held every
    cell of it: 41 kB a row of this record's 98 columns here, and the archiver process grew by 8 MB per
    100 facets at 236 columns."""
    import tracemalloc

    def peak_of_a_save(folder, rows_in_part):
        for i in range(rows_in_part):
            journal.append(f"{folder.name}-{i}", make_record(f"S{i}"))
        write_pending(journal, folder)
        for i in range(rows_in_part, rows_in_part + 5):
            journal.append(f"{folder.name}-{i}", make_record(f"S{i}"))
        tracemalloc.start()
        try:
            report = write_pending(journal, folder)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert report.rows_written == 5 and len(read_workbook(workbook_path(folder, "2026-03-02"))) == rows_in_part + 5
        return peak

    small, large = peak_of_a_save(tmp_path / "small", 20), peak_of_a_save(tmp_path / "large", 200)
    assert large - small < 180 * 10_000, f"{(large - small) / 180:.0f} bytes more per row of the part"


def test_a_save_streams_its_sheets_beside_the_part(journal, tmp_path, monkeypatch):
    """openpyxl's sheet streams go beside the part (removed at the next start if a kill leaves them), not /tmp."""
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(system_tmp))
    folder = tmp_path / "archive"
    seen = []
    real = wbmod._save_to

    def looking(wb, fh):
        seen.extend(sorted(p.name for p in temp_files(folder)))
        return real(wb, fh)

    monkeypatch.setattr(wbmod, "_save_to", looking)
    journal.append("cycle-1", SAMPLE_RECORD)
    write_pending(journal, folder)
    pid = os.getpid()
    streams = [n for n in seen if n.startswith(".results-2026-11-25.xlsx.sheet.")]
    assert len(streams) == 2 and all(is_temp_file(folder / n) and f".{pid}." in n for n in streams)
    assert list(system_tmp.iterdir()) == []                      # nothing of the save in the system's folder
    assert temp_files(folder) == []                              # and nothing left beside the part
    assert [r["cycle_id"] for r in read_workbook(workbook_path(folder, "2026-11-25"))] == ["cycle-1"]


def test_a_row_amended_while_its_part_is_written_is_written_whole_at_the_next_pass(journal, tmp_path, monkeypatch):
    """The part writer reads every record from the journal twice (the columns, then the rows). A late
    result amended between the two reads brought a column the first did not see (a KeyError that failed the
    pass, seen in a full-resolution soak). That pass now writes what its header holds; the amended row
    stays pending and the next pass writes it whole."""
    folder = tmp_path / "archive"
    journal.append("c1", make_record("S-1", "2026-11-25T10:00:00.000+01:00"))
    journal.append("c2", make_record("S-2", "2026-11-25T10:01:00.000+01:00"))
    reads = []
    real = journal.rows_by_ids

    def rows_by_ids(ids):
        reads.append(list(ids))
        if len(reads) == 2:                              # the second pass over the rows begins: amend c2
            rec = make_record("S-2", "2026-11-25T10:01:00.000+01:00", late=True, late_verdict="pass",
                              late_by_s=1.5)
            journal.amend("c2", rec)
        return real(ids)
    monkeypatch.setattr(journal, "rows_by_ids", rows_by_ids)
    report = write_pending(journal, folder)
    assert not report.errors
    assert [r.cycle_id for r in journal.pending_workbook()] == ["c2"]     # amended meanwhile: still pending
    monkeypatch.undo()
    write_pending(journal, folder)
    rows = {r["cycle_id"]: r for r in read_workbook(workbook_path(folder, "2026-11-25"))}
    assert rows["c2"]["late"] is True and rows["c2"]["late_verdict"] == "pass" and journal.pending_workbook() == []
