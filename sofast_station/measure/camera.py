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
    (N, 3) float64 array of unit vectors with z > 0.
    """
    pts = np.column_stack([columns, rows]).astype(np.float64).reshape(-1, 1, 2)
    norm = _undistort(pts, camera.matrix, camera.distortion, None, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA).reshape(-1, 2)
    rays = np.empty((norm.shape[0], 3))
    rays[:, :2] = norm
    rays[:, 2] = 1.0
    rays /= np.sqrt(np.einsum("ij,ij->i", rays, rays))[:, None]
    return rays


def project(camera: CameraIntrinsics, pose: Pose, points: np.ndarray) -> np.ndarray:
    """Image positions (column, row) of 3-D *points* given in the frame *pose* maps into the camera."""
    rvec, _ = cv2.Rodrigues(pose.rotation)
    img, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), rvec, pose.translation,
                               camera.matrix, camera.distortion)
    return img.reshape(-1, 2)


def ray_grid(camera: CameraIntrinsics) -> np.ndarray:
    """Unit rays of every pixel of the camera, (height, width, 3), camera frame.

    Undistorting two million points takes about a second; a station computes this once per camera
    calibration and hands it to every analysis (:func:`pixel_rays` gives the same rays for a subset).
    """
    rows, cols = np.mgrid[0:camera.height_px, 0:camera.width_px]
    return pixel_rays(camera, cols.ravel(), rows.ravel()).reshape(camera.height_px, camera.width_px, 3)
