"""One inspection: capture the fringe sequence, analyse it, and assemble the facet's result.

The station (:class:`~sofast_station.station.opened.Station`, opened by
:func:`~sofast_station.station.factory.open_station`) holds the devices behind their protocols; ``inspect``
cannot tell a simulated camera from a real one. On the simulated station the result also carries ``truth``,
the twin's ground truth for the pixels the analysis kept.
"""

from __future__ import annotations

import time

import numpy as np

from ..measure.analysis import analyse
from ..result.record import build_record
from ..result.verdict import judge
from .opened import Station


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


def inspect(station: Station, serial: str, progress=None, pictures_dir=None) -> dict:
    """Measure the facet in the fixture and return its result record (with ``truth`` on the twin); a heliostat
    station's record has one entry per facet (:func:`~sofast_station.station.heliostat.inspect_heliostat`,
    which writes its pictures to *pictures_dir* when given)."""
    t0 = time.perf_counter()
    frames, distance = capture(station, progress)
    t_capture = time.perf_counter() - t0
    if station.config.ensemble is not None:
        from .heliostat import inspect_heliostat
        return inspect_heliostat(station, serial, frames, distance, t_capture, pictures_dir)
    rays = station.rays_cam
    t1 = time.perf_counter()
    analysis = analyse(frames, station.config.fringes, station.config.geometry, station.config.design, distance,
                       station.config.analysis, rays_cam=rays, uncertainty=station.config.uncertainty,
                       sensitivity_cache=station.sensitivity_cache)
    t_analysis = time.perf_counter() - t1
    optics = getattr(station.config, "optics", None)
    if optics is not None:
        from ..result.optical_figures import DesignTraces, add_optics
        if station.design_traces is None:
            station.design_traces = DesignTraces()
        add_optics(analysis, station.config.design, optics, station.design_traces)
    timings = {"capture": t_capture, **{f"analysis_{k}": v for k, v in analysis.timings_s.items()},
               "analysis": t_analysis}
    config = station.config
    record = build_record(station.record_head(serial), figures=analysis.figures,
                          verdict=judge(analysis.figures, config.design, config.limits, config.quality),
                          truth=station.truth(analysis.valid, config.design, optics), timings=timings)
    record["timings_s"]["total"] = time.perf_counter() - t0
    return record
