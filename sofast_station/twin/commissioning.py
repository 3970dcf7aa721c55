"""What the cameras of a station's commissioning see, rendered from the twin's truth.

Two scenes (docs/calibration.md#commissioning-the-geometry):

* :class:`ScreenScene`, for ``calibrate screen``: the true panel (:class:`~sofast_station.twin.assembly.TrueScreen`,
  showing whatever the display shows) and a flat, certified scale board fixed beside it, photographed by
  a second, handheld or tripod camera from several poses (:func:`handheld_poses`).
* :class:`MirrorScene`, for ``calibrate pose``: the station camera, where it really is, looking at a flat
  reference mirror in the fixture whose printed frame is a target; through the mirror it sees the true
  panel.

Both are traced once per pose (every pixel's sub-rays: what they hit, and where on the display or the board),
so a frame is a lookup into the display image. Sub-rays lie on a rook lattice (the twin's, for sharp edges
of printed squares and displayed markers), their ideal image coordinates from the pixel centre's exact ones
and their image gradients (the distortion is smooth across a pixel). An LCD pixel is a uniform square: a
sub-ray takes the value of the display pixel it lands in.

Written from the geometry of the scenes; nothing is shared with :mod:`sofast_station.measure`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, GeometryError
from ..geometry import CameraIntrinsics, Pose, ScreenSpec
from .assembly import TrueScreen
from .board import PlanarTarget
from .camera import TwinCamera
from .parameters import TwinOptics
from . import sensor
from .station import rook_lattice

#: What a sub-ray hits.
_NOTHING, _BEZEL, _BOARD, _DISPLAY = 0, 1, 2, 3


def _apply(pose: Pose, points: np.ndarray, translate: bool = True) -> np.ndarray:
    """*pose* applied to (N, 3) points (or, without *translate*, directions), component by component: an
    (N, 3) @ (3, 3) product is several times slower in numpy for millions of rows."""
    r, t = pose.rotation, pose.translation
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    out = np.empty_like(points)
    for i in range(3):
        out[:, i] = r[i, 0] * x + r[i, 1] * y + r[i, 2] * z
        if translate:
            out[:, i] += t[i]
    return out


def _luminance_table(gamma: float, floor: float) -> np.ndarray:
    """Display luminance (fraction of white) of each command 0..255."""
    levels = np.arange(256, dtype=np.float64) / 255.0
    return (floor + (1.0 - floor) * levels ** gamma).astype(np.float32)


def _sub_rays(camera: TwinCamera, supersample: int) -> tuple[np.ndarray, int]:
    """Unit ray directions (n_px * s, 3), camera frame, of every pixel's sub-rays (pixel-major), and s.

    Every pixel's rook lattice is shifted by its own offset (modulo the pixel; a fixed pseudo-random one
    per pixel): the same lattice in every pixel would quantise a long straight edge's position to the same
    1/s^2 of a pixel all along it (a bias of up to 1/(2 s^2) px for a side that runs along the pixel grid),
    where shifted lattices leave errors that average away along the edge, as a sensor's area does.
    """
    height, width = camera.intrinsics.shape
    v_px, u_px = np.mgrid[0:height, 0:width].astype(np.float64)
    x0, y0 = camera.undistort((u_px - camera.cx) / camera.fx, (v_px - camera.cy) / camera.fy)
    if supersample > 1:
        lattice = rook_lattice(int(supersample)) + 0.5                           # in [0, 1)
        shift = np.random.default_rng(0x5EED).random((height * width, 1, 2))
        offsets = np.mod(lattice[None, :, :] + shift, 1.0) - 0.5                 # (n_px, s, 2)
        dx_du, dx_dv = np.gradient(x0, axis=1), np.gradient(x0, axis=0)
        dy_du, dy_dv = np.gradient(y0, axis=1), np.gradient(y0, axis=0)
        x = x0.reshape(-1, 1) + offsets[:, :, 0] * dx_du.reshape(-1, 1) + offsets[:, :, 1] * dx_dv.reshape(-1, 1)
        y = y0.reshape(-1, 1) + offsets[:, :, 0] * dy_du.reshape(-1, 1) + offsets[:, :, 1] * dy_dv.reshape(-1, 1)
        count = lattice.shape[0]
    else:
        x, y = x0.reshape(-1, 1), y0.reshape(-1, 1)
        count = 1
    rays = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=-1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return rays, count


def sub_rays(intrinsics: CameraIntrinsics, supersample: int) -> tuple[np.ndarray, int]:
    """Every pixel's sub-rays of a camera (unit directions, camera frame) and their count per pixel."""
    return _sub_rays(TwinCamera(intrinsics), supersample)


def _display_hits(screen: TrueScreen, stated: ScreenSpec, origins: np.ndarray, directions: np.ndarray,
                  bezel_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays (screen frame) against the panel: (path t, kind, display pixel flat index)."""
    n = origins.shape[0]
    # only rays that meet the panel's plane near the panel go on to its true (bowed) surface
    with np.errstate(invalid="ignore", divide="ignore"):
        t0 = -origins[:, 2] / directions[:, 2]
        px = origins[:, 0] + t0 * directions[:, 0]
        py = origins[:, 1] + t0 * directions[:, 1]
    reach = 0.5 * max(screen.width_m, screen.height_m) * 0.05 + bezel_m + 0.01
    near = np.flatnonzero(np.isfinite(t0) & (t0 > 0) & (np.abs(px) < 0.5 * screen.width_m + reach)
                          & (np.abs(py) < 0.5 * screen.height_m + reach))
    t = np.full(n, np.nan)
    pos = np.full((n, 2), np.nan)
    if near.size:
        t[near], pos[near] = screen.trace(origins[near], directions[near])
    kind = np.full(n, _NOTHING, dtype=np.uint8)
    index = np.zeros(n, dtype=np.int64)
    with np.errstate(invalid="ignore"):
        col = np.floor(pos[:, 0] / stated.pitch_x_m)
        row = np.floor((stated.height_m - pos[:, 1]) / stated.pitch_y_m)
        on_panel = np.isfinite(t) & (col >= 0) & (col < stated.width_px) & (row >= 0) & (row < stated.height_px)
        # the bezel: a dark frame around the active area, measured in the panel's true metres
        margin_x, margin_y = bezel_m / screen.scale_x, bezel_m / screen.scale_y
        on_bezel = np.isfinite(t) & ~on_panel & (pos[:, 0] > -margin_x) & (pos[:, 0] < stated.width_m + margin_x) \
            & (pos[:, 1] > -margin_y) & (pos[:, 1] < stated.height_m + margin_y)
    kind[on_panel] = _DISPLAY
    kind[on_bezel] = _BEZEL
    index[on_panel] = row[on_panel].astype(np.int64) * stated.width_px + col[on_panel].astype(np.int64)
    t = np.where(on_panel | on_bezel, t, np.inf)
    return t, kind, index


def _board_hits(board: PlanarTarget, board_to_frame: Pose, origins: np.ndarray,
                directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays (in the frame *board_to_frame* maps into) against the board's plane: (path t, reflectance
    (NaN off the board), board-frame hit points (x, y))."""
    to_board = board_to_frame.inverse()
    o = _apply(to_board, origins)
    d = _apply(to_board, directions, translate=False)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = -o[:, 2] / d[:, 2]
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    with np.errstate(invalid="ignore"):
        x = o[:, 0] + t * d[:, 0]
        y = o[:, 1] + t * d[:, 1]
    refl = board.reflectance(np.where(np.isfinite(t), x, np.nan), np.where(np.isfinite(t), y, np.nan))
    t = np.where(np.isfinite(refl), t, np.inf)
    return t, refl, np.stack([x, y], axis=-1)


@dataclass(frozen=True)
class HandheldCamera:
    """The second camera of ``calibrate screen``: its intrinsics and its sensor.

    Parameters
    ----------
    intrinsics : CameraIntrinsics
        The camera as it really is (OpenCV pinhole and distortion).
    black_dn : float
        Black level, DN.
    white_dn : float
        DN of the display's full white seen straight on (black level included).
    board_white_dn : float
        DN of a white square of the scale board in the room's light.
    bezel_dn, background_dn : float
        DN of the screen's bezel and of the room behind.
    read_noise_dn : float
        Read noise, DN.
    electrons_per_dn : float
        Shot noise: variance (DN^2) = signal above black / electrons_per_dn; 0 turns it off.
    """

    intrinsics: CameraIntrinsics
    black_dn: float = 6.0
    white_dn: float = 225.0
    board_white_dn: float = 170.0
    bezel_dn: float = 12.0
    background_dn: float = 40.0
    read_noise_dn: float = 0.8
    electrons_per_dn: float = 30.0

    def __post_init__(self):
        if not 0 <= self.black_dn < self.white_dn <= 255:
            raise ConfigError(f"handheld camera: need 0 <= black_dn < white_dn <= 255, got {self.black_dn}, "
                              f"{self.white_dn}")
        if self.read_noise_dn < 0 or self.electrons_per_dn < 0:
            raise ConfigError("handheld camera: read_noise_dn and electrons_per_dn must be >= 0")


def _finish(signal: np.ndarray, black_dn: float, read_noise_dn: float, electrons_per_dn: float,
            rng: np.random.Generator | None, gain: float = 1.0) -> np.ndarray:
    """Sensor noise (read x gain, shot), rounding and clipping of a linear signal (DN)."""
    dn = signal.astype(np.float64)
    if rng is not None and (read_noise_dn > 0 or electrons_per_dn > 0):
        var = (read_noise_dn * gain) ** 2 + (np.maximum(dn - black_dn, 0.0) * gain / electrons_per_dn
                                             if electrons_per_dn > 0 else 0.0)
        dn = dn + rng.standard_normal(dn.shape) * np.sqrt(var)
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


class _View:
    """One traced pose: per sub-ray what it hits, the display pixel or the board's reflectance."""

    def __init__(self, shape: tuple[int, int], subs: int, kind: np.ndarray, index: np.ndarray, refl: np.ndarray):
        self.shape, self.subs = shape, subs
        self.kind = kind
        self.display = np.flatnonzero(kind == _DISPLAY)
        self.display_index = index[self.display]
        self.static = None                 # the light of everything but the display (set by the scene)
        self.refl = refl

    def display_light(self, luminance: np.ndarray) -> np.ndarray:
        """Mean display luminance over each pixel's sub-rays (0 for sub-rays not on the display)."""
        acc = np.zeros(self.kind.size, dtype=np.float32)
        acc[self.display] = luminance.ravel()[self.display_index]
        return acc.reshape(-1, self.subs).mean(axis=1).reshape(self.shape)


class ScreenScene:
    """The true panel and a scale board beside it, seen by a handheld camera (``calibrate screen``).

    Parameters
    ----------
    screen : TrueScreen
        The panel as it really is.
    camera : HandheldCamera
        The second camera.
    board : PlanarTarget, optional
        The certified flat scale board (OpenCV's board frame: origin at the top-left of the pattern, x
        along its columns, y down its rows, z into the board).
    board_to_screen : Pose, optional
        Where the board is fixed, in the screen frame.
    display_gamma, display_floor : float
        The display's response (as :class:`~sofast_station.twin.parameters.TwinOptics`).
    bezel_m : float
        Width of the dark bezel around the active area, metres.
    supersample : int
        Sub-rays per pixel edge (``supersample**2`` per pixel).
    """

    def __init__(self, screen: TrueScreen, camera: HandheldCamera, board: PlanarTarget | None = None,
                 board_to_screen: Pose | None = None, display_gamma: float = 2.2, display_floor: float = 0.02,
                 bezel_m: float = 0.015, supersample: int = 3):
        if (board is None) != (board_to_screen is None):
            raise ConfigError("a scale board needs its pose (board_to_screen), and a pose a board")
        self.screen, self.camera_spec = screen, camera
        self.board, self.board_to_screen = board, board_to_screen
        self.bezel_m = float(bezel_m)
        self._twin_camera = TwinCamera(camera.intrinsics)
        self._rays, self._subs = _sub_rays(self._twin_camera, supersample)
        self._lut = _luminance_table(display_gamma, display_floor)
        self._view: _View | None = None
        self.screen_to_camera: Pose | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.camera_spec.intrinsics.shape

    def move(self, screen_to_camera: Pose) -> None:
        """Put the handheld camera at a pose (the screen frame in its frame) and trace what it sees."""
        to_screen = screen_to_camera.inverse()
        origin = np.broadcast_to(to_screen.translation, self._rays.shape)
        dirs = _apply(to_screen, self._rays, translate=False)
        t_disp, kind, index = _display_hits(self.screen, self.screen.stated, origin, dirs, self.bezel_m)
        refl = np.zeros(kind.size, dtype=np.float32)
        if self.board is not None:
            t_board, board_refl, _ = _board_hits(self.board, self.board_to_screen, origin, dirs)
            nearer = t_board < t_disp
            kind[nearer] = _BOARD
            refl[nearer] = board_refl[nearer]
        if not np.any(kind == _DISPLAY):
            raise GeometryError("the handheld camera does not see the screen from this pose")
        view = _View(self.shape, self._subs, kind, index, refl)
        spec = self.camera_spec
        static = np.select([kind == _BOARD, kind == _BEZEL, kind == _NOTHING],
                           [spec.black_dn + (spec.board_white_dn - spec.black_dn) * refl,
                            np.full(kind.size, spec.bezel_dn), np.full(kind.size, spec.background_dn)], 0.0)
        view.static = static.reshape(-1, self._subs).mean(axis=1).reshape(self.shape).astype(np.float32)
        self._view = view
        self.screen_to_camera = screen_to_camera

    def capture(self, display_image: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The handheld camera's frame while the display shows *display_image* (uint8 commands)."""
        if self._view is None:
            raise GeometryError("the handheld camera has no pose yet (move it first)")
        stated = self.screen.stated
        image = np.asarray(display_image)
        if image.dtype != np.uint8 or image.shape != (stated.height_px, stated.width_px):
            raise GeometryError(f"display image must be uint8 of shape {(stated.height_px, stated.width_px)}")
        spec = self.camera_spec
        on_display = self._view.display_light(self._lut[image])
        signal = self._view.static + (spec.white_dn - spec.black_dn) * on_display
        return _finish(signal, spec.black_dn, spec.read_noise_dn, spec.electrons_per_dn, rng)

    def coverage_of_display(self) -> float:
        """Fraction of the camera's pixels whose sub-rays all land on the display's active area."""
        if self._view is None:
            return 0.0
        return float(np.mean(np.all((self._view.kind == _DISPLAY).reshape(-1, self._subs), axis=1)))


def handheld_poses(n: int, rng: np.random.Generator, look_at_m=(0.0, 0.0, 0.0), distance_m=(0.85, 1.1),
                   tilt_deg=(15.0, 35.0), roll_deg: float = 8.0) -> list[Pose]:
    """Poses of a handheld camera around a screen: *n* views from directions spread in azimuth.

    View k looks at *look_at_m* (screen frame) from *distance_m* away (uniform in the range), from a
    direction tilted from the screen's normal by an angle in *tilt_deg* toward azimuth 2 pi k / n (plus
    up to a third of a step at random), turned about its axis by up to +-*roll_deg*, upright otherwise
    (image up along the screen's +y).

    Returns
    -------
    list of Pose
        ``screen_to_camera`` of each view.
    """
    if int(n) < 1:
        raise ConfigError(f"need at least one view, got {n}")
    target = np.asarray(look_at_m, dtype=np.float64)
    poses = []
    for k in range(int(n)):
        azimuth = 2.0 * math.pi * (k + rng.uniform(-1.0 / 3.0, 1.0 / 3.0)) / n
        tilt = math.radians(rng.uniform(*tilt_deg))
        dist = rng.uniform(*distance_m)
        direction = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth), math.cos(tilt)])
        centre = target + dist * direction
        z_cam = (target - centre) / dist
        up = np.array([0.0, 1.0, 0.0])
        y_cam = -(up - (up @ z_cam) * z_cam)
        y_cam /= np.linalg.norm(y_cam)
        x_cam = np.cross(y_cam, z_cam)
        roll = math.radians(rng.uniform(-roll_deg, roll_deg))
        x_r = math.cos(roll) * x_cam + math.sin(roll) * y_cam
        y_r = -math.sin(roll) * x_cam + math.cos(roll) * y_cam
        rot = np.vstack([x_r, y_r, z_cam])                # rows: camera axes in the screen frame
        poses.append(Pose(rot, -rot @ centre))
    return poses


class MirrorScene:
    """The station camera looking at a flat reference mirror in the fixture (``calibrate pose``).

    The mirror's reflecting surface is the plane of its printed frame (the target): rays that land in the
    target's *window* are reflected and meet the true panel; the others see the printed frame, lit by the
    room, or the room behind. The scene answers :meth:`capture` like
    :class:`~sofast_station.twin.station.TwinStation`, so the simulated camera grabs through it.

    Parameters
    ----------
    geometry : StationGeometry
        The station as it really is (:func:`~sofast_station.twin.assembly.true_geometry`): camera,
        stated screen, true screen and fixture poses.
    screen : TrueScreen
        The panel as it really is.
    target : PlanarTarget
        The printed frame (OpenCV's board frame: z into the board, so the mirror faces -z).
    window_m : (x0, y0, x1, y1)
        The mirror's opening in the target frame, metres.
    target_to_fixture : Pose
        Where the target sits in the fixture frame.
    optics : TwinOptics
        The station's sensor and display (offset, white level at the reference exposure, noise, gamma,
        flicker); the mirror reflects as the facet does (``optics.reflectance``).
    target_white_dn : float
        DN of a white square of the printed frame in the room's light, black level included, at the
        reference exposure and gain 1.
    supersample : int
        Sub-rays per pixel edge.
    measure_point_m : (x, y), optional
        The range finder's point on the target, target frame, metres (:meth:`measured_distance_m`).
    rays : (rays, count), optional
        The camera's sub-rays (:func:`sub_rays`), when several placements share them.
    """

    def __init__(self, geometry, screen: TrueScreen, target: PlanarTarget, window_m, target_to_fixture: Pose,
                 optics: TwinOptics = TwinOptics(), target_white_dn: float = 150.0, background_dn: float = 10.0,
                 supersample: int = 3, bezel_m: float = 0.015, measure_point_m=None, rays=None):
        self.geometry, self.screen, self.optics = geometry, screen, optics
        self.target, self.target_to_fixture = target, target_to_fixture
        self.measure_point_m = measure_point_m
        x0, y0, x1, y1 = (float(v) for v in window_m)
        if not (x1 > x0 and y1 > y0):
            raise ConfigError(f"mirror window must be (x0, y0, x1, y1) with x1 > x0 and y1 > y0, got {window_m}")
        self.window_m = (x0, y0, x1, y1)
        rays, subs = rays if rays is not None else sub_rays(geometry.camera, supersample)
        target_to_camera = geometry.fixture_to_camera.compose(target_to_fixture)
        origin = np.zeros_like(rays)
        t_board, refl, xy = _board_hits(target, target_to_camera, origin, rays)
        # the window: the same plane, a mirror instead of print
        to_target = target_to_camera.inverse()
        o_t = _apply(to_target, origin)
        d_t = _apply(to_target, rays, translate=False)
        with np.errstate(invalid="ignore", divide="ignore"):
            t_plane = -o_t[:, 2] / d_t[:, 2]
            hit_t = o_t + t_plane[:, None] * d_t
            in_window = np.isfinite(t_plane) & (t_plane > 0) & (hit_t[:, 0] >= x0) & (hit_t[:, 0] < x1) \
                & (hit_t[:, 1] >= y0) & (hit_t[:, 1] < y1)
        kind = np.full(rays.shape[0], _NOTHING, dtype=np.uint8)
        kind[np.isfinite(t_board)] = _BOARD
        kind[in_window] = _NOTHING                       # the mirror, unless it shows the display (below)
        # reflect in the target plane (its normal is its z axis) and go on to the panel
        normal_t = np.array([0.0, 0.0, 1.0])
        d_ref_t = d_t - 2.0 * (d_t @ normal_t)[:, None] * normal_t
        target_to_screen = geometry.screen_to_camera.inverse().compose(target_to_camera)
        idx = np.flatnonzero(in_window)
        _, k_disp, index = _display_hits(screen, geometry.screen, _apply(target_to_screen, hit_t[idx]),
                                         _apply(target_to_screen, d_ref_t[idx], translate=False), bezel_m)
        kind[idx] = np.where(k_disp == _DISPLAY, _DISPLAY, np.where(k_disp == _BEZEL, _BEZEL, _NOTHING))
        full_index = np.zeros(rays.shape[0], dtype=np.int64)
        full_index[idx] = index
        refl = np.where(kind == _BOARD, refl, 0.0).astype(np.float32)
        self._view = _View(geometry.camera.shape, subs, kind, full_index, refl)
        off = optics.camera_offset_dn
        static = np.select([kind == _BOARD, kind == _NOTHING, kind == _BEZEL],
                           [(target_white_dn - off) * refl, np.full(kind.size, background_dn - off),
                            np.zeros(kind.size)], 0.0)
        self._static = static.reshape(-1, subs).mean(axis=1).reshape(geometry.camera.shape).astype(np.float32)
        self._lut = _luminance_table(optics.display_gamma, optics.display_floor)
        self._white_above_offset = (optics.white_dn - off) * optics.reflectance / (optics.reflectance + optics.ambient)

    def measured_distance_m(self) -> float:
        """Distance (m) from the true screen centre to the target's measure point (the range finder's)."""
        if self.measure_point_m is None:
            raise GeometryError("the mirror scene has no measure point for the range finder")
        point = np.array([self.measure_point_m[0], self.measure_point_m[1], 0.0])
        target_to_camera = self.geometry.fixture_to_camera.compose(self.target_to_fixture)
        return float(np.linalg.norm(target_to_camera.apply(point) - self.geometry.screen_to_camera.translation))

    def mirror_pixels(self) -> np.ndarray:
        """(H, W) bool: pixels all of whose sub-rays see the display through the mirror."""
        v = self._view
        return np.all((v.kind == _DISPLAY).reshape(-1, v.subs), axis=1).reshape(v.shape)

    def sensor_scale(self, exposure_s: float | None = None, gain: float | None = None) -> float:
        """The sensor's exposure x gain, as the twin station's sensor forms it (:func:`~sofast_station.twin.sensor.
        exposure_scale`)."""
        return sensor.exposure_scale(self.optics, exposure_s, gain)

    def flicker_factor(self, exposure_s: float | None = None, phase: float | None = None) -> float:
        """The display's flicker over an exposure, as the twin station's sensor sees it
        (:func:`~sofast_station.twin.sensor.flicker_factor`)."""
        return sensor.flicker_factor(self.optics, exposure_s, phase)

    def capture(self, display_image: np.ndarray, rng: np.random.Generator | None = None, *,
                exposure_s: float | None = None, gain: float | None = None, flicker_phase: float | None = None,
                ambient_z: float | None = None) -> np.ndarray:
        """The station camera's frame while the display shows *display_image* (uint8 commands)."""
        stated = self.geometry.screen
        image = np.asarray(display_image)
        if image.dtype != np.uint8 or image.shape != (stated.height_px, stated.width_px):
            raise GeometryError(f"display image must be uint8 of shape {(stated.height_px, stated.width_px)}")
        scale = self.sensor_scale(exposure_s, gain)
        flicker = self.flicker_factor(exposure_s, flicker_phase)
        light = self._view.display_light(self._lut[image])
        off = self.optics.camera_offset_dn
        signal = off + scale * (self._static + flicker * self._white_above_offset * light)
        return _finish(signal, off, self.optics.read_noise_dn, self.optics.electrons_per_dn, rng,
                       1.0 if gain is None else float(gain))
