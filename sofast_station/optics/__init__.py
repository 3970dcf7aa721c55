"""Optical performance of a facet: ray trace of measured (or design) points and normals in sunlight.

Pure numpy (no file, hardware or global state). See :mod:`.sun` for the sun shapes, :mod:`.trace` for the
trace and the spot's figures, :mod:`.facet` for a facet against its design.
"""

from .facet import (FacetOptics, OpticsSettings, Scene, analytic_spot_radius_m, design_samples, design_trace,
                    facet_optics, make_scene, pixel_areas_m2, trace_surface)
from .sun import SUN_HALF_ANGLE_RAD, SunShape
from .trace import Aperture, Hits, Target, flux_map, make_target, spot_figures, trace

__all__ = ["Aperture", "FacetOptics", "Hits", "OpticsSettings", "Scene", "SunShape", "SUN_HALF_ANGLE_RAD", "Target",
           "analytic_spot_radius_m", "design_samples", "design_trace", "facet_optics", "flux_map", "make_scene",
           "make_target", "pixel_areas_m2", "spot_figures", "trace", "trace_surface"]
