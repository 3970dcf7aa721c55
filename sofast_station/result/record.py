"""A facet's result record: its keys, how a figure is read out of it, and the one builder.

The record is a JSON-ready dict (docs/conventions.md#reported-figures): what the journal, the workbook row,
the dump's ``result`` group and ``inspect --json`` hold. Whoever makes one (``inspect``, the production
loop's cycle, ``reprocess``) makes it with :func:`build_record`, so the three cannot drift apart: first the
head (:class:`RecordHead`: which facet, when, on which station, with which calibration), then the
analysis's figures (:data:`FIGURE_KEYS` first) judged against the recipe's limits, or a fault, then the
twin's truth where there is one, then the timings.

A nested figure is named by a dotted path (``slope_rms_mrad.design.magnitude``) and read with
:func:`figure_value`; its expanded uncertainty (k = 2) with :func:`figure_uncertainty`.
"""

from __future__ import annotations

import datetime as _dt
from dataclasses import dataclass

from .. import __version__
from .focal import focal_length_interval

#: Figures copied from an analysis into the result first (and compared with the twin's truth).
FIGURE_KEYS = ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
               "twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m",
               "principal_curvatures_per_m", "axis_angle_rad", "slope_rms_mrad", "n_points", "boresight_mrad",
               "optical_tilt_mrad")

#: Figures added after 0.3.1: an analysis of an older version (a dump's, a test's hand-written figures) may lack
#: them, and its record then has them as None (not measured) rather than failing.
ADDED_FIGURE_KEYS = ("principal_curvatures_per_m",)


def now_iso() -> str:
    """Local date and time with its UTC offset, ISO 8601, to the millisecond."""
    return _dt.datetime.now().astimezone().isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class RecordHead:
    """What a record says before its figures: which facet, when, where, with what.

    Attributes
    ----------
    serial : str
    time : str
        ISO 8601 with time zone (:func:`now_iso`; a re-analysis keeps the capture's).
    station : str
        The station's name.
    config_hash : str
        Of the station file and facet file in force.
    calibration : dict
        The calibration records in force (``radiometric``, ``camera``) and their staleness warnings.
    camera : dict
        ``exposure_s`` and ``gain`` of the capture.
    facet : str or None
        The facet design's name (None for a fault before the recipe was known).
    cycle_id, recipe : str or None
        The production loop's cycle and the recipe that applied (absent for a single ``inspect``).
    request : dict or None
        What the robot or the operator asked for (the loop's records).
    serial_raw : str or None
        The serial as received, when making it safe changed it (:mod:`sofast_station.serials`).
    station_checks : dict or None
        What the line's checks of itself found in this cycle (``marks``: the fixture's marks,
        :mod:`sofast_station.station.marks`; ``temperature``); absent when none ran.
    software_version : str
    """

    serial: str
    time: str
    station: str
    config_hash: str
    calibration: dict
    camera: dict
    facet: str | None = None
    cycle_id: str | None = None
    recipe: str | None = None
    request: dict | None = None
    serial_raw: str | None = None
    station_checks: dict | None = None
    software_version: str = __version__

    def to_dict(self) -> dict:
        out = {"cycle_id": self.cycle_id, "serial": self.serial, "serial_raw": self.serial_raw, "time": self.time,
               "recipe": self.recipe,
               "station": self.station, "facet": self.facet, "software_version": self.software_version,
               "config_hash": self.config_hash, "calibration": self.calibration, "camera": self.camera,
               "request": self.request, "station_checks": self.station_checks}
        return {k: v for k, v in out.items() if v is not None}


def build_record(head: RecordHead, *, figures: dict | None = None, verdict: dict | None = None,
                 fault: tuple[int, str] | None = None, truth: dict | None = None, timings: dict | None = None,
                 **extra) -> dict:
    """A facet's result record.

    Parameters
    ----------
    head : RecordHead
    figures : dict, optional
        The analysis's figures (:data:`FIGURE_KEYS` first, then every other one; ``timings_s`` is not a
        figure and is left out).
    verdict : dict, optional
        :func:`~sofast_station.result.verdict.judge`'s answer for *figures* (``verdict``, ``reasons``...).
    fault : (code, reason), optional
        A cycle that ended without figures: its reason code (docs/plc.md) and its reason, which becomes the
        record's first reason.
    truth : dict, optional
        The digital twin's ground truth for the pixels the analysis kept: only :data:`FIGURE_KEYS` (and the
        optical figures, ``optics``) are kept.
    timings : dict, optional
        Seconds per step of the cycle (``timings_s``).
    **extra
        More keys, after the figures (``measured_distance_m``, ``capture_notes``...).

    Returns
    -------
    dict
    """
    if (figures is None) == (fault is None):
        raise ValueError("a record has either figures or a fault")
    out = head.to_dict()
    if figures is not None:
        out.update({k: figures[k] if k not in ADDED_FIGURE_KEYS else figures.get(k) for k in FIGURE_KEYS})
        out.update({k: v for k, v in figures.items() if k not in FIGURE_KEYS and k != "timings_s"})
        for axis in ("x", "y"):      # f's exact interval from the focal power's U (result/focal.py)
            interval = focal_length_interval(out.get(f"curvature_{axis}_per_m"), out.get(f"curvature_{axis}_per_m_U"))
            if interval is not None:
                out[f"focal_length_{axis}_m_interval"] = interval
    out.update(extra)
    if fault is not None:
        code, reason = fault
        out.update({"verdict": "fault", "fault_code": code, "reasons": [reason]})
    if verdict is not None:
        out.update(verdict)
    if truth is not None:
        out["truth"] = {k: truth[k] for k in (*FIGURE_KEYS, "optics") if k in truth}
    out["timings_s"] = dict(timings or {})
    return out


def figure_value(record: dict, path: str):
    """The figure at a dotted *path* of *record* (``slope_rms_mrad.design.magnitude``), or None."""
    node = record
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node if isinstance(node, (int, float)) and not isinstance(node, bool) else None


def figure_uncertainty(record: dict, path: str):
    """The expanded uncertainty (k = 2) of the figure at *path*: the sibling ``NAME_U`` of the path's
    first key, with the same nesting (``slope_rms_mrad_U.design.magnitude``), or of a deeper key
    (``optics.intercept_U``, ``optics.centroid_offset_mrad_U.x``); None when absent."""
    parts = path.split(".")
    for i in range(len(parts)):
        u = figure_value(record, ".".join(parts[:i] + [parts[i] + "_U"] + parts[i + 1:]))
        if u is not None:
            return u
    return None
