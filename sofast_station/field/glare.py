"""Glint and glare of a heliostat seen by an observer (issue 45, item 5): the retinal irradiance and the
subtended source angle, from the factory's measured facets, and by the patent's camera route.

The eye (Sandia's patent, "Mobile computing device configured to compute irradiance, glint, and glare of the
sun", its description's Eqs. (47) and (48), ¶150-151; after Ho, Ghanbari and Diver, J. Sol. Energy Eng. 2011):
a source subtending the angle omega forms a retinal image of diameter ``d_r = f omega`` (f = 0.017 m, the eye's
focal length); the power the pupil (diameter d_p = 2 mm in sunlight) takes from the corneal irradiance E_c,
times the ocular media's transmission tau = 0.5, spread over that image, is the **retinal irradiance**
``E_r = E_c (d_p / d_r)^2 tau`` (:func:`retinal_irradiance`). For a flat mirror of reflectivity rho larger than
the sun's image, the source is the sun's disc (omega = 2 x 4.65 mrad) and E_c = rho DNI: E_r is the sun's own
times rho (the patent's Eq. (57) with the mirror's beta the sun's angle).

**From the measured facets** (:func:`facet_glare`): each facet of the factory record is sampled as for its
spot (:mod:`.spot`: its design surface with the measured curvature, turned by its measured canting error,
scattered by its residual slope RMS) on the heliostat as it stands (tracking the aim point at a moment, or a
commanded orientation: stow, standby). An observer at O sees at a surface point P (unit normal n) the sky in
the direction ``s = 2 (n.v) n - v`` (v the unit vector from P to O); the point shows the sun's radiance
L(theta) at theta, the angle between s and the sun's centre, times rho, over the solid angle ``dA (n.v) / |O -
P|^2`` it subtends at O. The corneal irradiance is the sum; the **source** is the part showing the sun's disc
(theta within 4.65 mrad), and omega the diameter of the disc of the same solid angle, ``2 sqrt(Omega / pi)``.
The sun's radiance: uniform over its disc (pillbox), or Buie's limb-darkened disc and aureole
(:func:`~sofast_station.optics.sun.buie_radiance`), each normalised so that it integrates to the DNI.

**The camera route** (:func:`camera_glare`, the patent's ¶55 and ¶182-183): an image of the sun (through a
neutral density filter) and one of the glare source, same lens and zoom, and the DNI. The sun's disc (pixels
above half its level over the sky) calibrates the angle per pixel (its radius is 4.65 mrad, Eq. (8)) and the
pixel values' power (Eq. (5): its pixel sum is the DNI); the glare source's pixel sum, corrected for each
image's exposure and filter, is then its corneal irradiance ``E_c = DNI sum(V_glare) / sum(V_sun)`` and the
pixels above half its level give omega.

**Not given here: the hazard class.** The ocular-hazard thresholds (retinal burn, potential for a temporary
after-image, low potential) are curves of E_r against omega published by Ho et al. (2011) and used by Sandia's
SGHAT; their formulas could not be found in a source this work could quote, and the house rule is never to
invent constants. The chart shows E_r against omega for each observer beside the sun seen directly.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..errors import CaptureError, ConfigError
from ..optics.sun import BUIE_OUTER_RAD, SUN_HALF_ANGLE_RAD, buie_radiance
from .spot import _facet_samples, _in_frame, _turn, refuse_clipped

#: The eye's focal length, metres (the patent's Eq. (47): f = 0.017 m).
EYE_FOCAL_M = 0.017
#: The pupil's diameter adjusted to sunlight, metres (the patent's ¶151: about 2 mm).
PUPIL_M = 0.002
#: The ocular media's transmission (the patent's ¶151: about 0.5).
OCULAR_TRANSMISSION = 0.5


def retinal_irradiance(corneal_w_m2, omega_rad, pupil_m: float = PUPIL_M, eye_focal_m: float = EYE_FOCAL_M,
                       tau: float = OCULAR_TRANSMISSION):
    """``E_r = E_c (d_p / (f omega))^2 tau``, W/m^2 (module docstring; the patent's Eqs. (47), (48))."""
    omega = np.asarray(omega_rad, dtype=np.float64)
    return np.asarray(corneal_w_m2, dtype=np.float64) * (pupil_m / (eye_focal_m * omega)) ** 2 * tau


@dataclass(frozen=True)
class Sunlight:
    """The sun's direction (unit vector towards it), its shape (``"pillbox"`` or ``"buie"`` with ``csr``) and
    its DNI, W/m^2."""

    direction: np.ndarray
    dni_w_m2: float
    shape: str = "pillbox"
    csr: float = 0.05

    def radiance(self, theta_rad: np.ndarray) -> np.ndarray:
        """The sun's radiance at *theta_rad* from its centre, W/m^2/sr, integrating to the DNI (small angles)."""
        theta = np.asarray(theta_rad, dtype=np.float64)
        if self.shape == "pillbox":
            return np.where(theta <= SUN_HALF_ANGLE_RAD, self.dni_w_m2 / (math.pi * SUN_HALF_ANGLE_RAD ** 2), 0.0)
        if self.shape == "buie":
            t = np.linspace(0.0, BUIE_OUTER_RAD, 20001)
            norm = float(np.trapezoid(buie_radiance(t, self.csr) * 2.0 * math.pi * t, t))
            return self.dni_w_m2 * buie_radiance(theta, self.csr) / norm
        raise ConfigError(f"sun shape must be 'pillbox' or 'buie', got {self.shape!r}")


def sun_seen_directly(dni_w_m2: float) -> dict:
    """The sun itself as a glare source: E_c = DNI, omega = its disc (a reference on the chart)."""
    omega = 2.0 * SUN_HALF_ANGLE_RAD
    return {"corneal_w_m2": dni_w_m2, "omega_rad": omega, "retinal_w_m2": float(retinal_irradiance(dni_w_m2, omega))}


def facet_glare(points_m: np.ndarray, normals: np.ndarray, areas_m2: np.ndarray, observer_m, sun: Sunlight,
                reflectivity: float = 0.94) -> dict:
    """The glare an observer sees in mirror samples (module docstring).

    Parameters
    ----------
    points_m : (3, N) array
        Surface samples, field frame, metres.
    normals : (3, N) array
        Their unit normals.
    areas_m2 : (N,) array
        The surface each stands for.
    observer_m : (3,) sequence
        The observer's eye, field frame.
    sun : Sunlight
    reflectivity : float

    Returns
    -------
    dict
        ``corneal_w_m2``, ``omega_rad`` (None when the sun's disc is seen nowhere), ``retinal_w_m2`` (None
        likewise), ``source_samples`` (samples showing the disc), ``source_solid_angle_sr``, ``glare`` (bool),
        ``distance_m`` (to the samples' middle).
    """
    o = np.asarray(observer_m, dtype=np.float64)[:, None]
    v = o - points_m
    r = np.linalg.norm(v, axis=0)
    v = v / r
    nv = np.sum(normals * v, axis=0)
    s = 2.0 * nv * normals - v
    d = np.asarray(sun.direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    cos_t = np.clip(d @ s, -1.0, 1.0)
    # the angle from the sun's centre; arccos loses precision near 0, so the chord is used there
    theta = 2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(s - d[:, None], axis=0), 0.0, 1.0))
    front = (nv > 0) & (cos_t > 0)
    d_omega = np.where(front, areas_m2 * nv / (r * r), 0.0)
    corneal = float(reflectivity * np.sum(sun.radiance(theta) * d_omega))
    disc = front & (theta <= SUN_HALF_ANGLE_RAD)
    solid = float(np.sum(d_omega[disc]))
    n = int(np.count_nonzero(disc))
    middle = float(np.linalg.norm(np.asarray(observer_m, float) - points_m.mean(axis=1)))
    if n == 0:
        return {"corneal_w_m2": corneal, "omega_rad": None, "retinal_w_m2": None, "source_samples": 0,
                "source_solid_angle_sr": 0.0, "glare": False, "distance_m": middle}
    omega = 2.0 * math.sqrt(solid / math.pi)
    return {"corneal_w_m2": corneal, "omega_rad": omega, "retinal_w_m2": float(retinal_irradiance(corneal, omega)),
            "source_samples": n, "source_solid_angle_sr": solid, "glare": True, "distance_m": middle}


def heliostat_samples(models: list, ensemble, rotation: np.ndarray, origin_m, per_facet: int = 6000,
                      seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every facet's samples (:mod:`.spot`'s model of the factory record) in the field: points (3, N), unit
    normals (3, N), areas (N,), for the heliostat frame *rotation* (heliostat -> field) at *origin_m*."""
    pts, nrm, area = [], [], []
    for m, rot, pos, p, s, a in _facet_samples(ensemble, models, per_facet, np.random.default_rng([seed, 41])):
        ph, sh = _in_frame(p, s, rot @ _turn(*m.canting_mrad), pos)
        nh = np.stack([-sh[0], -sh[1], np.ones(sh.shape[1])])
        nh /= np.linalg.norm(nh, axis=0)
        pts.append(rotation @ ph + np.asarray(origin_m, float)[:, None])
        nrm.append(rotation @ nh)
        area.append(a * np.sqrt(1.0 + s[0] ** 2 + s[1] ** 2))   # the projected share on the tilted surface
    return np.hstack(pts), np.hstack(nrm), np.concatenate(area)


# ----------------------------------------------------------------------------------------- the camera route
def _grey(image) -> np.ndarray:
    img = np.asarray(image)
    return (img.mean(axis=2) if img.ndim == 3 else img).astype(np.float64)


def _level(img: np.ndarray) -> tuple[float, float]:
    b = max(2, int(round(0.04 * min(img.shape))))
    border = np.concatenate([img[:b].ravel(), img[-b:].ravel(), img[:, :b].ravel(), img[:, -b:].ravel()])
    level = float(np.median(border))
    return level, max(1.4826 * float(np.median(np.abs(border - level))), 1e-9)


def _source(img: np.ndarray, what: str, hint: str) -> tuple[np.ndarray, float, float]:
    """(half-level region, its pixel sum over the level within the widened region, noise) of the brightest
    source in *img*."""
    level, noise = _level(img)
    signal = img - level
    peak = float(ndimage.uniform_filter(signal, 3).max())
    if peak < 20.0 * noise:
        raise CaptureError(f"no {what} found: its brightest stands {peak / noise:.1f} times the noise above the "
                           f"background; {hint}")
    labels, _ = ndimage.label(signal > 0.5 * peak)
    top = np.unravel_index(int(np.argmax(ndimage.uniform_filter(signal, 3))), signal.shape)
    half = labels == labels[top]
    b = max(2, int(round(0.04 * min(img.shape))))
    if half[:b].any() or half[-b:].any() or half[:, :b].any() or half[:, -b:].any():
        raise CaptureError(f"the {what} reaches the image's edge: frame it whole")
    wide = ndimage.binary_dilation(half, iterations=max(3, int(0.3 * math.sqrt(half.sum()))))
    return half, float(signal[wide].sum()), noise


def camera_glare(sun_image, glare_image, dni_w_m2: float | None, *, sun_factor: float = 1.0,
                 glare_factor: float = 1.0) -> dict:
    """The patent's camera route (module docstring): corneal irradiance, subtended angle and retinal
    irradiance of the glare source in *glare_image*, calibrated by *sun_image* and the DNI.

    *sun_factor*, *glare_factor*: each image's exposure times its filter's transmission (any unit, the same
    for both): the pixel values are divided by it.

    Raises
    ------
    ConfigError
        No DNI.
    CaptureError
        An overexposed sun (clipped pixels in its disc), no sun or no glare source found, or either cut off.
    """
    if dni_w_m2 is None or not (math.isfinite(dni_w_m2) and dni_w_m2 > 0):
        raise ConfigError("no DNI: the camera route scales the sun image's pixels to the direct normal irradiance "
                          "measured when it was taken (W/m^2); give it")
    sun = _grey(sun_image)
    disc, sun_sum, _ = _source(sun, "sun", "is the sun in the image, the filter not too dense?")
    refuse_clipped(sun_image, disc, "the sun image", "of its disc",
                   "use a denser neutral density filter or a shorter exposure")
    r_sun_px = math.sqrt(disc.sum() / math.pi)
    rad_per_px = SUN_HALF_ANGLE_RAD / r_sun_px           # the patent's Eq. (8), small angles
    glare = _grey(glare_image)
    src, glare_sum, _ = _source(glare, "glare source", "is the mirror's glint in view?")
    refuse_clipped(glare_image, src, "the glare image", "of the source", "use a denser filter or a shorter exposure")
    corneal = dni_w_m2 * (glare_sum / glare_factor) / (sun_sum / sun_factor)
    omega = 2.0 * math.sqrt(src.sum() / math.pi) * rad_per_px
    return {"corneal_w_m2": corneal, "omega_rad": omega, "retinal_w_m2": float(retinal_irradiance(corneal, omega)),
            "sun_radius_px": r_sun_px, "mrad_per_px": 1e3 * rad_per_px, "source_px": int(src.sum())}


#: Draws of the canting's Monte Carlo for the glare's U.
GLARE_DRAWS = 8


def observers_glare(models: list, ensemble, rotation: np.ndarray, origin_m, observers: list, sun: Sunlight,
                    reflectivity: float = 0.94, per_facet: int = 6000, draws: int = GLARE_DRAWS,
                    seed: int = 1) -> list:
    """Each observer's glare (:func:`facet_glare`) of the heliostat's measured facets, with U (k = 2) from
    *draws* draws of every facet's canting within its U (each axis a normal draw of U/2).

    Parameters
    ----------
    models : list of FacetModel
    ensemble : EnsembleDesign
    rotation, origin_m
        The heliostat frame in the field (heliostat -> field) and its origin.
    observers : list of (name, (3,) position)
    sun : Sunlight
    reflectivity, per_facet, draws, seed

    Returns
    -------
    list of dict
        Per observer: ``name``, ``position_m``, :func:`facet_glare`'s figures, ``corneal_w_m2_U``,
        ``omega_rad_U`` and ``retinal_w_m2_U`` (over the draws that saw glare; None without glare or with fewer
        than 3 such draws), ``glare_in_draws`` (the share of the draws that saw the sun's disc).
    """
    base = heliostat_samples(models, ensemble, rotation, origin_m, per_facet, seed)
    rng = np.random.default_rng([seed, 51])
    drawn = []
    for _ in range(draws):
        turned = [dataclasses.replace(m, canting_mrad=m.canting_mrad + 0.5 * m.canting_u_mrad * rng.standard_normal(2))
                  for m in models]
        drawn.append(heliostat_samples(turned, ensemble, rotation, origin_m, per_facet, seed))
    out = []
    for name, pos in observers:
        g = facet_glare(*base, pos, sun, reflectivity)
        runs = [facet_glare(*d, pos, sun, reflectivity) for d in drawn]
        seen = [r for r in runs if r["glare"]]
        u = {}
        for key in ("corneal_w_m2", "omega_rad", "retinal_w_m2"):
            if g["glare"] and len(seen) >= 3:
                u[f"{key}_U"] = 2.0 * float(np.sqrt(np.mean([(r[key] - g[key]) ** 2 for r in seen])))
            else:
                u[f"{key}_U"] = None
        out.append({"name": name, "position_m": list(pos), **g, **u,
                    "glare_in_draws": len(seen) / draws if draws else None})
    return out
