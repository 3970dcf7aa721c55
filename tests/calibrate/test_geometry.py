"""Station geometry: a reference facet of known shape checks the camera/screen geometry the analysis uses,
and the geometry is kept as a record with its provenance."""

from __future__ import annotations

import argparse
import json

import pytest

from sofast_station.calibrate.geometry import (check_geometry, compare_to_reference, load_reference,
                                               reference_from_simulation, station_reference)
from sofast_station.calibrate.geometry_record import load_geometry_record, save_geometry
from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.station import simulated as simulated_station
from sofast_station.station.calibrate_cli import register
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import inspect

from .conftest import small_config


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    folder = tmp_path_factory.mktemp("geometry")
    cfg = small_config(folder)
    station = open_station(cfg, noise=False)
    try:
        check = check_geometry(inspect(station, "GEOMETRY-REFERENCE"), station_reference(station), cfg.uncertainty)
    finally:
        station.close()
    return cfg, check


def test_the_reference_facet_agrees_with_the_station_geometry(measured, monkeypatch):
    """A perfect twin station against the reference's certified figures (the twin's truth): the focal
    lengths agree to a few thousandths of a percent. Against the facet's design (its paraboloid's 5.42 and
    5.35 m) the same measurement would be off by the facet's own best-fit difference (here f_y +0.055 %; on
    the default station -0.105 %, as the issue reported): that is the facet, not the station."""
    cfg, check = measured
    f = check["focal_lengths"]
    print(f"\nreference check: f_x {100 * f['x']['relative_error']:+.4f} %, "
          f"f_y {100 * f['y']['relative_error']:+.4f} %, "
          f"placement {check['placement_error_mm']} mm, {check['placement_error_mrad']} mrad")
    assert check["within_tolerance"] and not check["reasons"]
    assert "twin's true facet" in check["reference"]
    assert abs(f["x"]["relative_error"]) < 5e-5 and abs(f["y"]["relative_error"]) < 5e-5
    figures = {"focal_length_x_m": f["x"]["measured_m"], "focal_length_y_m": f["y"]["measured_m"], "placement": {}}
    design = compare_to_reference(figures, reference_from_simulation(cfg))["focal_lengths"]
    print(f"against the design instead: f_x {100 * design['x']['relative_error']:+.4f} %, "
          f"f_y {100 * design['y']['relative_error']:+.4f} %")
    assert abs(design["y"]["relative_error"]) > 4e-4     # what the old comparison called a station error
    assert max(abs(v) for v in check["placement_error_mm"]) < 0.5
    # what the check determines, with standard uncertainties, and the twin's truth within 3 of them
    det = check["determined"]
    print(f"determined: {det}")
    for key in ("fixture_translation_mm", "fixture_rotation_mrad"):
        assert all(s > 0 for s in det[key]["std"])
        assert all(abs(o) < 3 * s for o, s in zip(det[key]["offset"], det[key]["std"]))
    assert 0 < det["distance_mm"]["std"] < 50
    path = save_geometry(cfg.data_dir, cfg, check, "tests")
    record = load_geometry_record(path)
    assert path.parent == cfg.data_dir / "calibration" / "geometry"
    assert record["screen"] == {"width_px": 1920, "height_px": 1080, "pitch_m": 0.000275}
    assert record["screen_to_camera"] == cfg.geometry.screen_to_camera.to_dict()
    assert "[screen]" in record["provenance"]["screen"] and "[layout]" in record["provenance"]["screen_to_camera"]
    assert record["reference_check"]["within_tolerance"] and record["created"] and record["record_id"] == path.stem
    # the budget uses what the record determined: the fixture pose's std replaces [uncertainty]'s
    det = record["reference_check"]["determined"]
    monkeypatch.setenv("SOFAST_DATA_DIR", str(cfg.data_dir))       # (the tests' isolation sets another)
    used = load_config(cfg.path).uncertainty
    assert used.fixture_rotation_mrad == pytest.approx(tuple(det["fixture_rotation_mrad"]["std"]))
    assert used.fixture_translation_mm == pytest.approx(tuple(det["fixture_translation_mm"]["std"]))
    assert used.distance_mm == max(cfg.uncertainty.distance_mm, det["distance_mm"]["std"])


def test_wrong_known_values_are_reported_outside_tolerance(measured):
    _, check = measured
    figures = {"focal_length_x_m": check["focal_lengths"]["x"]["measured_m"],
               "focal_length_y_m": check["focal_lengths"]["y"]["measured_m"],
               "placement": {"mm": [0.0, 0.0, 0.0], "mrad": [0.0, 0.0, 0.0]}}
    from sofast_station.calibrate.geometry import GeometryReference
    wrong = compare_to_reference(figures, GeometryReference("wrong", 5.60, 5.35, placement_mm=(3.0, 0.0, 0.0)))
    assert not wrong["within_tolerance"]
    assert any(r.startswith("f_x") for r in wrong["reasons"]) and any("placement" in r for r in wrong["reasons"])
    assert wrong["focal_lengths"]["x"]["relative_error"] == pytest.approx(figures["focal_length_x_m"] / 5.60 - 1)


def test_a_wrong_camera_to_screen_separation_shows_in_the_placement(tmp_path, monkeypatch):
    """The real camera sits 5 cm farther from the screen than station.toml says: the reference facet's
    placement comes out turned by more than the tolerance. (Screen pitch and camera focal length errors of
    2 % barely show: with the screen near the centre of curvature the facet reflects only a small patch
    of it, which is what makes the station insensitive to them.)"""
    cfg = small_config(tmp_path / "station")
    true_file = tmp_path / "true" / "station.toml"
    true_file.parent.mkdir()
    true_file.write_text(cfg.path.read_text().replace("separation_m = 0.34", "separation_m = 0.39"))
    true_cfg = load_config(true_file)
    build = simulated_station.build_twin
    monkeypatch.setattr(simulated_station, "build_twin", lambda config, noise=True: build(true_cfg, noise))
    station = open_station(cfg, noise=False)
    try:
        check = check_geometry(inspect(station, "GEOMETRY-REFERENCE"), reference_from_simulation(cfg),
                               cfg.uncertainty)
    finally:
        station.close()
    print(f"\n5 cm separation error: placement {check['placement_error_mm']} mm, {check['placement_error_mrad']} mrad")
    assert not check["within_tolerance"]
    assert any(r.startswith("rotation differs") for r in check["reasons"])


def test_a_range_finder_error_shows_in_the_focal_lengths_and_the_placement(tmp_path):
    cfg = small_config(tmp_path, simulation={"distance_error_m": 0.08})
    station = open_station(cfg, noise=False)
    try:
        check = check_geometry(inspect(station, "GEOMETRY-REFERENCE"), reference_from_simulation(cfg),
                               cfg.uncertainty)
    finally:
        station.close()
    f = check["focal_lengths"]
    print(f"\n8 cm distance error: f_x {100 * f['x']['relative_error']:+.2f} %, "
          f"f_y {100 * f['y']['relative_error']:+.2f} %, "
          f"z {check['placement_error_mm'][2]:+.1f} mm")
    assert not check["within_tolerance"] and abs(check["placement_error_mm"][2] + 80) < 5
    assert f["x"]["relative_error"] > 0.005 and f["y"]["relative_error"] > 0.005


def test_calibrate_geometry_command_with_a_reference_file(tmp_path, capsys):
    cfg = small_config(tmp_path)
    ref = tmp_path / "reference.toml"
    ref.write_text('[reference]\nname = "R-01"\nfocal_length_x_m = 5.42\nfocal_length_y_m = 5.35\n'
                   "focal_length_tolerance = 0.003\n")
    parser = argparse.ArgumentParser(prog="sofast-station")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["calibrate", "geometry", "--config", str(cfg.path), "--reference", str(ref),
                              "--noise-free", "--json"])
    assert args.func(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["reference"] == "R-01" and out["within_tolerance"] and "/calibration/geometry/" in out["path"]
    ref.write_text('[reference]\nfocal_length_x_m = 5.42\nfocal_lenght_y_m = 5.35\n')
    with pytest.raises(ConfigError, match=r"reference\.toml \[reference\] has unknown key\(s\) focal_lenght_y_m"):
        load_reference(ref)
