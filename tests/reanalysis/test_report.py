"""Issue 7, item 3: slope-error maps in the style of the paper's Figs. 8-10, and trend plots (headless)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from matplotlib.image import imread

from sofast_station.reanalysis.batch import run_batch
from sofast_station.reanalysis.cli import main
from sofast_station.errors import ReportError
from sofast_station.report.maps import MODELS, slope_error_maps, write_slope_error_maps
from sofast_station.report.trend import trend_records_from_journal, trend_records_from_results, write_trend
from sofast_station.reanalysis.reprocess import reprocess_dump


def _png_size(path):
    img = imread(path)
    return img.shape[1], img.shape[0]


def test_slope_error_maps_show_the_measured_pixels_and_the_reported_figures(station_dumps):
    res = reprocess_dump(station_dumps.good[0])
    maps = slope_error_maps(res.analysis)
    a = res.analysis
    rows, cols = np.nonzero(a.valid)
    for model in MODELS:
        m = maps[model]
        ex, ey = a.residuals_mrad[model]
        # the panel titles' figures are the reported ones
        for k in ("x", "y", "magnitude"):
            assert m.rms_mrad[k] == pytest.approx(res.record["slope_rms_mrad"][model][k], rel=1e-12)
        # nearest-pixel resampling: every coloured cell shows one measured pixel's magnitude
        shown = m.magnitude_mrad[np.isfinite(m.magnitude_mrad)]
        assert np.all(np.isin(shown, np.hypot(ex, ey)))
        # the grid covers the facet (0.6 m square) at about the camera's pixel size on it
        x0, x1, y0, y1 = m.extent_m
        assert x1 - x0 == pytest.approx(0.6, abs=0.02) and y1 - y0 == pytest.approx(0.6, abs=0.02)
        assert shown.size == pytest.approx(rows.size, rel=0.1)
        # arrows on every 10th camera row and column, as in the paper
        assert m.arrow_step_px == 10
        expected = np.count_nonzero((rows % 10 == 0) & (cols % 10 == 0))
        assert m.arrow_x_m.size == expected
    # facet coordinates: the design map's x residual grows with x when the design is the wrong shape
    big = slope_error_maps(reprocess_dump(station_dumps.good[0], _wrong_design()).analysis)["design"]
    assert np.corrcoef(big.arrow_x_m, big.arrow_ex_mrad)[0, 1] < -0.9


def test_map_titles_carry_each_figures_uncertainty(station_dumps):
    """Every figure a map's title shows is a measurement result: value ± U (k = 2 in the page title)."""
    from sofast_station.report.maps import _titles
    from sofast_station.result.formatting import with_u

    res = reprocess_dump(station_dumps.good[0])
    rec = res.record
    titles = _titles(res, slope_error_maps(res.analysis))
    assert rec.get("coverage_factor") == 2
    for model in MODELS:
        u = rec["slope_rms_mrad_U"][model]
        for k in ("x", "y", "magnitude"):
            assert with_u(rec['slope_rms_mrad'][model][k], u[k]) in titles[model]
    assert with_u(rec['focal_length_x_m'], rec['focal_length_x_m_U']) in titles["parabola"]
    # a record without U (an old dump's) shows the values alone
    bare = {k: v for k, v in rec.items() if not k.endswith("_U")}
    plain = _titles(dataclasses.replace(res, record=bare), slope_error_maps(res.analysis))
    assert "±" not in plain["design"]


def _wrong_design():
    from sofast_station.reanalysis.reprocess import Overrides
    return Overrides(focal_length_m=4.5)        # a stronger design: measured slopes fall short as x grows


def test_report_writes_a_png_per_dump(station_dumps, tmp_path, capsys):
    dumps = [str(d) for d in station_dumps.good[:2]]
    assert main(["report", *dumps, "--out", str(tmp_path / "maps")]) == 0
    written = capsys.readouterr().out.split()
    assert len(written) == 4                    # the three models' maps and the detail page, per dump
    assert written[1].endswith(f"{station_dumps.good[0].stem}-detail-parabola.png")
    assert _png_size(written[1])[0] > 1000
    written = written[::2]
    for path, dump in zip(written, station_dumps.good[:2]):
        assert path.endswith(f"{dump.stem}.png")
        w, h = _png_size(path)
        assert w > 2 * h                        # three panels side by side
    assert main(["report", dumps[0], "--out", str(tmp_path / "single"), "--separate", "--vmax", "2",
                 "--arrow-step", "20", "--detail", "none"]) == 0
    files = sorted((tmp_path / "single").glob("*.png"))
    assert [f.name.rsplit("-", 1)[1] for f in files] == ["design.png", "higher_order.png", "parabola.png"]


def test_a_refused_capture_has_no_map(station_dumps, tmp_path, caplog):
    res = reprocess_dump(station_dumps.fault)
    with pytest.raises(ReportError, match="refused the capture"):
        write_slope_error_maps(res, tmp_path)
    assert main(["report", str(station_dumps.fault), "--out", str(tmp_path)]) == 2
    assert str(station_dumps.fault) in caplog.text and "dark" in caplog.text


def test_trend_from_the_journal_and_from_batch_results(station_dumps, tmp_path, capsys):
    records = trend_records_from_journal(station_dumps.journal)
    assert len(records) == 4                   # three measured facets and one fault
    # each measured facet's figures come with their U: the plot draws them as bars
    assert sum(isinstance(r.get("focal_length_x_m_U"), float) and r["focal_length_x_m_U"] > 0 for r in records) == 3
    times = [r["time"] for r in records]
    out = write_trend(records, tmp_path / "t.png", title="journal")
    assert _png_size(out)[0] > 500
    # a period that holds only the first two rows
    assert len(trend_records_from_journal(station_dumps.journal, times[0], times[2])) == 2
    assert main(["report", "trend", "--journal", str(station_dumps.journal), "--from", times[0],
                 "--out", str(tmp_path / "trend.png")]) == 0
    assert capsys.readouterr().out.strip() == str(tmp_path / "trend.png")
    # from a folder of batch results
    run_batch(list(map(str, station_dumps.good)), tmp_path / "batch", workers=1)
    got = trend_records_from_results(tmp_path / "batch")
    assert [r["serial"] for r in got] == ["SIM-0001", "SIM-0002", "SIM-0003"]
    assert main(["report", "trend", "--results", str(tmp_path / "batch"), "--out", str(tmp_path)]) == 0
    (png,) = tmp_path.glob("trend-start-*.png")
    assert _png_size(png)[0] > 500
    # an empty period says so
    with pytest.raises(ReportError, match="no measured facet"):
        write_trend(trend_records_from_journal(station_dumps.journal, "2001-01-01", "2001-01-02"),
                    tmp_path / "none.png")
    # focal lengths beyond 20 m are shown as focal power
    long = [dict(r, focal_length_x_m=100.0, focal_length_y_m=None, curvature_x_per_m=0.01, curvature_y_per_m=0.0)
            for r in got]
    assert write_trend(long, tmp_path / "long.png").exists()


def test_report_trend_takes_one_source(tmp_path, caplog, station_dumps):
    assert main(["report", "trend", "--journal", str(station_dumps.journal), "--results", str(tmp_path)]) == 2
    assert "one of --journal PATH and --results DIR, not both" in caplog.text


def test_report_trend_reads_the_station_journal_by_default(tmp_path, caplog, monkeypatch, station_dumps):
    """Without --journal or --results, the journal in the station file's data_dir (no home path to type)."""
    station = station_dumps.journal.parent.parent / "station.toml"
    monkeypatch.setenv("SOFAST_DATA_DIR", str(tmp_path / "empty"))
    assert main(["report", "trend", "--config", str(station), "--out", str(tmp_path)]) == 2
    assert f"no journal at {tmp_path / 'empty' / 'journal.sqlite3'}" in caplog.text
    monkeypatch.setenv("SOFAST_DATA_DIR", str(station_dumps.journal.parent))
    assert main(["report", "trend", "--config", str(station), "--out", str(tmp_path)]) == 0
    pngs = list(tmp_path.glob("*.png"))
    assert len(pngs) == 1 and pngs[0].stat().st_size > 10_000
