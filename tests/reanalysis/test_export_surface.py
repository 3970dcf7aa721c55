"""Issue 29: a measured surface for the ray tracers the field uses (``sofast-station export surface``).

Each format is written from a dump of the small simulated station and read back: the OpenCSP file through
our own OpenCSP reader (:func:`read_opencsp_result`) to the same focal lengths, twists, slopes, points and
pixel mask as the reprocessed dump; the CSV, PLY and SolTrace files to the same points, with the serial and
the units in their headers.
"""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.cli import main
from sofast_station.interop.opencsp import read_opencsp_result
from sofast_station.reanalysis.sources import load_measured


@pytest.fixture(scope="module")
def exported(station_dumps, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    dump = str(station_dumps.good[0])
    files = {}
    for fmt, suffix in (("csv", ".csv"), ("ply", ".ply"), ("opencsp", ".h5"), ("soltrace", ".fed")):
        assert main(["export", "surface", dump, "--format", fmt, "--out", str(out)]) == 0
        files[fmt] = out / f"surface-SIM-0001{suffix}"
        assert files[fmt].exists()
    return load_measured(dump), files


def test_the_opencsp_export_reads_back_to_the_same_figures(exported):
    m, files = exported
    back = read_opencsp_result(files["opencsp"])
    rec = m.record
    assert back.focal_length_x_m == pytest.approx(rec["focal_length_x_m"], rel=1e-12)
    assert back.focal_length_y_m == pytest.approx(rec["focal_length_y_m"], rel=1e-12)
    assert back.twist_e1_mrad_per_m == pytest.approx(rec["twist_e1_mrad_per_m"], rel=1e-12)
    assert back.twist_e2_mrad_per_m == pytest.approx(rec["twist_e2_mrad_per_m"], rel=1e-12)
    np.testing.assert_array_equal(back.slopes, m.analysis.slopes)
    np.testing.assert_array_equal(back.points_m, m.analysis.points_facet_m)
    np.testing.assert_array_equal(back.mask, m.analysis.valid)
    assert back.mask.sum() == back.slopes.shape[1] and not back.robust


def test_csv_ply_and_soltrace_hold_the_points_with_serial_and_units(exported):
    m, files = exported
    points = m.analysis.points_facet_m
    n = points.shape[1]
    text = files["csv"].read_text()
    assert "# serial: SIM-0001" in text and "x_m,y_m,z_m,n_x,n_y,n_z,slope_error_x_mrad" in text
    assert "height error in micrometres" in text
    table = np.loadtxt(files["csv"], delimiter=",", comments="#")
    assert table.shape == (n, 9)
    np.testing.assert_allclose(table[:, :3].T, points, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(table[:, 3:6], axis=1), 1.0, atol=1e-8)
    # the normal is the measured slope's: s_x = -n_x / n_z
    np.testing.assert_allclose(-table[:, 3] / table[:, 5], m.analysis.slopes[0], rtol=1e-6, atol=1e-9)
    # the height error (against the design) is a few micrometres on this facet, zero mean by construction
    assert 0.1 < np.nanstd(table[:, 8]) < 100 and abs(np.nanmean(table[:, 8])) < np.nanstd(table[:, 8])

    raw = files["ply"].read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    assert b"comment serial: SIM-0001" in head and f"element vertex {n}".encode() in head
    vertex = np.frombuffer(body, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"),
                                        ("nz", "<f4"), ("height_error_um", "<f4")])
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]]), points)

    lines = files["soltrace"].read_text().splitlines()
    assert lines[0].startswith("SIM-0001 ") and int(lines[1]) == n
    fed = np.loadtxt(lines[2:])
    np.testing.assert_allclose(fed[:, :2].T, points[:2], atol=1e-9)
    design_z = m.design.z(points[0], points[1])
    np.testing.assert_allclose(fed[:, 2], design_z + 1e-6 * np.nan_to_num(table[:, 8]), atol=2e-9)


def test_an_unknown_format_is_a_usage_error(station_dumps, capsys):
    with pytest.raises(SystemExit) as info:
        main(["export", "surface", str(station_dumps.good[0]), "--format", "stl"])
    assert info.value.code == 2 and "invalid choice: 'stl'" in capsys.readouterr().err
