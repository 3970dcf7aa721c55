"""Photographs of ArUco markers and of a dot target, rendered from a known truth, for the geometry calibrations'
tests (``calibrate camera-position``, ``calibrate dots``).

Nothing here comes from ``sofast_station``: the lens is OpenCV's pinhole with the 5-term distortion written out
in numpy and inverted by fixed-point iteration, every pixel is sampled on an n x n lattice of sub-rays (a
sensor integrates its area), each sub-ray is intersected with the planes of the scene (markers on their white
paper, the dot board, the wall behind), and the picture is blurred, given noise and rounded to 8 bits. OpenCV
draws only the markers' printed bit patterns (``generateImageMarker``: what a printer would be given) and the
blur.

Frames: the world frame is the markers' (metres); a camera is ``x_cam = R x_world + t`` (OpenCV's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class Lens:
    """A camera: image size (pixels), focal lengths and principal point (pixels), distortion (k1 k2 p1 p2 k3)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)

    def undistort(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image coordinates (x, y) whose distorted projection is the pixel (u, v)."""
        xd, yd = (u - self.cx) / self.fx, (v - self.cy) / self.fy
        x, y = xd.copy(), yd.copy()
        for _ in range(50):
            px, py = self.distort(x, y)
            ex, ey = xd - px, yd - py
            x, y = x + ex, y + ey
            if max(np.abs(ex).max(initial=0.0), np.abs(ey).max(initial=0.0)) < 1e-13:
                break
        return x, y

    def project(self, rotation: np.ndarray, translation: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points (N, 3)."""
        pc = points @ rotation.T + translation
        x, y = self.distort(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2])
        return np.column_stack([self.fx * x + self.cx, self.fy * y + self.cy])


@dataclass
class Plane:
    """A textured planar patch: points ``origin + s a + t b`` for (s, t) where ``texture(s, t)`` is not NaN.

    ``texture`` returns reflectance 0..1 (NaN: the patch is not there); ``corners`` are the patch's outline
    in the world (for the pixel box it can cover)."""

    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    texture: object
    corners: np.ndarray


def look_at(position: np.ndarray, target: np.ndarray, down: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a camera at *position* looking at *target*, its image rows running along *down* (world)."""
    z = np.asarray(target, float) - position
    z /= np.linalg.norm(z)
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rotation = np.vstack([x, y, z])
    return rotation, -rotation @ position


def marker_plane(marker_id: int, corners: np.ndarray, dictionary: str = "DICT_4X4_1000",
                 margin: float = 0.25) -> Plane:
    """An ArUco marker printed on white paper: *corners* (4, 3) are its top-left, top-right, bottom-right and
    bottom-left corners (a square); the paper reaches *margin* times the side beyond them."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    cells = d.markerSize + 2
    bits = cv2.aruco.generateImageMarker(d, int(marker_id), cells, borderBits=1).astype(float) / 255.0
    origin = corners[0]
    side = np.linalg.norm(corners[1] - corners[0])
    a = (corners[1] - corners[0]) / side
    b = (corners[3] - corners[0]) / np.linalg.norm(corners[3] - corners[0])

    def texture(s, t):
        out = np.full(s.shape, np.nan)
        paper = (s > -margin * side) & (s < (1 + margin) * side) & (t > -margin * side) & (t < (1 + margin) * side)
        out[paper] = 0.92
        inside = (s >= 0) & (s < side) & (t >= 0) & (t < side)
        i = np.clip((t[inside] / side * cells).astype(int), 0, cells - 1)
        j = np.clip((s[inside] / side * cells).astype(int), 0, cells - 1)
        out[inside] = 0.05 + 0.87 * bits[i, j]
        return out

    m = margin * side
    outline = np.array([origin - m * a - m * b, origin + (side + m) * a - m * b,
                        origin + (side + m) * a + (side + m) * b, origin - m * a + (side + m) * b])
    return Plane(origin, a, b, texture, outline)


@dataclass
class DotBoard:
    """A board of dark round dots on a square lattice: dot (i, j) at ``origin + i pitch a + j pitch b`` for
    i in ``range(*i_range)``, j in ``range(*j_range)`` (the board reaches half a pitch beyond the outer dots)."""

    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    pitch: float
    radius: float
    i_range: tuple
    j_range: tuple
    bow: float = 0.0               # a bow of the board along its normal, metres at its corners (parabolic)
    centres: dict = field(default_factory=dict)

    def __post_init__(self):
        self.a = np.asarray(self.a, float) / np.linalg.norm(self.a)
        b = np.asarray(self.b, float) - np.dot(self.b, self.a) * self.a          # the lattice is square
        self.b = b / np.linalg.norm(b)
        self.normal = np.cross(self.a, self.b)

    def dots(self) -> dict[tuple[int, int], np.ndarray]:
        """Every dot's true centre (world, metres), by lattice index (i, j)."""
        out = {}
        for i in range(*self.i_range):
            for j in range(*self.j_range):
                out[(i, j)] = self.origin + i * self.pitch * self.a + j * self.pitch * self.b + \
                    self.sag(i * self.pitch, j * self.pitch) * self.normal
        return out

    def sag(self, s, t):
        half = max(abs(v) for v in (*self.i_range, *self.j_range)) * self.pitch
        return self.bow * (np.asarray(s) ** 2 + np.asarray(t) ** 2) / (2 * half * half)

    def plane(self) -> Plane:
        p, r = self.pitch, self.radius
        lo_i, hi_i = self.i_range[0] - 0.5, self.i_range[1] - 0.5
        lo_j, hi_j = self.j_range[0] - 0.5, self.j_range[1] - 0.5

        def texture(s, t):
            out = np.full(s.shape, np.nan)
            on = (s > lo_i * p) & (s < hi_i * p) & (t > lo_j * p) & (t < hi_j * p)
            out[on] = 0.9
            ds = s[on] - np.round(s[on] / p) * p
            dt = t[on] - np.round(t[on] / p) * p
            out[np.flatnonzero(on)[ds * ds + dt * dt < r * r]] = 0.12
            return out

        o, a, b = self.origin, self.a, self.b
        outline = np.array([o + lo_i * p * a + lo_j * p * b, o + hi_i * p * a + lo_j * p * b,
                            o + hi_i * p * a + hi_j * p * b, o + lo_i * p * a + hi_j * p * b])
        return Plane(o, a, b, texture, outline)


def render(lens: Lens, rotation: np.ndarray, translation: np.ndarray, planes: list[Plane],
           board: DotBoard | None = None, wall: float = 0.8, samples: int = 4, blur_px: float = 0.6,
           noise_dn: float = 1.5, rng: np.random.Generator | None = None) -> np.ndarray:
    """A grey uint8 photograph of *planes* (and the dot *board*, bowed as it is) in front of a uniform wall."""
    rng = np.random.default_rng(0) if rng is None else rng
    image = np.full((lens.height, lens.width), wall)
    centre = -rotation.T @ translation
    targets = list(planes) + ([board.plane()] if board is not None else [])
    for index, plane in enumerate(targets):
        px = lens.project(rotation, translation, plane.corners)
        u0, v0 = np.floor(px.min(axis=0)).astype(int) - 2
        u1, v1 = np.ceil(px.max(axis=0)).astype(int) + 3
        u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, lens.width), min(v1, lens.height)
        if u1 <= u0 or v1 <= v0:
            continue
        offsets = (np.arange(samples) + 0.5) / samples - 0.5
        vv, uu = np.mgrid[v0:v1, u0:u1]
        shape = uu.shape + (samples, samples)
        su = np.broadcast_to(uu[..., None, None] + offsets[None, None, None, :], shape).ravel()
        sv = np.broadcast_to(vv[..., None, None] + offsets[None, None, :, None], shape).ravel()
        x, y = lens.undistort(su, sv)
        rays = np.column_stack([x, y, np.ones_like(x)]) @ rotation       # world directions (rows)
        is_board = board is not None and index == len(targets) - 1
        normal = np.cross(plane.a, plane.b)
        lam = ((plane.origin - centre) @ normal) / (rays @ normal)
        hit = centre + lam[:, None] * rays
        if is_board:                      # one Newton step onto the bowed surface is plenty for millimetres
            rel = hit - plane.origin
            s, t = rel @ plane.a, rel @ plane.b
            lam = lam + board.sag(s, t) / (rays @ normal)
            hit = centre + lam[:, None] * rays
        rel = hit - plane.origin
        value = plane.texture(rel @ plane.a, rel @ plane.b)
        value[lam <= 0] = np.nan
        block = image[v0:v1, u0:u1][..., None, None].repeat(samples, 2).repeat(samples, 3).ravel()
        value = np.where(np.isnan(value), block, value)
        image[v0:v1, u0:u1] = value.reshape(v1 - v0, u1 - u0, samples, samples).mean(axis=(2, 3))
    dn = 20.0 + 215.0 * image
    if blur_px > 0:
        dn = cv2.GaussianBlur(dn, (0, 0), blur_px)
    dn = dn + rng.normal(0.0, noise_dn, dn.shape)
    return np.clip(np.round(dn), 0, 255).astype(np.uint8)


# -- scenes ------------------------------------------------------------------------------------------------------
#: The world frame of OpenCSP's dot calibration: the markers on a wall at z = 0, a camera in front of it at
#: z > 0 looking along -z sees +x to its left and +y downwards.
RIGHT, DOWN = np.array([-1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])


def wall_markers(centres_xy: list, ids: list, side: float, rng: np.random.Generator, z_sd: float = 0.01):
    """Markers printed upright (as the camera sees them) on the wall, each off the wall by a random few
    millimetres (a surveyed table need not be planar): (ids, corners (M, 4, 3), planes)."""
    corners = []
    for x, y in centres_xy:
        o = np.array([x, y, rng.normal(0.0, z_sd)]) - 0.5 * side * RIGHT - 0.5 * side * DOWN
        corners.append([o, o + side * RIGHT, o + side * (RIGHT + DOWN), o + side * DOWN])
    corners = np.array(corners)
    return list(ids), corners, [marker_plane(i, c) for i, c in zip(ids, corners)]


def camera_in_front(rng: np.random.Generator, x: float = 0.0, distance: float = 2.6, spread: float = 0.1):
    """(R, t, centre) of a camera about *distance* in front of the wall, *x* to the side, aimed near the
    origin."""
    centre = np.array([x + rng.normal(0.0, spread), rng.normal(0.0, 1.5 * spread), distance + rng.normal(0.0, spread)])
    target = np.array([rng.normal(0.0, 0.05), rng.normal(0.0, 0.05), 0.0])
    rotation, translation = look_at(centre, target, DOWN)
    return rotation, translation, centre
