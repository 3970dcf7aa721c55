"""Heliostats on the twin, many at a time: the population behind the canting's accuracy and coverage claims.

A :class:`HeliostatRig` renders the fringe images once and, per case, traces a drawn heliostat
(:func:`~sofast_station.twin.heliostat.draw_heliostat`), photographs it (optionally with the station's inputs
drawn from their uncertainties: the twin sees the perturbed station, the analysis believes the nominal one),
analyses it (:func:`~sofast_station.measure.heliostat.analyse_heliostat`) and compares every facet with the
twin's truth (:func:`~sofast_station.twin.heliostat.heliostat_truth`). Used by the tests
(``tests/station/test_heliostat_accuracy.py``) and ``benchmarks/heliostat.py``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ..devices.renderer import FringeRenderer
from ..ensemble import EnsembleDesign
from ..fringes import FringeSet
from ..geometry import StationGeometry
from ..measure.heliostat import HeliostatSettings, analyse_heliostat
from ..measure.pipeline import AnalysisSettings
from ..precompute import ray_table
from ..twin.heliostat import TwinHeliostat, heliostat_truth
from .study import perturbed_geometry


@dataclass
class CaseResult:
    """One heliostat of a population: per facet (label) the measured and true canting (mrad) and its U, the
    curvature and slope RMS errors; the statuses; the analysis's seconds."""

    canting: dict
    truth: dict
    u: dict
    curvature_error_per_m: dict
    slope_rms_error_mrad: dict
    status: dict
    seconds: float
    analysis: object = None
    twin: object = None


class HeliostatRig:
    """The twin of a heliostat station without the production devices.

    Parameters
    ----------
    geometry : StationGeometry
        The nominal station (what the analysis believes).
    ensemble : EnsembleDesign
    fringes : FringeSet
    radiometric : RadiometricRecord
        The display's linearisation, exposure and gain.
    analysis : AnalysisSettings
    heliostat : HeliostatSettings
    uncertainty : InputUncertainties or None
    """

    def __init__(self, geometry: StationGeometry, ensemble: EnsembleDesign, fringes: FringeSet, radiometric,
                 analysis: AnalysisSettings = AnalysisSettings(), heliostat: HeliostatSettings = HeliostatSettings(),
                 uncertainty=None):
        self.geometry, self.ensemble, self.fringes = geometry, ensemble, fringes
        self.analysis, self.heliostat, self.uncertainty = analysis, heliostat, uncertainty
        scr = geometry.screen
        with FringeRenderer(scr.width_px, scr.height_px, lut=radiometric.lut, floor_level=radiometric.floor_level,
                            max_level=radiometric.max_level) as renderer:
            self.images = renderer.render_all(fringes.patterns())
        for img in self.images:
            img.setflags(write=False)
        self.exposure_s, self.gain = radiometric.exposure_s, radiometric.gain
        self.rays = ray_table(geometry.camera)
        #: Every facet's sensitivities, kept from case to case (the nominal geometry does not change).
        self.cache: dict = {}

    def twin(self, true_heliostat, optics, geometry: StationGeometry | None = None):
        return TwinHeliostat(geometry or self.geometry, self.ensemble, true_heliostat, optics)

    def capture(self, twin, rng: np.random.Generator | None) -> np.ndarray:
        return np.stack([twin.capture(img, rng, exposure_s=self.exposure_s, gain=self.gain) for img in self.images])

    def case(self, true_heliostat, optics, rng: np.random.Generator | None, perturb: bool = False,
             keep: bool = False, drawn: dict | None = None) -> CaseResult:
        """Trace, photograph, analyse and compare one heliostat. With *perturb*, the twin's station (camera,
        screen, fixture, pitch) and the measured distance are drawn from ``[uncertainty]`` (*rng*); *drawn*, a
        dict, then receives each input's draw (:func:`~sofast_station.station.study.perturbed_geometry`)."""
        geometry, distance_error = self.geometry, 0.0
        if perturb:
            geometry, distance_error = perturbed_geometry(self.geometry, self.uncertainty, rng, drawn)
        twin = self.twin(true_heliostat, optics, geometry)
        frames = self.capture(twin, rng if optics.has_noise else None)
        t = time.perf_counter()
        res = analyse_heliostat(frames, self.fringes, self.geometry, self.ensemble,
                                twin.measured_distance_m() + distance_error, self.analysis, self.heliostat,
                                rays_cam=self.rays, uncertainty=self.uncertainty, sensitivity_cache=self.cache)
        seconds = time.perf_counter() - t
        truth = heliostat_truth(twin, res.valid)["facets"]
        out = CaseResult({}, {}, {}, {}, {}, {}, seconds, res if keep else None, twin if keep else None)
        for f in res.figures["facets"]:
            label = f["label"]
            out.status[label] = f["status"]
            if "canting_mrad" not in f or label not in truth:
                continue
            tr = truth[label]
            out.canting[label] = (f["canting_mrad"]["x"], f["canting_mrad"]["y"])
            out.truth[label] = (tr["canting_mrad"]["x"], tr["canting_mrad"]["y"])
            u = f.get("canting_mrad_U")
            out.u[label] = None if u is None else (u["x"], u["y"])
            out.curvature_error_per_m[label] = (f["curvature_x_per_m"] - tr["curvature_x_per_m"],
                                                f["curvature_y_per_m"] - tr["curvature_y_per_m"])
            out.slope_rms_error_mrad[label] = (f["slope_rms_mrad"]["parabola"]["magnitude"]
                                               - tr["slope_rms_mrad"]["parabola"]["magnitude"])
        return out


def scaled_camera(camera, scale: int):
    """The camera with its resolution divided by *scale*, the same field of view."""
    k = camera.matrix.copy()
    k[:2] /= scale
    w, h = camera.width_px // scale, camera.height_px // scale
    k[0, 2], k[1, 2] = (w - 1) / 2, (h - 1) / 2
    return dataclasses.replace(camera, width_px=w, height_px=h, matrix=k)
