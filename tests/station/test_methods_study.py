"""Issue 42 item 5: both methods on the same capture of a population station (station/methods_study.py).

One drawn heliostat-facet station (seed 0, station 0: 400 x 300 camera), two placements, each photographed with the
26 fringe frames (16 periods at the finest) and with one dot frame. What must hold whatever the draw: both methods
measured every capture; the fixed method used one frame, so its capture time is 1/26 of the fringes' (frames x the
same settle + exposure), with one point per dot (a few hundred against tens of thousands of pixels); its focal
lengths lie within their U of the twin's truth (the U is a 95 % claim: over this seed's two captures and two axes
an error beyond U would be a 1-in-20 event per figure, and the population study's coverage, docs/method.md, is the
statistical check). A dish station's layout is refused by name.

Both ends of the fixed method's U on the figures its centroid model error reaches (docs/uncertainty.md, "Dot
centroid model"): the twist E and the slope RMS about the parabola (x, y), with the focal lengths, over the two
captures. Low end: each error within its U. High end: the twelve values of error / (U / 2) pooled (these ten
and the boresight x's two, below) have an RMS of at least 0.3: for a right U they are about standard normal, so
their mean square is about chi-square with 12 degrees of freedom over 12, below 0.09 with probability 2e-5 (fewer
effective degrees of freedom, as f x and the slope RMS x share errors, make it at most 3e-3 at 6); a U stated
three times too large would fail it. Before the model error the twist's and slope RMS values' errors were 2-5
times U / 2 on this population.

The boresight x from both sides too, with its corners' model error (docs/uncertainty.md, "Dot frame's
corners"): each capture's error within its U (without the model error the first capture's was 2.02 times
U / 2 here, the population's RMS 1.69), and its two values of error / (U / 2) with an RMS of at least 0.15
(for a right U their mean square is chi-square with 2 degrees of freedom over 2, below 0.0225 with
probability 1 - exp(-0.0225) = 2 %).
"""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.station.methods_study import run_methods, summarise_methods


#: The heliostat station's fringe capture: dark, white, and 4 phase steps of 3 periods (1, 4, 16) in x and y.
FRINGE_FRAMES = 2 + 2 * 3 * 4


@pytest.fixture(scope="module")
def cases():
    return run_methods(2, seed=0, per_station=2, kinds=("heliostat",))


def test_both_methods_measure_the_same_captures(cases):
    fringe = [c for c in cases if c["method"] == "fringe"]
    fixed = [c for c in cases if c["method"] == "fixed"]
    assert [c["outcome"] for c in fringe + fixed] == ["measured"] * 4, [c.get("error") for c in cases]
    for a, b in zip(fringe, fixed):
        assert (a["index"], a["capture"]) == (b["index"], b["capture"]) and a["truth"] != {}
        assert a["n_frames"] == FRINGE_FRAMES and b["n_frames"] == 1
        assert b["capture_s"] == pytest.approx(a["capture_s"] / FRINGE_FRAMES)
        assert 150 <= b["n_points"] < a["n_points"] / 50
    z, z_boresight = [], []
    for b in fixed:
        for name in ("focal_length_x_m", "focal_length_y_m", "twist_mrad_per_m", "slope_rms_mrad.parabola.x",
                     "slope_rms_mrad.parabola.y", "boresight_mrad.x"):
            err = b["figures"][name] - b["truth"][name]
            assert abs(err) <= b["U"][name], (name, err, b["U"][name])
            z.append(err / (b["U"][name] / 2))
        z_boresight.append(z[-1])
    assert np.sqrt(np.mean(np.square(z))) >= 0.3, z
    assert np.sqrt(np.mean(np.square(z_boresight))) >= 0.15, z_boresight
    s = summarise_methods(cases)
    assert s["fixed"]["frames"] == 1 and s["fringe"]["frames"] == FRINGE_FRAMES and s["layout_refused"] == []
    assert {r["figure"] for r in s["fixed"]["coverage"]} >= {"focal_length_x_m", "twist_mrad_per_m"}


def test_the_study_refuses_a_dish_by_its_layout():
    from sofast_station.errors import StationError
    from sofast_station.station.study_cli import cmd_study_methods

    class Args:
        captures, per_station, seed, kinds, out, json, config = 1, 1, 0, "dish", None, False, None

    with pytest.raises(StationError, match="cannot be measured by the fixed method"):
        cmd_study_methods(Args())
