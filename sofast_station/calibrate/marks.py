"""The fixture's marks: their design (``[marks]`` in station.toml), their commissioned image positions (the
``marks`` record, written by ``calibrate marks`` and by ``calibrate commission``), and the hold the station
puts itself on when they show that the camera has moved (docs/reliability.md#the-station-checks-itself).

``calibrate marks`` shows a white screen, grabs a few frames with the station's camera and finds every mark
near where the geometry in force (the pose record's fixture pose, else station.toml's layout) projects it, a
wide search (``commission_search_mrad``: the station is built to a few millimetres); the mean of each mark's
centroids over the frames is its commissioned position, their scatter its repeatability. Every later cycle
looks for each mark within ``search_mrad`` of that position (:mod:`sofast_station.station.marks`).

The hold (``data_dir/calibration/marks/hold.json``): written by the line when the marks show a moved camera,
naming the marks record it was measured against; while that record is the newest, the station judges no facet
(it answers "fault: calibration"), also after a restart. A newer marks record (``calibrate marks`` after
``calibrate confirm-geometry`` has checked a reference, or ``calibrate commission``) ends it.

The routines see the hardware only through the device protocols (Display, Camera).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError, check_table
from ..files import write_json_atomic
from ..fringes import Pattern
from ..geometry import FixtureMarks, StationGeometry
from ..measure.camera import project
from ..measure.fixture_marks import locate_marks
from .errors import CalibrationError
from .store import newest_record_path, read_record, record_dir, write_record

log = logging.getLogger(__name__)

SCHEMA = 1

_KEYS = {"centres_mm", "diameter_mm", "search_mrad", "commission_search_mrad", "max_turn_mrad", "max_roll_mrad",
         "min_marks", "sigmas", "min_contrast_dn", "frames", "enabled"}


@dataclass(frozen=True)
class MarkSettings:
    """``[marks]`` in station.toml.

    Attributes
    ----------
    design : FixtureMarks
        The marks: ``centres_mm`` ([x, y] or [x, y, z] in the fixture frame, mm) and ``diameter_mm``.
    search_mrad : float
        Each cycle, a mark is sought within this camera turn of its commissioned place (0.002 rad is 27 px at
        13,636 px focal length); farther, it counts as not found.
    commission_search_mrad : float
        ``calibrate marks`` seeks each mark within this of where the geometry in force projects it.
    max_turn_mrad : float
        The line stops judging facets when the marks' common shift amounts to a camera turn of more than this
        (about the camera's x or y axis; a sideways slide of D times as much looks alike).
    max_roll_mrad : float
        ... or when they turn about the optical axis by more than this.
    min_marks : int
        Fewer marks found: the check cannot judge the camera, and the facet is not judged either.
    sigmas : float
        A shift counts only when it is also this many of its own standard deviations (from the marks'
        scatter about their common motion): the check never stops the line for its own noise.
    min_contrast_dn : float
        A mark stands at least this far above its surroundings, DN.
    frames : int
        White frames ``calibrate marks`` averages.
    enabled : bool
        False: the marks are not checked (the record is still written by ``calibrate marks``).
    """

    design: FixtureMarks
    search_mrad: float = 2.0
    commission_search_mrad: float = 5.0
    max_turn_mrad: float = 0.05
    max_roll_mrad: float = 0.5
    min_marks: int = 3
    sigmas: float = 6.0
    min_contrast_dn: float = 20.0
    frames: int = 4
    enabled: bool = True


def mark_settings(config) -> MarkSettings | None:
    """``[marks]`` of a station file (*config*: ``path`` and ``raw``), checked; None when it has none.

    Raises
    ------
    ConfigError
        Naming the file, the key, the value and what is allowed.
    """
    table = config.raw.get("marks")
    if table is None:
        return None
    where = f"{config.path} [marks]"
    check_table(table, _KEYS, where)
    centres = table.get("centres_mm")
    if not isinstance(centres, list) or len(centres) < 3 or not all(
            isinstance(c, list) and len(c) in (2, 3) and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                             and math.isfinite(v) for v in c) for c in centres):
        raise ConfigError(f"{where} centres_mm must list at least 3 marks as [x, y] or [x, y, z] in the fixture frame, "
                          f"mm, got {centres!r}")
    xyz = np.array([[float(v) for v in c] + [0.0] * (3 - len(c)) for c in centres]) * 1e-3

    def number(key, default, low, high, integer=False):
        value = table.get(key, default)
        ok = isinstance(value, int) if integer else isinstance(value, (int, float))
        if isinstance(value, bool) or not ok or not math.isfinite(value) or not low < value <= high:
            kind = "a whole number" if integer else "a number"
            raise ConfigError(f"{where} {key} must be {kind} above {low:g} and at most {high:g}, got {value!r}")
        return int(value) if integer else float(value)

    diameter = number("diameter_mm", None, 0.0, 500.0) if "diameter_mm" in table else None
    if diameter is None:
        raise ConfigError(f"{where} needs diameter_mm, the marks' diameter in mm")
    enabled = table.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"{where} enabled must be true or false, got {enabled!r}")
    settings = MarkSettings(
        design=FixtureMarks(xyz, 1e-3 * diameter),
        search_mrad=number("search_mrad", 2.0, 0.0, 50.0),
        commission_search_mrad=number("commission_search_mrad", 5.0, 0.0, 100.0),
        max_turn_mrad=number("max_turn_mrad", 0.05, 0.0, 10.0),
        max_roll_mrad=number("max_roll_mrad", 0.5, 0.0, 50.0),
        min_marks=number("min_marks", 3, 2, 1000, integer=True),
        sigmas=number("sigmas", 6.0, 0.0, 100.0),
        min_contrast_dn=number("min_contrast_dn", 20.0, 0.0, 255.0),
        frames=number("frames", 4, 0, 100, integer=True),
        enabled=enabled)
    if settings.min_marks > len(settings.design):
        raise ConfigError(f"{where} min_marks = {settings.min_marks} is more than the {len(settings.design)} marks "
                          "centres_mm lists")
    if settings.search_mrad > settings.commission_search_mrad:
        raise ConfigError(f"{where} search_mrad ({settings.search_mrad:g}) must not exceed commission_search_mrad "
                          f"({settings.commission_search_mrad:g}): a cycle looks near the commissioned place")
    return settings


# -- where the marks should be, and their image size ---------------------------------------------------------
def image_radius_px(settings: MarkSettings, geometry: StationGeometry) -> float:
    """The marks' mean image radius, pixels (their diameter over their depth in the camera, times f)."""
    depth = geometry.fixture_to_camera.apply(settings.design.centres_m)[:, 2]
    focal = float(np.mean(np.diag(geometry.camera.matrix)[:2]))
    return float(0.5 * settings.design.diameter_m * focal / np.mean(depth))


def focal_px(geometry: StationGeometry) -> float:
    return float(np.mean(np.diag(geometry.camera.matrix)[:2]))


def predicted_px(settings: MarkSettings, geometry: StationGeometry) -> np.ndarray:
    """Where the geometry projects each mark's centre, (N, 2) pixels."""
    return project(geometry.camera, geometry.fixture_to_camera, settings.design.centres_m)


# -- commissioning --------------------------------------------------------------------------------------------
@dataclass
class MarkCommissioning:
    """What ``calibrate marks`` found: each mark's mean position over the frames, its scatter, the predicted
    positions it started from."""

    positions_px: np.ndarray
    std_px: np.ndarray
    predicted_px: np.ndarray
    radius_px: float
    frames: int
    contrast_dn: np.ndarray


def commission_marks(display, camera, settings: MarkSettings, geometry: StationGeometry,
                     timeout_s: float = 2.0) -> MarkCommissioning:
    """Show white, grab ``settings.frames`` frames and find every mark near its predicted position.

    Raises
    ------
    CalibrationError
        When a mark is not found in every frame: which, where it was sought and what to check.
    """
    predicted = predicted_px(settings, geometry)
    radius = image_radius_px(settings, geometry)
    search = 1e-3 * settings.commission_search_mrad * focal_px(geometry)
    found = []
    contrast = None
    for _ in range(settings.frames):
        display.show(Pattern("uniform", command=255))
        frame = camera.grab(timeout_s)
        loc = locate_marks(frame, predicted, radius, search, settings.min_contrast_dn)
        found.append(loc.centres_px)
        contrast = loc.contrast_dn if contrast is None else np.minimum(contrast, loc.contrast_dn)
    found = np.array(found)
    missing = np.flatnonzero(~np.isfinite(found[..., 0]).all(axis=0))
    if missing.size:
        where = ", ".join(f"mark {k} near ({predicted[k, 0]:.0f}, {predicted[k, 1]:.0f}) px (contrast "
                          f"{contrast[k]:.0f} DN)" for k in missing[:4])
        raise CalibrationError(f"{missing.size} of {len(predicted)} fixture marks were not found in every white frame: "
                               f"{where}. Check that they are clean, lit and in view, and that [marks] centres_mm are "
                               f"their places in the fixture frame (sought within {settings.commission_search_mrad:g} "
                               "mrad of where the geometry in force projects them: commission_search_mrad)")
    return MarkCommissioning(found.mean(axis=0), found.std(axis=0, ddof=1) if len(found) > 1 else np.zeros_like(
        found[0]), predicted, radius, len(found), contrast)


def save_marks_record(data_dir, result: MarkCommissioning, settings: MarkSettings, geometry: StationGeometry,
                      source: str, station: dict | None = None, extra: dict | None = None) -> tuple[Path, str]:
    """Write a ``marks`` record (the marks' commissioned image positions); returns its path and id."""
    cam = geometry.camera

    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": "marks", "record_id": record_id, "created": created, "source": source,
                "design": settings.design.to_dict(), "positions_px": result.positions_px.tolist(),
                "std_px": result.std_px.tolist(), "predicted_px": result.predicted_px.tolist(),
                "radius_px": result.radius_px, "frames": result.frames, "contrast_dn": result.contrast_dn.tolist(),
                "camera": {"width_px": cam.width_px, "height_px": cam.height_px,
                           "focal_px": [float(cam.matrix[0, 0]), float(cam.matrix[1, 1])]},
                **(extra or {})}

    return write_record(data_dir, "marks", build, station=station)


def load_marks_record(path, settings: MarkSettings | None = None, geometry: StationGeometry | None = None) -> dict:
    """A marks record, checked against the station's [marks] and camera when given (ConfigError naming the
    file and what to do otherwise)."""
    redo = "run 'sofast-station calibrate marks'"
    d = read_record(path, "marks", SCHEMA, "marks record", redo)
    try:
        positions = np.asarray(d["positions_px"], dtype=np.float64)
        d["positions_px"] = positions
        design = FixtureMarks.from_dict(d["design"])
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise ConfigError(f"marks record {path} is incomplete ({exc}); {redo}") from None
    if positions.shape != (len(design), 2) or not np.all(np.isfinite(positions)):
        raise ConfigError(f"marks record {path} has positions of shape {positions.shape} for {len(design)} marks; "
                          f"{redo}")
    if settings is not None and (len(design) != len(settings.design)
                                 or not np.allclose(design.centres_m, settings.design.centres_m, atol=1e-6)):
        raise ConfigError(f"marks record {path} was made for other marks than [marks] lists now ({len(design)} "
                          f"against {len(settings.design)}, or moved): {redo}")
    if geometry is not None:
        cam = d.get("camera", {})
        if (cam.get("width_px"), cam.get("height_px")) != (geometry.camera.width_px, geometry.camera.height_px):
            raise ConfigError(f"marks record {path} was made with a {cam.get('width_px')} x {cam.get('height_px')} "
                              f"camera, the station's is {geometry.camera.width_px} x {geometry.camera.height_px}: "
                              f"{redo}")
    return d


def marks_in_force(config, settings: MarkSettings | None = None) -> dict | None:
    """The newest marks record of the station (checked), or None when there is none."""
    path = newest_record_path(config.data_dir, "marks", config.identity)
    if path is None:
        return None
    record = load_marks_record(path, settings, config.geometry)
    record["path"] = str(path)
    return record


# -- the hold -------------------------------------------------------------------------------------------------
def hold_path(data_dir) -> Path:
    return record_dir(data_dir, "marks") / "hold.json"


def read_hold(data_dir, record_id: str | None) -> dict | None:
    """The hold in force: the hold file when it was measured against *record_id* (the newest marks record), else
    None (no hold, or one a newer record ended)."""
    try:
        hold = json.loads(hold_path(data_dir).read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        # a hold that cannot be read still holds: the line must not judge facets on a camera that moved
        log.error("the marks' hold file %s cannot be read (%s): the station keeps holding", hold_path(data_dir), exc)
        return {"reason": f"the hold file {hold_path(data_dir)} cannot be read ({exc})", "against": record_id}
    if not isinstance(hold, dict) or hold.get("against") != record_id:
        return None
    return hold


def write_hold(data_dir, hold: dict) -> None:
    """Put the station on hold (*hold*: ``against`` the marks record id, ``reason``, when and at which facet)."""
    write_json_atomic(hold_path(data_dir), hold)


def clear_hold(data_dir) -> bool:
    """Remove the hold file (a new marks record was written); True when there was one."""
    try:
        hold_path(data_dir).unlink()
        return True
    except FileNotFoundError:
        return False
