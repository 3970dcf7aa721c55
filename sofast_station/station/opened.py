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
from ..precompute import ray_table

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
