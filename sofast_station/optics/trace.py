"""Ray trace of a facet in sunlight onto a target plane, and the figures of the spot.

Geometry (facet frame, metres; docs/conventions.md, "Optics"):

- The sun's central ray travels along ``-(sin i, 0, cos i)``: it comes from the facet frame's +z side,
  tilted by the incidence angle *i* towards +x, so ``i = 0`` is the sun on the design's optical axis
  (for a gore, the dish's axis).
- The facet's centre ``c`` is the outline's area centroid on the design surface; the design normal there
  reflects the central ray into the *central reflected ray* ``r_c``.
- The target plane is normal to ``r_c`` at the slant range *L* from ``c``; the aim point is ``c + L r_c``.
  The default *L* is the design's distance from ``c`` to its focus, ``f + z(c)``: the focal length for a
  facet centred on the paraboloid's vertex.
- Target-plane coordinates: ``u_x`` is the facet's x axis made perpendicular to ``r_c``; ``u_y = r_c x u_x``.

Each measured point stands for a patch of surface; its reflected power is ``DNI rho cos(theta_i) dA``.
Each ray leaves the point in the direction the point's normal reflects a direction drawn from the sun
shape, and carries its share of the point's power to where it meets the target plane.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .sun import SunShape


@dataclass(frozen=True)
class Aperture:
    """The receiver's aperture on the target plane, centred on the aim point.

    ``shape`` is ``"circle"`` (``radius_m``) or ``"rectangle"`` (``width_m`` along the target's x axis,
    ``height_m`` along its y axis).
    """

    shape: str = "circle"
    radius_m: float = 0.0
    width_m: float = 0.0
    height_m: float = 0.0

    def __post_init__(self):
        if self.shape == "circle":
            if not (np.isfinite(self.radius_m) and self.radius_m > 0):
                raise ValueError(f"a circular aperture needs radius_m > 0 (metres), got {self.radius_m}")
        elif self.shape == "rectangle":
            for key in ("width_m", "height_m"):
                v = getattr(self, key)
                if not (np.isfinite(v) and v > 0):
                    raise ValueError(f"a rectangular aperture needs {key} > 0 (metres), got {v}")
        else:
            raise ValueError(f"aperture shape must be \"circle\" or \"rectangle\", got {self.shape!r}")

    def contains(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Which target-plane points (metres from the aim point) fall inside."""
        if self.shape == "circle":
            return x_m * x_m + y_m * y_m <= self.radius_m ** 2
        return (np.abs(x_m) <= 0.5 * self.width_m) & (np.abs(y_m) <= 0.5 * self.height_m)

    @property
    def half_size_m(self) -> float:
        """Half the aperture's largest extent along either target axis, metres."""
        return self.radius_m if self.shape == "circle" else 0.5 * max(self.width_m, self.height_m)

    def to_dict(self) -> dict:
        if self.shape == "circle":
            return {"shape": "circle", "radius_m": self.radius_m}
        return {"shape": "rectangle", "width_m": self.width_m, "height_m": self.height_m}


@dataclass(frozen=True)
class Target:
    """Where the beam goes: the central rays and the target plane (facet frame, metres; unit vectors).

    Attributes
    ----------
    u_sun : (3,) array
        Travel direction of the sun's central ray.
    centre_m : (3,) array
        The facet's centre c on the design surface.
    u_reflected : (3,) array
        The central reflected ray r_c, which is also the target plane's normal.
    aim_m : (3,) array
        The aim point c + L r_c.
    u_x, u_y : (3,) arrays
        The target plane's axes.
    slant_range_m : float
        L.
    incidence_angle_rad : float
    """

    u_sun: np.ndarray
    centre_m: np.ndarray
    u_reflected: np.ndarray
    aim_m: np.ndarray
    u_x: np.ndarray
    u_y: np.ndarray
    slant_range_m: float
    incidence_angle_rad: float


def make_target(centre_m: np.ndarray, normal: np.ndarray, incidence_angle_rad: float,
                slant_range_m: float) -> Target:
    """The target for a facet whose design has unit *normal* at its centre *centre_m* (see module docstring)."""
    if not (np.isfinite(slant_range_m) and slant_range_m > 0):
        raise ValueError(f"slant range must be a positive number of metres, got {slant_range_m}")
    if not (0.0 <= incidence_angle_rad < 0.5 * np.pi):
        raise ValueError(f"incidence angle must lie in [0, 90) degrees, got {np.degrees(incidence_angle_rad)}")
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    u_sun = -np.array([np.sin(incidence_angle_rad), 0.0, np.cos(incidence_angle_rad)])
    r = u_sun - 2.0 * np.dot(u_sun, n) * n
    if r[2] <= 0:
        raise ValueError("the sun lies behind the facet's centre at this incidence angle")
    x = np.array([1.0, 0.0, 0.0]) - r[0] * r
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - r[1] * r
    u_x = x / np.linalg.norm(x)
    u_y = np.cross(r, u_x)
    centre = np.asarray(centre_m, dtype=np.float64)
    return Target(u_sun=u_sun, centre_m=centre, u_reflected=r, aim_m=centre + slant_range_m * r, u_x=u_x, u_y=u_y,
                  slant_range_m=float(slant_range_m), incidence_angle_rad=float(incidence_angle_rad))


@dataclass
class Hits:
    """Traced rays on the target plane.

    Attributes
    ----------
    x_m, y_m : (M,) arrays
        Where each ray that reaches the plane meets it, metres from the aim point along u_x, u_y.
    power_w : (M,) array
        Power each of those rays carries, watts.
    reflected_w : float
        Power the facet reflects (rays that never reach the plane included), watts.
    incident_w : float
        Power the sun delivers onto the traced surface, DNI x sum(cos(theta_i) dA), watts.
    n_rays : int
        Rays traced.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    power_w: np.ndarray
    reflected_w: float
    incident_w: float
    n_rays: int


def _perpendicular_pair(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to *u* and to each other; for u in the x-z plane, b = y."""
    b = np.array([0.0, 1.0, 0.0]) if abs(u[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    b = b - np.dot(b, u) * u
    b /= np.linalg.norm(b)
    return np.cross(b, u), b


def _combine(const: float, *terms) -> np.ndarray:
    """const + sum(c * array) over the (c, array) terms, skipping zero coefficients (in the arrays' type)."""
    out = None
    for c, arr in terms:
        if c == 0.0:
            continue
        term = arr if c == 1.0 else (-arr if c == -1.0 else arr.dtype.type(c) * arr)
        out = term if out is None else out + term
    if out is None:
        return np.full(terms[0][1].shape, const, dtype=terms[0][1].dtype)
    return out + out.dtype.type(const) if const != 0.0 else out


def trace(points_m: np.ndarray, slopes: np.ndarray, area_m2: np.ndarray, target: Target, sun: SunShape,
          rng: np.random.Generator, rays_per_point: float = 1.0, dni_w_m2: float = 1000.0,
          reflectivity: float = 0.94) -> Hits:
    """Reflect sunlight off the surface samples onto the target plane.

    Parameters
    ----------
    points_m : (3, N) array
        Surface points, facet frame, metres.
    slopes : (2, N) array
        Surface slopes (dz/dx, dz/dy) there; the unit normal is (-s_x, -s_y, 1) / sqrt(1 + s_x^2 + s_y^2).
    area_m2 : (N,) array
        Surface area each point stands for, square metres.
    target : Target
    sun : SunShape
    rng : numpy.random.Generator
        Source of the sun-shape samples; the same state gives the same rays.
    rays_per_point : float
        Rays per point on average (> 0): 1 traces one ray from every point, 0.5 every second point,
        4 four rays from each; the points' power is shared by their rays.
    dni_w_m2 : float
        Direct normal irradiance, W/m^2.
    reflectivity : float
        Specular reflectivity, 0 to 1.

    Returns
    -------
    Hits
    """
    n_points = points_m.shape[1]
    if slopes.shape != (2, n_points) or area_m2.shape != (n_points,):
        raise ValueError(f"points {points_m.shape}, slopes {slopes.shape} and areas {area_m2.shape} disagree")
    if not rays_per_point > 0:
        raise ValueError(f"rays per point must be positive, got {rays_per_point}")
    if not 0.0 <= reflectivity <= 1.0:
        raise ValueError(f"reflectivity must lie between 0 and 1, got {reflectivity}")
    # Per-ray arithmetic in float32 (positions to micrometres at 100 m, directions to 0.1 urad): it halves
    # the memory traffic, which is what a trace of half a million rays waits for. Sums stay float64.
    f32 = np.float32
    s_x, s_y = slopes.astype(f32)
    mm = 1.0 + s_x * s_x + s_y * s_y                  # |m|^2 of the unnormalised normal m = (-s_x, -s_y, 1)
    d = target.u_sun
    cos_i = (-d[2] + d[0] * s_x + d[1] * s_y) / np.sqrt(mm)
    np.maximum(cos_i, 0.0, out=cos_i)
    power = (dni_w_m2 * reflectivity) * cos_i.astype(np.float64) * area_m2      # per point, W
    incident = float(dni_w_m2 * np.sum(cos_i.astype(np.float64) * area_m2))
    reflected = float(power.sum())

    # Points in the target frame, relative to the aim point: q = P - aim along u_x, u_y and the plane normal.
    # (Element-wise arithmetic and numpy's own sums only, no BLAS: the bits must not depend on its threads,
    # so that a dump re-analysed anywhere reproduces the archived figures.)
    rot = np.stack([target.u_x, target.u_y, target.u_reflected])
    q = points_m - target.aim_m[:, None]
    q_x, q_y, q_n = (_combine(0.0, *((rot[j, c], q[c]) for c in range(3))).astype(f32) for j in range(3))

    n_rays = max(1, int(round(rays_per_point * n_points)))
    if n_rays == n_points:
        per_ray = power
    else:
        pick = (np.arange(n_rays, dtype=np.int64) * n_points) // n_rays   # spread evenly over the points
        counts = np.bincount(pick, minlength=n_points)
        s_x, s_y, mm, q_x, q_y, q_n = (np.take(c, pick) for c in (s_x, s_y, mm, q_x, q_y, q_n))
        per_ray = np.take(power / np.maximum(counts, 1), pick)

    # Sun directions about the central ray d: i = d + tan(theta) (cos(phi) a + sin(phi) b), unnormalised
    # (reflection is linear and the plane intersection a ratio, so the length does not matter).
    theta, phi = sun.sample(n_rays, rng)
    tan_t = np.tan(theta).astype(f32)
    phi = phi.astype(f32)
    t_a, t_b = tan_t * np.cos(phi), tan_t * np.sin(phi)
    a, b = _perpendicular_pair(d)
    i_x = _combine(d[0], (a[0], t_a), (b[0], t_b))
    i_y = _combine(d[1], (a[1], t_a), (b[1], t_b))
    i_z = _combine(d[2], (a[2], t_a), (b[2], t_b))

    # Law of reflection: r = i - 2 (i.m) m / |m|^2.
    k = (2.0 * (i_z - i_x * s_x - i_y * s_y)) / mm
    r_x = i_x + k * s_x
    r_y = i_y + k * s_y
    r_z = i_z - k
    # The reflected direction in the target frame, then the plane q_n + t r_n = 0.
    r_u = [_combine(0.0, (rot[j, 0], r_x), (rot[j, 1], r_y), (rot[j, 2], r_z)) for j in range(3)]
    forward = r_u[2] * q_n < 0.0                      # the plane lies ahead of the ray
    t = -q_n / np.where(forward, r_u[2], f32(1.0))
    x = q_x + t * r_u[0]
    y = q_y + t * r_u[1]
    if not np.all(forward):
        x, y, per_ray = x[forward], y[forward], per_ray[forward]
    return Hits(x_m=x, y_m=y, power_w=per_ray, reflected_w=reflected, incident_w=incident, n_rays=n_rays)


def flux_map(hits: Hits, half_width_m: float, cells: int) -> tuple[np.ndarray, float]:
    """Irradiance on a square grid about the aim point, W/m^2, and the power that fell outside it, W.

    Row j, column i of the (cells, cells) map covers y in [-h + j w, -h + (j + 1) w) and x likewise,
    with h the half-width and w = 2 h / cells.
    """
    if not (half_width_m > 0 and cells >= 2):
        raise ValueError(f"flux grid needs half_width_m > 0 and at least 2 cells, got {half_width_m}, {cells}")
    w = 2.0 * half_width_m / cells
    # Cell indices clipped into a one-cell border around the grid, which collects what falls outside.
    edge = cells + 2
    i = np.clip(np.floor((hits.x_m + np.float32(half_width_m)) * np.float32(1.0 / w)), -1, cells).astype(np.int32)
    j = np.clip(np.floor((hits.y_m + np.float32(half_width_m)) * np.float32(1.0 / w)), -1, cells).astype(np.int32)
    flat = (j + 1) * edge + (i + 1)
    power = np.bincount(flat, weights=hits.power_w, minlength=edge * edge).reshape(edge, edge)[1:-1, 1:-1]
    outside = float(hits.power_w.sum() - power.sum())
    return power.reshape(cells, cells) / (w * w), outside


def spot_figures(hits: Hits, aperture: Aperture, slant_range_m: float, fraction: float = 0.9) -> dict:
    """The spot's figures (docs/conventions.md, "Optics").

    Returns
    -------
    dict
        ``intercept`` (power inside the aperture over the power reflected), ``intercepted_w``,
        ``reflected_w``, ``incident_w``, ``on_target_w`` (power that reaches the plane),
        ``centroid_m`` {x, y} (power-weighted mean of the hits, from the aim point),
        ``centroid_offset_mrad`` {x, y, magnitude} (the centroid seen from the facet's centre, 1000 x /L),
        ``spot_radius_m`` (the radius about the centroid holding *fraction* of the reflected power; None
        if the rays reaching the plane hold less), ``spot_radius_mrad`` (1000 x that / L).
    """
    p = hits.power_w
    total = hits.reflected_w
    on_plane = float(p.sum())
    inside = aperture.contains(hits.x_m, hits.y_m)
    intercepted = float(p[inside].sum())
    if on_plane > 0:
        cx = float(np.sum(p * hits.x_m) / on_plane)
        cy = float(np.sum(p * hits.y_m) / on_plane)
    else:
        cx = cy = float("nan")
    radius = None
    if total > 0 and on_plane >= fraction * total:
        radius = _radius_holding(hits.x_m - np.float32(cx), hits.y_m - np.float32(cy), p, fraction * total)
    ms = 1000.0 / slant_range_m
    return {
        "intercept": intercepted / total if total > 0 else float("nan"),
        "intercepted_w": intercepted,
        "reflected_w": total,
        "incident_w": hits.incident_w,
        "on_target_w": on_plane,
        "centroid_m": {"x": cx, "y": cy},
        "centroid_offset_mrad": {"x": cx * ms, "y": cy * ms, "magnitude": float(np.hypot(cx, cy)) * ms},
        "spot_radius_m": radius,
        "spot_radius_mrad": None if radius is None else radius * ms,
    }


def _radius_holding(dx: np.ndarray, dy: np.ndarray, power: np.ndarray, wanted: float) -> float:
    """The radius about the origin within which the rays hold *wanted* power (exactly as sorting all rays
    would give, between the bracketing rays' radii), by a histogram of r^2 and a sort of one bin only."""
    r2 = (dx * dx + dy * dy).astype(np.float64)
    top = float(r2.max())
    bins = 1 << 16
    if top > 0:
        which = np.minimum((r2 * (bins / top)).astype(np.int64), bins - 1)
        cum = np.cumsum(np.bincount(which, weights=power, minlength=bins))
        b = min(int(np.searchsorted(cum, wanted)), bins - 1)
        below = float(cum[b - 1]) if b > 0 else 0.0
        sel = np.flatnonzero(which == b)
    else:
        below, sel = 0.0, np.arange(r2.size)
    order = sel[np.argsort(r2[sel], kind="stable")]
    cum = below + np.cumsum(power[order])
    k = min(int(np.searchsorted(cum, wanted)), order.size - 1)
    r_hi = math.sqrt(r2[order[k]])
    lo_cum = cum[k - 1] if k > 0 else below
    if k > 0:
        r_lo = math.sqrt(r2[order[k - 1]])
    else:        # the ray before lies in an earlier bin: the largest radius below this bin
        earlier = r2[which < b] if top > 0 and b > 0 else np.zeros(1)
        r_lo = math.sqrt(float(earlier.max())) if earlier.size else 0.0
    s = (wanted - lo_cum) / (cum[k] - lo_cum) if cum[k] > lo_cum else 1.0
    return r_lo + s * (r_hi - r_lo)
