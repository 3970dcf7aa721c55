"""What the monitor shows, read from the station's files: the journal (read-only), the live status, the
per-facet pictures and the disk. Nothing here writes, and nothing here talks to the station's process.

:class:`LineData` keeps the shift's parsed journal rows and reads only rows it has not seen (by ``seq``),
so a snapshot costs a few milliseconds however long the shift.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
import os
import shutil
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path

from ..calibrate.settings import calibration_settings
from ..calibrate.store import select_radiometric
from ..live.pictures import picture_path
from ..live.status import read_status, status_path
from ..recipes import recipes_from_config
from ..result.formatting import figure_decimals
from ..result.record import figure_uncertainty, figure_value
from ..result.shift import cycle_seconds, summarize
from ..result.specs import figure_specs
from ..result.verdict import LONG_FOCAL_LENGTH_M
from ..times import parse_time, utc_key

log = logging.getLogger(__name__)

#: How many facets the page's charts show.
CHART_FACETS = 50


def shift_start(now: _dt.datetime, starts: tuple) -> _dt.datetime:
    """The latest shift start (local "HH:MM" times in *starts*) at or before *now* (tz-aware)."""
    best = None
    for day in (now.date(), now.date() - _dt.timedelta(days=1)):
        for hhmm in starts:
            h, m = (int(v) for v in hhmm.split(":"))
            t = _dt.datetime.combine(day, _dt.time(h, m), tzinfo=now.tzinfo)
            if t <= now and (best is None or t > best):
                best = t
    return best


@dataclass
class FigureRow:
    """One figure of the last facet, as the page shows it."""

    label: str
    value: float | None
    uncertainty: float | None
    unit: str
    decimals: int
    limit: str
    ok: bool | None


def heliostat_rows(record: dict, recipe) -> list[FigureRow]:
    """A heliostat's figures for the page: each facet's canting error (its size, with U along it) against the
    recipe's ``max_canting_mrad``, or its status when it was not measured."""
    limit = recipe.limits.max_canting_mrad if recipe is not None else None
    rows = []
    for f in record["facets"]:
        c = f.get("canting_mrad")
        if c is None:
            rows.append(FigureRow(f"{f.get('label')}: {f.get('status')}", None, None, "", 3, "", False))
            continue
        size = math.hypot(c["x"], c["y"])
        u = f.get("canting_mrad_U") or {}
        big_u = (math.hypot(c["x"] * (u.get("x") or 0.0), c["y"] * (u.get("y") or 0.0)) / size
                 if size > 0 and u else None)
        rows.append(FigureRow(f"{f.get('label')} canting ({f.get('verdict', '')})", size, big_u, "mrad", 3,
                              f"≤ {limit:g}" if limit is not None else "",
                              None if limit is None else size <= limit))
    return rows


def figure_rows(record: dict, recipe) -> list[FigureRow]:
    """The last facet's figures with their limits (from its recipe) and whether each is within them; a
    heliostat's are its facets' canting errors (:func:`heliostat_rows`)."""
    if isinstance(record.get("facets"), list):
        return heliostat_rows(record, recipe)
    rows = []
    lim = recipe.limits if recipe is not None else None
    f_design = recipe.design.focal_length_m if recipe is not None else None
    long_focus = f_design is not None and f_design > LONG_FOCAL_LENGTH_M
    for axis in ("x", "y"):
        if long_focus:
            path = f"curvature_{axis}_per_m"
            v = figure_value(record, path)
            k0, tol = 1.0 / f_design, lim.curvature_tolerance_per_m
            rows.append(FigureRow(f"curvature {axis}", v, figure_uncertainty(record, path), "1/m",
                                  figure_decimals(path), f"{k0 - tol:.6f} to {k0 + tol:.6f}",
                                  None if v is None else abs(v - k0) <= tol))
        else:
            path = f"focal_length_{axis}_m"
            v = figure_value(record, path)
            limit, ok = "", None
            if lim is not None:
                lo, hi = f_design * (1 - lim.focal_length_tolerance), f_design * (1 + lim.focal_length_tolerance)
                limit = f"{lo:.3f} to {hi:.3f}"
                ok = None if v is None else lo <= v <= hi
            rows.append(FigureRow(f"focal length {axis}", v, figure_uncertainty(record, path), "m",
                                  figure_decimals(path), limit, ok))
    v = figure_value(record, "twist_mrad_per_m")
    t = lim.max_twist_mrad_per_m if lim is not None else None
    rows.append(FigureRow("twist", v, figure_uncertainty(record, "twist_mrad_per_m"), "mrad/m",
                          figure_decimals("twist_mrad_per_m"),
                          f"|t| ≤ {t:g}" if t is not None else "", None if v is None or t is None else abs(v) <= t))
    for model in ("design", "parabola", "higher_order"):
        path = f"slope_rms_mrad.{model}.magnitude"
        v = figure_value(record, path)
        if v is None:
            continue
        m = lim.max_slope_rms_mrad.get(model) if lim is not None else None
        rows.append(FigureRow(f"slope RMS vs {model.replace('_', ' ')}", v, figure_uncertainty(record, path),
                              "mrad", figure_decimals(path), f"≤ {m:g}" if m is not None else "",
                              None if m is None else v <= m))
    return rows


class LineData:
    """Reads the line's state for the page and the OPC UA server.

    Parameters
    ----------
    config : StationConfig
    settings : WebSettings
    """

    def __init__(self, config, settings):
        self.config = config
        self.settings = settings
        self.data_dir = Path(config.data_dir)
        self.journal_path = self.data_dir / "journal.sqlite3"
        self.recipes = recipes_from_config(config)
        self._db: sqlite3.Connection | None = None
        self._rows: list[tuple[int, str, dict]] = []     # (seq, time_utc, record) of the shift
        self._last_seq = 0
        self._shift_key: str | None = None
        self._calibration: tuple[float, dict, dict | None] | None = None
        self._disk: tuple[float, dict] | None = None

    # -- the journal, read-only -------------------------------------------------------------------------
    def _conn(self) -> sqlite3.Connection | None:
        if self._db is None:
            if not self.journal_path.exists():
                return None
            try:
                self._db = sqlite3.connect(f"file:{self.journal_path}?mode=ro", uri=True, timeout=5.0,
                                           check_same_thread=False)
            except sqlite3.Error as exc:
                log.warning("cannot open the journal %s read-only: %s", self.journal_path, exc)
                return None
        return self._db

    def _query(self, sql: str, params: tuple = ()) -> list:
        db = self._conn()
        if db is None:
            return []
        try:
            return db.execute(sql, params).fetchall()
        except sqlite3.Error as exc:
            if "no such table" not in str(exc):      # else: the station is creating the journal right now
                log.warning("reading the journal %s: %s", self.journal_path, exc)
            self.close()
            return []

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None

    def version(self) -> tuple:
        """Changes whenever anything the page shows may have changed (cheap: one query, two stats)."""
        rows = self._query("SELECT MAX(seq) FROM cycles")
        seq = rows[0][0] if rows else None
        try:
            st = status_path(self.data_dir).stat().st_mtime_ns
        except OSError:
            st = 0
        last = self._query("SELECT cycle_id FROM cycles ORDER BY seq DESC LIMIT 1")
        pic = picture_path(self.data_dir, last[0][0]) if last else None
        return seq, st, bool(pic and pic.exists()), read_status(self.data_dir).get("state")

    def _refresh(self, now: _dt.datetime) -> None:
        start = shift_start(now, self.settings.shift_starts)
        key = utc_key(start.isoformat())
        if key != self._shift_key:
            self._shift_key, self._rows, self._last_seq = key, [], 0
        new = self._query("SELECT seq, time_utc, record FROM cycles WHERE seq > ? AND time_utc >= ? ORDER BY seq",
                          (self._last_seq, key))
        for seq, time_utc, text in new:
            try:
                self._rows.append((int(seq), time_utc, json.loads(text)))
            except ValueError:
                log.warning("journal row %s is not JSON; skipped", seq)
            self._last_seq = max(self._last_seq, int(seq))
        self._shift_start = start

    def last_record(self) -> dict | None:
        """The newest journal row's record (in this shift or not)."""
        rows = self._query("SELECT record FROM cycles ORDER BY seq DESC LIMIT 1")
        return json.loads(rows[0][0]) if rows else None

    # -- the station --------------------------------------------------------------------------------------
    def calibration(self, status: dict | None = None) -> dict:
        """The calibration records in force, the radiometric record's age and the allowed age (re-read every
        30 s). While the line runs they are the ones it loaded (its live *status*'s ``in_force``: the screen,
        pose and camera records too); a newer radiometric record written since is named as waiting
        (``newer``). Without a running line: the record the next start would use."""
        now = time.monotonic()
        live = (status or {}).get("in_force") if (status or {}).get("state", "offline") != "offline" else None
        if self._calibration and now - self._calibration[0] < 30 and self._calibration[2] == live:
            return self._calibration[1]
        info: dict = {"record": None, "origin": None, "age_h": None, "max_age_h": None}
        try:
            status = select_radiometric(self.config, tolerant=True)
            info.update(record=status.record.record_id, origin=status.origin)
            info["max_age_h"] = calibration_settings(self.config)[0].max_age_h
            created = _dt.datetime.fromisoformat(status.record.created) if status.record.created else None
            if created is not None and created.tzinfo is not None:
                info["age_h"] = (_dt.datetime.now(created.tzinfo) - created).total_seconds() / 3600.0
            info["exempt"] = status.origin == "shipped default" and self.config.backend == "simulated"
            if live and live.get("radiometric"):
                newest = status.record.record_id
                info.update(record=live["radiometric"], origin=live.get("origin", info["origin"]))
                info["others"] = {k: live[k] for k in ("camera", "screen", "pose") if live.get(k)}
                info["newer"] = newest if newest != live["radiometric"] else None
                made = live.get("radiometric_created")
                made = _dt.datetime.fromisoformat(made) if made else None
                info["age_h"] = (None if made is None or made.tzinfo is None else
                                 (_dt.datetime.now(made.tzinfo) - made).total_seconds() / 3600.0)
        except Exception as exc:                  # the page must show the rest whatever the record holds
            info["error"] = str(exc)
        self._calibration = (now, info, live)
        return info

    def disk(self) -> dict:
        """Free space under data_dir and the archive's backlog (re-read every 5 s)."""
        now = time.monotonic()
        if self._disk and now - self._disk[0] < 5:
            return self._disk[1]
        try:
            usage = shutil.disk_usage(self.data_dir)
            free_gb = usage.free / 1e9
        except OSError:
            free_gb = None
        rows = self._query("SELECT SUM(workbook_path IS NULL), SUM(dump_requested = 1 AND dump_path IS NULL AND "
                           "dump_error IS NULL) FROM cycles")
        pending_rows, pending_dumps = (rows[0] if rows else (0, 0))
        try:
            spool = sum(1 for e in os.scandir(self.data_dir / "spool") if e.name.endswith(".npz"))
        except OSError:
            spool = 0
        raw = self.config.raw
        min_free = float(raw.get("archive", {}).get("min_free_gb", raw.get("run", {}).get("min_free_gb", 2.0)))
        info = {"free_gb": free_gb, "min_free_gb": min_free, "workbook_backlog": int(pending_rows or 0),
                "dump_backlog": int(pending_dumps or 0), "spool_files": spool}
        self._disk = (now, info)
        return info

    def alarms(self, status: dict, last: dict | None, calibration: dict, disk: dict) -> list:
        """(kind, text) of every alarm in force: ``offline`` when no station process runs, the loop's (camera,
        plc, drift-RECIPE from the control-chart rules of station/drift.py) and the monitor's own
        (calibration, disk)."""
        out = []
        if status.get("state", "offline") == "offline":
            when = status.get("updated") or status.get("since")
            heard = f" (last heard of {str(when)[:19].replace('T', ' ')})" if when else ""
            out.append(("offline", "the station is not running" + heard
                        + ": nothing on this page is live; start it with sofast-station run"))
        out += [(k, str(v)) for k, v in sorted((status.get("alarms") or {}).items())]
        warnings = ((last or {}).get("calibration") or {}).get("warnings") or []
        if warnings:
            out.append(("calibration", "; ".join(warnings)))
        elif (calibration.get("age_h") is not None and calibration.get("max_age_h")
              and not calibration.get("exempt") and calibration["age_h"] > calibration["max_age_h"]):
            out.append(("calibration", f"radiometric record {calibration['record']} is {calibration['age_h']:.1f} h "
                                       f"old (max {calibration['max_age_h']:g} h)"))
        if disk.get("free_gb") is not None and disk["free_gb"] < disk["min_free_gb"]:
            out.append(("disk", f"only {disk['free_gb']:.1f} GB free in data_dir (dumps stop below "
                                f"{disk['min_free_gb']:g} GB)"))
        return out

    # -- everything the page shows -----------------------------------------------------------------------
    def snapshot(self, now: _dt.datetime | None = None) -> dict:
        now = now or _dt.datetime.now().astimezone()
        self._refresh(now)
        records = [r for _, _, r in self._rows]
        last = self.last_record()
        status = read_status(self.data_dir)
        calibration = self.calibration(status)
        disk = self.disk()
        summary = summarize(records)
        recipe_name, recipe = "default", None
        if last is not None:
            recipe_name = last.get("recipe") or "default"
            recipe = self.recipes.get(recipe_name, self.recipes["default"])
        pic = picture_path(self.data_dir, last.get("cycle_id", "")) if last else None
        age_s = time_s = None
        if last is not None and last.get("time"):
            try:
                time_s = parse_time(last["time"]).timestamp()
                age_s = max(0.0, now.timestamp() - time_s)
            except (TypeError, ValueError):
                age_s = time_s = None
        return {
            "now": now.isoformat(timespec="seconds"),
            "station": self.config.name,
            "status": status,
            "last": last,
            "last_age_s": age_s,
            "last_time_s": time_s,
            "stale_after_s": self.settings.stale_after_s,
            "last_has_picture": bool(pic and pic.exists()),
            "figures": figure_rows(last, recipe) if last and last.get("verdict") != "fault" else [],
            "shift_start": self._shift_start.isoformat(timespec="minutes"),
            "summary": summary,
            "chart": chart_data(records, recipe_name, recipe or self.recipes["default"]),
            "calibration": calibration,
            "disk": disk,
            "alarms": self.alarms(status, last, calibration, disk),
            "token_required": bool(self.settings.token),
        }


#: Colours of the charts' series, in order (the page's dark background).
SERIES_COLOURS = ("#3b82f6", "#f59e0b", "#10b981", "#e879f9")


def chart_data(records: list[dict], recipe_name: str, recipe) -> dict:
    """The page's charts: the shift's last :data:`CHART_FACETS` facets of the last facet's recipe, each
    figure with that recipe's limits (:func:`~sofast_station.result.specs.figure_specs`; focal powers in
    place of focal lengths above 20 m).

    Returns ``{"recipe", "serials", "verdicts", "cycle_s", "panels"}``; a panel is ``{"title", "unit",
    "decimals", "series": [(name, values, colour)], "limits": [(value, colour, label)]}``.
    """
    chosen = [r for r in records if (r.get("recipe") or "default") == recipe_name][-CHART_FACETS:]
    specs = {s.key: s for s in figure_specs(recipe.design.focal_length_m, recipe.limits)}
    long_focus = recipe.design.focal_length_m > LONG_FOCAL_LENGTH_M
    axes = ("curvature_x_per_m", "curvature_y_per_m") if long_focus else ("focal_length_x_m", "focal_length_y_m")
    first = specs[axes[0]]
    panels = [{"title": "focal powers (1/m)" if long_focus else "focal lengths (m)", "unit": first.unit,
               "decimals": 6 if long_focus else 4,
               "series": [(("kappa_" if long_focus else "f_") + axis[-1], [figure_value(r, key) for r in chosen],
                           colour) for key, axis, colour in zip(axes, ("x", "y"), SERIES_COLOURS)],
               "limits": [(first.lsl, "#ef4444", "LSL"), (first.usl, "#ef4444", "USL"),
                          (first.design, "#9ca3af", "design")]}]
    rms = [specs[f"slope_rms_mrad.{m}.magnitude"] for m in ("design", "parabola")]
    panels.append({"title": "slope error RMS (mrad)", "unit": "mrad", "decimals": 3,
                   "series": [(f"vs {s.key.split('.')[1]}", [figure_value(r, s.key) for r in chosen], colour)
                              for s, colour in zip(rms, (SERIES_COLOURS[0], SERIES_COLOURS[2]))],
                   "limits": [(s.usl, colour, f"limit vs {s.key.split('.')[1]}")
                              for s, colour in zip(rms, ("#ef4444", "#a855f7"))]})
    return {"recipe": recipe_name, "serials": [r.get("serial", "") for r in chosen],
            "verdicts": [r.get("verdict") for r in chosen], "cycle_s": [cycle_seconds(r) for r in chosen],
            "panels": panels}

