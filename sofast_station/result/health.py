"""The line's own health: rules that say when the station is failing as a line, not a facet as a facet.

A facet's verdict judges the facet. A line whose every facet times out, or whose yield falls far below what
the same recipe gave an hour ago, or whose cycles crowd the deadline, is a station problem (a busy or slow
machine, a camera that drops frames, a fixture out of place) that no single verdict names. These rules watch
the answered records and raise the station's *line* alarm (page, OPC UA, the PLC's warning bits, the
console); the alarm clears by itself when the rule no longer holds.

The rules (:class:`HealthSettings`):

* **faults in a row**: the last *faults_in_row* facets were all answered fault (any kind);
* **yield far below the recipe's recent yield**: of the newest *yield_window* facets of a recipe that were
  judged (station faults left out, see below), so few passed that a line still at the recipe's recent yield
  (the facets before them, at least *yield_baseline_min*) would give that few with probability below
  *yield_p* (the binomial tail: 1e-4, so a steady line alarms about once in tens of thousands of facets);
* **cycles running into the deadline**: at least *deadline_count* of the newest *deadline_window* cycles
  took more than *deadline_fraction* of the deadline, or timed out;
* at the start, **a machine that cannot keep up** (:meth:`LineHealth.startup`): the warm-up's capture
  and a second, timed analysis together above *deadline_fraction* of the deadline.

**A fault of the station is not a facet's failure.** A timeout, a camera or display that stopped, a stale
calibration, an unknown recipe, a dead worker, a full disk or a bug (:data:`STATION_FAULT_KINDS`) says
nothing about the facet: it counts against the line's health, and the yield (:mod:`~sofast_station.result.
shift`) leaves it out. A capture, geometry or analysis fault (no facet in view, a facet out of place, too
few valid pixels) may be the facet's own and stays in the yield as a facet that did not pass.

Pure: records (dicts, as journaled) and times in, alarm texts out; no I/O.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

from .faults import fault_kind

#: Fault kinds that are the station's, not the facet's (:mod:`~sofast_station.result.faults`).
STATION_FAULT_KINDS = frozenset({"timeout", "camera", "display", "calibration", "recipe", "worker", "archive",
                                 "internal"})

#: The line's alarm names (the status file's keys; the page, OPC UA's ``Alarms/Line`` and the PLC's
#: warning bit ``line`` follow any of them).
ALARMS = ("line-faults", "line-yield", "line-deadline", "line-startup", "line-geometry")


def station_fault(record: dict) -> bool:
    """Whether *record* is a fault of the station (:data:`STATION_FAULT_KINDS`), not of the facet."""
    return str(record.get("verdict")) == "fault" and fault_kind(record) in STATION_FAULT_KINDS


@dataclass(frozen=True)
class HealthSettings:
    """The line-health rules' thresholds (``[run]`` in station.toml: ``alarm_faults_in_row``,
    ``alarm_yield_window``; the others fixed here, see the module docstring)."""

    faults_in_row: int = 3
    yield_window: int = 20
    yield_baseline_min: int = 30
    yield_baseline_max: int = 200
    yield_p: float = 1e-4
    deadline_fraction: float = 0.8
    deadline_window: int = 10
    deadline_count: int = 5

    def __post_init__(self):
        if self.faults_in_row < 1 or self.yield_window < 5 or self.deadline_window < 1:
            raise ValueError("the line-health windows must be at least 1 fault, 5 facets and 1 cycle")


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(X <= k) for X ~ Binomial(n, p): the chance a line at yield *p* passes at most *k* of *n* facets."""
    if p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 1.0 if k >= n else 0.0
    return float(min(1.0, sum(math.comb(n, i) * p ** i * (1.0 - p) ** (n - i) for i in range(k + 1))))


class LineHealth:
    """The line-health rules over a running line: :meth:`add` each answered facet, read :attr:`alarms`.

    Parameters
    ----------
    deadline_s : float
        The cycle deadline, seconds.
    settings : HealthSettings
    history : dict, optional
        Recipe name -> its recent records (oldest first, from the journal) to start each recipe's yield
        baseline from, so a restarted station does not forget its recent yield.
    """

    def __init__(self, deadline_s: float, settings: HealthSettings = HealthSettings(), history: dict | None = None):
        self.deadline_s = float(deadline_s)
        self.settings = settings
        self.alarms: dict[str, str] = {}
        self._faults = 0
        self._fault_kinds: deque = deque(maxlen=settings.faults_in_row)
        self._cycles: deque = deque(maxlen=settings.deadline_window)
        self._passed: dict[str, deque] = {}
        for recipe, records in (history or {}).items():
            for rec in records:
                self._judged(recipe, rec)

    def _judged(self, recipe: str, record: dict) -> None:
        if station_fault(record) or record.get("verdict") is None:
            return
        keep = self.settings.yield_window + self.settings.yield_baseline_max
        self._passed.setdefault(recipe, deque(maxlen=keep)).append(record.get("verdict") == "pass")

    def add(self, recipe: str, record: dict, cycle_s: float | None) -> dict[str, str | None]:
        """Count one answered facet (its record as journaled, its cycle time in seconds; None when unknown).

        Returns the alarms that changed: name -> its text (raised or reworded) or None (cleared)."""
        s = self.settings
        before = dict(self.alarms)
        now: dict[str, str] = {k: v for k, v in self.alarms.items() if k == "line-startup"}
        # faults in a row
        if record.get("verdict") == "fault":
            self._faults += 1
            self._fault_kinds.append(fault_kind(record))
        else:
            self._faults = 0
            self._fault_kinds.clear()
        if self._faults >= s.faults_in_row:
            kinds: dict[str, int] = {}
            for k in self._fault_kinds:
                kinds[k] = kinds.get(k, 0) + 1
            what = ", ".join(f"{k} x{n}" for k, n in sorted(kinds.items(), key=lambda kv: -kv[1]))
            now["line-faults"] = (f"the line is failing: the last {self._faults} facets were all faults ({what}); "
                                  "see the log and the newest rows' reasons")
        # yield against the recipe's recent yield
        self._judged(recipe, record)
        passed = self._passed.get(recipe)
        if passed is not None and len(passed) >= s.yield_window + s.yield_baseline_min:
            seq = list(passed)
            window, base = seq[-s.yield_window:], seq[:-s.yield_window]
            k, p0 = sum(window), sum(base) / len(base)
            if binomial_tail(k, s.yield_window, p0) < s.yield_p:
                now["line-yield"] = (f"yield of recipe {recipe} fell to {k} of the last {s.yield_window} facets "
                                     f"({100.0 * k / s.yield_window:.0f} %) against {100.0 * p0:.0f} % over its "
                                     f"{len(base)} facets before: check the press, the fixture and the station")
        # cycles running into the deadline (a timeout counts as one)
        timed_out = record.get("verdict") == "fault" and fault_kind(record) == "timeout"
        slow = timed_out or (cycle_s is not None and math.isfinite(cycle_s)
                             and cycle_s > s.deadline_fraction * self.deadline_s)
        self._cycles.append(bool(slow))
        n_slow = sum(self._cycles)
        if n_slow >= s.deadline_count:
            now["line-deadline"] = (f"cycles are running into the deadline: {n_slow} of the last {len(self._cycles)} "
                                    f"took over {s.deadline_fraction * self.deadline_s:.1f} s or timed out "
                                    f"(deadline {self.deadline_s:g} s); the machine is too slow or too busy: stop "
                                    "other programs, or raise [run] deadline_s")
        elif "line-startup" in now and len(self._cycles) >= s.deadline_window:
            del now["line-startup"]          # the line has shown it keeps up after all
        self.alarms = now
        changed = {k: v for k, v in now.items() if before.get(k) != v}
        changed.update({k: None for k in before if k not in now})
        return changed

    def startup(self, capture_s: float, analysis_s: float) -> str | None:
        """Judge the machine before the first facet: the warm-up's capture time and a timed analysis (after the
        first, which pays for imports and caches), seconds. Returns the alarm text (also kept in
        :attr:`alarms` until a full window of cycles keeps up) or None."""
        need = capture_s + analysis_s
        limit = self.settings.deadline_fraction * self.deadline_s
        if not (math.isfinite(need) and need > limit):
            return None
        text = (f"this machine may not keep up: a capture and an analysis took {need:.1f} s "
                f"({capture_s:.1f} + {analysis_s:.1f}) against the {self.deadline_s:g} s deadline "
                f"({100.0 * need / self.deadline_s:.0f} %); facets may time out: stop other programs, or raise "
                "[run] deadline_s")
        self.alarms["line-startup"] = text
        return text
