"""Issue 47, item 1 at the population's heliostat station: the facet of f about 100 m at 4 m from a 2.64 m screen
(fixtures/stations/heliostat.toml, its camera at 400 x 300 as the population uses it), three drawn stations of
the population (:func:`~sofast_station.station.population.draw_station`, kind "heliostat": each its own true
facet, slope errors, lens distortion, edge model, display gamma and flicker), noise-free captures.

The truth is the twin's exact surface fitted the way the pipeline fits, over the pixels the analysis kept
(:func:`~sofast_station.twin.truth.ground_truth`). The twin's truth is put into the pipeline one stage at a
time (docs/method.md, "Nearly flat facets far from the screen"). Measured on these stations (f x / y, ppm):
station 2 (k1 +0.27, point-sampled edge, 0.58 mrad of slope error over 2.9 cm), 6 (k1 -0.28, bevelled rim)
and 10 (k1 -0.10, defocused lens):

* the twin's true screen positions and its true facet pose: +18/+11, -6/-4, +5/+9. Not zero (on the fixture's
  facet without slope errors at 1600 x 1200 it is 0.0/0.0; the pixel rays agree with the twin's to 1e-10 rad
  at these lenses): most on the facet with the most and finest slope error, so probably the surface heights the
  closing integrates (a height error dz is 2 dz / D^2 of curvature, 12 ppm per um at 4 m); not found.
* the true positions, the corner pose as found: +20/+13, -25/-25, +8/+12. The corner pose's sideways placement
  of the measure point (about 10 um at 4 m on the fixture's facet) becomes a height error of the whole facet
  through the range finder's oblique distance to the screen centre.
* the whole pipeline (16 periods, as shipped): -2.5/+53.9, -16.7/-40.1, -9.1/+36.4 (-18/+60, -85/-44, -22/-38
  before the twin's pixels integrated their footprint on the screen, ``population.Kind.screen_grid``, and the
  drawn fringes' correction saw the display through it, ``phase.pixel_footprint_px``). What the positions add
  is now the camera's own rounding to whole counts (noise-free, one capture's pattern of it): frames the camera
  did not round come within 25 ppm on seed 0's seven heliostat stations without a blurred lens
  (docs/method.md, "Nearly flat facets far from the screen").

The issue's 20 ppm is not met at 4 m on 8-bit frames (docs/method.md states it as open): the asserts are guards
at about 1.4 times these stations' largest error per stage, so a change that makes a stage worse fails.

3 drawn stations, about 12 s of CPU; station 2 runs with ``-m slow`` (tests/conftest.py), stations 6 and 10 in
the default set.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.measure import pipeline
from tests.station.population_capture import noise_free_capture, truth_of

#: Stations of the population of seed 0 that are heliostat stations (kinds in turn: every fourth from 2).
STATIONS = (2, 6, 10)
#: The whole pipeline's guard, ppm of f (1.4 times the largest error measured on these stations, +53.9 ppm).
LIMIT_PPM = 75.0


def _errors_ppm(twin, reduction) -> list[float]:
    truth = truth_of(twin, reduction)
    return [1e6 * (reduction.figures[k] / truth[k] - 1) for k in ("focal_length_x_m", "focal_length_y_m")]


@pytest.fixture(scope="module")
def images():
    return {}


@pytest.mark.parametrize("index", STATIONS)
def test_focal_length_against_truth_stage_by_stage(index, images, tmp_path):
    st, twin, whole, args = noise_free_capture(index, "heliostat", images, tmp_path)
    spec, cfg = st.spec, st.config
    assert cfg.fringes.periods_x[-1] == 16 and cfg.fringes.drawn, "the station's fringes as shipped"

    # the twin's true screen position of every pixel the analysis kept
    phases = whole.phases
    true_xy = twin.screen_position_m.reshape(-1, 2)[whole.region.idx]
    ok = phases.ok & np.all(np.isfinite(true_xy), axis=1)
    true_phases = dataclasses.replace(phases, ok=ok, positions_m={a: np.where(ok, true_xy[:, i], 0.0)
                                                                  for i, a in enumerate("xy")})
    positions = pipeline.rerun(whole, "rays", phases=true_phases, **args)
    true_pose = dataclasses.replace(positions.pose, facet_to_camera=twin.facet_to_camera)
    both = pipeline.rerun(positions, "shape", pose=true_pose, **args)

    errors = {name: _errors_ppm(twin, r) for name, r in
              (("pipeline", whole), ("true positions", positions), ("true positions and pose", both))}
    for name, (ex, ey) in errors.items():
        print(f"station {index} (k1 {spec['k1']:+.2f}, {spec['edge']}) {name}: f x {ex:+.1f} ppm, y {ey:+.1f} ppm")
    # guards at about 1.4 times the largest error measured on these stations (docstring), not the 20 ppm
    assert max(map(abs, errors["true positions and pose"])) < 25.0
    assert max(map(abs, errors["true positions"])) < 35.0
    assert max(map(abs, errors["pipeline"])) < LIMIT_PPM
