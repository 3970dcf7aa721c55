"""What a chart of one figure shows: a value range scaled to the data, and which limits fit in it.

A control chart scaled to the specification limits shows its data as a flat line and hides the control
limits (a 3 mrad slope limit above data at 0.5 mrad). The rule used by ``report spc`` and the line's page:
the range holds the data and the lines that belong to them (centre, control limits); a specification
limit is drawn when it lies within *reach* times that range beyond it, so the data still fill at least
``1 / (1 + 2 reach)`` of the axis; a limit farther away is left out of the range and named beside the
chart ("USL 3 mrad above the view").

Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class ChartView:
    """A chart's value range and its limits.

    Attributes
    ----------
    low, high : float
        The value range shown (padded).
    shown : tuple
        The limits (value, label) inside the range: draw them.
    above, below : tuple
        The limits (value, label) beyond the range, above or below it: name them.
    """

    low: float
    high: float
    shown: tuple
    above: tuple
    below: tuple

    def notes(self, unit: str = "", digits: int = 4) -> list[str]:
        """One short text per limit left out, e.g. ``"USL 3 mrad above the view"``."""
        unit = f" {unit}" if unit else ""
        return ([f"{label} {value:.{digits}g}{unit} above the view" for value, label in self.above]
                + [f"{label} {value:.{digits}g}{unit} below the view" for value, label in self.below])


def chart_view(values, keep=(), limits=(), *, reach: float = 1.0, pad: float = 0.08) -> ChartView:
    """The range of a chart of *values* (None and non-finite ones ignored).

    Parameters
    ----------
    values : iterable of float
        The data.
    keep : iterable of float
        Lines always inside the range (a baseline's centre and control limits).
    limits : iterable of (float, str)
        Specification limits (value, label); None values are skipped.
    reach : float
        How far beyond the data's range (in units of that range) a limit may lie and still be drawn.
    pad : float
        Margin added on both sides, as a fraction of the range.

    Returns
    -------
    ChartView
    """
    data = [float(v) for v in list(values) + list(keep) if v is not None and math.isfinite(float(v))]
    marks = [(float(v), str(label)) for v, label in limits if v is not None and math.isfinite(float(v))]
    if not data:
        data = [v for v, _ in marks] or [0.0, 1.0]
    lo, hi = min(data), max(data)
    span = hi - lo
    if span <= 0:
        span = max(abs(hi) * 0.01, 1e-9)
        lo, hi = lo - span / 2, hi + span / 2
    shown, above, below = [], [], []
    for v, label in marks:
        if v > hi + reach * span:
            above.append((v, label))
        elif v < lo - reach * span:
            below.append((v, label))
        else:
            shown.append((v, label))
    lo = min([lo] + [v for v, _ in shown])
    hi = max([hi] + [v for v, _ in shown])
    margin = pad * (hi - lo)
    return ChartView(lo - margin, hi + margin, tuple(shown), tuple(above), tuple(below))


def nice_ticks(low: float, high: float, most: int = 6) -> list[float]:
    """Round tick values (1, 2, 2.5 or 5 times a power of ten apart) inside [low, high], at most *most*."""
    if not (math.isfinite(low) and math.isfinite(high)) or high <= low:
        return []
    raw = (high - low) / max(most - 1, 1)
    power = 10.0 ** (math.floor(math.log10(raw)) - 1)
    for m in (1.0, 2.0, 2.5, 5.0, 10.0, 20.0, 25.0, 50.0, 100.0):
        step = m * power
        first = math.ceil(low / step - 1e-9)
        last = math.floor(high / step + 1e-9)
        if last - first + 1 <= most:
            return [round(k * step, 12) for k in range(first, last + 1)]
    return [low, high]
