"""Statistical process control for one figure measured facet after facet (pure: numpy in, numpy out).

Individuals chart
-----------------
Each facet is one observation x_i. The centre line and sigma come from a *baseline* period judged to be
in control: centre = mean of the baseline, sigma = MR-bar / d2 with MR-bar the mean moving range
|x_i - x_(i-1)| of the baseline and d2 = 1.128 (the within-process sigma of an individuals chart;
Montgomery, *Introduction to Statistical Quality Control*, 2009, sec. 6.4). Control limits are
centre +- 3 sigma; the moving-range chart's upper limit is D4 * MR-bar with D4 = 3.267.

Run rules
---------
A rule is satisfied at point i when the window of points ending at i meets it; z = (x - centre) / sigma.

Western Electric (*Statistical Quality Control Handbook*, 1956), ``"western_electric"``:

- ``WE1`` one point beyond 3 sigma;
- ``WE2`` two of three consecutive points beyond 2 sigma on the same side;
- ``WE3`` four of five consecutive points beyond 1 sigma on the same side;
- ``WE4`` eight consecutive points on the same side of the centre line.

Nelson (*Journal of Quality Technology* 16, 1984), ``"nelson"``: ``N1`` beyond 3 sigma; ``N2`` nine in a
row on one side; ``N3`` six in a row steadily increasing or decreasing; ``N4`` fourteen in a row
alternating up and down; ``N5`` two of three beyond 2 sigma, same side; ``N6`` four of five beyond 1
sigma, same side; ``N7`` fifteen in a row within 1 sigma; ``N8`` eight in a row with none within 1 sigma.

At the start of a series (or after a restart) the "k of n" rules count over the points there are; the
"in a row" rules need their full run.

Alarm rates
-----------
With normal, independent, in-control data, rule WE1 alone signals on average once in 370.4 points, the
four Western Electric rules together once in 91.75 (Champ and Woodall, *Technometrics* 29, 1987): that is
the nominal false-alarm rate, 1.09 % of the facets. :func:`average_run_length` estimates the average run
length of any rule set for a step of the mean by simulation; :func:`signals` counts alarms the way the
line raises them (after an alarm the rules start afresh).

EWMA
----
z_i = lambda x_i + (1 - lambda) z_(i-1), z_0 = centre; limits centre +- L sigma
sqrt(lambda / (2 - lambda) (1 - (1 - lambda)^(2 i))) (Montgomery, sec. 9.2). lambda = 0.2, L = 3 by default
(in-control ARL about 560, a 1-sigma step found after about 10 points).

Capability
----------
Cp = (USL - LSL) / (6 sigma), Cpk = min(USL - mean, mean - LSL) / (3 sigma) with the within sigma (MR-bar /
d2); Pp, Ppk the same with the sample standard deviation. With one limit only, Cp and Pp are undefined
(None) and Cpk, Ppk use that limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Bias constants of the moving range of two observations (Montgomery, Appendix VI).
D2 = 1.128
D4 = 3.267

#: The rule sets: name -> the rules it applies.
RULE_SETS = {
    "western_electric": ("WE1", "WE2", "WE3", "WE4"),
    "nelson": ("N1", "N2", "N3", "N4", "N5", "N6", "N7", "N8"),
    "beyond_limits": ("WE1",),
}

#: What each rule means, for legends and alarm messages.
RULE_TEXT = {
    "WE1": "one point beyond 3 sigma", "WE2": "2 of 3 beyond 2 sigma on one side",
    "WE3": "4 of 5 beyond 1 sigma on one side", "WE4": "8 in a row on one side of the centre",
    "N1": "one point beyond 3 sigma", "N2": "9 in a row on one side of the centre",
    "N3": "6 in a row steadily rising or falling", "N4": "14 in a row alternating up and down",
    "N5": "2 of 3 beyond 2 sigma on one side", "N6": "4 of 5 beyond 1 sigma on one side",
    "N7": "15 in a row within 1 sigma", "N8": "8 in a row with none within 1 sigma",
}

#: Published in-control average run lengths (Champ and Woodall 1987) of the rule sets.
NOMINAL_ARL0 = {"western_electric": 91.75, "beyond_limits": 370.4}


@dataclass(frozen=True)
class Baseline:
    """Centre and within sigma of a figure, from an in-control period.

    Attributes
    ----------
    centre : float
        Mean of the baseline observations (same unit as the figure).
    sigma : float
        MR-bar / d2 (same unit).
    mr_bar : float
        Mean moving range.
    n : int
        Number of baseline observations.
    """

    centre: float
    sigma: float
    mr_bar: float
    n: int

    @property
    def ucl(self) -> float:
        return self.centre + 3.0 * self.sigma

    @property
    def lcl(self) -> float:
        return self.centre - 3.0 * self.sigma

    @property
    def mr_ucl(self) -> float:
        return D4 * self.mr_bar

    def to_dict(self) -> dict:
        return {"centre": self.centre, "sigma": self.sigma, "mr_bar": self.mr_bar, "n": self.n}

    @classmethod
    def from_dict(cls, d: dict) -> "Baseline":
        return cls(float(d["centre"]), float(d["sigma"]), float(d["mr_bar"]), int(d["n"]))


def _finite_1d(x, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {a.shape}")
    return a


def moving_range(x) -> np.ndarray:
    """|x_i - x_(i-1)| for i >= 1, with NaN first (same length as *x*)."""
    a = _finite_1d(x, "x")
    out = np.full(a.shape, np.nan)
    out[1:] = np.abs(np.diff(a))
    return out


def baseline(x) -> Baseline:
    """Centre and within sigma (MR-bar / d2) of in-control observations *x* (NaN ignored).

    Raises
    ------
    ValueError
        With fewer than two finite observations, or no variation at all.
    """
    a = _finite_1d(x, "x")
    a = a[np.isfinite(a)]
    if a.size < 2:
        raise ValueError(f"a baseline needs at least 2 observations, got {a.size}")
    mr_bar = float(np.mean(np.abs(np.diff(a))))
    if not mr_bar > 0:
        raise ValueError("the baseline observations do not vary (moving range 0): no sigma to set limits")
    return Baseline(float(np.mean(a)), mr_bar / D2, mr_bar, int(a.size))


# -- rules ------------------------------------------------------------------------------------------
def _windows(v: np.ndarray, w: int, fill) -> np.ndarray:
    """(..., T, w) sliding windows ending at each point, padded at the start with *fill*."""
    pad = np.full(v.shape[:-1] + (w - 1,), fill, dtype=v.dtype)
    return np.lib.stride_tricks.sliding_window_view(np.concatenate([pad, v], axis=-1), w, axis=-1)


def _k_of_n_same_side(z: np.ndarray, k: int, n: int, level: float) -> np.ndarray:
    up = _windows((z > level).astype(np.int8), n, 0).sum(-1) >= k
    down = _windows((z < -level).astype(np.int8), n, 0).sum(-1) >= k
    return (up | down) & np.isfinite(z)


def _run(cond: np.ndarray, n: int) -> np.ndarray:
    return _windows(cond, n, False).all(-1)


def rule_conditions(z, rules=RULE_SETS["western_electric"]) -> dict[str, np.ndarray]:
    """Where each rule is met, for standardised observations.

    Parameters
    ----------
    z : array (..., T)
        (x - centre) / sigma along the last axis; NaN (a facet without the figure) meets no rule and
        breaks runs.
    rules : sequence of str
        Rule names (:data:`RULE_TEXT`).

    Returns
    -------
    dict
        Rule -> bool array (..., T): True at i when the window ending at i meets the rule.
    """
    z = np.asarray(z, dtype=np.float64)
    fin = np.isfinite(z)
    out = {}
    for r in rules:
        if r in ("WE1", "N1"):
            c = np.abs(np.where(fin, z, 0.0)) > 3.0
        elif r in ("WE2", "N5"):
            c = _k_of_n_same_side(z, 2, 3, 2.0)
        elif r in ("WE3", "N6"):
            c = _k_of_n_same_side(z, 4, 5, 1.0)
        elif r in ("WE4", "N2"):
            n = 8 if r == "WE4" else 9
            c = _run(fin & (z > 0), n) | _run(fin & (z < 0), n)
        elif r == "N3":
            d = np.diff(z, axis=-1, prepend=np.nan)
            c = _run(np.isfinite(d) & (d > 0), 5) | _run(np.isfinite(d) & (d < 0), 5)
        elif r == "N4":
            d = np.diff(z, axis=-1, prepend=np.nan)
            alt = np.isfinite(d) & np.isfinite(np.roll(d, 1, axis=-1)) & (d * np.roll(d, 1, axis=-1) < 0)
            alt[..., :2] = False
            c = _run(alt, 12)          # 13 alternating differences need 12 sign changes: 14 points
        elif r == "N7":
            c = _run(fin & (np.abs(np.where(fin, z, 0.0)) < 1.0), 15)
        elif r == "N8":
            c = _run(fin & (np.abs(np.where(fin, z, 0.0)) > 1.0), 8)
        else:
            raise ValueError(f"unknown rule {r!r}; known: {', '.join(RULE_TEXT)}")
        out[r] = c
    return out


def rules_of(rule_set) -> tuple[str, ...]:
    """The rules of a named set (``western_electric``, ``nelson``, ``beyond_limits``) or a list of rules."""
    if isinstance(rule_set, str):
        if rule_set not in RULE_SETS:
            raise ValueError(f"unknown rule set {rule_set!r}; known: {', '.join(RULE_SETS)}")
        return RULE_SETS[rule_set]
    rules = tuple(rule_set)
    for r in rules:
        if r not in RULE_TEXT:
            raise ValueError(f"unknown rule {r!r}; known: {', '.join(RULE_TEXT)}")
    return rules


def violations(x, base: Baseline, rule_set="western_electric") -> dict[str, np.ndarray]:
    """Every point where a rule is met (what a control chart marks), rule -> indices into *x*."""
    z = (_finite_1d(x, "x") - base.centre) / base.sigma
    return {r: np.flatnonzero(c) for r, c in rule_conditions(z, rules_of(rule_set)).items()}


def signals(x, base: Baseline, rule_set="western_electric") -> list[tuple[int, tuple[str, ...]]]:
    """The alarms a line raises on *x* in order: after each alarm the rules start afresh.

    Returns
    -------
    list of (index, rules)
        The index of each alarming point and the rules it met.
    """
    z = (_finite_1d(x, "x") - base.centre) / base.sigma
    rules = rules_of(rule_set)
    out = []
    start = 0
    while start < z.size:
        cond = rule_conditions(z[start:], rules)
        hit = np.zeros(z.size - start, dtype=bool)
        for c in cond.values():
            hit |= c
        idx = np.flatnonzero(hit)
        if idx.size == 0:
            break
        i = int(idx[0])
        out.append((start + i, tuple(r for r, c in cond.items() if c[i])))
        start += i + 1
    return out


def alarm_at_last(x, base: Baseline, rule_set="western_electric") -> tuple[str, ...]:
    """The rules met by the last point of *x* (the newest facet): the line's drift check.

    *x* holds the recent observations since the previous alarm (so the rules start afresh after one).
    """
    z = (_finite_1d(x, "x") - base.centre) / base.sigma
    if z.size == 0:
        return ()
    return tuple(r for r, c in rule_conditions(z, rules_of(rule_set)).items() if c[-1])


def average_run_length(shift_sigma: float, rule_set="western_electric", *, runs: int = 2000,
                       length: int = 4000, rng: np.random.Generator | None = None) -> tuple[float, float]:
    """Average number of points until the first alarm, for a step of the mean by *shift_sigma* sigmas
    present from the first point (normal, independent observations, known centre and sigma).

    Parameters
    ----------
    shift_sigma : float
        Step of the mean, in sigmas (0: in control).
    rule_set : str or sequence of str
    runs : int
        Simulated series.
    length : int
        Points per series; a series without an alarm counts as *length* (a bias only if the ARL
        approaches it).
    rng : numpy.random.Generator, optional
        Seeded generator (reproducible); a fresh default_rng(0) when None.

    Returns
    -------
    (float, float)
        The ARL and its standard error.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    rules = rules_of(rule_set)
    first = np.empty(runs)
    chunk = max(1, 2_000_000 // length)
    for s in range(0, runs, chunk):
        z = rng.standard_normal((min(chunk, runs - s), length)) + float(shift_sigma)
        hit = np.zeros(z.shape, dtype=bool)
        for c in rule_conditions(z, rules).values():
            hit |= c
        any_hit = hit.any(-1)
        first[s:s + z.shape[0]] = np.where(any_hit, hit.argmax(-1) + 1, length)
    return float(first.mean()), float(first.std(ddof=1) / math.sqrt(runs))


# -- EWMA -------------------------------------------------------------------------------------------
def ewma(x, centre: float, lam: float = 0.2) -> np.ndarray:
    """The EWMA statistic z_i of *x* started at *centre*; a NaN observation carries z over."""
    if not 0 < lam <= 1:
        raise ValueError(f"lam must be in (0, 1], got {lam}")
    a = _finite_1d(x, "x")
    out = np.empty_like(a)
    z = float(centre)
    for i, v in enumerate(a):
        if math.isfinite(v):
            z = lam * v + (1 - lam) * z
        out[i] = z
    return out


def ewma_limits(n: int, base: Baseline, lam: float = 0.2, width: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper EWMA control limits for points 1..n (time-varying, then steady)."""
    i = np.arange(1, n + 1)
    half = width * base.sigma * np.sqrt(lam / (2 - lam) * (1 - (1 - lam) ** (2 * i)))
    return base.centre - half, base.centre + half


def ewma_violations(x, base: Baseline, lam: float = 0.2, width: float = 3.0) -> np.ndarray:
    """Indices where the EWMA leaves its limits."""
    z = ewma(x, base.centre, lam)
    lo, hi = ewma_limits(z.size, base, lam, width)
    return np.flatnonzero((z < lo) | (z > hi))


# -- capability -------------------------------------------------------------------------------------
def capability(x, lsl: float | None, usl: float | None, sigma_within: float | None = None) -> dict:
    """Cp, Cpk (within sigma) and Pp, Ppk (overall sample standard deviation) against spec limits.

    Parameters
    ----------
    x : array
        Observations (NaN ignored).
    lsl, usl : float or None
        Specification limits, same unit; None for a one-sided specification.
    sigma_within : float, optional
        Within sigma (a baseline's MR-bar / d2); from *x* itself when None.

    Returns
    -------
    dict
        ``n``, ``mean``, ``sigma_within``, ``sigma_overall``, ``cp``, ``cpk``, ``pp``, ``ppk`` (None where
        undefined).
    """
    a = _finite_1d(x, "x")
    a = a[np.isfinite(a)]
    if lsl is None and usl is None:
        raise ValueError("capability needs at least one specification limit")
    if lsl is not None and usl is not None and not usl > lsl:
        raise ValueError(f"the upper specification limit {usl} must exceed the lower {lsl}")
    out = {"n": int(a.size), "mean": None, "sigma_within": None, "sigma_overall": None,
           "cp": None, "cpk": None, "pp": None, "ppk": None}
    if a.size < 2:
        return out
    mean = float(np.mean(a))
    s_within = float(sigma_within) if sigma_within is not None else float(np.mean(np.abs(np.diff(a)))) / D2
    s_overall = float(np.std(a, ddof=1))
    out.update(mean=mean, sigma_within=s_within, sigma_overall=s_overall)

    def pair(s):
        if not s > 0:
            return None, None
        cp = (usl - lsl) / (6 * s) if lsl is not None and usl is not None else None
        sides = [v for v in ((usl - mean) / (3 * s) if usl is not None else None,
                             (mean - lsl) / (3 * s) if lsl is not None else None) if v is not None]
        return cp, min(sides)

    out["cp"], out["cpk"] = pair(s_within)
    out["pp"], out["ppk"] = pair(s_overall)
    return out
