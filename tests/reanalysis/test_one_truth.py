"""Issue 43 item 3: one facet, one truth on every screen.

SIM-0016's f_x was ± 0.00079 m on the console, the page and the certificate and ± 0.00071 m in ``report`` and
``report diff``, and ``reprocess`` said "0 difference" because it compared no U. Here one facet of the
simulated line (SIM-0002 of the session's line, whose U came from the line's pooled frame brightness and from
sensitivities computed before it, on the warm-up capture) and its dump go through every output a person
reads: the console line, the record's summary (``inspect``'s), the line's web page, the workbook row, the
dump, ``reprocess``, ``report`` (the maps' titles and text), ``report diff`` and the certificate (its PDF's
text). Each is parsed back, figure by figure, value and U, at the decimals it shows, and must read exactly
as GUM 7.2.6 writes the line's own record (U to two significant digits, the value to the same place), which
this test writes by its own means (Python's ``%e`` gives U's leading digit's place), not by the package's.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import re
import shutil
import sqlite3

import pytest

from sofast_station.archive import Journal
from sofast_station.archive.dumps import read_dump
from sofast_station.reanalysis.cli import main
from tests.reanalysis.test_reports_people_see import _text_boxes

#: The figures compared: (record path, its U's path).
FIGURES = {"f_x": ("focal_length_x_m", "focal_length_x_m_U"), "f_y": ("focal_length_y_m", "focal_length_y_m_U"),
           "twist": ("twist_mrad_per_m", "twist_mrad_per_m_U"),
           "rms_design": ("slope_rms_mrad.design.magnitude", "slope_rms_mrad_U.design.magnitude"),
           "rms_parabola": ("slope_rms_mrad.parabola.magnitude", "slope_rms_mrad_U.parabola.magnitude")}
#: ``value ± U`` as every output writes it.
PM = re.compile(r"([+-]?\d+\.?\d*) ± (\d+\.?\d*)")


def _get(record: dict, path: str):
    node = record
    for part in path.split("."):
        node = node[part]
    return node


def expected(record: dict, name: str) -> tuple[str, str]:
    """The figure *name* of *record* and its U as GUM 7.2.6 writes them, by this test's own arithmetic: U's
    leading digit's decimal place from ``%e`` after rounding U to two significant digits, one more place for
    the second digit; the value rounded to the same place."""
    value, u = _get(record, FIGURES[name][0]), _get(record, FIGURES[name][1])
    mantissa, exponent = f"{u:.1e}".split("e")
    places = max(1 - int(exponent), 0)
    assert float(mantissa) < 10 and places < 12, (name, u)
    return f"{value:.{places}f}", f"{u:.{places}f}"


def _pairs(text: str) -> list[tuple[str, str]]:
    return PM.findall(text)


def _line(text: str, start: str) -> str:
    found = [ln for ln in text.splitlines() if ln.strip().startswith(start)]
    assert found, (start, text)
    return found[0]


def _page(station_dumps, serial: str, tmp_path) -> str:
    """The line's page (its "last facet" section) as it was just after *serial* was journaled: the station's
    journal up to that facet, read by the monitor's own reader and renderer."""
    from sofast_station.config import load_config
    from sofast_station.web.data import LineData
    from sofast_station.web.render import last_html
    from sofast_station.web.settings import web_settings

    data = tmp_path / "page-data"
    data.mkdir()
    shutil.copyfile(station_dumps.journal, data / "journal.sqlite3")
    with sqlite3.connect(data / "journal.sqlite3") as db:
        (seq, time), = db.execute("SELECT seq, time FROM cycles WHERE serial = ?", (serial,)).fetchall()
        db.execute("DELETE FROM cycles WHERE seq > ?", (seq,))
    cfg = load_config(station_dumps.config)
    lines = LineData(dataclasses.replace(cfg, data_dir=data), web_settings(cfg))
    try:
        snap = lines.snapshot(now=dt.datetime.fromisoformat(time) + dt.timedelta(seconds=5))
    finally:
        lines.close()
    assert snap["last"]["serial"] == serial
    return last_html(snap)


def _workbook_row(station_dumps, serial: str) -> dict:
    """{column: (value, number format)} of *serial*'s row in the line's workbook."""
    from openpyxl import load_workbook

    books = sorted((station_dumps.journal.parent / "archive").glob("*.xlsx"))
    for book in books:
        ws = load_workbook(book)["results"]
        head = [c.value for c in ws[1]]
        for row in ws.iter_rows(min_row=2):
            cells = dict(zip(head, row))
            if cells["serial"].value == serial:
                return {k: (c.value, c.number_format) for k, c in cells.items()}
    raise AssertionError(f"{serial} is in no workbook of {books}")


def _shown(value: float, number_format: str) -> str:
    """A cell's number as Excel shows it with its format ``0.00000``."""
    places = len(number_format.split(".")[1]) if "." in number_format else 0
    assert set(number_format) <= set("0."), number_format
    return f"{value:.{places}f}"


def _certificate_rows(pdf) -> dict:
    """{row label: the texts on its line} of the certificate's figure table, from the PDF's own text positions."""
    boxes, _ = _text_boxes(pdf)
    out = {}
    for text, x0, y0, x1, y1 in boxes:
        if text in ("focal length f_x", "focal length f_y", "twist", "slope error RMS vs design",
                    "slope error RMS vs parabola"):
            mid = 0.5 * (y0 + y1)
            out[text] = " | ".join(t for t, a, b, c, d in boxes if b <= mid <= d and t != text)
    return out


@pytest.fixture(scope="module")
def shown(station_dumps, tmp_path_factory):
    """{output: {figure name: (value text, U text)}} for SIM-0002, and the records the line journaled of SIM-0002
    and SIM-0001."""
    tmp = tmp_path_factory.mktemp("one-truth")
    with pytest.MonkeyPatch.context() as mp:   # as tests/conftest.py's _data_dir, which a module fixture precedes
        mp.setenv("SOFAST_DATA_DIR", str(tmp / "station-data"))
        mp.setenv("SOFAST_NICE", "0")
        return _outputs(station_dumps, tmp)


def _outputs(station_dumps, tmp):
    import matplotlib.text

    from sofast_station.report import maps
    from sofast_station.station.cli import summary_text

    journal = Journal(station_dumps.journal)
    try:
        rows = {r.serial: r for r in journal.rows()}
    finally:
        journal.close()
    line, first = rows["SIM-0002"].record, rows["SIM-0001"].record
    dump_a, dump_b = (str(p) for p in station_dumps.good[:2])
    out: dict = {}

    console = _line("\n".join(station_dumps.console), next(ln for ln in station_dumps.console if "SIM-0002" in ln)
                    .strip()[:12])
    out["console line"] = dict(zip(("f_x", "f_y", "rms_design", "rms_parabola"), _pairs(console)))

    summary = summary_text(line)
    design, parabola = (_pairs(_line(summary, m)) for m in ("design ", "parabola "))
    out["summary"] = {"f_x": _pairs(_line(summary, "focal length x"))[0],
                      "f_y": _pairs(_line(summary, "focal length y"))[0],
                      "twist": _pairs(_line(summary, "twist  "))[0],
                      "rms_design": design[-1], "rms_parabola": parabola[-1]}

    page = _page(station_dumps, "SIM-0002", tmp)
    cells = dict(re.findall(r"<th>([^<]*)</th><td class='num'>([^<]*)</td>", page))
    out["page"] = {name: _pairs(cells[label])[0] for name, label in (
        ("f_x", "focal length x"), ("f_y", "focal length y"), ("twist", "twist"),
        ("rms_design", "slope RMS vs design"), ("rms_parabola", "slope RMS vs parabola"))}

    row = _workbook_row(station_dumps, "SIM-0002")
    out["workbook"] = {name: (_shown(*row[v]), _shown(*row[u])) for name, (v, u) in FIGURES.items()}

    dumped = read_dump(dump_b, load_frames=False)
    out["dump"] = {name: expected(dumped.record, name) for name in FIGURES}
    assert all(_get(dumped.record, p) == _get(line, p) for pair in FIGURES.values() for p in pair)

    capsys_out = tmp / "out.txt"

    def run(args) -> str:
        import contextlib
        with open(capsys_out, "w") as fh, contextlib.redirect_stdout(fh):
            assert main(args) == 0, args
        return capsys_out.read_text()

    text = run(["reprocess", dump_b])
    for side, i in (("reprocess, archived", 0), ("reprocess, new", 1)):
        out[side] = {name: _pairs(_line(text, path))[i] for name, (path, _) in FIGURES.items()}
    out["reprocess summary"] = text.strip().splitlines()[-1]

    drawn: list[str] = []
    saved = maps.savefig_atomic

    def keep_texts(fig, path, dpi):
        drawn.extend(t.get_text() for t in fig.findobj(matplotlib.text.Text))
        return saved(fig, path, dpi)

    maps.savefig_atomic = keep_texts
    try:
        run(["report", dump_b, "--out", str(tmp / "maps")])
    finally:
        maps.savefig_atomic = saved
    text = "\n".join(drawn)
    out["report"] = {"f_x": _pairs(_line(text, "f x"))[0], "f_y": _pairs(_line(text, "f y"))[0],
                     "twist": _pairs(_line(text, "twist"))[0],
                     "rms_design": _pairs(_line(text, "slope RMS design"))[0],
                     "rms_parabola": _pairs(_line(text, "slope RMS parabola"))[0]}
    titles = [t for t in drawn if t.startswith("compared with the fitted parabola")]
    out["report, map title"] = {"f_x": _pairs(titles[0])[0], "f_y": _pairs(titles[0])[1],
                                "rms_parabola": _pairs(titles[0])[-1]}

    text = run(["report", "diff", dump_a, dump_b, "--out", str(tmp / "diff")])
    labels = {"f_x": "focal length f_x", "f_y": "focal length f_y", "twist": "twist",
              "rms_design": "slope error RMS vs design", "rms_parabola": "slope error RMS vs parabola"}
    out["report diff, B"] = {name: _pairs(_line(text, label))[1] for name, label in labels.items()}
    out["report diff, A"] = {name: _pairs(_line(text, label))[0] for name, label in labels.items()}

    run(["report", "certificate", "SIM-0002", "--config", str(station_dumps.config), "--journal",
         str(station_dumps.journal), "--out", str(tmp)])
    cert = _certificate_rows(tmp / "certificate-SIM-0002.pdf")
    out["certificate"] = {name: _pairs(cert[label])[0] for name, label in labels.items()}
    return out, line, first


def test_every_output_shows_the_lines_figures_and_u_of_one_facet(shown):
    out, line, first = shown
    want = {name: expected(line, name) for name in FIGURES}
    for output, figures in out.items():
        if output in ("reprocess summary", "report diff, A"):
            continue
        assert figures, output
        for name, pair in figures.items():
            assert tuple(pair) == want[name], f"{output}: {name} reads {' ± '.join(pair)}, the line's " \
                                              f"{' ± '.join(want[name])}"
    # every output above holds every figure it is meant to show
    assert set(out["console line"]) == {"f_x", "f_y", "rms_design", "rms_parabola"}
    assert all(set(out[k]) == set(FIGURES) for k in ("summary", "page", "workbook", "dump", "reprocess, new",
                                                     "report", "report diff, B", "certificate"))
    # A of the diff is the first facet, as its own line wrote it
    assert out["report diff, A"] == {name: expected(first, name) for name in FIGURES}
    # reprocess compared the U too, and found them the line's
    assert "reproduced exactly" in out["reprocess summary"] and "and U identical" in out["reprocess summary"]


def test_the_facets_u_came_from_evidence_the_dump_keeps(station_dumps):
    """What made the outputs differ: the line pools each capture's frame brightness with the earlier captures'
    and takes the optical figures' sensitivities from the first facet of the type; the dump keeps both, and the
    input uncertainties with the radiometric record's rounding of the display response (the cause once
    suspected), so the re-analysis needs nothing the line had in memory."""
    content = read_dump(station_dumps.good[1], load_frames=False)
    fb = content.record["uncertainty_budget"]["frame_brightness"]
    assert fb["source"] == "pooled" and fb["captures"] >= 2           # SIM-0002 was pooled with earlier captures
    assert len(content.sensitivities["frame_pool"]) == fb["captures"] - 1 and content.sensitivities["optics"]
    assert content.uncertainty_inputs["response_record_rad"] > 0
    assert "record" in content.record["uncertainty_budget"]["display_response"]["source"]


def test_a_report_of_an_older_dump_says_its_u_are_the_reanalysiss(station_dumps, tmp_path, caplog):
    """An older dump keeps no frame-brightness pool: its re-analysis has the capture's own frame brightness, so
    ``report`` and ``report diff`` (which reprocess it) would show another U than the line's without a word;
    they say whose U they show, and what the dump lacks."""
    import json
    import logging

    import h5py

    from sofast_station.reanalysis.sources import load_measured
    from tests.reanalysis.conftest import copy_dump

    dump = copy_dump(station_dumps.good[1], tmp_path / station_dumps.good[1].name)
    with h5py.File(dump, "r+") as f:
        raw = f["result/sensitivities_json"][()]
        sens = json.loads(raw.decode() if isinstance(raw, bytes) else raw)
        del sens["frame_pool"]                       # as the station wrote it before the pool was kept
        del f["result/sensitivities_json"]
        f["result"].create_dataset("sensitivities_json", data=json.dumps(sens), dtype=h5py.string_dtype())
    with caplog.at_level(logging.WARNING):
        m = load_measured(str(dump))
    assert "the U shown are the re-analysis's, not the line's" in caplog.text
    assert "does not keep the frame-brightness pool" in caplog.text
    line = read_dump(station_dumps.good[1], load_frames=False).record
    assert m.record["focal_length_x_m"] == line["focal_length_x_m"]
    assert m.record["focal_length_x_m_U"] != line["focal_length_x_m_U"]     # what the warning is about
