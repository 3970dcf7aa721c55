"""What a shift's facets add up to: counts, yield, the spread of each figure, cycle times.

Pure: result records (dicts, as journaled) in, numbers out; the console's end-of-run summary and the
line's web page both use it. Figures are read with :func:`figure_value`, so a nested figure such as the
slope-error RMS of one model is named by a path (``slope_rms_mrad.design.magnitude``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: The figures a shift summary describes: (path in the record, label, unit, decimals).
SUMMARY_FIGURES = (
    ("focal_length_x_m", "focal length x", "m", 4),
    ("focal_length_y_m", "focal length y", "m", 4),
    ("twist_mrad_per_m", "twist", "mrad/m", 3),
    ("slope_rms_mrad.design.magnitude", "slope RMS vs design", "mrad", 3),
    ("slope_rms_mrad.parabola.magnitude", "slope RMS vs parabola", "mrad", 3),
)

VERDICTS = ("pass", "fail", "invalid", "fault")


def figure_value(record: dict, path: str):
    """The figure at a dotted *path* of *record* (``slope_rms_mrad.design.magnitude``), or None."""
    node = record
    for part in path.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node if isinstance(node, (int, float)) and not isinstance(node, bool) else None


def figure_uncertainty(record: dict, path: str):
    """The expanded uncertainty (k = 2) of the figure at *path*: the sibling ``NAME_U`` of the path's
    first key, with the same nesting (``slope_rms_mrad_U.design.magnitude``); None when absent."""
    head, _, rest = path.partition(".")
    return figure_value(record, f"{head}_U" + (f".{rest}" if rest else ""))


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
        Facets per verdict (pass, fail, invalid, fault).
    total : int
    yield_fraction : float or None
        Passed facets over all facets measured (faults included: a faulted facet did not pass).
    figures : dict
        Record path -> :class:`FigureStats` over the facets that have the figure.
    cycle_median_s, cycle_p95_s, cycle_worst_s : float or None
        Cycle times, seconds.
    faults_by_kind : dict
        Fault kind (the reason's first word: camera, capture, timeout...) -> count.
    """

    counts: dict
    total: int
    yield_fraction: float | None
    figures: dict
    cycle_median_s: float | None
    cycle_p95_s: float | None
    cycle_worst_s: float | None
    faults_by_kind: dict = field(default_factory=dict)


def fault_kind(record: dict) -> str:
    """The kind of a faulted record: the part of its first reason before the colon ("camera", ...)."""
    reasons = record.get("reasons") or []
    head = str(reasons[0]).split(":", 1)[0].strip() if reasons else ""
    return head if head and len(head) <= 20 and " " not in head else "other"


def cycle_seconds(record: dict):
    """Trigger to journal, seconds, as the record holds it (``timings_s.until_journal``), or None."""
    return figure_value(record, "timings_s.until_journal")


def summarize(records: list[dict], cycle_s: list[float] | None = None) -> ShiftSummary:
    """Summarise *records*; cycle times from *cycle_s* (seconds), else from each record."""
    counts = {v: 0 for v in VERDICTS}
    faults: dict[str, int] = {}
    for rec in records:
        verdict = str(rec.get("verdict") or "fault")
        counts[verdict] = counts.get(verdict, 0) + 1
        if verdict == "fault":
            kind = fault_kind(rec)
            faults[kind] = faults.get(kind, 0) + 1
    total = len(records)
    figures = {}
    for path, *_ in SUMMARY_FIGURES:
        values = np.array([v for rec in records if rec.get("verdict") in ("pass", "fail", "invalid", "indeterminate")
                           and (v := figure_value(rec, path)) is not None and math.isfinite(v)], dtype=float)
        figures[path] = FigureStats(float(values.mean()) if values.size else None,
                                    float(values.std(ddof=1)) if values.size > 1 else None, int(values.size))
    times = [float(t) for t in (cycle_s if cycle_s is not None else (cycle_seconds(r) for r in records))
             if t is not None and math.isfinite(t)]
    med = p95 = worst = None
    if times:
        med, p95, worst = (float(np.percentile(times, 50)), float(np.percentile(times, 95)), max(times))
    return ShiftSummary(counts, total, counts["pass"] / total if total else None, figures, med, p95, worst,
                        dict(sorted(faults.items())))
