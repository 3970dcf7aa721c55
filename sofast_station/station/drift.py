"""Drift alarms in the line: after each facet, the control-chart rules on that recipe's recent facets.

The station evaluates, for every charted figure of the facet's recipe (f_x, f_y or kappa_x, kappa_y,
twist, slope RMS vs design and vs parabola: :func:`sofast_station.result.specs.figure_specs`), the run rules
(:mod:`sofast_station.qc.spc`, Western Electric by default) on the facets measured since the recipe's last
alarm, against the recipe's *baseline*: the centre and sigma of each figure over an in-control period,
saved by ``sofast-station report spc --recipe NAME --save-baseline`` as
``data_dir/quality/baseline-NAME.json``. Without a baseline file a recipe has no drift alarm.

A rule met by the newest facet raises an alarm: a warning in the log and on the console, the list in
the facet's journal row (``drift_alarms``), and the WARNINGS register's drift bit to the PLC with the
answer (docs/plc.md). The line does not stop. After an alarm the rules start afresh for that recipe, so
a drift that persists alarms again after a few facets rather than on every one.

station.toml::

    [drift]
    enabled = true                 # false: no drift alarms at all
    rules = "western_electric"     # or "nelson", "beyond_limits"
    window = 30                    # at most this many recent facets per recipe are looked at

    [drift.recipes.gore-a]         # per recipe, the same keys
    enabled = false
"""

from __future__ import annotations

import json
import logging
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..files import safe_name, write_json_atomic
from ..qc.spc import RULE_TEXT, Baseline, alarm_at_last
from ..result.record import figure_value
from ..result.specs import figure_specs

log = logging.getLogger(__name__)

_KEYS = {"enabled", "rules", "window", "recipes"}
_RULE_SETS = ("western_electric", "nelson", "beyond_limits")


@dataclass(frozen=True)
class DriftSettings:
    enabled: bool = True
    rules: str = "western_electric"
    window: int = 30


def _settings(table: dict, where: str, base: DriftSettings) -> DriftSettings:
    unknown = sorted(set(table) - (_KEYS - {"recipes"}))
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: enabled, rules, window")
    enabled = table.get("enabled", base.enabled)
    if not isinstance(enabled, bool):
        raise ConfigError(f"{where}: enabled = {enabled!r} must be true or false")
    rules = table.get("rules", base.rules)
    if rules not in _RULE_SETS:
        raise ConfigError(f"{where}: rules = {rules!r} must be one of {', '.join(_RULE_SETS)}")
    window = table.get("window", base.window)
    if isinstance(window, bool) or not isinstance(window, int) or window < 15:
        raise ConfigError(f"{where}: window = {window!r} must be a whole number of facets >= 15 (the longest rule "
                          "needs 15)")
    return DriftSettings(enabled, rules, window)


def drift_settings(config) -> dict[str, DriftSettings]:
    """``[drift]`` of station.toml: recipe name -> settings (key ``"*"``: every other recipe)."""
    table = config.raw.get("drift", {})
    where = f"{config.path} [drift]"
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    unknown = sorted(set(table) - _KEYS)
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(_KEYS))}")
    base = _settings({k: v for k, v in table.items() if k != "recipes"}, where, DriftSettings())
    out = {"*": base}
    for name, t in (table.get("recipes") or {}).items():
        if not isinstance(t, dict):
            raise ConfigError(f"{where}.recipes.{name} must be a table")
        out[name] = _settings(t, f"{config.path} [drift.recipes.{name}]", base)
    return out


def baseline_path(data_dir: Path, recipe: str) -> Path:
    return Path(data_dir) / "quality" / f"baseline-{safe_name(recipe)}.json"


def save_baseline(data_dir: Path, recipe: str, baselines: dict, period: dict) -> Path:
    """Write a recipe's baseline (figure key -> :class:`~sofast_station.qc.spc.Baseline`) atomically."""
    path = baseline_path(data_dir, recipe)
    write_json_atomic(path, {"recipe": recipe, "period": period,
                             "figures": {k: b.to_dict() for k, b in baselines.items()}})
    return path


def load_baseline(data_dir: Path, recipe: str) -> dict | None:
    """A recipe's saved baseline (figure key -> Baseline), or None when there is none."""
    path = baseline_path(data_dir, recipe)
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        return {k: Baseline.from_dict(v) for k, v in data["figures"].items()}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.error("the drift baseline %s cannot be read (%s): no drift alarms for recipe %s until it is saved "
                  "again (sofast-station report spc --recipe %s --save-baseline)", path, exc, recipe, recipe)
        return None


class DriftMonitor:
    """Evaluates the rules after each facet (one instance per running station).

    Parameters
    ----------
    config : StationConfig
    recipes : dict[str, Recipe]
    journal : Journal, optional
        To start each recipe's recent history from the journal when the station starts.
    """

    def __init__(self, config, recipes: dict, journal=None):
        self.settings = drift_settings(config)
        self.data_dir = config.data_dir
        self.recipes = recipes
        self.journal = journal
        self._history: dict[str, deque] = {}
        self._baselines: dict[str, dict | None] = {}
        self._specs: dict[str, list] = {}

    def _setting(self, recipe: str) -> DriftSettings:
        return self.settings.get(recipe, self.settings["*"])

    def _prime(self, recipe: str, window: int) -> deque:
        hist: deque = deque(maxlen=window)
        if self.journal is not None:
            try:
                rows = self.journal.recent(5000)      # not rows()[-5000:]: the journal holds months
            except Exception as exc:           # the alarm is an aid: never stop the line for it
                log.warning("drift: cannot read the journal for recipe %s's recent facets: %s", recipe, exc)
                rows = []
            for row in rows:
                r = row.record
                if (r.get("recipe") or "default") != recipe or r.get("verdict") not in ("pass", "fail"):
                    continue
                if r.get("drift_alarms"):
                    hist.clear()             # the rules start afresh after an alarm
                    continue
                hist.append(r)
        return hist

    def check(self, recipe: str, record: dict) -> list[str]:
        """The alarms the facet's *record* raises (empty: none); remembers the facet.

        Only measured facets (pass or fail) count; faults and invalid measurements are skipped.
        """
        s = self._setting(recipe)
        if not s.enabled or record.get("verdict") not in ("pass", "fail"):
            return []
        if recipe not in self._baselines:
            self._baselines[recipe] = load_baseline(self.data_dir, recipe)
            if self._baselines[recipe] is None:
                log.info("drift alarms for recipe %s are off until a baseline exists (sofast-station report spc "
                         "--recipe %s --from ... --to ... --save-baseline)", recipe, recipe)
        base = self._baselines[recipe]
        if not base:
            return []
        if recipe not in self._history:
            self._history[recipe] = self._prime(recipe, s.window)
        hist = self._history[recipe]
        hist.append(record)

        if recipe not in self._specs:
            r = self.recipes.get(recipe)
            self._specs[recipe] = figure_specs(r.design.focal_length_m, r.limits) if r is not None else []
        alarms = []
        for spec in self._specs[recipe]:
            b = base.get(spec.key)
            if b is None:
                continue
            values = (figure_value(r, spec.key) for r in hist)
            x = np.array([np.nan if v is None else v for v in values], float)
            rules = alarm_at_last(x, b, s.rules)
            if rules:
                alarms.append(f"{spec.label}: " + "; ".join(f"{r} {RULE_TEXT[r]}" for r in rules)
                              + f" (centre {b.centre:.6g}, sigma {b.sigma:.3g} {spec.unit})")
        if alarms:
            hist.clear()
        return alarms
