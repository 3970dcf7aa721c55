"""The twin's own OpenCV pinhole camera with 5-term distortion (written from the model, not calling cv2).

Model (normalised coordinates x = X/Z, y = Y/Z, r^2 = x^2 + y^2)::

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y
    u = fx x_d + cx,   v = fy y_d + cy

Pixel (column u, row v) has its centre at image coordinates (u, v).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError, GeometryError
from ..geometry import CameraIntrinsics

#: Newton stops when the distortion residual and step are below this, normalised units.
UNDISTORT_TOLERANCE = 1e-12


class TwinCamera:
    """Projection and back-projection for a :class:`~sofast_station.geometry.CameraIntrinsics`.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
        Camera matrix (no skew: OpenCV's projection ignores it) and distortion (k1, k2, p1, p2, k3).
    """

    def __init__(self, intrinsics: CameraIntrinsics):
        k = intrinsics.matrix
        if k[0, 1] != 0 or k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] != 1:
            raise ConfigError("camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (OpenCV's model has "
                              f"no skew), got {k.tolist()}; recalibrate without skew")
        self.intrinsics = intrinsics
        self.fx, self.fy = float(k[0, 0]), float(k[1, 1])
        self.cx, self.cy = float(k[0, 2]), float(k[1, 2])
        self.k1, self.k2, self.p1, self.p2, self.k3 = (float(c) for c in intrinsics.distortion)

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted normalised coordinates from ideal ones (dimensionless)."""
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        x_d = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        y_d = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return x_d, y_d

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Image coordinates (..., 2) = (u, v) pixels of points (..., 3) in the camera frame, metres.

        Points with Z <= 0 (behind the camera) give NaN.
        """
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            z_pos = np.where(z > 0, z, np.nan)
            x_d, y_d = self.distort(p[..., 0] / z_pos, p[..., 1] / z_pos)
        return np.stack([self.fx * x_d + self.cx, self.fy * y_d + self.cy], axis=-1)

    def undistort(self, x_d: np.ndarray, y_d: np.ndarray, max_iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
        """Ideal normalised coordinates from distorted ones, by Newton's method to 1e-12.

        Raises
        ------
        GeometryError
            If the distortion does not invert for some point (the model folds over inside the image).
        """
        x_d = np.asarray(x_d, dtype=np.float64)
        y_d = np.asarray(y_d, dtype=np.float64)
        x, y = x_d.copy(), y_d.copy()
        k1, k2, k3, p1, p2 = self.k1, self.k2, self.k3, self.p1, self.p2
        converged = False
        for _ in range(max_iterations):
            # All points iterate together: they converge within a step or two of each other, and whole-
            # array arithmetic is much cheaper than tracking the unconverged subset.
            xy = x * y
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_radial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))      # 2 d(radial)/d(r^2)
            res_x = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x) - x_d
            res_y = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy - y_d
            j_xx = radial + x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
            j_xy = xy * d_radial + 2.0 * p1 * x + 2.0 * p2 * y             # = j_yx
            j_yy = radial + y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
            det = j_xx * j_yy - j_xy * j_xy
            step_x = (j_yy * res_x - j_xy * res_y) / det
            step_y = (j_xx * res_y - j_xy * res_x) / det
            x -= step_x
            y -= step_y
            worst = max(float(np.max(np.abs(res_x), initial=0.0)), float(np.max(np.abs(res_y), initial=0.0)),
                        float(np.max(np.abs(step_x), initial=0.0)), float(np.max(np.abs(step_y), initial=0.0)))
            if worst < UNDISTORT_TOLERANCE:
                converged = True
                break
        if not converged:
            bad = ~((np.abs(res_x) < UNDISTORT_TOLERANCE) & (np.abs(res_y) < UNDISTORT_TOLERANCE)
                    & (np.abs(step_x) < UNDISTORT_TOLERANCE) & (np.abs(step_y) < UNDISTORT_TOLERANCE))
            first = np.flatnonzero(bad.ravel())[0]
            raise GeometryError(f"the camera distortion does not invert at {int(bad.sum())} image points "
                                f"(e.g. normalised {float(x_d.ravel()[first]):.4g}, {float(y_d.ravel()[first]):.4g}): "
                                "the distortion model folds over inside the image; recalibrate the camera")
        return x, y

    def pixel_rays(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit ray directions (..., 3) in the camera frame through image points (u, v), pixels."""
        x_d = (np.asarray(u, dtype=np.float64) - self.cx) / self.fx
        y_d = (np.asarray(v, dtype=np.float64) - self.cy) / self.fy
        x, y = self.undistort(x_d, y_d)
        rays = np.stack([x, y, np.ones_like(x)], axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)
