"""One inspection: capture the fringe sequence, analyse it, and assemble the facet's result.

The station (:class:`~sofast_station.station.opened.Station`, opened by
:func:`~sofast_station.station.factory.open_station`) holds the devices behind their protocols; ``inspect``
cannot tell a simulated camera from a real one. On the simulated station the result also carries ``truth``,
the twin's ground truth for the pixels the analysis kept.
"""

from __future__ import annotations

import datetime as _dt
import logging
import time

import numpy as np

from .. import __version__
from ..measure.analysis import analyse
from ..measure.pipeline import Analysis
from .opened import Station
from .verdict import judge

log = logging.getLogger(__name__)

#: Figures copied from an analysis into the result (and compared with truth).
FIGURE_KEYS = ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
               "twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m",
               "axis_angle_rad", "slope_rms_mrad", "n_points", "boresight_mrad", "optical_tilt_mrad")


def calibration_entry(station: Station, warnings: list[str] | None = None) -> dict:
    """The ``calibration`` entry of a result record: the record in force, where it came from, and the
    staleness warnings that applied to this facet (*warnings*; those found when the station opened by
    default), so an archive row says when it was measured on a stale calibration."""
    entry = {"radiometric": station.radiometric.record_id}
    if station.config.camera_record is not None:
        entry["camera"] = station.config.camera_record["record_id"]
    status = station.calibration
    if status is not None:
        entry["origin"] = status.origin
        entry["warnings"] = list(status.warnings if warnings is None else warnings)
    return entry


def capture(station: Station, progress=None) -> tuple[np.ndarray, float]:
    """Show every pattern and grab a frame for each; returns (frames, measured distance in metres)."""
    patterns = station.config.fringes.patterns()
    frames = None
    for i, pattern in enumerate(patterns):
        station.display.show(pattern)
        frame = station.camera.grab()
        if frames is None:
            frames = np.empty((len(patterns), *frame.shape), dtype=frame.dtype)
        frames[i] = frame
        if progress:
            progress(i + 1, len(patterns))
    distance = float(station.range_finder.measure())
    return frames, distance


def now_iso() -> str:
    """Local date and time with its UTC offset, ISO 8601, to the millisecond."""
    return _dt.datetime.now().astimezone().isoformat(timespec="milliseconds")


def result_record(station: Station, serial: str, analysis: Analysis, timings: dict) -> dict:
    """The facet's result as a JSON-ready dict (docs/conventions.md#reported-figures)."""
    fig = analysis.figures
    out = {"serial": serial, "time": now_iso()}
    out.update({k: fig[k] for k in FIGURE_KEYS})
    out.update({k: v for k, v in fig.items() if k not in FIGURE_KEYS and k != "timings_s"})
    out["camera"] = {"exposure_s": station.radiometric.exposure_s, "gain": station.radiometric.gain}
    out["calibration"] = calibration_entry(station)
    out["software_version"] = __version__
    out["config_hash"] = station.config.config_hash
    out["station"] = station.config.name
    out["facet"] = station.config.design.name
    out["timings_s"] = timings
    return out


def inspect(station: Station, serial: str, progress=None) -> dict:
    """Measure the facet in the fixture and return its result record (with ``truth`` on the twin)."""
    t0 = time.perf_counter()
    frames, distance = capture(station, progress)
    t_capture = time.perf_counter() - t0
    rays = station.rays_cam
    t1 = time.perf_counter()
    analysis = analyse(frames, station.config.fringes, station.config.geometry, station.config.design, distance,
                       station.config.analysis, rays_cam=rays, uncertainty=station.config.uncertainty,
                       sensitivity_cache=station.sensitivity_cache)
    t_analysis = time.perf_counter() - t1
    optics = getattr(station.config, "optics", None)
    if optics is not None:
        from .optics import DesignTraces, add_optics
        if station.design_traces is None:
            station.design_traces = DesignTraces()
        add_optics(analysis, station.config.design, optics, station.design_traces)
    timings = {"capture": t_capture, **{f"analysis_{k}": v for k, v in analysis.timings_s.items()},
               "analysis": t_analysis}
    record = result_record(station, serial, analysis, timings)
    record.update(judge(analysis.figures, station.config.design, station.config.limits, station.config.quality))
    if station.twin is not None:
        from ..twin.truth import ground_truth
        truth = ground_truth(station.twin, analysis.valid)
        record["truth"] = {k: truth[k] for k in FIGURE_KEYS if k in truth}
        if optics is not None:       # the same trace of the twin's exact surface at the kept pixels
            from .optics import truth_optics
            record["truth"]["optics"] = truth_optics(station.twin, analysis.valid, station.config.design, optics,
                                                     station.design_traces)
    record["timings_s"]["total"] = time.perf_counter() - t0
    return record
