"""A facet's optical performance: its measured surface and its design traced in the same sunlight.

:func:`facet_optics` takes the measured points and slopes of every valid pixel (the analysis's
``points_facet_m`` and ``slopes``, in the boresighted facet frame), traces them and the design surface
with :func:`~sofast_station.optics.trace.trace`, and returns the figures the station reports (intercept
factor, 90 % spot radius, centroid offset, intercepted power against the design) with both flux maps.

Pure numpy: no file, no hardware, no global state; the same settings and seed give the same bits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..facet import FacetDesign
from .sun import SUN_HALF_ANGLE_RAD, SunShape
from .trace import Aperture, Hits, Target, flux_map, make_target, spot_figures, trace
from .uncertainty import optics_sensitivities, optics_uncertainty

#: The fraction of the reflected power the spot radius holds (docs/conventions.md, "Optics").
SPOT_FRACTION = 0.9


@dataclass(frozen=True)
class OpticsSettings:
    """How the facet is lit and where its beam is judged (``[optics]`` in station.toml).

    Attributes
    ----------
    sun : SunShape
    dni_w_m2 : float
        Direct normal irradiance, W/m^2.
    reflectivity : float
        Specular reflectivity of the mirror, 0 to 1.
    incidence_angle_deg : float
        Angle of the sun's central ray from the facet's optical axis (facet frame z), in the x-z plane, degrees.
    slant_range_m : float or None
        Distance from the facet's centre to the target plane, metres; None: the design's distance from the
        centre to its focus (the focal length for a facet centred on the paraboloid's vertex).
    aperture : Aperture or None
        The receiver's aperture; None: a circle of twice the radius of the sun's image at the slant range.
    rays_per_pixel : float
        Rays traced per measured point on average (0.5: every second point).
    min_rays : int
        At least this many rays per facet: a measurement with few points (a downsampled camera) gets more
        rays per point, so its flux map is not dominated by sampling noise.
    grid_cells : int
        Cells per side of the flux map.
    grid_half_width_m : float or None
        Half-width of the flux map, metres; None: 1.5 x the larger of the aperture and the design's
        analytic beam radius.
    design_points : int
        Samples of the design surface (a regular grid inside the outline).
    seed : int
        Seed of the sun-shape samples.
    """

    sun: SunShape = field(default_factory=SunShape)
    dni_w_m2: float = 1000.0
    reflectivity: float = 0.94
    incidence_angle_deg: float = 0.0
    slant_range_m: float | None = None
    aperture: Aperture | None = None
    rays_per_pixel: float = 1.0
    min_rays: int = 200_000
    grid_cells: int = 151
    grid_half_width_m: float | None = None
    design_points: int = 50_000
    seed: int = 1

    def __post_init__(self):
        if not (np.isfinite(self.dni_w_m2) and self.dni_w_m2 > 0):
            raise ValueError(f"dni_w_m2 must be a positive irradiance in W/m^2, got {self.dni_w_m2}")
        if not (0.0 < self.reflectivity <= 1.0):
            raise ValueError(f"reflectivity must lie in (0, 1], got {self.reflectivity}")
        if not (0.0 <= self.incidence_angle_deg < 90.0):
            raise ValueError(f"incidence_angle_deg must lie in [0, 90), got {self.incidence_angle_deg}")
        if self.slant_range_m is not None and not (np.isfinite(self.slant_range_m) and self.slant_range_m > 0):
            raise ValueError(f"slant_range_m must be a positive distance in metres, got {self.slant_range_m}")
        if not (np.isfinite(self.rays_per_pixel) and self.rays_per_pixel > 0):
            raise ValueError(f"rays_per_pixel must be positive, got {self.rays_per_pixel}")
        if not (isinstance(self.min_rays, int) and self.min_rays >= 0):
            raise ValueError(f"min_rays must be a whole number >= 0, got {self.min_rays}")
        if not (isinstance(self.grid_cells, int) and 2 <= self.grid_cells <= 4001):
            raise ValueError(f"grid_cells must be a whole number from 2 to 4001, got {self.grid_cells}")
        if self.grid_half_width_m is not None and not (self.grid_half_width_m > 0):
            raise ValueError(f"grid_half_width_m must be a positive distance in metres, got {self.grid_half_width_m}")
        if not (isinstance(self.design_points, int) and self.design_points >= 100):
            raise ValueError(f"design_points must be a whole number of at least 100, got {self.design_points}")


# -- the design surface ----------------------------------------------------------------------------------
def outline_area_m2(outline_m: np.ndarray) -> float:
    """Area of a counter-clockwise polygon (shoelace), square metres."""
    x, y = outline_m[:, 0], outline_m[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def inside_polygon(x: np.ndarray, y: np.ndarray, outline_m: np.ndarray) -> np.ndarray:
    """Which points (x, y) lie inside the polygon (even-odd rule)."""
    inside = np.zeros(np.shape(x), dtype=bool)
    xs, ys = outline_m[:, 0], outline_m[:, 1]
    for k in range(len(outline_m)):
        x0, y0, x1, y1 = xs[k - 1], ys[k - 1], xs[k], ys[k]
        crosses = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= crosses & (x < x_at)
    return inside


def design_samples(design: FacetDesign, n_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, slopes and surface areas of the design surface on a regular grid inside its outline.

    The grid (spacing about h = sqrt(area / n_points), dividing the outline's bounding box evenly) gives
    about *n_points* samples; each stands for an equal share of the outline's projected area.

    Returns
    -------
    points_m (3, N), slopes (2, N), area_m2 (N,)
    """
    outline = design.outline_m
    area = outline_area_m2(outline)
    h = math.sqrt(area / n_points)
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    # Cell centres of a grid that divides the bounding box evenly (symmetric for a symmetric outline).
    nx, ny = (max(1, int(round((hi[k] - lo[k]) / h))) for k in (0, 1))
    gx = lo[0] + (np.arange(nx) + 0.5) * ((hi[0] - lo[0]) / nx)
    gy = lo[1] + (np.arange(ny) + 0.5) * ((hi[1] - lo[1]) / ny)
    x, y = (a.ravel() for a in np.meshgrid(gx, gy, indexing="xy"))
    keep = inside_polygon(x, y, outline)
    x, y = x[keep], y[keep]
    a, b, c, d, e, _ = design.coefficients
    s_x = 2.0 * a * x + c + e * y
    s_y = 2.0 * b * y + d + e * x
    points = np.stack([x, y, design.z(x, y)])
    projected = np.full(x.size, area / x.size)
    return points, np.stack([s_x, s_y]), projected * np.sqrt(1.0 + s_x * s_x + s_y * s_y)


def pixel_areas_m2(points_m: np.ndarray, slopes: np.ndarray, camera_m: np.ndarray, total_projected_m2: float
                   ) -> np.ndarray:
    """Surface area each measured point stands for, from how large a camera pixel looks on the surface.

    A pixel's solid angle is the same for every pixel of a narrow camera (to cos^3 of the field angle, a
    few parts per thousand here), so its footprint on the surface is proportional to d^2 / |cos(view)|,
    with d the distance from the camera centre and view the angle between the line of sight and the
    normal. The footprints are scaled so their projections on the facet's x-y plane add up to
    *total_projected_m2* (the design outline's area): the points that were not measured are taken to
    reflect like the average of those that were.

    Parameters
    ----------
    points_m : (3, N) array
        Measured points, facet frame, metres.
    slopes : (2, N) array
    camera_m : (3,) array
        Camera centre, facet frame, metres.
    total_projected_m2 : float
    """
    f32 = np.float32
    s_x, s_y = slopes.astype(f32)
    inv = 1.0 / np.sqrt(1.0 + s_x * s_x + s_y * s_y)
    v = (np.asarray(camera_m, dtype=np.float64)[:, None] - points_m).astype(f32)
    d2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    cos_view = np.abs(v[2] - s_x * v[0] - s_y * v[1]) * inv / np.sqrt(d2)
    footprint = (d2 / np.maximum(cos_view, f32(1e-3))).astype(np.float64)
    return footprint * (total_projected_m2 / float(np.sum(footprint * inv)))


# -- the scene ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Scene:
    """Everything the traces of one facet type share: target, aperture, flux grid and the design's focus.

    Attributes
    ----------
    target : Target
    aperture : Aperture
    grid_half_width_m : float
    focus_distance_m : float
        The design's distance from the facet's centre to its focus, f + z(c), metres.
    mirror_area_m2 : float
        The design outline's projected area, square metres.
    """

    target: Target
    aperture: Aperture
    grid_half_width_m: float
    focus_distance_m: float
    mirror_area_m2: float


def make_scene(design: FacetDesign, settings: OpticsSettings) -> Scene:
    """The target plane, aperture and flux grid for facets of *design* under *settings*."""
    cx, cy = design.centroid_m
    centre = np.array([cx, cy, float(design.z(cx, cy))])
    a, b, c, d, e, _ = design.coefficients
    normal = np.array([-(2 * a * cx + c + e * cy), -(2 * b * cy + d + e * cx), 1.0])
    focus_distance = design.focal_length_m + float(centre[2])
    slant = settings.slant_range_m if settings.slant_range_m is not None else focus_distance
    target = make_target(centre, normal, math.radians(settings.incidence_angle_deg), slant)
    aperture = settings.aperture or Aperture("circle", radius_m=2.0 * slant * SUN_HALF_ANGLE_RAD)
    area = outline_area_m2(design.outline_m)
    if settings.grid_half_width_m is not None:
        half = float(settings.grid_half_width_m)
    else:
        beam = analytic_spot_radius_m(slant, focus_distance, area, 0.0)["beam_radius_m"]
        half = 1.5 * max(aperture.half_size_m, beam)
    return Scene(target, aperture, half, focus_distance, area)


# -- the patent's analytic model ---------------------------------------------------------------------------
def analytic_spot_radius_m(slant_range_m: float, focal_distance_m: float | None, mirror_area_m2: float,
                           slope_error_mrad: float, sun_half_angle_rad: float = SUN_HALF_ANGLE_RAD) -> dict:
    """The beam radius of the point-focus model in Sandia's US patent 8,669,509 (Ho et al.), Eqs. 51-55.

    ``R = L tan(beta/2) + R_h |L/b - 1|``: the first term is the spread of the sun and the slope errors,
    with beta/2 = sun half-angle + 2 sigma (the patent's "Sun half angle and any additional slope errors";
    a slope error turns the reflected ray by twice its angle), the second the mirror's own image
    converging to (L < b) or diverging from (L > b) its focus at distance b; R_h = sqrt(A/pi) is the radius
    of the round mirror of the facet's area. The model assumes a uniform sun, a round focused mirror, no
    cosine loss or off-axis aberration, and a uniformly lit beam, so the radius holding 90 % of the power
    is sqrt(0.9) R.

    Parameters
    ----------
    slant_range_m : float
        L, metres.
    focal_distance_m : float or None
        b, the mirror's focal distance, metres; None (a flat mirror) or inf makes the second term R_h.
    mirror_area_m2 : float
    slope_error_mrad : float
        sigma, mrad.
    sun_half_angle_rad : float

    Returns
    -------
    dict with ``beam_radius_m`` (R), ``spot_radius_m`` (sqrt(0.9) R), ``spread_m`` and ``defocus_m``.
    """
    half = sun_half_angle_rad + 2e-3 * slope_error_mrad
    spread = slant_range_m * math.tan(half)
    r_h = math.sqrt(mirror_area_m2 / math.pi)
    if focal_distance_m is None or not math.isfinite(focal_distance_m) or focal_distance_m == 0:
        defocus = r_h
    else:
        defocus = r_h * abs(slant_range_m / focal_distance_m - 1.0)
    beam = spread + defocus
    return {"beam_radius_m": beam, "spot_radius_m": math.sqrt(SPOT_FRACTION) * beam, "spread_m": spread,
            "defocus_m": defocus}


# -- one facet ---------------------------------------------------------------------------------------------
@dataclass
class SurfaceTrace:
    """One traced surface: its spot figures and flux map (W/m^2; rows are target y, columns target x)."""

    figures: dict
    flux_w_m2: np.ndarray
    off_grid_w: float
    hits: Hits


def trace_surface(points_m: np.ndarray, slopes: np.ndarray, area_m2: np.ndarray, scene: Scene,
                  settings: OpticsSettings, seed_offset: int = 0, rays_per_point: float | None = None
                  ) -> SurfaceTrace:
    """Trace one surface into *scene*; the generator is seeded with (settings.seed, seed_offset)."""
    rng = np.random.default_rng([settings.seed, seed_offset])
    hits = trace(points_m, slopes, area_m2, scene.target, settings.sun, rng,
                 rays_per_point=settings.rays_per_pixel if rays_per_point is None else rays_per_point,
                 dni_w_m2=settings.dni_w_m2, reflectivity=settings.reflectivity)
    figures = spot_figures(hits, scene.aperture, scene.target.slant_range_m, SPOT_FRACTION)
    flux, off_grid = flux_map(hits, scene.grid_half_width_m, settings.grid_cells)
    return SurfaceTrace(figures, flux, off_grid, hits)


def design_trace(design: FacetDesign, settings: OpticsSettings, scene: Scene | None = None) -> SurfaceTrace:
    """The design surface traced like a measured one (one ray per sample); the same for every facet of a type."""
    scene = scene or make_scene(design, settings)
    points, slopes, areas = design_samples(design, settings.design_points)
    return trace_surface(points, slopes, areas, scene, settings, seed_offset=1, rays_per_point=1.0)


@dataclass
class FacetOptics:
    """What :func:`facet_optics` returns: the reported figures and both traces."""

    figures: dict
    scene: Scene
    measured: SurfaceTrace
    design: SurfaceTrace
    #: Each input's standard contribution per figure (from :func:`~sofast_station.optics.uncertainty.
    #: optics_uncertainty`), when the figures carry an uncertainty.
    uncertainty_rows: dict | None = None
    #: The optical sensitivities used (:func:`~sofast_station.optics.uncertainty.optics_sensitivities`).
    sensitivities: dict | None = None


def _rounded(v):
    return None if v is None else float(v)


def facet_optics(points_m: np.ndarray, slopes: np.ndarray, camera_m: np.ndarray, design: FacetDesign,
                 settings: OpticsSettings, slope_error_mrad: float = 0.0, focal_power_per_m: float | None = None,
                 scene: Scene | None = None, design_result: SurfaceTrace | None = None,
                 surface_u=None, sensitivities: dict | None = None) -> FacetOptics:
    """Trace the measured facet and its design; the figures the station reports.

    Parameters
    ----------
    points_m, slopes : (3, N), (2, N) arrays
        Measured points and slopes of every valid pixel, boresighted facet frame.
    camera_m : (3,) array
        The camera centre in that frame (for the area each pixel stands for).
    design : FacetDesign
    settings : OpticsSettings
    slope_error_mrad : float
        The slope error the analytic estimate uses (the magnitude RMS against the fitted parabola).
    focal_power_per_m : float, optional
        The measured mean focal power (1/f_x + 1/f_y) / 2, for the analytic estimate's focal distance.
    scene, design_result : optional
        From :func:`make_scene` and :func:`design_trace` for the same design and settings (they do not
        depend on the facet, so a station computes them once per facet type).
    surface_u : SurfaceUncertainty, optional
        The measured surface's standard uncertainties; with them the figures get their expanded
        uncertainty (k = 2) as ``_U`` and ``_U_random`` siblings (:mod:`sofast_station.optics.uncertainty`).
    sensitivities : dict, optional
        From :func:`~sofast_station.optics.uncertainty.optics_sensitivities` for the same design and
        settings (computed on a station's first facet of a type and kept); None: computed for this facet
        (returned in :attr:`FacetOptics.sensitivities`).

    Returns
    -------
    FacetOptics
        ``figures``: ``intercept``, ``spot_radius_m``, ``spot_radius_mrad``, ``centroid_offset_mrad``
        {x, y, magnitude}, ``power_ratio_vs_design`` (intercepted power over the design's),
        ``analytic_spot_radius_m``, ``design`` {intercept, spot_radius_m, analytic_spot_radius_m},
        ``reflected_w``, ``intercepted_w`` and ``conditions`` (sun, DNI, reflectivity, incidence,
        slant range, aperture, rays).
    """
    scene = scene or make_scene(design, settings)
    design_result = design_result or design_trace(design, settings, scene)
    areas = pixel_areas_m2(points_m, slopes, np.asarray(camera_m, dtype=np.float64), scene.mirror_area_m2)
    rays = max(settings.rays_per_pixel, settings.min_rays / max(points_m.shape[1], 1))
    measured = trace_surface(points_m, slopes, areas, scene, settings, rays_per_point=rays)
    m, d = measured.figures, design_result.figures
    slant = scene.target.slant_range_m
    # The analytic model's focal distance: the design's, scaled by the measured focal power.
    b = None
    if focal_power_per_m is not None and focal_power_per_m > 0:
        b = scene.focus_distance_m * design.curvature_per_m / focal_power_per_m
    elif focal_power_per_m is None:
        b = scene.focus_distance_m
    analytic = analytic_spot_radius_m(slant, b, scene.mirror_area_m2, slope_error_mrad)
    analytic_design = analytic_spot_radius_m(slant, scene.focus_distance_m, scene.mirror_area_m2, 0.0)
    figures = {
        "intercept": m["intercept"],
        "spot_radius_m": _rounded(m["spot_radius_m"]),
        "spot_radius_mrad": _rounded(m["spot_radius_mrad"]),
        "centroid_offset_mrad": m["centroid_offset_mrad"],
        "power_ratio_vs_design": m["intercepted_w"] / d["intercepted_w"] if d["intercepted_w"] > 0 else None,
        "analytic_spot_radius_m": analytic["spot_radius_m"],
        "design": {"intercept": d["intercept"], "spot_radius_m": _rounded(d["spot_radius_m"]),
                   "analytic_spot_radius_m": analytic_design["spot_radius_m"]},
        "reflected_w": m["reflected_w"],
        "intercepted_w": m["intercepted_w"],
        "conditions": {"sun": _sun_dict(settings.sun), "dni_w_m2": settings.dni_w_m2,
                       "reflectivity": settings.reflectivity, "incidence_angle_deg": settings.incidence_angle_deg,
                       "slant_range_m": slant, "aperture": scene.aperture.to_dict(), "rays": measured.hits.n_rays},
    }
    rows = None
    if surface_u is not None:
        if sensitivities is None:
            sensitivities = optics_sensitivities(points_m, slopes, areas, design, settings, scene, d,
                                                 slope_error_mrad, SPOT_FRACTION)
        extra = optics_uncertainty(sensitivities, scene, measured.hits, m, design_result.hits, d, surface_u,
                                   SPOT_FRACTION)
        rows = extra.pop("uncertainty_rows")
        figures.update(extra)
    return FacetOptics(figures, scene, measured, design_result, rows, sensitivities)


def _sun_dict(sun: SunShape) -> dict:
    if sun.kind == "pillbox":
        return {"shape": "pillbox", "half_angle_mrad": sun.half_angle_mrad}
    if sun.kind == "gaussian":
        return {"shape": "gaussian", "sigma_mrad": sun.sigma_mrad}
    return {"shape": "buie", "csr": sun.csr}
