"""``report flux``: a dump's flux map and optical figures, recomputed from its frames."""

from __future__ import annotations

import re


from sofast_station.archive.dumps import read_dump
from sofast_station.reanalysis.cli import main


def test_report_flux_of_a_dump_draws_the_map_and_reproduces_the_archived_figures(station_dumps, tmp_path, capsys):
    dump = station_dumps.good[0]
    archived = read_dump(dump, load_frames=False).record["optics"]
    assert main(["report", "flux", str(dump), "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    png = tmp_path / f"flux-{dump.name.removesuffix('.h5')}.png"
    assert png.stat().st_size > 20_000 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The same settings and seed as on the line: the same figures, printed.
    assert f"intercept {archived['intercept']:.4f}" in out
    # The optical figures' U come from sensitivities taken on the first facet of a type (on the line the
    # warm-up capture, here the dump's own): the value is the archived one, its U a few per cent apart.
    shown = re.search(r"90 % spot radius (\S+) ± (\S+) mm", out)
    value, big_u = float(shown[1]), float(shown[2])
    decimals = len(shown[1].partition(".")[2])
    assert value == round(1000 * archived["spot_radius_m"], decimals)
    assert abs(big_u / (1000 * archived["spot_radius_m_U"]) - 1) < 0.2


def test_report_flux_options_change_the_conditions(station_dumps, tmp_path, capsys):
    dump = station_dumps.good[1]
    assert main(["report", "flux", str(dump), "--out", str(tmp_path / "a.png"), "--aperture", "0.02",
                 "--dni", "800", "--sun", "gaussian", "--sigma-mrad", "2.5"]) == 0
    out = capsys.readouterr().out
    assert "aperture a circle of 0.020 m radius" in out
    assert (tmp_path / "a.png").exists()
    intercept = float(out.split("intercept ")[1].split()[0])
    assert intercept < 0.9                       # a 20 mm aperture cannot hold a 25 mm sun image


def test_report_flux_needs_dumps_or_an_opencsp_folder(caplog):
    assert main(["report", "flux"]) != 0
    assert "needs dump(s) or opencsp:DIR" in caplog.text
