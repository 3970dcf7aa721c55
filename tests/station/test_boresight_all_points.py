"""The electronic boresight holds for the reported parabola, the one fitted to every valid pixel (issue 26).

The shape and boresight iterate on a subsample (every 10th valid pixel); the reported parabola is fitted to
all of them. On a gore, whose slopes differ from any parabola's by about 1 mrad in a structured way, the
two fits' normals at the alignment point differed by up to a few tenths of a mrad, so the frame the figures
were stated in was not the one the definition (and the twin's truth) gives, and the design residual's RMS y
was off by up to 0.049 mrad (5 %) against a U of 0.01 on drawn gore stations. The boresight now closes on
every pixel (boresight.close_on_all_points).

Cases: the drawn gore stations of seed 21 whose subsample boresight was furthest off (stations 6, 12 and 16,
area and point-sampled edges, 2 to 4 captures each: 9 captures; before the change their design RMS y was
off by -0.019 to +0.049 mrad, median 0.020).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest

from sofast_station.station import population as pop

SEED = 21
STATIONS = {16: 4, 6: 3, 12: 2}
#: The design residual's RMS against the truth's, mrad. After the change these 9 captures are within
#: 0.0002-0.0175 (the rest: the corner pose's error of up to 24 mm and 10 mrad, and the noise's bias, both in U).
DESIGN_RMS_TOLERANCE_MRAD = 0.025
#: The first capture's analysis inputs, kept by the fixture.
GRAB: dict = {}


@pytest.fixture(scope="module")
def gore_captures():
    """(case, analysis, design) of every capture of :data:`STATIONS`."""
    kept = []
    original = pop.analyse

    def keep(*args, **kwargs):
        result = original(*args, **kwargs)
        kept.append(result)
        if not GRAB:                 # the first capture's inputs, for a rerun of its stages
            GRAB["args"] = args[:6]  # frames, fringes, geometry, design, distance, settings
        return result

    out = []
    pop.analyse = keep
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for index, captures in STATIONS.items():
                spec = pop.draw_station(index, SEED, ("gore",), ("area", "point"))
                kept.clear()
                cases = pop.run_station(spec, captures, SEED, Path(tmp), {}, faults=())
                design = pop.kind_config(spec["kind"], Path(tmp)).design
                out += [(case, a, design) for case, a in zip(cases, kept)]
    finally:
        pop.analyse = original
    return out


def test_the_reported_parabola_has_the_design_normal_at_the_alignment_point(gore_captures):
    assert len(gore_captures) == sum(STATIONS.values())
    for case, a, design in gore_captures:
        xa, ya = design.alignment_point_m
        a_, b_, c_, d_, e_ = (float(v) for v in a.coefficients[:5])
        fitted = np.arctan([2 * a_ * xa + c_ + e_ * ya, 2 * b_ * ya + d_ + e_ * xa])
        wanted = np.arctan(np.array([xa, ya]) / (2.0 * design.focal_length_m))
        # the loop stops when a step turns it by less than 1 microradian
        assert np.all(np.abs(fitted - wanted) < 2e-6), (case["index"], case["capture"], fitted - wanted)


def test_the_design_residual_is_stated_in_the_truths_frame(gore_captures):
    errors = []
    for case, a, design in gore_captures:
        for axis in ("x", "y"):
            key = f"slope_rms_mrad.design.{axis}"
            errors.append(case["figures"][key] - case["truth"][key])
    errors = np.abs(errors)
    print(f"|design RMS - truth| over {len(gore_captures)} captures, x and y: median {np.median(errors):.4f}, "
          f"largest {errors.max():.4f} mrad")
    assert errors.max() < DESIGN_RMS_TOLERANCE_MRAD


def test_the_subsample_fit_is_still_the_subsamples_own(gore_captures):
    """``subsample_fit`` (what a program that stops at the subsample, OpenCSP's SOFAST, reports) is the
    subsample's converged parabola, not the all-point fit the closing steps end with: the reduction
    stopped after the subsample's boresight gives the same focal lengths to the last bit."""
    from sofast_station.measure.pipeline import reduce_stages

    case, a, design = gore_captures[0]
    red, _ = reduce_stages(*GRAB["args"], stop_after_boresight=True)
    sub = red.shape.solution.coefficients
    assert a.figures["subsample_fit"]["focal_length_x_m"] == 1.0 / (4.0 * float(sub[0]))
    assert a.figures["subsample_fit"]["focal_length_y_m"] == 1.0 / (4.0 * float(sub[1]))
    # on a gore the two fits differ (else this test could not tell them apart)
    assert a.figures["subsample_fit"]["focal_length_x_m"] != a.figures["focal_length_x_m"]
