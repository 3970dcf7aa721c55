"""Issue 47, item 1: the heliostat facet of f 100 m at 10 m from a 4.8 m screen of 2.5 mm pitch (6000 px camera,
fixtures/stations/heliostat-10m.toml) measured within 0.002 % of its like-for-like truth without noise.

The truth is the twin's exact surface fitted the way the pipeline fits, over the pixels the analysis kept
(:func:`~sofast_station.twin.truth.ground_truth`). Three true facets (the fixture's 95 / 104 m, twist and
0.3 mrad of slope error, three surface seeds), noise-free captures. Tolerance: the issue's 20 ppm of f; this
station's measured errors are -4.5 to +3.6 ppm (x) and -6.2 to -1.5 ppm (y) on these seeds (-5.6 to +3.1 and
-5.9 to -1.1 before the height cells were centred, 2026-12-07), and with the
default 4 fringe periods (1.2 m each, about the screen patch the facet reflects) they were +23 to +42 ppm
(x) and +6 to +18 ppm (y) with the display's rounding taken off, 52-101 ppm without (docs/method.md,
"Nearly flat facets far from the screen"). 3 captures, about 8 s of CPU each: seed 9 in the default set, 3
and 17 with ``-m slow`` (tests/conftest.py LONG_TESTS).
"""

from __future__ import annotations

import dataclasses

import pytest

from sofast_station.measure.analysis import analyse
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import capture
from sofast_station.twin.truth import ground_truth
from tests.conftest import ROOT, load_station


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    return load_station(ROOT / "fixtures/stations/heliostat-10m.toml", tmp_path_factory.mktemp("far") / "data")


@pytest.mark.parametrize("surface_seed", [9, 3, 17])
def test_focal_length_within_0_002_percent_of_truth(config, surface_seed):
    assert config.fringes.periods_x[-1] == 16 and config.fringes.drawn, "the station's fringes as shipped"
    sim = dict(config.simulation)
    sim["facet"] = {**sim["facet"], "surface_seed": surface_seed}
    cfg = dataclasses.replace(config, simulation=sim)
    station = open_station(cfg, seed=surface_seed, noise=False)
    try:
        frames, distance = capture(station)
        a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis, rays_cam=station.rays_cam)
        truth = ground_truth(station.twin, a.valid)
    finally:
        station.close()
    for k in ("focal_length_x_m", "focal_length_y_m"):
        err = a.figures[k] / truth[k] - 1
        print(f"seed {surface_seed} {k}: {a.figures[k]:.4f} m vs truth {truth[k]:.4f} m, {1e6 * err:+.1f} ppm")
        assert abs(err) < 2e-5, f"{k} {1e6 * err:+.1f} ppm off like-for-like truth"
    # the facet really is not the design: the test would see a bias toward it
    assert abs(truth["focal_length_x_m"] / 95.0 - 1) < 0.01 and abs(truth["focal_length_y_m"] / 104.0 - 1) < 0.01
