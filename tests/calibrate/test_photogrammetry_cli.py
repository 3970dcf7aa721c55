"""``calibrate camera-position`` and ``calibrate dots`` as a technician runs them, on photographs rendered from a
known truth (tests/calibrate/photographs.py) with the files a technician has: PNG photographs, a marker table
CSV, a camera record; and ``calibrate screen-data`` on OpenCSP's published screen-shape files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sofast_station.calibrate.camera import SCHEMA as CAMERA_SCHEMA
from sofast_station.calibrate.dot_locations import load_dots
from sofast_station.calibrate.store import list_records
from sofast_station.config import load_config
from sofast_station.geometry import CameraIntrinsics
from sofast_station.interop.opencsp_calibration import read_dot_locations, write_dot_locations
from sofast_station.measure.dots import dot_grid
from tests.calibrate.photographs import DOWN, RIGHT, DotBoard, Lens, camera_in_front, render, wall_markers
from tests.calibrate.test_geomcal_opencsp import DATA, run, station

LENS = Lens(960, 640, 700.0, 699.0, 481.0, 322.0, (-0.06, 0.04, 0.0003, -0.0002, 0.0))
CENTRES = [(-0.8, -0.6), (0.0, -0.65), (0.8, -0.6), (-0.85, 0.05), (0.8, 0.0), (-0.8, 0.65), (0.05, 0.7), (0.8, 0.65)]
IDS = [3, 7, 11, 15, 21, 30, 41, 52]


def write_table(path, ids, corners):
    lines = ["# Marker ID,Corner ID,x (meter),y (meter),z (meter)"]
    lines += [f"{m},{4 * m + k},{c[0]:.9f},{c[1]:.9f},{c[2]:.9f}" for m, cs in zip(ids, corners)
              for k, c in enumerate(cs)]
    path.write_text("\n".join(lines) + "\n")


def write_camera_record(path, std_fx_px: float):
    camera = CameraIntrinsics(LENS.width, LENS.height, LENS.matrix, np.array(LENS.distortion))
    std = {"fx": std_fx_px, "fy": std_fx_px, "cx": 0.2, "cy": 0.2, "distortion": [0.001, 0.002, 1e-5, 1e-5, 0.0]}
    path.write_text(json.dumps({"schema": CAMERA_SCHEMA, "kind": "camera", "record_id": path.stem,
                                "created": "2026-01-01T00:00:00+00:00", "camera": camera.to_dict(),
                                "std_intrinsics": std}))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """Three photographs (PNG) of eight surveyed markers and a 13 x 11 dot board, the marker table, a camera
    record, the board's truth as OpenCSP's dot file (x index = -i: the lattice runs along world -x)."""
    folder = tmp_path_factory.mktemp("scene")
    ids, corners, planes = wall_markers(CENTRES, IDS, 0.10, np.random.default_rng(99))
    target = DotBoard(origin=np.array([0.03, 0.02, 0.015]), a=RIGHT, b=DOWN, pitch=0.04, radius=0.009,
                      i_range=(-6, 7), j_range=(-5, 6), bow=0.003)
    rng = np.random.default_rng(11)
    photos, origins, centres = [], [], []
    for n, x in enumerate((-1.0, 0.0, 1.0)):
        rotation, translation, centre = camera_in_front(rng, x=x, distance=2.6)
        image = render(LENS, rotation, translation, planes, board=target, samples=3, rng=rng)
        path = folder / f"photo{n}.png"
        cv2.imwrite(str(path), image)
        photos.append(path)
        origins.append(LENS.project(rotation, translation, target.origin[None])[0].round(0))
        centres.append(centre)
    write_table(folder / "markers.csv", ids, corners)
    write_camera_record(folder / "camera-record.json", std_fx_px=0.0)
    write_camera_record(folder / "camera-record-std.json", std_fx_px=3.0)
    truth = target.dots()
    keys = np.array([(-i, j) for i, j in truth])
    write_dot_locations(folder / "truth.h5", dot_grid(keys, np.array(list(truth.values()))))
    return folder, photos, origins, centres


def test_camera_position_from_a_png_with_a_camera_record(scene, tmp_path):
    """The camera's centre within its U of the truth; the record's standard deviations (fx 3 px of 700)
    enter U: it grows."""
    folder, photos, _, centres = scene
    cfg = station(tmp_path)
    base = ["calibrate", "camera-position", str(photos[1]), "--markers", str(folder / "markers.csv"), "--config",
            str(cfg), "--json"]
    code, out = run(base + ["--camera", str(folder / "camera-record.json")])
    exact = json.loads(out)
    code_std, out_std = run(base + ["--camera", str(folder / "camera-record-std.json")])
    with_std = json.loads(out_std)
    assert code == code_std == 0
    position, u = np.array(exact["camera_position_m"]), np.array(exact["camera_position_m_U"])
    assert np.all(np.abs(position - centres[1]) <= u), (position - centres[1], u)
    assert np.all(np.array(with_std["camera_position_m_U"]) > u)
    assert exact["markers_used"] == IDS and exact["verdict"] == "pass"
    assert len(list_records(load_config(cfg).data_dir, "cameraposition")) == 2
    code, text = run(["calibrate", "status", "--config", str(cfg)])
    assert "cameraposition: 2 record(s)" in text and "dots: 0 record(s)" in text


def test_calibrate_dots_from_pngs_writes_a_record_that_agrees_with_the_truth(scene, tmp_path):
    """Three PNG photographs: every dot located, the record and OpenCSP's file written, and the comparison
    with the truth (given as OpenCSP's file) printed: RMS under 0.2 mm (0.07, 0.06, 0.18 mm measured) and
    at least 90 % of the coordinates within our U per axis (97 %, 99 %, 100 % measured; one scene of 143
    dots, whose errors share three photographs' pose errors, so the bound is looser than 95 %)."""
    folder, photos, origins, _ = scene
    cfg = station(tmp_path)
    argv = ["calibrate", "dots", *map(str, photos)]
    for o in origins:
        argv += ["--origin", f"{o[0]:.0f},{o[1]:.0f}"]
    argv += ["--camera", str(folder / "camera-record.json"), "--markers", str(folder / "markers.csv"),
             "--compare", str(folder / "truth.h5"), "--opencsp-out", str(tmp_path / "ours.h5"), "--config", str(cfg)]
    code, out = run(argv + ["--json"])
    assert code == 0
    data = json.loads(out)
    assert data["dots_located"] == 143 and data["verdict"] == "pass" and data["compare"]["dots"] == 143
    assert max(data["compare"]["rms_m"]) < 2e-4 and min(data["compare"]["within_U"]) >= 0.9, data["compare"]
    records = list_records(load_config(cfg).data_dir, "dots")
    grid, record = load_dots(records[0])
    assert grid.x_index.tolist() == list(range(-6, 7)) and grid.y_index.tolist() == list(range(-5, 6))
    np.testing.assert_array_equal(read_dot_locations(tmp_path / "ours.h5").xyz_m, grid.xyz_m)
    assert len(record["photos"]) == 3 and record["inputs"]["photos"] == [str(p) for p in photos]


def test_calibrate_screen_data_checks_opencsps_published_files(tmp_path):
    """OpenCSP's 100 x 100 screen distortion data (8808 points, 1192 left out by OpenCSP's 1 mm ray-intersection
    threshold): our model returns its points exactly; built on every other node it strays by 0.13, 0.11,
    0.30 mm RMS (x, y, z) at the others (under 0.3 mm asserted in x and y, 0.6 in z: the data's node-to-node
    scatter); at the 8 calibration fiducials the data lies 1.2, 0.9, 1.4 mm RMS (2.4 mm the largest) from the
    surveyed marker corners paired with them (under 2 mm RMS and 3 mm largest asserted: the fiducials sat
    where the markers say, the frames and the y-flip are read right). Against display_distorted_2d.h5, the
    same projection screen over its full 1920-pixel width: 7.6 mm RMS in x directly, 0.57 mm after an affine
    map whose x scale is 1.0073 (under 1 mm asserted): one shape, two calibrations 0.7 % apart in x scale."""
    common_ = DATA / "sofast_common"
    shape = DATA / "display_shape_calibration"
    code, out = run(["calibrate", "screen-data", str(shape / "data_expected/screen_distortion_data_100_100.h5"),
                     "--markers", str(common_ / "aruco_corner_locations.csv"), "--point-pairs",
                     str(shape / "data_measurement/screen_calibration_point_pairs.csv"), "--projection",
                     str(common_ / "image_projection.h5"), "--display", str(common_ / "display_distorted_2d.h5"),
                     "--config", str(station(tmp_path)), "--json"])
    assert code == 0
    d = json.loads(out)
    assert d["nodes"] == 8808 and max(d["reproduction"]["max_m"]) < 1e-12
    assert max(d["holdout"]["rms_m"][:2]) < 3e-4 and d["holdout"]["rms_m"][2] < 6e-4
    fid = d["fiducials"]
    assert len(fid["pairs"]) == 8 and max(fid["rms_m"]) < 2e-3 and max(fid["max_m"]) < 3e-3
    assert max(d["display"]["affine"]["rms_m"]) < 1e-3 and d["display"]["direct"]["rms_m"][0] > 5e-3
    assert d["display"]["map"][0][0] == pytest.approx(1.0073, abs=5e-4)
    assert d["verdict"] == "pass"
