"""The commissioned geometry in force: the newest screen and pose records turned into the analysis's
geometry and the uncertainty budget's geometry rows.

With ``[calibration] geometry = "records"`` (the default) the analysis measures with

* the screen's measured shape (an interpolated 3-D screen, :class:`~sofast_station.geometry.MeasuredScreen`)
  from the newest screen record (``calibrate screen``), and
* the camera's pose against the screen and the fixture's pose from the newest pose record
  (``calibrate pose``),

and the budget takes their stated standard uncertainties instead of ``[uncertainty]``'s defaults: the pose
record's for the camera-to-screen rotation and translation and the fixture pose, the screen record's for
the pitch, and the shape's own uncertainty fields as the ``screen shape`` rows. Without records (or with
``geometry = "station.toml"``) the station measures with station.toml's [screen] and [layout], as before.

A record made by another station (:func:`~sofast_station.calibrate.store.check_station`), or for another
display (its pixels, or a pitch more than :data:`PITCH_TOLERANCE` off the one [screen] states: another
station's screen of the same pixel count) or another camera (its image size) is a ConfigError naming the
file and what to do; a pose record made with an older screen record is used, with a warning to repeat
``calibrate pose``.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry import MeasuredScreen, Pose, ScreenSpec, StationGeometry
from .store import newest_record_path

log = logging.getLogger(__name__)

GEOMETRY_SOURCES = ("records", "station.toml")
#: Largest relative difference between a screen record's measured pitch and the pitch [screen] states that
#: is still taken for this screen: a screen calibration finds a display's pitch within a few tenths of a
#: percent of its data sheet (1 % on the twin's station 1, tests/calibrate/test_commission.py); a record 10 %
#: off is another display of the same pixel count, and would put every focal length about 9 mm off.
PITCH_TOLERANCE = 0.03


def geometry_in_force(data_dir: str | Path, stated: StationGeometry, where: str, source: str = "records",
                      station: dict | None = None) -> tuple[StationGeometry, dict | None, dict]:
    """The geometry the analysis uses, what it comes from, and what the records lend the budget.

    Parameters
    ----------
    data_dir : path
        The station's data folder.
    stated : StationGeometry
        The geometry station.toml states (its camera may already be a camera record's).
    where : str
        The station file, for messages.
    source : str
        ``"records"`` or ``"station.toml"`` (``[calibration] geometry``).
    station : dict, optional
        The station's identity (``StationConfig.identity``): a record another station made is refused.

    Returns
    -------
    geometry : StationGeometry
    info : dict or None
        ``screen`` and ``pose`` (record id and path of each record in force) and ``warnings``; None when no
        record is in force.
    std : dict
        ``[uncertainty]`` keys the records state (``screen_rotation_mrad``, ``screen_translation_mm``,
        ``screen_pitch_relative``, ``fixture_rotation_mrad``, ``fixture_translation_mm``), and the pose
        record's joint covariance of the screen's and the fixture's poses (``pose_covariance``, mrad and mm)
        where it has one.
    """
    if source not in GEOMETRY_SOURCES:
        raise ConfigError(f"{where} [calibration] geometry must be \"records\" (the newest screen and pose records) "
                          f"or \"station.toml\" ([screen] and [layout] as entered), got {source!r}")
    if source == "station.toml":
        return stated, None, {}
    # lazy: pose.py, screen.py bring OpenCV's fiducials (~50 ms CPU); config.py imports this module for every command
    from .pose import joint_covariance_mrad_mm, load_pose_record
    from .screen import load_screen_record  # lazy: as pose.py, the line above

    geometry, info, std = stated, {"warnings": []}, {}
    screen_path = newest_record_path(data_dir, "screen", station)
    if screen_path is not None:
        rec = load_screen_record(screen_path)
        made_for = ScreenSpec.from_dict(rec["stated_screen"])
        if (made_for.width_px, made_for.height_px) != (stated.screen.width_px, stated.screen.height_px):
            raise ConfigError(f"screen record {screen_path} is for a {made_for.width_px} x {made_for.height_px} "
                              "display "
                              f"but {where} [screen] says {stated.screen.width_px} x {stated.screen.height_px}: run "
                              "'sofast-station calibrate screen' for this display, or set [calibration] geometry = "
                              "\"station.toml\"")
        _check_pitch(rec, screen_path, stated.screen, where)
        grid = rec["grid"]
        uv = np.asarray(grid["nodes_uv_m"], dtype=np.float64)
        nodes_px = uv / [made_for.pitch_x_m, made_for.pitch_y_m]          # the record's own stated pitch
        measured = MeasuredScreen(nodes_px, np.asarray(grid["nodes_screen_m"], dtype=np.float64),
                                  np.asarray(grid.get("modes_m", []), dtype=np.float64), rec["record_id"])
        geometry = dataclasses.replace(geometry, measured_screen=measured)
        std["screen_pitch_relative"] = max(float(rec["pitch_m"][a]["std"]) / float(rec["pitch_m"][a]["value"])
                                           for a in ("x", "y"))
        info["screen"] = {"record_id": rec["record_id"], "path": str(screen_path)}
    pose_path = newest_record_path(data_dir, "pose", station)
    if pose_path is not None:
        rec = load_pose_record(pose_path)
        cam = rec.get("camera", {})
        if (cam.get("width_px"), cam.get("height_px")) != (stated.camera.width_px, stated.camera.height_px):
            raise ConfigError(f"pose record {pose_path} was made with a {cam.get('width_px')} x {cam.get('height_px')} "
                              f"camera but {where} [camera] is {stated.camera.width_px} x {stated.camera.height_px}: "
                              "run 'sofast-station calibrate pose' with this camera, or set [calibration] geometry = "
                              "\"station.toml\"")
        geometry = dataclasses.replace(geometry, screen_to_camera=Pose.from_dict(rec["screen_to_camera"]),
                                       fixture_to_camera=Pose.from_dict(rec["fixture_to_camera"]))
        std.update({"screen_rotation_mrad": tuple(rec["screen_std"]["rotation_mrad"]),
                    "screen_translation_mm": tuple(rec["screen_std"]["translation_mm"]),
                    "fixture_rotation_mrad": tuple(rec["fixture_std"]["rotation_mrad"]),
                    "fixture_translation_mm": tuple(rec["fixture_std"]["translation_mm"])})
        joint = joint_covariance_mrad_mm(rec)        # validated by load_pose_record; None in older records
        if joint is not None:
            std["pose_covariance"] = joint
        info["pose"] = {"record_id": rec["record_id"], "path": str(pose_path)}
        used = rec.get("screen_record")
        newest = info.get("screen", {}).get("record_id")
        if used != newest:
            info["warnings"].append(f"pose record {rec['record_id']} was measured with screen record "
                                    f"{used or 'none (a flat screen)'}, the newest is {newest or 'none'}: run "
                                    "'sofast-station calibrate pose' again")
        if cam != stated.camera.to_dict():
            info["warnings"].append(f"pose record {rec['record_id']} was measured with other camera intrinsics than "
                                    "the station's now: run 'sofast-station calibrate pose' again")
    if "screen" not in info and "pose" not in info:
        return stated, None, {}
    for w in info["warnings"]:
        log.warning("%s", w)
    return geometry, info, std


def _check_pitch(record: dict, path: Path, stated: ScreenSpec, where: str) -> None:
    """Refuse a screen record whose measured pitch is more than :data:`PITCH_TOLERANCE` off [screen]'s: it is
    not this display (the same pixel count, another size)."""
    try:
        measured = {a: float(record["pitch_m"][a]["value"]) for a in ("x", "y")}
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"screen record {path} has no measured pitch: rerun 'sofast-station calibrate screen'") \
            from None
    for axis, said in (("x", stated.pitch_x_m), ("y", stated.pitch_y_m)):
        off = measured[axis] / said - 1.0
        if abs(off) > PITCH_TOLERANCE:
            raise ConfigError(f"screen record {path} measured a pitch of {1e6 * measured[axis]:.1f} um in {axis}, "
                              f"{100 * off:+.1f} % off the {1e6 * said:.1f} um {where} [screen] states (more than "
                              f"{100 * PITCH_TOLERANCE:g} %): it is another display's (another station's record?). "
                              "Run 'sofast-station calibrate screen' for this display; if the record is right, "
                              "correct [screen] pitch_m")
