"""Station geometry: a reference facet of known shape checks the camera/screen geometry the analysis uses,
and the geometry is kept as a record with its provenance."""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np
import pytest

from sofast_station.calibrate.geometry import (check_geometry, compare_to_reference, load_reference,
                                               pitch_sensitivities, reference_from_simulation, station_reference,
                                               summary_text)
from sofast_station.calibrate.geometry_record import load_geometry_record, save_geometry
from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.station import simulated as simulated_station
from sofast_station.station.calibrate_cli import register
from sofast_station.station.commissioning import sensitivities_in_force
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import inspect

from .conftest import small_config


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    folder = tmp_path_factory.mktemp("geometry")
    cfg = small_config(folder)
    station = open_station(cfg, noise=False)
    try:
        rec = inspect(station, "GEOMETRY-REFERENCE")
        check = check_geometry(rec, station_reference(station), cfg.uncertainty)
    finally:
        station.close()
    check["_budget"] = rec["uncertainty_budget"]
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
    # The distance is confirmed as well as the focal lengths' other uncertainties allow: those over f's
    # sensitivity to the distance (mm of distance per metre of f). Its window from the budget's rows: no
    # better than the screen's depth row alone (a screen nearer the camera and a longer distance move f
    # alike: the same place of the surface against the screen), no worse than all of U(f) (k = 1) but the
    # distance's own; a window guessed wide (0 to 50 mm before) passed a std a hundred times off.
    budget = check.pop("_budget")
    rows = {r["group"]: r for r in budget["rows"]}
    per_mm = []
    for axis in ("x", "y"):
        j = budget["figures"].index(f"focal_length_{axis}_m")
        c = rows["measured distance"]["contributions"][j] / cfg.uncertainty.distance_mm
        depth = rows["camera-to-screen translation"]["contributions"][j]
        rest = np.sqrt(sum((r["contributions"][j] or 0.0) ** 2 for r in budget["rows"]
                           if r["group"] != "measured distance"))
        per_mm.append((depth / c, rest / c))
    low, high = min(a for a, _ in per_mm), min(b for _, b in per_mm)
    print(f"distance confirmed to {det['distance_mm']['std']:.3f} mm (window {low:.3f}-{high:.3f} mm)")
    assert low <= det["distance_mm"]["std"] <= high * (1 + 1e-9)
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


def _pitch_check(tmp_path, monkeypatch, pitch_scale: float, facet: dict | None = None):
    """The reference check on the small dish station whose twin's screen pitch is *pitch_scale* times
    the configured one (the analysis keeps station.toml's), the reference facet *facet* in the fixture."""
    cfg = small_config(tmp_path / "station", simulation={"facet": facet} if facet else None)
    true_file = tmp_path / "true" / "station.toml"
    true_file.parent.mkdir()
    true_file.write_text(cfg.path.read_text().replace("pitch_m = 0.000275", f"pitch_m = {0.000275 * pitch_scale!r}"))
    true_cfg = dataclasses.replace(load_config(true_file), simulation=cfg.simulation)
    build = simulated_station.build_twin
    with monkeypatch.context() as patch:
        patch.setattr(simulated_station, "build_twin", lambda config, noise=True: build(true_cfg, noise))
        station = open_station(cfg, noise=False)
    try:
        rec = inspect(station, "GEOMETRY-REFERENCE")
        return check_geometry(rec, station_reference(station), cfg.uncertainty,
                              pitch_sensitivities(sensitivities_in_force(station)))
    finally:
        station.close()


#: A reference facet whose focal lengths are 10 % from the station's design (5.33 m): off the layout's
#: centre of curvature, the screen points it sees spread, and the pitch shows in its focal lengths.
REFERENCE_FACET = {"focal_length_x_m": 5.9, "focal_length_y_m": 5.8, "twist_mrad_per_m": 0.1,
                   "slope_error_rms_mrad": 0.5}


@pytest.mark.parametrize("pitch_scale", [1.01, 0.99])
def test_a_one_percent_screen_pitch_error_is_flagged(tmp_path, monkeypatch, pitch_scale):
    """Issue 26: a screen pitch 10 % off passed the daily check (f off 9 mm, within its 0.5 % tolerance).
    The check now estimates the screen's scale from the focal lengths' deviations and their (signed)
    sensitivity to the pitch: 1 % is found within its U and flagged."""
    check = _pitch_check(tmp_path, monkeypatch, pitch_scale, REFERENCE_FACET)
    scale = check["screen_scale"]
    print(f"\npitch x {pitch_scale}: screen scale {100 * scale['value']:+.3f} +- {100 * scale['U']:.3f} % (k=2); "
          f"f {[round(100 * e['relative_error'], 3) for e in check['focal_lengths'].values()]} %")
    assert scale["resolves"] and scale["flagged"] and not check["within_tolerance"]
    assert abs(scale["value"] - (pitch_scale - 1.0)) < scale["U"]
    assert any("the screen's scale" in r and "pitch_m" in r for r in check["reasons"])
    # the focal lengths alone stay within the reference's 0.5 % tolerance: the scale is what catches it
    assert all(abs(e["relative_error"]) < 0.005 for e in check["focal_lengths"].values())


def test_the_right_screen_pitch_is_not_flagged_and_a_coarse_reference_says_so(tmp_path, monkeypatch):
    right = _pitch_check(tmp_path / "right", monkeypatch, 1.0, REFERENCE_FACET)
    scale = right["screen_scale"]
    print(f"\nright pitch: screen scale {100 * scale['value']:+.3f} +- {100 * scale['U']:.3f} % (k=2)")
    assert scale["resolves"] and not scale["flagged"] and right["within_tolerance"]
    assert abs(scale["value"]) < scale["U"]
    # a reference at the design's focal length, whose centre of curvature the layout puts midway between
    # camera and screen: every pixel sees nearly the same screen point, so the pitch cannot show; said so,
    # not flagged
    coarse = _pitch_check(tmp_path / "coarse", monkeypatch, 1.01, {**REFERENCE_FACET, "focal_length_x_m": 5.335,
                                                                    "focal_length_y_m": 5.33})
    scale = coarse["screen_scale"]
    print(f"reference at the design's f, pitch 1 % off: {scale}")
    assert not scale["resolves"] and not scale["flagged"] and "resolves the screen's scale" in scale["note"]
    assert "screen scale" in summary_text(coarse)
