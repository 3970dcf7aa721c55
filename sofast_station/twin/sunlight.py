"""The twin's own trace of its true facet in sunlight: the optical figures the station should report.

The measurement traces the points and slopes it measured (``sofast_station/optics/``). The twin's truth
must not come from that code, so this module traces the true surface itself, from the definitions of
docs/conventions.md ("Optics") and docs/optics.md, sharing nothing with ``optics/``:

- **Facet frame**: the frame the electronic boresight defines for the truth (:mod:`sofast_station.twin.truth`,
  the rotation R = R_y(beta) R_x(alpha) about the alignment point on the design surface): the frame the
  station's optical figures are stated in.
- **Sun**: its central ray travels along ``-(sin i, 0, cos i)`` (incidence i from the facet frame's z, toward
  +x). A ray of the sun makes the angle theta with it, at an azimuth uniform about it, theta drawn from the
  sun shape: ``pillbox`` (uniform over the half-angle, 4.65 mrad), ``gaussian`` (a circular normal of
  ``sigma_mrad`` per direction: theta is Rayleigh-distributed) or ``buie`` (Buie, Monger and Dey, Solar
  Energy 74, 2003: radiance cos(0.326 theta) / cos(0.308 theta) inside 4.65 mrad, exp(kappa) theta^gamma out
  to 43.6 mrad, theta in mrad, kappa = 0.9 ln(13.5 chi) chi^-0.3, gamma = 2.2 ln(0.52 chi) chi^0.43 - 0.1
  for the circumsolar ratio chi). The power within theta is the integral of the radiance times theta (the
  small-angle solid angle): here by Gauss-Legendre quadrature inside the disc and in closed form in the
  aureole, inverted for sampling.
- **Target**: the facet's centre c is the outline's area centroid on the design surface; the design's normal
  there reflects the central ray into the central reflected ray r_c. The target plane is normal to r_c at
  the slant range L from c (default: the design's distance from c to its focus, f + z(c)); the aim point is
  ``c + L r_c``; the plane's x axis is the facet's x made perpendicular to r_c (its y when x is parallel to
  r_c), its y axis ``r_c x x``. The aperture (a circle, or a rectangle along those axes) is centred on the aim
  point; by default a circle of twice the sun's image, ``2 L 4.65 mrad``.
- **Power**: a patch of surface dA with unit normal n reflects ``DNI rho cos(theta_i) dA``, with
  ``cos(theta_i) = max(0, -u_sun . n)``; the patches' projections on the facet's x-y plane add up to the
  outline's area.
- **Figures**: the *intercept factor* is the power inside the aperture over the power reflected; the
  *centroid* is the power-weighted mean of the hits on the plane (seen from the facet's centre: 1000 x / L
  mrad); the *90 % spot radius* is the radius about the centroid of the circle that holds 90 % of the power
  reflected (rays that never reach the plane count as outside; None when the plane gets less than 90 %).

**How the integral is taken.** The surface is sampled where the twin knows it exactly, its true surface
over the whole outline (not the pixels a measurement kept: the station's figures state the whole facet's
optics), on a scrambled Sobol sequence (fixed seed: the same facet gives the same bits) whose third
coordinate is the azimuth psi of the sample's sun rays about the sun's centre. The angle theta from the
centre is not drawn but integrated: to first order in theta, the rays a sample reflects at the azimuth psi
meet the plane on the line ``h + theta v``, h the sample's central hit and ``v = J (cos psi, sin psi)``, J the
2 x 2 derivative of the hit with respect to the incoming ray's direction (reflection, then the plane). The
theta for which that line lies inside a circle or a rectangle is an interval (the roots of a quadratic, or
two slabs), and its share of the power is the sun shape's radial distribution there
(:func:`sun_share_within`): every sample contributes a continuous share, not a ray's 0 or 1, so the estimate
converges like a smooth integral. The second-order terms in theta (a shift of the ray's hit by about
theta^2 D tan(obliquity), micrometres) are left out; the centroid is that of the central hits (the sun is
symmetric about its centre).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq
from scipy.stats import qmc

from ..errors import ConfigError
from ..facet import FacetDesign
from .outline import inside_outline

#: The sun's mean angular radius, rad: the pillbox's half-angle and the edge of Buie's solar disc.
SUN_RADIUS_RAD = 4.65e-3
#: Where Buie's aureole ends, rad.
BUIE_AUREOLE_END_RAD = 43.6e-3
#: The share of the reflected power the spot radius holds.
SPOT_SHARE = 0.9
SUN_SHAPES = ("pillbox", "gaussian", "buie")


@dataclass(frozen=True)
class Sunlight:
    """How the twin's facet is lit and where its beam is judged (the station's ``[optics]``, read by the caller).

    Attributes
    ----------
    sun : str
        ``"pillbox"``, ``"gaussian"`` or ``"buie"``.
    half_angle_mrad : float
        The pillbox sun's half-angle, mrad.
    sigma_mrad : float
        The Gaussian sun's standard deviation per direction, mrad.
    csr : float
        The Buie sun's circumsolar ratio, 0 < csr < 1.
    dni_w_m2 : float
        Direct normal irradiance, W/m^2.
    reflectivity : float
        Specular reflectivity, (0, 1].
    incidence_angle_deg : float
        The sun's central ray from the facet frame's z axis, toward +x, degrees, [0, 90).
    slant_range_m : float or None
        Facet centre to target plane, metres; None: the design's distance from its centre to its focus.
    aperture : tuple or None
        ``("circle", radius_m)`` or ``("rectangle", width_m, height_m)``, metres; None: a circle of radius
        ``2 L 4.65 mrad``.
    samples : int
        Quasi-random samples of the facet, each with one azimuth of the sun's rays (a power of two keeps the Sobol
        sequence balanced).
    seed : int
        Seed of the Sobol sequence's scrambling.
    """

    sun: str = "pillbox"
    half_angle_mrad: float = 1e3 * SUN_RADIUS_RAD
    sigma_mrad: float = 2.51
    csr: float = 0.05
    dni_w_m2: float = 1000.0
    reflectivity: float = 0.94
    incidence_angle_deg: float = 0.0
    slant_range_m: float | None = None
    aperture: tuple | None = None
    samples: int = 2 ** 15
    seed: int = 1

    def __post_init__(self):
        def bad(what):
            raise ConfigError(f"the twin's sunlight: {what}")

        if self.sun not in SUN_SHAPES:
            bad(f"sun must be one of {SUN_SHAPES}, got {self.sun!r}")
        for key in ("half_angle_mrad", "sigma_mrad", "dni_w_m2"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                bad(f"{key} must be a positive number, got {value!r}")
        if not 0.0 < self.csr < 1.0:
            bad(f"csr must lie between 0 and 1, got {self.csr!r}")
        if not 0.0 < self.reflectivity <= 1.0:
            bad(f"reflectivity must lie in (0, 1], got {self.reflectivity!r}")
        if not 0.0 <= self.incidence_angle_deg < 90.0:
            bad(f"incidence_angle_deg must lie in [0, 90), got {self.incidence_angle_deg!r}")
        if self.slant_range_m is not None and not (math.isfinite(self.slant_range_m) and self.slant_range_m > 0):
            bad(f"slant_range_m must be a positive distance in metres, got {self.slant_range_m!r}")
        ap = self.aperture
        if ap is not None and not ((len(ap) == 2 and ap[0] == "circle" and ap[1] > 0)
                                   or (len(ap) == 3 and ap[0] == "rectangle" and ap[1] > 0 and ap[2] > 0)):
            bad(f"aperture must be ('circle', radius_m) or ('rectangle', width_m, height_m), got {ap!r}")
        if not (isinstance(self.samples, int) and self.samples >= 256):
            bad(f"samples must be a whole number of at least 256, got {self.samples!r}")


# ----------------------------------------------------------------------------------------------- the sun
def _buie_disc_radiance(theta_mrad: np.ndarray) -> np.ndarray:
    """Buie's relative radiance inside the solar disc (theta <= 4.65 mrad): 1 at the centre."""
    t = np.asarray(theta_mrad, dtype=np.float64)
    return np.cos(0.326 * t) / np.cos(0.308 * t)


def _buie_exponents(csr: float) -> tuple[float, float]:
    kappa = 0.9 * math.log(13.5 * csr) * csr ** -0.3
    gamma = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1
    return kappa, gamma


def _aureole_power(theta_mrad: np.ndarray, csr: float) -> np.ndarray:
    """The aureole's power (in the units of the disc's, radiance x mrad^2) from 4.65 mrad to *theta_mrad*:
    the integral of exp(kappa) t^gamma t dt in closed form."""
    kappa, gamma = _buie_exponents(csr)
    t0 = 1e3 * SUN_RADIUS_RAD
    t = np.asarray(theta_mrad, dtype=np.float64)
    if abs(gamma + 2.0) < 1e-12:
        return math.exp(kappa) * np.log(t / t0)
    return math.exp(kappa) * (t ** (gamma + 2.0) - t0 ** (gamma + 2.0)) / (gamma + 2.0)


@functools.lru_cache(maxsize=8)
def buie_radial_table(csr: float, cells: int = 512) -> tuple[np.ndarray, np.ndarray, float]:
    """The Buie sun's power within theta across its disc: (theta_mrad at the cell edges, the power there, and
    the aureole's power), in radiance x mrad^2 (read-only arrays, kept per csr: a pure function's result).

    Each cell of the disc is integrated by 8-point Gauss-Legendre quadrature of ``radiance(t) t``; the
    aureole in closed form (:func:`_aureole_power`).
    """
    edges = np.linspace(0.0, 1e3 * SUN_RADIUS_RAD, cells + 1)
    nodes, weights = np.polynomial.legendre.leggauss(8)
    mid, half = 0.5 * (edges[1:] + edges[:-1]), 0.5 * np.diff(edges)
    t = mid[:, None] + half[:, None] * nodes[None, :]
    per_cell = half * np.sum(weights[None, :] * _buie_disc_radiance(t) * t, axis=1)
    within = np.concatenate([[0.0], np.cumsum(per_cell)])
    aureole = float(_aureole_power(1e3 * BUIE_AUREOLE_END_RAD, csr))
    edges.setflags(write=False)
    within.setflags(write=False)
    return edges, within, aureole


def sun_share_within(sunlight: Sunlight, theta_rad: np.ndarray) -> np.ndarray:
    """The share of the sun's power within the angle *theta_rad* of its centre (0 at 0, 1 far out): for the
    pillbox (theta / half-angle)^2, for the Gaussian sun 1 - exp(-theta^2 / 2 sigma^2) (a circular normal's
    radius is Rayleigh-distributed), for Buie's sun :func:`buie_radial_table` (linear between its cells inside
    the disc, in closed form in the aureole)."""
    theta = np.maximum(np.asarray(theta_rad, dtype=np.float64), 0.0)
    if sunlight.sun == "pillbox":
        return np.minimum(theta / (1e-3 * sunlight.half_angle_mrad), 1.0) ** 2
    if sunlight.sun == "gaussian":
        return -np.expm1(-0.5 * (theta / (1e-3 * sunlight.sigma_mrad)) ** 2)
    edges, within, aureole = buie_radial_table(sunlight.csr)
    total = within[-1] + aureole
    t = 1e3 * theta
    t_aureole = np.clip(t, 1e3 * SUN_RADIUS_RAD, 1e3 * BUIE_AUREOLE_END_RAD)
    in_disc = np.interp(t, edges, within)
    return np.where(t <= edges[-1], in_disc, within[-1] + _aureole_power(t_aureole, sunlight.csr)) / total


# ---------------------------------------------------------------------------------------------- the target
@dataclass(frozen=True)
class TargetPlane:
    """The target (facet frame, metres): the sun's central direction, the facet's centre, the central
    reflected ray (the plane's normal), the aim point, the plane's axes, the slant range and the aperture."""

    u_sun: np.ndarray
    centre_m: np.ndarray
    u_reflected: np.ndarray
    aim_m: np.ndarray
    u_x: np.ndarray
    u_y: np.ndarray
    slant_range_m: float
    aperture: tuple

    def inside_aperture(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Which plane points (metres from the aim point along u_x, u_y) fall inside the aperture."""
        if self.aperture[0] == "circle":
            return np.hypot(x_m, y_m) <= self.aperture[1]
        return (np.abs(x_m) <= 0.5 * self.aperture[1]) & (np.abs(y_m) <= 0.5 * self.aperture[2])


def target_plane(design: FacetDesign, sunlight: Sunlight) -> TargetPlane:
    """The target plane of *design* under *sunlight* (module docstring, "Target")."""
    cx, cy = (float(v) for v in design.centroid_m)
    a, b, c, d, e, _ = (float(v) for v in design.coefficients)
    centre = np.array([cx, cy, float(design.z(cx, cy))])
    normal = np.array([-(2.0 * a * cx + c + e * cy), -(2.0 * b * cy + d + e * cx), 1.0])
    normal /= np.linalg.norm(normal)
    i = math.radians(sunlight.incidence_angle_deg)
    u_sun = np.array([-math.sin(i), 0.0, -math.cos(i)])
    reflected = u_sun - 2.0 * float(u_sun @ normal) * normal
    if reflected[2] <= 0:
        raise ConfigError(f"the twin's sunlight: at {sunlight.incidence_angle_deg} degrees of incidence the sun "
                          "lies behind the facet's centre; use a smaller incidence angle")
    slant = sunlight.slant_range_m if sunlight.slant_range_m is not None else design.focal_length_m + centre[2]
    u_x = np.array([1.0, 0.0, 0.0]) - reflected[0] * reflected
    if np.linalg.norm(u_x) < 1e-6:
        u_x = np.array([0.0, 1.0, 0.0]) - reflected[1] * reflected
    u_x /= np.linalg.norm(u_x)
    aperture = sunlight.aperture or ("circle", 2.0 * slant * SUN_RADIUS_RAD)
    return TargetPlane(u_sun, centre, reflected, centre + slant * reflected, u_x, np.cross(reflected, u_x),
                       float(slant), tuple(aperture))


# ------------------------------------------------------------------------------------------- the lines
@dataclass(frozen=True)
class SunLines:
    """What every surface sample sends to the target: its power, and the line its rays at one azimuth trace.

    The sun's rays at the azimuth psi and the angle theta from its centre, reflected by a sample, meet the plane
    at ``hit + theta v`` (to first order in theta), ``v = J (cos psi, sin psi)``: a line through the sample's
    central hit, along which theta is distributed as the sun shape says.

    Attributes
    ----------
    power_w : (n,) array
        The power the sample reflects, ``DNI rho cos(theta_i) dA``, W.
    ahead : (n,) bool array
        Whether its central reflected ray meets the plane ahead (a sample whose ray misses counts as outside
        everywhere).
    x_m, y_m : (n,) arrays
        Its central hit on the plane, metres from the aim point along the plane's axes.
    v_x, v_y : (n,) arrays
        The line's direction, metres on the plane per radian of theta.
    """

    power_w: np.ndarray
    ahead: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    v_x: np.ndarray
    v_y: np.ndarray


def _dot(v: np.ndarray, w) -> np.ndarray:
    """v . w for vectors (3, n) and a (3,) vector, component by component (no BLAS)."""
    return v[0] * w[0] + v[1] * w[1] + v[2] * w[2]


def sun_lines(points_m: np.ndarray, normals: np.ndarray, area_m2: np.ndarray, azimuth_rad: np.ndarray,
              target: TargetPlane, sunlight: Sunlight) -> SunLines:
    """The lines of surface samples: *points_m* (3, n) metres and unit *normals* (3, n) in the facet frame, the
    area each stands for (m^2) and the azimuth (rad) of its rays about the sun's centre."""
    u_sun, r_c, aim = target.u_sun, target.u_reflected, target.aim_m
    cos_i = np.maximum(-_dot(normals, u_sun), 0.0)
    power = (sunlight.dni_w_m2 * sunlight.reflectivity) * cos_i * area_m2

    def reflect(v):
        """The law of reflection, v - 2 (v . n) n, of a (3,) direction at every sample."""
        twice = 2.0 * _dot(normals, v)
        return np.stack([v[k] - twice * normals[k] for k in range(3)])

    central = reflect(u_sun)
    along = _dot(central, r_c)
    before = _dot(aim[:, None] - points_m, r_c)           # > 0: the point lies before the plane
    with np.errstate(divide="ignore", invalid="ignore"):
        t = before / along
    ahead = (along != 0) & (t > 0)                        # the plane lies ahead of the ray
    t = np.where(ahead, t, 0.0)
    hit = np.stack([points_m[k] + t * central[k] - aim[k] for k in range(3)])
    # The ray at the angle theta and the azimuth psi comes along u_sun + theta (cos psi a_1 + sin psi a_2), a_2 = y
    # made perpendicular to u_sun (a sun in the facet frame's x-z plane), a_1 = a_2 x u_sun.
    across_2 = np.array([0.0, 1.0, 0.0]) - u_sun[1] * u_sun
    across_2 /= np.linalg.norm(across_2)
    across_1 = np.cross(across_2, u_sun)
    cos_psi, sin_psi = np.cos(azimuth_rad), np.sin(azimuth_rad)
    offset = np.stack([cos_psi * across_1[k] + sin_psi * across_2[k] for k in range(3)])
    # reflection is linear: the reflected ray turns by the reflected offset; the hit moves along the plane by
    # t (turned - (turned . r_c) / (central . r_c) central)
    twice = 2.0 * (offset[0] * normals[0] + offset[1] * normals[1] + offset[2] * normals[2])
    turned = np.stack([offset[k] - twice * normals[k] for k in range(3)])
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = _dot(turned, r_c) / along
    move = np.stack([t * (turned[k] - shift * central[k]) for k in range(3)])
    on_plane = [np.where(ahead, _dot(v, axis), 0.0) for v in (hit, move) for axis in (target.u_x, target.u_y)]
    return SunLines(power, ahead, *on_plane)


class CircleShares:
    """The share of each line's power (theta distributed as the sun shape) inside circles about one centre.

    The theta for which ``|hit + theta v - centre| <= r`` is the interval between the roots of
    ``|v|^2 theta^2 + 2 (c . v) theta + |c|^2 - r^2`` (c = hit - centre); its share is the sun shape's power
    there. What does not depend on r is formed once, so a radius is found by a few cheap evaluations.
    """

    def __init__(self, lines: SunLines, sunlight: Sunlight, centre_x_m: float, centre_y_m: float):
        self.sunlight = sunlight
        cx, cy = lines.x_m - centre_x_m, lines.y_m - centre_y_m
        self.vv = lines.v_x * lines.v_x + lines.v_y * lines.v_y
        self.cv = cx * lines.v_x + cy * lines.v_y
        self.cc = cx * cx + cy * cy
        self.base = self.cv * self.cv - self.vv * self.cc          # the discriminant at r = 0
        self.moving = self.vv > 0
        with np.errstate(divide="ignore"):
            self.inv_vv = np.where(self.moving, 1.0 / np.where(self.moving, self.vv, 1.0), 0.0)

    def share(self, radius_m: float) -> np.ndarray:
        """Each line's share of its power within *radius_m* of the centre."""
        disc = self.base + self.vv * (radius_m * radius_m)
        root = np.sqrt(np.maximum(disc, 0.0))
        lo, hi = (-self.cv - root) * self.inv_vv, (-self.cv + root) * self.inv_vv
        share = sun_share_within(self.sunlight, hi) - sun_share_within(self.sunlight, lo)
        # a line of no length (a ray that misses the plane): its hit alone decides
        return np.where(self.moving, np.where(disc > 0, share, 0.0), (self.cc <= radius_m * radius_m) * 1.0)


def share_in_rectangle(lines: SunLines, sunlight: Sunlight, width_m: float, height_m: float) -> np.ndarray:
    """The share of each line's power inside the rectangle ``|x| <= width/2``, ``|y| <= height/2`` about the aim
    point: the theta within both slabs (an interval) and its share of the sun."""
    lo = np.zeros(lines.x_m.shape)
    hi = np.full(lines.x_m.shape, np.inf)
    for centre, v, half in ((lines.x_m, lines.v_x, 0.5 * width_m), (lines.y_m, lines.v_y, 0.5 * height_m)):
        with np.errstate(divide="ignore", invalid="ignore"):
            a, b = (-half - centre) / v, (half - centre) / v
        moving = v != 0
        # a line parallel to the slab is in it throughout or nowhere
        inside = np.abs(centre) <= half
        lo = np.maximum(lo, np.where(moving, np.minimum(a, b), np.where(inside, 0.0, np.inf)))
        hi = np.minimum(hi, np.where(moving, np.maximum(a, b), np.where(inside, np.inf, -np.inf)))
    return np.where(hi > lo, sun_share_within(sunlight, hi) - sun_share_within(sunlight, lo), 0.0)


def _rms_angle_rad(sunlight: Sunlight) -> float:
    """About the RMS angle of the sun's rays from its centre (exact for the pillbox and the Gaussian sun; the
    disc's for Buie's): where the search for the spot's radius starts."""
    if sunlight.sun == "gaussian":
        return math.sqrt(2.0) * 1e-3 * sunlight.sigma_mrad
    half = 1e-3 * sunlight.half_angle_mrad if sunlight.sun == "pillbox" else SUN_RADIUS_RAD
    return half / math.sqrt(2.0)


def beam_figures(lines: SunLines, target: TargetPlane, sunlight: Sunlight) -> dict:
    """The beam's figures from its samples' lines (module docstring, "Figures").

    Returns
    -------
    dict
        ``reflected_w``, ``intercepted_w``, ``intercept``, ``centroid_m`` {x, y}, ``centroid_offset_mrad``
        {x, y, magnitude}, ``spot_radius_m`` and ``spot_radius_mrad`` (None when less than 90 % of the
        reflected power reaches the plane).
    """
    power = lines.power_w
    reflected = float(power.sum())
    on = np.where(lines.ahead, power, 0.0)
    on_target = float(on.sum())
    if target.aperture[0] == "circle":
        share = CircleShares(lines, sunlight, 0.0, 0.0).share(target.aperture[1])
    else:
        share = share_in_rectangle(lines, sunlight, target.aperture[1], target.aperture[2])
    intercepted = float(np.sum(on * share))
    # A sample's rays are centred on its central hit (the sun is symmetric about its centre; to first order in
    # theta): the centroid of the central hits.
    cx = float(np.sum(on * lines.x_m)) / on_target if on_target > 0 else math.nan
    cy = float(np.sum(on * lines.y_m)) / on_target if on_target > 0 else math.nan
    radius = None
    if reflected > 0 and on_target >= SPOT_SHARE * reflected:
        wanted = SPOT_SHARE * reflected
        about = CircleShares(lines, sunlight, cx, cy)

        def short(r):
            return float(np.sum(on * about.share(r))) - wanted

        # a bracket about the beam's RMS size (the hits' spread, and the sun's at the lines' mean length), then
        # Brent's method; the power within r grows with r from none to all that reaches the plane
        spread = float(np.sum(on * about.cc)) / on_target + float(np.mean(about.vv)) * _rms_angle_rad(sunlight) ** 2
        lo = hi = max(math.sqrt(spread), 1e-9)
        for _ in range(200):
            if short(lo) <= 0:
                break
            lo *= 0.8
        while short(hi) < 0:
            hi *= 1.25
        radius = float(brentq(short, lo, hi, xtol=1e-12, rtol=1e-10))
    per_mrad = 1e3 / target.slant_range_m
    return {"reflected_w": reflected, "on_target_w": on_target, "intercepted_w": intercepted,
            "intercept": intercepted / reflected if reflected > 0 else math.nan,
            "centroid_m": {"x": cx, "y": cy},
            "centroid_offset_mrad": {"x": cx * per_mrad, "y": cy * per_mrad,
                                     "magnitude": math.hypot(cx, cy) * per_mrad},
            "spot_radius_m": radius, "spot_radius_mrad": None if radius is None else radius * per_mrad}


# ------------------------------------------------------------------------------------------- a facet
def _unit_normals(slope_x: np.ndarray, slope_y: np.ndarray) -> np.ndarray:
    """Unit normals (3, n) of slopes (dz/dx, dz/dy): (-s_x, -s_y, 1) / sqrt(1 + s_x^2 + s_y^2)."""
    n_z = 1.0 / np.sqrt(1.0 + slope_x * slope_x + slope_y * slope_y)
    return np.stack([-slope_x * n_z, -slope_y * n_z, n_z])


def _turn(vectors: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """R v for vectors (3, n), component by component (no BLAS)."""
    return np.stack([rotation[k, 0] * vectors[0] + rotation[k, 1] * vectors[1] + rotation[k, 2] * vectors[2]
                     for k in range(3)])


@dataclass(frozen=True)
class SunlitPlan:
    """What the sunlight of every facet of a design shares: the samples, the target and the design's figures.

    Attributes
    ----------
    x_m, y_m : (n,) arrays
        The samples inside the outline, facet frame, metres.
    azimuth_rad : (n,) array
        The azimuth of their rays about the sun's centre.
    projected_m2 : float
        The outline's projected area each sample stands for.
    target : TargetPlane
    design : dict
        :func:`beam_figures` of the design surface.
    """

    x_m: np.ndarray
    y_m: np.ndarray
    azimuth_rad: np.ndarray
    projected_m2: float
    target: TargetPlane
    design: dict


def sunlit_plan(design: FacetDesign, sunlight: Sunlight) -> SunlitPlan:
    """The samples and target of *design* under *sunlight*, and the design surface's figures (module docstring)."""
    outline = np.asarray(design.outline_m, dtype=np.float64)
    lo, hi = outline.min(axis=0), outline.max(axis=0)
    u = qmc.Sobol(3, scramble=True, seed=sunlight.seed).random(sunlight.samples)
    x, y = lo[0] + (hi[0] - lo[0]) * u[:, 0], lo[1] + (hi[1] - lo[1]) * u[:, 1]
    inside = inside_outline(x, y, outline)
    if not np.any(inside):
        raise ConfigError(f"the twin's sunlight: no sample fell inside the outline of {design.name!r}; "
                          "use more samples")
    x, y = x[inside], y[inside]
    azimuth = 2.0 * np.pi * u[inside, 2]
    # each sample stands for an equal share of the outline's projected area (shoelace)
    x_c, y_c = outline[:, 0], outline[:, 1]
    projected = 0.5 * abs(float(np.sum(x_c * np.roll(y_c, -1) - np.roll(x_c, -1) * y_c))) / x.size
    target = target_plane(design, sunlight)
    a, b, c, d, e, _ = (float(v) for v in design.coefficients)
    s_x, s_y = 2.0 * a * x + c + e * y, 2.0 * b * y + d + e * x
    ideal = sun_lines(np.stack([x, y, design.z(x, y)]), _unit_normals(s_x, s_y),
                      projected * np.sqrt(1.0 + s_x * s_x + s_y * s_y), azimuth, target, sunlight)
    for array in (x, y, azimuth):
        array.setflags(write=False)
    return SunlitPlan(x, y, azimuth, projected, target, beam_figures(ideal, target, sunlight))


def facet_in_sunlight(surface, plan: SunlitPlan, sunlight: Sunlight, rotation: np.ndarray | None = None,
                      pivot_m: np.ndarray | None = None) -> dict:
    """The optical figures of a true surface in sunlight (module docstring).

    Parameters
    ----------
    surface : TrueSurface
        The true surface (``height_and_slopes``), in its true facet frame; its outline is the plan's design's.
    plan : SunlitPlan
        From :func:`sunlit_plan` for the facet's design and *sunlight* (the same for every facet of a design).
    sunlight : Sunlight
    rotation, pivot_m : (3, 3) and (3,) arrays, optional
        The frame the figures are stated in: ``X' = R (X - P) + P``, ``n' = R n`` (the truth's boresight,
        :func:`~sofast_station.twin.truth.boresight_frame`); the true facet frame when None.

    Returns
    -------
    dict
        :func:`beam_figures` of the true surface, ``power_ratio_vs_design`` (its intercepted power over the
        design's), ``design`` ({``intercept``, ``spot_radius_m``, ``intercepted_w``}), ``samples`` and
        ``sunlight`` (sun, slant range, aperture, incidence).
    """
    x, y = plan.x_m, plan.y_m
    z, s_x, s_y = surface.height_and_slopes(x, y)
    points = np.stack([x, y, z])
    normals = _unit_normals(s_x, s_y)
    if rotation is not None:
        pivot = np.asarray(pivot_m, dtype=np.float64)[:, None]
        points = _turn(points - pivot, rotation) + pivot
        normals = _turn(normals, rotation)
    # the surface area a sample stands for: its projected share over n_z (in its own true frame)
    area = plan.projected_m2 * np.sqrt(1.0 + s_x * s_x + s_y * s_y)
    lines = sun_lines(points, normals, area, plan.azimuth_rad, plan.target, sunlight)
    figures = beam_figures(lines, plan.target, sunlight)
    ideal = plan.design
    figures["power_ratio_vs_design"] = (figures["intercepted_w"] / ideal["intercepted_w"]
                                        if ideal["intercepted_w"] > 0 else None)
    figures["design"] = {"intercept": ideal["intercept"], "spot_radius_m": ideal["spot_radius_m"],
                         "intercepted_w": ideal["intercepted_w"]}
    figures["samples"] = int(x.size)
    target = plan.target
    figures["sunlight"] = {"sun": sunlight.sun, "slant_range_m": target.slant_range_m,
                           "aperture": [target.aperture[0], *(float(v) for v in target.aperture[1:])],
                           "incidence_angle_deg": sunlight.incidence_angle_deg}
    return figures
