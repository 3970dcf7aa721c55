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
from sofast_station.measure.surface import intersect_quadratic, normal_slopes, surface_slopes_of_points


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
