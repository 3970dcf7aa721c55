"""The compiled kernels (measure/kernels.py) against numpy's arithmetic they replace."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from sofast_station.geometry import Pose
from sofast_station.measure import kernels
from sofast_station.measure.camera import to_frame
from sofast_station.measure.fit import CUBIC_TERMS, CubicFit
from sofast_station.measure.phase import phase_and_modulation
from sofast_station.measure.surface import (intersect_quadratic, normal_slopes, surface_slopes,
                                           surface_slopes_of_points)


def _ulps(got: np.ndarray, ref: np.ndarray) -> np.ndarray:
    return np.abs(got - ref) / np.spacing(np.abs(ref))


def test_atan_is_numpys_to_three_units_in_the_last_place():
    rng = np.random.default_rng(3)
    x = np.concatenate([rng.normal(0, 1e-3, 200_000), rng.normal(0, 0.3, 200_000), rng.standard_cauchy(200_000),
                        np.logspace(-300, 300, 20_000), -np.logspace(-300, 300, 20_000),
                        np.linspace(0.41, 0.42, 10_000), np.linspace(0.99, 1.01, 10_000)])
    got = kernels.atan(x)
    assert _ulps(got, np.arctan(x)).max() <= 3.0
    # out may be the input itself
    y = x.copy()
    assert kernels.atan(y, out=y) is y and np.array_equal(y, got)


def test_atan_keeps_the_special_values():
    x = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 1.0, -1.0, 1e-310])
    got = kernels.atan(x)
    assert np.array_equal(np.signbit(got[:2]), [False, True]) and np.all(got[:2] == 0.0)
    assert got[2] == np.pi / 2 and got[3] == -np.pi / 2 and np.isnan(got[4])
    assert got[5] == np.arctan(1.0) and got[6] == -np.arctan(1.0) and got[7] == 1e-310
    with pytest.raises(ValueError, match="1-D"):
        kernels.atan(np.zeros((2, 2)))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_phase_of_counts_is_the_rounded_exact_phase_and_the_rest_is_numpys(dtype):
    """Every 8-bit (s, c) difference (and random 16-bit counts): the phase within half a float32 step of
    atan2(s, c) in [0, 2 pi) computed exactly, modulation and consistency the same values as numpy's
    float32 general path."""
    if dtype == np.uint8:
        i0, i2 = (g.ravel() for g in np.meshgrid(np.arange(256), np.arange(256)))
        frames = np.stack([np.concatenate([i0] * 3), np.concatenate([np.full_like(i0, v) for v in (0, 128, 255)]),
                           np.concatenate([i2] * 3), np.concatenate([np.full_like(i0, v) for v in (255, 127, 0)])])
    else:
        frames = np.random.default_rng(5).integers(0, 65536, size=(4, 300_000))
    frames = frames.astype(dtype)
    phase, modulation, consistency = (np.empty(frames.shape[1], np.float32) for _ in range(3))
    kernels.phase_counts(frames, phase, modulation, consistency)
    s = frames[1].astype(np.float64) - frames[3]
    c = frames[0].astype(np.float64) - frames[2]
    exact = np.mod(np.arctan2(s, c), 2 * np.pi)
    assert phase.min() >= 0.0 and phase.max() < 2 * np.pi
    assert np.abs(phase - exact).max() <= 0.5 * np.spacing(np.float32(2 * np.pi)) + 1e-12
    _, mod_ref, cons_ref = phase_and_modulation(frames.astype(np.int64))     # the general (float) path
    assert np.array_equal(modulation, mod_ref.astype(np.float32))
    assert np.array_equal(consistency, cons_ref.astype(np.float32))


def _random_assembly(rng, n):
    rays = rng.normal([0.0, 0.0, 1.0], [0.08, 0.08, 0.0], size=(n, 3)).T
    rays /= np.linalg.norm(rays, axis=0)
    screen = rng.normal([0.3, 0.0, -0.2], [0.2, 0.15, 0.01], size=(n, 3)).T
    a, b = np.deg2rad([1.5, -2.0])
    rot = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) @ \
        np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rays, screen, Pose(rot, np.array([0.01, -0.02, -5.3]))


def test_reflect_gives_numpys_chain_bits():
    rng = np.random.default_rng(11)
    rays, screen, pose = _random_assembly(rng, 50_000)
    rays[:, :5] = (np.array([0.9, 0.0, 0.1]) / np.hypot(0.9, 0.1))[:, None]   # far off the axis: they miss
    coeffs = np.array([0.047, 0.046, 0.001, -0.002, 0.0005, 0.0])
    rays_f = to_frame(pose, rays, translate=False)
    points_ref = intersect_quadratic(coeffs, pose.translation, rays_f)
    slopes_ref = np.stack(normal_slopes(points_ref, pose.translation, to_frame(pose, screen)))
    points, slopes = np.empty((3, rays.shape[1])), np.empty((2, rays.shape[1]))
    with ThreadPoolExecutor(2) as pool:
        kernels.halves(pool, kernels.reflect, rays.shape[1], rays, screen, pose.rotation, pose.translation, coeffs,
                       points, slopes)
    assert np.isnan(points_ref).any()
    np.testing.assert_array_equal(points, points_ref)
    np.testing.assert_array_equal(slopes, slopes_ref)


def test_reflect_blend_is_reflect_then_numpys_move_bit_for_bit():
    """Points and slopes moved in place toward the intersection with a raised model, by a scale per point
    (close_on_all_points' move to each pixel's height): reflect's bits, then numpy's base + (up - base) *
    scale, over two halves as on the pool; the rays that miss are counted."""
    rng = np.random.default_rng(19)
    rays, screen, pose = _random_assembly(rng, 30_000)
    rays[:, :7] = (np.array([0.9, 0.0, 0.1]) / np.hypot(0.9, 0.1))[:, None]   # they miss
    coeffs = np.array([0.047, 0.046, 0.001, -0.002, 0.0005, 0.0])
    n = rays.shape[1]
    base_p, base_s = np.empty((3, n)), np.empty((2, n))
    kernels.reflect(rays, screen, pose.rotation, pose.translation, coeffs, base_p, base_s, 0, n)
    raised = coeffs + [0, 0, 0, 0, 0, 1e-5]
    up_p, up_s = np.empty((3, n)), np.empty((2, n))
    kernels.reflect(rays, screen, pose.rotation, pose.translation, raised, up_p, up_s, 0, n)
    scale = rng.normal(0.0, 2.0, n)
    ref_p, ref_s = base_p + (up_p - base_p) * scale, base_s + (up_s - base_s) * scale
    p, sl = base_p.copy(), base_s.copy()
    missed = sum(kernels.reflect_blend(rays, screen, pose.rotation, pose.translation, raised, scale, p, sl, lo, hi)
                 for lo, hi in ((0, n // 2), (n // 2, n)))
    assert missed == int((~(np.isfinite(up_s[0]) & np.isfinite(up_s[1]))).sum()) == 7
    np.testing.assert_array_equal(p, ref_p)
    np.testing.assert_array_equal(sl, ref_s)


def test_model_residuals_are_numpys_to_the_last_bits():
    rng = np.random.default_rng(12)
    n = 40_000
    x, y = rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n)
    s_x, s_y = 0.09 * x + rng.normal(0, 1e-3, n), 0.09 * y + rng.normal(0, 1e-3, n)
    design = np.array([0.0469, 0.0469, 0.0, 0.0, 0.0, 0.0])
    fitted = np.array([0.0461, 0.0468, 1e-4, -2e-4, 3e-4, 1e-3])
    cubic = CubicFit(rng.normal(0, 1e-3, len(CUBIC_TERMS)), 0.01, -0.02, 0.3)
    out = np.empty((6, n))
    cx, cy = cubic.slope_coefficients()
    args = (x, y, s_x, s_y, [design, fitted], [cubic.x0, cubic.y0, cubic.h, *cx, *cy], out)
    kernels.halves(None, kernels.model_residuals, n, *args)
    refs = [surface_slopes_of_points(design, x, y), surface_slopes_of_points(fitted, x, y), cubic.slopes(x, y)]
    for m, (mx, my) in enumerate(refs):
        for k, (s, model) in enumerate(((s_x, mx), (s_y, my))):
            ref = 1000.0 * (np.arctan(s) - np.arctan(model))
            assert np.abs(out[2 * m + k] - ref).max() < 1e-12       # mrad: the arctangents' last bits
    # on two threads, the same values
    again = np.empty_like(out)
    with ThreadPoolExecutor(2) as pool:
        kernels.halves(pool, kernels.model_residuals, n, *args[:-1], again)
    np.testing.assert_array_equal(again, out)


def test_reflect_in_place_gives_the_intersection_and_normals_bits():
    """With the identity rotation, no translation and the camera centre as *origin* (the boresight loop's
    use): intersect_quadratic and normal_slopes' bits."""
    rng = np.random.default_rng(13)
    rays, screen, pose = _random_assembly(rng, 20_000)
    coeffs = np.array([0.047, 0.046, 0.001, -0.002, 0.0005, 0.0])
    camera = pose.translation
    points_ref = intersect_quadratic(coeffs, camera, rays)
    slopes_ref = np.stack(normal_slopes(points_ref, camera, screen))
    points, slopes = np.empty((3, rays.shape[1])), np.empty((2, rays.shape[1]))
    kernels.reflect(rays, screen, np.eye(3), np.zeros(3), coeffs, points, slopes, 0, rays.shape[1], origin=camera)
    np.testing.assert_array_equal(points, points_ref)
    np.testing.assert_array_equal(slopes, slopes_ref)


def _points(n=70_000, seed=14):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.3, 0.35, n), rng.uniform(-0.25, 0.3, n)
    s_x = 0.094 * x + rng.normal(0, 1e-3, n)
    s_y = 0.093 * y + rng.normal(0, 1e-3, n)
    s_x[:50] += 0.02                            # outliers beyond the bisquare's reach
    return x, y, s_x, s_y


def _same_on_two_threads(fn, *args):
    one = fn(*args)
    with ThreadPoolExecutor(2) as pool:
        two = fn(*args, pool=pool)
    np.testing.assert_array_equal(one, two)
    return one


def test_the_sums_kernels_are_numpys_sums_and_the_same_bits_on_two_threads():
    x, y, s_x, s_y = _points()
    xm, ym = 0.02, 0.03
    xc, yc = x - xm, y - ym
    got = _same_on_two_threads(kernels.parabola_sums, x, y, s_x, s_y, xm, ym)
    ref = [xc * xc, xc, xc * yc, yc * yc, yc, xc * s_x, s_x, yc * s_x, yc * s_y, s_y, xc * s_y]
    np.testing.assert_allclose(got, [np.sum(r) for r in ref], rtol=1e-12, atol=1e-12)

    pairs = [(a, b) for a in range(6) for b in range(a, 6)]
    got = _same_on_two_threads(kernels.cubic_sums, x, y, s_x, s_y, 0.01, -0.02, 0.3, pairs)
    u, v = (x - 0.01) / 0.3, (y + 0.02) / 0.3
    m = [np.ones_like(u), u, v, u * u, u * v, v * v]
    ref = [np.sum(m[a] * m[b]) for a, b in pairs] + [np.sum(k * s_x) for k in m] + [np.sum(k * s_y) for k in m]
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)


def test_the_newton_step_sums_follow_the_bisquare():
    """Tukey's bisquare psi(r) = r (1 - (r/c)^2)^2 and its derivative, written out here independently."""
    x, y, s_x, s_y = _points()
    xm, ym = float(np.mean(x)), float(np.mean(y))
    k0x, k0y, sigma = np.array([0.094, 1e-4, 0.0]), np.array([0.093, -1e-4, 0.0]), (1.1e-3, 0.9e-3)
    got = _same_on_two_threads(kernels.reweight_sums, x, y, s_x, s_y, xm, ym, k0x, k0y, sigma, 4.685)
    xc, yc = x - xm, y - ym
    ref = [np.sum(xc ** 2), np.sum(yc ** 2)]
    for c0, c2, s, k0, sg in ((xc, yc, s_x, k0x, sigma[0]), (yc, xc, s_y, k0y, sigma[1])):
        r = s - (k0[0] * c0 + k0[1] + k0[2] * c2)
        inside = np.abs(r) < 4.685 * sg
        t = r / (4.685 * sg)
        psi = np.where(inside, r * (1 - t ** 2) ** 2, 0.0)
        dpsi = np.where(inside, (1 - t ** 2) * (1 - 5 * t ** 2), 0.0)
        ref += [np.sum(c0 * psi), np.sum(psi), np.sum(c2 * psi), np.sum(c0 * c0 * dpsi), np.sum(c0 * dpsi),
                np.sum(c0 * c2 * dpsi), np.sum(dpsi), np.sum(c2 * dpsi), np.sum(c2 * c2 * dpsi)]
    assert not np.all(np.abs(s_x - 0.094 * x) < 4.685 * sigma[0])      # the outliers are outside
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("with_level", [False, True])
def test_cleaned_residuals_are_the_harmonic_model_removed_to_float32_rounding(with_level):
    rng = np.random.default_rng(15)
    n = 100_000
    phase = rng.uniform(0, 2 * np.pi, n).astype(np.float32)
    phase[:4] = [0.0, np.float32(np.pi), np.nextafter(np.float32(2 * np.pi), 0, dtype=np.float32), 1e-7]
    modulation = rng.uniform(5, 120, n).astype(np.float32)
    residual = rng.integers(-6, 7, n).astype(np.float32)
    level = rng.uniform(20, 240, n).astype(np.float32) if with_level else None
    harmonic, own = np.array([0.31, -0.12, 0.02, -0.015]), np.array([0.4, -0.003])
    got = kernels.cleaned_residuals(residual, phase, modulation, level, harmonic, own)
    assert got.dtype == np.float32
    # the harmonic model in double precision; the model term is at most ~60 DN: a few float32 steps of it
    phi2 = 2.0 * phase.astype(np.float64)
    model = modulation * (harmonic[0] * np.cos(phi2) + harmonic[1] * np.sin(phi2) + harmonic[2] * np.cos(3 * phi2)
                          + harmonic[3] * np.sin(3 * phi2)) + own[0] + (own[1] * level if with_level else 0.0)
    assert np.abs(got - (residual - model)).max() < 2e-5


def test_noise_rows_are_the_harmonic_regressors_on_the_stride():
    rng = np.random.default_rng(16)
    n = 50_001
    phase = rng.uniform(0, 2 * np.pi, n).astype(np.float32)
    modulation = rng.uniform(5, 120, n).astype(np.float32)
    residual = rng.integers(-6, 7, n).astype(np.float32)
    level = rng.uniform(20, 240, n).astype(np.float32)
    own, shared, r = kernels.noise_rows(phase, modulation, residual, level, 7)
    phi, b = phase[::7].astype(np.float64), modulation[::7].astype(np.float64)
    ref = [b * np.cos(2 * phi), b * np.sin(2 * phi), b * np.cos(6 * phi), b * np.sin(6 * phi)]
    assert shared.shape == (4, r.size) and r.size == len(range(0, n, 7))
    np.testing.assert_allclose(shared, ref, rtol=0, atol=1e-11)
    np.testing.assert_array_equal(own, [np.ones(r.size), level[::7]])
    np.testing.assert_array_equal(r, residual[::7])
    own, _, _ = kernels.noise_rows(phase, modulation, residual, None, 7)
    np.testing.assert_array_equal(own, [np.ones(r.size)])


def test_to_frame_every_is_to_frame_of_the_strided_columns():
    rng = np.random.default_rng(17)
    rays, screen, pose = _random_assembly(rng, 10_001)
    for v, translate in ((rays, False), (screen, True)):
        got = kernels.to_frame_every(v, pose.rotation, pose.translation, 7, translate=translate)
        np.testing.assert_array_equal(got, to_frame(pose, v[:, ::7], translate=translate))


def test_minus_models_is_numpys_expression_bit_for_bit():
    rng = np.random.default_rng(18)
    r, own, shared = rng.normal(size=5000), rng.normal(size=(2, 5000)), rng.normal(size=(4, 5000))
    a, b = rng.normal(size=2), rng.normal(size=4)
    ref = r - (a[0] * own[0] + a[1] * own[1]) - (((b[0] * shared[0] + b[1] * shared[1]) + b[2] * shared[2])
                                                 + b[3] * shared[3])
    np.testing.assert_array_equal(kernels.minus_models(r, own, a, shared, b), ref)
    np.testing.assert_array_equal(kernels.minus_models(r, own, a), r - (a[0] * own[0] + a[1] * own[1]))


def test_trimmed_std_keeps_its_meaning():
    """A Gaussian's deviation through 2 % of gross outliers, and integer-valued residuals."""
    from sofast_station.measure.phase import trimmed_std

    rng = np.random.default_rng(19)
    r = rng.normal(0, 1.3, 100_000)
    r[:2000] = rng.uniform(30, 60, 2000)
    assert trimmed_std(r) == pytest.approx(1.3, rel=0.01)
    assert trimmed_std(np.round(rng.normal(0, 2.0, 100_000))) == pytest.approx(np.hypot(2.0, 1 / np.sqrt(12)),
                                                                               rel=0.01)


def test_label_areas_count_every_label():
    labels = np.random.default_rng(20).integers(0, 37, size=(300, 410)).astype(np.int32)
    np.testing.assert_array_equal(kernels.label_areas(labels, 37), np.bincount(labels.ravel(), minlength=37))


def _distorted_grid(rng, nx: int, ny: int):
    """A measured screen's grid: uneven node positions (nx by ny), points near half of them in metres with
    a little out of plane, and a pose 3 m away."""
    xs, ys = np.cumsum(rng.uniform(0.05, 0.15, nx)), np.cumsum(rng.uniform(0.05, 0.15, ny))
    gx, gy = np.meshgrid(xs, ys)
    uv = np.column_stack([gx.ravel(), gy.ravel()])
    pts = np.column_stack([uv * 0.5 + rng.normal(0, 0.002, uv.shape), rng.normal(0, 0.003, len(uv))])
    return xs, ys, uv, pts, Pose(np.eye(3), np.array([0.1, -0.2, 3.0]))


def test_a_measured_grid_screen_is_scipys_triangulation_found_directly():
    """A distorted screen on a rectangular grid (as OpenCSP's display models): the direct cell lookup gives
    scipy's piecewise-linear interpolation over the same triangles, NaN outside, on the edges too."""
    from scipy.interpolate import LinearNDInterpolator

    from sofast_station.measure.screen import InterpolatedScreen

    rng = np.random.default_rng(21)
    xs, ys, uv, pts, pose = _distorted_grid(rng, 9, 7)
    screen = InterpolatedScreen(1.0, 1.0, uv, pts, pose)
    assert screen._grid is not None
    u = np.concatenate([rng.uniform(xs[0] - 0.05, xs[-1] + 0.05, 20_000), xs, [xs[0], xs[-1]]])
    v = np.concatenate([rng.uniform(ys[0] - 0.05, ys[-1] + 0.05, 20_000), np.full(xs.size, ys[3]), [ys[-1], ys[0]]])
    got = screen.points_camera(u, v)
    ref = LinearNDInterpolator(uv, pts)(np.column_stack([u, v])).T + pose.translation[:, None]
    assert np.array_equal(np.isnan(got), np.isnan(ref)) and np.isnan(got).any()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-14)


def test_a_screen_given_the_grid_split_of_another_is_the_same_screen_without_a_triangulation(tmp_path):
    """The split (which diagonal scipy's triangulation took in each cell) depends on the grid positions
    alone: a screen built with it (from the station's cache) gives the same points to the bit, and builds
    no triangulation; stretched and displaced screens keep it; the cache gives it back as stored."""
    from sofast_station.cache import load_screen_split, open_cache, save_screen_split
    from sofast_station.measure.screen import InterpolatedScreen

    rng = np.random.default_rng(24)
    xs, ys, uv, pts, pose = _distorted_grid(rng, 11, 8)
    first = InterpolatedScreen(1.0, 1.0, uv, pts, pose)
    split = first.split
    assert split.shape == (ys.size - 1, xs.size - 1)
    cache = open_cache(tmp_path)
    assert load_screen_split(cache, uv) is None
    assert save_screen_split(cache, uv, split)
    kept = load_screen_split(cache, uv)
    np.testing.assert_array_equal(kept, split)
    assert load_screen_split(cache, uv + 1e-9) is None               # other grid positions: not theirs
    other_pts = pts + rng.normal(0, 0.001, pts.shape)                 # another shape on the same grid
    again = InterpolatedScreen(1.0, 1.0, uv, other_pts, pose, split=kept)
    assert again._interp_built is None
    u, v = rng.uniform(xs[0], xs[-1], 5000), rng.uniform(ys[0], ys[-1], 5000)
    np.testing.assert_array_equal(again.points_camera(u, v),
                                  InterpolatedScreen(1.0, 1.0, uv, other_pts, pose).points_camera(u, v))
    assert again.stretched("x", 1.001)._interp_built is None
    with pytest.raises(ValueError, match="grid split of shape"):
        InterpolatedScreen(1.0, 1.0, uv, pts, pose, split=kept[:-1])


def test_gather_runs_is_numpys_fancy_index():
    from sofast_station.measure.pipeline import _runs

    rng = np.random.default_rng(22)
    frames = rng.integers(0, 256, size=(5, 60, 70)).astype(np.uint8)
    region = rng.uniform(size=(60, 70)) < 0.7
    idx = np.flatnonzero(region)
    flat = frames.reshape(5, -1)
    out = np.empty((5, idx.size), dtype=np.uint8)
    kernels.gather_runs(flat, idx, _runs(idx), out)
    np.testing.assert_array_equal(out, flat[:, idx])


def test_normal_slopes_kernel_is_the_numpy_function_bit_for_bit():
    rng = np.random.default_rng(23)
    points = rng.normal([0, 0, 0.01], [0.3, 0.3, 0.005], size=(5000, 3)).T
    screen = rng.normal([0.2, 0.0, -5.3], [0.2, 0.1, 0.01], size=(5000, 3)).T
    camera = np.array([0.05, -0.02, -5.35])
    np.testing.assert_array_equal(kernels.normal_slopes(points, camera, screen),
                                  np.stack(normal_slopes(points, camera, screen)))


def _median_window_holds(values: np.ndarray, lo: float, hi: float) -> bool:
    """Whether the median's order statistics (the middle one, or the two middle ones of an even count) all
    lie in [lo, hi], from numpy's sort: what median_in_window must find (and nothing else)."""
    v = np.sort(values)
    n = v.size
    if n == 0 or np.isnan(v).any():
        return False
    low, high = (v[n // 2], v[n // 2]) if n % 2 else (v[n // 2 - 1], v[n // 2])
    return bool(lo <= low and high <= hi)


def test_median_near_a_guess_is_numpys_median_bit_for_bit():
    """Windows that hold the median, that miss it, none at all; odd and even counts, ties, |a - about|.
    ``median_in_window`` must say found exactly where its window holds the median's order statistics (from
    numpy's sort, :func:`_median_window_holds`), and then give numpy's median bit for bit: a kernel that
    never found (and so always fell back to the full selection) would fail, as one that found wrongly."""
    rng = np.random.default_rng(11)
    scratch = np.empty(5000)
    for n in (1, 2, 3, 64, 65, 999, 1000, 4096, 4097):
        for kind in ("normal", "ties", "outliers"):
            a = rng.normal(0.3, 2.0, n)
            if kind == "ties":
                a = np.round(a)
            elif kind == "outliers":
                a[: n // 10] += 50.0
            for about, absolute in ((0.0, False), (0.25, True)):
                ref = float(np.median(np.abs(a - about) if absolute else a))
                for lo, hi in ((ref - 0.01, ref + 0.01), (ref, ref), (ref + 0.5, ref + 0.6), (-1e9, 1e9),
                               (np.nan, np.nan), (ref - 3.0, ref - 2.0)):
                    got = kernels._median_of(a, about, absolute, lo, hi, scratch)
                    assert got == ref, (n, kind, absolute, lo, hi)
                    m, found = kernels.median_in_window(a, about, absolute, lo, hi, scratch)
                    values = np.abs(a - about) if absolute else a
                    assert found == _median_window_holds(values, lo, hi), (n, kind, absolute, lo, hi)
                    assert (not found) or m == ref
    # a NaN makes the median NaN, as numpy's
    a = rng.normal(size=101)
    a[7] = np.nan
    assert np.isnan(kernels._median_of(a, 0.0, False, -0.1, 0.1, scratch))
    assert np.isnan(kernels._median_of(a, 0.0, True, np.nan, np.nan, scratch))


def _irls_reference(x_cols, target, w, tolerance, max_iterations):
    """Textbook IRLS with Tukey's bisquare, written with numpy's least squares (the kernel's definition)."""
    X = np.stack(x_cols, axis=1)
    prev, sigma = None, np.nan
    for _ in range(max_iterations):
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(X * sw[:, None], target * sw, rcond=None)[0]
        r = target - X @ coef
        h = w * np.einsum("ij,jk,ik->i", X, np.linalg.inv(X.T @ (X * w[:, None])), X)
        r_adj = r / np.sqrt(np.maximum(1.0 - h, 1e-12))
        ms = np.sum(w * r * r) / max(np.sum(w), 1.0)
        if prev is not None and abs(ms - prev) <= tolerance * max(prev, 1e-30):
            break
        prev = ms
        mad = np.median(np.abs(r_adj - np.median(r_adj)))
        sigma = mad / 0.6745
        u = r_adj / (4.685 * sigma)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    return coef, w, sigma


def test_the_compiled_bisquare_iteration_is_the_textbook_one():
    rng = np.random.default_rng(5)
    n = 20_000
    x, y = rng.uniform(-0.7, 0.7, n), rng.uniform(-0.5, 0.5, n)
    s = 4e-3 * x + 2e-4 + 1e-4 * y + 2e-4 * rng.standard_normal(n)
    s[rng.choice(n, 800, replace=False)] += rng.uniform(5e-3, 2e-2, 800)      # 4 % outliers, one-sided
    cols = [x - x.mean(), np.ones(n), y - y.mean()]
    ref_coef, ref_w, ref_sigma = _irls_reference(cols, s, np.ones(n), 1e-9, 50)
    scale = np.sqrt(np.array(kernels.sum_squares(*cols)) / n)
    for start_sigma in (np.nan, ref_sigma, 3.0 * ref_sigma):       # the guess changes the time, not the fit
        w = np.ones(n)
        coef = np.empty(3)
        status, sigma = kernels.irls_bisquare(*cols, s, w, scale, 1e-9, 50, start_sigma, 4.685, 0.6745, 0.01, coef)
        assert status == 0
        np.testing.assert_allclose(coef, ref_coef, rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(w, ref_w, rtol=0, atol=1e-9)
        assert sigma == pytest.approx(ref_sigma, rel=1e-9)
    # the outliers are down-weighted to nothing, and the slope is the true one to its noise
    assert abs(coef[0] - 4e-3) < 1e-5 and np.mean(w[s > 4e-3 * x + 4e-3] == 0.0) > 0.95
    # a degenerate column: the kernel says so instead of returning numbers
    flat = [np.zeros(n), np.ones(n), y]
    status, _ = kernels.irls_bisquare(*flat, s, np.ones(n), np.ones(3), 1e-9, 50, np.nan, 4.685, 0.6745, 0.01,
                                      np.empty(3))
    assert status in (kernels.SINGULAR, kernels.ILL_CONDITIONED)
    bad = s.copy()
    bad[3] = np.nan
    status, _ = kernels.irls_bisquare(*cols, bad, np.ones(n), scale, 1e-9, 50, np.nan, 4.685, 0.6745, 0.01,
                                      np.empty(3))
    assert status == kernels.ILL_CONDITIONED


def test_dot_centroids_ring_background_and_scatter_are_numpys_median_and_mad():
    """Each dot's background is the median of its ring (pixels whose squared distance from the rounded start
    lies in ((o - 2)^2, o^2], o = 2 r + 3 for the radius r) and its scatter 1.4826 times the median absolute
    deviation about it (:func:`~sofast_station.measure.dots._centroids`). The kernel finds both from the counts
    of the ring's whole values: here against numpy's median and MAD of the same pixels, bit for bit, for radii
    whose rings hold an odd and an even number of pixels, 8- and 16-bit frames, flat rings (every pixel one
    value), and 16-bit rings spanning more counts than the kernel's histogram (numpy's median then)."""
    rng = np.random.default_rng(42)
    checked = {"odd": 0, "even": 0, "wide": 0}
    for dtype, top in ((np.uint8, 255), (np.uint16, 4095), (np.uint16, 65535)):
        for spread in (0, 3, 40, 3000):
            image = np.clip(rng.normal(top // 3, spread, (120, 160)), 0, top).astype(dtype)
            starts = rng.uniform(25, 95, (30, 2))
            for radius in (1.0, 1.5, 2.5, 4.0):
                _, ok, _, background, ring_sigma, _ = kernels.dot_centroids(image, starts, radius, True)
                outer = 2.0 * radius + 3.0
                for k in np.flatnonzero(ok):
                    cu, cv = (int(round(v)) for v in starts[k])
                    dy, dx = np.mgrid[-12:13, -12:13]
                    r2 = dx * dx + dy * dy
                    ring = image[cv + dy, cu + dx][((outer - 2.0) ** 2 < r2) & (r2 <= outer ** 2)].astype(float)
                    bg = np.median(ring)
                    assert background[k] == bg, (dtype, spread, radius, k)
                    assert ring_sigma[k] == 1.4826 * np.median(np.abs(ring - bg)), (dtype, spread, radius, k)
                    checked["odd" if ring.size % 2 else "even"] += 1
                    checked["wide"] += int(np.ptp(ring) >= 1024)
    assert min(checked["even"], checked["wide"]) > 20, checked
    # a ring's pixel count is a multiple of four (it is symmetric under quarter turns): the odd counts' branch
    # of the counted median, on its own
    for n in (1, 2, 3, 7, 84, 85, 301):
        for span in (1, 2, 9, 200):
            values = rng.integers(17, 17 + span, n).astype(float)
            hist = np.bincount((values - 17).astype(np.int64), minlength=1024)
            bg = kernels._counted_median(hist, span, 17.0, n)
            assert bg == np.median(values), (n, span)
            assert kernels._counted_mad(hist, span, 17.0, n, bg) == np.median(np.abs(values - bg)), (n, span)


def _numpy_bilinear(h: np.ndarray, x0: float, y0: float, cell: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """HeightGrid.at as it was in numpy (clip, truncate, four takes by flat index), which the kernel replaces."""
    ny, nx = h.shape
    u = np.clip((x - x0) / cell - 0.5, 0.0, nx - 1.0)
    v = np.clip((y - y0) / cell - 0.5, 0.0, ny - 1.0)
    j = np.minimum(u.astype(np.int64), max(nx - 2, 0))
    i = np.minimum(v.astype(np.int64), max(ny - 2, 0))
    tu, tv = u - j, v - i
    flat, k = h.ravel(), i * nx + j
    dj, di = min(nx - 1, 1), min(ny - 1, 1) * nx
    su = 1.0 - tu
    return ((1.0 - tv) * (su * flat.take(k) + tu * flat.take(k + dj))
            + tv * (su * flat.take(k + di) + tu * flat.take(k + (di + dj))))


@pytest.mark.parametrize("shape", [(29, 31), (1, 7), (6, 1), (1, 1), (2, 2)])
def test_bilinear_is_numpys_clip_and_takes_bit_for_bit(shape):
    """Random heights read at every cell centre, at random points inside and beyond the outer centres
    (clamped), on grids one cell wide or high too."""
    rng = np.random.default_rng(31)
    h = rng.normal(0.0, 1e-5, shape)
    x0, y0, cell = -0.61, 0.37, 0.043
    ny, nx = shape
    # every cell centre, the outer ones' edges exactly, then random points inside and beyond
    centres = np.meshgrid(x0 + (np.arange(nx + 1) + 0.5) * cell, y0 + (np.arange(ny + 1) + 0.5) * cell)
    cx, cy = (g.ravel() for g in centres)
    x = np.concatenate([cx, [x0, x0 - cell], rng.uniform(x0 - 0.2, x0 + (nx + 4) * cell, 4000)])
    y = np.concatenate([cy, [y0 - cell, y0], rng.uniform(y0 - 0.2, y0 + (ny + 4) * cell, 4000)])
    got = kernels.bilinear(h, x0, y0, cell, x, y)
    ref = _numpy_bilinear(h, x0, y0, cell, x, y)
    assert np.array_equal(got.view(np.int64), ref.view(np.int64))          # the same bits, zeros' signs too
    assert np.all(np.isnan(kernels.bilinear(h, x0, y0, cell, np.array([np.nan, 0.1]), np.array([0.5, np.inf]))))


def test_grid_sums_are_grid_slopes_bincounts_and_height_grid_its_centred_integral_bit_for_bit():
    """Scattered slopes (some not finite, some beyond the grid, cells left empty) less a quadratic model's
    (surface_slopes), binned by numpy (grid_slopes' bincounts) and by the kernel: each cell's count and sums of
    slopes and of offsets from its centre, the same bits, with and without the model; and height_grid's heights
    are integrate_full_grid's of grid_slopes' cells moved to their centres (centred_slopes), empty ones 0."""
    from sofast_station.measure.heights import centred_slopes, grid_slopes, height_grid, integrate_full_grid

    rng = np.random.default_rng(37)
    for n, cells in ((3537, 29), (200, 12), (9, 4)):
        x, y = rng.uniform(-0.6, 0.6, n), rng.uniform(-0.5, 0.4, n)
        keep = np.hypot(x, y) < 0.55                  # a round facet in its box: the box's corners empty
        x, y = x[keep], y[keep]
        g_x, g_y = rng.normal(0, 1e-3, x.size), rng.normal(0, 1e-3, x.size)
        g_x[::97] = np.nan
        g_y[5::89] = np.inf
        cell = 1.2 / cells
        x0, y0 = float(x.min()) - 0.5 * cell, float(y.min()) - 0.3 * cell
        extent = (x0, float(x.max()) - 2 * cell, y0, float(y.max()) + 0.5 * cell)   # some points beyond it
        model = rng.normal(0.0, [0.05, 0.05, 1e-3, 1e-3, 1e-3, 1e-3])
        m_x, m_y = surface_slopes(model, x, y)
        for mod, (a, b) in ((model, (g_x - m_x, g_y - m_y)), (None, (g_x, g_y))):
            g = grid_slopes(x, y, a, b, cell, extent_m=extent)
            count, s_x, s_y, o_x, o_y = kernels.grid_sums(x, y, g_x, g_y, x0, y0, cell, g["s_x"].shape, mod)
            assert (count == 0).any() and np.array_equal(count, g["count"])
            full = count > 0
            for got, ref in ((s_x, g["s_x"]), (s_y, g["s_y"]), (o_x, g["offset_x_m"]), (o_y, g["offset_y_m"])):
                assert np.array_equal((got[full] / count[full]).view(np.int64), ref[full].view(np.int64))
                assert np.all(got[~full] == 0.0) and np.all(np.isnan(ref[~full]))
        ok = np.isfinite(g_x) & np.isfinite(g_y)
        grid = height_grid(x[ok], y[ok], g_x[ok], g_y[ok], cells=cells, model=model)
        span = max(np.ptp(x[ok]), np.ptp(y[ok]))
        full = grid_slopes(x[ok], y[ok], g_x[ok] - m_x[ok], g_y[ok] - m_y[ok], span / cells, extent_m=(
            x[ok].min() - 0.5 * span / cells, x[ok].max() + 0.5 * span / cells,
            y[ok].min() - 0.5 * span / cells, y[ok].max() + 0.5 * span / cells))
        c_x, c_y = centred_slopes(full["s_x"], full["s_y"], full["offset_x_m"], full["offset_y_m"], span / cells)
        ref = integrate_full_grid(np.nan_to_num(c_x, nan=0.0), np.nan_to_num(c_y, nan=0.0), span / cells)
        assert grid.heights_m.shape == ref.shape and np.array_equal(grid.heights_m, ref)


def test_label_moments_are_numpys_bincounts_of_the_labelled_pixels_bit_for_bit():
    """Blobs of a random binary picture labelled by OpenCV: each label's count and sums of row, column and
    their products as np.bincount of its pixels in raster order gives them (what dots._elongation took), and
    the areas and centroids OpenCV's statistics give (what find_pattern_dots took)."""
    import cv2

    rng = np.random.default_rng(41)
    binary = (cv2.GaussianBlur(rng.uniform(size=(300, 420)), (0, 0), 2.0) > 0.52).astype(np.uint8)
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    assert n > 50
    at = np.flatnonzero(labels)
    flat = labels.ravel()[at]
    rows, cols = np.divmod(at, labels.shape[1])
    ref = np.stack([np.bincount(flat, minlength=n).astype(np.float64)]
                   + [np.bincount(flat, w, n) for w in (rows, cols, rows * rows, cols * cols, rows * cols)])
    ref[:, 0] = 0.0
    got = kernels.label_moments(labels, n)
    np.testing.assert_array_equal(got, ref)
    # find_pattern_dots' blob areas and centroids: OpenCV's statistics of the same labelling, bit for bit
    n2, labels2, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    assert n2 == n and np.array_equal(labels2, labels)
    np.testing.assert_array_equal(got[0, 1:].astype(np.int64), stats[1:, cv2.CC_STAT_AREA])
    np.testing.assert_array_equal(np.column_stack([got[2, 1:] / got[0, 1:], got[1, 1:] / got[0, 1:]]), centroids[1:])


def test_fill_holes_is_opencvs_statistics_rule():
    """The holes a region's box fills: the labels of its complement (4-connected) that touch no edge of the
    box and have at most max_area pixels, as OpenCV's statistics (bounding box, area) select them; in a
    view of a larger array too."""
    import cv2

    rng = np.random.default_rng(43)
    for max_area in (0, 5, 40, 10_000):
        whole = np.zeros((220, 260), bool)
        box = whole[10:210, 20:250]
        box[:] = cv2.GaussianBlur(rng.uniform(size=box.shape), (0, 0), 1.5) > 0.47
        before = box.copy()
        n, labels, stats, _ = cv2.connectedComponentsWithStats((~box).view(np.uint8), connectivity=4)
        x, y, bw, bh, area = (stats[:, k] for k in range(5))
        fill = ~((x == 0) | (y == 0) | (x + bw == box.shape[1]) | (y + bh == box.shape[0])) & (area <= max_area)
        fill[0] = False
        n2, labels2 = cv2.connectedComponents((~box).view(np.uint8), connectivity=4)
        assert n2 == n and np.array_equal(labels2, labels)
        kernels.fill_holes(labels2, n2, max_area, box)
        np.testing.assert_array_equal(box, before | fill[labels])
        assert max_area == 0 or (box != before).any()
        assert not whole[:10].any() and not whole[:, :20].any()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_laplacian_median_is_numpys_float32_median_of_the_subsampled_laplacian(dtype):
    """Noisy pictures with edges (odd and even sizes, odd and even counts of masked values, views): the
    median of the absolute Laplacian at every other pixel counted from the histogram is numpy's median of
    the float32 Laplacians; image_noise_dn gives the numpy chain's bits."""
    from sofast_station.measure.dots import image_noise_dn

    rng = np.random.default_rng(47)
    top = np.iinfo(dtype).max
    for shape in ((61, 80), (64, 77), (9, 9), (3, 40)):
        img = np.clip(rng.normal(0.3 * top, 0.01 * top + 2, shape) + (np.arange(shape[1]) > shape[1] // 2) * 0.4 * top,
                      0, top).astype(dtype)
        big = np.zeros((shape[0] + 4, shape[1] + 6), dtype)
        big[2:-2, 3:-3] = img
        view = big[2:-2, 3:-3]
        for mask in (np.ones(shape, bool), rng.uniform(size=shape) < 0.6, np.zeros(shape, bool)):
            f = img.astype(np.float32)
            c = f[1:-1:2, 1:-1:2]
            lap = 4.0 * c - f[:-2:2, 1:-1:2][:c.shape[0], :c.shape[1]] - f[2::2, 1:-1:2][:c.shape[0], :c.shape[1]] \
                - f[1:-1:2, :-2:2][:c.shape[0], :c.shape[1]] - f[1:-1:2, 2::2][:c.shape[0], :c.shape[1]]
            values = np.abs(lap[mask[1:-1:2, 1:-1:2]])
            ref = np.median(values) if values.size else 0.0
            got = kernels.laplacian_median(view, mask)
            assert got == ref and np.float32(got) == ref
            ref_noise = float(1.4826 * np.median(values) / np.sqrt(20.0)) if values.size else 0.0
            assert image_noise_dn(view, mask) == ref_noise
    assert kernels.laplacian_median(np.zeros((2, 2), dtype), np.ones((2, 2), bool)) == 0.0

