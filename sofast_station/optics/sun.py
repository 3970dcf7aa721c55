"""Sun shapes: the angular distribution of the sun's radiance about its centre, and samples from it.

Three shapes (docs/conventions.md, "Optics"):

``pillbox``
    Uniform over a disc of half-angle 4.65 mrad (the sun's mean angular radius).
``gaussian``
    A circular normal distribution with standard deviation ``sigma_mrad`` in each of two perpendicular
    directions (so the RMS angle from the centre is sqrt(2) sigma).
``buie``
    The circumsolar model of Buie, Monger and Dey, "Sunshape distributions for terrestrial solar
    simulations", Solar Energy 74 (2003): radiance phi(theta) = cos(0.326 theta) / cos(0.308 theta) inside
    the solar disc (theta <= 4.65 mrad) and exp(kappa) theta^gamma in the aureole out to 43.6 mrad, with
    kappa = 0.9 ln(13.5 chi) chi^-0.3 and gamma = 2.2 ln(0.52 chi) chi^0.43 - 0.1 for the circumsolar
    ratio chi (``csr``, 0 < chi < 1). As in the paper, chi is the model's parameter; the aureole's actual
    share of the power differs from it by a few per cent (:func:`buie_power_fraction_outside_disc`).

Angles are radians unless a name says mrad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The sun's mean angular radius, rad.
SUN_HALF_ANGLE_RAD = 4.65e-3
#: Where Buie's aureole ends, rad.
BUIE_OUTER_RAD = 43.6e-3

SHAPES = ("pillbox", "gaussian", "buie")


@dataclass(frozen=True)
class SunShape:
    """A sun shape (see the module docstring).

    Attributes
    ----------
    kind : str
        ``"pillbox"``, ``"gaussian"`` or ``"buie"``.
    sigma_mrad : float
        Standard deviation per direction of the Gaussian sun, mrad.
    csr : float
        Circumsolar ratio of the Buie sun, 0 < csr < 1.
    half_angle_mrad : float
        Half-angle of the pillbox sun, mrad.
    """

    kind: str = "pillbox"
    sigma_mrad: float = 2.51
    csr: float = 0.05
    half_angle_mrad: float = 1000.0 * SUN_HALF_ANGLE_RAD

    def __post_init__(self):
        if self.kind not in SHAPES:
            raise ValueError(f"sun shape must be one of {SHAPES}, got {self.kind!r}")
        if not (np.isfinite(self.sigma_mrad) and self.sigma_mrad > 0):
            raise ValueError(f"sun sigma_mrad must be a positive number of mrad, got {self.sigma_mrad}")
        if not (0.0 < self.csr < 1.0):
            raise ValueError(f"sun csr (circumsolar ratio) must lie between 0 and 1, got {self.csr}")
        if not (np.isfinite(self.half_angle_mrad) and self.half_angle_mrad > 0):
            raise ValueError(f"sun half_angle_mrad must be a positive number of mrad, got {self.half_angle_mrad}")

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """*n* ray directions about the sun's centre as (theta, phi): angle from the centre (rad) and azimuth.

        Deterministic for a given *rng* state.
        """
        phi = rng.random(n) * (2.0 * np.pi)
        u = rng.random(n)
        if self.kind == "pillbox":
            theta = (1e-3 * self.half_angle_mrad) * np.sqrt(u)
        elif self.kind == "gaussian":
            # Radial part of a circular normal: the Rayleigh distribution, by inversion.
            theta = (1e-3 * self.sigma_mrad) * np.sqrt(-2.0 * np.log1p(-u))
        else:
            grid, cdf = buie_radial_cdf(self.csr)
            theta = np.interp(u, cdf, grid)
        return theta, phi


def buie_radiance(theta_rad: np.ndarray, csr: float) -> np.ndarray:
    """Buie's relative radiance at *theta_rad* from the sun's centre (1 at the centre, 0 beyond 43.6 mrad)."""
    t = 1e3 * np.asarray(theta_rad, dtype=np.float64)                  # the model is written in mrad
    kappa = 0.9 * np.log(13.5 * csr) * csr ** -0.3
    gamma = 2.2 * np.log(0.52 * csr) * csr ** 0.43 - 0.1
    disc = np.cos(0.326 * t) / np.cos(0.308 * t)
    with np.errstate(divide="ignore"):
        aureole = np.exp(kappa) * np.maximum(t, 1e-12) ** gamma
    out = np.where(t <= 1e3 * SUN_HALF_ANGLE_RAD, disc, aureole)
    return np.where(t <= 1e3 * BUIE_OUTER_RAD, out, 0.0)


def buie_radial_cdf(csr: float, n: int = 4097) -> tuple[np.ndarray, np.ndarray]:
    """(theta in rad, cumulative power fraction) of the Buie sun, for sampling by inversion.

    The power within theta is the integral of phi(t) t dt (trapezoids on a grid that is fine inside the
    disc, where the radiance falls off, and carries the aureole's power-law tail).
    """
    inner = np.linspace(0.0, SUN_HALF_ANGLE_RAD, n // 2)
    outer = np.geomspace(SUN_HALF_ANGLE_RAD, BUIE_OUTER_RAD, n - n // 2 + 1)[1:]
    # Both sides of the disc's edge, where the radiance jumps down to the aureole.
    grid = np.concatenate([inner, [SUN_HALF_ANGLE_RAD * (1 + 1e-9)], outer])
    density = buie_radiance(grid, csr) * grid
    steps = 0.5 * (density[1:] + density[:-1]) * np.diff(grid)
    steps[n // 2 - 1] = 0.0                                             # the jump itself carries no power
    cdf = np.concatenate([[0.0], np.cumsum(steps)])
    return grid, cdf / cdf[-1]


def buie_power_fraction_outside_disc(csr: float) -> float:
    """The share of the Buie sun's power outside 4.65 mrad (the circumsolar ratio the profile really has)."""
    grid, cdf = buie_radial_cdf(csr)
    return float(1.0 - np.interp(SUN_HALF_ANGLE_RAD, grid, cdf))
