"""Slope fits: slopes from a known paraboloid give its coefficients back."""

import numpy as np
import pytest

from sofast_station.errors import AnalysisError
from sofast_station.measure.fit import fit_parabola
from sofast_station.measure.kernels import model_residuals
from sofast_station.measure.metrics import focal_length_m, principal_axes, rms_summary


@pytest.mark.parametrize("x0, half", [(0.0, 0.3), (3.0, 1.5)], ids=["dish", "gore-like offset"])
def test_fit_round_trip(x0, half):
    rng = np.random.default_rng(1)
    x = x0 + rng.uniform(-half, half, 50_000)
    y = rng.uniform(-0.3, 0.3, 50_000)
    a, b, c, d, e1, e2 = 1 / (4 * 5.42), 1 / (4 * 5.35), 2e-3, -1e-3, 1.3e-4, 0.7e-4
    fit = fit_parabola(x, y, 2 * a * x + c + e1 * y, 2 * b * y + d + e2 * x)
    got = np.array([fit.a, fit.b, fit.c, fit.d, fit.e1, fit.e2])
    assert np.allclose(got, [a, b, c, d, e1, e2], rtol=1e-10, atol=1e-13)
    assert fit.e == pytest.approx(0.5 * (e1 + e2))


def test_fit_is_bitwise_repeatable():
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-0.3, 0.3, (2, 100_000))
    sx, sy = 0.05 * x + rng.normal(0, 1e-3, x.size), 0.05 * y + rng.normal(0, 1e-3, x.size)
    assert fit_parabola(x, y, sx, sy) == fit_parabola(x.copy(), y.copy(), sx.copy(), sy.copy())


def test_fit_refuses_degenerate_points():
    x = np.linspace(0, 1, 100)
    with pytest.raises(AnalysisError, match="too few|singular|ill-conditioned|span"):
        fit_parabola(x, np.zeros_like(x), x, x)


def test_residuals_are_angles_not_slope_differences():
    # (the analysis' residuals: a model of constant slope 0.39 in x, measured slope 0.4)
    out = np.empty((6, 1))
    slope_0_39 = np.array([0.0, 0.0, 0.39, 0.0, 0.0, 0.0])
    model_residuals(np.zeros(1), np.zeros(1), np.array([0.4]), np.array([0.0]), [slope_0_39, slope_0_39],
                    np.r_[0.0, 0.0, 1.0, np.zeros(12)], out, 0, 1)
    ex = out[0]
    assert ex[0] == pytest.approx(1000 * (np.arctan(0.4) - np.arctan(0.39)))
    assert ex[0] < 0.9 * 10.0       # 0.01 in slope units is only ~8.6 mrad at slope 0.4


def test_rms_summary_and_focal_lengths():
    s = rms_summary(np.array([3.0, -3.0]), np.array([4.0, 4.0]))
    assert s == {"x": 3.0, "y": 4.0, "magnitude": 5.0}
    assert focal_length_m(1e-9) is None and focal_length_m(-0.5) == -2.0
    f, angle = principal_axes(1 / (4 * 5.0), 1 / (4 * 6.0), 0.0)
    assert f == pytest.approx([5.0, 6.0]) and angle == 0.0
    f, angle = principal_axes(1 / (4 * 6.0), 1 / (4 * 5.0), 0.0)   # shorter along y
    assert f == pytest.approx([5.0, 6.0]) and angle == pytest.approx(np.pi / 2)


@pytest.mark.parametrize("x0, half", [(0.0, 0.3), (3.0, 1.5)], ids=["dish", "gore-like offset"])
def test_higher_order_round_trip(x0, half):
    """Slopes of a known cubic surface (evaluated here, by hand) give a zero residual and the same slopes."""
    from sofast_station.measure.fit import fit_cubic
    rng = np.random.default_rng(4)
    x = x0 + rng.uniform(-half, half, 40_000)
    y = rng.uniform(-0.4, 0.4, 40_000)
    # z = 0.05 x^2 + 0.045 y^2 + 1e-4 xy + 2e-3 x - 1e-3 y + 3e-4 x^3 - 2e-4 x^2 y + 1e-4 x y^2 + 5e-5 y^3
    sx = 0.1 * x + 1e-4 * y + 2e-3 + 9e-4 * x**2 - 4e-4 * x * y + 1e-4 * y**2
    sy = 0.09 * y + 1e-4 * x - 1e-3 - 2e-4 * x**2 + 2e-4 * x * y + 1.5e-4 * y**2
    fit = fit_cubic(x, y, sx, sy)
    mx, my = fit.slopes(x, y)
    assert np.abs(mx - sx).max() < 1e-12 and np.abs(my - sy).max() < 1e-12
    # fresh points: the model is the surface, not just a good fit at the samples
    xt, yt = np.array([x0 - half, x0 + half]), np.array([0.3, -0.2])
    ex = 0.1 * xt + 1e-4 * yt + 2e-3 + 9e-4 * xt**2 - 4e-4 * xt * yt + 1e-4 * yt**2
    assert np.allclose(fit.slopes(xt, yt)[0], ex, atol=1e-12)


def test_robust_fit_ignores_outliers_that_pull_the_plain_fit():
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-0.6, 0.6, (2, 20_000))
    a, b = 1 / (4 * 110.0), 1 / (4 * 105.0)
    sx = 2 * a * x + rng.normal(0, 1e-4, x.size)
    sy = 2 * b * y + rng.normal(0, 1e-4, x.size)
    edge = np.abs(x) > 0.57                      # edge pixels that saw past the screen: wild slopes
    sx[edge] += 0.02 * np.sign(x[edge])
    plain = fit_parabola(x, y, sx, sy)
    robust = fit_parabola(x, y, sx, sy, robust=True)
    assert abs(1 / (4 * plain.a) / 110.0 - 1) > 0.05            # the outliers move the plain fit a lot
    assert abs(1 / (4 * robust.a) / 110.0 - 1) < 2e-3
    assert abs(1 / (4 * robust.b) / 105.0 - 1) < 2e-3
    assert fit_parabola(x, y, sx, sy, robust=True) == robust    # deterministic


def outlier_slopes(n, seed=7):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.6, 0.6, (2, n))
    a, b = 1 / (4 * 110.0), 1 / (4 * 105.0)
    sx = 2 * a * x + 3e-5 * y + rng.normal(0, 1e-4, x.size)
    sy = 2 * b * y + 2e-5 * x + rng.normal(0, 1e-4, x.size)
    edge = np.abs(x) > 0.57
    sx[edge] += 0.02 * np.sign(x[edge])
    return x, y, sx, sy


def test_robust_fit_started_from_earlier_weights_converges_to_the_same_fit():
    """The shape iteration starts each robust fit from the previous one's weights (the same points,
    moved a little): it ends where a fit from equal weights ends, to the iteration's tolerance."""
    x, y, sx, sy = outlier_slopes(20_000)
    earlier = fit_parabola(x, y, sx * 1.001 + 1e-5, sy * 0.999, robust=True)
    cold = fit_parabola(x, y, sx, sy, robust=True)
    warm = fit_parabola(x, y, sx, sy, robust=True, start=earlier)
    for k in ("a", "b", "c", "d", "e1", "e2"):
        assert abs(getattr(warm, k) - getattr(cold, k)) <= 1e-8 * max(abs(getattr(cold, k)), 1e-3), k


def test_one_weighted_pass_on_all_points_matches_iterating_on_all_points():
    """The robust fit on every point is one Newton step from the fit converged on every 10th point (a
    one-step M-estimate): the curvatures differ from iterating on all points by far less than their own
    statistical uncertainty (1e-4 / (sqrt(N) 0.35 m) / 2A ~ 1.4e-4 relative here; found ~3e-7), where
    the subsample's own fit is off by up to 1e-3, and both recover the truth."""
    from sofast_station.measure.fit import reweight_parabola

    x, y, sx, sy = outlier_slopes(200_000, seed=11)
    sub = fit_parabola(x[::10], y[::10], sx[::10], sy[::10], robust=True)
    one = reweight_parabola(x, y, sx, sy, sub)
    full = fit_parabola(x, y, sx, sy, robust=True)
    assert abs(one.a / full.a - 1) < 2e-6 and abs(one.b / full.b - 1) < 2e-6
    assert abs(one.e1 - full.e1) < 1e-8 and abs(one.e2 - full.e2) < 1e-8
    assert abs(1 / (4 * one.a) / 110.0 - 1) < 1e-3 and abs(1 / (4 * one.b) / 105.0 - 1) < 1e-3


def test_one_weighted_pass_is_the_same_on_two_threads():
    """reweight_parabola's second equation on a pool, its terms in blocks: the same bits as in one thread."""
    from concurrent.futures import ThreadPoolExecutor

    from sofast_station.measure.fit import reweight_parabola

    x, y, sx, sy = outlier_slopes(50_001, seed=5)
    sub = fit_parabola(x[::10], y[::10], sx[::10], sy[::10], robust=True)
    with ThreadPoolExecutor(max_workers=2) as pool:
        two = reweight_parabola(x, y, sx, sy, sub, pool=pool)
    one = reweight_parabola(x, y, sx, sy, sub)
    assert one == two and one.sigma == two.sigma


def test_the_paired_solve_is_two_single_solves_bit_for_bit():
    """fit_parabola's two normal equations solved together (one stacked solve and condition number) give
    _solve_scaled's bits for each; a singular or ill-conditioned pair raises what the single solves raise."""
    from sofast_station.measure.fit import _solve_scaled, _solve_scaled_pair

    rng = np.random.default_rng(61)
    for _ in range(50):
        a = rng.normal(size=(2, 40, 3)) * rng.uniform(0.01, 10.0, size=(2, 1, 3))
        grams, rhs = np.swapaxes(a, 1, 2) @ a, rng.normal(size=(2, 3))
        scales = np.sqrt(np.einsum("kij,kij->kj", a, a) / 40)
        ref = np.array([_solve_scaled(grams[k], rhs[k], scales[k]) for k in range(2)])
        assert np.array_equal(_solve_scaled_pair(grams, rhs, scales), ref)
    singular = grams.copy()
    singular[1] = 0.0
    ill = grams.copy()
    ill[0] = np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) + 1e-14 * np.eye(3)
    for bad, what in ((singular, "singular"), (ill, "ill-conditioned")):
        with pytest.raises(AnalysisError, match=what):
            _solve_scaled_pair(bad, rhs, np.ones((2, 3)))
