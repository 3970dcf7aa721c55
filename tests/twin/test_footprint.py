"""A camera pixel integrates the display over its footprint on the screen (``TwinOptics.screen_grid``).

Far from the screen a camera pixel sees many display pixels: one of the population's heliostat station (its
400 x 300 camera at 4 m from a 2.64 m screen of 1.1 mm pitch) spans about 9.7 of them. Sampling the display
at the pixel's centre ray alone shows the display's pixel steps and the fringes' rounding at full depth, a
ripple no camera sees (issue 47: the heliostat stations' focal-length bias).

The truth here is written without the footprint's code: each pixel's footprint from its neighbours' centre-ray
screen points (the plain trace), and the average of a sinusoid over a 4 x 4 grid spanning that parallelogram,
in closed form.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.station.population import kind_config
from sofast_station.twin import TrueFacet, TwinOptics, TwinStation

#: Display pixels per period of the test's fringes along x (a footprint of about half a period).
PERIOD_PX = 20.0


def _grid_average(x: np.ndarray, n: int) -> np.ndarray:
    """How much of a sinusoid's amplitude survives the mean of n samples spaced 1/n of a width x periods
    across, centred: sin(pi x) / (n sin(pi x / n)) (x = 0: 1)."""
    x = np.asarray(x, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.sin(np.pi * x) / (n * np.sin(np.pi * x / n))
    return np.where(np.abs(x) < 1e-12, 1.0, out)


@pytest.fixture(scope="module")
def heliostat(tmp_path_factory):
    cfg = kind_config("heliostat", tmp_path_factory.mktemp("records"))
    facet = TrueFacet(focal_length_x_m=95.0, focal_length_y_m=104.0, slope_error_rms_mrad=0.3,
                      slope_error_correlation_m=0.04, surface_seed=9)
    optics = TwinOptics(display_gamma=1.0, display_floor=0.0, ambient=0.0, background=0.0, vignetting=0.0)
    return cfg, facet, optics.noise_free()


def _four_step(twin, cfg) -> tuple[np.ndarray, np.ndarray]:
    """Phase (rad) and modulation (DN) every pixel sees of an x fringe of PERIOD_PX display pixels, from the
    noise-free signal before rounding."""
    scr = cfg.geometry.screen
    col = np.arange(scr.width_px) + 0.5
    frames = []
    for k in range(4):
        row = 127.5 + 120.0 * np.cos(2.0 * np.pi * col / PERIOD_PX - 0.5 * np.pi * k)
        image = np.broadcast_to(np.rint(row).astype(np.uint8), (scr.height_px, scr.width_px))
        frames.append(twin.linear_dn(np.ascontiguousarray(image)).astype(np.float64))
    s, c = frames[1] - frames[3], frames[0] - frames[2]
    return np.arctan2(s, c), 0.5 * np.hypot(s, c)


def test_a_pixel_averages_the_display_over_its_footprint(heliostat):
    """With ``screen_grid = 4`` a fringe of 20 display pixels reaches each pixel with the amplitude the mean of
    a 4 x 4 grid over its footprint leaves, sin(pi x)/(4 sin(pi x / 4)) per footprint edge (x: the edge's
    extent along the fringes in periods, from the neighbours' centre rays), about 0.675 here; and at the centre
    ray's phase to second order (the footprint's centroid is off its centre by the screen map's curvature over
    the pixel, which the facet's slope errors make).

    47,554 interior pixels (fully covered, neighbours seen). Measured: the amplitude ratio's median deviation
    from the closed form 0.0021, its 95th percentile 0.0052 (the footprint from neighbours is a two-pixel chord
    of a map the slope errors curve, and the display's rounding to whole commands); the phase differs by
    2.6 mrad RMS (9 um of the 22 mm period: the centroid's offset), its mean by 0.02 mrad. Tolerances: 0.005
    (median), 0.01 (95 %), 4 mrad RMS and 0.5 mrad mean (the centroid's offset averages out over the facet;
    without the footprint, the ratio would be 1, 0.3 from the closed form)."""
    cfg, facet, optics = heliostat
    point = TwinStation(cfg.geometry, cfg.design, facet, optics)
    grid = TwinStation(cfg.geometry, cfg.design, facet, dataclasses.replace(optics, screen_grid=4))
    phase_1, mod_1 = _four_step(point, cfg)
    phase_4, mod_4 = _four_step(grid, cfg)

    u = np.asarray(point.screen_position_m)[..., 0] / cfg.geometry.screen.pitch_m     # display columns
    d_col = 0.5 * (u[1:-1, 2:] - u[1:-1, :-2])
    d_row = 0.5 * (u[2:, 1:-1] - u[:-2, 1:-1])
    inner = (np.asarray(point.coverage)[1:-1, 1:-1] >= 1.0) & np.isfinite(d_col) & np.isfinite(d_row)
    predicted = _grid_average(d_col / PERIOD_PX, 4) * _grid_average(d_row / PERIOD_PX, 4)
    with np.errstate(invalid="ignore", divide="ignore"):          # (pixels that see no fringe: not inner)
        ratio = mod_4[1:-1, 1:-1] / mod_1[1:-1, 1:-1]
    dev = np.abs(ratio - predicted)[inner]
    print(f"{inner.sum()} pixels, footprint {np.median(np.abs(d_col[inner])):.2f} x "
          f"{np.median(np.abs(d_row[inner])):.2f} px, predicted ratio {np.median(predicted[inner]):.3f}, "
          f"|deviation| median {np.median(dev):.4f}, 95 % {np.percentile(dev, 95):.4f}")
    assert inner.sum() > 20_000
    assert np.median(dev) < 0.005 and np.percentile(dev, 95) < 0.01
    turn = np.angle(np.exp(1j * (phase_4 - phase_1)))[1:-1, 1:-1][inner]
    print(f"phase difference RMS {1e3 * np.sqrt(np.mean(turn ** 2)):.3f} mrad, mean {1e3 * np.mean(turn):+.3f} mrad")
    assert np.sqrt(np.mean(turn ** 2)) < 4e-3 and abs(np.mean(turn)) < 0.5e-3


def test_the_next_facets_footprint_is_a_new_traces(heliostat):
    """:meth:`TwinStation.with_facet` (the line's next facet, the outline kept) gives every pixel the footprint a
    new trace of that facet gives (to 1e-9 m: Newton's tolerance on the hits, 1e-12 m, through the 4 m
    lever)."""
    cfg, facet, optics = heliostat
    optics = dataclasses.replace(optics, screen_grid=3)
    first = TwinStation(cfg.geometry, cfg.design, facet, optics)
    other = dataclasses.replace(facet, focal_length_x_m=96.0, surface_seed=10)
    fast = first.with_facet(other)
    anew = TwinStation(cfg.geometry, cfg.design, other, optics)
    assert fast.trace.coverage is first.trace.coverage            # the fast path, not a new trace
    assert fast.trace.footprint_u_scr_m.shape == (fast.trace.seen_idx.size, 9, 2)
    common, i_fast, i_anew = np.intersect1d(fast.trace.seen_idx, anew.trace.seen_idx, return_indices=True)
    assert common.size > 0.99 * anew.trace.seen_idx.size
    np.testing.assert_allclose(fast.trace.footprint_u_scr_m[i_fast], anew.trace.footprint_u_scr_m[i_anew],
                               rtol=0, atol=1e-9)
