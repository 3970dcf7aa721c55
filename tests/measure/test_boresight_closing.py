"""The boresight's closing steps on every pixel (measure/boresight.close_on_all_points), on stand-ins for
the intersection and the fit: they stop when the fit meets the design normal, and when they cannot, they
return the frame the returned points are in, marked not converged."""

from __future__ import annotations

import numpy as np

from sofast_station.config import load_config
from sofast_station.measure.boresight import Motion, ShapeSolution, close_on_all_points
from sofast_station.measure.fit import ParabolaFit


def _start(design):
    a = 1.0 / (4.0 * design.focal_length_m)
    pivot = np.array([*design.alignment_point_m, float(design.z(*design.alignment_point_m))])
    return ShapeSolution(np.array([a, a, 0.0, 0.0, 0.0, 0.0]), Motion(0.0, 0.0, 0.0, pivot), 5, 3, True)


def test_closing_turns_the_frame_by_the_all_point_fits_tilt_then_stops(repo_root):
    design = load_config(repo_root / "station.toml").design
    a = 1.0 / (4.0 * design.focal_length_m)
    used = []

    def reduce_all(motion, coefficients):
        used.append(motion)
        return np.zeros((3, 4)), np.zeros((2, 4))

    def fit_all(points, slopes):
        # the all-point fit's normal at the alignment point 0.3 mrad from the design's about y, less what
        # the frame has been turned since (a facet that turns with the frame, as a real one does)
        tilt = 3e-4 - used[-1].beta_rad
        return ParabolaFit(a, a, np.tan(tilt), 0.0, 0.0, 0.0)

    out, *_ = close_on_all_points(_start(design), design, 5.0, np.array([0.0, 0.0, 10.0]), reduce_all, fit_all)
    assert out.converged
    assert abs(out.motion.beta_rad - 3e-4) < 1e-9 and out.motion.alpha_rad == 0.0
    assert len(used) == 2 and out.boresight_iterations == 3 + 2 and out.shape_iterations == 5 + 2
    np.testing.assert_array_equal(out.subsample_coefficients, [a, a, 0.0, 0.0, 0.0, 0.0])


def test_closing_that_cannot_converge_keeps_the_frame_of_its_points(repo_root):
    design = load_config(repo_root / "station.toml").design
    a = 1.0 / (4.0 * design.focal_length_m)
    used = []

    def reduce_all(motion, coefficients):
        used.append(motion)
        return np.full((3, 4), float(len(used))), np.zeros((2, 4))

    def fit_all(points, slopes):
        return ParabolaFit(a, a, 1e-3 * len(used), 0.0, 0.0, 0.0)     # a tilt that never settles

    out, points, _, _ = close_on_all_points(_start(design), design, 5.0, np.array([0.0, 0.0, 10.0]),
                                            reduce_all, fit_all, max_iterations=4)
    assert not out.converged and len(used) == 4
    assert out.motion is used[-1] and np.all(points == 4.0)     # the motion the returned points were made in
