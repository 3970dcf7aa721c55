"""The real camera/screen assembly: how it differs from the designed one that station.toml describes.

A real LCD bows by a fraction of a millimetre, its pixel pitch may be other than the data sheet says, and a
real station is assembled to a few millimetres. :class:`TrueAssembly` states those differences;
:class:`TrueScreen` is the screen they make (its true shape and pitch, and where a ray meets it), and
:func:`true_geometry` the station geometry with the camera where it really is.

Screen frame (docs/conventions.md#screen-frame), made precise for a screen that is not flat: the origin is
the display's centre point on the panel, +z the panel's normal there (toward the facet), +x along the
display row through the centre, +y up. In this frame the true panel is ::

    x = u_x p_x / p_x0 - W_true / 2,   y = u_y p_y / p_y0 - H_true / 2
    z = sag (cos(pi xi / 2) cos(pi eta / 2) - 1) + twist xi eta,    xi = 2 x / W_true,  eta = 2 y / H_true

with (u_x, u_y) the display position counted in the stated pitch (p_x0, p_y0) as the fringes encode it,
(p_x, p_y) the true pitch and W_true, H_true the true active extents: the centre stands ``sag`` in front of
the plane of the edges, the corners are turned ``+-twist`` out of it. (A bowed panel's pixels keep their
arc length; the difference from the projection used here is second order, a few micrometres.)

Written from the definitions above; nothing is shared with :mod:`sofast_station.measure`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, GeometryError
from ..geometry import Pose, ScreenSpec, StationGeometry
from .parameters import _check_keys, _number, _vector

#: Newton's method on the panel stops when the height residual is below this, metres (a ray grazing the
#: panel at 10 mrad is then off along it by a micrometre at most).
TRACE_TOLERANCE_M = 1e-11


@dataclass(frozen=True)
class TrueAssembly:
    """The true camera/screen assembly, as differences from the designed one.

    Parameters
    ----------
    screen_sag_mm : float
        How far the panel's centre stands in front of (toward the facet, +z) the plane of its edges, mm
        (negative: behind). A real LCD: 0.1 to 1 mm.
    screen_twist_mm : float
        The panel's twist: its corners turned ``+-twist`` out of the plane (+ at the top right and bottom
        left corners), mm.
    screen_pitch_scale : (float, float)
        True pixel pitch over the stated one, along the display's columns (x) and rows (y): 1.01 is a
        pitch 1 % larger than station.toml says.
    camera_shift_mm : (float, float, float)
        Where the camera's centre really is, relative to where the design puts it, in the designed camera
        frame (OpenCV axes: x right, y down, z along the optical axis), mm.
    camera_turn_mrad : (float, float, float)
        The camera's true orientation relative to the designed one: R = R_z(rz) R_y(ry) R_x(rx) about the
        designed camera's axes, mrad.
    """

    screen_sag_mm: float = 0.0
    screen_twist_mm: float = 0.0
    screen_pitch_scale: tuple[float, float] = (1.0, 1.0)
    camera_shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    camera_turn_mrad: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        owner = "TrueAssembly"
        for key in ("screen_sag_mm", "screen_twist_mm"):
            value = _number(owner, key, getattr(self, key))
            if abs(value) > 20.0:
                raise ConfigError(f"{owner}.{key} must lie within +-20 mm (a panel, not a dish), got {value}")
            object.__setattr__(self, key, value)
        scale = _vector(owner, "screen_pitch_scale", self.screen_pitch_scale, 2)
        if not all(0.5 < s < 2.0 for s in scale):
            raise ConfigError(f"{owner}.screen_pitch_scale must lie in (0.5, 2) (true over stated pitch), got {scale}")
        object.__setattr__(self, "screen_pitch_scale", scale)
        shift = _vector(owner, "camera_shift_mm", self.camera_shift_mm, 3)
        turn = _vector(owner, "camera_turn_mrad", self.camera_turn_mrad, 3)
        if max(abs(v) for v in shift) > 200.0 or max(abs(v) for v in turn) > 100.0:
            raise ConfigError(f"{owner}: camera_shift_mm must lie within +-200 mm and camera_turn_mrad within "
                              f"+-100 mrad (a misplaced camera, not another station), got {shift}, {turn}")
        object.__setattr__(self, "camera_shift_mm", shift)
        object.__setattr__(self, "camera_turn_mrad", turn)

    @property
    def ideal(self) -> bool:
        """True when the assembly is exactly the designed one (a flat screen of the stated pitch)."""
        return (self.screen_sag_mm == 0.0 and self.screen_twist_mm == 0.0 and self.screen_pitch_scale == (1.0, 1.0)
                and self.camera_shift_mm == (0.0, 0.0, 0.0) and self.camera_turn_mrad == (0.0, 0.0, 0.0))

    @property
    def screen_is_ideal(self) -> bool:
        """True when the screen is flat and of the stated pitch."""
        return self.screen_sag_mm == 0.0 and self.screen_twist_mm == 0.0 and self.screen_pitch_scale == (1.0, 1.0)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "TrueAssembly":
        """Build from plain data (``[simulation.assembly]``); unknown keys raise ConfigError naming them."""
        _check_keys("TrueAssembly", d, cls)
        return cls(**d)


def _rotation_zyx(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    r_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    r_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    r_z = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return r_z @ r_y @ r_x


def camera_error_pose(assembly: TrueAssembly) -> Pose:
    """The true camera frame in the designed one: ``x_designed_camera = R x_true_camera + t``."""
    return Pose(_rotation_zyx(*(1e-3 * np.asarray(assembly.camera_turn_mrad))),
                1e-3 * np.asarray(assembly.camera_shift_mm, dtype=np.float64))


def true_geometry(stated: StationGeometry, assembly: TrueAssembly) -> StationGeometry:
    """The station geometry with the camera where it really is.

    The screen and the fixture stay where the design puts them; the camera is moved by the assembly's
    error, so both the screen's and the fixture's poses in the camera frame change. The camera's
    intrinsics and the screen's stated size are kept (the true pitch is :class:`TrueScreen`'s).
    """
    to_true = camera_error_pose(assembly).inverse()          # designed camera frame -> true camera frame
    return dataclasses.replace(stated, screen_to_camera=to_true.compose(stated.screen_to_camera),
                               fixture_to_camera=to_true.compose(stated.fixture_to_camera))


class TrueScreen:
    """The panel as it really is: its shape, its pitch, and where a ray meets it (module docstring).

    Parameters
    ----------
    stated : ScreenSpec
        The screen as station.toml states it (size in pixels, stated pitch): the fringes encode positions
        in its units.
    assembly : TrueAssembly
        The true sag, twist and pitch.
    """

    def __init__(self, stated: ScreenSpec, assembly: TrueAssembly = TrueAssembly()):
        self.stated = stated
        self.sag_m = 1e-3 * assembly.screen_sag_mm
        self.twist_m = 1e-3 * assembly.screen_twist_mm
        self.scale_x, self.scale_y = (float(s) for s in assembly.screen_pitch_scale)
        self.pitch_x_m = stated.pitch_x_m * self.scale_x
        self.pitch_y_m = stated.pitch_y_m * self.scale_y
        self.width_m = stated.width_px * self.pitch_x_m
        self.height_m = stated.height_px * self.pitch_y_m

    @property
    def flat(self) -> bool:
        return self.sag_m == 0.0 and self.twist_m == 0.0

    def height_and_slopes(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The panel's z and its slopes dz/dx, dz/dy at in-plane points (screen frame, metres)."""
        half_w, half_h = 0.5 * self.width_m, 0.5 * self.height_m
        xi, eta = np.asarray(x_m) / half_w, np.asarray(y_m) / half_h
        a, b = 0.5 * np.pi * xi, 0.5 * np.pi * eta
        ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
        z = self.sag_m * (ca * cb - 1.0) + self.twist_m * xi * eta
        zx = (-self.sag_m * 0.5 * np.pi * sa * cb + self.twist_m * eta) / half_w
        zy = (-self.sag_m * 0.5 * np.pi * ca * sb + self.twist_m * xi) / half_h
        return z, zx, zy

    def points(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        """Screen-frame points (N, 3), metres, of display positions (u_x, u_y) counted in the stated pitch
        (metres from the active area's left and bottom edges, as the fringes encode them)."""
        x = np.asarray(u_x_m, dtype=np.float64) * self.scale_x - 0.5 * self.width_m
        y = np.asarray(u_y_m, dtype=np.float64) * self.scale_y - 0.5 * self.height_m
        z, _, _ = self.height_and_slopes(x, y)
        return np.stack([x, y, z], axis=-1)

    def positions(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Display positions (..., 2) = (u_x, u_y), stated-pitch metres, of in-plane screen-frame points."""
        u_x = (np.asarray(x_m) + 0.5 * self.width_m) / self.scale_x
        u_y = (np.asarray(y_m) + 0.5 * self.height_m) / self.scale_y
        return np.stack([u_x, u_y], axis=-1)

    def trace(self, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where rays meet the panel.

        Parameters
        ----------
        origins, directions : (N, 3) arrays
            Rays in the screen frame (metres; directions need not be unit vectors).

        Returns
        -------
        path : (N,) array
            Ray parameter t of the hit (``origin + t direction``); NaN where the ray does not reach the
            panel going forward.
        positions_m : (N, 2) array
            Display positions (u_x, u_y) of the hits, stated-pitch metres (NaN where there is none).
        """
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = -o[:, 2] / d[:, 2]
            if not self.flat:
                # Newton on f(t) = z(t) - h(x(t), y(t)): the panel departs from its tangent plane by at most
                # millimetres, so from the plane's hit it converges in a few steps.
                for _ in range(50):
                    p = o + t[:, None] * d
                    h, hx, hy = self.height_and_slopes(p[:, 0], p[:, 1])
                    f = p[:, 2] - h
                    step = f / (d[:, 2] - hx * d[:, 0] - hy * d[:, 1])
                    t = t - step
                    worst = np.nanmax(np.abs(f), initial=0.0)
                    if worst < TRACE_TOLERANCE_M:
                        break
                else:
                    raise GeometryError("rays do not converge onto the twin's bowed screen (the panel's shape "
                                        "folds over along them); use a smaller screen_sag_mm or screen_twist_mm")
        t = np.where(np.isfinite(t) & (t > 0), t, np.nan)
        hit = o + t[:, None] * d
        return t, self.positions(hit[:, 0], hit[:, 1])
