"""Where a focal length means something: f = 1/kappa, shown as ``value ± U`` only where that U is linear.

A facet's focal length is the inverse of its focal power (curvature) kappa. The budget propagates kappa's
uncertainty to f linearly, U(f) = U(kappa) / kappa^2, which holds while U(kappa) is a small fraction of kappa.
On a nearly flat facet (f of hundreds of metres) it is not: kappa = 1/600 /m measured to +-0.00045 /m maps
to f between 415 and 662 m, not 510 +- 120 m; and where kappa's interval holds 0 the facet is flat within its
U and f is unbounded (beyond +415 m or beyond -2200 m). The exact interval is kappa's mapped through 1/kappa,
which is monotonic on each side of 0, so it covers the truth exactly as often as kappa's U does: the
curvature is what such a facet is judged on (:mod:`.verdict`, beyond 20 m), the interval is how its f is
written (:func:`~sofast_station.result.formatting.figure_text`, the record's ``focal_length_x_m_interval``).

Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math

#: f is written ``value ± U`` while kappa's U is at most this fraction of |kappa|: then the linear U is
#: within 11 % of the exact interval's longer side (1 / (1 - r) - 1 at r = 0.1) and within 9 % of its shorter
#: one; beyond it the interval is written instead.
LINEAR_FRACTION = 0.1


def focal_length_interval(kappa_per_m, u_kappa_per_m) -> list[float] | None:
    """The interval of f = 1/kappa (metres) that kappa ± U (k = 2) maps to.

    Parameters
    ----------
    kappa_per_m, u_kappa_per_m : float or None
        The focal power (1/m) and its expanded uncertainty (1/m).

    Returns
    -------
    [lo, hi] or None
        With lo <= hi (same sign) when kappa's interval excludes 0: f lies in [lo, hi]. With lo > 0 > hi when
        it holds 0 (flat within U): f >= lo or f <= hi, the interval through infinity (either may be None
        when kappa's interval ends exactly at 0). None without kappa or its U.
    """
    if not _number(kappa_per_m) or not _number(u_kappa_per_m) or u_kappa_per_m < 0:
        return None
    k, u = float(kappa_per_m), float(u_kappa_per_m)
    low, high = k - u, k + u
    if low > 0 or high < 0:
        a, b = 1.0 / high, 1.0 / low
        return [min(a, b), max(a, b)]
    return [1.0 / high if high > 0 else None, 1.0 / low if low < 0 else None]


def is_linear(kappa_per_m, u_kappa_per_m, fraction: float = LINEAR_FRACTION) -> bool:
    """Whether f's linear U stands for its interval: kappa's U at most *fraction* of |kappa| (True without a
    U: then there is nothing to map)."""
    if not _number(kappa_per_m) or not _number(u_kappa_per_m):
        return True
    return float(u_kappa_per_m) <= fraction * abs(float(kappa_per_m))


def interval_decimals(interval: list) -> int:
    """Decimals that give the interval's nearer end three significant digits (0 from 100 m on)."""
    ends = [abs(v) for v in interval if v is not None and v != 0]
    return max(0, 2 - math.floor(math.log10(min(ends)))) if ends else 0


def interval_text(interval: list, unit: str = "", *, compact: bool = False) -> str:
    """*interval* (:func:`focal_length_interval`) in words: ``415 to 662 m``, or for a facet flat within its U
    ``>= 415 or <= -2200 m (flat within U)``; *compact* (a table's cell): ``415..662``, ``>=415|<=-2200``."""
    d = interval_decimals(interval)
    lo, hi = interval
    if lo is not None and hi is not None and lo <= hi:
        return f"{lo:.{d}f}..{hi:.{d}f}" if compact else f"{lo:.{d}f} to {hi:.{d}f}{unit}"
    sides = ([f">={lo:.{d}f}" if compact else f">= {lo:.{d}f}"] if lo is not None else []) \
        + ([f"<={hi:.{d}f}" if compact else f"<= {hi:.{d}f}"] if hi is not None else [])
    if compact:
        return "|".join(sides) or "flat"
    return f"{' or '.join(sides) or 'any'}{unit} (flat within U)"


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
