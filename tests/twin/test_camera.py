"""The twin's own camera model against OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sofast_station.errors import ConfigError
from sofast_station.geometry import CameraIntrinsics
from sofast_station.twin import TwinCamera

WIDE = CameraIntrinsics(1600, 1200, [[1100.0, 0, 812.3], [0, 1090.0, 590.7], [0, 0, 1]],
                        [-0.28, 0.09, 0.0012, -0.0007, -0.012])


@pytest.fixture(params=["station", "wide"])
def intrinsics(request, camera_intrinsics):
    return camera_intrinsics if request.param == "station" else WIDE


def test_project_matches_cv2(intrinsics):
    rng = np.random.default_rng(3)
    camera = TwinCamera(intrinsics)
    half_x = 0.6 * intrinsics.width_px / intrinsics.matrix[0, 0]
    half_y = 0.6 * intrinsics.height_px / intrinsics.matrix[1, 1]
    z = rng.uniform(0.5, 12.0, 5000)
    points = np.column_stack([rng.uniform(-half_x, half_x, z.size) * z, rng.uniform(-half_y, half_y, z.size) * z, z])
    ours = camera.project(points)
    theirs, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), intrinsics.matrix, intrinsics.distortion)
    assert np.max(np.abs(ours - theirs.reshape(-1, 2))) < 1e-9


def test_pixel_ray_round_trip(intrinsics):
    camera = TwinCamera(intrinsics)
    w, h = intrinsics.width_px, intrinsics.height_px
    rng = np.random.default_rng(4)
    u = np.concatenate([[-0.5, w - 0.5, -0.5, w - 0.5, 0, w - 1], rng.uniform(-0.5, w - 0.5, 20000)])
    v = np.concatenate([[-0.5, -0.5, h - 0.5, h - 0.5, 0, h - 1], rng.uniform(-0.5, h - 0.5, 20000)])
    rays = camera.pixel_rays(u, v)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-15, rtol=0)
    back = camera.project(rays * 7.3)
    assert np.max(np.abs(back - np.column_stack([u, v]))) < 1e-8
    # and through OpenCV's projection too
    theirs, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), intrinsics.matrix, intrinsics.distortion)
    assert np.max(np.abs(theirs.reshape(-1, 2) - np.column_stack([u, v]))) < 1e-8


def test_points_behind_the_camera_do_not_project(camera_intrinsics):
    uv = TwinCamera(camera_intrinsics).project(np.array([[0.1, 0.1, -1.0], [0.0, 0.0, 0.0]]))
    assert np.all(np.isnan(uv))


def test_skew_is_rejected():
    skewed = CameraIntrinsics(100, 100, [[100.0, 0.5, 50], [0, 100.0, 50], [0, 0, 1]], [0, 0, 0, 0, 0])
    with pytest.raises(ConfigError, match="skew"):
        TwinCamera(skewed)
