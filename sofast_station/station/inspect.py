"""One inspection: capture the fringe sequence, analyse it, and assemble the facet's result.

The station object holds the devices behind their protocols; ``inspect`` cannot tell a simulated camera
from a real one. On the simulated station the result also carries ``truth``, the twin's ground truth for
the pixels the analysis kept.
"""

from __future__ import annotations

import datetime as _dt
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from .. import __version__
from ..calibrate.records import RadiometricRecord
from ..config import StationConfig
from ..devices.protocols import Camera, Display, RangeFinder
from ..measure.analysis import analyse
from ..measure.pipeline import Analysis
from ..precompute import ray_table
from .verdict import judge

log = logging.getLogger(__name__)

#: Figures copied from an analysis into the result (and compared with truth).
FIGURE_KEYS = ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
               "twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m",
               "axis_angle_rad", "slope_rms_mrad", "n_points", "boresight_mrad", "optical_tilt_mrad")


@dataclass
class Station:
    """A ready station: devices, configuration, calibration, and per-camera precomputation."""

    config: StationConfig
    display: Display
    camera: Camera
    range_finder: RangeFinder
    radiometric: RadiometricRecord
    twin: object | None = None
    camera_factory: object | None = field(default=None, repr=False)
    #: The radiometric record's status when the station opened (CalibrationStatus: origin, warnings).
    calibration: object | None = None
    _rays: np.ndarray | None = field(default=None, repr=False)
    #: The design's optical trace, computed once per facet type (:class:`~sofast_station.station.optics.DesignTraces`).
    design_traces: object | None = field(default=None, repr=False)
    #: Sensitivities of the figures to the station's inputs, per geometry and recipe, computed on the first
    #: facet and reused (:mod:`sofast_station.measure.uncertainty`).
    sensitivity_cache: dict = field(default_factory=dict, repr=False)

    @property
    def rays_cam(self):
        """Unit pixel rays of the calibrated camera (a RayTable: each pixel's ray computed once)."""
        if self._rays is None:
            self._rays = ray_table(self.config.geometry.camera)
        return self._rays

    def reopen_camera(self) -> None:
        """Close the camera (which aborts a blocked grab) and open it again."""
        if self.camera_factory is None:
            return
        try:
            self.camera.close()
        except Exception:
            log.exception("error while closing the camera")
        self.camera = self.camera_factory()

    def close(self) -> None:
        for dev in (self.camera, self.display):
            try:
                dev.close()
            except Exception:  # closing must not hide the error that made us close
                log.exception("error while closing %s", type(dev).__name__)


def open_station(config: StationConfig, seed: int | None = None, noise: bool = True,
                 calibration_checks: bool = True) -> Station:
    """Connect the devices named in the configuration, with the radiometric calibration in force.

    The calibration is the newest record under ``data_dir``, else the shipped default of ``[calibration]``
    (:mod:`sofast_station.calibrate.store`). A stale record (too old, or the dark level moved) warns or
    refuses as configured; the optional warm-up interlock refuses a cold camera. The calibration routines
    open the station with ``calibration_checks=False``: no staleness checks, and an unreadable record
    falls back to a linear display with a warning (the routine is what replaces it).
    """
    from ..calibrate.store import check_opened_station, open_calibration

    status = open_calibration(config, checks=calibration_checks)
    radiometric = status.record
    if config.backend == "simulated":
        from .simulated import open_simulated
        station = open_simulated(config, radiometric, seed=seed, noise=noise)
    else:
        station = open_hardware(config, radiometric)
        if radiometric.settle_s is not None:     # the display-latency calibration's settle time
            station.display.settle_s = radiometric.settle_s
    station.calibration = status
    try:
        if calibration_checks:
            check_opened_station(station, status)
    except BaseException:
        station.close()
        raise
    return station


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


class FixedRangeFinder:
    """A distance entered by the operator (metres), for stations without a laser range finder."""

    def __init__(self, distance_m: float):
        if not (np.isfinite(distance_m) and distance_m > 0):
            from ..errors import ConfigError
            raise ConfigError(f"[devices] range_finder_options.distance_m must be a positive distance in metres, "
                              f"got {distance_m}")
        self.distance_m = float(distance_m)

    def measure(self) -> float:
        return self.distance_m


def open_hardware(config: StationConfig, radiometric: RadiometricRecord) -> Station:
    """The real station of ``[devices]``: an LCD window, a camera backend, a range finder.

    ::

        [devices]
        display_options = { monitor = "DP-1", settle_s = 0.05 }
        camera = "basler"                       # basler | aravis | replay
        camera_options = { serial = "40012345" }
        range_finder_options = { distance_m = 10.6612 }
    """
    from ..devices.cameras import open_camera
    from ..devices.lcd import LcdDisplay
    from ..errors import ConfigError

    dev = config.raw.get("devices", {})
    where = f"{config.path} [devices]"
    scr, cam = config.geometry.screen, config.geometry.camera
    disp = dict(dev.get("display_options", {}))
    if "monitor" not in disp:
        raise ConfigError(f"{where}: display_options.monitor must name the LCD's monitor (see xrandr)")
    # The settle time after each image: the display-latency calibration's, or station.toml's until one exists.
    settle_s = radiometric.settle_s if radiometric.settle_s is not None else float(disp.get("settle_s", 0.05))
    log.info("display settle time %.3f s (%s)", settle_s,
             "from the latency calibration" if radiometric.settle_s is not None else "from station.toml")
    display = LcdDisplay(disp["monitor"], scr.width_px, scr.height_px, radiometric.lut, radiometric.floor_level,
                         radiometric.max_level, settle_s)
    try:
        kind = dev.get("camera", "basler")
        options = dict(dev.get("camera_options", {}))
        if kind == "replay" and "dump" in options:      # serve a data dump's frames, as captured
            from ..archive import read_dump
            options = {"frames": read_dump(options.pop("dump")).frames(), "loop": True, **options}
        elif kind != "replay":
            options.setdefault("expected_shape", cam.shape)

        def camera_factory():
            camera = open_camera(kind, **options)
            camera.set_exposure(radiometric.exposure_s)
            camera.set_gain(radiometric.gain)
            return camera

        camera = camera_factory()
        rf = dict(dev.get("range_finder_options", {}))
        range_finder = FixedRangeFinder(float(rf.get("distance_m", float("nan"))))
    except BaseException:
        display.close()
        raise
    return Station(config=config, display=display, camera=camera, range_finder=range_finder,
                   radiometric=radiometric, camera_factory=camera_factory)


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
