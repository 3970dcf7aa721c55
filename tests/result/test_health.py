"""Issue 43, item 1: the line's own health (result/health.py), rule by rule, and its false-alarm rate and
detection over drawn lines.

The yield rule's claims rest on drawn lines (a seeded generator, pass/fail per facet drawn at a set yield):

* **false alarms**: three steady lines at 80, 90 and 97 % yield, 4,000 facets each: the rule's per-facet test
  level is 1e-4, so over 12,000 (overlapping) tests a correct rule raises about one alarm; at most 4 onsets are
  allowed (a rule at the 1 % level would raise dozens);
* **detection**: 100 lines at 95 % whose yield drops to 50 % after 100 facets: the alarm comes within 20
  facets of the drop in at least 95 of them (at 20 facets of 50 % the window passes about 10, and the tail
  P(X <= 10 | 20, 0.95) is 1e-8).
"""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.result.health import (STATION_FAULT_KINDS, HealthSettings, LineHealth, binomial_tail,
                                          station_fault)
from sofast_station.result.shift import ShiftTally


def rec(verdict: str, kind: str | None = None, recipe: str = "dish") -> dict:
    r = {"verdict": verdict, "recipe": recipe}
    if verdict == "fault":
        r["reasons"] = [f"{kind or 'timeout'}: what happened"]
    return r


def test_binomial_tail_against_a_direct_sum():
    # P(X <= 1 | n = 3, p = 0.5) = (1 + 3) / 8
    assert binomial_tail(1, 3, 0.5) == pytest.approx(0.5)
    assert binomial_tail(13, 20, 0.95) == pytest.approx(sum(
        __import__("math").comb(20, i) * 0.95 ** i * 0.05 ** (20 - i) for i in range(14)))
    assert binomial_tail(2, 2, 1.0) == 1.0 and binomial_tail(1, 2, 1.0) == 0.0


def test_faults_in_a_row_raise_the_alarm_and_a_measured_facet_clears_it():
    h = LineHealth(10.0, HealthSettings(faults_in_row=3))
    assert h.add("dish", rec("fault"), 10.0) == {}
    assert h.add("dish", rec("fault", "camera"), 1.0) == {}
    changed = h.add("dish", rec("fault"), 10.0)
    assert "line-faults" in changed and "last 3 facets were all faults" in changed["line-faults"]
    assert "timeout x2" in changed["line-faults"] and "camera x1" in changed["line-faults"]
    assert "line-faults" in h.add("dish", rec("fault"), 10.0)        # reworded: 4 now
    assert h.add("dish", rec("pass"), 3.0) == {"line-faults": None}
    assert "line-faults" not in h.alarms


def test_cycles_at_the_deadline_raise_the_alarm_from_the_fifth_of_ten():
    h = LineHealth(10.0)
    for t in (3.0,) * 6 + (8.5,) * 4:
        assert "line-deadline" not in h.add("dish", rec("pass"), t)
    assert "line-deadline" in h.add("dish", rec("pass"), 9.0)       # 5 of the last 10 over 8 s
    assert "5 of the last 10" in h.alarms["line-deadline"]
    # a timeout is a cycle at the deadline whatever its recorded time
    h2 = LineHealth(10.0, HealthSettings(faults_in_row=100))
    for _ in range(4):
        h2.add("dish", rec("fault", "timeout"), None)
    assert "line-deadline" in h2.add("dish", rec("fault", "timeout"), None)


def test_a_machine_too_slow_at_start_is_said_and_cleared_once_the_line_keeps_up():
    h = LineHealth(10.0)
    assert h.startup(1.0, 5.0) is None
    text = h.startup(2.0, 7.5)
    assert text and "9.5 s" in text and "[run] deadline_s" in text and "line-startup" in h.alarms
    for i in range(9):
        h.add("dish", rec("pass"), 3.0)
        assert "line-startup" in h.alarms
    assert h.add("dish", rec("pass"), 3.0) == {"line-startup": None}


def test_station_faults_are_left_out_of_the_yield_facet_faults_are_not():
    assert STATION_FAULT_KINDS >= {"timeout", "camera", "worker"}
    assert station_fault(rec("fault", "timeout")) and not station_fault(rec("fault", "capture"))
    tally = ShiftTally()
    for r in [rec("pass")] * 6 + [rec("fail")] * 2 + [rec("fault", "timeout")] * 10 + [rec("fault", "capture")] * 2:
        tally.add(r, 1.0)
    s = tally.summary()
    assert (s.total, s.station_faults, s.judged) == (20, 10, 10)
    assert s.yield_fraction == pytest.approx(6 / 10)


def _onsets(rng, yields) -> list[int]:
    h = LineHealth(10.0)
    onsets, was, i = [], False, 0
    for n, p in yields:
        for passed in rng.random(n) < p:
            h.add("dish", rec("pass" if passed else "fail"), 3.0)
            now = "line-yield" in h.alarms
            if now and not was:
                onsets.append(i)
            was, i = now, i + 1
    return onsets


def test_a_steady_line_rarely_raises_the_yield_alarm():
    rng = np.random.default_rng(20261206)
    onsets = sum(len(_onsets(rng, [(4000, p)])) for p in (0.80, 0.90, 0.97))
    assert onsets <= 4, onsets


def test_a_yield_collapse_is_caught_within_a_window():
    rng = np.random.default_rng(43)
    caught = 0
    for _ in range(100):
        onsets = [i for i in _onsets(rng, [(100, 0.95), (40, 0.5)]) if i >= 100]
        caught += bool(onsets) and onsets[0] < 120
    assert caught >= 95, caught


def test_the_yield_baseline_starts_from_the_journal_history():
    history = {"dish": [rec("pass")] * 60}
    h = LineHealth(10.0, history=history)
    for _ in range(12):
        h.add("dish", rec("fail"), 3.0)
    assert "line-yield" in h.alarms and "against 100 % over its" in h.alarms["line-yield"]
    # another recipe's history is its own
    assert not LineHealth(10.0, history={"gore": [rec("pass")] * 60}).add("dish", rec("fail"), 3.0)
