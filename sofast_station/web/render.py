"""The page's HTML, rendered on the server from a :meth:`LineData.snapshot`: every value that comes from
the journal, the status file or the configuration is escaped here (a serial such as ``<script>`` or
``../../etc/passwd`` is text on the page and never part of a file name). Charts are inline SVG.

The page is cut into sections (:data:`SECTIONS`); the live updates send the sections' HTML again and the
page's script puts it in place, so there is one renderer for the first load and for every update.
"""

from __future__ import annotations

import html
import math

from ..qc.view import chart_view, nice_ticks
from ..result.formatting import method_text, with_u
from ..result.shift import SUMMARY_FIGURES, VERDICTS

SECTIONS = ("state", "last", "shift", "station")
_VERDICT_CLASS = {"pass": "pass", "fail": "fail", "invalid": "invalid", "indeterminate": "indeterminate",
                  "fault": "fault"}


def esc(value) -> str:
    return html.escape("" if value is None else str(value), quote=True)


def _num(v, decimals: int) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v:.{decimals}f}"


def _with_u(v, u, decimals: int) -> str:
    """``value ± U`` by GUM's rule (:func:`~sofast_station.result.formatting.with_u`); a dash for no value."""
    return _num(v, decimals) if v is None or not math.isfinite(v) else with_u(v, u, decimals=decimals)


def _short(serial, most: int = 60) -> str:
    """A serial too long for the big heading: its start and its end, the middle left out (the page's
    tooltip and the journal keep it whole)."""
    text = "" if serial is None else str(serial)
    if len(text) <= most:
        return text
    keep = (most - 1) // 2
    return f"{text[:keep]}…{text[-keep:]}"


def age_text(seconds) -> str:
    """A verdict's age for the operator: "12 s ago", "17 min ago", "3.2 h ago" (the page's script says
    the same as it ticks)."""
    if seconds is None or not math.isfinite(seconds):
        return "age unknown"
    if seconds < 90:
        return f"{seconds:.0f} s ago"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min ago"
    if seconds < 172800:
        return f"{seconds / 3600:.1f} h ago"
    return f"{seconds / 86400:.1f} days ago"


def staleness(snap: dict) -> str | None:
    """Why the last verdict is not live (the page greys it), or None while it is: the station is offline,
    or the verdict is older than ``[web] stale_after_s``. (The page's script adds a lost connection.)"""
    if (snap.get("status") or {}).get("state", "offline") == "offline":
        return "the station is offline"
    age, limit = snap.get("last_age_s"), snap.get("stale_after_s")
    if age is not None and limit is not None and age > limit:
        return f"no facet for more than {limit:g} s"
    return None


def _age(hours) -> str:
    if hours is None:
        return "unknown age"
    if hours < 1:
        return f"{hours * 60:.0f} min old"
    if hours < 48:
        return f"{hours:.1f} h old"
    return f"{hours / 24:.1f} days old"


# -- sections ---------------------------------------------------------------------------------------------
def state_html(snap: dict) -> str:
    status = snap["status"]
    state = status.get("state", "offline")
    extra = ""
    if state == "measuring" and status.get("serial") is not None:
        extra = f" <span class='muted'>{esc(status['serial'])}</span>"
    if status.get("manual_serial"):
        extra += f" <span class='muted'>next serial (typed): {esc(status['manual_serial'])}</span>"
    return f"<span class='badge state-{esc(state)}' data-state='{esc(state)}'>{esc(state)}</span>{extra}"


def last_html(snap: dict) -> str:
    rec = snap.get("last")
    if rec is None:
        return "<h2>Last facet</h2><p class='muted'>No facet measured yet.</p>"
    verdict = str(rec.get("verdict") or "fault")
    cls = _VERDICT_CLASS.get(verdict, "fault")
    request = rec.get("request") or {}
    notes = []
    if request.get("serial_source") == "operator":
        notes.append(f"serial typed by the operator (the robot said {esc(request.get('serial_read'))})")
    if request.get("operator") == "remeasure":
        notes.append("re-measured on the operator's request")
    reasons = "".join(f"<li>{esc(r)}</li>" for r in rec.get("reasons") or [])
    rows = []
    for f in snap.get("figures", []):
        mark = "" if f.ok is None else ("<span class='ok'>✓</span>" if f.ok else "<span class='bad'>✗</span>")
        rows.append(f"<tr class='{'' if f.ok is None else 'in' if f.ok else 'out'}'><th>{esc(f.label)}</th>"
                    f"<td class='num'>{esc(_with_u(f.value, f.uncertainty, f.decimals))} {esc(f.unit)}</td>"
                    f"<td class='lim'>{esc(f.limit)} {esc(f.unit) if f.limit else ''}</td><td>{mark}</td></tr>")
    table = ""
    if rows:
        k = rec.get("coverage_factor")
        head = "value ± U (k = " + esc(k) + ")" if k and any(f.uncertainty is not None for f in snap["figures"]) \
            else "value"
        table = (f"<table class='figures'><thead><tr><th>figure</th><th>{head}</th><th>limit</th><th></th></tr>"
                 f"</thead><tbody>{''.join(rows)}</tbody></table>")
    cid = esc(rec.get("cycle_id", ""))
    stale = staleness(snap)
    age = snap.get("last_age_s")
    age_line = f"measured {age_text(age)}" + (f" · not live: {stale}" if stale else "")
    pictures = ""
    if snap.get("last_has_picture"):
        pictures = (f"<div class='pictures'><figure><img id='white' alt='white frame with the found outline' "
                    f"src='/facet/{cid}/white.png'><figcaption>camera's white frame, found outline</figcaption>"
                    f"</figure>")
        if verdict != "fault" and isinstance(rec.get("facets"), list):      # a heliostat: the map of its facets
            pictures += (f"<figure><img id='facets' alt='map of the heliostat's facets' src='/facet/{cid}/facets.png'>"
                         f"<figcaption>its facets and their canting errors (mrad)</figcaption></figure>")
        elif verdict != "fault":
            pictures += (f"<figure><img id='map' alt='slope-error map' src='/facet/{cid}/map.png'>"
                         f"<figcaption>slope error vs design (mrad)</figcaption></figure>")
        pictures += "</div>"
    return (f"<h2>Last facet</h2>"
            f"<div class='facet-head'><div class='serial' title='{esc(rec.get('serial'))}'>"
            f"{esc(_short(rec.get('serial')))}</div><div class='meta'>recipe {esc(rec.get('recipe') or 'default')}"
            + (f" · {esc(method_text(rec))}" if method_text(rec) else "")
            + f" · {esc(rec.get('time'))} · cycle {cid}</div></div>"
            f"<div class='verdict-box'><div id='verdict' class='verdict {cls}{' stale' if stale else ''}' "
            f"data-verdict='{esc(verdict)}' data-time-s='{esc(snap.get('last_time_s') or '')}' "
            f"data-stale-after-s='{esc(snap.get('stale_after_s'))}'><span class='word'>{esc(verdict.upper())}</span>"
            f"</div></div><p id='verdict-age' class='verdict-age{' stale' if stale else ''}'>{esc(age_line)}</p>"
            + (f"<p class='muted'>{'; '.join(notes)}</p>" if notes else "")
            + (f"<ul class='reasons'>{reasons}</ul>" if reasons else "")
            + table + pictures)


def shift_html(snap: dict) -> str:
    s = snap["summary"]
    c = s.counts
    yield_text = "–" if s.yield_fraction is None else f"{100 * s.yield_fraction:.1f} %"
    faults = ", ".join(f"{n} {esc(k)}" for k, n in s.faults_by_kind.items()) or "none"
    cycle = ("–" if s.cycle_median_s is None else
             f"median {s.cycle_median_s:.2f} s · 95th percentile {s.cycle_p95_s:.2f} s · worst {s.cycle_worst_s:.2f} s")
    stats = []
    for path, label, unit, decimals in SUMMARY_FIGURES:
        st = s.figures.get(path)
        if st and st.n:
            stats.append(f"<tr><th>{esc(label)}</th><td class='num'>{_num(st.mean, decimals)}</td>"
                         f"<td class='num'>{_num(st.std, decimals)}</td><td>{esc(unit)}</td></tr>")
    ch = snap["chart"]
    charts = "".join(svg_chart(p["title"], p["series"], p["limits"], decimals=p["decimals"], unit=p["unit"])
                     for p in ch["panels"])
    n_chart = len(ch["serials"])
    colours = {"pass": "pass-t", "fail": "fail-t", "indeterminate": "indeterminate-t", "invalid": "invalid-t",
               "fault": "fault-t"}
    kpis = "".join(f"<div><b class='{colours[v]}'>{c.get(v, 0)}</b><span>{v}</span></div>" for v in VERDICTS)
    return (f"<h2>Shift <span class='muted'>since {esc(snap['shift_start'])}</span></h2>"
            f"<div class='kpis'><div><b>{s.total}</b><span>facets</span></div>"
            f"<div><b>{yield_text}</b><span>yield</span></div>{kpis}</div>"
            + (f"<p class='muted'>yield over {s.judged} facets: {s.station_faults} fault(s) of the station "
               "(timeouts, camera...) count against the line's health, not the facets'</p>" if s.station_faults else "")
            + f"<p>faults by kind: {faults}</p><p>cycle time (trigger to result): {cycle}</p>"
            + (f"<table class='stats'><thead><tr><th></th><th>mean</th><th>std</th><th></th></tr></thead>"
               f"<tbody>{''.join(stats)}</tbody></table>" if stats else "")
            + f"<h3>Recipe {esc(ch['recipe'])}: its last {n_chart} facet{'s' if n_chart != 1 else ''} of the shift, "
              f"with its limits</h3><div class='charts'>{charts}</div>")


def station_html(snap: dict) -> str:
    cal = snap["calibration"]
    disk = snap["disk"]
    if cal.get("record"):
        cal_text = (f"radiometric record {esc(cal['record'])} ({esc(cal.get('origin'))}), {esc(_age(cal.get('age_h')))}"
                    + (" (the simulated station's shipped record does not age)" if cal.get("exempt") else
                       f", allowed {cal['max_age_h']:g} h" if cal.get("max_age_h") else ""))
        others = cal.get("others") or {}
        if others:
            cal_text += "; " + ", ".join(f"{esc(k)} record {esc(v)}" for k, v in sorted(others.items()))
        if cal.get("newer"):
            cal_text += (f" <span class='fail-t'>(a newer radiometric record {esc(cal['newer'])} waits: the line "
                         "takes it at its next start)</span>")
    else:
        cal_text = esc(cal.get("error") or "no calibration in force")
    free = "–" if disk.get("free_gb") is None else f"{disk['free_gb']:.1f} GB"
    alarms = "".join(f"<li class='alarm'><b>{esc(kind)}</b>: {esc(text)}</li>" for kind, text in snap["alarms"])
    # the line's checks of itself on the last facet (station/runner.py station_checks): beside the facets' verdicts
    health = (snap.get("status") or {}).get("station_health") or {}
    checks = "".join(f"<tr><th>{esc(name)}</th><td>{esc(text)}</td></tr>" for name, text in sorted(health.items())
                     if isinstance(text, str))
    return (f"<h2>Station</h2><table class='station'>"
            f"<tr><th>state</th><td>{state_html(snap)}</td></tr>"
            + checks +
            f"<tr><th>calibration in force</th><td>{cal_text}</td></tr>"
            f"<tr><th>free disk</th><td>{esc(free)} (data_dir)</td></tr>"
            f"<tr><th>archive backlog</th><td>{disk['workbook_backlog']} rows for the workbook, "
            f"{disk['dump_backlog']} dumps, {disk['spool_files']} spooled</td></tr></table>"
            f"<h3>Alarms</h3>" + (f"<ul class='alarms'>{alarms}</ul>" if alarms else "<p class='ok'>none</p>"))


def sections(snap: dict) -> dict:
    return {"state": state_html(snap), "last": last_html(snap), "shift": shift_html(snap),
            "station": station_html(snap)}


# -- charts -----------------------------------------------------------------------------------------------
def svg_chart(title: str, series: list, limits: list, decimals: int = 3, unit: str = "", width: int = 520,
              height: int = 200) -> str:
    """A small line chart of *series* [(name, values (None: gap), colour)] with horizontal *limits*
    [(value, colour, label)], as inline SVG: scaled to the data (a limit far from it is named, not drawn:
    :func:`~sofast_station.qc.view.chart_view`), round ticks on the value axis, the facets oldest to newest."""
    values = [v for _, vs, _ in series for v in vs if v is not None and math.isfinite(v)]
    if not values:
        return (f"<svg class='chart' viewBox='0 0 {width} {height}' role='img' aria-label='{esc(title)}'>"
                f"<text x='8' y='18' class='ct'>{esc(title)}</text><text x='8' y='60' class='cl'>no facet measured"
                f"</text></svg>")
    colour_of = {label: colour for _, colour, label in limits}
    view = chart_view(values, limits=[(v, label) for v, _, label in limits])
    lo, hi = view.low, view.high
    left, right, top, bottom = 62, 10, 28, 42
    n = max(len(vs) for _, vs, _ in series)

    def x(i):
        return left + (width - left - right) * (i / max(n - 1, 1))

    def y(v):
        return top + (height - top - bottom) * (1 - (v - lo) / (hi - lo))
    parts = [f"<svg class='chart' viewBox='0 0 {width} {height}' role='img' aria-label='{esc(title)}'>",
             f"<text x='8' y='16' class='ct'>{esc(title)}</text>",
             f"<rect x='{left}' y='{top}' width='{width - left - right}' height='{height - top - bottom}' "
             f"class='frame'/>"]
    ticks = nice_ticks(lo, hi, 5)
    step = ticks[1] - ticks[0] if len(ticks) > 1 else 0
    tick_decimals = next((d for d in range(13) if abs(round(step, d) - step) <= 1e-9 * step), decimals) \
        if step > 0 else decimals
    for t in ticks:
        parts.append(f"<line x1='{left}' x2='{width - right}' y1='{y(t):.1f}' y2='{y(t):.1f}' class='grid'/>")
        parts.append(f"<text x='{left - 5}' y='{y(t) + 4:.1f}' class='cl' text-anchor='end'>{t:.{tick_decimals}f}"
                     f"</text>")
    for v, label in view.shown:
        parts.append(f"<line x1='{left}' x2='{width - right}' y1='{y(v):.1f}' y2='{y(v):.1f}' "
                     f"stroke='{colour_of[label]}' stroke-dasharray='5 4' stroke-width='1.5'/>")
        parts.append(f"<text x='{width - right - 4}' y='{y(v) - 3:.1f}' class='cl' text-anchor='end' "
                     f"fill='{colour_of[label]}'>{esc(label)} {v:.{decimals}f}</text>")
    legend_x = left + 200
    for name, vs, colour in series:
        path, pen = [], "M"
        for i, v in enumerate(vs):
            if v is None or not math.isfinite(v):
                pen = "M"
                continue
            path.append(f"{pen}{x(i):.1f},{y(v):.1f}")
            pen = "L"
        if path:
            parts.append(f"<path d='{' '.join(path)}' fill='none' stroke='{colour}' stroke-width='2'/>")
        for i, v in enumerate(vs):
            if v is not None and math.isfinite(v):
                parts.append(f"<circle cx='{x(i):.1f}' cy='{y(v):.1f}' r='2.5' fill='{colour}'/>")
        parts.append(f"<text x='{legend_x}' y='16' class='lg' fill='{colour}'>■ {esc(name)}</text>")
        legend_x += 110
    parts.append(f"<text x='{left}' y='{height - 20}' class='cl'>facets, oldest to newest ({n})</text>")
    beyond = [f"{label} {v:.{decimals}g} {unit} {'↑' if (v, label) in view.above else '↓'}"
              for v, label in view.above + view.below]
    if beyond:
        parts.append(f"<text x='{left}' y='{height - 6}' class='cl'>beyond the view: {esc('; '.join(beyond))}</text>")
    parts.append("</svg>")
    return "".join(parts)
