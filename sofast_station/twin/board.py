"""Images of a flat calibration target (chessboard, ChArUco) seen by the twin's camera model.

Written with the twin's own camera (:class:`~sofast_station.twin.camera.TwinCamera`: OpenCV's pinhole and
5-term distortion model, inverted by Newton's method), not with OpenCV, so that a camera calibration
tested on these images is checked against an independent forward model.

Target frame (as OpenCV's boards): origin at the top-left corner of the patterned area, +x along its
columns, +y down its rows, +z = x cross y, into the board (away from a camera that sees its face).
A pose ``target_to_camera`` maps target points to the camera frame; the identity rotation with a
translation (0, 0, d) shows the target upright and face-on at d metres.

Each pixel averages ``supersample**2`` sub-rays on a rook lattice; a sub-ray's ideal normalised
coordinates come from the pixel centre's (exact) ones and their image gradients (the distortion is smooth,
so the linearisation is good to far below a micro-pixel over a pixel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from ..errors import ConfigError
from ..geometry import CameraIntrinsics, Pose
from .camera import TwinCamera
from .station import rook_lattice


@dataclass(frozen=True)
class PlanarTarget:
    """A printed flat target: a texture of reflectances on a board with a plain margin.

    Parameters
    ----------
    texture : (rows, cols) array
        Reflectance 0 (black) .. 1 (white) of each texel; texel (r, c) covers target
        x in [c, c + 1) * width_m / cols and y in [r, r + 1) * height_m / rows.
    width_m, height_m : float
        Extent of the textured area, metres.
    margin_m : float
        Width of the plain border around it, metres (a chessboard needs a white quiet zone).
    margin_reflectance : float
        Reflectance of that border, 0..1.
    """

    texture: np.ndarray
    width_m: float
    height_m: float
    margin_m: float = 0.0
    margin_reflectance: float = 1.0

    def __post_init__(self):
        tex = np.asarray(self.texture, dtype=np.float64)
        if tex.ndim != 2 or tex.size == 0 or not np.all(np.isfinite(tex)) or tex.min() < 0 or tex.max() > 1:
            raise ConfigError("target texture must be a non-empty 2-D array of reflectances in 0..1")
        if not (self.width_m > 0 and self.height_m > 0 and self.margin_m >= 0):
            raise ConfigError(f"target size must be positive metres (got {self.width_m} x {self.height_m}, "
                              f"margin {self.margin_m})")
        tex.setflags(write=False)
        object.__setattr__(self, "texture", tex)

    def reflectance(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Reflectance at target points (metres); NaN off the board (texture plus margin)."""
        rows, cols = self.texture.shape
        col = np.floor(x_m * (cols / self.width_m))
        row = np.floor(y_m * (rows / self.height_m))
        with np.errstate(invalid="ignore"):
            in_tex = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
            m = self.margin_m
            on_board = (x_m >= -m) & (x_m < self.width_m + m) & (y_m >= -m) & (y_m < self.height_m + m)
        out = np.full(np.shape(x_m), self.margin_reflectance)
        out[in_tex] = self.texture[row[in_tex].astype(np.intp), col[in_tex].astype(np.intp)]
        out[~on_board] = np.nan
        return out


def chessboard_target(squares_x: int, squares_y: int, square_m: float, margin_m: float | None = None) -> PlanarTarget:
    """A chessboard of ``squares_x`` x ``squares_y`` squares, the top-left one black.

    Its inner corners, (squares_x - 1) x (squares_y - 1) of them, lie at ((i + 1) s, (j + 1) s) in the
    target frame (s = ``square_m``). The margin defaults to one square of white.
    """
    if int(squares_x) < 2 or int(squares_y) < 2:
        raise ConfigError(f"a chessboard needs at least 2 x 2 squares, got {squares_x} x {squares_y}")
    r, c = np.mgrid[0:int(squares_y), 0:int(squares_x)]
    texture = ((r + c) % 2).astype(np.float64)
    return PlanarTarget(texture, squares_x * square_m, squares_y * square_m,
                        square_m if margin_m is None else margin_m, 1.0)


def render_target_images(intrinsics: CameraIntrinsics, target: PlanarTarget, target_to_camera: list[Pose], *,
                         supersample: int = 4, dark_dn: float = 25.0, bright_dn: float = 215.0,
                         background_dn: float = 70.0, blur_px: float = 0.0, noise_dn: float = 0.0,
                         rng: np.random.Generator | None = None) -> list[np.ndarray]:
    """Camera frames of *target* in each of the given poses.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
        The camera (OpenCV pinhole and distortion).
    target : PlanarTarget
    target_to_camera : list of Pose
        Where the target is, one frame per pose (metres).
    supersample : int
        Sub-rays per pixel edge (``supersample**2`` per pixel).
    dark_dn, bright_dn : float
        DN of reflectance 0 and 1.
    background_dn : float
        DN where a ray misses the board.
    blur_px : float
        Standard deviation of a Gaussian blur (defocus), pixels; 0 for none.
    noise_dn : float
        Standard deviation of additive Gaussian noise, DN (needs *rng*).
    rng : numpy Generator, optional

    Returns
    -------
    list of (height_px, width_px) uint8 arrays
    """
    camera = TwinCamera(intrinsics)
    height, width = intrinsics.shape
    v_px, u_px = np.mgrid[0:height, 0:width].astype(np.float64)
    x0, y0 = camera.undistort((u_px - camera.cx) / camera.fx, (v_px - camera.cy) / camera.fy)
    dx_du, dx_dv = np.gradient(x0, axis=1), np.gradient(x0, axis=0)
    dy_du, dy_dv = np.gradient(y0, axis=1), np.gradient(y0, axis=0)
    offsets = rook_lattice(int(supersample)) if supersample > 1 else np.zeros((1, 2))
    images = []
    for pose in target_to_camera:
        # Ideal normalised image point -> target point: the ray s d, d = (x, y, 1), meets the target plane
        # n . (P - t) = 0 (n its z axis, t its origin, camera frame) at s = k / (n . d), k = n . t; the
        # target coordinates are b_j = r_j . (s d - t) = (k r_j - (r_j . t) n) . d / (n . d) (r_j its axes):
        # a homography with rows k r_0 - (r_0 . t) n, k r_1 - (r_1 . t) n and n.
        r, t = pose.rotation, pose.translation
        n = r[:, 2]
        k = float(n @ t)
        h = np.array([k * r[:, 0] - (r[:, 0] @ t) * n, k * r[:, 1] - (r[:, 1] @ t) * n, n])
        acc = np.zeros((height, width))
        for du, dv in offsets:
            x = x0 + du * dx_du + dv * dx_dv
            y = y0 + du * dy_du + dv * dy_dv
            w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
            hit = (w * k) > 0                       # the ray meets the plane in front of the camera
            with np.errstate(divide="ignore", invalid="ignore"):
                bx = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
                by = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
            refl = target.reflectance(np.where(hit, bx, np.nan), np.where(hit, by, np.nan))
            acc += np.where(np.isfinite(refl), dark_dn + (bright_dn - dark_dn) * np.nan_to_num(refl), background_dn)
        img = acc / len(offsets)
        if blur_px > 0:
            img = gaussian_filter(img, float(blur_px), mode="nearest")
        if noise_dn > 0:
            if rng is None:
                raise ConfigError("noise_dn > 0 needs an rng")
            img = img + rng.normal(0.0, float(noise_dn), img.shape)
        images.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return images
