"""The boresight's closing steps on every pixel (measure/boresight.close_on_all_points), on stand-ins for
the intersection and the fit: they stop when the fit meets the design normal, and when they cannot, they
return the frame the returned points are in, marked not converged."""

from __future__ import annotations

import numpy as np

from sofast_station.config import load_config
from sofast_station.measure.boresight import Assembly, Motion, ShapeSolution, close_on_all_points
from sofast_station.measure.fit import ParabolaFit


def _close(repo_root, tilt_of, max_iterations: int = 20):
    """close_on_all_points from the design's own parabola (5 shape and 3 boresight iterations so far), with
    an all-point fit whose x slope at the alignment point is tan(tilt_of(motions so far)). Returns (the
    solution, the returned points, the motions the intersections were made in, the design's A)."""
    design = load_config(repo_root / "station.toml").design
    a = 1.0 / (4.0 * design.focal_length_m)
    pivot = np.array([*design.alignment_point_m, float(design.z(*design.alignment_point_m))])
    start = ShapeSolution(np.array([a, a, 0.0, 0.0, 0.0, 0.0]), Motion(0.0, 0.0, 0.0, pivot), 5, 3, True)
    used = []

    def reduce_all(motion, coefficients):
        used.append(motion)
        return np.full((3, 4), float(len(used))), np.zeros((2, 4))

    def fit_all(points, slopes):
        return ParabolaFit(a, a, np.tan(tilt_of(used)), 0.0, 0.0, 0.0)

    assembly = Assembly(np.zeros(3), np.zeros((3, 0)), np.zeros((3, 0)), np.array([0.0, 0.0, 10.0]))  # screen centre
    out, points, _, _ = close_on_all_points(start, design, 5.0, assembly, reduce_all, fit_all, max_iterations)
    return out, points, used, a


def test_closing_turns_the_frame_by_the_all_point_fits_tilt_then_stops(repo_root):
    # the all-point fit's normal at the alignment point 0.3 mrad from the design's about y, less what the
    # frame has been turned since (a facet that turns with the frame, as a real one does)
    out, _, used, a = _close(repo_root, lambda used: 3e-4 - used[-1].beta_rad)
    assert out.converged
    assert abs(out.motion.beta_rad - 3e-4) < 1e-9 and out.motion.alpha_rad == 0.0
    assert len(used) == 2 and out.boresight_iterations == 3 + 2 and out.shape_iterations == 5 + 2
    np.testing.assert_array_equal(out.subsample_coefficients, [a, a, 0.0, 0.0, 0.0, 0.0])


def test_closing_that_cannot_converge_keeps_the_frame_of_its_points(repo_root):
    out, points, used, _ = _close(repo_root, lambda used: 1e-3 * len(used), max_iterations=4)  # never settles
    assert not out.converged and len(used) == 4
    assert out.motion is used[-1] and np.all(points == 4.0)     # the motion the returned points were made in
