"""Issue 16: control charts, contract acceptance, certificates and diffs through the command line."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread

from sofast_station.archive.journal import Journal
from sofast_station.reanalysis.cli import main

SAMPLE = json.loads((Path(__file__).parents[1] / "archive" / "sample_record.json").read_text())

CONTRACT = """
[acceptance.default]
population = 14500
confidence = 0.95
relative_error = 0.05

[acceptance.default.figures."slope_rms_mrad.design.magnitude"]
name = "slope deviation SD_2D,RMS"
contract = 1.3
tolerance = 0.2
expected_std = 0.3
sense = "at_most"

[acceptance.default.figures."focal_length_x_m"]
contract = 5.33
tolerance = 0.11
expected_std = 0.02
relative_error = 0.002
"""


def synthetic_journal(path: Path, n: int, *, step_at: int | None = None, seed: int = 1) -> list[dict]:
    """*n* in-control facets of the default recipe, one every 10 minutes from 2026-11-20 06:00 (+00:00),
    f_x ~ N(5.42, 0.01); with *step_at* f_x steps up by one standard deviation from that facet on."""
    rng = np.random.default_rng(seed)
    t0 = dt.datetime(2026, 11, 20, 6, 0, tzinfo=dt.timezone.utc)
    out = []
    with Journal(path) as j:
        for i in range(n):
            r = json.loads(json.dumps(SAMPLE))
            r.pop("truth")
            r["serial"] = f"SYN-{i + 1:04d}"
            r["recipe"] = "default"
            r["time"] = (t0 + dt.timedelta(minutes=10 * i)).isoformat(timespec="milliseconds")
            r["focal_length_x_m"] = 5.42 + 0.01 * rng.standard_normal() + (0.01 if step_at and i + 1 >= step_at else 0)
            r["focal_length_y_m"] = 5.35 + 0.01 * rng.standard_normal()
            r["twist_mrad_per_m"] = 0.1 + 0.05 * rng.standard_normal()
            r["slope_rms_mrad"]["design"]["magnitude"] = float(rng.weibull(2.0) * 1.2)
            r["slope_rms_mrad"]["parabola"]["magnitude"] = 0.7 + 0.03 * rng.standard_normal()
            r["verdict"] = "pass"
            j.append(f"c{i:05d}", r)
            out.append(r)
    return out


@pytest.fixture
def station(tmp_path, small_station_toml):
    cfg = small_station_toml
    cfg.write_text(cfg.read_text() + CONTRACT)
    return cfg


def test_report_spc_draws_charts_and_writes_the_summary_workbook(station, tmp_path, capsys):
    from openpyxl import load_workbook

    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, 120, step_at=80)
    assert main(["report", "spc", "--config", str(station), "--journal", str(journal), "--from", "2026-11-20",
                 "--to", "2026-11-21", "--ewma", "0.2", "--out", str(tmp_path / "out")]) == 0
    png, yield_png, book = capsys.readouterr().out.split()
    assert imread(png).shape[0] > 1000 and imread(yield_png).shape[1] > 800
    wb = load_workbook(book)
    rows = list(wb["summary"].iter_rows(min_row=3, values_only=True))
    fx = next(r for r in rows if r and r[0] == "focal length f_x")
    # the step at facet 80 is flagged; the capability numbers are numbers
    assert fx[16] > 0 and isinstance(fx[13], float)
    # [2026-11-20, 2026-11-21): 108 facets from 06:00 to 23:50
    assert fx[2] == 108
    facets = wb["facets"]
    assert isinstance(facets["A2"].value, dt.datetime) and isinstance(facets["C2"].value, float)
    yield_sheet = wb["yield"]
    header = [c.value for c in yield_sheet[1]]
    assert header[2:7] == ["pass", "fail", "indeterminate", "invalid", "fault"]
    assert yield_sheet.cell(row=2, column=header.index("yield") + 1).value == 1.0


def test_spc_charts_are_scaled_to_their_data_and_name_a_far_limit(station, tmp_path, monkeypatch):
    """Scaled to the specification limits, the data were a flat line and the control limits invisible; the
    journal's path was in the title."""
    from sofast_station.report import control_charts as report_spc

    figures = []
    monkeypatch.setattr(report_spc, "savefig_atomic", lambda fig, path, dpi: figures.append(fig) or path)
    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, 60)
    assert main(["report", "spc", "--config", str(station), "--journal", str(journal), "--out", str(tmp_path)]) == 0
    charts = figures[0]
    title = charts._suptitle.get_text()
    assert str(journal) not in title and "j.sqlite3" not in title
    assert title.startswith("Control charts, recipe default (dish-5.33): 60 facets, 2026-11-20 06:00 to")
    by_title = {ax.get_title().split(" (")[0]: ax for ax in charts.axes}
    rms = by_title["slope error RMS vs parabola"]              # data about 0.7 mrad, limit 2 mrad
    low, high = rms.get_ylim()
    assert high < 1.0 and low > 0.5, (low, high)
    assert any(t.get_text() == "USL 2 mrad above the view" for t in rms.texts)
    lines = [ln.get_ydata()[0] for ln in rms.get_lines() if len(set(ln.get_ydata())) == 1]
    assert any(low < y < high for y in lines)                   # the control limits are in view
    fx = by_title["focal length f_x"]                           # 5.42 +- 0.01 m, USL 5.4366 m: in view
    assert fx.get_ylim()[1] > 5.4366 and any("USL 5.4366" in t for t in fx.get_legend_handles_labels()[1])
    assert rms.get_ylabel() == "slope error RMS vs parabola (mrad)"


def test_acceptance_works_out_of_the_box_with_human_names_and_units(tmp_path, monkeypatch, capsys):
    """The shipped station.toml had no contract, and the axes showed record keys without units."""
    from sofast_station.report import acceptance as report_acceptance

    figures = []
    monkeypatch.setattr(report_acceptance, "savefig_atomic", lambda fig, path, dpi: figures.append(fig) or path)
    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, 120, seed=2)
    shipped = Path(__file__).parents[2] / "station.toml"
    assert main(["report", "acceptance", "--config", str(shipped), "--journal", str(journal),
                 "--out", str(tmp_path)]) in (0, 1)
    out = capsys.readouterr().out
    assert "slope deviation SD_2D,RMS: contract 1 mrad (at most +0.5 mrad)" in out
    assert str(journal) not in figures[0]._suptitle.get_text()
    labels = [ax.get_xlabel() for ax in figures[0].axes]
    assert labels == ["slope error RMS vs design (mrad)", "focal length f_x (m)"], labels
    assert "slope_rms_mrad" not in " ".join(labels)


def test_report_spc_refuses_a_reversed_period_and_a_bad_date(station, tmp_path, caplog):
    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, 5)
    assert main(["report", "spc", "--config", str(station), "--journal", str(journal), "--from", "2026-11-21",
                 "--to", "2026-11-20"]) == 2
    assert "reversed" in caplog.text
    assert main(["report", "spc", "--config", str(station), "--journal", str(journal), "--from", "last week"]) == 2
    assert "'today' or 'yesterday'" in caplog.text


def test_report_acceptance_counts_what_is_missing_then_passes(station, tmp_path, capsys):
    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, 40)
    assert main(["report", "acceptance", "--config", str(station), "--journal", str(journal),
                 "--out", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    # the guideline asks for 82 facets for SD_2D,RMS at N_pop 14,500, mu_e 1.3, sigma_e 0.3, e* 5 %, 95 %
    assert "sample size (guideline Eq. 7, mu_e 1.3, sigma_e 0.3, e* 5 %): 82; measured 40; MISSING 42" in out
    assert "UNDECIDED" in out
    journal2 = tmp_path / "j2.sqlite3"
    synthetic_journal(journal2, 120, seed=2)
    assert main(["report", "acceptance", "--config", str(station), "--journal", str(journal2),
                 "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "overall: PASS" in out
    png = out.strip().splitlines()[-1]
    assert imread(png).shape[1] > 1000


@pytest.mark.parametrize("value", ["5", "0", "-0.2", "nan"])
def test_report_spc_refuses_an_ewma_weight_outside_0_to_1(station, tmp_path, value, capsys):
    """Issue 28: `report spc --ewma 5` was a ValueError traceback; it is a usage error naming the range."""
    journal = tmp_path / "j.sqlite3"
    synthetic_journal(journal, 5)
    with pytest.raises(SystemExit) as info:
        main(["report", "spc", "--config", str(station), "--journal", str(journal), "--ewma", value])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--ewma" in err and "Traceback" not in err
    assert "between 0 (excluded) and 1" in err


def test_a_certificate_of_a_path_like_serial_stays_in_its_folder(station, tmp_path, capsys):
    """Issue 28: `report certificate ../../../x --out OUT` wrote the PDF above OUT and made stray folders. A
    journal may hold such a serial (journaled before serials were made safe): the file stays inside OUT."""
    journal = tmp_path / "deep" / "er" / "j.sqlite3"
    journal.parent.mkdir(parents=True)
    rec = json.loads(json.dumps(SAMPLE))
    rec.pop("truth")
    rec["serial"] = "../../../x"
    with Journal(journal) as j:
        j.append("c00001", rec)
    out = tmp_path / "deep" / "er" / "out"
    before = {p for p in tmp_path.rglob("*")}
    assert main(["report", "certificate", "../../../x", "--config", str(station), "--journal", str(journal),
                 "--out", str(out)]) == 0
    pdf = Path(capsys.readouterr().out.strip())
    assert pdf.resolve().parent == out.resolve() and pdf.suffix == ".pdf" and pdf.stat().st_size > 1000
    made = {p for p in tmp_path.rglob("*")} - before
    assert all(p.resolve().is_relative_to(out.resolve()) or p == out for p in made), sorted(made)


def test_a_certificate_is_found_under_the_serial_as_printed(station, tmp_path, capsys):
    """The station journals a serial made safe ("MF/2024/001" -> "MF_2024_001", the original in serial_raw);
    the quality engineer types it as printed on the facet and gets its certificate."""
    journal = tmp_path / "j.sqlite3"
    rec = json.loads(json.dumps(SAMPLE))
    rec.pop("truth")
    rec.update(serial="MF_2024_001", serial_raw="MF/2024/001")
    with Journal(journal) as j:
        j.append("c00001", rec)
    assert main(["report", "certificate", "MF/2024/001", "--config", str(station), "--journal", str(journal),
                 "--out", str(tmp_path / "out")]) == 0
    assert Path(capsys.readouterr().out.strip()).name == "certificate-MF_2024_001.pdf"


@pytest.fixture
def nothing_heavy(monkeypatch):
    """Fails a test that reprocesses a measurement, loads the station file or lowers the priority; the calls to
    lower the priority are listed (a refusal must come before it: on a busy machine, niceness 10 made the
    refusal's own checks wait for a core)."""
    from sofast_station import commands
    from sofast_station.reanalysis import quality_reports, sources

    def forbidden(what):
        def call(*args, **kwargs):
            raise AssertionError(f"{what} before the refusal")
        return call

    monkeypatch.setattr(sources, "load_measured", forbidden("a measurement was reprocessed"))
    monkeypatch.setattr(quality_reports, "_config", forbidden("the station file was loaded"))
    lowered: list[int] = []
    monkeypatch.setattr(commands, "lower_priority", lambda *a, **k: lowered.append(1))
    return lowered


def test_a_certificate_of_a_faulted_facet_is_refused_before_any_heavy_work(station, tmp_path, capsys, caplog,
                                                                           nothing_heavy):
    """Issue 43: `report certificate` of a faulted facet took 7 min 26 s to refuse on a busy machine: it
    reprocessed the facet's dump (for the maps) at niceness 10, then refused. The refusal now comes from the
    journal's record, before the dump is reprocessed, the station file loaded or the priority lowered; so
    does the refusal of a serial never measured."""
    import os

    journal = Path(os.environ["SOFAST_DATA_DIR"]) / "journal.sqlite3"      # the station's own journal
    journal.parent.mkdir(parents=True)
    dump = tmp_path / "F-0001.h5"
    dump.write_bytes(b"a dump the refusal must not open")
    rec = json.loads(json.dumps(SAMPLE))
    rec.pop("truth")
    rec.update(serial="F-0001", verdict="fault", fault_code=7, reasons=["capture: the white frame is dark everywhere"])
    with Journal(journal) as j:
        j.append("c00001", rec, dump_requested=True)
        j.mark_dump("c00001", dump)
    for serial, words in (("F-0001", "its cycle ended in a fault: capture: the white frame is dark"),
                          ("NEVER-MEASURED", "serial 'NEVER-MEASURED' is not in the journal")):
        caplog.clear()
        assert main(["report", "certificate", serial, "--config", str(station), "--out", str(tmp_path / "out")]) == 2
        assert words in caplog.text, caplog.text
    assert nothing_heavy == [] and not (tmp_path / "out").exists()


def test_report_diff_refuses_an_unreadable_second_input_before_reprocessing_the_first(tmp_path, caplog,
                                                                                       nothing_heavy, repo_root):
    """`report diff A B` reprocessed A (minutes for a full-resolution dump) before finding that B cannot be
    read. Both are checked first (a dump's metadata, an OpenCSP folder's files)."""
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"not HDF5 at all")
    opencsp = f"opencsp:{repo_root / 'fixtures/opencsp/test_data'}"
    assert main(["report", "diff", opencsp, str(broken), "--out", str(tmp_path / "out")]) == 2
    assert "broken.h5" in caplog.text and nothing_heavy == []
