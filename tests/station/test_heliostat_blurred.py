"""Issue 47, item 1: the population's heliostat station (f about 100 m at 4 m, its camera at 400 x 300) with a
lens that blurs, noise-free captures (8-bit, each frame at its own refresh phase), f against the twin's
like-for-like truth (:func:`~sofast_station.twin.truth.ground_truth` over the pixels the analysis kept).

The blur moves the decoded positions by (sigma^2 / 2)(lap s + 2 grad ln A . grad s) (measure/deblur.py), and
its part that grows across the facet read as 100-230 ppm of f. Measured on seed 0's blurred heliostat stations
(2026-12-07; x / y, ppm), without the correction and with it:

* station 30 (Gaussian blur, 10,335 points): -60/-120 and -29/-79
* station 34 (Gaussian blur, edge blur measured 0.65 px): -122/-115 and -19/-9
* station 42 (defocused lens, 0.79 px): -118/-100 and -44/-27

(unrounded frames at one refresh phase: -113/-131 and -10/-25 on station 34, -109/-104 and -36/-30 on 42). Since
the heights' cells are centred (measure/heights.py, centred_slopes): station 34 -83/-102 and +20/+3, station 42
-123/-98 and -49/-24 (the heights had taken up to 40 ppm off station 34's x without it and with it). The
asserts: with the correction within 1.4 times the largest of these two stations' errors before the centring,
without it beyond 75 ppm on both axes, so the test fails if the correction stops working. Station 42 runs
with ``-m slow`` (its cover here: station 34, the same path). About 6 s of CPU per station. The figures' own
sharpening (:func:`~sofast_station.measure.pipeline.sharpened_fit`) is left out of that test, and judged over
drawn facets by the second.

The blur also smooths the facet's fine slope errors, whose projection on the parabola then differs from the
facet's own: with the smooth shift alone f scattered tens of ppm from facet to facet. The sharpening of the
fitted figures takes most of it off, and the budget carries what it leaves as half its size
(:data:`~sofast_station.measure.deblur.ROUGHNESS_LEFT`). Judged over seven drawn facets per station (the
station's own and surface seeds 11-66).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.measure import deblur, pipeline
from sofast_station.measure.analysis import add_sharpening_row
from tests.station.population_capture import noise_free_capture, truth_of

#: station: (limit with the correction, ppm of f)
LIMITS = {34: 30.0, 42: 65.0}


def _errors_ppm(twin, reduction) -> list[float]:
    truth = truth_of(twin, reduction)
    return [1e6 * (reduction.figures[k] / truth[k] - 1) for k in ("focal_length_x_m", "focal_length_y_m")]


@pytest.mark.parametrize("index", sorted(LIMITS))
def test_a_blurred_heliostats_focal_length_with_and_without_the_blurs_shift(index, tmp_path, monkeypatch):
    st, twin, corrected, args = noise_free_capture(index, "heliostat", {}, tmp_path)
    blur = corrected.figures["edge_blur_px"]
    assert blur >= deblur.MIN_BLUR_PX, f"station {index}: the edge blur {blur:.2f} px, the correction's threshold"
    # the smooth shift alone: the figures' sharpening of the fine structure is judged below
    sharpening = corrected.figures["lens_blur_sharpening"]
    figures = {k: corrected.figures[k] - sharpening[k] for k in ("focal_length_x_m", "focal_length_y_m")}
    corrected = dataclasses.replace(corrected, figures=figures)
    frames = st.capture(twin, np.random.default_rng(index))       # the same frames (noise_free_capture's draw)
    monkeypatch.setattr(deblur, "MIN_BLUR_PX", np.inf)
    plain, _ = pipeline.reduce_stages(frames, args["fringes"], args["geometry"], args["design"],
                                      args["measured_distance_m"], args["settings"])
    with_shift, without = _errors_ppm(twin, corrected), _errors_ppm(twin, plain)
    print(f"station {index} ({st.spec['edge']}, edge blur {blur:.2f} px): f x / y {without[0]:+.1f} / "
          f"{without[1]:+.1f} ppm without the blur's shift, {with_shift[0]:+.1f} / {with_shift[1]:+.1f} with it")
    assert max(map(abs, with_shift)) < LIMITS[index]
    assert min(map(abs, without)) > 75.0


#: Surface seeds of the facets the sharpening is judged on (None: the station's own draw).
SURFACE_SEEDS = (None, 11, 22, 33, 44, 55, 66)


@pytest.mark.parametrize("index", sorted(LIMITS))
def test_the_sharpened_fit_takes_most_of_the_blurs_smoothing_off_f_and_the_budget_carries_the_rest(index, tmp_path):
    """Over seven drawn facets of the station (f x and y: 14 values): with the sharpening f's RMS error from the
    like-for-like truth is at most 0.6 of the smooth shift's alone; the budget's row for what it leaves
    (:func:`~sofast_station.measure.analysis.add_sharpening_row`) is right-sized in aggregate (RMS error over RMS
    row 0.6-1.4; 14 values put the RMS's own spread near 20 %) and at least 9 of the 14 errors lie within twice
    it. Measured 2026-12-07 (ppm RMS, without -> with; RMS error / RMS row; within 2 rows): station 34 86.8 -> 38.0,
    1.01, 13 of 14; station 42 45.2 -> 23.0, 1.07, 10 of 14. A facet's own correction is a poor measure of its own
    remainder (station 42's errors beyond twice the row had rows of 4-14 ppm; the remainder has a part the
    correction does not scale, about -17 ppm on station 42), so the row is right-sized on average, not
    facet by facet, and the last assert guards only against its collapse."""
    before, after, row = [], [], []
    for seed in SURFACE_SEEDS:
        st, twin, reduction, _ = noise_free_capture(index, "heliostat", {}, tmp_path / f"s{seed}", surface_seed=seed)
        truth = truth_of(twin, reduction)
        keys = ("focal_length_x_m", "focal_length_y_m")
        figures = {**reduction.figures, **{f"{k}_U": 0.0 for k in keys}}
        added = add_sharpening_row(figures)
        for k in keys:
            correction = reduction.figures["lens_blur_sharpening"][k]
            after.append(1e6 * (reduction.figures[k] / truth[k] - 1))
            before.append(1e6 * ((reduction.figures[k] - correction) / truth[k] - 1))
            row.append(1e6 * added[k] / 2.0 / truth[k])
    after, before, row = np.array(after), np.array(before), np.array(row)
    rms = {name: float(np.sqrt(np.mean(np.square(v)))) for name, v in (("before", before), ("after", after),
                                                                         ("row", row))}
    within = int(np.count_nonzero(np.abs(after) <= 2.0 * row))
    print(f"station {index}: f {rms['before']:.1f} -> {rms['after']:.1f} ppm RMS over {after.size} values; "
          f"error / row {rms['after'] / rms['row']:.2f}; within 2 rows {within}; errors {np.round(after, 1)}, "
          f"rows {np.round(row, 1)}")
    assert rms["after"] <= 0.6 * rms["before"]
    assert 0.6 <= rms["after"] / rms["row"] <= 1.4
    assert within >= 9
