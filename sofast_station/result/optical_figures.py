"""A result's optical figures: ``[optics]`` in station.toml, and the trace of each analysed facet.

Reads the ``[optics]`` table (and a recipe's ``optics`` overrides) into
:class:`~sofast_station.optics.OpticsSettings`, traces an :class:`~sofast_station.measure.pipeline.Analysis`
with :func:`~sofast_station.optics.facet_optics`, and keeps the design's trace, which is the same for every
facet of a type, in a small cache. ::

    [optics]
    sun = "pillbox"                  # pillbox (4.65 mrad) | gaussian (sigma_mrad) | buie (csr)
    dni_w_m2 = 1000.0
    reflectivity = 0.94
    incidence_angle_deg = 0.0        # the sun's central ray from the facet's optical axis, in its x-z plane
    slant_range_m = 5.33             # default: the design's distance from the facet's centre to its focus
    aperture = { shape = "circle", radius_m = 0.035 }   # or { shape = "rectangle", width_m, height_m }
    rays_per_pixel = 1.0
    min_rays = 200000                # at least this many rays per facet (more per point on small cameras)
    grid_cells = 151
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import OrderedDict

import numpy as np

from ..errors import ConfigError
from ..optics import Aperture, OpticsSettings, SunShape, design_trace, facet_optics, make_scene
from ..optics.facet import FacetOptics
from ..optics.uncertainty import SurfaceUncertainty

log = logging.getLogger(__name__)

#: The keys of ``[optics]`` (and of a recipe's ``optics`` table).
OPTICS_KEYS = ("enabled", "sun", "sigma_mrad", "csr", "dni_w_m2", "reflectivity", "incidence_angle_deg",
               "slant_range_m", "aperture", "rays_per_pixel", "min_rays", "grid_cells", "grid_half_width_m",
               "design_points",
               "seed")
_APERTURE_KEYS = {"circle": ("shape", "radius_m"), "rectangle": ("shape", "width_m", "height_m")}


def _number(where: str, key: str, value, *, integer: bool = False):
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok or not math.isfinite(value):
        kind = "a whole number" if integer else "a number"
        raise ConfigError(f"{where}: {key} must be {kind}, got {value!r}")
    return value if integer else float(value)


def optics_from_table(table: dict, where: str) -> OpticsSettings | None:
    """Validated optics settings from an ``[optics]`` table; None when ``enabled = false``.

    Errors name *where* (file and section), the key, the value and what is allowed.
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table of optics settings")
    unknown = sorted(set(table) - set(OPTICS_KEYS))
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(OPTICS_KEYS)}")
    enabled = table.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"{where}: enabled must be true or false, got {enabled!r}")
    if not enabled:
        return None
    kind = table.get("sun", "pillbox")
    sun_args = {"kind": kind}
    for key in ("sigma_mrad", "csr"):
        if key in table:
            sun_args[key] = _number(where, key, table[key])
    try:
        sun = SunShape(**sun_args)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    aperture = None
    if "aperture" in table:
        ap = table["aperture"]
        if not isinstance(ap, dict) or ap.get("shape") not in _APERTURE_KEYS:
            raise ConfigError(f"{where}: aperture must be {{ shape = \"circle\", radius_m = R }} or "
                              f"{{ shape = \"rectangle\", width_m = W, height_m = H }} (metres), got {ap!r}")
        allowed = _APERTURE_KEYS[ap["shape"]]
        extra = sorted(set(ap) - set(allowed))
        missing = [k for k in allowed if k not in ap]
        if extra or missing:
            raise ConfigError(f"{where}: a {ap['shape']} aperture takes exactly {', '.join(allowed)}; "
                              + (f"unknown {', '.join(extra)}" if extra else f"missing {', '.join(missing)}"))
        try:
            aperture = Aperture(ap["shape"], **{k: _number(where, f"aperture.{k}", ap[k]) for k in allowed[1:]})
        except ValueError as exc:
            raise ConfigError(f"{where}: {exc}") from None
    args = {}
    for key in ("dni_w_m2", "reflectivity", "incidence_angle_deg", "slant_range_m", "rays_per_pixel",
                "grid_half_width_m"):
        if key in table:
            args[key] = _number(where, key, table[key])
    for key in ("grid_cells", "design_points", "seed", "min_rays"):
        if key in table:
            args[key] = _number(where, key, table[key], integer=True)
    try:
        return OpticsSettings(sun=sun, aperture=aperture, **args)
    except ValueError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def optics_for(raw: dict, where: str, recipe: str | None = None) -> OpticsSettings | None:
    """The optics settings of a station file's raw tables: ``[optics]``, with a recipe's ``optics`` table
    (``[recipes.NAME] optics = { aperture = {...} }``) on top."""
    table = dict(raw.get("optics", {}) or {})
    section = f"{where} [optics]"
    if recipe and recipe != "default":
        over = raw.get("recipes", {}).get(recipe, {})
        if isinstance(over, dict) and "optics" in over:
            if not isinstance(over["optics"], dict):
                raise ConfigError(f"{where} [recipes.{recipe}].optics must be a table")
            table.update(over["optics"])
            section = f"{where} [optics] with [recipes.{recipe}].optics"
    return optics_from_table(table, section)


class DesignTraces:
    """The design's trace per (design, settings): the same for every facet of a type, so traced once.

    Keeps the *size* most recently used (a station changes recipes a few times a shift).
    """

    def __init__(self, size: int = 4):
        self._size = size
        self._cache: OrderedDict = OrderedDict()
        #: The optical figures' sensitivities per (design, settings), from the first facet traced with
        #: an uncertainty (docs/uncertainty.md, "Optical figures").
        self.sensitivities: dict = {}

    @staticmethod
    def key(design, settings: OpticsSettings) -> tuple:
        return (json.dumps(design.to_dict(), sort_keys=True), repr(settings))

    def get(self, design, settings: OpticsSettings):
        key = self.key(design, settings)
        hit = self._cache.get(key)
        if hit is None:
            t = time.perf_counter()
            scene = make_scene(design, settings)
            hit = (scene, design_trace(design, settings, scene))
            log.info("design %s traced in %.2f s", design.name, time.perf_counter() - t)
            self._cache[key] = hit
            while len(self._cache) > self._size:
                old, _ = self._cache.popitem(last=False)
                self.sensitivities.pop(old, None)
        self._cache.move_to_end(key)
        return hit


def camera_in_facet_m(analysis) -> np.ndarray:
    """The camera centre in the analysis's (boresighted) facet frame, metres."""
    return analysis.facet_to_camera.inverse().translation


def analysis_optics(analysis, design, settings: OpticsSettings, cache: DesignTraces | None = None) -> FacetOptics:
    """Trace the analysed facet (every valid pixel) and its design."""
    fig = analysis.figures
    cache = cache or DesignTraces(1)
    scene, design_result = cache.get(design, settings)
    kappa = 0.5 * (fig["curvature_x_per_m"] + fig["curvature_y_per_m"])
    # With the analysis's uncertainty, the optical figures get theirs (docs/uncertainty.md, "Optical figures");
    # their sensitivities are computed on the first facet of a type and kept with the design's trace.
    key = DesignTraces.key(design, settings)
    res = facet_optics(analysis.points_facet_m, analysis.slopes, camera_in_facet_m(analysis), design, settings,
                       slope_error_mrad=fig["slope_rms_mrad"]["parabola"]["magnitude"], focal_power_per_m=kappa,
                       scene=scene, design_result=design_result, surface_u=SurfaceUncertainty.from_figures(fig),
                       sensitivities=cache.sensitivities.get(key))
    if res.sensitivities is not None:
        cache.sensitivities[key] = res.sensitivities
    return res


def add_optics(analysis, design, settings: OpticsSettings | None, cache: DesignTraces | None = None
               ) -> FacetOptics | None:
    """Put the optical figures into ``analysis.figures["optics"]`` (and their time into the timings)."""
    if settings is None:
        return None
    t = time.perf_counter()
    res = analysis_optics(analysis, design, settings, cache)
    analysis.figures["optics"] = res.figures
    seconds = time.perf_counter() - t
    analysis.timings_s["optics"] = seconds
    analysis.figures.setdefault("timings_s", {})["optics"] = seconds
    return res
