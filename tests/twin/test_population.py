"""Issue 29: a simulated line whose facets differ (``[simulation.population]``).

The simulated line made the same facet every time (f_x std 0.2 mm over 40 facets), so control charts,
acceptance, drift alarms and yield had nothing to show. Facet k of a run is drawn from (seed, k): part-to-part
variation of f, twist and slope error, an occasional dent, a slow drift of f. Each drawn facet is traced from
the nominal one (:meth:`TwinStation.with_facet`), which must give what a new trace gives.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.errors import ConfigError
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.twin import TrueFacet, TwinOptics, TwinStation
from sofast_station.twin.outline import inside_outline
from sofast_station.twin.population import FacetPopulation
from sofast_station.twin.station import MAX_KEPT_EDGE_SHIFT_PX

NOMINAL = TrueFacet(focal_length_x_m=5.42, focal_length_y_m=5.35, twist_mrad_per_m=0.12, slope_error_rms_mrad=0.5,
                    surface_seed=7)
LINE = FacetPopulation(seed=11, focal_length_sd=0.001, twist_sd_mrad_per_m=0.05, slope_error_sd_mrad=0.05,
                       defect_rate=0.03, drift_focal_length_per_100=0.001)


def test_the_same_seed_makes_the_same_line_facet_by_facet(design):
    again = FacetPopulation(**dataclasses.asdict(LINE))
    assert [LINE.draw(NOMINAL, k, design) for k in range(20)] == [again.draw(NOMINAL, k, design) for k in range(20)]
    facets = [LINE.draw(NOMINAL, k, design) for k in range(20)]
    assert len({f.focal_length_x_m for f in facets}) == 20 and len({f.surface_seed for f in facets}) == 20
    other = dataclasses.replace(LINE, seed=12)
    assert other.draw(NOMINAL, 3, design) != LINE.draw(NOMINAL, 3, design)
    assert all(f.placement_mm == NOMINAL.placement_mm for f in facets)         # placement is not varied


def test_spread_drift_and_defects_follow_the_population(design):
    """4000 facets: each statistic within four of its standard errors (a false failure in about 1e-4 per
    statistic; the draws are deterministic, so this is a check of the drawing, not a gamble)."""
    n = 4000
    steady = dataclasses.replace(LINE, drift_focal_length_per_100=0.0)
    facets = [steady.draw(NOMINAL, k, design) for k in range(n)]
    fx = np.array([f.focal_length_x_m for f in facets]) / 5.42 - 1
    fy = np.array([f.focal_length_y_m for f in facets]) / 5.35 - 1
    twist = np.array([f.twist_mrad_per_m for f in facets])
    slope = np.array([f.slope_error_rms_mrad for f in facets])
    for values, mean, sd in ((fx, 0.0, 0.001), (fy, 0.0, 0.001), (twist, 0.12, 0.05), (slope, 0.5, 0.05)):
        assert abs(values.mean() - mean) < 4 * sd / np.sqrt(n)
        assert abs(values.std(ddof=1) / sd - 1) < 4 * np.sqrt(0.5 / (n - 1))
    assert abs(np.corrcoef(fx, fy)[0, 1]) < 4 / np.sqrt(n)                     # each axis on its own
    dented = [f.dents[0] for f in facets if f.dents]
    assert abs(len(dented) - 0.03 * n) < 4 * np.sqrt(n * 0.03 * 0.97)
    xy = np.array([[d["x_m"], d["y_m"]] for d in dented])
    assert inside_outline(xy[:, 0], xy[:, 1], design.outline_m).all()
    assert all(-0.25e-3 <= d["depth_m"] <= -0.05e-3 and 0.02 <= d["radius_m"] <= 0.04 for d in dented)
    # the drift moves the mean and nothing else: the same draws, shifted by 0.1 % per 100 facets
    drifting = [LINE.draw(NOMINAL, k, design) for k in (0, 100, 1000)]
    for k, f in zip((0, 100, 1000), drifting):
        same = steady.draw(NOMINAL, k, design)
        assert f.focal_length_x_m == pytest.approx(same.focal_length_x_m + 5.42 * 0.001 * k / 100, rel=1e-12)
        assert f.twist_mrad_per_m == same.twist_mrad_per_m and f.dents == same.dents


def test_a_bad_population_is_refused_naming_the_key():
    for table, match in (({"focal_length_sd": -0.1}, "focal_length_sd"), ({"defect_rate": 1.5}, "defect_rate"),
                         ({"defect_depth_mm": [0.3, 0.1]}, "defect_depth_mm"), ({"seed": -1}, "seed"),
                         ({"drift": 0.1}, "unknown key 'drift'"), ({"drift_focal_length_per_100": 0.5}, "per 100")):
        with pytest.raises(ConfigError, match=match):
            FacetPopulation.from_dict(table)


@pytest.fixture(scope="module")
def small(design):
    camera = CameraIntrinsics(400, 300, [[3409, 0, 199.5], [0, 3409, 149.5], [0, 0, 1]],
                              [-0.05, 0.1, 0.0002, -0.0001, 0.0])
    geometry = layout_station(design, camera, ScreenSpec(1920, 1080, 0.000275), separation_m=0.34)
    return TwinStation(geometry, design, NOMINAL, TwinOptics.noise_free())


def test_a_drawn_facet_is_traced_as_a_new_trace_would(small, design):
    """The next facet's twin from the nominal one (same outline, new surface) against a station traced anew
    for it: the same screen point for every pixel that sees the facet, the same frames but for the pixels the
    edge crosses (their exact area coverage moves with the outline's image, by well under its
    MAX_KEPT_EDGE_SHIFT_PX), every figure of the truth the new surface's."""
    facet = dataclasses.replace(LINE.draw(NOMINAL, 5, design),
                                dents=({"x_m": 0.1, "y_m": -0.05, "depth_m": -2e-4, "radius_m": 0.03},))
    fast = small.with_facet(facet)
    anew = TwinStation(small.geometry, design, facet, small.optics)
    assert fast.trace.coverage is small.trace.coverage and fast.surface.facet == facet    # the outline was kept
    common, i_fast, i_anew = np.intersect1d(fast.trace.seen_idx, anew.trace.seen_idx, return_indices=True)
    assert common.size > 0.999 * anew.trace.seen_idx.size
    np.testing.assert_allclose(fast.trace.u_scr_m[i_fast], anew.trace.u_scr_m[i_anew], rtol=0, atol=1e-9)   # metres
    np.testing.assert_allclose(fast.trace.slope[i_fast], anew.trace.slope[i_anew], rtol=0, atol=1e-12)
    # The kept outline moves less than MAX_KEPT_EDGE_SHIFT_PX: only pixels the edge crosses change their (exact
    # area) coverage, each by at most that shift times the edge's length in the pixel (sqrt 2 at most).
    changed = np.abs(fast.coverage - anew.coverage) > 0
    edge = ((fast.coverage > 0) & (fast.coverage < 1)) | ((anew.coverage > 0) & (anew.coverage < 1))
    print(f"{changed.sum()} pixels' coverage changed, by at most {np.abs(fast.coverage - anew.coverage).max():.4f}")
    assert not np.any(changed & ~edge)
    assert np.abs(fast.coverage - anew.coverage).max() <= np.sqrt(2.0) * MAX_KEPT_EDGE_SHIFT_PX
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (1080, 1920), dtype=np.uint8)
    diff = np.abs(fast.capture(image).astype(int) - anew.capture(image).astype(int))
    assert diff[~changed].max() == 0, "frames differ away from the edge pixels whose coverage changed"
    assert fast.measured_distance_m() == anew.measured_distance_m()
    # a facet placed elsewhere in the fixture is traced anew
    moved = small.with_facet(dataclasses.replace(facet, placement_mm=(1.0, 0.0, 0.0)))
    assert moved.trace.coverage is not small.trace.coverage and not np.array_equal(moved.coverage, small.coverage)


def test_a_drawn_facets_twin_is_freed_when_dropped_without_the_garbage_collector(small, design):
    """The simulated line draws a new twin per facet, each keeping its display samples (tens to a hundred MB
    at full resolution). Their cache's weak-reference callback held the twin's dict, a reference cycle that
    only a full garbage collection freed: a soak's station grew 470 MB per 100 cycles. Dropped, a twin must
    go at once, by reference counting alone (the collector off), while the display image lives on."""
    import gc
    import weakref

    screen = small.geometry.screen
    image = np.full((screen.height_px, screen.width_px), 128, np.uint8)
    image.setflags(write=False)                 # a rendered pattern: read-only, cached by the twin
    twin = small.with_facet(LINE.draw(NOMINAL, 3, design))
    gc.collect()
    gc.disable()
    try:
        twin.capture(image)
        assert twin.renderer._samples, "the read-only image was not cached: this test would prove nothing"
        gone = weakref.ref(twin)
        sample = weakref.ref(next(iter(twin.renderer._samples.values()))[1])      # the cached display sample
        del twin
        assert gone() is None and sample() is None, "the twin's display samples outlive it"
        assert weakref.getweakrefcount(image) == 0
    finally:
        gc.enable()
