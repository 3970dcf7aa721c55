"""The line's check of its own geometry: the fixture's marks in every cycle's white frame
(docs/reliability.md#the-station-checks-itself).

:class:`MarkCheck` finds the marks (``[marks]``) near their commissioned places (the newest ``marks`` record,
:mod:`sofast_station.calibrate.marks`) and fits their common motion (:mod:`sofast_station.measure.fixture_marks`):

* a shift that amounts to a camera turn beyond ``max_turn_mrad`` (or a roll beyond ``max_roll_mrad``), and
  beyond ``sigmas`` of its own noise, means the camera has moved since commissioning: the facet is not judged
  (the robot hears "fault: calibration", code 7, with the reason), the station's alarm ``line-geometry`` goes
  to the page, OPC UA's ``Alarms/Line``, the PLC's warning bit ``line`` and the console, and the station puts
  itself on hold: it judges no facet, also after a restart, until a newer marks record ends the hold
  (``calibrate confirm-geometry`` after a reference check, or ``calibrate commission``);
* fewer than ``min_marks`` marks found: the geometry cannot be judged, and this facet is not judged either
  (no hold: a hand or a cloth in front of a mark goes away);
* a smaller shift is the fixture pose's uncertainty it implies, added to the figures it reaches
  (:func:`~sofast_station.measure.fixture_marks.widen_for_pose`).

Every facet's record carries what was found (``station_checks.marks``).
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import time

import numpy as np

from ..calibrate.errors import StaleCalibrationError
from ..calibrate.marks import (MarkSettings, focal_px, image_radius_px, mark_settings, marks_in_force, read_hold,
                               write_hold)
from ..measure.fixture_marks import apparent_turn_rad, implied_pose_u, locate_marks, mark_motion

log = logging.getLogger(__name__)

#: The alarm's name in the status file (a line alarm: the page, OPC UA's Alarms/Line and the PLC's bit follow it).
ALARM = "line-geometry"

#: A mark whose residual is this many times the others' RMS (and over OUTLIER_FLOOR_PX) is left out, once.
OUTLIER_FACTOR = 5.0
OUTLIER_FLOOR_PX = 0.05

_ADVICE = ("the station judges no facet until the geometry is confirmed ('sofast-station calibrate confirm-geometry': "
           "a reference facet checked, then the marks' new places taken) or recommissioned ('sofast-station "
           "calibrate commission')")


class CameraMoved(StaleCalibrationError):
    """The fixture's marks show that the camera has moved since commissioning, or cannot be found: the facet
    is not judged (a fault of kind "calibration", the station's, not the facet's)."""


class MarkCheck:
    """The marks' check on a running line (see the module docstring).

    Parameters
    ----------
    settings : MarkSettings
    record : dict
        The marks record in force (:func:`~sofast_station.calibrate.marks.marks_in_force`).
    geometry : StationGeometry
        The geometry the analysis measures with (camera, fixture pose).
    data_dir : path
        Where the hold is kept.
    """

    def __init__(self, settings: MarkSettings, record: dict, geometry, data_dir):
        self.settings = settings
        self.record = record
        self.geometry = geometry
        self.data_dir = data_dir
        self.positions_px = np.asarray(record["positions_px"], dtype=np.float64)
        self.radius_px = image_radius_px(settings, geometry)
        self.focal = (float(geometry.camera.matrix[0, 0]), float(geometry.camera.matrix[1, 1]))
        self.search_px = 1e-3 * settings.search_mrad * focal_px(geometry)
        self.distance_m = float(np.linalg.norm(geometry.fixture_to_camera.translation))
        self.hold = read_hold(data_dir, record["record_id"])

    @classmethod
    def open(cls, config) -> "MarkCheck | None":
        """The check of a station (*config*), or None when it has no ``[marks]``, turns the check off, or has no
        marks record yet (said in the log: run ``calibrate marks``)."""
        settings = mark_settings(config)
        if settings is None:
            return None
        if not settings.enabled:
            log.warning("%s [marks] enabled = false: the fixture's marks are not checked; a moved camera goes "
                        "unnoticed until the next calibration", config.path)
            return None
        record = marks_in_force(config, settings)
        if record is None:
            log.warning("the fixture's marks have no commissioned places (no marks record in %s): they are not "
                        "checked; run 'sofast-station calibrate marks' (or 'calibrate commission')",
                        config.data_dir)
            return None
        return cls(settings, record, config.geometry, config.data_dir)

    @property
    def held(self) -> bool:
        return self.hold is not None

    def check(self, white: np.ndarray, cycle_id: str | None = None, serial: str | None = None) -> dict:
        """Find the marks in a white frame and judge the camera; the record's ``station_checks.marks`` entry.

        Never raises for what it finds: ``withhold`` (the reason) is set when the facet must not be judged
        (the caller raises :class:`CameraMoved` with it), ``pose_u`` when a small shift widens the U's
        (:func:`~sofast_station.measure.fixture_marks.widen_for_pose`)."""
        t0 = time.perf_counter()
        s = self.settings
        loc = locate_marks(white, self.positions_px, self.radius_px, self.search_px, s.min_contrast_dn)
        n, total = int(loc.found.sum()), len(self.positions_px)
        entry: dict = {"record": self.record["record_id"], "found": n, "marks": total, "withhold": None}
        moved = None
        if n < s.min_marks:
            missing = ", ".join(str(k) for k in np.flatnonzero(~loc.found)[:8])
            entry["withhold"] = (f"only {n} of {total} fixture marks were found near their commissioned places "
                                 f"(missing: {missing}): the camera may have moved by more than "
                                 f"{s.search_mrad:g} mrad, or marks are covered, dirty or unlit; the facet is not "
                                 "judged. Clean and uncover the marks; if the camera was moved, recommission "
                                 "('sofast-station calibrate commission')")
        else:
            motion = mark_motion(loc.centres_px, self.positions_px)
            left_out = None
            if n >= 4:
                worst = int(np.nanargmax(np.hypot(*motion.residuals_px.T)))
                rest = mark_motion(loc.centres_px, self.positions_px, use=np.arange(total) != worst)
                resid = float(np.hypot(*motion.residuals_px[worst]))
                if resid > max(OUTLIER_FACTOR * max(rest.residual_rms_px, 1e-12) * math.sqrt(2.0), OUTLIER_FLOOR_PX) \
                        and n - 1 >= s.min_marks:
                    motion, left_out = rest, (worst, resid)
            turn = apparent_turn_rad(motion, self.focal)
            turn_xy = float(np.hypot(turn[0], turn[1]))
            entry.update({"shift_px": [round(float(v), 4) for v in motion.shift_px],
                          "turn_mrad": [round(1e3 * float(v), 5) for v in turn],
                          "scale_ppm": round(1e6 * motion.scale, 2),
                          "residual_rms_px": round(motion.residual_rms_px, 4),
                          "shift_sigma_px": round(motion.shift_sigma_px, 5)})
            if left_out is not None:
                entry["left_out"] = (f"mark {left_out[0]} disagrees with the others by {left_out[1]:.2f} px (knocked, "
                                     "dirty or partly covered?): left out")
            sig_xy = max(motion.shift_sigma_px, 1e-6)
            if turn_xy > 1e-3 * s.max_turn_mrad and motion.shift_norm_px > s.sigmas * sig_xy:
                moved = (f"the camera has moved by {motion.shift_norm_px:.1f} px ({1e3 * turn_xy:.2f} mrad, or "
                         f"{1e3 * turn_xy * self.distance_m:.1f} mm sideways) since commissioning (marks record "
                         f"{self.record['record_id']}, limit {s.max_turn_mrad:g} mrad)")
            elif abs(motion.roll_rad) > 1e-3 * s.max_roll_mrad and \
                    abs(motion.roll_rad) > s.sigmas * max(motion.roll_sigma_rad, 1e-9):
                moved = (f"the camera has turned about its axis by {1e3 * abs(motion.roll_rad):.2f} mrad since "
                         f"commissioning (marks record {self.record['record_id']}, limit {s.max_roll_mrad:g} mrad)")
            else:
                entry["pose_u"] = implied_pose_u(turn, self.geometry.fixture_to_camera.rotation, self.distance_m)
        if moved is not None:
            entry["withhold"] = f"{moved}: {_ADVICE}"
            if self.hold is None:
                self.hold = {"against": self.record["record_id"], "reason": entry["withhold"], "cycle_id": cycle_id,
                             "serial": serial, "time": _dt.datetime.now().astimezone().isoformat(timespec="seconds"),
                             "shift_px": entry.get("shift_px"), "turn_mrad": entry.get("turn_mrad")}
                try:
                    write_hold(self.data_dir, self.hold)
                except OSError as exc:            # the hold stays in force in this process all the same
                    log.error("could not write the marks' hold file: %s", exc)
        elif self.hold is not None:
            since = self.hold.get("serial") or self.hold.get("cycle_id") or "an earlier facet"
            entry["withhold"] = (f"the station has judged no facet since {self.hold.get('time', '?')} ({since}): "
                                 f"{self.hold.get('reason')}")
        if self.hold is not None:
            entry["held_since"] = self.hold.get("time")
        entry["seconds"] = round(time.perf_counter() - t0, 5)
        return entry

    def alarm_text(self) -> str | None:
        """The station's geometry alarm while the hold lasts, else None."""
        if self.hold is None:
            return None
        return f"geometry: {self.hold.get('reason')}"
