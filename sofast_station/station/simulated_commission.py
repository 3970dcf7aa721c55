"""The simulated station's commissioning: the twin's second camera around the screen (``calibrate screen``)
and the reference mirror in the twin's fixture (``calibrate pose``).

What is true here is the twin's (:mod:`sofast_station.twin.commissioning`): the screen as it really is, the
camera where it really is, the scale board where it is fixed, the mirror where the shims tilt it. The
calibration routines see none of it: they get frames through the Camera protocol and ask for views and
placements through ``place(k, n, hint)``, as on a real station.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import ConfigError
from ..geometry import Pose
from ..layout import mirror_seat
from ..measure.fiducials import CharucoLayout
from ..twin.assembly import TrueScreen
from ..twin.board import PlanarTarget
from ..twin.commissioning import HandheldCamera, MirrorScene, ScreenScene, handheld_poses, sub_rays
from ..twin.station import rotation_zyx

log = logging.getLogger(__name__)

#: Where the scale board is fixed: beside the screen's right edge, this far from the active area (m), a
#: little in front of the panel and turned (the technician clamps it to the bezel, not to a machinist's
#: tolerance).
BOARD_GAP_M = 0.035
BOARD_OFFSET_Z_M = 0.003
BOARD_TURN_RAD = (0.004, -0.012, 0.006)
#: Sub-rays per pixel edge of the second camera's frames.
SUPERSAMPLE = 2
#: The shims' tilt of the reference mirror, rad, and the random part of every placement (rad).
SHIM_TILT_RAD = 0.003
PLACEMENT_JITTER_RAD = 0.0005


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    return rotation_zyx(rx, ry, rz)


def _true_screen(twin):
    return twin.screen_shape if twin.screen_shape is not None else TrueScreen(twin.geometry.screen)


class SimulatedHandheld:
    """The twin's second camera: a Camera (``grab`` sees the display's image on the true screen) and
    ``place(k, n, hint)``, which moves it to view k.

    Parameters
    ----------
    station : SimulatedStation
    settings : ScreenSettings
        The routine's settings: the camera's stated calibration is the physical camera here (as the [camera]
        table is the station camera's), the scale board and the number of views.
    seed : int, optional
        Seed of the views' poses and the camera's noise (the station's simulation seed by default).
    """

    def __init__(self, station, settings, seed: int | None = None):
        intrinsics = settings.camera.intrinsics
        if intrinsics is None:
            raise ConfigError("the simulated station's second camera is [calibration.screen] camera: give its "
                              "width_px, height_px and focal_length_px")
        twin = station.twin
        self.station = station
        seed = station.config.simulation.get("seed", 0) if seed is None else seed
        rng = np.random.default_rng([int(seed), 0x5C2E])
        self._noise = np.random.default_rng([int(seed), 0x5C2F]) if station.camera.rng is not None else None
        b = settings.board
        layout = CharucoLayout(b.squares[0], b.squares[1], b.square_m, b.marker_m, b.dictionary, b.first_id)
        board = PlanarTarget(layout.image(40).astype(np.float64) / 255.0, b.squares[0] * b.square_m,
                             b.squares[1] * b.square_m, 0.01, 1.0)
        screen = _true_screen(twin)
        # the board's frame: x along the screen's x, y down (-y), z into the board (-z); top-left corner beside
        # the active area's right edge, the board's middle at the screen's height
        turn = _rotation(*BOARD_TURN_RAD) @ np.diag([1.0, -1.0, -1.0])
        corner = np.array([0.5 * screen.width_m + BOARD_GAP_M, 0.5 * board.height_m, BOARD_OFFSET_Z_M])
        self.board_to_screen = Pose(turn, corner)
        # 2 x 2 sub-rays per pixel, on lattices shifted pixel by pixel: the fiducials' corners come out as
        # sharp as with 3 x 3 (0.07 px against the twin's truth), at half the trace
        self.scene = ScreenScene(screen, HandheldCamera(intrinsics), board, self.board_to_screen,
                                 display_gamma=twin.optics.display_gamma, display_floor=twin.optics.display_floor,
                                 supersample=SUPERSAMPLE)
        look_at = (0.5 * (BOARD_GAP_M + board.width_m), 0.0, 0.0)
        self.poses = handheld_poses(settings.views, rng, look_at_m=look_at, distance_m=(0.8, 0.95))
        self.shape = intrinsics.shape

    def place(self, k: int, n: int, hint: str) -> None:
        log.info("simulated second camera: view %d of %d (%s)", k + 1, n, hint)
        self.scene.move(self.poses[k % len(self.poses)])

    def set_exposure(self, seconds: float) -> None:
        pass

    def set_gain(self, gain: float) -> None:
        pass

    def grab(self, timeout_s: float = 2.0) -> np.ndarray:
        display = self.station.display
        frame = self.scene.capture(display.image, self._noise)
        display.advance(1.0 / self.station.twin.optics.refresh_hz)
        return frame

    def close(self) -> None:
        pass


class SimulatedMirror:
    """The reference mirror in the twin's fixture: ``place(k, n, hint)`` seats it (k = 0) or tilts it with a
    shim (k > 0), and the station's camera and range finder then see it; ``restore()`` puts the facet back.

    Parameters
    ----------
    station : SimulatedStation
    target : MirrorTarget
        The mirror's certificate (its print; the seat puts its window's centre on the facet's middle).
    seed : int, optional
        Seed of the placements' random part (the simulation seed by default).
    """

    def __init__(self, station, target, seed: int | None = None):
        self.station = station
        self.target = target
        seed = station.config.simulation.get("seed", 0) if seed is None else seed
        self._rng = np.random.default_rng([int(seed), 0x3A1B])
        layout = CharucoLayout(target.squares[0], target.squares[1], target.square_m, target.marker_m,
                               target.dictionary, target.first_id)
        self.print = PlanarTarget(layout.image(40).astype(np.float64) / 255.0, target.squares[0] * target.square_m,
                                  target.squares[1] * target.square_m, target.border_m, 1.0)
        self.seat = mirror_seat(station.config.design, target.window_centre_m)
        self.scene = None
        self.placements: list[Pose] = []
        self.supersample = 3
        self._rays = None

    def placement(self, k: int) -> Pose:
        """The true ``target_to_fixture`` of placement k: the seat, tilted about the window's centre by the
        shim under edge k (none for k = 0), plus a little of the placing's randomness."""
        tilt = np.zeros(3)
        jitter = self._rng.normal(0.0, PLACEMENT_JITTER_RAD, 2)
        if k > 0:
            axis, sign = [(1, -1.0), (0, 1.0), (1, 1.0), (0, -1.0)][(k - 1) % 4]
            tilt[axis] = sign * SHIM_TILT_RAD
            # a shim never lifts an edge by exactly its nominal height: the tilted placements' own randomness
            tilt[:2] += jitter
        # Seated, the mirror sits as its certificate says its seat repeats (seating_u_*), no worse: the pose
        # calibration takes that placement as the fixture's pose and carries the certificate's repeatability.
        # (Until 2026-12-05 the seated placement also drew the shims' 0.5 mrad per axis, ten times the
        # certificate's 0.05 mrad: the commissioned fixture was off by that much, outside its stated
        # uncertainty, and so was every optical tilt measured with it: 0.73 +- 0.21 mrad against the
        # twin's -0.007 on the shipped station, issue 47.)
        seat_err = np.concatenate([self._rng.normal(0.0, 1e-3 * self.target.seating_u_mrad, 3),
                                   self._rng.normal(0.0, 1e-3 * self.target.seating_u_mm, 3)])
        r = _rotation(*(tilt + seat_err[:3]))
        c = self.target.window_centre_m
        return self.seat.compose(Pose(r, c - r @ c + seat_err[3:]))

    def place(self, k: int, n: int, hint: str) -> None:
        log.info("simulated reference mirror: placement %d of %d (%s)", k + 1, n, hint)
        twin = self.station.twin
        pose = self.placement(k)
        self.placements.append(pose)
        if self._rays is None:
            self._rays = sub_rays(twin.geometry.camera, self.supersample)
        self.scene = MirrorScene(twin.geometry, _true_screen(twin), self.print, self.target.window_m, pose,
                                 twin.optics, measure_point_m=self.target.measure_point,
                                 supersample=self.supersample, rays=self._rays)
        self.station.camera.twin = self.scene
        self.station.range_finder.twin = self.scene

    def restore(self) -> None:
        """The facet back in the fixture."""
        self.station.camera.twin = self.station.twin
        self.station.range_finder.twin = self.station.twin
