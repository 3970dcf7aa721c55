"""A simulated production line's facets: each one drawn from a population around the nominal facet.

``[simulation.population]`` in station.toml describes how the facets of a simulated line differ from one
another: part-to-part variation of the focal lengths, the twist and the slope error, an occasional
defect (a dent), and a slow drift of the focal lengths over the shift (a press warming up). Facet ``k``
of a run (k = 0, 1, ...) is drawn from the generator seeded with ``(seed, k)``: the same seed gives the
same line, facet by facet, whatever else the run does. The nominal facet is ``[simulation.facet]``; the
placement in the fixture is not varied.

Pure: a record and its draw, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .parameters import TrueFacet, _check_keys, _number
from .outline import inside_outline


def _range(owner: str, key: str, value, low: float) -> tuple[float, float]:
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ConfigError(f"{owner}.{key} must be a list [smallest, largest], got {value!r}")
    a, b = (_number(owner, f"{key}[{i}]", v) for i, v in enumerate(value))
    if not low <= a <= b:
        raise ConfigError(f"{owner}.{key} = {list(value)!r}: needs {low:g} <= smallest <= largest")
    return a, b


@dataclass(frozen=True)
class FacetPopulation:
    """How the facets of a simulated line differ from the nominal facet (``[simulation.facet]``).

    Parameters
    ----------
    seed : int
        Facet k of a run is drawn from ``numpy.random.default_rng([seed, k])``.
    focal_length_sd : float
        Part-to-part standard deviation of f_x and f_y, each drawn on its own, relative (0.001: 0.1 %).
    twist_sd_mrad_per_m : float
        Part-to-part standard deviation of the twist, mrad/m.
    slope_error_sd_mrad : float
        Part-to-part standard deviation of the random slope error's RMS, mrad (drawn values below 0 are 0);
        every facet's random surface has a seed of its own.
    defect_rate : float
        Probability that a facet carries a dent, 0 to 1.
    defect_depth_mm, defect_radius_mm : [smallest, largest]
        A dent's depth and radius (Gaussian standard deviation), drawn uniformly, millimetres; it sits
        anywhere inside the outline, at least three radii from its edge where the facet allows.
    drift_focal_length_per_100 : float
        The focal lengths' mean moves by this fraction per 100 facets (0.001: +0.1 % after 100 facets).
    """

    seed: int = 0
    focal_length_sd: float = 0.0
    twist_sd_mrad_per_m: float = 0.0
    slope_error_sd_mrad: float = 0.0
    defect_rate: float = 0.0
    defect_depth_mm: tuple[float, float] = (0.05, 0.2)
    defect_radius_mm: tuple[float, float] = (20.0, 40.0)
    drift_focal_length_per_100: float = 0.0

    def __post_init__(self):
        owner = "FacetPopulation"
        seed = self.seed
        if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or seed < 0:
            raise ConfigError(f"{owner}.seed must be a whole number >= 0, got {seed!r}")
        for key, high in (("focal_length_sd", 0.1), ("twist_sd_mrad_per_m", 100.0), ("slope_error_sd_mrad", 100.0),
                          ("defect_rate", 1.0)):
            value = _number(owner, key, getattr(self, key))
            if not 0.0 <= value <= high:
                raise ConfigError(f"{owner}.{key} = {value!r} must lie in [0, {high:g}]")
            object.__setattr__(self, key, value)
        drift = _number(owner, "drift_focal_length_per_100", self.drift_focal_length_per_100)
        if not -0.1 <= drift <= 0.1:
            raise ConfigError(f"{owner}.drift_focal_length_per_100 = {drift!r} must lie in [-0.1, 0.1] (a fraction of "
                              "the focal length per 100 facets; 0.001 is +0.1 %)")
        object.__setattr__(self, "drift_focal_length_per_100", drift)
        object.__setattr__(self, "defect_depth_mm", _range(owner, "defect_depth_mm", self.defect_depth_mm, 0.0))
        object.__setattr__(self, "defect_radius_mm", _range(owner, "defect_radius_mm", self.defect_radius_mm, 1e-3))

    @classmethod
    def from_dict(cls, d: dict) -> "FacetPopulation":
        """Build from plain data; unknown keys raise ConfigError naming the key."""
        _check_keys("FacetPopulation", d, cls)
        return cls(**d)

    def draw(self, nominal: TrueFacet, index: int, design) -> TrueFacet:
        """Facet *index* (0 for the first of a run) of the line whose nominal facet is *nominal*.

        Parameters
        ----------
        nominal : TrueFacet
            ``[simulation.facet]``; its focal lengths (the design's when None), twist and slope error are
            the population's centre at facet 0.
        index : int
            The facet's place in the run (drift and seed).
        design : FacetDesign
            Its focal length stands in for a nominal None; its outline bounds where a dent may sit.
        """
        if isinstance(index, bool) or not isinstance(index, numbers.Integral) or index < 0:
            raise ValueError(f"a facet's index must be a whole number >= 0, got {index!r}")
        rng = np.random.default_rng([int(self.seed), int(index)])
        drift = 1.0 + self.drift_focal_length_per_100 * index / 100.0
        focal = []
        for f in (nominal.focal_length_x_m, nominal.focal_length_y_m):
            f = float(design.focal_length_m) if f is None else float(f)
            z = rng.standard_normal()
            focal.append(f * (drift + self.focal_length_sd * z) if math.isfinite(f) else f)
        twist = nominal.twist_mrad_per_m + self.twist_sd_mrad_per_m * rng.standard_normal()
        slope = max(0.0, nominal.slope_error_rms_mrad + self.slope_error_sd_mrad * rng.standard_normal())
        dents = list(nominal.dents)
        if rng.random() < self.defect_rate:
            dents.append(self._dent(rng, design.outline_m))
        return dataclasses.replace(nominal, focal_length_x_m=focal[0], focal_length_y_m=focal[1],
                                   twist_mrad_per_m=float(twist), slope_error_rms_mrad=float(slope),
                                   surface_seed=int(nominal.surface_seed) + 1 + int(index), dents=tuple(dents))

    def _dent(self, rng: np.random.Generator, outline_m: np.ndarray) -> dict:
        depth = 1e-3 * rng.uniform(*self.defect_depth_mm)
        radius = 1e-3 * rng.uniform(*self.defect_radius_mm)
        lo, hi = outline_m.min(axis=0), outline_m.max(axis=0)
        inner_lo, inner_hi = lo + 3.0 * radius, hi - 3.0 * radius
        if np.any(inner_hi <= inner_lo):             # a facet smaller than the dent: anywhere on it
            inner_lo, inner_hi = lo, hi
        for _ in range(1000):
            x, y = rng.uniform(inner_lo, inner_hi)
            if inside_outline(np.array([x]), np.array([y]), outline_m)[0]:
                break
        return {"x_m": float(x), "y_m": float(y), "depth_m": float(-depth), "radius_m": float(radius)}
