"""Issue 29: a chart is scaled to its data and control limits; specification limits are drawn when they
fit beside the data, else named (the control chart of a 3 mrad limit drew its 0.5 mrad data as a flat line)."""

from __future__ import annotations

import numpy as np

from sofast_station.qc.view import chart_view, nice_ticks


def test_the_data_and_control_limits_fill_the_view_and_far_limits_are_named():
    x = 0.5 + 0.02 * np.random.default_rng(1).standard_normal(50)
    view = chart_view(x, keep=(0.44, 0.56), limits=[(3.0, "USL"), (None, "LSL")])
    assert view.low < 0.44 and view.high > 0.56 and view.high - view.low < 0.2
    assert view.shown == () and view.above == ((3.0, "USL"),) and view.below == ()
    assert view.notes("mrad") == ["USL 3 mrad above the view"]


def test_a_limit_near_the_data_is_drawn_inside_the_view():
    x = np.linspace(5.40, 5.43, 30)
    view = chart_view(x, limits=[(5.4366, "USL"), (5.2234, "LSL")])
    assert view.shown == ((5.4366, "USL"),) and view.below == ((5.2234, "LSL"),)
    assert view.low < 5.40 and 5.4366 < view.high < 5.45
    # the data still fill at least a third of the axis with reach 1
    assert (5.43 - 5.40) / (view.high - view.low) > 1 / 3


def test_constant_and_empty_data_give_a_usable_range():
    view = chart_view([1.0, 1.0, None, float("nan")])
    assert view.low < 1.0 < view.high
    assert chart_view([], limits=[(2.0, "USL")]).shown == ((2.0, "USL"),)


def test_ticks_are_round_and_inside():
    assert nice_ticks(0.43, 0.71, 6) == [0.45, 0.5, 0.55, 0.6, 0.65, 0.7]
    assert nice_ticks(5.2, 5.45, 6) == [5.2, 5.25, 5.3, 5.35, 5.4, 5.45]
    assert nice_ticks(5.2, 5.45, 5) == [5.2, 5.3, 5.4]
    ticks = nice_ticks(-1.3, 1.7, 6)
    assert ticks[0] >= -1.3 and ticks[-1] <= 1.7 and len(ticks) <= 7 and 0.0 in ticks
    assert nice_ticks(1.0, 1.0) == []
