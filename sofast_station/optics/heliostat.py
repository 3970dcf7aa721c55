"""A heliostat's optics: all its facets' measured surfaces traced together in sunlight onto its target.

Three traces, in the heliostat's optical frame (docs/conventions.md#canting), with the same sun samples
where they can be:

* **design**: every facet's design surface at its design pose (its canting included);
* **measured**: every facet's measured points and slopes, each facet where it was measured;
* **corrected**: the same surfaces, each facet turned back by its canting error about its own origin
  (what re-canting would give; its shape errors stay).

The target (docs/conventions.md#optics, applied to the heliostat): the heliostat frame's origin is the
centre, its +z the design normal there, the slant range ``[optics] slant_range_m`` or the heliostat's design
focal length (its canting's). The figures of each trace are the single facet's (intercept factor, 90 % spot
radius, centroid offset) plus each facet's own beam centroid. The canting's U reaches the measured and the
corrected figures through each facet's turn: drawn facet by facet from its canting U (a Monte Carlo with the
sun samples held, on a decimated trace), with the trace's own sampling error of the intercept added.

Pure numpy: no file, no hardware, no state; the same inputs and seed give the same bits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..ensemble import EnsembleDesign
from .facet import SPOT_FRACTION, OpticsSettings, Scene, analytic_spot_radius_m, design_samples, pixel_areas_m2
from .sun import SUN_HALF_ANGLE_RAD
from .trace import Aperture, Hits, flux_map, make_target, spot_figures, trace

#: Draws of the canting's Monte Carlo.
CANTING_DRAWS = 16
#: Points per draw of the canting's Monte Carlo (the whole heliostat).
DRAW_POINTS = 40_000


@dataclass(frozen=True)
class FacetSurface:
    """One facet's measured surface and where it is on the heliostat.

    Attributes
    ----------
    label : str
    points_m : (3, N) array
        Measured points, the facet's own (boresighted) frame, metres.
    slopes : (2, N) array
        Measured slopes there.
    camera_m : (3,) array
        The camera centre in that frame (for the area each point stands for).
    area_m2 : float
        The facet's design outline's area.
    rotation, translation : (3, 3), (3,) arrays
        The facet's frame in the heliostat's optical frame, as measured.
    corrected_rotation : (3, 3) array
        Its frame with its canting error turned out.
    canting_u_mrad : (2,) array or None
        Its canting's expanded uncertainty (k = 2), about its x and y axes.
    """

    label: str
    points_m: np.ndarray
    slopes: np.ndarray
    camera_m: np.ndarray
    area_m2: float
    rotation: np.ndarray
    translation: np.ndarray
    corrected_rotation: np.ndarray
    canting_u_mrad: np.ndarray | None = None


@dataclass
class HeliostatOptics:
    """What :func:`heliostat_optics` returns.

    Attributes
    ----------
    figures : dict
        ``design``, ``measured``, ``corrected``: each ``intercept``, ``spot_radius_m``, ``spot_radius_mrad``,
        ``centroid_offset_mrad`` {x, y, magnitude}, ``intercepted_w``, ``reflected_w``, ``facet_centroids_mrad``
        {label: {x, y}} (and ``_U`` siblings for the measured and corrected); ``recanting_gain``: the corrected
        intercept less the measured; ``conditions``.
    scene : Scene
    flux_w_m2 : dict
        Trace name -> (cells, cells) flux map, W/m^2 (rows: target y, columns: target x).
    """

    figures: dict
    scene: Scene
    flux_w_m2: dict = field(default_factory=dict)


def heliostat_scene(ensemble: EnsembleDesign, settings: OpticsSettings) -> Scene:
    """The target, aperture and flux grid of a heliostat: centre at its frame's origin, design normal +z, slant
    range ``settings.slant_range_m`` or its design focal length."""
    slant = settings.slant_range_m if settings.slant_range_m is not None else ensemble.focal_length_m
    target = make_target(np.zeros(3), np.array([0.0, 0.0, 1.0]), math.radians(settings.incidence_angle_deg), slant)
    aperture = settings.aperture or Aperture("circle", radius_m=2.0 * slant * SUN_HALF_ANGLE_RAD)
    area = float(sum(_area(f.design.outline_m) for f in ensemble.facets))
    if settings.grid_half_width_m is not None:
        half = float(settings.grid_half_width_m)
    else:
        # the largest facet's image (a flat facet keeps its size) beside the sun's spread
        facet_r = max(math.sqrt(_area(f.design.outline_m) / math.pi) for f in ensemble.facets)
        beam = analytic_spot_radius_m(slant, None, math.pi * facet_r ** 2, 0.0)["beam_radius_m"]
        half = 1.5 * max(aperture.half_size_m, beam)
    return Scene(target, aperture, half, float(ensemble.focal_length_m), area)


def _area(outline: np.ndarray) -> float:
    x, y = outline[:, 0], outline[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _to_heliostat(points: np.ndarray, slopes: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """Points and slopes of a facet frame in the heliostat frame (element-wise: no BLAS on point arrays)."""
    r = np.asarray(rotation, dtype=np.float64)
    p = [r[k, 0] * points[0] + r[k, 1] * points[1] + r[k, 2] * points[2] + translation[k] for k in range(3)]
    nx, ny = -slopes[0], -slopes[1]
    n = [r[k, 0] * nx + r[k, 1] * ny + r[k, 2] for k in range(3)]
    return np.stack(p), np.stack([-n[0] / n[2], -n[1] / n[2]])


def _turn(rx_mrad: float, ry_mrad: float) -> np.ndarray:
    a, b = 1e-3 * rx_mrad, 1e-3 * ry_mrad
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    return np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]]) @ np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa],
                                                                                  [0.0, sa, ca]])


def _trace_facets(parts: list, scene: Scene, settings: OpticsSettings, rays_per_point: float, seed: int) -> tuple:
    """Trace each facet's (label, points, slopes, areas) in turn, each with its own generator; the figures of
    all together and each facet's beam centroid (mrad from the aim point)."""
    xs, ys, ps = [], [], []
    reflected = incident = 0.0
    n_rays = 0
    centroids = {}
    ms = 1000.0 / scene.target.slant_range_m
    for k, (label, pts, slopes, areas) in enumerate(parts):
        rng = np.random.default_rng([settings.seed, seed, k])
        hits = trace(pts, slopes, areas, scene.target, settings.sun, rng, rays_per_point=rays_per_point,
                     dni_w_m2=settings.dni_w_m2, reflectivity=settings.reflectivity)
        xs.append(hits.x_m)
        ys.append(hits.y_m)
        ps.append(hits.power_w)
        reflected += hits.reflected_w
        incident += hits.incident_w
        n_rays += hits.n_rays
        on = float(hits.power_w.sum())
        centroids[label] = ({"x": float(np.sum(hits.power_w * hits.x_m) / on) * ms,
                             "y": float(np.sum(hits.power_w * hits.y_m) / on) * ms} if on > 0 else
                            {"x": None, "y": None})
    hits = Hits(np.concatenate(xs), np.concatenate(ys), np.concatenate(ps), reflected, incident, n_rays)
    return hits, centroids


def _figures(hits: Hits, scene: Scene, centroids: dict) -> dict:
    m = spot_figures(hits, scene.aperture, scene.target.slant_range_m, SPOT_FRACTION)
    return {"intercept": m["intercept"], "spot_radius_m": m["spot_radius_m"], "spot_radius_mrad": m["spot_radius_mrad"],
            "centroid_offset_mrad": m["centroid_offset_mrad"], "intercepted_w": m["intercepted_w"],
            "reflected_w": m["reflected_w"], "facet_centroids_mrad": centroids}


#: The figures whose U the canting's Monte Carlo gives.
_U_KEYS = ("intercept", "spot_radius_m", "spot_radius_mrad")


def heliostat_optics(facets: list, ensemble: EnsembleDesign, settings: OpticsSettings,
                     design_points: int | None = None) -> HeliostatOptics:
    """The heliostat's design, measured and canting-corrected traces (see the module docstring).

    Parameters
    ----------
    facets : list of FacetSurface
        The measured facets (a facet missing from the list is missing from the measured traces; the design
        has them all).
    ensemble : EnsembleDesign
    settings : OpticsSettings
    design_points : int, optional
        Samples of each facet's design surface; default ``settings.design_points`` shared among the facets.

    Returns
    -------
    HeliostatOptics
    """
    scene = heliostat_scene(ensemble, settings)
    # the design, every facet at its design pose
    per = max(200, int((design_points or settings.design_points) / ensemble.n_facets))
    design_parts = []
    for f in ensemble.facets:
        pts, slopes, areas = design_samples(f.design, per)
        p, s = _to_heliostat(pts, slopes, f.rotation, f.position_m)
        design_parts.append((f.label, p, s, areas))
    n_total = sum(f.points_m.shape[1] for f in facets)
    rays = max(settings.rays_per_pixel, settings.min_rays / max(n_total, 1))
    measured_parts, corrected_parts, areas_of = [], [], {}
    for f in facets:
        areas = pixel_areas_m2(f.points_m, f.slopes, np.asarray(f.camera_m, np.float64), f.area_m2)
        areas_of[f.label] = areas
        measured_parts.append((f.label, *_to_heliostat(f.points_m, f.slopes, f.rotation, f.translation), areas))
        corrected_parts.append((f.label, *_to_heliostat(f.points_m, f.slopes, f.corrected_rotation, f.translation),
                                areas))
    out, flux = {}, {}
    design_rays = max(1.0, settings.min_rays / max(sum(p[1].shape[1] for p in design_parts), 1))
    for name, parts, rpp, seed in (("design", design_parts, design_rays, 1), ("measured", measured_parts, rays, 2),
                                   ("corrected", corrected_parts, rays, 2)):
        hits, centroids = _trace_facets(parts, scene, settings, rpp, seed)
        out[name] = _figures(hits, scene, centroids)
        out[name]["rays"] = hits.n_rays
        flux[name], _ = flux_map(hits, scene.grid_half_width_m, settings.grid_cells)
    d = out["design"]["intercepted_w"]
    for name in ("measured", "corrected"):
        out[name]["power_ratio_vs_design"] = out[name]["intercepted_w"] / d if d > 0 else None
    if all(f.canting_u_mrad is not None for f in facets) and facets:
        for name, rot_of in (("measured", lambda f: f.rotation), ("corrected", lambda f: f.corrected_rotation)):
            out[name].update(_canting_u(facets, areas_of, rot_of, scene, settings, out[name]))
    spot = (out["measured"]["spot_radius_mrad"], out["corrected"]["spot_radius_mrad"])
    out["recanting_gain"] = {"intercept": out["corrected"]["intercept"] - out["measured"]["intercept"],
                             "spot_radius_mrad": None if None in spot else spot[1] - spot[0]}
    out["conditions"] = {"sun": settings.sun.kind, "dni_w_m2": settings.dni_w_m2, "reflectivity": settings.reflectivity,
                         "incidence_angle_deg": settings.incidence_angle_deg,
                         "slant_range_m": scene.target.slant_range_m, "aperture": scene.aperture.to_dict(),
                         "facets_traced": [f.label for f in facets]}
    return HeliostatOptics(out, scene, flux)


def _canting_u(facets: list, areas_of: dict, rot_of, scene: Scene, settings: OpticsSettings, full: dict) -> dict:
    """U (k = 2) of a trace's figures from the facets' canting U: each draw turns every facet about its own x
    and y by normal draws of its canting's standard uncertainty, on a decimated trace whose sun samples are
    held; the spread of the figures over the draws, and for the intercept its sampling error too."""
    n_total = sum(f.points_m.shape[1] for f in facets)
    step = max(1, n_total // DRAW_POINTS)
    rng = np.random.default_rng([settings.seed, 77])
    base_parts = []
    for f in facets:
        base_parts.append((f, f.points_m[:, ::step], f.slopes[:, ::step], areas_of[f.label][::step] * step))
    values = []
    for draw in range(CANTING_DRAWS + 1):
        parts = []
        for f, pts, slopes, areas in base_parts:
            r = rot_of(f)
            if draw:
                ux, uy = 0.5 * np.asarray(f.canting_u_mrad, float)
                r = r @ _turn(ux * float(rng.standard_normal()), uy * float(rng.standard_normal()))
            parts.append((f.label, *_to_heliostat(pts, slopes, r, f.translation), areas))
        hits, centroids = _trace_facets(parts, scene, settings, 1.0, 3)
        fig = _figures(hits, scene, centroids)
        values.append([np.nan if fig[k] is None else float(fig[k]) for k in _U_KEYS]
                      + [fig["centroid_offset_mrad"]["magnitude"]])
    v = np.array(values)
    u = np.nanstd(v[1:] - v[0], axis=0, ddof=1)
    p = full["intercept"]
    sampling = math.sqrt(max(p * (1.0 - p), 0.0) / max(full["rays"], 1))
    res = {f"{k}_U": (None if not np.isfinite(u[j]) else float(2.0 * (math.hypot(u[j], sampling) if k == "intercept"
                                                                         else u[j])))
           for j, k in enumerate(_U_KEYS)}
    res["centroid_offset_mrad_U"] = {"magnitude": None if not np.isfinite(u[3]) else float(2.0 * u[3])}
    res["u_draws"] = CANTING_DRAWS
    return res
