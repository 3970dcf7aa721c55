"""Trend plots for the process engineer: focal lengths (or focal powers, for facets focused beyond 20 m),
residual slope errors and twist over a period, from the station's journal or from a folder of batch results.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
from pathlib import Path

import numpy as np
from matplotlib.dates import AutoDateLocator, ConciseDateFormatter
from matplotlib.figure import Figure

from ..archive.journal import Journal
from ..errors import ReportError
from ..result.verdict import LONG_FOCAL_LENGTH_M
from ..times import parse_time, utc_key
from ._common import savefig_atomic
from .maps import MODEL_LABELS, MODELS

log = logging.getLogger(__name__)


# -- trends -----------------------------------------------------------------------------------------------
def _in_period(time_iso, since, until) -> bool:
    try:
        key = utc_key(time_iso)
    except (TypeError, ValueError):
        return False
    return (since is None or key >= utc_key(since)) and (until is None or key < utc_key(until))


def trend_records_from_journal(journal: str | Path, since=None, until=None) -> list[dict]:
    """The journal's records with time in ``[since, until)`` (ISO 8601; None is open), in time order."""
    journal = Path(journal)
    if not journal.is_file():
        raise ReportError(f"journal {journal} does not exist")
    j = Journal(journal)
    try:
        return [r.record for r in j.rows(since, until)]
    finally:
        j.close()


def trend_records_from_results(folder: str | Path, since=None, until=None) -> list[dict]:
    """The reprocessed records of a batch output folder (or its ``results/``) in ``[since, until)``; a result
    file that cannot be read is left out with a warning naming it."""
    folder = Path(folder)
    results = folder / "results" if (folder / "results").is_dir() else folder
    if not results.is_dir():
        raise ReportError(f"{folder} is not a folder of batch results")
    out, unreadable = [], []
    for p in sorted(results.glob("*.json")):
        if p.name.startswith("."):
            continue
        try:
            obj = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            unreadable.append(f"{p.name} ({exc})")
            continue
        if isinstance(obj, dict) and obj.get("status") == "ok" and _in_period(obj.get("time"), since, until):
            out.append(obj)
    if unreadable:
        log.warning("the trend leaves out %d unreadable result file(s) of %s: %s", len(unreadable), results,
                    "; ".join(unreadable))
    out.sort(key=lambda r: utc_key(r["time"]))
    return out


def write_trend(records: list[dict], out_path: str | Path, *, title: str = "", dpi: int = 110) -> Path:
    """Plot focal lengths (or focal powers), residual slope errors and twist against time.

    Parameters
    ----------
    records : list of dict
        Result records (journal rows or reprocessed results); those without figures (faults) are
        counted in the title and skipped.
    out_path : str or Path
        The PNG to write.
    title : str
        First line of the title (the source and the period).

    Returns
    -------
    Path

    Raises
    ------
    ReportError
        When no record in *records* has figures.
    """
    rows = [r for r in records if isinstance(r.get("slope_rms_mrad"), dict) and r.get("time")]
    if not rows:
        raise ReportError(f"no measured facet in the period ({len(records)} record(s), none with figures)")
    t = [parse_time(r["time"]) for r in rows]
    fx = np.array([np.nan if r.get("focal_length_x_m") is None else r["focal_length_x_m"] for r in rows], float)
    fy = np.array([np.nan if r.get("focal_length_y_m") is None else r["focal_length_y_m"] for r in rows], float)
    both = np.abs(np.concatenate([fx, fy]))
    long_focus = not np.any(np.isfinite(both)) or float(np.nanmedian(both)) > LONG_FOCAL_LENGTH_M
    fig = Figure(figsize=(11.0, 8.5), layout="constrained")
    ax_f, ax_e, ax_t = fig.subplots(3, 1, sharex=True)

    def u_of(key, sub=()):
        """Each facet's expanded uncertainty of a figure (0 where a record has none: no bar)."""
        out = []
        for r in rows:
            v = r.get(key)
            for k in sub:
                v = v.get(k) if isinstance(v, dict) else None
            out.append(v if isinstance(v, (int, float)) and np.isfinite(v) else 0.0)
        return np.array(out, float)

    def points(ax, values, u, marker, label=None):
        """The facets' values with their ± U as bars (every plotted figure is a measurement result)."""
        ax.errorbar(t, values, yerr=u, fmt=marker, ms=3, elinewidth=0.7, capsize=0, label=label)

    if long_focus:
        kx = np.array([r.get("curvature_x_per_m", np.nan) for r in rows], float)
        ky = np.array([r.get("curvature_y_per_m", np.nan) for r in rows], float)
        points(ax_f, kx, u_of("curvature_x_per_m_U"), "o", "kappa_x")
        points(ax_f, ky, u_of("curvature_y_per_m_U"), "s", "kappa_y")
        ax_f.set_ylabel("focal power (1/m)")
    else:
        points(ax_f, fx, u_of("focal_length_x_m_U"), "o", "f_x")
        points(ax_f, fy, u_of("focal_length_y_m_U"), "s", "f_y")
        ax_f.set_ylabel("focal length (m)")
    designs = {(r.get("reprocess") or {}).get("design", {}).get("focal_length_m") for r in rows} - {None}
    for f in sorted(designs):
        ax_f.axhline(1.0 / f if long_focus else f, color="0.4", ls="--", lw=0.8, label=f"design {f:g} m")
    bad = [i for i, r in enumerate(rows) if r.get("verdict") not in ("pass", None)]
    if bad:
        ax_f.plot([t[i] for i in bad], (kx if long_focus else fx)[bad], "o", mfc="none", mec="red", ms=7,
                  label="fail or invalid")
    ax_f.legend(fontsize=8, loc="best")
    for model, marker in zip(MODELS, "o^s"):
        v = [((r["slope_rms_mrad"].get(model) or {}).get("magnitude")) for r in rows]
        points(ax_e, np.array([np.nan if x is None else x for x in v], float),
               u_of("slope_rms_mrad_U", (model, "magnitude")), marker,
               MODEL_LABELS[model].replace("compared with the ", ""))
    ax_e.set_ylabel("slope error RMS,\nmagnitude (mrad)")
    ax_e.legend(fontsize=8, loc="best")
    points(ax_t, np.array([r.get("twist_mrad_per_m", np.nan) for r in rows], float), u_of("twist_mrad_per_m_U"), "o")
    ax_t.set_ylabel("twist (mrad/m)")
    locator = AutoDateLocator(tz=t[0].tzinfo)          # the station's local time, as in the records
    ax_t.xaxis.set_major_locator(locator)
    ax_t.xaxis.set_major_formatter(ConciseDateFormatter(locator, tz=t[0].tzinfo))
    skipped = len(records) - len(rows)
    with_u = any(isinstance(r.get("focal_length_x_m_U"), (int, float)) or isinstance(r.get("curvature_x_per_m_U"),
                                                                                    (int, float)) for r in rows)
    fig.suptitle((title + "\n" if title else "") + f"{len(rows)} measured facet(s) from {rows[0]['time'][:19]} to "
                 f"{rows[-1]['time'][:19]}" + (f" ({skipped} fault(s) without figures not shown)" if skipped else "")
                 + ("; bars: ± U, the expanded uncertainty (k = 2)" if with_u else ""), fontsize=10)
    path = savefig_atomic(fig, Path(out_path), dpi)
    log.info("trend of %d facet(s): %s", len(rows), path)
    return path


def default_trend_name(since, until) -> str:
    """``trend-<from>-<to>.png`` with file-name-safe dates."""
    def part(v, default):
        return default if v is None else str(v).replace(":", "").replace("+", "p")
    return f"trend-{part(since, 'start')}-{part(until, _dt.date.today().isoformat())}.png"
