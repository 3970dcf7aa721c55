"""Camera model: pixel rays and projection (OpenCV pinhole with the 5-term distortion model)."""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry import CameraIntrinsics, Pose

_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-14)
# OpenCV 4 names the variant with a convergence criterion undistortPointsIter; OpenCV 5 folds it into
# undistortPoints. The default (5 fixed iterations) leaves errors far above our needs near the corners.
_undistort = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)


def pixel_rays(camera: CameraIntrinsics, columns: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Unit ray directions in the camera frame through the given pixel centres.

    Parameters
    ----------
    columns, rows : (N,) arrays
        Image coordinates, pixels (pixel centres at integers, as in OpenCV).

    Returns
    -------
    (3, N) float64 array of unit vectors with z > 0 (components in rows).
    """
    pts = np.column_stack([columns, rows]).astype(np.float64).reshape(-1, 1, 2)
    norm = _undistort(pts, camera.matrix, camera.distortion, None, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA).reshape(-1, 2)
    x, y = norm[:, 0], norm[:, 1]
    inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
    return np.stack([x * inv, y * inv, inv])


def project(camera: CameraIntrinsics, pose: Pose, points: np.ndarray) -> np.ndarray:
    """Image positions (column, row) of 3-D *points* given in the frame *pose* maps into the camera."""
    rvec, _ = cv2.Rodrigues(pose.rotation)
    img, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), rvec, pose.translation,
                               camera.matrix, camera.distortion)
    return img.reshape(-1, 2)


def ray_grid(camera: CameraIntrinsics) -> np.ndarray:
    """Unit rays of every pixel of the camera, (3, height, width), camera frame.

    Undistorting two million points takes about a second; a station computes this once per camera
    calibration and hands it to every analysis (:func:`pixel_rays` gives the same rays for a subset).
    """
    rows, cols = np.mgrid[0:camera.height_px, 0:camera.width_px]
    return pixel_rays(camera, cols.ravel(), rows.ravel()).reshape(3, camera.height_px, camera.width_px)


def to_frame(pose: Pose, v: np.ndarray, translate: bool = True) -> np.ndarray:
    """Apply *pose* to (3, N) points (or, with ``translate=False``, directions), component by component.

    Written out rather than as a matrix product: (N, 3) @ (3, 3) is slow in numpy for long N, and
    explicit sums cannot depend on BLAS threading.
    """
    r, t = pose.rotation, pose.translation
    return np.stack([r[i, 0] * v[0] + r[i, 1] * v[1] + r[i, 2] * v[2] + (t[i] if translate else 0.0)
                     for i in range(3)])
