"""Photographs of a chessboard as a lab takes them, rendered through a known camera: the truth of
tests/calibrate/test_camera_photos.py and benchmarks/camera_calibration.py.

It shares no code with ``sofast_station`` (nor with the twin's board renderer): numpy and scipy for the
optics, OpenCV only to encode a JPEG. The camera is OpenCV's pinhole with the 5-term distortion model
(k1, k2, p1, p2, k3), written out here; a pixel's ray comes from inverting the distortion by Newton's
method on a grid of pixel positions every few pixels, interpolated (cubic spline) to the sub-pixel
samples, and every render checks the interpolation against the forward model on random samples.

What a photograph holds, in the order light meets it:

* the board: black and white squares (reflectances ``black``, ``white``) inside a white border, on a
  background of another grey (or a given background image), lit by a lamp whose irradiance changes
  linearly across the board (``light_gradient``: the fraction it changes by from one side of the board
  to the other);
* the lens: vignetting, irradiance falling as ``1 - vignetting * (r / r_corner)^2`` in the image;
* pixel integration: each pixel averages ``samples`` sub-pixel rays on a rank-1 lattice (every sample on
  its own row and column, so an edge's position is resolved to 1/(2 samples) px);
* optical blur: a Gaussian point spread of ``blur_px``;
* the sensor: shot noise (``electrons_per_dn``) and read noise (``read_noise_dn``), 8-bit quantisation
  and clipping; optionally JPEG compression.

Board frame (as OpenCV's chessboards): origin at the top-left corner of the squares, +x along the board's
``squares_x`` squares, +y down its ``squares_y``, +z into the board (away from a camera that sees its
face). A pose (R, t) maps board points X to camera points R X + t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class TrueCamera:
    """A pinhole camera with OpenCV's distortion model: pixel u = fx * x_d + cx for the distorted
    normalised coordinate x_d (pixel centres at whole numbers)."""

    width_px: int
    height_px: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float]

    def scaled(self, factor: float) -> TrueCamera:
        """The same lens on a sensor with *factor* times the pixels along each side (a pixel's centre
        u maps to (u + 1/2) * factor - 1/2); the distortion, in normalised coordinates, is unchanged."""
        return replace(self, width_px=int(round(self.width_px * factor)), height_px=int(round(self.height_px * factor)),
                       fx=self.fx * factor, fy=self.fy * factor, cx=(self.cx + 0.5) * factor - 0.5,
                       cy=(self.cy + 0.5) * factor - 0.5)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def distort(self, x, y):
        """Distorted normalised coordinates of undistorted ones."""
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return (x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)

    def undistort(self, xd, yd, iterations: int = 30):
        """Undistorted normalised coordinates of distorted ones: Newton's method with the exact Jacobian.

        Raises RuntimeError where it does not converge to 1e-12 (a lens model that folds within the image).
        """
        k1, k2, p1, p2, k3 = self.distortion
        x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            slope = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)           # d(radial)/d(r2)
            fx_, fy_ = self.distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            a = radial + 2.0 * x * x * slope + 2.0 * p1 * y + 6.0 * p2 * x
            b = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y     # d xd/dy = d yd/dx
            d = radial + 2.0 * y * y * slope + 6.0 * p1 * y + 2.0 * p2 * x
            det = a * d - b * b
            x -= (d * ex - b * ey) / det
            y -= (a * ey - b * ex) / det
        fx_, fy_ = self.distort(x, y)
        if not np.all(np.hypot(fx_ - xd, fy_ - yd) < 1e-12):
            raise RuntimeError("the distortion model does not invert within the image: a lens that folds")
        return x, y

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Pixel positions (N, 2) of camera-frame points (N, 3); NaN behind the camera or outside the
        field of view the model is valid in (beyond 1.05 times the image corner's radius, where a
        polynomial lens model can fold back into the image)."""
        p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        xd, yd = self.distort(x, y)
        uv = np.column_stack([self.fx * xd + self.cx, self.fy * yd + self.cy])
        bad = (p[:, 2] <= 0) | (np.hypot(x, y) > 1.05 * self.field_radius())
        uv[bad] = np.nan
        return uv

    def field_radius(self) -> float:
        """Undistorted normalised radius of the image's farthest corner."""
        return _field_radius(self)


@lru_cache(maxsize=8)
def _field_radius(camera: TrueCamera) -> float:
    u = np.array([-0.5, camera.width_px - 0.5, -0.5, camera.width_px - 0.5])
    v = np.array([-0.5, -0.5, camera.height_px - 0.5, camera.height_px - 0.5])
    x, y = camera.undistort((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
    return float(np.max(np.hypot(x, y)))


#: The NSTTF SOFAST camera (OpenCSP's test data, sofast_common/camera_sofast.h5: "Basler Optics Lab
#: Landscape", 1626 x 1236 px): a long lens, 16.8 degrees across.
NSTTF_BASLER = TrueCamera(1626, 1236, 5492.06431, 5486.27060, 812.5, 617.5,
                          (-0.144160743, 1.60974438, 2.50349816e-05, -1.89904226e-03, 0.0))
#: A short wide-angle lens on a 1920 x 1080 sensor (80 degrees across): strong barrel distortion, the
#: image's corners 24 % nearer its centre than a pinhole would put them, which needs k3.
WIDE_ANGLE = TrueCamera(1920, 1080, 1150.0, 1151.2, 957.3, 543.8, (-0.22, 0.05, 6e-4, -4e-4, -0.004))


@dataclass(frozen=True)
class Board:
    """A printed chessboard: squares_x by squares_y squares of side square_m metres, in a white border of
    border_m metres."""

    squares_x: int
    squares_y: int
    square_m: float
    border_m: float

    @property
    def inner(self) -> tuple[int, int]:
        return self.squares_x - 1, self.squares_y - 1

    def corners(self) -> np.ndarray:
        """Inner corners (N, 3), board frame, metres: rows along x, as OpenCV orders a chessboard's."""
        j, i = np.mgrid[1:self.squares_y, 1:self.squares_x]
        return np.column_stack([i.ravel(), j.ravel(), np.zeros(i.size)]) * self.square_m

    def outline(self, per_side: int = 40) -> np.ndarray:
        """Points (4 per_side, 3) along the outer edge of the white border, board frame."""
        b, w, h = self.border_m, self.squares_x * self.square_m, self.squares_y * self.square_m
        s = np.linspace(0.0, 1.0, per_side, endpoint=False)
        x0, x1, y0, y1 = -b, w + b, -b, h + b
        sides = [(x0 + (x1 - x0) * s, np.full_like(s, y0)), (np.full_like(s, x1), y0 + (y1 - y0) * s),
                 (x1 - (x1 - x0) * s, np.full_like(s, y1)), (np.full_like(s, x0), y1 - (y1 - y0) * s)]
        return np.concatenate([np.column_stack([sx, sy, np.zeros_like(sx)]) for sx, sy in sides])

    def centre(self) -> np.ndarray:
        return np.array([self.squares_x * self.square_m / 2, self.squares_y * self.square_m / 2, 0.0])


#: The reported board: 18 x 23 inner corners (19 x 24 squares), here of 25 mm with a 25 mm border.
LAB_BOARD = Board(19, 24, 0.025, 0.025)


@dataclass(frozen=True)
class Look:
    """How a photograph looks (module docstring): reflectances, light, lens, sensor."""

    white: float = 0.85
    black: float = 0.06
    background: float = 0.3
    exposure_dn: float = 235.0          # DN of the white border where the light is brightest
    light_gradient: float = 0.4
    light_angle_deg: float = 0.0         # direction of the gradient on the board, from +x toward +y
    vignetting: float = 0.35
    blur_px: float = 1.0
    read_noise_dn: float = 1.2
    electrons_per_dn: float = 40.0
    jpeg_quality: int | None = None
    samples: int = 9
    bits: int = 8                       # a deeper sensor's counts (12: 0..4095, as uint16), exposure scaled


def lattice(n: int) -> np.ndarray:
    """n sub-pixel offsets (n, 2) in (-1/2, 1/2): ((j + 1/2)/n, (g j mod n + 1/2)/n) with g the integer
    nearest n / golden ratio that is prime to n."""
    g = max(1, round(n / 1.618034))
    while math.gcd(g, n) != 1:
        g += 1
    j = np.arange(n)
    return np.column_stack([(j + 0.5) / n, ((g * j) % n + 0.5) / n]) - 0.5


@lru_cache(maxsize=4)
def rays(camera: TrueCamera, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted normalised coordinates (x, y) of every pixel's sub-pixel samples, each (H, W, samples).

    Newton's inverse on a grid every 4 px (reaching 48 px beyond the image, so the spline's ends do not
    reach in), cubic-spline interpolated; checked against the forward model on 4000 random samples
    (to 1e-5 px, else RuntimeError).
    """
    step, pad = 4.0, 12
    gu = np.arange(-pad * step, camera.width_px + pad * step + 1, step)
    gv = np.arange(-pad * step, camera.height_px + pad * step + 1, step)
    uu, vv = np.meshgrid(gu, gv)
    gx, gy = camera.undistort((uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy)
    off = lattice(samples)
    u = np.arange(camera.width_px)[None, :, None] + off[None, None, :, 0]
    v = np.arange(camera.height_px)[:, None, None] + off[None, None, :, 1]
    u, v = np.broadcast_arrays(u, v)
    coords = np.stack([((v - gv[0]) / step).ravel(), ((u - gu[0]) / step).ravel()])
    x = map_coordinates(gx, coords, order=3, mode="nearest").reshape(u.shape)
    y = map_coordinates(gy, coords, order=3, mode="nearest").reshape(u.shape)
    pick = np.random.default_rng(0).integers(0, u.size, 4000)
    xd, yd = camera.distort(x.ravel()[pick], y.ravel()[pick])
    err = np.hypot(camera.fx * xd + camera.cx - u.ravel()[pick], camera.fy * yd + camera.cy - v.ravel()[pick])
    if err.max() > 1e-5:
        raise RuntimeError(f"ray interpolation off by {err.max():.2e} px")
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


def render(camera: TrueCamera, board: Board, pose: tuple[np.ndarray, np.ndarray], look: Look,
           rng: np.random.Generator, background: np.ndarray | None = None) -> np.ndarray:
    """The photograph (H, W) uint8 of *board* at *pose* (R, t), as the module docstring says.

    *background*: reflectance (H, W) of what lies behind the board, instead of ``look.background``.
    """
    r, t = (np.asarray(a, dtype=np.float64) for a in pose)
    x, y = rays(camera, look.samples)
    # the ray s (x, y, 1) meets the board plane n . (X - t) = 0, n the board's +z in the camera frame
    n = r[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (n @ t) / (n[0] * x + n[1] * y + n[2])
        px, py, pz = s * x - t[0], s * y - t[1], s - t[2]
        bx = r[0, 0] * px + r[1, 0] * py + r[2, 0] * pz
        by = r[0, 1] * px + r[1, 1] * py + r[2, 1] * pz
    w, h, q = board.squares_x * board.square_m, board.squares_y * board.square_m, board.square_m
    on = (s > 0) & (bx >= -board.border_m) & (bx < w + board.border_m) & (by >= -board.border_m) \
        & (by < h + board.border_m)
    ix, iy = np.floor(bx / q), np.floor(by / q)
    black = (ix >= 0) & (ix < board.squares_x) & (iy >= 0) & (iy < board.squares_y) & ((ix + iy) % 2 == 0)
    a = np.deg2rad(look.light_angle_deg)
    along = ((bx - w / 2) * np.cos(a) + (by - h / 2) * np.sin(a)) / max(w, h)
    light = (1.0 + look.light_gradient * along) / (1.0 + look.light_gradient / 2)
    refl = np.where(black, look.black, look.white) * light
    board_part = np.where(on, refl, 0.0).mean(axis=2)
    cover = on.mean(axis=2)
    behind = look.background if background is None else background
    img = board_part + (1.0 - cover) * behind
    # vignetting, then exposure: the brightest white reads exposure_dn
    uu, vv = np.meshgrid(np.arange(camera.width_px) - camera.cx, np.arange(camera.height_px) - camera.cy)
    r2 = (uu ** 2 + vv ** 2) / (max(camera.cx, camera.width_px - camera.cx) ** 2
                                + max(camera.cy, camera.height_px - camera.cy) ** 2)
    img = img * (1.0 - look.vignetting * r2) * (look.exposure_dn / look.white)
    if look.blur_px > 0:
        img = gaussian_filter(img, look.blur_px, mode="nearest")
    sigma = np.sqrt(look.read_noise_dn ** 2 + np.maximum(img, 0.0) / look.electrons_per_dn)
    img = img + sigma * rng.standard_normal(img.shape)
    if look.bits > 8:
        top = 2 ** look.bits - 1
        return np.clip(np.round(img * (top / 255.0)), 0, top).astype(np.uint16)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    if look.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(look.jpeg_quality)])
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    return img


def true_corners(camera: TrueCamera, board: Board, pose) -> np.ndarray:
    """Pixel positions (N, 2) of the board's inner corners, in :meth:`Board.corners` order (NaN where not
    imaged)."""
    r, t = (np.asarray(a, dtype=np.float64) for a in pose)
    return camera.project(board.corners() @ r.T + t)


def in_view(uv: np.ndarray, camera: TrueCamera, margin_px: float) -> np.ndarray:
    return np.isfinite(uv).all(axis=1) & (uv[:, 0] >= margin_px) & (uv[:, 0] <= camera.width_px - 1 - margin_px) \
        & (uv[:, 1] >= margin_px) & (uv[:, 1] <= camera.height_px - 1 - margin_px)


def board_pose(camera: TrueCamera, board: Board, rng: np.random.Generator, *, tilt_deg: tuple[float, float],
               fill: float, centre: tuple[float, float] = (0.5, 0.5), partial: tuple[float, float] | None = None,
               roll_deg: float = 0.0, margin_px: float = 10.0):
    """A pose (R, t): the board tilted by *tilt_deg* about its x then y axis and rolled by *roll_deg*, its
    centre seen at *centre* (fractions of the width and height).

    Whole (``partial`` None): as near as the board, border included, stays *margin_px* inside the image
    and spans at most *fill* of its width or height. Partly out of view (``partial`` = (lo, hi)): the
    nearest distance at which the fraction of inner corners inside the image is within [lo, hi] while
    the board's outline crosses the image's edge. None when no distance qualifies.
    """
    rot = Rotation.from_euler("zyx", [roll_deg, tilt_deg[1], tilt_deg[0]], degrees=True).as_matrix()
    u = (centre[0] * camera.width_px - camera.cx) / camera.fx
    v = (centre[1] * camera.height_px - camera.cy) / camera.fy
    (x,), (y,) = camera.undistort(np.array([u]), np.array([v]))
    ray = np.array([x, y, 1.0])
    outline, corners = board.outline(), board.corners()
    size = max(camera.width_px, camera.height_px)
    for z in np.geomspace(0.02, 50.0, 700):
        t = z * ray - rot @ board.centre()
        edge = camera.project(outline @ rot.T + t)
        if partial is None:
            if not np.all(in_view(edge, camera, margin_px)):
                continue
            span = max(np.ptp(edge[:, 0]) / camera.width_px, np.ptp(edge[:, 1]) / camera.height_px)
            if span <= fill:
                return rot, t
        else:
            seen = in_view(camera.project(corners @ rot.T + t), camera, margin_px).mean()
            finite = np.isfinite(edge).all(axis=1)
            if partial[0] <= seen <= partial[1] and not np.all(in_view(edge[finite], camera, 0.0)) \
                    and np.ptp(edge[finite], axis=0).max() < 4 * size:
                return rot, t
    return None
