"""The commissioning routines say what to do when they cannot measure, and write no record of parameters that
are not determined: too few views, markers not found, poor coverage, views from one side, the mirror not in
the fixture; and every ``calibrate`` command ends with its verdict line."""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
import pytest

from sofast_station.calibrate.commission_settings import HandheldCameraSettings, PoseSettings, ScreenSettings
from sofast_station.calibrate.errors import CalibrationError
from sofast_station.calibrate.screen import ScreenCalibration, calibrate_screen, judge_screen, save_screen
from sofast_station.calibrate.store import list_records
from sofast_station.fringes import FringeSet
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.measure.commission import fit_screen
from sofast_station.measure.screen_shape import ScreenShape
from tests.measure.test_commission import CAM, H, W, _views

SCREEN = ScreenSpec(1920, 1080, 0.000275)


class _Blank:
    """A display and a camera that see nothing: the second camera pointed at a wall."""

    shape = (480, 640)

    def show(self, pattern):
        pass

    def grab(self, timeout_s=2.0):
        return np.full(self.shape, 12, dtype=np.uint8)

    def close(self):
        pass


def test_markers_not_found_is_said_per_view_and_too_few_views_refuses():
    settings = ScreenSettings(views=4, camera=HandheldCameraSettings(CAM))
    blank = _Blank()
    with pytest.raises(CalibrationError) as err:
        calibrate_screen(blank, blank, lambda k, n, hint: None, settings, SCREEN, FringeSet(), CAM, (0.5,) * 9)
    msg = str(err.value)
    assert msg.startswith("too few views: 0 usable of 4, at least 4 needed")
    assert "Take 4 views from around the screen" in msg
    assert msg.count("fiducials not found: 0 corners") == 4 and "in focus and not saturated" in msg


def test_a_camera_of_another_size_than_its_calibration_is_refused():
    blank = _Blank()
    other = CameraIntrinsics(800, 600, [[700.0, 0, 399.5], [0, 700.0, 299.5], [0, 0, 1]], np.zeros(5))
    with pytest.raises(CalibrationError, match="calibrate camera --handheld"):
        calibrate_screen(blank, blank, lambda k, n, h: None, ScreenSettings(), SCREEN, FringeSet(), other, (0.5,) * 9)


def _calibration(views) -> ScreenCalibration:
    fit = fit_screen(views, CAM, W, H)
    cal = ScreenCalibration(fit, [], SCREEN, CAM, (0.0,) * 9, ScreenSettings())
    cal.quality = judge_screen(cal, views)
    return cal


def test_views_from_one_side_are_refused_and_no_record_is_written(tmp_path):
    """Six views all from within a few degrees of one direction: their depths cannot be told from the screen's
    size, the routine refuses (the views' spread, 20 degrees at least) and save_screen writes nothing."""
    rng = np.random.default_rng(11)
    views, _ = _views(ScreenShape("flat", W, H), rng, n=6)
    # the same views, turned about the screen centre to come all from one side (within ~6 degrees)
    from tests.measure import test_commission as T

    narrow = []
    for k, v in enumerate(views):
        az = math.radians(60 + 2 * k)
        tilt = math.radians(25 + k)
        pose = T._looking_at(np.array([0.13, 0, 0]) + 0.9 * np.array([math.sin(tilt) * math.cos(az),
                                                                      math.sin(tilt) * math.sin(az), math.cos(tilt)]))
        from sofast_station.measure import bundle
        cam = bundle.camera_vector(CAM)
        shape = ScreenShape("flat", W, H)
        c_px = bundle.project(cam, pose.apply(shape.points(v.corners_uv[:, 0], v.corners_uv[:, 1])))
        f_px = bundle.project(cam, pose.apply(shape.points(v.fringe_uv[:, 0], v.fringe_uv[:, 1])))
        board_xyz = np.column_stack([v.board_xy, np.zeros(len(v.board_xy))])
        b_px = bundle.project(cam, pose.apply(T.BOARD_TO_SCREEN.apply(board_xyz)))
        narrow.append(dataclasses.replace(v, corners_px=c_px + rng.normal(0, 0.07, c_px.shape),
                                          fringe_px=f_px, board_px=b_px + rng.normal(0, 0.07, b_px.shape)))
    cal = _calibration(narrow)
    assert cal.verdict == "refused"
    assert any("directions differ by at most" in r for r in cal.quality["refuse_reasons"])
    assert any("opposite sides" in a for a in cal.quality["advice"])
    with pytest.raises(CalibrationError, match="screen calibration refused \\(no record written\\)"):
        save_screen(tmp_path, cal, "tests")
    assert list_records(tmp_path, "screen") == []


def test_poor_coverage_is_refused():
    """Views whose fringes cover only the screen's left third (the rest out of the image): refused, "keep the
    whole screen in the image"."""
    rng = np.random.default_rng(12)
    views, _ = _views(ScreenShape("flat", W, H), rng, n=6)
    cropped = []
    for v in views:
        keep = v.fringe_uv[:, 0] < W / 3
        cropped.append(dataclasses.replace(v, fringe_px=v.fringe_px[keep], fringe_uv=v.fringe_uv[keep],
                                           fringe_sigma_uv=v.fringe_sigma_uv[keep]))
    cal = _calibration(cropped)
    assert cal.verdict == "refused"
    assert any(r.startswith("poor coverage") for r in cal.quality["refuse_reasons"])
    assert any("whole screen in the image" in a for a in cal.quality["advice"])


def test_the_mirror_missing_from_the_fixture_is_said_and_refused(small_station_toml, monkeypatch):
    """The technician seats the reference mirror, then forgets it for the later placements (the camera sees
    the facet): each is left out with "target not found", and with one placement of three the routine
    refuses ("too few placements") and says what to do."""
    from sofast_station.calibrate.commission_settings import load_mirror_target
    from sofast_station.calibrate.pose import calibrate_pose
    from sofast_station.config import load_config
    from sofast_station.measure.screen_shape import ScreenShape as Shape
    from sofast_station.station.factory import open_station
    from tests.conftest import ROOT

    config = load_config(small_station_toml)
    target = load_mirror_target(ROOT / "fixtures/targets/reference_mirror.toml")
    station = open_station(config, noise=False, calibration_checks=False)
    try:
        placer = station.mirror_placer(target)

        def forgetful(k, n, hint):
            if k == 0:
                placer.place(k, n, hint)
            else:
                placer.restore()

        settings = PoseSettings(placements=3, min_placements=2)
        stated = config.geometry
        with pytest.raises(CalibrationError) as err:
            calibrate_pose(station.display, station.camera, station.range_finder, forgetful, settings, target, stated,
                           config.design, config.fringes, Shape("flat", stated.screen.width_m, stated.screen.height_m))
    finally:
        station.close()
    msg = str(err.value)
    assert msg.startswith("too few placements: 1 usable of 3, at least 2 needed: seat the reference mirror")
    assert msg.count("target not found") == 2 and "is the reference mirror in the fixture" in msg


def test_the_seated_placement_missing_refuses_at_once(small_station_toml):
    """Without the seated placement there is no fixture pose: the routine stops at the first placement."""
    from sofast_station.calibrate.commission_settings import load_mirror_target
    from sofast_station.calibrate.pose import calibrate_pose
    from sofast_station.config import load_config
    from sofast_station.measure.screen_shape import ScreenShape as Shape
    from sofast_station.station.factory import open_station
    from tests.conftest import ROOT

    config = load_config(small_station_toml)
    target = load_mirror_target(ROOT / "fixtures/targets/reference_mirror.toml")
    station = open_station(config, noise=False, calibration_checks=False)
    try:
        with pytest.raises(CalibrationError, match="placement 1 \\(seated, which gives the fixture's pose\\): target "
                                                   "not found"):
            calibrate_pose(station.display, station.camera, station.range_finder, lambda k, n, h: None,
                           PoseSettings(placements=3), target, config.geometry, config.design, config.fringes,
                           Shape("flat", 0.528, 0.297))
    finally:
        station.close()


# -- the command line ---------------------------------------------------------------------------------
def _run(argv):
    from sofast_station.station.calibrate_cli import register

    parser = argparse.ArgumentParser(prog="sofast-station")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.mark.parametrize("verdict, code", [("pass", 0), ("warn", 0), ("refused", 1)])
def test_screen_and_pose_commands_end_with_their_verdict(small_station_toml, monkeypatch, capsys, verdict, code):
    from sofast_station.station import commissioning

    def fake(config, **kwargs):
        return commissioning.Step("screen", verdict, f"Screen calibration ...\nverdict: {verdict.upper()}")

    monkeypatch.setattr(commissioning, "run_screen", fake)
    monkeypatch.setattr(commissioning, "run_pose", fake)
    for sub in ("screen", "pose"):
        assert _run(["calibrate", sub, "--config", str(small_station_toml)]) == code
        assert capsys.readouterr().out.rstrip().splitlines()[-1] == f"verdict: {verdict.upper()}"


def test_commission_runs_the_steps_in_order_and_stops_at_a_refusal(small_station_toml, monkeypatch, capsys):
    """radiometric, screen, pose, geometry in order, each on the configuration read again (the records the
    step before wrote are in force); a refused step stops it, and one summary ends with the verdict."""
    from sofast_station.station import commissioning

    calls = []

    def step(name, verdict):
        def run(config, **kwargs):
            calls.append(name)
            return commissioning.Step(name, verdict, f"{name} ...\nverdict: {verdict.upper()}", {"headline": name})
        return run

    monkeypatch.setattr(commissioning, "run_radiometric", step("radiometric", "pass"))
    monkeypatch.setattr(commissioning, "run_screen", step("screen", "warn"))
    monkeypatch.setattr(commissioning, "run_pose", step("pose", "pass"))
    monkeypatch.setattr(commissioning, "run_geometry", step("geometry", "pass"))
    assert _run(["calibrate", "commission", "--config", str(small_station_toml)]) == 0
    out = capsys.readouterr().out
    assert calls == ["radiometric", "screen", "pose", "geometry"]
    assert out.rstrip().splitlines()[-1] == "verdict: WARN" and "Commissioning of" in out
    calls.clear()
    monkeypatch.setattr(commissioning, "run_pose", step("pose", "refused"))
    assert _run(["calibrate", "commission", "--config", str(small_station_toml)]) == 1
    out = capsys.readouterr().out
    assert calls == ["radiometric", "screen", "pose"]
    assert "stopped after pose" in out and out.rstrip().splitlines()[-1] == "verdict: REFUSED"
