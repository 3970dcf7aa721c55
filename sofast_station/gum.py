"""How a number with its expanded uncertainty is written: ``5.4183 ± 0.0021 m`` (GUM 7.2.6).

The uncertainty is given to (at most) two significant digits, and the value is rounded to the same decimal
place. Pure text, standard library only, on the floor of plain data so that every floor can write a figure
with its U the same way; :mod:`sofast_station.result.formatting` (which re-exports these) adds the budget
table. Nothing else in the package writes a U's digits (``tests/result/test_formatting.py``).
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
