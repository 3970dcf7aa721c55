"""An opened station: its devices behind their protocols, its configuration and radiometric calibration,
and what is computed once per camera or per facet type and kept while it is open.

Opening one is :func:`~sofast_station.station.factory.open_station`'s work.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..calibrate.records import RadiometricRecord
from ..config import StationConfig
from ..devices.protocols import Camera, Display, RangeFinder
from ..job import job_for
from ..precompute import ray_table
from ..result.record import RecordHead, now_iso

log = logging.getLogger(__name__)


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
    #: The design's optical trace, computed once per facet type
    #: (:class:`~sofast_station.result.optical_figures.DesignTraces`).
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

    def calibration_entry(self, warnings: list[str] | None = None) -> dict:
        """The ``calibration`` entry of a result record: the record in force, where it came from, and the
        staleness warnings that applied to this facet (*warnings*; those found when the station opened by
        default), so an archive row says when it was measured on a stale calibration."""
        entry = {"radiometric": self.radiometric.record_id}
        if self.config.camera_record is not None:
            entry["camera"] = self.config.camera_record["record_id"]
        commissioned = getattr(self.config, "commissioned", None)
        for kind in ("screen", "pose"):
            if commissioned and kind in commissioned:
                entry[kind] = commissioned[kind]["record_id"]
        status = self.calibration
        if status is not None:
            entry["origin"] = status.origin
            entry["warnings"] = list(status.warnings if warnings is None else warnings)
        return entry

    def record_head(self, serial: str, warnings: list[str] | None = None, **more) -> RecordHead:
        """The head of a result record of this station (its name, configuration, calibration and camera
        settings, now), for :func:`~sofast_station.result.record.build_record`; *more*: ``facet`` (the
        station's own by default), ``cycle_id``, ``recipe``, ``request``."""
        more.setdefault("facet", self.config.design.name)
        return RecordHead(serial=serial, time=now_iso(), station=self.config.name, config_hash=self.config.config_hash,
                          calibration=self.calibration_entry(warnings),
                          camera={"exposure_s": self.radiometric.exposure_s, "gain": self.radiometric.gain}, **more)

    def job_for(self, recipe, serial: str | None = None):
        """The job that measures a facet of *recipe* on this station (:func:`~sofast_station.job.job_for`). The
        simulated station may give one that injects the faults its tests ask for *serial*
        (:meth:`~sofast_station.station.simulated.SimulatedStation.job_for`); a real station never does. A
        heliostat recipe with canting prescriptions judges *serial* against its own (docs/field.md)."""
        return job_for(recipe, self.config, serial)

    def truth(self, valid: np.ndarray, job=None) -> dict | None:
        """The ground truth of the facet in the fixture at the pixels *valid* (the analysis kept them), for
        the result record of *job*; None: a real station knows none (the simulated station does,
        :class:`~sofast_station.station.simulated.SimulatedStation`)."""
        return None

    def close(self) -> None:
        for dev in (self.camera, self.display):
            try:
                dev.close()
            except Exception:  # closing must not hide the error that made us close
                log.exception("error while closing %s", type(dev).__name__)
