"""The rays of a camera whose inputs are moved a little, to first order (measure/camera.py ``moved_rays``), against
OpenCV's undistortion of the same image points through each moved camera."""

import dataclasses

import numpy as np
import pytest

from sofast_station.geometry import CameraIntrinsics
from sofast_station.measure.camera import CAMERA_INPUTS, moved_rays, pixel_rays

#: Where each input sits in (matrix, distortion).
_MATRIX = ((0, 0), (1, 1), (0, 2), (1, 2))


def _moved(camera: CameraIntrinsics, q: int, step: float) -> CameraIntrinsics:
    matrix, dist = camera.matrix.copy(), camera.distortion.copy()
    if q < 4:
        matrix[_MATRIX[q]] += step
    else:
        dist[q - 4] += step
    return dataclasses.replace(camera, matrix=matrix, distortion=dist)


@pytest.mark.parametrize("seed", range(4))
def test_each_moved_cameras_rays_to_first_order(seed):
    """Four drawn cameras like the stations' and OpenCSP's (f 2000-6000 px over 1600 px, principal point within
    5 % of the centre, k1 -0.15 to 0.05, k2 -0.1 to 1.6, tangential terms to 2e-3, k3 to 0.02) and 3000 image
    points each over the whole frame; each input moved by about twice OpenCSP's standard uncertainties (f 2 px, c
    3 px, k1 0.004, k2 0.02, p 1e-4, k3 0.01) and the points undistorted again by OpenCV (the truth). The
    first-order rays must carry the change to 1 % of its RMS: the error is second order in the move, (step /
    scale) of the change, where the scale over which the rays' response curves is the focal length for f and c
    (0.05-0.09 % measured) and about the coefficient's own range for the distortion (at most 0.19 %, k2's, on
    20 cameras so drawn); 1 % allows five times that."""
    rng = np.random.default_rng(seed)
    w, h = 1600, 1200
    f = rng.uniform(2000.0, 6000.0)
    camera = CameraIntrinsics(w, h, [[f, 0.0, w / 2 + rng.uniform(-80, 80)], [0.0, f * rng.uniform(0.99, 1.01),
                                                                              h / 2 + rng.uniform(-60, 60)],
                                     [0.0, 0.0, 1.0]],
                              [rng.uniform(-0.15, 0.05), rng.uniform(-0.1, 1.6), rng.uniform(-2e-3, 2e-3),
                               rng.uniform(-2e-3, 2e-3), rng.uniform(-0.02, 0.02)])
    cols, rows = rng.uniform(0, w - 1, 3000), rng.uniform(0, h - 1, 3000)
    rays = pixel_rays(camera, cols, rows)
    steps = np.array([2.0, 2.0, 3.0, 3.0, 0.004, 0.02, 1e-4, 1e-4, 0.01])
    ours = moved_rays(camera, rays, steps)
    assert ours.shape == (len(CAMERA_INPUTS), 3, rays.shape[1])
    assert ours.flags.c_contiguous                      # each camera's rays one contiguous (3, N) block
    np.testing.assert_allclose(np.linalg.norm(ours, axis=1), 1.0, atol=1e-14)
    for q, name in enumerate(CAMERA_INPUTS):
        truth = pixel_rays(_moved(camera, q, steps[q]), cols, rows)
        change = np.sqrt(np.mean((truth - rays) ** 2))
        assert change > 1e-9, name                       # the move is seen, far above rounding (1e-16)
        assert np.sqrt(np.mean((ours[q] - truth) ** 2)) < 0.01 * change, name


def test_a_zero_step_leaves_the_rays():
    """No move, no change: the rays come back to rounding (they go through the normalised coordinates and back)."""
    camera = CameraIntrinsics(800, 600, [[900.0, 0.0, 401.0], [0.0, 905.0, 299.0], [0.0, 0.0, 1.0]],
                              [-0.2, 0.05, 1e-3, -1e-3, 0.0])
    rng = np.random.default_rng(7)
    rays = pixel_rays(camera, rng.uniform(0, 799, 500), rng.uniform(0, 599, 500))
    out = moved_rays(camera, rays, np.zeros(9))
    for q in range(9):
        np.testing.assert_allclose(out[q], rays, atol=1e-15)
