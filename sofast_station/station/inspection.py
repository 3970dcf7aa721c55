"""One inspection: capture the fringe sequence as the line does, analyse it, and assemble the facet's result.

The station (:class:`~sofast_station.station.opened.Station`, opened by
:func:`~sofast_station.station.factory.open_station`) holds the devices behind their protocols; ``inspect``
cannot tell a simulated camera from a real one. It measures through the line's own sequence
(:func:`~sofast_station.station.frames.capture_sequence`: a four-step set that fails its check is retaken;
the capture cropped to the facet and restored, so the analysis sees what a dump keeps) and the recipe's job
(:mod:`sofast_station.job`), so its record is the line's. On the simulated station the result also carries
``truth``, the twin's ground truth for the pixels the analysis kept.
"""

from __future__ import annotations

import time

import numpy as np

from ..job import Capture, job_for
from ..recipes import default_recipe
from ..result.optical_figures import DesignTraces
from .frames import capture_sequence, crop, restore
from .opened import Station


def capture(station: Station, progress=None) -> tuple[np.ndarray, float]:
    """Show every pattern once and grab a frame for each, with no retake and no crop: ``(frames, measured
    distance in metres)``. The raw capture, for studies that analyse one capture several ways; ``inspect``
    and the line capture through :func:`~sofast_station.station.frames.capture_sequence`."""
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
    return frames, float(station.range_finder.measure())


def inspect(station: Station, serial: str, progress=None, pictures_dir=None, recipe=None) -> dict:
    """Measure the facet in the fixture with *recipe* (the station's default) and return its result record
    (with ``truth`` on the twin); a heliostat station's record has one entry per facet, and its pictures are
    written to *pictures_dir* when given."""
    t0 = time.perf_counter()
    config = station.config
    recipe = recipe or default_recipe(config)
    # (the recipe's job for this serial: its canting prescription, if the recipe has them; no simulated faults)
    job = job_for(recipe, config, serial)
    raw, notes = capture_sequence(station.display, station.camera, job.shows(config.fringes),
                                  recipe.analysis.mask_threshold_dn, progress=progress)
    distance = float(station.range_finder.measure())
    box = job.crop_box(*raw[:2])
    frames = restore(crop(raw, box), box, raw.shape[1:])
    del raw
    t_capture = time.perf_counter() - t0
    t1 = time.perf_counter()
    if station.design_traces is None:
        station.design_traces = DesignTraces()
    outcome = job.analyse(Capture(frames, distance, config.fringes, config.geometry, station.rays_cam),
                          uncertainty=config.uncertainty, sensitivity_cache=station.sensitivity_cache,
                          design_traces=station.design_traces)
    timings = {"capture": t_capture, "analysis": time.perf_counter() - t1}
    record = job.record(station.record_head(serial, facet=job.name), outcome.figures,
                        station.truth(outcome.valid, job), timings, measured_distance_m=distance,
                        capture_notes=notes)
    record["crop_box"] = list(box)
    if pictures_dir is not None:
        pictures = job.pictures(record, outcome, pictures_dir)
        if pictures:
            record["pictures"] = pictures
    record["timings_s"]["total"] = time.perf_counter() - t0
    return record
