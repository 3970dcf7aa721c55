"""Contract acceptance of a population of facets from a sample (pure: numpy in, numpy out), and the
contract itself as station.toml states it (:func:`contract_from_config`, ``[acceptance.RECIPE]``).

Sample size
-----------
From the heliostat field performance testing guideline (Röger, Schlichting, Herrmann et al.,
"Developments towards the heliostat field performance testing guideline", Solar Energy, 2025), for a
property with estimated mean mu_e and standard deviation sigma_e (coefficient of variation
V_e = sigma_e / mu_e), a permitted relative error e* of the mean and a confidence with standard normal
deviate z (1.96 for 95 %):

- Eq. (4), drawing with replacement: n = z^2 V^2 / e*^2;
- Eq. (7), drawing without replacement from N_pop: n = (z^2 V^2 / e*^2) / ((1 - 1/N_pop) + z^2 V^2 / (e*^2 N_pop));
- Eq. (8), Slovin's approximation for N_pop > 100: n = (z^2 V^2 / e*^2) / (1 + z^2 V^2 / (e*^2 N_pop)).

Each is rounded up to a whole facet (the guideline's Tables 2 and 3 do so: 82 facets for slope
deviation at N_pop = 14,500, mu_e = 1.3 mrad, sigma_e = 0.3 mrad, e* = 5 %, 95 %).

Confidence interval of the observed mean
----------------------------------------
mean +- t(1 - alpha/2, n - 1) s / sqrt(n) sqrt((N_pop - n) / (N_pop - 1)), Student's t with the finite
population correction of the guideline's Eq. (5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConfigError, check_table


def z_for(confidence: float) -> float:
    """Two-sided standard normal deviate for *confidence* (0.95 -> 1.959964)."""
    # lazy: scipy.stats costs ~950 ms CPU; config.py loads this module to check [acceptance] at every start
    from scipy.stats import norm

    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be between 0 and 1 (e.g. 0.95), got {confidence}")
    return float(norm.ppf(0.5 + confidence / 2))


def sample_size(mean: float, std: float, relative_error: float, confidence: float = 0.95,
                population: int | None = None, equation: int = 7, z: float | None = None) -> int:
    """Guideline sample size (Eq. 4, 7 or 8), rounded up.

    Parameters
    ----------
    mean, std : float
        Estimated mean mu_e and standard deviation sigma_e of the property (same unit; mean not 0).
    relative_error : float
        Permitted relative error e* of the mean (0.05 for 5 %).
    confidence : float
        Two-sided confidence (0.95); ignored when *z* is given.
    population : int, optional
        N_pop, facets in the contract; needed by Eq. 7 and 8.
    equation : int
        4, 7 or 8.
    z : float, optional
        Standard normal deviate (the guideline uses z = 1.96 for 95 %).

    Returns
    -------
    int
        The minimum number of facets to measure (never more than *population*).
    """
    if not mean or not math.isfinite(mean):
        raise ValueError(f"the estimated mean must be a non-zero number, got {mean}")
    if not (std >= 0 and math.isfinite(std)):
        raise ValueError(f"the estimated standard deviation must be >= 0, got {std}")
    if not 0 < relative_error < 1:
        raise ValueError(f"relative_error must be between 0 and 1 (0.05 for 5 %), got {relative_error}")
    z = z_for(confidence) if z is None else float(z)
    n0 = z * z * (std / mean) ** 2 / relative_error ** 2
    if equation == 4:
        n = n0
    elif equation in (7, 8):
        if population is None or int(population) < 1:
            raise ValueError(f"Eq. {equation} needs the population size N_pop (a positive whole number)")
        npop = int(population)
        n = n0 / ((1 - 1 / npop) + n0 / npop) if equation == 7 else n0 / (1 + n0 / npop)
        n = min(n, npop)
    else:
        raise ValueError(f"equation must be 4, 7 or 8 (the guideline's), got {equation}")
    # rounding up; a hair of floating-point noise above a whole number is not a facet more
    return max(1, int(math.ceil(n - 1e-9)))


def mean_interval(x, confidence: float = 0.95, population: int | None = None) -> dict:
    """Observed mean of *x* with its two-sided confidence interval (Student's t, finite population).

    Returns
    -------
    dict
        ``n``, ``mean``, ``std`` (sample), ``half_width``, ``low``, ``high`` (None where undefined).
    """
    # lazy: scipy.stats costs ~950 ms CPU; config.py loads this module to check [acceptance] at every start
    from scipy.stats import t as student_t

    a = np.asarray(x, dtype=np.float64)
    a = a[np.isfinite(a)]
    n = int(a.size)
    out = {"n": n, "mean": None, "std": None, "half_width": None, "low": None, "high": None}
    if n == 0:
        return out
    mean = float(a.mean())
    out["mean"] = mean
    if n < 2:
        return out
    s = float(a.std(ddof=1))
    fpc = 1.0
    if population is not None and population > 1:
        fpc = math.sqrt(max(population - n, 0) / (population - 1))
    half = float(student_t.ppf(0.5 + confidence / 2, n - 1)) * s / math.sqrt(n) * fpc
    out.update(std=s, half_width=half, low=mean - half, high=mean + half)
    return out


def judge_mean(interval: dict, contract: float, tolerance: float, sense: str = "two_sided") -> tuple[str, str]:
    """Pass or fail of a figure's mean against its contract value and tolerance.

    Parameters
    ----------
    interval : dict
        From :func:`mean_interval`.
    contract, tolerance : float
        Contract value and its tolerance (same unit as the figure).
    sense : str
        ``"two_sided"`` (the mean must lie within contract +- tolerance, the whole confidence interval
        included) or ``"at_most"`` (the upper end of the interval must not exceed contract + tolerance:
        a slope deviation is better when smaller).

    Returns
    -------
    (str, str)
        ``"pass"``, ``"fail"`` or ``"undecided"`` (fewer than two facets), and why.
    """
    if interval.get("low") is None:
        return "undecided", f"{interval.get('n', 0)} facet(s): too few for a confidence interval"
    lo, hi = interval["low"], interval["high"]
    top = contract + tolerance
    if sense == "at_most":
        ok = hi <= top
        why = f"upper confidence bound {hi:.4g} {'<=' if ok else '>'} contract {contract:g} + {tolerance:g}"
    elif sense == "two_sided":
        bottom = contract - tolerance
        ok = lo >= bottom and hi <= top
        why = (f"confidence interval [{lo:.4g}, {hi:.4g}] {'within' if ok else 'not within'} "
               f"[{bottom:.4g}, {top:.4g}]")
    else:
        raise ValueError(f"sense must be 'two_sided' or 'at_most', got {sense!r}")
    return ("pass" if ok else "fail"), why


def fit_normal(x) -> dict:
    """Normal fit (maximum likelihood): ``mu``, ``sigma``."""
    a = np.asarray(x, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size < 2:
        raise ValueError(f"a normal fit needs at least 2 values, got {a.size}")
    return {"mu": float(a.mean()), "sigma": float(a.std(ddof=0))}


def fit_weibull(x) -> dict | None:
    """Two-parameter Weibull fit (maximum likelihood, location 0): ``shape`` k and ``scale`` lambda.

    None when the values are not all positive (a Weibull describes a positive quantity such as
    SD_2D,RMS; the guideline's Fig. 4 shows one with k = 2, a Rayleigh distribution).
    """
    # lazy: scipy.stats costs ~950 ms CPU; config.py loads this module to check [acceptance] at every start
    from scipy.stats import weibull_min

    a = np.asarray(x, dtype=np.float64)
    a = a[np.isfinite(a)]
    if a.size < 3 or np.any(a <= 0) or np.ptp(a) == 0:
        return None
    k, _, lam = weibull_min.fit(a, floc=0.0)
    return {"shape": float(k), "scale": float(lam)}


# ------------------------------------------------------------------------------- the contract
_KEYS = {"population", "confidence", "relative_error", "figures"}
_FIGURE_KEYS = {"name", "contract", "tolerance", "expected_mean", "expected_std", "sense", "relative_error"}


@dataclass
class ContractFigure:
    key: str
    name: str
    contract: float
    tolerance: float
    expected_std: float
    expected_mean: float
    sense: str = "two_sided"
    relative_error: float | None = None


@dataclass
class Contract:
    recipe: str
    population: int
    confidence: float
    relative_error: float
    figures: list = field(default_factory=list)


def _number(table: dict, key: str, where: str, positive: bool = False) -> float:
    v = table.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise ConfigError(f"{where}: {key} = {v!r} must be a{' positive' if positive else ''} number")
    return float(v)


def contract_from_config(config, recipe: str) -> Contract:
    """The ``[acceptance.RECIPE]`` table of station.toml, validated (messages name file, table, key)."""
    tables = config.raw.get("acceptance", {})
    where = f"{config.path} [acceptance.{recipe}]"
    if recipe not in tables:
        raise ConfigError(f"{config.path} has no [acceptance.{recipe}] table: add the contract's population, "
                          f"confidence, relative_error and figures (docs/quality.md)"
                          + (f"; tables present: {', '.join(sorted(tables))}" if tables else ""))
    t = check_table(tables[recipe], _KEYS, where)
    population = t.get("population")
    if isinstance(population, bool) or not isinstance(population, int) or population < 1:
        raise ConfigError(f"{where}: population = {population!r} must be a whole number of facets >= 1")
    confidence = _number(t, "confidence", where) if "confidence" in t else 0.95
    if not 0 < confidence < 1:
        raise ConfigError(f"{where}: confidence = {confidence} must lie between 0 and 1 (e.g. 0.95)")
    rel = _number(t, "relative_error", where) if "relative_error" in t else 0.05
    if not 0 < rel < 1:
        raise ConfigError(f"{where}: relative_error = {rel} must lie between 0 and 1 (0.05 for 5 %)")
    figs = t.get("figures")
    if not isinstance(figs, dict) or not figs:
        raise ConfigError(f"{where}: figures must be a table of at least one figure, e.g. "
                          f"[acceptance.{recipe}.figures.\"slope_rms_mrad.design.magnitude\"]")
    out = []
    for key, f in figs.items():
        fw = f"{where} figures.{key}"
        check_table(f, _FIGURE_KEYS, fw)
        contract = _number(f, "contract", fw)
        sense = f.get("sense", "two_sided")
        if sense not in ("two_sided", "at_most"):
            raise ConfigError(f"{fw}: sense = {sense!r} must be 'two_sided' or 'at_most'")
        out.append(ContractFigure(key, str(f.get("name", key)), contract, _number(f, "tolerance", fw, True),
                                  _number(f, "expected_std", fw, True),
                                  _number(f, "expected_mean", fw) if "expected_mean" in f else contract, sense,
                                  _number(f, "relative_error", fw) if "relative_error" in f else None))
    return Contract(recipe, population, confidence, rel, out)
