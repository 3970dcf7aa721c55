"""The axis angle's bound from kappa_x - kappa_y's own uncertainty (issue 47 item 6): a row that moves both
curvatures alike (the range, a camera's focal length) leaves the axis where it is and must not widen its U; a
row that moves them apart must. The truth is drawn here: the axis angle of (kappa_x, kappa_y, twist) perturbed
by each row's signed response, 4,000 draws, against the bound the budget states."""

from __future__ import annotations

import numpy as np

from sofast_station.measure.uncertainty import budget
from sofast_station.measure.uncertainty.inputs import Input
from sofast_station.measure.uncertainty.systematic import Sensitivities

PATHS = [("curvature_x_per_m",), ("curvature_y_per_m",), ("twist_mrad_per_m",)]


def _axis(kx, ky, tw):
    return 0.5 * np.arctan2(1e-3 * np.asarray(tw), 0.25 * (np.asarray(kx) - np.asarray(ky)))


def _case(rows: np.ndarray):
    """Sensitivities with the signed responses *rows* (n, 3) per standard deviation, every row systematic."""
    inputs = [Input(f"row {i}", f"group {i}", 1.0, "-") for i in range(len(rows))]
    sens = Sensitivities(inputs, PATHS, np.asarray(rows, float), np.zeros((len(rows), 3)), 1000)
    u = np.sqrt(np.sum(np.asarray(rows) ** 2, axis=0))
    return sens, u


def test_common_curvature_change_leaves_the_axis_bound_alone_and_a_split_widens_it():
    figures = {"curvature_x_per_m": 0.0052, "curvature_y_per_m": 0.0050, "twist_mrad_per_m": 0.4}
    kinds = np.array(["systematic"] * 2)
    rng = np.random.default_rng(7)
    for common, split in ((2e-4, 2e-6), (2e-6, 5e-5)):
        rows = np.array([[common, common, 0.0], [split, -split, 4e-3]])
        sens, u = _case(rows)
        u_d, _ = budget._difference_u(sens, sens.linear, np.ones(2), kinds, np.zeros(3), None, None)
        assert abs(u_d - 2 * split) < 1e-12                     # the common row cancels
        bound = budget._axis_angle_floor(figures, PATHS, u, u_d)
        naive = budget._axis_angle_floor(figures, PATHS, u)
        z = rng.normal(size=(4000, 2))
        moved = np.array([figures[p[0]] for p in PATHS])[None, :] + z @ rows
        err = _axis(*moved.T) - _axis(*(figures[p[0]] for p in PATHS))
        err = (err + np.pi / 2) % np.pi - np.pi / 2
        coverage = np.mean(np.abs(err) <= bound)
        assert coverage >= 0.95, coverage                       # the bound still covers the drawn truth
        if common > split:
            # independent curvatures would state it several times wider than anything the draws reach
            assert naive > 3 * bound and np.quantile(np.abs(err), 0.99) < bound
        else:
            # a row moving them apart moves the difference by twice its part: wider than independent errors
            assert bound > 1.2 * naive
