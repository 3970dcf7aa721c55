"""Issue 16: the certificate and the diff of dumped facets (they share the re-analysis tests' station run)."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
from matplotlib.image import imread

from sofast_station.reanalysis.cli import main


def test_certificate_pdf_of_a_dumped_facet(station_dumps, tmp_path, capsys):
    cfg = station_dumps.journal.parent.parent / "station.toml"
    out = tmp_path / "cert.pdf"
    assert main(["report", "certificate", "SIM-0001", "--config", str(cfg), "--journal", str(station_dumps.journal),
                 "--out", str(out)]) == 0
    data = out.read_bytes()
    assert data.startswith(b"%PDF") and b"/Count 1" in data           # one page
    if shutil.which("pdftoppm"):
        subprocess.run(["pdftoppm", "-png", "-r", "60", str(out), str(tmp_path / "cert")], check=True)
        (page,) = tmp_path.glob("cert*.png")
        img = imread(page)
        assert img.shape[0] > img.shape[1] > 400                        # A4 portrait
    # a serial the journal does not know
    assert main(["report", "certificate", "NOPE", "--config", str(cfg), "--journal", str(station_dumps.journal),
                 "--out", str(tmp_path)]) == 2


def test_diff_of_two_measurements_of_one_facet_type(station_dumps, tmp_path, capsys):
    a, b = (str(p) for p in station_dumps.good[:2])
    assert main(["report", "diff", a, b, "--out", str(tmp_path / "d.png")]) == 0
    assert imread(tmp_path / "d.png").shape[1] > 1000
    from sofast_station.report.diff import common_grid_difference
    from sofast_station.reanalysis.sources import load_measured
    same = load_measured(a)
    d = common_grid_difference(same, same)
    assert np.nanmax(np.abs(d["e_x_mrad"])) == 0 and np.nanmax(np.abs(d["height_um"])) < 1e-9
