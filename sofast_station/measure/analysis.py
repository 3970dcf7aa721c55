"""One capture's whole analysis: the data reduction's stages (:mod:`~sofast_station.measure.pipeline`)
and, when the station's input uncertainties are given, every figure's expanded uncertainty and its budget
(:mod:`~sofast_station.measure.uncertainty`).

:func:`analyse` takes arrays and plain records and returns an :class:`~.pipeline.Analysis`; it reads no
file, touches no hardware and keeps no state (but the sensitivity cache its caller hands it), so a data
dump reprocesses to the same bits.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ..facet import FacetDesign
from ..fringes import FringeSet
from ..geometry import StationGeometry
from .budget_rows import add_budget_row
from .deblur import ROUGHNESS_LEFT
from .pipeline import (Analysis, AnalysisSettings, Reduction, figure_at, reduce_stages, thread_pool,
                       to_analysis)
from .screen import ScreenModel
from .sensitivity_record import to_record
from .uncertainty import InputUncertainties, sensitivity_key, uncertainty_figures


def analyse(frames: np.ndarray, fringes: FringeSet, geometry: StationGeometry, design: FacetDesign,
            measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
            screen: ScreenModel | None = None, rays_cam: np.ndarray | None = None,
            pixel_mask: np.ndarray | None = None, uncertainty: InputUncertainties | None = None,
            sensitivity_cache: dict | None = None) -> Analysis:
    """Reduce one capture to the reported figures (docs/conventions.md#measurement-sequence, #data-reduction).

    The reduction runs as named stages (:func:`reduce_stages`): facet region, phase and unwrapping,
    screen points and rays, corners and pose, shape and boresight, fits and figures.

    Parameters
    ----------
    frames : (n, rows, columns) integer array
        Dark, white, then the fringe frames in the order of ``fringes.patterns()``, camera counts (DN).
    fringes : FringeSet
    geometry : StationGeometry
        Camera intrinsics, camera/screen assembly, and the fixture's nominal facet pose.
    design : FacetDesign
    measured_distance_m : float
        Range finder's distance from the screen centre to ``design.measure_point_m``, metres.
    settings : AnalysisSettings
    screen : ScreenModel, optional
        Screen positions -> camera-frame points; the flat screen of ``geometry`` by default.
    rays_cam : (3, rows, columns) array or RayTable, optional
        Precomputed unit pixel rays (:func:`~sofast_station.measure.camera.ray_grid`, or a
        :class:`~sofast_station.measure.camera.RayTable` that keeps the rays it computes); computed for the
        valid pixels when absent.
    pixel_mask : (rows, columns) bool array, optional
        Only these pixels may be used for the shape (to exclude a region, or to compare with another
        program on its own pixels); the facet region and corners still come from the whole image.
    uncertainty : InputUncertainties, optional
        The station inputs' standard uncertainties: with them the figures also carry their expanded
        uncertainties ``name_U`` (k = 2), the noise floor of the slope RMS values and the budget
        (:mod:`sofast_station.measure.uncertainty`).
    sensitivity_cache : dict, optional
        Where the sensitivities (per geometry, recipe and input uncertainties) are kept between calls; the
        caller owns it. Without it they are computed for this capture alone.

    Returns
    -------
    Analysis
    """
    reduction, timings = reduce_stages(frames, fringes, geometry, design, measured_distance_m, settings, screen,
                                       rays_cam, pixel_mask)
    return finish_analysis(reduction, timings, fringes=fringes, geometry=geometry, design=design,
                           measured_distance_m=measured_distance_m, settings=settings, screen=screen,
                           uncertainty=uncertainty, sensitivity_cache=sensitivity_cache)


def finish_analysis(reduction: Reduction, timings: dict, *, fringes: FringeSet, geometry: StationGeometry,
                    design: FacetDesign, measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
                    screen: ScreenModel | None = None, uncertainty: InputUncertainties | None = None,
                    sensitivity_cache: dict | None = None) -> Analysis:
    """The :class:`~.pipeline.Analysis` of a finished reduction (:func:`~.pipeline.reduce_stages`, or one
    rerun from a stage with :func:`~.pipeline.rerun`), with every figure's expanded uncertainty when
    *uncertainty* is given (as :func:`analyse`: its parameters of the same names). *timings* (seconds) gets
    the uncertainty's."""
    if uncertainty is not None:
        t0 = time.perf_counter()
        key = sensitivity_key(geometry, design, fringes, settings, uncertainty, screen)
        with thread_pool(settings.threads) as pool:
            extra = uncertainty_figures(
                reduction, fringes=fringes, geometry=geometry, design=design, measured_distance_m=measured_distance_m,
                settings=settings, inputs=uncertainty, screen=screen, cache=sensitivity_cache, cache_key=key,
                pool=pool)
        sensitivity_s = extra.pop("_sensitivity_seconds")
        frame_pool = extra.pop("_frame_pool")
        reduction.figures.update(extra)
        add_sharpening_row(reduction.figures)
        timings["uncertainty"] = time.perf_counter() - t0
        if sensitivity_s:
            timings["uncertainty_sensitivities"] = sensitivity_s
        if sensitivity_cache is not None and key in sensitivity_cache:
            analysis = to_analysis(reduction, timings)
            analysis.sensitivities = to_record(key, sensitivity_cache[key], frame_pool)
            return analysis
    return to_analysis(reduction, timings)


#: The budget's row for what the figures' sharpening leaves (:data:`~.deblur.ROUGHNESS_LEFT`).
SHARPENING_GROUP = "lens blur on the facet's roughness"


def add_sharpening_row(figures: dict) -> dict:
    """Carry what a blurring lens's sharpening of the fitted figures leaves (``figures["lens_blur_sharpening"]``,
    :func:`~.pipeline.sharpened_fit`) as a systematic row of the budget; nothing for a sharp lens. Its standard
    uncertainty is :data:`~.deblur.ROUGHNESS_LEFT` times the correction pooled over the two axes (root mean
    square): of the curvatures for the curvatures and focal lengths (a focal length's as f^2 times its
    curvature's), and of the two twists e1, e2 for the twists. Returns what was added to each expanded
    uncertainty (:func:`~.budget_rows.add_budget_row`)."""
    correction = figures.get("lens_blur_sharpening") or {}

    def pooled(*paths):
        values = [correction.get(p) for p in paths]
        return ROUGHNESS_LEFT * math.sqrt(sum(v * v for v in values) / len(values)) \
            if all(isinstance(v, float) and math.isfinite(v) for v in values) else 0.0

    curvature = pooled("curvature_x_per_m", "curvature_y_per_m")
    twist = pooled("twist_e1_mrad_per_m", "twist_e2_mrad_per_m")
    if not (curvature or twist):
        return {}
    contributions = {"curvature_x_per_m": curvature, "curvature_y_per_m": curvature,
                     "principal_curvatures_per_m.0": curvature, "principal_curvatures_per_m.1": curvature,
                     "twist_mrad_per_m": twist, "twist_e1_mrad_per_m": twist, "twist_e2_mrad_per_m": twist}
    for path in ("focal_length_x_m", "focal_length_y_m", "principal_focal_lengths_m.0", "principal_focal_lengths_m.1"):
        f = figure_at(figures, path)
        if isinstance(f, (int, float)) and math.isfinite(f):
            contributions[path] = curvature * f * f
    blur = figures.get("edge_blur_px") or 0.0
    return add_budget_row(figures, SHARPENING_GROUP,
                          [f"edge blur {blur:.2f} px on the facet's fine slope structure: "
                           f"{ROUGHNESS_LEFT:g} x the fitted figures' sharpening"], contributions)
