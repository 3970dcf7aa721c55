"""Control charts of a period: one individuals and moving-range chart per figure, yield per day and shift,
and a summary workbook (``sofast-station report spc``).

The statistics are :mod:`sofast_station.qc.spc`; this module picks the figures out of result records,
takes the specification limits from the recipe, draws, and writes the workbook.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from openpyxl import Workbook
from openpyxl.styles import Font

from ..archive.workbook import WorkbookSettings, period_key, save_atomic
from ..errors import ReportError
from ..qc import spc
from ..qc.view import chart_view
from ..result.health import station_fault
from ..result.record import figure_value
from ..result.shift import VERDICTS
from ..result.specs import FigureSpec
from ..times import parse_time
from ._common import savefig_atomic

log = logging.getLogger(__name__)


def select_records(records, *, recipe: str | None = None, facet: str | None = None, serial: str | None = None,
                   since=None, until=None) -> list[dict]:
    """Records matching the filters (recipe name, facet type, serial regular expression, period), in time
    order. A record whose time cannot be read cannot be placed on a chart: it is left out with a warning
    naming it (its serial and cycle)."""
    try:
        pattern = re.compile(serial) if serial else None
    except re.error as exc:
        raise ReportError(f"--serial {serial!r} is not a valid regular expression: {exc}") from None
    lo = parse_time(since) if since is not None else None
    hi = parse_time(until) if until is not None else None
    out, timeless = [], []
    for r in records:
        if recipe is not None and (r.get("recipe") or "default") != recipe:
            continue
        if facet is not None and r.get("facet") != facet:
            continue
        if pattern is not None and not pattern.search(str(r.get("serial", ""))):
            continue
        try:
            t = parse_time(r["time"])
        except (KeyError, TypeError, ValueError) as exc:
            timeless.append(f"{r.get('serial', '?')} (cycle {r.get('cycle_id', '?')}: time {r.get('time')!r}, "
                            f"{type(exc).__name__})")
            continue
        if (lo is not None and t < lo) or (hi is not None and t >= hi):
            continue
        out.append(r)
    if timeless:
        log.warning("%d record(s) left out: their time cannot be read: %s", len(timeless), "; ".join(timeless))
    out.sort(key=lambda r: parse_time(r["time"]))
    return out


@dataclass
class Chart:
    """One figure's chart data and statistics."""

    spec: FigureSpec
    times: list
    values: np.ndarray
    serials: list
    baseline: spc.Baseline | None
    violations: dict = field(default_factory=dict)
    ewma_out: np.ndarray | None = None
    capability: dict = field(default_factory=dict)


#: The fewest facets whose moving ranges make control limits (their sigma is then known to about +-30 %;
#: 20 to 25 are usual, Montgomery 2009, sec. 6.4): below it ``report spc`` refuses rather than draw
#: limits from too few facets.
MIN_BASELINE_FACETS = 10


def build_charts(records: list[dict], specs: list[FigureSpec], *, baseline_n: int = 25, baselines: dict | None = None,
                 rule_set: str = "western_electric", ewma_lambda: float | None = None) -> list[Chart]:
    """Charts of the measured (pass, fail or indeterminate) records: limits from *baselines* (figure key ->
    Baseline) or from the first *baseline_n* facets.

    Raises
    ------
    ReportError
        When no saved baseline is given and fewer than ``max(baseline_n, MIN_BASELINE_FACETS)`` facets were
        measured: the control limits would not be the ones the title promises.
    """
    measured = [r for r in records if r.get("verdict") in ("pass", "fail", "indeterminate")]
    if not measured:
        raise ReportError(f"no measured facet (pass, fail or indeterminate) among the {len(records)} selected "
                          "record(s): widen --from/--to, or check --recipe, --facet-type and --serial")
    if baseline_n < MIN_BASELINE_FACETS:
        raise ReportError(f"--baseline-n {baseline_n} is too few facets for control limits: give at least "
                          f"{MIN_BASELINE_FACETS} (20 to 25 are usual)")
    if baselines is None and len(measured) < baseline_n:
        raise ReportError(f"the selection holds {len(measured)} measured facet(s), fewer than the {baseline_n} the "
                          f"control limits come from (--baseline-n): measure more facets, widen --from/--to, or "
                          f"give --baseline-n between {MIN_BASELINE_FACETS} and {len(measured)}"
                          if len(measured) >= MIN_BASELINE_FACETS else
                          f"the selection holds {len(measured)} measured facet(s): control limits need at least "
                          f"{MIN_BASELINE_FACETS} (20 to 25 are usual); measure more facets or widen --from/--to")
    charts = []
    for s in specs:
        vals = np.array([np.nan if figure_value(r, s.key) is None else figure_value(r, s.key) for r in measured], float)
        base = (baselines or {}).get(s.key)
        if base is None:
            head = vals[:baseline_n]
            try:
                base = spc.baseline(head)
            except ValueError:
                base = None
        c = Chart(s, [parse_time(r["time"]) for r in measured], vals, [r.get("serial") for r in measured], base)
        if base is not None:
            c.violations = spc.violations(vals, base, rule_set)
            if ewma_lambda:
                c.ewma_out = spc.ewma_violations(vals, base, ewma_lambda)
        if s.lsl is not None or s.usl is not None:
            c.capability = spc.capability(vals, s.lsl, s.usl, base.sigma if base else None)
        charts.append(c)
    return charts


def yield_table(records: list[dict], shift_starts_h=(6.0, 14.0, 22.0)) -> dict:
    """Counts of each verdict (pass, fail, indeterminate, invalid, fault) per day and per shift, the station's
    own faults among them (``station_fault``), and the yield: pass over every facet but the station's faults
    (:data:`~sofast_station.result.health.STATION_FAULT_KINDS`, the line's health, not the facets')."""
    day_s = WorkbookSettings(period="day")
    shift_s = WorkbookSettings(period="shift", shift_starts_h=tuple(shift_starts_h))
    out = {"day": {}, "shift": {}}
    for r in records:
        verdict = r.get("verdict") or "fault"
        for kind, settings in (("day", day_s), ("shift", shift_s)):
            key = period_key(r["time"], settings)
            row = out[kind].setdefault(key, {**{v: 0 for v in VERDICTS}, "station_fault": 0})
            row[verdict if verdict in row else "fault"] += 1
            row["station_fault"] += station_fault(r)
    for kind in out:
        for row in out[kind].values():
            n = sum(row[v] for v in VERDICTS)
            row["total"] = n
            judged = n - row["station_fault"]
            row["yield"] = row["pass"] / judged if judged else None
    return out


def draw_charts(charts: list[Chart], path: Path, title: str, *, ewma_lambda: float | None = None,
                dpi: int = 100) -> Path:
    """One row per figure: individuals chart (values, design, spec limits, centre and control limits,
    rule violations marked) and its moving-range chart; an EWMA line when *ewma_lambda* is given."""
    n = len(charts)
    fig = Figure(figsize=(15.0, 2.9 * n + 0.8), layout="constrained")
    axes = fig.subplots(n, 2, width_ratios=(3.2, 1.0), squeeze=False)
    for (ax, ax_mr), c in zip(axes, charts):
        s, x = c.spec, c.values
        i = np.arange(1, x.size + 1)
        ax.plot(i, x, "-o", color="0.25", ms=3, lw=0.7, label="facet")
        if s.design is not None and np.any(np.isfinite(x)) and \
                abs(s.design - np.nanmean(x)) < 3 * (np.nanmax(x) - np.nanmin(x) + 1e-300):
            ax.axhline(s.design, color="tab:green", lw=1.0, ls="-", label=f"design {s.design:.6g}")
        # Scaled to the data and control limits; a specification limit far from them is named, not drawn
        # (qc/view.py): scaled to a 3 mrad limit, 0.5 mrad data were a flat line and their limits invisible.
        keep = [] if c.baseline is None else [c.baseline.lcl, c.baseline.ucl]
        view = chart_view(x, keep=keep, limits=[(s.lsl, "LSL"), (s.usl, "USL")])
        ax.set_ylim(view.low, view.high)
        for lim, name in view.shown:
            ax.axhline(lim, color="tab:red", lw=1.2, ls="-", label=f"{name} {lim:.6g}")
        for k, (value, name) in enumerate(view.above):        # named at the edge they lie beyond
            ax.text(0.995, 0.97 - 0.1 * k, f"{name} {value:.6g} {s.unit} above the view", transform=ax.transAxes,
                    ha="right", va="top", fontsize=8, color="tab:red")
        for k, (value, name) in enumerate(view.below):
            ax.text(0.995, 0.03 + 0.1 * k, f"{name} {value:.6g} {s.unit} below the view", transform=ax.transAxes,
                    ha="right", va="bottom", fontsize=8, color="tab:red")
        if c.baseline is not None:
            b = c.baseline
            ax.axhline(b.centre, color="tab:blue", lw=0.9, ls="--", label=f"centre {b.centre:.6g}")
            for lim in (b.lcl, b.ucl):
                ax.axhline(lim, color="tab:blue", lw=0.9, ls=":")
            ax.axhspan(b.lcl, b.ucl, color="tab:blue", alpha=0.05, label="control limits (baseline, 3 sigma)")
            marked = sorted({int(k) for v in c.violations.values() for k in v})
            if marked:
                ax.plot(i[marked], x[marked], "o", mfc="none", mec="red", ms=9, mew=1.5,
                        label="rule violated: " + ", ".join(r for r, v in c.violations.items() if len(v)))
            if ewma_lambda:
                z = spc.ewma(x, b.centre, ewma_lambda)
                lo, hi = spc.ewma_limits(x.size, b, ewma_lambda)
                ax.plot(i, z, color="tab:orange", lw=1.2, label=f"EWMA (lambda {ewma_lambda:g})")
                ax.plot(i, lo, color="tab:orange", lw=0.6, ls=":")
                ax.plot(i, hi, color="tab:orange", lw=0.6, ls=":")
        cap = c.capability
        extra = ""
        if cap.get("cpk") is not None:
            extra = (f"   Cp {cap['cp']:.2f}" if cap.get("cp") is not None else "") + f"   Cpk {cap['cpk']:.2f}"
        ax.set_title(f"{s.label} ({s.unit}): {np.count_nonzero(np.isfinite(x))} facets{extra}", fontsize=10)
        ax.set_ylabel(f"{s.label} ({s.unit})")
        ax.legend(fontsize=7, loc="upper left", ncol=3)
        mr = spc.moving_range(x)
        ax_mr.plot(i, mr, "-o", color="0.25", ms=2, lw=0.6)
        if c.baseline is not None:
            ax_mr.axhline(c.baseline.mr_bar, color="tab:blue", ls="--", lw=0.9)
            ax_mr.axhline(c.baseline.mr_ucl, color="tab:blue", ls=":", lw=0.9)
        ax_mr.set_title(f"moving range ({s.unit})", fontsize=9)
    axes[-1][0].set_xlabel("facet (in time order)")
    axes[-1][1].set_xlabel("facet")
    fig.suptitle(title, fontsize=11)
    return savefig_atomic(fig, Path(path), dpi)


def draw_yield(table: dict, path: Path, title: str, dpi: int = 100) -> Path:
    """Yield per day and per shift as bars, with the facet counts."""
    fig = Figure(figsize=(12.0, 6.5), layout="constrained")
    for ax, kind in zip(fig.subplots(2, 1), ("day", "shift")):
        keys = sorted(table[kind])
        y = [100 * (table[kind][k]["yield"] or 0) for k in keys]
        bars = ax.bar(range(len(keys)), y, color="tab:green")
        for b, k in zip(bars, keys):
            ax.text(b.get_x() + b.get_width() / 2, b.get_height() + 1, f"{table[kind][k]['total']}", ha="center",
                    fontsize=7)
        ax.set_xticks(range(len(keys)), keys, rotation=30, ha="right", fontsize=8)
        ax.set_ylim(0, 110)
        ax.set_ylabel("yield (% pass)")
        ax.set_title(f"yield per {kind} (number above a bar: facets)", fontsize=10)
    fig.suptitle(title, fontsize=11)
    return savefig_atomic(fig, Path(path), dpi)


def write_summary_workbook(charts: list[Chart], table: dict, path: Path, title: str, rule_set: str) -> Path:
    """A workbook with a ``summary`` sheet (one row per figure: limits, baseline, Cp/Cpk, violations), a
    ``yield`` sheet and a ``facets`` sheet (time as an Excel date, each figure a number)."""
    wb = Workbook()
    ws = wb.active
    ws.title = "summary"
    ws.append([title])
    ws["A1"].font = Font(bold=True)
    head = ["figure", "unit", "n", "mean", "design", "LSL", "USL", "centre (baseline)", "sigma (baseline)",
            "LCL", "UCL", "baseline n", "Cp", "Cpk", "Pp", "Ppk", "points violating a rule", "rules violated"]
    ws.append(head)
    for cell in ws[2]:
        cell.font = Font(bold=True)
    for c in charts:
        b, cap = c.baseline, c.capability
        marked = sorted({int(k) for v in c.violations.values() for k in v})
        ws.append([c.spec.label, c.spec.unit, int(np.count_nonzero(np.isfinite(c.values))),
                   float(np.nanmean(c.values)) if np.any(np.isfinite(c.values)) else None, c.spec.design, c.spec.lsl,
                   c.spec.usl, b.centre if b else None, b.sigma if b else None, b.lcl if b else None,
                   b.ucl if b else None, b.n if b else None, cap.get("cp"), cap.get("cpk"), cap.get("pp"),
                   cap.get("ppk"), len(marked),
                   ", ".join(f"{r} ({len(v)})" for r, v in c.violations.items() if len(v))])
    ws.append([])
    ws.append([f"rules: {rule_set}: " + "; ".join(f"{r} {spc.RULE_TEXT[r]}" for r in spc.rules_of(rule_set))])
    ws.column_dimensions["A"].width = 28
    ys = wb.create_sheet("yield")

    ys.append(["period", "kind", *VERDICTS, "total", "station faults", "yield"])
    for cell in ys[1]:
        cell.font = Font(bold=True)
    for kind in ("day", "shift"):
        for k in sorted(table[kind]):
            row = table[kind][k]
            ys.append([k, kind, *(row[v] for v in VERDICTS), row["total"], row["station_fault"], row["yield"]])
            ys.cell(row=ys.max_row, column=len(VERDICTS) + 5).number_format = "0.0%"
    fs = wb.create_sheet("facets")
    fs.append(["time", "serial"] + [f"{c.spec.label} ({c.spec.unit})" for c in charts])
    for cell in fs[1]:
        cell.font = Font(bold=True)
    if charts:
        for j, t in enumerate(charts[0].times):
            fs.append([t.replace(tzinfo=None), charts[0].serials[j]]
                      + [None if not np.isfinite(c.values[j]) else float(c.values[j]) for c in charts])
            fs.cell(row=fs.max_row, column=1).number_format = "yyyy-mm-dd hh:mm:ss"
    fs.column_dimensions["A"].width = 20
    path = Path(path)
    save_atomic(wb, path)
    return path
