"""``[camera] intrinsics = "record"``: the station measures with the newest ``calibrate camera`` record.

On the simulated station the twin keeps the [camera] table's camera (the physical one) while the analysis
takes the record's (the estimate), so a record that is wrong shows in the figures: a good record (focal
length 0.1 % and principal point 0.5 px off, about what the board calibration achieves) still meets the
core's tolerances, a lens 30 % longer than the real one does not pass silently, and missing, corrupt
or mismatched records are clear errors naming the file.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from sofast_station.calibrate.camera import BoardSpec, CameraCalibration, save_camera
from sofast_station.config import load_config
from sofast_station.errors import ConfigError, GeometryError, StationError
from sofast_station.geometry import CameraIntrinsics
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import inspect

from tests.station.test_facets import check_against_truth


@pytest.fixture
def station_toml(small_station_toml):
    text = small_station_toml.read_text().replace("[camera]\n", "[camera]\nintrinsics = \"record\"\n", 1)
    small_station_toml.write_text(text)
    return small_station_toml


def write_camera_record(data_dir, camera: CameraIntrinsics):
    cal = CameraCalibration(camera, 0.05, {"fx": 0.1, "fy": 0.1, "cx": 0.2, "cy": 0.2, "distortion": [0.0] * 5}, [],
                            BoardSpec("chessboard", 13, 10, 0.02), True)
    return save_camera(data_dir, cal, "tests: a camera record written by hand")


def scaled(camera: CameraIntrinsics, focal_factor: float, shift_px: float = 0.0) -> CameraIntrinsics:
    k = camera.matrix.copy()
    k[0, 0] *= focal_factor
    k[1, 1] *= focal_factor
    k[:2, 2] += shift_px
    return CameraIntrinsics(camera.width_px, camera.height_px, k, camera.distortion)


def test_a_good_record_is_used_and_named_in_the_result(station_toml):
    stated = load_config(station_toml, use_camera_record=False)
    with pytest.raises(ConfigError, match=r"no camera record in .*calibration/camera: run 'sofast-station calibrate "
                                          r"camera"):
        load_config(station_toml)
    estimate = scaled(stated.geometry.camera, 1.001, 0.5)
    path = write_camera_record(stated.data_dir, estimate)
    cfg = load_config(station_toml)
    assert np.array_equal(cfg.geometry.camera.matrix, estimate.matrix)
    assert cfg.camera_record["record_id"] == path.stem and cfg.camera_record["path"] == path
    # the rest of the geometry is the station's, not the record's
    assert cfg.geometry.fixture_to_camera.to_dict() == stated.geometry.fixture_to_camera.to_dict()
    assert cfg.geometry.screen_to_camera.to_dict() == stated.geometry.screen_to_camera.to_dict()
    station = open_station(cfg, noise=False)
    try:
        assert np.array_equal(station.twin.geometry.camera.matrix, stated.geometry.camera.matrix)
        rec = inspect(station, "CAMREC-1")
    finally:
        station.close()
    assert rec["calibration"]["camera"] == path.stem
    check_against_truth(rec, long_focus=False, tilt=False)
    # The tilt in the fixture is read through the camera: the record's principal point, 0.5 px off in
    # each axis, turns every ray by 0.5 / f_px, and the tilt with them.
    turn_mrad = 1e3 * 0.5 / stated.geometry.camera.matrix[0, 0]
    for axis in "xy":
        err = rec["optical_tilt_mrad"][axis] - rec["truth"]["optical_tilt_mrad"][axis]
        print(f"optical tilt {axis} off by {err:+.4f} mrad; the principal point turns rays by {turn_mrad:.4f} mrad")
        assert abs(abs(err) - turn_mrad) < 0.02


def test_a_wrong_record_is_refused_by_the_distance_check(station_toml):
    """A record whose lens is 30 % longer than the real one does not pass silently: the inspection is refused
    by the range check, which names both distances.

    The facet's corners keep their pixels, so the corner pose (solvePnP with the record's camera) puts the
    facet 1.3 times as far as it is; the screen centre sits beside the camera, so the corner pose's distance
    from it to the measure point is 1.3 times the measured one to well within 1 % (the screen-to-camera
    offset is small against a 10 m range), far beyond the 0.25 m the check allows."""
    stated = load_config(station_toml, use_camera_record=False)
    write_camera_record(stated.data_dir, scaled(stated.geometry.camera, 1.3))     # a 30 % longer lens
    station = open_station(load_config(station_toml), noise=False)
    try:
        with pytest.raises(GeometryError, match=r"measured distance (\d+\.\d+) m differs from the corner pose's "
                                                r"(\d+\.\d+) m by more than 0\.25 m; re-measure the distance") as err:
            inspect(station, "CAMREC-2")
    finally:
        station.close()
    found = re.search(r"distance (\S+) m differs .* pose's (\S+) m", str(err.value))
    measured, corner = float(found[1]), float(found[2])
    print(f"\nrefused: {err.value}\n(corner pose / measured = {corner / measured:.4f})")
    assert corner / measured == pytest.approx(1.3, rel=0.01)


def test_mismatched_or_corrupt_records_name_the_file(station_toml):
    stated = load_config(station_toml, use_camera_record=False)
    cam = stated.geometry.camera
    other = CameraIntrinsics(640, 480, cam.matrix, cam.distortion)
    path = write_camera_record(stated.data_dir, other)
    with pytest.raises(ConfigError, match=rf"{path.name} is for a 640 x 480 camera, but .* says 400 x 300"):
        load_config(station_toml)
    path = write_camera_record(stated.data_dir, cam)
    path.write_text("{ not json")
    with pytest.raises(ConfigError, match=rf"{path.name} is corrupt"):
        load_config(station_toml)
    bad = station_toml.read_text().replace('intrinsics = "record"', 'intrinsics = "newest"')
    station_toml.write_text(bad)
    with pytest.raises(ConfigError, match=r"intrinsics must be \"station.toml\" .* or \"record\""):
        load_config(station_toml)


def test_calibrate_camera_runs_before_any_record_exists(station_toml):
    """A station set to use the record can still make its first one."""
    import argparse

    from sofast_station.station.calibrate_cli import register

    parser = argparse.ArgumentParser(prog="sofast-station")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["calibrate", "camera", "missing.png", "--squares", "13x10", "--square-mm", "20",
                              "--config", str(station_toml)])
    # no record yet, and the images are unreadable: the error is about the images, not the missing record
    with pytest.raises(StationError, match="usable board image"):
        args.func(args)
    assert dataclasses.is_dataclass(load_config(station_toml, use_camera_record=False))


def test_calibrate_status_names_the_camera_intrinsics_in_force(station_toml, capsys):
    from sofast_station.cli import main

    assert main(["calibrate", "status", "--config", str(station_toml)]) == 0
    out = capsys.readouterr().out
    assert "camera intrinsics: from the newest camera record (none usable)" in out and "no camera record in" in out
    stated = load_config(station_toml, use_camera_record=False)
    path = write_camera_record(stated.data_dir, stated.geometry.camera)
    assert main(["calibrate", "status", "--config", str(station_toml)]) == 0
    assert f"camera intrinsics: from the newest camera record ({path.name})" in capsys.readouterr().out
