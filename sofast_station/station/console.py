"""The operator's console: one aligned line per facet, a header that matches it, a summary at the end.

Every kind of row (PASS, FAIL, INVALID, FAULT) has the same columns; a missing figure is a dash in its
column. A figure shows ``value ± U`` when the record carries its expanded uncertainty ``NAME_U``
(docs/conventions.md). After the figures come all the reasons of a FAIL, INVALID or FAULT, separated by
``; ``. The log gets one line per facet with the same content, unpadded (:func:`log_line`).
"""

from __future__ import annotations

from ..result.formatting import figure_decimals, figure_parts, with_u
from ..result.record import figure_uncertainty, figure_value
from ..result.shift import SUMMARY_FIGURES, ShiftSummary

#: Console columns: (heading, record path, width of the value, width of its "± U"). A figure is written as every
#: screen writes it (:func:`~sofast_station.result.formatting.figure_parts`: with its U by GUM's rule, U to two
#: significant digits and the value to the same place; without, to the figure's own decimals).
_FIGURES = (
    ("f_x (m)", "focal_length_x_m", 7, 10),
    ("f_y (m)", "focal_length_y_m", 7, 10),
    ("RMS design", "slope_rms_mrad.design.magnitude", 5, 8),
    ("RMS parab.", "slope_rms_mrad.parabola.magnitude", 5, 8),
)
SERIAL_WIDTH = 16
_VERDICT_WIDTH = 13                  # INDETERMINATE


def _serial_cell(serial: str) -> str:
    """The serial, cut to the column with an ellipsis when longer (the record keeps it whole)."""
    serial = "".join(ch if ch.isprintable() else "?" for ch in str(serial))
    return serial if len(serial) <= SERIAL_WIDTH else serial[:SERIAL_WIDTH - 1] + "…"


def _count_cell(n: int | None, total: int | None, width: int) -> str:
    if n is None:
        return " " * width
    text = f"{n}/{total}" if total else str(n)
    return f"{text:>{width}}"


def _count_width(total: int | None) -> int:
    digits = len(str(total)) if total else 4
    return max(5, 2 * digits + 1)


def _figure_cell(record: dict, path: str, width: int, u_width: int) -> str:
    parts = figure_parts(record, path)
    if parts is None:
        return f"{'-':>{width}}" + " " * u_width
    text, u = parts
    if u is None and len(text) > width:      # a nearly flat facet's f interval: the whole cell
        return f"{text:>{width + u_width}}"
    return f"{text:>{width}}" + (f" ± {u:<{u_width - 3}}" if u is not None else " " * u_width)


def header(total: int | None = None) -> str:
    """The heading line of :func:`facet_line`'s columns."""
    cells = [f"{'n':>{_count_width(total)}}", f"{'serial':<{SERIAL_WIDTH}}", f"{'verdict':<{_VERDICT_WIDTH}}"]
    for head, _, width, u_width in _FIGURES:
        cells.append(f"{head:>{width + u_width}}")
    cells.append(f"{'cycle':>7}")
    return "  ".join(cells) + "  reasons"


def facet_line(record: dict, answer: str, cycle_s: float | None, n: int | None = None,
               total: int | None = None) -> str:
    """One facet's console line, aligned with :func:`header` whatever its verdict."""
    cells = [_count_cell(n, total, _count_width(total)), f"{_serial_cell(record.get('serial', '')):<{SERIAL_WIDTH}}",
             f"{answer.upper():<{_VERDICT_WIDTH}}"]
    for _, path, width, u_width in _FIGURES:
        cells.append(_figure_cell(record, path, width, u_width))
    cells.append(f"{cycle_s:6.2f}s" if cycle_s is not None else f"{'-':>7}")
    text = "  ".join(cells)
    notes = list(record.get("reasons") or []) if answer in ("fail", "invalid", "indeterminate", "fault") else []
    if record.get("calibration", {}).get("warnings"):
        notes.append("calibration stale: see the log")
    if record.get("drift_alarms"):
        notes.append("DRIFT ALARM: " + " | ".join(record["drift_alarms"]))
    return text + ("  " + "; ".join(notes) if notes else "")


def log_line(record: dict, answer: str, cycle_s: float | None, n: int | None = None,
             total: int | None = None) -> str:
    """The facet's line for logs/station.log: the same facts without padding."""
    parts = [f"facet {n}/{total}" if n and total else f"facet {n}" if n else "facet",
             f"serial={record.get('serial', '')!r}", f"cycle={record.get('cycle_id', '')}",
             f"recipe={record.get('recipe') or 'default'}", f"verdict={answer}"]
    for _, path, _, _ in _FIGURES:
        value = figure_value(record, path)
        if value is not None:       # two more decimals than the screens for a value without U, to look into later
            text = with_u(value, figure_uncertainty(record, path), decimals=figure_decimals(path) + 2
                          ).replace(" ± ", "±")
            parts.append(f"{path.replace('slope_rms_mrad.', 'rms_').replace('.magnitude', '')}={text}")
    if cycle_s is not None:
        parts.append(f"cycle_s={cycle_s:.3f}")
    reasons = record.get("reasons") or []
    if reasons and answer != "pass":
        parts.append("reasons=" + " | ".join(str(r) for r in reasons))
    return " ".join(parts)


def summary_text(summary: ShiftSummary) -> str:
    """The end-of-run summary: verdict counts and yield, mean and spread of each figure, cycle times."""
    c = summary.counts
    lines = [f"{summary.total} facet(s): {c.get('pass', 0)} pass, {c.get('fail', 0)} fail, "
             f"{c.get('invalid', 0)} invalid, {c.get('fault', 0)} fault"
             + (f", {c['indeterminate']} indeterminate" if c.get("indeterminate") else "")]
    if summary.yield_fraction is not None:
        lines[0] += f"; yield {100 * summary.yield_fraction:.1f} % ({c.get('pass', 0)}/{summary.judged})"
        if summary.station_faults:
            lines[0] += (f" ({summary.station_faults} fault(s) of the station not counted against the facets: "
                         "the line's health)")
    if summary.faults_by_kind:
        lines.append("faults: " + ", ".join(f"{n} {k}" for k, n in summary.faults_by_kind.items()))
    if any(s.n for s in summary.figures.values()):
        lines.append(f"  {'figure':<30}{'mean':>10}{'std':>10}{'n':>6}")
        for path, label, unit, decimals in SUMMARY_FIGURES:
            s = summary.figures.get(path)
            if s is None or not s.n:
                continue
            mean = f"{s.mean:.{decimals}f}"
            std = "-" if s.std is None else f"{s.std:.{decimals}f}"
            lines.append(f"  {label + f' ({unit})':<30}{mean:>10}{std:>10}{s.n:>6}")
    if summary.cycle_median_s is not None:
        lines.append(f"cycle time: median {summary.cycle_median_s:.2f} s, 95th percentile "
                     f"{summary.cycle_p95_s:.2f} s, worst {summary.cycle_worst_s:.2f} s")
    return "\n".join(lines)
