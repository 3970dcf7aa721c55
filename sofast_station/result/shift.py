"""What a shift's facets add up to: counts, yield, the spread of each figure, cycle times.

Pure: result records (dicts, as journaled) in, numbers out; the console's end-of-run summary and the
line's web page both use it. A running station keeps a :class:`ShiftTally` (running statistics, a fixed
size whatever the number of facets) rather than a list of records: it runs for months. Figures are read
with :func:`~sofast_station.result.record.figure_value`, so a nested figure such as the slope-error RMS of
one model is named by a path (``slope_rms_mrad.design.magnitude``).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .faults import fault_kind
from .health import STATION_FAULT_KINDS
from .record import figure_value

#: The figures a shift summary describes: (path in the record, label, unit, decimals).
SUMMARY_FIGURES = (
    ("focal_length_x_m", "focal length x", "m", 4),
    ("focal_length_y_m", "focal length y", "m", 4),
    ("twist_mrad_per_m", "twist", "mrad/m", 3),
    ("slope_rms_mrad.design.magnitude", "slope RMS vs design", "mrad", 3),
    ("slope_rms_mrad.parabola.magnitude", "slope RMS vs parabola", "mrad", 3),
)

#: Every verdict a facet's record can carry, in the order the console, the page and OPC UA count them
#: (``indeterminate``: within U of a limit under the guarded decision rule).
VERDICTS = ("pass", "fail", "indeterminate", "invalid", "fault")


@dataclass
class FigureStats:
    """Mean, sample standard deviation and count of one figure over a shift (None when no value)."""

    mean: float | None
    std: float | None
    n: int


@dataclass
class ShiftSummary:
    """A shift's (or a run's) facets at a glance.

    Attributes
    ----------
    counts : dict
        Facets per verdict (:data:`VERDICTS`: pass, fail, indeterminate, invalid, fault).
    total : int
    yield_fraction : float or None
        Passed facets over the facets the station could judge: every facet but the station's own faults (a
        timeout, a camera, a dead worker...: :data:`~sofast_station.result.health.STATION_FAULT_KINDS`), which
        count against the line's health, not the facets'; a capture, geometry or analysis fault stays in (it
        may be the facet's own). None when there is none.
    figures : dict
        Record path -> :class:`FigureStats` over the facets that have the figure.
    cycle_median_s, cycle_p95_s, cycle_worst_s : float or None
        Cycle times (:func:`cycle_seconds`), seconds.
    faults_by_kind : dict
        Fault kind (the reason's first word: camera, capture, timeout...) -> count.
    station_faults : int
        Faults of the station (left out of the yield).
    references : int
        Reference facets measured (a reference recipe's rows, ``station_checks.reference``): they judge the
        station, not the production, so they are left out of the counts, the yield and the figures.
    """

    counts: dict
    total: int
    yield_fraction: float | None
    figures: dict
    cycle_median_s: float | None
    cycle_p95_s: float | None
    cycle_worst_s: float | None
    faults_by_kind: dict = field(default_factory=dict)
    station_faults: int = 0
    references: int = 0

    @property
    def judged(self) -> int:
        """The facets the yield is over: all but the station's faults."""
        return self.total - self.station_faults


def cycle_seconds(record: dict):
    """A facet's cycle time, seconds, or None: from the robot's trigger to the facet's journal row
    (``timings_s.until_journal``), the moment its answer is decided; the robot hears it right after.

    The one definition the console (each facet's line and the run's summary), the page and OPC UA show. A
    facet whose analysis overran the deadline was answered "fault: timeout" at the deadline: its cycle
    ends there, and the late result that came after (``timings_s.until_late_result``) does not lengthen it.
    """
    return figure_value(record, "timings_s.until_journal")


class RunningStats:
    """Count, mean and sample standard deviation of a stream of numbers in constant memory (Welford's
    update: B. P. Welford, "Note on a method for calculating corrected sums of squares and products",
    Technometrics, 1962)."""

    __slots__ = ("n", "mean", "_m2")

    def __init__(self):
        self.n, self.mean, self._m2 = 0, 0.0, 0.0

    def add(self, x: float) -> None:
        self.n += 1
        delta = x - self.mean
        self.mean += delta / self.n
        self._m2 += delta * (x - self.mean)

    def stats(self) -> FigureStats:
        return FigureStats(self.mean if self.n else None,
                           math.sqrt(max(self._m2, 0.0) / (self.n - 1)) if self.n > 1 else None, self.n)


#: The newest cycle times a running tally keeps for its median and 95th percentile (8 bytes each).
CYCLE_WINDOW = 10_000


class ShiftTally:
    """A run's summary kept up to date facet by facet, in memory that does not grow with the facets.

    Verdict and fault counts, and for each figure of :data:`SUMMARY_FIGURES` a running mean and standard
    deviation (:class:`RunningStats`); the cycle-time median and 95th percentile are over the newest
    *cycle_window* cycles (None: all of them, for a finite list), the worst cycle over all.
    """

    def __init__(self, cycle_window: int | None = CYCLE_WINDOW):
        self.counts = {v: 0 for v in VERDICTS}
        self.faults: dict[str, int] = {}
        self.figures = {path: RunningStats() for path, *_ in SUMMARY_FIGURES}
        self.cycle_s: deque = deque(maxlen=cycle_window)
        self.worst_s: float | None = None
        self.total = 0
        self.station_faults = 0
        self.references = 0

    def add(self, record: dict, cycle_s: float | None = None) -> None:
        """Count one facet's *record*; its cycle time is the record's own (:func:`cycle_seconds`) unless
        *cycle_s* (seconds) is given. A reference's row is counted apart (:attr:`ShiftSummary.references`)."""
        if isinstance(record.get("station_checks"), dict) and "reference" in record["station_checks"]:
            self.references += 1                   # it judged the station (station/reference.py), not a facet
            self.add_cycle(cycle_s if cycle_s is not None else cycle_seconds(record))
            return
        verdict = str(record.get("verdict") or "fault")
        self.counts[verdict] = self.counts.get(verdict, 0) + 1
        self.total += 1
        if verdict == "fault":
            kind = fault_kind(record)
            self.faults[kind] = self.faults.get(kind, 0) + 1
            self.station_faults += kind in STATION_FAULT_KINDS
        elif verdict in VERDICTS:
            for path, stats in self.figures.items():
                v = figure_value(record, path)
                if v is not None and math.isfinite(v):
                    stats.add(float(v))
        self.add_cycle(cycle_s if cycle_s is not None else cycle_seconds(record))

    def add_cycle(self, t: float | None) -> None:
        """One cycle time, seconds (None or not finite: not counted)."""
        if t is not None and math.isfinite(t):
            self.cycle_s.append(float(t))
            self.worst_s = float(t) if self.worst_s is None else max(self.worst_s, float(t))

    def summary(self) -> ShiftSummary:
        med = p95 = None
        if self.cycle_s:
            times = np.fromiter(self.cycle_s, float, len(self.cycle_s))
            med, p95 = float(np.percentile(times, 50)), float(np.percentile(times, 95))
        judged = self.total - self.station_faults
        return ShiftSummary(dict(self.counts), self.total, self.counts["pass"] / judged if judged else None,
                            {path: st.stats() for path, st in self.figures.items()}, med, p95, self.worst_s,
                            dict(sorted(self.faults.items())), self.station_faults, self.references)


def summarize(records, cycle_s: list[float] | None = None) -> ShiftSummary:
    """Summarise *records*; cycle times from *cycle_s* (seconds), else from each record."""
    tally = ShiftTally(cycle_window=None)
    for rec in records:
        tally.add(rec, math.nan if cycle_s is not None else None)     # NaN: the time comes from cycle_s
    for t in cycle_s if cycle_s is not None else ():
        tally.add_cycle(t)
    return tally.summary()
