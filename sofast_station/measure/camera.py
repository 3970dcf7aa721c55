"""Camera model: pixel rays and projection (OpenCV pinhole with the 5-term distortion model)."""

from __future__ import annotations

import cv2
import numpy as np

from ..geometry import CameraIntrinsics, Pose

UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-14)
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
    norm = _undistort(pts, camera.matrix, camera.distortion, None, np.eye(3), np.eye(3),
                      UNDISTORT_CRITERIA).reshape(-1, 2)
    x, y = norm[:, 0], norm[:, 1]
    inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
    return np.stack([x * inv, y * inv, inv])


#: The camera's inputs :func:`moved_rays` moves, in OpenCV's order of the projection's derivatives.
CAMERA_INPUTS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def moved_rays(camera: CameraIntrinsics, rays: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """The unit rays of the image points whose rays through *camera* are *rays* (3, N), with each of the
    camera's inputs (:data:`CAMERA_INPUTS`: f and c in pixels, the distortion coefficients) moved in turn by
    its *steps* (9,), to first order in the move: (9, 3, N).

    Each point's normalised image coordinates n move by -(dp/dn)^-1 dp/dq step for input q, with the
    projection's derivatives p(n; q) from one OpenCV call for all points and inputs (undistorting every point
    anew for each moved camera, :func:`pixel_rays`, took 12 times as long on 3,500 points). Against that
    exact undistortion the error is second order in the step: for moves of the order of a camera
    calibration's standard uncertainty, a few parts in a thousand of the rays' change (tested)."""
    r = np.asarray(rays, np.float64)
    x, y = r[0] / r[2], r[1] / r[2]
    n = x.size
    obj = np.column_stack([x, y, np.ones(n)]).reshape(-1, 1, 3)
    _, jac = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), camera.matrix, camera.distortion)
    jac = jac.reshape(n, 2, -1)
    # dp/dn: the derivatives by the translation's x and y (the points lie at unit depth, the pose is the identity)
    a00, a01, a10, a11 = jac[:, 0, 3], jac[:, 0, 4], jac[:, 1, 3], jac[:, 1, 4]
    step = np.asarray(steps, np.float64)[:, None]
    b0, b1 = jac[:, 0, 6:15].T * step, jac[:, 1, 6:15].T * step            # (9, N): dp/dq times the step
    det = a00 * a11 - a01 * a10
    mx = x - (a11 * b0 - a01 * b1) / det
    my = y - (a00 * b1 - a10 * b0) / det
    out = np.empty((step.shape[0], 3, n))            # C order: each moved camera's rays contiguous, as the kernels'
    out[:, 2] = 1.0 / np.sqrt(mx * mx + my * my + 1.0)
    out[:, 0] = mx * out[:, 2]
    out[:, 1] = my * out[:, 2]
    return out


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
    out = np.empty((3, v.shape[1]), dtype=np.result_type(v, r))
    tmp = np.empty(v.shape[1], dtype=out.dtype)
    for i in range(3):      # ((r_i0 v0 + r_i1 v1) + r_i2 v2) + t_i, in place (the same bits)
        row = np.multiply(v[0], r[i, 0], out=out[i])
        row += np.multiply(v[1], r[i, 1], out=tmp)
        row += np.multiply(v[2], r[i, 2], out=tmp)
        row += t[i] if translate else 0.0
    return out


class RayTable:
    """Unit pixel rays of one camera, computed per pixel the first time a pixel is asked for.

    The same rays as :func:`pixel_rays` (each pixel is undistorted on its own, so a pixel's ray is the same
    bits whichever batch computes it) without the full grid's cost up front: a facet imaged near where the
    previous one was needs (almost) no new undistortion. Memory: 24 bytes and a flag per camera pixel.

    Parameters
    ----------
    camera : CameraIntrinsics
    """

    def __init__(self, camera: CameraIntrinsics):
        self.camera = camera
        n = camera.width_px * camera.height_px
        self._rays = np.empty((3, n))
        self._known = np.zeros(n, dtype=bool)
        self._full = False          # every pixel known (then take() checks nothing)

    @classmethod
    def from_grid(cls, camera: CameraIntrinsics, grid: np.ndarray) -> "RayTable":
        """A table already filled from :func:`ray_grid` (3, height, width)."""
        if grid.shape != (3, camera.height_px, camera.width_px):
            raise ValueError(f"ray grid has shape {grid.shape}, expected {(3, camera.height_px, camera.width_px)}")
        table = cls(camera)
        table._rays[:] = grid.reshape(3, -1)
        table._known[:] = True
        table._full = True
        return table

    def fill(self, flat_idx: np.ndarray | None = None) -> None:
        """Compute the rays of the flat pixel indices *flat_idx* (every pixel when None) not known yet."""
        if self._full:
            return
        if flat_idx is None:
            flat_idx = np.arange(self._known.size)
        missing = flat_idx[~self._known[flat_idx]]
        if missing.size:
            rows, cols = np.divmod(missing, self.camera.width_px)
            self._rays[:, missing] = pixel_rays(self.camera, cols, rows)
            self._known[missing] = True
        self._full = bool(self._known.all()) if missing.size else self._full

    @property
    def n_known(self) -> int:
        """How many pixels' rays are known."""
        return int(np.count_nonzero(self._known))

    def known(self) -> tuple[np.ndarray, np.ndarray]:
        """The pixels computed so far: their flat (raster) indices (N,) and rays (3, N), a copy."""
        idx = np.flatnonzero(self._known)
        return idx, self._rays[:, idx]

    def add_known(self, flat_idx: np.ndarray, rays: np.ndarray) -> None:
        """Take rays computed earlier for this camera (:meth:`known` of a table of the same calibration, kept
        elsewhere): the pixels *flat_idx* (N,) are then known with the rays (3, N)."""
        flat_idx = np.asarray(flat_idx, dtype=np.int64)
        rays = np.asarray(rays, dtype=np.float64)
        if flat_idx.ndim != 1 or rays.shape != (3, flat_idx.size):
            raise ValueError(f"need (N,) pixel indices and (3, N) rays, got {flat_idx.shape} and {rays.shape}")
        if flat_idx.size and (flat_idx.min() < 0 or flat_idx.max() >= self._known.size):
            raise ValueError(f"pixel indices outside the camera's {self._known.size} pixels")
        self._rays[:, flat_idx] = rays
        self._known[flat_idx] = True
        self._full = bool(self._known.all())

    def take(self, flat_idx: np.ndarray) -> np.ndarray:
        """(3, N) unit rays, camera frame, of the pixels with flat (raster) indices *flat_idx*."""
        self.fill(flat_idx)
        out = np.empty((3, np.size(flat_idx)))
        for k in range(3):
            np.take(self._rays[k], flat_idx, out=out[k])
        return out
