"""The fixed-pattern (dot grid) method (measure/fixed.py) on frames of a facet reflecting a dot grid, drawn by
a ray tracer that shares no code with the detection (tests/measure/dot_render.py: its own camera model,
surface intersection, reflection and area-sampled discs). The truth is the renderer's: its surface's
coefficients (f = 1/(4A), twist = 1000 E) or, with a dent, the least-squares parabola of its exact slopes at
the points the analysis reports (numpy's lstsq here), and its exact slope at every reported point.

Tolerances, from the renderer and the geometry (facet 0.6 m at 4 m, dots 40 mm apart and 11 px apart in the
image, the screen about 4 m from the facet):

* a slope per pixel of a dot's centre: 40 mm / 11.2 px over twice the 4 m to the screen, 0.45 mrad/px;
* the renderer samples each pixel with 3 x 3 rays, so each edge pixel's share of a dot is known to 1/18 of
  the dot's depth: a 4.5 px dot's centre is drawn about 0.02 px off its true one (1 sd), 0.009 mrad; and a
  centre moves by roughly its radius times the noise over the dot's depth, 2.25 px x 1 DN / 125 DN = 0.018 px
  per DN of noise, 0.008 mrad per DN. A dot's slope may so be off by 0.02 + 0.008 sigma_n mrad (RMS, about
  twice both), ``dot_tolerance_mrad``;
* errors of that RMS e at N dots over a facet of half side h move a least-squares slope fit's 2A by
  e / (h sqrt(N / 3)) (1 sd) and E1, E2 by as much: f within 3 f^2 2 e / (h sqrt(N / 3)), twist within
  3000 e / (h sqrt(N / 3)) mrad/m;
* an index off by one dot moves the slope by 40 mm / (2 x 4 m) = 5 mrad: no dot's error may come near that
  (at most 5 times the RMS tolerance).
"""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.errors import DotsNotFoundError, DoubleLatticeError, OriginNotFoundError, TooFewDotsError
from sofast_station.geometry import Pose
from sofast_station.measure.dots import find_pattern_dots, pattern_background
from sofast_station.measure.fixed import (FixedSettings, LcdDotGrid, analyse_fixed, dot_screen, find_origin_mark,
                                          lcd_dot_locations, reduce_fixed)
from sofast_station.measure.pipeline import AnalysisSettings
from sofast_station.measure.screen import FlatScreen, InterpolatedScreen
from sofast_station.measure.uncertainty import InputUncertainties
from tests.measure.dot_render import Scene

SETTINGS = AnalysisSettings(threads=1)
H = 0.3                                     # the facet's half side, m


def dot_tolerance_mrad(noise_dn: float) -> float:
    """RMS slope error a dot may have (module docstring)."""
    return 0.02 + 0.008 * noise_dn


def fit_tolerances(e_mrad: float, n: int, f_m: float) -> tuple[float, float]:
    """(f tolerance in m, twist tolerance in mrad/m) for slope errors of RMS *e_mrad* at *n* dots."""
    sd_2a = 1e-3 * e_mrad / (H * np.sqrt(n / 3.0))
    return 3.0 * f_m * f_m * 2.0 * sd_2a, 3000.0 * sd_2a


def truth_fit(scene: Scene, points: np.ndarray) -> tuple[float, float, float, float]:
    """(f x, f y, E1, E2) of the least-squares parabola through the exact slopes at *points* (x, y)."""
    tx, ty = scene.slopes(points[0], points[1])
    n = points.shape[1]
    kx = np.linalg.lstsq(np.column_stack([2 * points[0], np.ones(n), points[1]]), tx, rcond=None)[0]
    ky = np.linalg.lstsq(np.column_stack([2 * points[1], np.ones(n), points[0]]), ty, rcond=None)[0]
    return 1.0 / (4.0 * kx[0]), 1.0 / (4.0 * ky[0]), 1000.0 * kx[2], 1000.0 * ky[2]


def check_against_truth(scene: Scene, analysis, noise_dn: float) -> dict:
    """Every reported point's slope against the renderer's exact one (less their mean: the boresight turns
    the frame onto the fitted normal, which a dent moves), and the fitted figures against the truth."""
    pts, sl = analysis.points_facet_m, analysis.slopes
    tx, ty = scene.slopes(pts[0], pts[1])
    d = 1000.0 * (sl - np.vstack([tx, ty]))
    d -= d.mean(axis=1, keepdims=True)
    e = dot_tolerance_mrad(noise_dn)
    rms = np.sqrt(np.mean(d ** 2, axis=1))
    assert np.all(rms <= e), (rms, e)
    assert np.abs(d).max() <= 5 * e, np.abs(d).max()
    fig = analysis.figures
    fx, fy, e1, e2 = truth_fit(scene, pts)
    tol_f, tol_t = fit_tolerances(e, pts.shape[1], max(fx, fy))
    assert abs(fig["focal_length_x_m"] - fx) <= tol_f, (fig["focal_length_x_m"], fx, tol_f)
    assert abs(fig["focal_length_y_m"] - fy) <= tol_f, (fig["focal_length_y_m"], fy, tol_f)
    assert abs(fig["twist_e1_mrad_per_m"] - e1) <= tol_t, (fig["twist_e1_mrad_per_m"], e1, tol_t)
    assert abs(fig["twist_e2_mrad_per_m"] - e2) <= tol_t, (fig["twist_e2_mrad_per_m"], e2, tol_t)
    return {"rms_mrad": rms, "f_error_m": (fig["focal_length_x_m"] - fx, fig["focal_length_y_m"] - fy)}


CASES = {
    # name: (scene, noise DN, seed, nominal pose off the true one by (mrad about x, mm along y))
    "sharp, exact": (Scene(), 0.0, 0, (0.0, 0.0)),
    "distorted lens, 2 DN": (Scene(k1=-0.05, a=1 / 84, b=1 / 80, e=-0.003), 2.0, 1, (2.0, 1.0)),
    "dented facet, 4 DN": (Scene(a=1 / 70, b=1 / 74, e=0.001, bump=(0.0004, 0.1, -0.05, 0.06)), 4.0, 2,
                           (-1.5, -2.0)),
}


@pytest.fixture(scope="module")
def sensitivities():
    return {}


@pytest.mark.parametrize("name", list(CASES))
def test_focal_lengths_twist_and_every_dots_slope_from_one_frame(name, sensitivities):
    """Three facets (plain, a lens with k1 = -0.05, a 0.4 mm dent), noise 0, 2 and 4 DN, the fixture's
    nominal pose off the true one by up to 2 mrad and 2 mm: the origin is found by its mark, the grid's
    directions predicted from the nominal geometry (the mirror shows this grid turned half a turn), every
    dot's slope and the fitted figures within the tolerances of the module docstring. The figures carry U
    (k = 2); the error of f lies within it."""
    scene, noise, seed, (off_mrad, off_mm) = CASES[name]
    nominal = scene.facet_to_camera().compose(Pose(np.array([[1.0, 0.0, 0.0],
                                                            [0.0, np.cos(1e-3 * off_mrad), -np.sin(1e-3 * off_mrad)],
                                                            [0.0, np.sin(1e-3 * off_mrad), np.cos(1e-3 * off_mrad)]]),
                                                  np.array([0.0, 1e-3 * off_mm, 0.0])))
    image = scene.render(noise, seed)
    a = analyse_fixed(image, scene.dots(), scene.geometry(nominal), scene.design(), scene.measured_distance_m(),
                      SETTINGS, uncertainty=InputUncertainties(), sensitivity_cache=sensitivities)
    fig = a.figures
    assert fig["method"] == "fixed" and fig["dots"]["origin_from"] == "mark"
    # most of the dots the facet shows are used: those the edge reaches are left out by design
    assert fig["n_points"] >= 0.8 * fig["dots"]["indexed"], fig["dropped"]
    err = check_against_truth(scene, a, noise)
    for axis, e in zip("xy", err["f_error_m"]):
        assert abs(e) <= fig[f"focal_length_{axis}_m_U"]
    assert fig["slope_curl"]["n"] > 100 and fig["display_response"] is None


def test_dots_missing_extra_and_merged_are_dropped_and_counted():
    """Five dots missing, six stray blobs between dots, three pairs of neighbouring dots run together by a dark
    bar: the lattice is walked past them (every used dot's slope within the tolerance, none off by a
    dot), the merged blobs are counted as such, the strays are not indexed, and the dots used are fewer by at
    least the missing and merged ones."""
    import cv2

    missing = [(2, 3), (-5, 1), (0, -4), (6, 6), (-3, -7)]
    scene = Scene(missing=missing)
    base = reduce_fixed(Scene().render(1.0, 5), scene.dots(), scene.geometry(), scene.design(),
                        scene.measured_distance_m(), SETTINGS)[0].figures
    image = scene.render(1.0, 5).astype(np.float64)
    p = scene.pitch
    for k, (i, j) in enumerate([(1, 1), (-4, 2), (3, -6), (-2, -3), (5, 2), (-6, 5)]):
        u, v = scene.seen_px((i + 0.5) * p, (j + 0.5) * p)
        rows, cols = np.mgrid[0:image.shape[0], 0:image.shape[1]]
        image -= 90.0 * np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * 0.9 ** 2))
    merged = [(-1, 4), (4, -2), (-7, -1)]
    for i, j in merged:
        a_, b_ = scene.seen_px(i * p, j * p), scene.seen_px((i + 1) * p, j * p)
        cv2.line(image, tuple(int(round(c)) for c in a_), tuple(int(round(c)) for c in b_), 30.0, 2)
    frame = np.clip(np.round(image), 0, 255).astype(np.uint8)
    red, _ = reduce_fixed(frame, scene.dots(), scene.geometry(), scene.design(), scene.measured_distance_m(), SETTINGS)
    fig = red.figures
    assert fig["dropped"]["merged"] >= len(merged)
    assert fig["dropped"]["not_indexed"] + fig["dropped"]["too_small"] >= 6
    assert fig["n_points"] <= base["n_points"] - len(missing) - 2 * len(merged) + 2   # (two may lie near the edge)
    from sofast_station.measure.pipeline import to_analysis

    check_against_truth(scene, to_analysis(red), 1.0)


def test_the_centres_covariance_is_the_scatter_of_the_centres():
    """Twenty frames of one scene with 3 DN of independent noise: each dot's centre scatters as its stated
    covariance says. Each dot's sample standard deviation from 20 draws is within 16 % (1 sd) of its own;
    the median ratio over some 600 dots is known to about 1 %; the statement leaves out the background's
    and the disc's own noise (a few %): the median ratio lies in 0.85..1.15, per axis."""
    scene = Scene()
    signal = scene.signal()
    region = pattern_background(scene.render(), 24) > 60
    ref = find_pattern_dots(scene.render(), region)
    rng = np.random.default_rng(11)
    centres, sds = [], []
    for _ in range(20):
        frame = np.clip(np.round(signal + rng.normal(0.0, 3.0, signal.shape)), 0, 255).astype(np.uint8)
        found = find_pattern_dots(frame, region)
        d = np.linalg.norm(found.centres_px[None, :, :] - ref.centres_px[:, None, :], axis=2)
        nn = np.argmin(d, axis=1)
        ok = d[np.arange(len(nn)), nn] < 0.5
        c = np.full(ref.centres_px.shape, np.nan)
        c[ok] = found.centres_px[nn[ok]]
        centres.append(c)
        cov = np.full((len(ref.centres_px), 2), np.nan)
        cov[ok] = np.sqrt(np.diagonal(found.cov_px2[nn[ok]], axis1=1, axis2=2))
        sds.append(cov)
    scatter = np.nanstd(np.stack(centres), axis=0, ddof=1)
    ratio = scatter / np.nanmean(np.stack(sds), axis=0)
    med = np.nanmedian(ratio, axis=0)
    assert np.all((med > 0.85) & (med < 1.15)), med


def test_lcd_dot_grid_locations_follow_the_screens_pixel_grid():
    """The station's own dot grid: each dot's 3-D location is its display pixel's centre, by the conventions'
    screen frame (column c at (c + 1/2) p - W/2, row r at H/2 - (r + 1/2) p), turned by the screen's pose;
    the image draws each dot symmetric about that pixel and the origin mark below the origin dot; through a
    measured (bowed) screen model the locations follow its shape."""
    grid = LcdDotGrid(width_px=64, height_px=48, pitch_px=8, diameter_px=3.0)
    pose = Pose(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([0.1, 0.2, 0.3]))
    pitch = 0.002
    screen = FlatScreen(64 * pitch, 48 * pitch, pose)
    loc = lcd_dot_locations(grid, screen)
    cols, rows = np.meshgrid(grid.centre_columns, grid.centre_rows)
    expected = np.stack([(cols + 0.5) * pitch - 32 * pitch, 24 * pitch - (rows + 0.5) * pitch, np.zeros(cols.shape)],
                        axis=2)
    np.testing.assert_allclose(loc.xyz_m, expected, atol=1e-12)
    assert loc.x_index.tolist() == list(range(-3, 4)) and loc.y_index.tolist() == list(range(-2, 3))
    assert cols[0, 3] == 32 and rows[2, 0] == 24                       # the origin dot at the middle
    img = grid.image()
    dark_r, dark_c = np.nonzero(img == 0)
    # each dot's pixels are symmetric about its centre pixel
    for r0, c0 in [(24, 32), (16, 8), (40, 56)]:
        near = (np.abs(dark_r - r0) <= 2) & (np.abs(dark_c - c0) <= 2)
        assert near.sum() > 0
        assert dark_r[near].mean() == r0 and dark_c[near].mean() == c0
    mark_r, mark_c = np.nonzero(img == 255)
    assert abs(mark_r.mean() - (24 + 0.4 * 8)) <= 0.5 and abs(mark_c.mean() - 32) <= 0.5
    # a bowed screen (z = 1 mm at the middle, 0 at the edges): the locations carry its z
    u, v = np.meshgrid(np.linspace(0, 64 * pitch, 9), np.linspace(0, 48 * pitch, 7))
    xy = np.column_stack([u.ravel() - 32 * pitch, v.ravel() - 24 * pitch])
    z = 1e-3 * (1 - (xy[:, 0] / (32 * pitch)) ** 2) * (1 - (xy[:, 1] / (24 * pitch)) ** 2)
    bowed = InterpolatedScreen(64 * pitch, 48 * pitch, np.column_stack([u.ravel(), v.ravel()]),
                               np.column_stack([xy, z]), pose)
    loc_b = lcd_dot_locations(grid, bowed)
    np.testing.assert_allclose(loc_b.xyz_m[..., :2], expected[..., :2], atol=1e-12)
    assert loc_b.xyz_m[2, 3, 2] == pytest.approx(1e-3 * (1 - (0.5 * pitch / (32 * pitch)) ** 2)
                                                 * (1 - (0.5 * pitch / (24 * pitch)) ** 2), rel=0.05)


def test_a_facet_reflecting_the_stations_own_lcd_grid():
    """The renderer shows the grid's display image (its own pixel geometry, the conventions'), the analysis
    takes the dots from lcd_dot_locations of a flat screen of that pitch: the facet's figures and every dot's
    slope within the module docstring's tolerances (an error of half a display pixel in the locations would
    move every slope by 2 mm / 8 m = 0.25 mrad)."""
    grid = LcdDotGrid(width_px=400, height_px=400, pitch_px=10, diameter_px=4.0)
    scene = Scene(screen_image=(grid.image(), 0.004), n_dots=0)
    screen = FlatScreen(1.6, 1.6, scene.screen_to_camera())
    dots = lcd_dot_locations(grid, screen)
    a = analyse_fixed(scene.render(1.0, 3), dots, scene.geometry(), scene.design(), scene.measured_distance_m(),
                      SETTINGS)
    assert a.figures["dots"]["origin_from"] == "mark"
    check_against_truth(scene, a, 1.0)


def test_the_origin_mark_is_found_where_the_renderer_put_it():
    """The mark (a 5 mm disc at 0.37 pitch from the origin dot) is found within 0.3 px of where the renderer
    sees its centre (its image is a few pixels across; the centre of its brightness above the pattern)."""
    scene = Scene()
    frame = scene.render(2.0, 4)
    bg = pattern_background(frame, 24)
    found = find_pattern_dots(frame, bg > 60)
    mark = find_origin_mark(frame, bg > 60, bg, found.diameter_px, found.noise_dn)
    expected = scene.seen_px(0.0, scene.mark_offset * scene.pitch)
    assert np.linalg.norm(mark - expected) < 0.3, (mark, expected)


def test_bad_captures_are_refused_with_what_is_wrong():
    """No dots, no origin (no mark; a given origin far from any dot), too few dots on the facet, the grid seen
    twice (a second lattice half a pitch off, as a front surface's reflection): each its own error, naming it."""
    plain = Scene()
    args = (plain.dots(), plain.geometry(), plain.design(), plain.measured_distance_m(), SETTINGS)
    with pytest.raises(DotsNotFoundError, match="no dot grid"):
        reduce_fixed(Scene(dark=150.0, mark_level=150.0).render(1.0, 0), *args)
    no_mark = Scene(mark_level=150.0).render(1.0, 0)
    with pytest.raises(OriginNotFoundError, match="no origin mark"):
        reduce_fixed(no_mark, *args)
    with pytest.raises(OriginNotFoundError, match="no dot beside"):
        reduce_fixed(no_mark, *args, origin_px=(400.0, 10.0))
    sparse = Scene(pitch=0.12, radius=0.024, n_dots=12)
    with pytest.raises(TooFewDotsError, match="only .* dots"):
        reduce_fixed(sparse.render(1.0, 0), sparse.dots(), sparse.geometry(), sparse.design(),
                     sparse.measured_distance_m(), SETTINGS)
    second = Scene(dot_offset=(0.5, 0.5), mark_level=150.0)
    twice = np.minimum(plain.render(1.0, 0), second.render(1.0, 1))      # (the mark is lost: given instead)
    with pytest.raises(DoubleLatticeError, match="seen twice"):
        reduce_fixed(twice, *args, origin_px=plain.seen_px(0.0, plain.mark_offset * plain.pitch))


def test_fixed_settings_refuse_what_cannot_work():
    from sofast_station.errors import ConfigError

    with pytest.raises(ConfigError, match="index_tolerance"):
        FixedSettings(index_tolerance=0.7)
    with pytest.raises(ConfigError, match="index_axes"):
        FixedSettings(index_axes=np.array([[1, 0], [1, 0]]))
    with pytest.raises(ConfigError, match="pitch of at least 6"):
        LcdDotGrid(100, 100, 4, 2.0)
    scene = Scene()
    screen = dot_screen(scene.dots(), scene.screen_to_camera())
    r = np.array([3.0, 10.0])
    np.testing.assert_allclose(screen.points_camera(r, r)[:, 0],
                               scene.screen_to_camera().apply(scene.dots().xyz_m[3, 3]), atol=1e-15)


def test_the_grid_prediction_is_kept_per_recipe_in_the_callers_cache(monkeypatch):
    """A caller's cache (analyse_fixed's sensitivity_cache) keeps the grid's predicted picture per recipe: a
    second capture with the same cache, its geometry, design and dots rebuilt equal (as a station's worker
    builds them per capture), does not compute it again and reduces to the figures it gives without a cache,
    bit for bit; a design of another focal length (which moves the prediction) computes its own."""
    import json

    from sofast_station.measure import fixed as fixed_mod

    calls = []
    real = fixed_mod.grid_prediction

    def counted(geometry, design, dots, screen):
        calls.append(design.focal_length_m)
        return real(geometry, design, dots, screen)

    monkeypatch.setattr(fixed_mod, "grid_prediction", counted)
    scene = Scene()

    def figures(seed, cache, focal_length_m=20.0):
        fig = reduce_fixed(scene.render(1.0, seed), scene.dots(), scene.geometry(), scene.design(focal_length_m),
                           scene.measured_distance_m(), SETTINGS, cache=cache)[0].figures
        return json.dumps({k: v for k, v in fig.items() if not k.startswith("timings")}, sort_keys=True, default=str)

    cache: dict = {}
    figures(0, cache)
    assert calls == [20.0]
    second = figures(1, cache)
    assert calls == [20.0]
    assert second == figures(1, None) and calls == [20.0, 20.0]
    figures(1, cache, 24.0)
    assert calls == [20.0, 20.0, 24.0]
    kept = [v for k, v in cache.items() if isinstance(k, tuple) and k[0] == "grid prediction"]
    assert len(kept) == 2 and not np.allclose(kept[0].jac, kept[1].jac, rtol=1e-3, atol=0)
