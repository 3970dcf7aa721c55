"""How a value with its expanded uncertainty is written, everywhere one is shown: ``5.4183 ± 0.0021 m``.

GUM 7.2.6: the uncertainty is given to (at most) two significant digits, and the value is rounded to the
same decimal place. Every place that shows a figure with its U (the station's console and ``inspect``,
``import-opencsp``, the line's page, ``reprocess``, the flux text, the map titles, the certificate) goes
through :func:`with_u`, so one figure reads the same wherever it is shown. A value without U keeps the
number of decimals its caller chose for it. :func:`budget_text` writes the uncertainty budget as a table.
"""

from __future__ import annotations

import math

#: More decimals than this are never shown (a U of 1e-13 is a number's rounding, not a measurement's).
MAX_DECIMALS = 12


def u_decimals(u) -> int | None:
    """The decimal place that shows *u* to two significant digits (GUM 7.2.6): 4 for 0.00213 (0.0021), 1 for
    1.564 (1.6), -1 for 156 (160); None when *u* is missing, not finite or not positive.

    A U that rounds up to the next power of ten (0.0996 -> 0.100) is shown one place shorter (0.10).
    """
    if u is None or isinstance(u, bool) or not isinstance(u, (int, float)) or not math.isfinite(u) or u <= 0:
        return None
    d = 1 - math.floor(math.log10(u))
    if round(u * 10.0 ** d) >= 100:
        d -= 1
    return min(d, MAX_DECIMALS)


def _fixed(v: float, decimals: int, sign: bool = False) -> str:
    """*v* rounded to *decimals* places (negative: to tens, hundreds...), no exponent."""
    if decimals < 0:
        v = round(v, decimals)
        decimals = 0
    return f"{v:{'+' if sign else ''}.{decimals}f}"


def value_and_u(value, u, decimals: int = 4, *, scale: float = 1.0, sign: bool = False) -> tuple[str, str | None]:
    """The value and its U as text, by GUM's rule (:func:`u_decimals`); the value alone to *decimals* places,
    and None for U, when *u* is missing or not positive. *scale* multiplies both (units: 1000 for m -> mm);
    *sign* writes the value's sign always (``+0.123``)."""
    v = float(value) * scale
    big_u = None if u is None else float(u) * abs(scale)
    d = u_decimals(big_u)
    if not math.isfinite(v):
        return str(v), None if d is None else _fixed(big_u, d)
    if d is None:
        return _fixed(v, decimals, sign), None
    return _fixed(v, d, sign), _fixed(big_u, d)


def with_u(value, u=None, unit: str = "", decimals: int = 4, *, scale: float = 1.0, sign: bool = False,
           missing: str = "-") -> str:
    """``value ± U unit`` (GUM 7.2.6: U to two significant digits, the value to the same place), or
    ``value unit`` to *decimals* places without a U; *missing* when there is no value.

    Parameters
    ----------
    value : float or None
    u : float or None
        The expanded uncertainty (k = 2 throughout this station), in *value*'s unit.
    unit : str
        Appended as it is (give it its leading space: ``" m"``).
    decimals : int
        Places of a value shown without U.
    scale : float
        Multiplies value and U before they are written (1000.0 to show metres as millimetres).
    sign : bool
        Always write the value's sign.
    missing : str
        What a missing value (None) is written as.
    """
    if value is None or isinstance(value, bool):
        return missing
    v, big_u = value_and_u(value, u, decimals, scale=scale, sign=sign)
    return f"{v}{unit}" if big_u is None else f"{v} ± {big_u}{unit}"


def shown_decimals(value, u, decimals: int = 4) -> int:
    """The decimals :func:`with_u` shows *value* with (for a column beside it, the truth say, to match)."""
    d = u_decimals(u)
    return decimals if d is None or value is None else max(d, 0)


#: Figures shown as columns of ``inspect --budget`` (the record's budget has every scalar figure).
BUDGET_COLUMNS = (("focal_length_x_m", "f x", "m"), ("focal_length_y_m", "f y", "m"),
                  ("twist_mrad_per_m", "twist", "mrad/m"),
                  ("slope_rms_mrad.design.magnitude", "RMS design", "mrad"),
                  ("slope_rms_mrad.parabola.magnitude", "RMS parab.", "mrad"),
                  ("boresight_mrad.x", "bore x", "mrad"), ("optical_tilt_mrad.x", "tilt x", "mrad"),
                  ("placement.mm.0", "place x", "mm"), ("placement.mrad.2", "place rz", "mrad"))


def budget_text(rec: dict, columns=BUDGET_COLUMNS) -> str:
    """The uncertainty budget as one table: input groups against figures, standard-uncertainty
    contributions (k = 1), then the combined standard and expanded uncertainties."""
    b = rec.get("uncertainty_budget")
    if not b:
        return "no uncertainty budget in this record"
    names = b["figures"]
    cols = [(names.index(key), title, unit) for key, title, unit in columns if key in names]

    def cell(v):
        return f"{'-' if v is None else format(v, '.2e'):>11}"

    lines = ["Uncertainty budget: standard-uncertainty contribution of each input to each figure (k=1), "
             "combined per GUM",
             f"  {'input':<30}{'':>10}" + "".join(f"{t:>11}" for _, t, _ in cols),
             f"  {'':<30}{'':>10}" + "".join(f"{u:>11}" for _, _, u in cols)]
    for row in b["rows"]:
        lines.append(f"  {row['group']:<30}{row['kind']:>10}"
                     + "".join(cell(row["contributions"][i]) for i, _, _ in cols))
    lines.append(f"  {'combined standard u':<30}{'':>10}"
                 + "".join(cell(b["combined_standard"][i]) for i, _, _ in cols))
    lines.append(f"  {'  of which random':<30}{'':>10}" + "".join(cell(b["random_standard"][i]) for i, _, _ in cols))
    k = b.get("coverage_factor", 2)
    lines.append(f"  {f'expanded U (k={k})':<30}{'':>10}" + "".join(
        cell(None if b["combined_standard"][i] is None else k * b["combined_standard"][i]) for i, _, _ in cols))
    lines.append("  inputs: " + "; ".join(", ".join(r["inputs"]) for r in b["rows"] if r["kind"] == "systematic"))
    lines.append(f"  sensitivities from {b.get('sensitivity_points')} points, computed once per geometry and "
                 "recipe; docs/uncertainty.md")
    return "\n".join(lines)
