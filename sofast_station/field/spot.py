"""The spot a heliostat will throw where it stands (issue 45, item 4), and its check against a photo of it.

**The prediction** (:func:`predict_spot`). The factory's record of the heliostat gives each facet's measured
figures: its canting error with U, its focal powers (curvature) and its slope errors left after the
parabola's fit. Each facet is modelled as its design surface with the measured curvature, turned by its
measured canting error (``R_i R_y(ry) R_x(rx)`` in its own frame, as :mod:`sofast_station.optics.heliostat`
turns it), its slopes scattered by the measured residual RMS per axis (independent normal draws: a statistical
stand-in for the surface the dump keeps). The heliostat stands at its field position tracking perfectly (its
optical axis the bisector of the sun and the aim point, :func:`~.sun.commanded_normal`); the sun's rays
(:class:`~sofast_station.optics.sun.SunShape`, from pvlib's position) are traced by the line's own tracer
(:func:`~sofast_station.optics.trace.trace`) onto the **target plane**: the tower's calibration target (or the
receiver's aperture), a plane through the aim point with its own normal. Its axes: ``u_x`` level and to the
right seen from the field (``u_x = z x n / |z x n|``, n the plane's normal towards the field), ``u_y = n x
u_x`` (up for a vertical target); metres from the aim point.

**The figures of a spot** (:func:`map_figures`): of any irradiance map on the plane (the predicted flux map or
the photo's pixels), its centroid (x, y, metres from the aim point) and its **spot radius**: the radius about
the centroid holding 90 % of the map's power (the optics' ``SPOT_FRACTION``), computed alike for both so
that their difference is the heliostat's, not the method's.

**U.** The prediction's U (k = 2): its figures over draws of every facet's canting within its U (each axis a
normal draw of U/2, the sun samples and slope draws held), with the tracer's own sampling noise (the spread of
the figures over the slope and sun draws) added in quadrature. The photo's: its stated pixel scale's and aim
pixel's uncertainty, and the spread of the figures over background thresholds. A difference is **flagged**
when it exceeds the two U combined (``sqrt(U_pred^2 + U_photo^2)``). The centroid's difference holds the
heliostat's tracking error on the day as well as its facets': the spot radius is the factory record's check.

Pure numpy (and the optics' tracer); the photo comes in as an array with its scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..ensemble import EnsembleDesign
from ..errors import CaptureError, ConfigError
from ..optics.facet import SPOT_FRACTION, design_samples
from ..optics.sun import SunShape
from ..optics.trace import Target, flux_map, trace
from .geometry import azimuth_elevation, heliostat_rotation
from .sun import commanded_normal

#: Draws of the canting's Monte Carlo.
DRAWS = 12


@dataclass(frozen=True)
class FacetModel:
    """One facet as the factory measured it.

    Attributes
    ----------
    label : str
    canting_mrad : (2,) array
        Its canting error about its x and y axes, mrad.
    canting_u_mrad : (2,) array
        Its expanded uncertainty (k = 2), mrad (zeros when the record states none).
    curvature_per_m : (2,) array or None
        Its measured focal powers 1/f_x, 1/f_y (1/m); None: the design's.
    slope_sigma_mrad : (2,) array
        The residual slope error's RMS per axis, mrad.
    """

    label: str
    canting_mrad: np.ndarray
    canting_u_mrad: np.ndarray
    curvature_per_m: np.ndarray | None = None
    slope_sigma_mrad: np.ndarray = field(default_factory=lambda: np.zeros(2))


def _pair(d, what: str) -> np.ndarray | None:
    if d is None:
        return None
    try:
        v = np.array([float(d["x"]), float(d["y"])])
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"factory record: {what} must hold numbers x and y, got {d!r}") from None
    return v if np.all(np.isfinite(v)) else None


def facet_models(record: dict) -> list[FacetModel]:
    """Each measured facet of a heliostat's record (``inspect --json``) as a :class:`FacetModel`; a facet the
    line did not measure is left out (its spot is then missing from the prediction, as from the heliostat's
    figures). ConfigError when no facet has a canting."""
    out = []
    for f in record.get("facets", []):
        c = _pair(f.get("canting_mrad"), f"facet {f.get('label')} canting_mrad")
        if c is None:
            continue
        u = _pair(f.get("canting_mrad_U"), f"facet {f.get('label')} canting_mrad_U")
        kx, ky = f.get("curvature_x_per_m"), f.get("curvature_y_per_m")
        curv = (np.array([float(kx), float(ky)]) if isinstance(kx, (int, float)) and isinstance(ky, (int, float))
                else None)
        rms = (f.get("slope_rms_mrad") or {}).get("parabola") or {}
        if isinstance(rms.get("x"), (int, float)) and isinstance(rms.get("y"), (int, float)):
            sigma = np.array([float(rms["x"]), float(rms["y"])])
        elif isinstance(rms.get("magnitude"), (int, float)):
            sigma = np.full(2, float(rms["magnitude"]) / math.sqrt(2.0))
        else:
            sigma = np.zeros(2)
        out.append(FacetModel(str(f["label"]), c, np.zeros(2) if u is None else u, curv, sigma))
    if not out:
        raise ConfigError("the factory record has no measured facet with a canting: no spot to predict (is it a "
                          "heliostat's record of 'sofast-station inspect --json'?)")
    return out


@dataclass(frozen=True)
class TargetPlane:
    """The target on the tower: its centre (the aim point) and unit normal towards the field, field frame."""

    centre_m: np.ndarray
    normal: np.ndarray

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(u_x, u_y): level and to the right seen from the field, and ``n x u_x`` (module docstring)."""
        n = np.asarray(self.normal, dtype=np.float64)
        x = np.cross([0.0, 0.0, 1.0], n)
        if np.linalg.norm(x) < 1e-9:
            raise ConfigError("the target plane faces straight up or down: give it a normal with a level part")
        x = x / np.linalg.norm(x)
        return x, np.cross(n, x)


def facing_target(aim_m, position_m, azimuth_deg: float | None = None) -> TargetPlane:
    """A vertical target at *aim_m* facing azimuth *azimuth_deg* (clockwise from north), or, without one,
    facing the heliostat at *position_m* (level)."""
    aim = np.asarray(aim_m, dtype=np.float64)
    if azimuth_deg is None:
        d = np.asarray(position_m, dtype=np.float64) - aim
        d[2] = 0.0
        if np.linalg.norm(d) < 1e-6:
            raise ConfigError("the heliostat stands under the aim point: give the target's facing azimuth")
        n = d / np.linalg.norm(d)
    else:
        a = math.radians(float(azimuth_deg))
        n = np.array([math.sin(a), math.cos(a), 0.0])
    return TargetPlane(aim, n)


def _turn(rx_mrad: float, ry_mrad: float) -> np.ndarray:
    """R_y(ry) R_x(rx), the canting error's turn in the facet's frame (docs/conventions.md#canting)."""
    a, b = 1e-3 * rx_mrad, 1e-3 * ry_mrad
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    return np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]]) @ np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa],
                                                                                  [0.0, sa, ca]])


def _in_frame(points, slopes, rotation, translation):
    """Points and slopes of a facet frame in the heliostat frame."""
    p = rotation @ points + np.asarray(translation, dtype=np.float64)[:, None]
    n = rotation @ np.stack([-slopes[0], -slopes[1], np.ones(slopes.shape[1])])
    return p, np.stack([-n[0] / n[2], -n[1] / n[2]])


def _facet_samples(ensemble: EnsembleDesign, models: list, per_facet: int, rng: np.random.Generator) -> list:
    """(label, design rotation, position, points, slopes with the measured curvature and scatter, areas)."""
    by_label = {f.label: f for f in ensemble.facets}
    out = []
    for m in models:
        if m.label not in by_label:
            raise ConfigError(f"the factory record's facet {m.label} is not in the heliostat's design "
                              f"{ensemble.name!r} ({', '.join(by_label)})")
        f = by_label[m.label]
        pts, slopes, areas = design_samples(f.design, per_facet)
        slopes = slopes.copy()
        if m.curvature_per_m is not None:
            # the design is z = kappa_d (x^2 + y^2) / 4: its slopes kappa x / 2; the measured powers replace it
            slopes[0] += 0.5 * (m.curvature_per_m[0] - f.design.curvature_per_m) * pts[0]
            slopes[1] += 0.5 * (m.curvature_per_m[1] - f.design.curvature_per_m) * pts[1]
        if np.any(m.slope_sigma_mrad > 0):
            slopes += 1e-3 * m.slope_sigma_mrad[:, None] * rng.standard_normal(slopes.shape)
        out.append((m, f.rotation, f.position_m, pts, slopes, areas))
    return out


@dataclass(frozen=True)
class SpotScene:
    """Where the heliostat stands and where its beam goes.

    Attributes
    ----------
    position_m : (3,) array
        The heliostat's pivot, field frame, metres.
    pivot_offset_m : float
        Its mirrors' middle in front of the pivot along its normal.
    plane : TargetPlane
    sun : (3,) unit vector
        Towards the sun, field frame.
    """

    position_m: np.ndarray
    pivot_offset_m: float
    plane: TargetPlane
    sun: np.ndarray

    def frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(R_h, origin): the tracking heliostat's frame in the field (heliostat -> field) and its origin."""
        n = commanded_normal(self.sun, self.position_m, self.plane.centre_m)
        r = heliostat_rotation(*azimuth_elevation(n))
        return r, np.asarray(self.position_m, dtype=np.float64) + self.pivot_offset_m * r[:, 2]

    def target(self) -> Target:
        """The target plane in the heliostat frame, as the tracer takes it (its plane normal in the place of the
        central reflected ray: the tracer meets the plane normal to it through the aim point)."""
        r, origin = self.frame()
        ux, uy = self.plane.axes
        aim = r.T @ (self.plane.centre_m - origin)
        s = np.asarray(self.sun, dtype=np.float64)
        s = s / np.linalg.norm(s)
        u_sun = r.T @ (-s)
        return Target(u_sun=u_sun, centre_m=np.zeros(3), u_reflected=r.T @ np.asarray(self.plane.normal, float),
                      aim_m=aim, u_x=r.T @ ux, u_y=r.T @ uy, slant_range_m=float(np.linalg.norm(aim)),
                      incidence_angle_rad=float(math.acos(min(1.0, max(-1.0, -u_sun[2])))))


def map_figures(image: np.ndarray, cell_m: float, x0_m: float, y0_m: float, fraction: float = SPOT_FRACTION,
                clip: bool = True) -> dict:
    """Centroid and spot radius of an irradiance map on the target plane.

    Parameters
    ----------
    image : (rows, columns) array
        Irradiance (any unit) per cell; row j, column i centred at (x0 + (i + 0.5) w, y0 + (j + 0.5) w) with
        w = *cell_m*, metres from the aim point along u_x, u_y.
    cell_m, x0_m, y0_m : float
    fraction : float
        The share of the power the spot radius holds.
    clip : bool
        Negative values count as none (a flux map); False: they count (a photo's zero-mean noise about its
        background, which clipping would turn into power).

    Returns
    -------
    dict
        ``centroid_m`` {x, y}, ``spot_radius_m`` (linear between the cells' radii), ``power`` (the map's sum
        times the cell's area).
    """
    w = np.asarray(image, dtype=np.float64)
    w = np.clip(w, 0.0, None) if clip else w
    total = float(w.sum())
    if not total > 0:
        raise CaptureError("the map holds no power: no spot on the target")
    rows, cols = w.shape
    x = x0_m + (np.arange(cols) + 0.5) * cell_m
    y = y0_m + (np.arange(rows) + 0.5) * cell_m
    cx = float((w.sum(axis=0) * x).sum() / total)
    cy = float((w.sum(axis=1) * y).sum() / total)
    r = np.hypot(x[None, :] - cx, y[:, None] - cy).ravel()
    order = np.argsort(r, kind="stable")
    cum = np.maximum.accumulate(np.cumsum(w.ravel()[order]) / total)
    k = int(np.searchsorted(cum, fraction))
    k = min(k, r.size - 1)
    lo_r, lo_c = (r[order[k - 1]], cum[k - 1]) if k > 0 else (0.0, 0.0)
    hi_r, hi_c = r[order[k]], cum[k]
    radius = lo_r + (fraction - lo_c) / (hi_c - lo_c) * (hi_r - lo_r) if hi_c > lo_c else hi_r
    return {"centroid_m": {"x": cx, "y": cy}, "spot_radius_m": float(radius), "power": total * cell_m * cell_m}


def _trace_once(samples, turns, target, sun, rays_per_point, dni, reflectivity, seed):
    """All facets' hits on the plane, each facet turned by its canting error plus *turns* (mrad)."""
    xs, ys, ps = [], [], []
    reflected = 0.0
    for k, (m, rot, pos, pts, slopes, areas) in enumerate(samples):
        dx, dy = m.canting_mrad + turns[k]
        p, s = _in_frame(pts, slopes, rot @ _turn(dx, dy), pos)
        hits = trace(p, s, areas, target, sun, np.random.default_rng([seed, k]), rays_per_point=rays_per_point,
                     dni_w_m2=dni, reflectivity=reflectivity)
        xs.append(hits.x_m)
        ys.append(hits.y_m)
        ps.append(hits.power_w)
        reflected += hits.reflected_w
    return np.concatenate(xs), np.concatenate(ys), np.concatenate(ps), reflected


def predict_spot(models: list, ensemble: EnsembleDesign, scene: SpotScene, *, sun_shape: SunShape = SunShape(),
                 dni_w_m2: float = 900.0, reflectivity: float = 0.94, points_per_facet: int = 4000,
                 rays_per_point: float = 4.0, cells: int = 121, half_width_m: float | None = None,
                 draws: int = DRAWS, seed: int = 1) -> dict:
    """The heliostat's predicted flux on the target plane, and its figures with U (module docstring).

    Parameters
    ----------
    models : list of FacetModel
    ensemble : EnsembleDesign
        The heliostat's design (its facets' surfaces and places).
    scene : SpotScene
    sun_shape, dni_w_m2, reflectivity
        The sunlight (W/m^2) and the mirrors' reflectivity.
    points_per_facet, rays_per_point : int, float
        Samples of each facet and rays from each.
    cells : int
        Cells per side of the flux map.
    half_width_m : float, optional
        The map's half width, metres; default 3 sun-image radii at the slant range plus the heliostat's size.
    draws : int
        Draws of the canting's Monte Carlo (0: no U from the canting).
    seed : int

    Returns
    -------
    dict
        ``flux_w_m2`` (cells, cells) array (row j: y, column i: x), ``cell_m``, ``origin_m`` (x0, y0 of the
        map's corner), ``figures``: ``centroid_m`` {x, y} with ``centroid_m_U``, ``spot_radius_m`` with
        ``spot_radius_m_U``, ``on_target_w``, ``reflected_w``, ``slant_range_m``, ``incidence_angle_deg``,
        ``facets`` (labels traced).
    """
    target = scene.target()
    slant = target.slant_range_m
    if target.u_sun[2] >= 0:
        raise ConfigError("the sun is behind the heliostat's mirrors at this hour: no spot")
    if half_width_m is None:
        size = float(np.max(np.abs([f.position_m[:2] for f in ensemble.facets])))
        half_width_m = 3.0 * slant * 4.65e-3 + 2.0 * size + 0.5
    rng = np.random.default_rng([seed, 11])
    samples = _facet_samples(ensemble, models, points_per_facet, rng)
    zero = np.zeros((len(samples), 2))
    x, y, p, reflected = _trace_once(samples, zero, target, sun_shape, rays_per_point, dni_w_m2, reflectivity, seed)
    cells_m = 2.0 * half_width_m / cells

    def figures(xx, yy, pp) -> dict:
        fmap, _ = flux_map(_Hits(xx, yy, pp), half_width_m, cells)
        return map_figures(fmap, cells_m, -half_width_m, -half_width_m)

    fmap, outside = flux_map(_Hits(x, y, p), half_width_m, cells)
    base = map_figures(fmap, cells_m, -half_width_m, -half_width_m)
    # the tracer's own noise: the same facets with other sun and slope draws
    noise = []
    for k in range(3):
        s2 = _facet_samples(ensemble, models, points_per_facet, np.random.default_rng([seed, 21, k]))
        noise.append(_values(figures(*_trace_once(s2, zero, target, sun_shape, rays_per_point, dni_w_m2,
                                                  reflectivity, seed + 100 + k)[:3])))
    u_noise = np.std(np.array(noise), axis=0, ddof=1)
    u_cant = np.zeros(3)
    if draws:
        drng = np.random.default_rng([seed, 31])
        vals = []
        base_v = _values(base)
        for _ in range(draws):
            turns = np.array([0.5 * m.canting_u_mrad * drng.standard_normal(2) for m in models])
            vals.append(_values(figures(*_trace_once(samples, turns, target, sun_shape, rays_per_point, dni_w_m2,
                                                     reflectivity, seed)[:3])) - base_v)
        u_cant = np.sqrt(np.mean(np.square(vals), axis=0))
    u = 2.0 * np.hypot(u_noise, u_cant)
    fig = {"centroid_m": base["centroid_m"], "centroid_m_U": {"x": float(u[0]), "y": float(u[1])},
           "spot_radius_m": base["spot_radius_m"], "spot_radius_m_U": float(u[2]),
           "on_target_w": float(p.sum()) - outside, "reflected_w": reflected, "slant_range_m": slant,
           "incidence_angle_deg": math.degrees(target.incidence_angle_rad), "facets": [m.label for m in models],
           "u_parts": {name: {"x": 2 * float(v[0]), "y": 2 * float(v[1]), "radius": 2 * float(v[2])}
                       for name, v in (("canting", u_cant), ("sampling", u_noise))}}
    return {"flux_w_m2": fmap, "cell_m": cells_m, "origin_m": (-half_width_m, -half_width_m), "figures": fig}


@dataclass
class _Hits:
    """The tracer's hits as :func:`~sofast_station.optics.trace.flux_map` reads them."""

    x_m: np.ndarray
    y_m: np.ndarray
    power_w: np.ndarray


def _values(fig: dict) -> np.ndarray:
    return np.array([fig["centroid_m"]["x"], fig["centroid_m"]["y"], fig["spot_radius_m"]])


@dataclass(frozen=True)
class PhotoScale:
    """How a BCS photo maps onto the target plane (a rectified view: columns along u_x, rows down along -u_y).

    Attributes
    ----------
    pixel_m : float
        Metres of the target per pixel.
    aim_px : (2,) array
        The aim point's pixel (column, row; pixel centres at whole numbers).
    pixel_m_rel_u : float
        The scale's relative standard uncertainty.
    aim_px_u : float
        The aim pixel's standard uncertainty per axis, pixels.
    """

    pixel_m: float
    aim_px: np.ndarray
    pixel_m_rel_u: float = 0.005
    aim_px_u: float = 0.5


#: Thresholds (times the noise) of the spot's region in a photo; the spread of its figures over them enters its U.
PHOTO_THRESHOLDS = (2.0, 3.0, 5.0)


def photo_figures(image: np.ndarray, scale: PhotoScale, dark: np.ndarray | None = None) -> dict:
    """The spot's figures in a photo of the lit target (the patent's BCS image), with U.

    The unlit target's level is the median of the photo's border (a frame 4 % of its size wide) or *dark* (the
    same view without the beam), its noise the border's median absolute deviation; the spot's region is where
    a 5 x 5 mean stands above that level by each of :data:`PHOTO_THRESHOLDS` times its noise, joined to the
    brightest and widened by 3 pixels, and :func:`map_figures` is taken of the pixels there less the level
    (noise and all: clipping it would add power).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        The photo (8 or 16 bit, or float); colour is averaged.
    scale : PhotoScale
    dark : array, optional
        The target without the beam, same view and exposure.

    Returns
    -------
    dict
        ``centroid_m`` {x, y} with ``centroid_m_U``, ``spot_radius_m`` with ``spot_radius_m_U``, ``background``,
        ``noise``, ``peak_counts`` (the spot's brightest pixel).

    Raises
    ------
    CaptureError
        No spot above the noise, the spot touching the photo's edge (cut off), or overexposed.
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = img.mean(axis=2)
    img = img.astype(np.float64)
    h, w = img.shape
    b = max(2, int(round(0.04 * min(h, w))))
    if dark is not None:
        d = np.asarray(dark, dtype=np.float64)
        d = d.mean(axis=2) if d.ndim == 3 else d
        if d.shape != img.shape:
            raise CaptureError(f"the dark photo is {d.shape[1]} x {d.shape[0]}, the BCS photo {w} x {h}: the same "
                               "view is needed")
        img = img - d
    border = np.concatenate([img[:b].ravel(), img[-b:].ravel(), img[:, :b].ravel(), img[:, -b:].ravel()])
    level = float(np.median(border))
    noise = max(1.4826 * float(np.median(np.abs(border - level))), 1e-9)
    signal = img - level
    if float(signal.max()) < 20.0 * noise:
        raise CaptureError(f"no spot found in the BCS photo: its brightest pixel stands {signal.max() / noise:.1f} "
                           "times the noise above the target (is the heliostat on the target, the exposure right?)")
    spot = _spot_region(signal, PHOTO_THRESHOLDS[0] * noise)
    edge = spot[:b].any() or spot[-b:].any() or spot[:, :b].any() or spot[:, -b:].any()
    if edge:
        raise CaptureError("the spot is cut off: it reaches the BCS photo's edge; frame the whole target")
    raw = np.asarray(image)
    raw = raw.max(axis=2) if raw.ndim == 3 else raw
    refuse_clipped(image, spot, "the BCS photo", "of the spot", "take it with a shorter exposure or a denser filter")
    p = float(scale.pixel_m)
    x0 = -(float(scale.aim_px[0]) + 0.5) * p
    y0 = -(h - 0.5 - float(scale.aim_px[1])) * p
    values = []
    smooth = ndimage.uniform_filter(signal, 5)
    for k in PHOTO_THRESHOLDS:
        # the spot where its 5 x 5 mean stands k times that mean's noise (the pixel's / 5) above the target,
        # widened by 3 pixels: its tails, with the noise's zero mean, are kept whole
        region = ndimage.binary_dilation(_spot_region(smooth, 0.2 * k * noise), iterations=3)
        kept = np.where(region, signal, 0.0)[::-1]
        values.append(_values(map_figures(kept, p, x0, y0, clip=False)))
    v = np.array(values)
    spread = np.std(v, axis=0, ddof=1)
    c = v[0]
    u_x = math.sqrt(spread[0] ** 2 + (scale.pixel_m_rel_u * c[0]) ** 2 + (scale.aim_px_u * p) ** 2)
    u_y = math.sqrt(spread[1] ** 2 + (scale.pixel_m_rel_u * c[1]) ** 2 + (scale.aim_px_u * p) ** 2)
    u_r = math.sqrt(spread[2] ** 2 + (scale.pixel_m_rel_u * c[2]) ** 2)
    return {"centroid_m": {"x": float(c[0]), "y": float(c[1])}, "centroid_m_U": {"x": 2 * u_x, "y": 2 * u_y},
            "spot_radius_m": float(c[2]), "spot_radius_m_U": 2 * u_r, "background": level, "noise": noise,
            "peak_counts": float(raw[spot].max())}


def refuse_clipped(image, region: np.ndarray, what: str, part: str, remedy: str) -> None:
    """CaptureError when more than 5 pixels (and 0.2 %) of *region* share the image's top value there: clipped
    (a 12-bit camera's top is 4095 in a 16-bit file, so the plateau is looked for, not the container's full
    scale; a lit source's noise leaves its top to a few pixels). Float images are not checked."""
    raw = np.asarray(image)
    if not np.issubdtype(raw.dtype, np.integer) or not region.any():
        return
    raw = raw.max(axis=2) if raw.ndim == 3 else raw
    top = raw[region].max()
    clipped = int(np.count_nonzero(raw[region] == top))
    if clipped > max(5, 0.002 * int(region.sum())):
        raise CaptureError(f"{what} is overexposed: {clipped} pixels {part} share its top value {int(top)} (clipped); "
                           f"{remedy}")


def _spot_region(signal: np.ndarray, threshold: float) -> np.ndarray:
    """The pixels above *threshold* joined to the brightest (after a 3 x 3 mean, so that a noise pixel is not
    it): the spot, without the noise's stray pixels elsewhere on the target."""
    labels, _ = ndimage.label(signal > threshold)
    top = np.unravel_index(int(np.argmax(ndimage.uniform_filter(signal, 3))), signal.shape)
    if labels[top] == 0:
        return np.zeros(signal.shape, dtype=bool)
    return labels == labels[top]


def compare_spots(predicted: dict, photographed: dict) -> dict:
    """The photographed spot against the predicted: each difference (photo less prediction), its combined U
    (``sqrt(U_pred^2 + U_photo^2)``) and whether it lies beyond it (``flagged``)."""
    out = {}
    for key, get in (("centroid_x_m", lambda f: (f["centroid_m"]["x"], f["centroid_m_U"]["x"])),
                     ("centroid_y_m", lambda f: (f["centroid_m"]["y"], f["centroid_m_U"]["y"])),
                     ("spot_radius_m", lambda f: (f["spot_radius_m"], f["spot_radius_m_U"]))):
        (a, ua), (b, ub) = get(predicted), get(photographed)
        u = math.hypot(ua, ub)
        out[key] = {"predicted": a, "photographed": b, "difference": b - a, "U": u, "flagged": abs(b - a) > u}
    out["flagged"] = [k for k, v in out.items() if v["flagged"]]
    return out


def photo_extent(shape: tuple, scale: PhotoScale) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the target plane's stretch a photo of *shape* (rows, columns) covers, metres."""
    h, w = shape[:2]
    p = float(scale.pixel_m)
    ax, ay = float(scale.aim_px[0]), float(scale.aim_px[1])
    return -(ax + 0.5) * p, (w - 0.5 - ax) * p, -(h - 0.5 - ay) * p, (ay + 0.5) * p
