"""A reference every shift that judges the station, not a facet (docs/reliability.md#a-reference-every-shift).

A recipe with a ``reference`` (its facet's certificate, or "twin" on the simulated station) is measured as any
facet is (the PLC sends it at shift start: its recipe, or a serial its pattern matches, e.g. ``REF-``); its
record is then judged against the certificate (:func:`~sofast_station.calibrate.geometry.compare_to_reference`:
the focal lengths within the certificate's ``focal_length_tolerance``, its placement within its tolerances, its
tilt from its slopes; a reference of unknown outline, whose placement the station does not measure, by its focal
lengths alone). The
reference's verdict is that comparison's: ``pass`` within the limits, ``fail`` beyond them (its facet verdict
against the recipe's limits is kept as ``facet_verdict``); ``station_checks.reference`` holds the errors.

A reference beyond its limits stops the line from judging facets (:class:`ReferenceCheck`): the station's alarm
``line-reference`` (page, OPC UA's Alarms/Line, the PLC's line bit, console), and every other facet withheld
("fault: calibration") until a reference passes again (or the station is recommissioned: a newer pose record);
the hold is kept in ``data_dir/line/reference.json`` and outlives a restart. With ``[run] reference_every_h``
the station also warns (the alarm ``line-reference-age``, no hold) when no reference was measured for that long.

Its result is trended as any recipe's figures are: on the page (the recipe's chart of the shift) and in the
quality reports (``report spc --recipe NAME``: its own control chart; a reference's focal lengths charted are
the station's error, since its certificate does not change).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
from pathlib import Path

from ..calibrate.errors import StaleCalibrationError
from ..calibrate.geometry import compare_to_reference
from ..files import write_json_atomic

log = logging.getLogger(__name__)

ALARM = "line-reference"
AGE_ALARM = "line-reference-age"
#: How many references' results the line keeps (data_dir/line/reference.json) for the page's trend.
HISTORY = 30


class ReferenceFailed(StaleCalibrationError):
    """The last reference was beyond its certificate's limits: the station judges no facet until one passes."""


def state_path(data_dir) -> Path:
    return Path(data_dir) / "line" / "reference.json"


def _now() -> _dt.datetime:
    return _dt.datetime.now().astimezone()


def judge_reference(record: dict, reference) -> dict:
    """Compare a reference facet's *record* with its certificate (*reference*, a GeometryReference): the
    station's errors, within the certificate's limits or not (module docstring)."""
    figures = dict(record)
    placed = isinstance(record.get("placement"), dict)
    tilt = record.get("optical_tilt_mrad")
    if placed and isinstance(tilt, dict) and all(isinstance(tilt.get(a), (int, float)) for a in "xy"):
        # its tilt from the slopes, not the corners (docs/method.md#the-placement-tilt: at 400 x 300 the corners
        # miss a tilt by several mrad, beyond a certificate's 2 mrad, and would hold the line for nothing)
        mrad = list(record["placement"]["mrad"])
        figures["placement"] = {**record["placement"], "mrad": [tilt["x"], tilt["y"], mrad[2]]}
    if not placed:
        # a reference of unknown outline: its placement is not measured, only its focal lengths are judged
        figures["placement"] = {"mm": list(reference.placement_mm), "mrad": list(reference.placement_mrad)}
    check = compare_to_reference(figures, reference)
    if not placed:
        check["placement_error_mm"] = check["placement_error_mrad"] = None
        check["placement_note"] = "not judged: the reference's outline is unknown, its placement is not measured"
    check["focal_length_relative_errors"] = {a: check["focal_lengths"][a]["relative_error"] for a in "xy"}
    return check


class ReferenceCheck:
    """The line's reference: its last result, the hold it puts the line on, its age (module docstring).

    Parameters
    ----------
    data_dir : path
    every_h : float
        Warn when no reference was measured for this long, hours (0: never).
    pose_record : str or None
        The pose record in force: a hold made with an older one ends (the station was recommissioned).
    """

    def __init__(self, data_dir, every_h: float = 0.0, pose_record: str | None = None):
        self.data_dir = data_dir
        self.every_h = float(every_h)
        self.pose_record = pose_record
        try:
            self.state = json.loads(state_path(data_dir).read_text())
            if not isinstance(self.state, dict):
                raise ValueError("not an object")
        except FileNotFoundError:
            self.state = {}
        except (OSError, ValueError) as exc:     # the last result unreadable: said, and forgotten
            log.error("the line's reference state %s cannot be read (%s): it starts anew", state_path(data_dir), exc)
            self.state = {}
        if self.state.get("hold") and self.state.get("pose_record") != pose_record and pose_record is not None:
            log.warning("the reference's hold ends: the station was recommissioned (pose record %s)", pose_record)
            self.state["hold"] = None

    @property
    def hold(self) -> str | None:
        return self.state.get("hold")

    def judged(self, record: dict, reference, recipe: str) -> dict:
        """Judge a reference's record (changes its verdict and reasons, see the module docstring) and update the
        line's state; the record's ``station_checks.reference``."""
        check = judge_reference(record, reference)
        within = bool(check["within_tolerance"])
        record["facet_verdict"] = record.get("verdict")
        record["verdict"] = "pass" if within else "fail"
        errors = check["focal_length_relative_errors"]
        text = ", ".join(f"f {a} {100 * e:+.4f} %" for a, e in errors.items() if e is not None)
        record["reasons"] = ([] if within else [f"reference {record.get('serial')} beyond its certificate's limits: "
                                                + "; ".join(check["reasons"])])
        when = _now().isoformat(timespec="seconds")
        last = {"serial": record.get("serial"), "recipe": recipe, "time": when, "within": within, "errors": text,
                "reasons": check["reasons"]}
        # the references' trend for the page's health line: their relative focal-length errors, newest last
        history = [h for h in self.state.get("history", []) if isinstance(h, dict)][-(HISTORY - 1):]
        history.append({"serial": last["serial"], "time": when, "within": within,
                        "f_error": {a: e for a, e in errors.items()}})
        self.state.update({"last": last, "history": history, "pose_record": self.pose_record})
        if within:
            if self.state.get("hold"):
                log.warning("reference %s passes (%s): the line judges facets again", record.get("serial"), text)
            self.state["hold"] = None
        else:
            self.state["hold"] = (f"the reference {record.get('serial')} measured {when} was beyond its certificate's "
                                  f"limits ({'; '.join(check['reasons'])}): the station judges no facet until a "
                                  "reference passes (send it again, recipe " f"{recipe}) or the station is "
                                  "recommissioned ('sofast-station calibrate commission')")
        self._save()
        return {"certificate": check["reference"], "within": within, "errors": text, **{
            k: check[k] for k in ("focal_lengths", "placement_error_mm", "placement_error_mrad", "tolerances",
                                  "reasons") if k in check}, **({"placement_note": check["placement_note"]}
                                                               if "placement_note" in check else {})}

    def trend_text(self, n: int = 5) -> str | None:
        """The last *n* references' relative focal-length errors (x / y, %), oldest first, for the page."""
        history = self.state.get("history") or []
        if not history:
            return None

        def pct(e):
            return "-" if not isinstance(e, (int, float)) else f"{100 * e:+.3f}"

        return "; ".join(f"{h.get('serial')} {pct((h.get('f_error') or {}).get('x'))} / "
                         f"{pct((h.get('f_error') or {}).get('y'))} %{'' if h.get('within') else ' FAIL'}"
                         for h in history[-n:])

    def age_text(self, now: _dt.datetime | None = None) -> str | None:
        """The age alarm's text when the last reference is older than ``every_h`` (or there is none), else None."""
        if not self.every_h > 0:
            return None
        last = (self.state.get("last") or {}).get("time")
        if last is None:
            return (f"no reference has been measured on this line: send the reference facet at shift start (every "
                    f"{self.every_h:g} h)")
        try:
            age_h = ((now or _now()) - _dt.datetime.fromisoformat(last)).total_seconds() / 3600.0
        except (TypeError, ValueError):
            return None
        if math.isfinite(age_h) and age_h > self.every_h:
            return (f"the last reference ({self.state['last'].get('serial')}) was measured {age_h:.1f} h ago, more "
                    f"than {self.every_h:g} h: send the reference facet")
        return None

    def _save(self) -> None:
        try:
            write_json_atomic(state_path(self.data_dir), self.state)
        except OSError as exc:                  # the hold stays in force in this process all the same
            log.error("could not write the line's reference state: %s", exc)
