"""Open a station from its configuration: the real devices of ``[devices]`` or the simulated station of
``[simulation]`` (:mod:`sofast_station.station.simulated`), with the radiometric calibration in force.
"""

from __future__ import annotations

import logging

import numpy as np

from ..calibrate.records import RadiometricRecord
from ..calibrate.store import check_opened_station, open_calibration
from ..config import StationConfig
from ..devices.cameras import open_camera
from ..devices.lcd import LcdDisplay
from ..errors import ConfigError
from .opened import Station

log = logging.getLogger(__name__)


def open_station(config: StationConfig, seed: int | None = None, noise: bool = True,
                 calibration_checks: bool = True) -> Station:
    """Connect the devices named in the configuration, with the radiometric calibration in force.

    The calibration is the newest record under ``data_dir``, else the shipped default of ``[calibration]``
    (:mod:`sofast_station.calibrate.store`). A stale record (too old, or the dark level moved) warns or
    refuses as configured; the optional warm-up interlock refuses a cold camera. The calibration routines
    open the station with ``calibration_checks=False``: no staleness checks, and an unreadable record
    falls back to a linear display with a warning (the routine is what replaces it).
    """
    status = open_calibration(config, checks=calibration_checks)
    radiometric = status.record
    if config.backend == "simulated":
        # A real station's run, inspect and calibrate open their station here and never need the twin.
        # lazy: the twin costs ~850 ms CPU (+649 modules, scipy) after this module's own imports
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


class FixedRangeFinder:
    """A distance entered by the operator (metres), for stations without a laser range finder."""

    def __init__(self, distance_m: float):
        if not (np.isfinite(distance_m) and distance_m > 0):
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
            # Inspect and calibrate open their station here; only a replay camera serving a dump needs it.
            # lazy: the archive package costs ~55 ms CPU (+18 modules) after this module's imports
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
