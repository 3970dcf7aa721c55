"""Issue 16: control-chart statistics against their published properties and a hand computation."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.qc import spc


def test_rule_set_run_lengths_match_the_published_ones():
    # Champ and Woodall (1987): the 3-sigma rule alone signals once in 370.4 in-control points and
    # after 43.9 points at a 1-sigma step; the four Western Electric rules together after 91.75 points.
    arl, se = spc.average_run_length(0.0, "beyond_limits", runs=1500, length=3000, rng=np.random.default_rng(3))
    assert arl == pytest.approx(370.4, abs=4 * se)
    arl, se = spc.average_run_length(1.0, "beyond_limits", runs=1500, length=600, rng=np.random.default_rng(4))
    assert arl == pytest.approx(43.89, abs=4 * se)
    arl, se = spc.average_run_length(0.0, "western_electric", runs=1500, length=1500, rng=np.random.default_rng(5))
    assert arl == pytest.approx(spc.NOMINAL_ARL0["western_electric"], abs=4 * se)


def _journal(rng, n=500, step_at=None, mean=5.42, sigma=0.01):
    x = rng.normal(mean, sigma, n)
    if step_at is not None:
        x[step_at - 1:] += sigma            # facet numbers count from 1
    return x


def test_500_in_control_facets_raise_no_more_false_alarms_than_the_nominal_rate():
    # Nominal: 1 alarm in 91.75 facets (1.09 %), 5.45 in 500. Limits come from a commissioning baseline
    # of 1000 facets; over 100 synthetic journals of 500 facets the mean count must not exceed the
    # nominal one by more than its simulation uncertainty (3 standard errors).
    rng = np.random.default_rng(11)
    nominal = 500 / spc.NOMINAL_ARL0["western_electric"]
    counts = []
    for _ in range(100):
        base = spc.baseline(rng.normal(5.42, 0.01, 1000))
        counts.append(len(spc.signals(_journal(rng), base)))
    counts = np.array(counts)
    assert counts.mean() <= nominal + 3 * counts.std(ddof=1) / np.sqrt(counts.size)
    # and the rate is not trivially low either (rules that never fire would pass the line above)
    assert counts.mean() > 0.6 * nominal


def test_a_one_sigma_step_at_facet_300_is_flagged_within_the_average_run_length():
    # ARL of the Western Electric rules at a 1-sigma step: 9.2 facets (simulated; 9.22 in Champ and
    # Woodall 1987). Baseline: the first 100 facets of each journal, as the line would take it.
    arl1, se = spc.average_run_length(1.0, "western_electric", runs=2000, length=300,
                                      rng=np.random.default_rng(6))
    assert 8.5 < arl1 < 10.0
    rng = np.random.default_rng(12)
    delays = []
    for _ in range(100):
        x = _journal(rng, step_at=300)
        base = spc.baseline(x[:100])
        after = [i for i, _ in spc.signals(x, base) if i >= 299]
        delays.append(after[0] - 299 + 1)          # facets from the step to the alarm, inclusive
    delays = np.array(delays)
    assert delays.mean() <= arl1 + 3 * delays.std(ddof=1) / np.sqrt(delays.size) + 3 * se
    # the first journal of the series, on its own
    assert delays[0] <= np.percentile(delays, 95)


def test_rules_mark_the_textbook_patterns():
    base = spc.Baseline(0.0, 1.0, spc.D2, 100)
    v = spc.violations([0, 0, 3.5, 0, 2.5, 0.2, 2.5, 0, 1.5, 1.5, -0.2, 1.5, 1.5], base)
    assert list(v["WE1"]) == [2]
    assert list(v["WE2"]) == [4, 6]               # (3.5, 0, 2.5) and (2.5, 0.2, 2.5): two of three beyond 2
    assert 12 in v["WE3"]                          # 1.5 1.5 -0.2 1.5 1.5: four of five beyond 1 sigma
    v = spc.violations([0.1] * 7 + [-0.1] + [0.1] * 8, base)
    assert list(v["WE4"]) == [15]                  # the second run reaches 8
    v = spc.violations([0, 1, 2, 3, 4, 5, 6] , spc.Baseline(0.0, 10.0, 1.0, 10), "nelson")
    assert list(v["N3"]) == [5, 6]                 # 6 rising points end at index 5
    alt = [0.5 * (-1) ** i for i in range(14)]
    assert list(spc.violations(alt, base, "nelson")["N4"]) == [13]


def test_signals_restart_after_an_alarm():
    base = spc.Baseline(0.0, 1.0, spc.D2, 100)
    x = [0.5] * 20
    assert [i for i, _ in spc.signals(x, base)] == [7, 15]       # 8 in a row, then 8 more
    assert spc.alarm_at_last(x[:8], base) == ("WE4",)
    assert spc.alarm_at_last(x[8:15], base) == ()


def test_baseline_uses_the_moving_range():
    x = np.array([10.0, 12.0, 11.0, 13.0, 12.0])
    b = spc.baseline(x)
    mr = (2 + 1 + 2 + 1) / 4
    assert b.centre == pytest.approx(11.6) and b.mr_bar == pytest.approx(mr)
    assert b.sigma == pytest.approx(mr / 1.128) and b.ucl == pytest.approx(11.6 + 3 * mr / 1.128)
    assert b.mr_ucl == pytest.approx(3.267 * mr)
    with pytest.raises(ValueError, match="do not vary"):
        spc.baseline([1.0, 1.0, 1.0])


def test_cp_and_cpk_against_a_hand_computation():
    # focal lengths of ten facets, design 5.33 m +- 2 %: LSL 5.2234, USL 5.4366
    x = np.array([5.40, 5.42, 5.41, 5.43, 5.42, 5.44, 5.41, 5.42, 5.43, 5.42])
    lsl, usl = 5.33 * 0.98, 5.33 * 1.02
    mean = 54.20 / 10                                           # 5.420
    mr = (0.02 + 0.01 + 0.02 + 0.01 + 0.02 + 0.03 + 0.01 + 0.01 + 0.01) / 9   # 0.14 / 9
    s_within = mr / 1.128                                       # 0.013790
    dev = x - mean
    s_overall = np.sqrt(np.sum(dev ** 2) / 9)                   # sqrt(0.0012 / 9) = 0.011547
    c = spc.capability(x, lsl, usl)
    assert c["mean"] == pytest.approx(mean)
    assert c["sigma_within"] == pytest.approx(0.0137904, rel=1e-5)
    assert c["cp"] == pytest.approx((usl - lsl) / (6 * s_within))           # 0.2132 / 0.082742 = 2.577
    assert c["cp"] == pytest.approx(2.5767, abs=1e-3)
    assert c["cpk"] == pytest.approx((usl - mean) / (3 * s_within))        # 0.0166 / 0.041371 = 0.4012
    assert c["cpk"] == pytest.approx(0.4012, abs=1e-3)
    assert c["pp"] == pytest.approx(0.2132 / (6 * s_overall)) and c["ppk"] == pytest.approx(0.0166 / (3 * s_overall))
    # one-sided (slope error: only a maximum): no Cp, Cpk from the upper limit
    c = spc.capability([0.7, 0.8, 0.75, 0.72], None, 2.0)
    assert c["cp"] is None and c["cpk"] == pytest.approx((2.0 - 0.7425) / (3 * (0.1 + 0.05 + 0.03) / 3 / 1.128))


def test_ewma_limits_widen_to_their_asymptote():
    base = spc.Baseline(0.0, 1.0, spc.D2, 100)
    lo, hi = spc.ewma_limits(200, base, lam=0.2)
    assert hi[0] == pytest.approx(3 * 0.2) and hi[-1] == pytest.approx(3 * np.sqrt(0.2 / 1.8))
    x = np.r_[np.zeros(50), np.full(50, 1.5)]
    first = spc.ewma_violations(x, base)[0]
    assert 50 <= first < 65
