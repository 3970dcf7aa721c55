"""Settings of the geometry commissioning (``[calibration.screen]``, ``[calibration.pose]``) and the reference
mirror's certificate.

::

    [calibration.screen]        # calibrate screen: the screen's shape and pitch (defaults shown)
    views = 8                   # views the technician takes with the second camera
    min_views = 4               # fewer usable views: refused
    model = "auto"              # or "flat", "distorted2d", "distorted3d"
    camera = { width_px = 640, height_px = 480, focal_length_px = 600.0, distortion = [0, 0, 0, 0, 0] }
    camera_std = { focal_px = 0.5, principal_px = 0.5, distortion = [0.002, 0.005, 1e-4, 1e-4, 0.0] }
    board = { squares = [7, 5], square_mm = 40.0, marker_mm = 29.0, dictionary = "DICT_4X4_100", first_id = 50,
              scale_u_relative = 5e-5 }
    fiducials = { squares = [12, 7], dictionary = "DICT_4X4_100" }
    max_samples = 1500          # fringe pixels per view in the fit

    [calibration.pose]          # calibrate pose: the camera against the screen (defaults shown)
    target = "fixtures/targets/reference_mirror.toml"   # the reference mirror's certificate
    placements = 6              # seated, then a shim under each edge in turn
    min_placements = 3
    max_samples = 2000          # fringe pixels per placement in the fit
    assembly_mm = 5.0           # how well the station is built to its drawing ([layout]): the screen's
    assembly_mrad = 3.0         # shifts and turns against the camera (standard uncertainties; a prior)

The handheld camera (``camera``) is the second camera's calibration (``calibrate camera --handheld``
writes a record that takes its place); ``camera_std`` its parameters' standard deviations, the priors of
the fit. The scale board is a certified flat ChArUco board fixed beside the screen; its squares set the
metric scale (``scale_u_relative``: its certificate's relative standard uncertainty).

This module imports nothing from the rest of the station but the plain data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..files import read_toml
from ..geometry import CameraIntrinsics

_MODELS = ("auto", "flat", "distorted2d", "distorted3d")


def _num(where: str, key: str, value, low: float | None = None, high: float | None = None, open_low=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f"{where} {key} must be a number, got {value!r}")
    v = float(value)
    if low is not None and (v < low or (open_low and v == low)):
        raise ConfigError(f"{where} {key} must be {'>' if open_low else '>='} {low:g}, got {v:g}")
    if high is not None and v > high:
        raise ConfigError(f"{where} {key} must be <= {high:g}, got {v:g}")
    return v


def _int(where: str, key: str, value, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"{where} {key} must be a whole number >= {low}, got {value!r}")
    return int(value)


def _pair(where: str, key: str, value, low: int) -> tuple[int, int]:
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ConfigError(f"{where} {key} must be two whole numbers [across, down], got {value!r}")
    return _int(where, key, value[0], low), _int(where, key, value[1], low)


def _keys(where: str, table, allowed: set) -> dict:
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table, got {table!r}")
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return table


@dataclass(frozen=True)
class BoardSettings:
    """A certified flat ChArUco board (the scale board beside the screen).

    Attributes
    ----------
    squares : (int, int)
    square_m, marker_m : float
    dictionary : str
    first_id : int
        Its first marker's id: the screen's fiducials use ids from 0, the board's must not overlap them.
    scale_u_relative : float
        Its certificate's relative standard uncertainty of the square size.
    """

    squares: tuple = (7, 5)
    square_m: float = 0.040
    marker_m: float = 0.029
    dictionary: str = "DICT_4X4_100"
    first_id: int = 50
    scale_u_relative: float = 5e-5

    @classmethod
    def from_table(cls, table: dict, where: str) -> "BoardSettings":
        t = _keys(where, table, {"squares", "square_mm", "marker_mm", "dictionary", "first_id", "scale_u_relative"})
        d = cls()
        square = _num(where, "square_mm", t.get("square_mm", 1e3 * d.square_m), 0.0, open_low=True) / 1e3
        marker = _num(where, "marker_mm", t.get("marker_mm", 1e3 * d.marker_m), 0.0, open_low=True) / 1e3
        if marker >= square:
            raise ConfigError(f"{where} marker_mm must be smaller than square_mm")
        return cls(_pair(where, "squares", t.get("squares", list(d.squares)), 3), square, marker,
                   str(t.get("dictionary", d.dictionary)), _int(where, "first_id", t.get("first_id", d.first_id), 0),
                   _num(where, "scale_u_relative", t.get("scale_u_relative", d.scale_u_relative), 0.0))


@dataclass(frozen=True)
class HandheldCameraSettings:
    """The second camera's calibration (as stated) and its parameters' standard deviations.

    Attributes
    ----------
    intrinsics : CameraIntrinsics or None
        None: no table; the newest ``handheld`` camera record must supply it.
    std : (9,) array
        Standard deviations of (fx, fy, cx, cy, k1, k2, p1, p2, k3): the fit's priors.
    """

    intrinsics: CameraIntrinsics | None = None
    std: tuple = (0.5, 0.5, 0.5, 0.5, 0.002, 0.005, 1e-4, 1e-4, 0.0)


@dataclass(frozen=True)
class ScreenSettings:
    """How ``calibrate screen`` runs (module docstring)."""

    views: int = 8
    min_views: int = 4
    model: str = "auto"
    camera: HandheldCameraSettings = field(default_factory=HandheldCameraSettings)
    board: BoardSettings = field(default_factory=BoardSettings)
    fiducial_squares: tuple = (12, 7)
    fiducial_dictionary: str = "DICT_4X4_100"
    max_samples: int = 1500
    min_corners: int = 12

    @classmethod
    def from_table(cls, table: dict, where: str) -> "ScreenSettings":
        t = _keys(where, table, {"views", "min_views", "model", "camera", "camera_std", "board", "fiducials",
                                 "max_samples", "min_corners"})
        d = cls()
        model = t.get("model", d.model)
        if model not in _MODELS:
            raise ConfigError(f"{where} model must be one of {', '.join(_MODELS)}, got {model!r}")
        views = _int(where, "views", t.get("views", d.views), 1)
        min_views = _int(where, "min_views", t.get("min_views", d.min_views), 3)
        camera = d.camera
        if "camera" in t:
            camera = HandheldCameraSettings(_camera_table(t["camera"], f"{where} camera"), camera.std)
        if "camera_std" in t:
            s = _keys(f"{where} camera_std", t["camera_std"], {"focal_px", "principal_px", "distortion"})
            dist = s.get("distortion", list(camera.std[4:]))
            if not isinstance(dist, (list, tuple)) or len(dist) != 5:
                raise ConfigError(f"{where} camera_std.distortion must be 5 numbers (k1, k2, p1, p2, k3)")
            focal = _num(where, "camera_std.focal_px", s.get("focal_px", camera.std[0]), 0.0)
            principal = _num(where, "camera_std.principal_px", s.get("principal_px", camera.std[2]), 0.0)
            distortion = (_num(where, "camera_std.distortion", v, 0.0) for v in dist)
            camera = HandheldCameraSettings(camera.intrinsics, (focal, focal, principal, principal, *distortion))
        board = BoardSettings.from_table(t.get("board", {}), f"{where} board")
        fid = _keys(f"{where} fiducials", t.get("fiducials", {}), {"squares", "dictionary"})
        return cls(views, min_views, model, camera, board, _pair(where, "fiducials.squares",
                                                                  fid.get("squares", list(d.fiducial_squares)), 3),
                   str(fid.get("dictionary", d.fiducial_dictionary)),
                   _int(where, "max_samples", t.get("max_samples", d.max_samples), 100),
                   _int(where, "min_corners", t.get("min_corners", d.min_corners), 6))


def _camera_table(table, where: str) -> CameraIntrinsics:
    t = _keys(where, table, {"width_px", "height_px", "focal_length_px", "principal_point_px", "distortion"})
    for key in ("width_px", "height_px", "focal_length_px"):
        if key not in t:
            raise ConfigError(f"{where} is missing {key}")
    w, h = _int(where, "width_px", t["width_px"], 1), _int(where, "height_px", t["height_px"], 1)
    f = t["focal_length_px"]
    fx, fy = (f, f) if not isinstance(f, (list, tuple)) else tuple(f)
    cx, cy = t.get("principal_point_px", [(w - 1) / 2.0, (h - 1) / 2.0])
    try:
        return CameraIntrinsics(w, h, [[float(fx), 0.0, float(cx)], [0.0, float(fy), float(cy)], [0.0, 0.0, 1.0]],
                                t.get("distortion", [0.0] * 5))
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class PoseSettings:
    """How ``calibrate pose`` runs (module docstring)."""

    target: str = "fixtures/targets/reference_mirror.toml"
    placements: int = 6
    min_placements: int = 3
    max_samples: int = 2000
    min_corners: int = 12
    min_mirror_pixels: int = 300
    assembly_mm: float = 5.0
    assembly_mrad: float = 3.0

    @classmethod
    def from_table(cls, table: dict, where: str) -> "PoseSettings":
        t = _keys(where, table, {"target", "placements", "min_placements", "max_samples", "min_corners",
                                 "min_mirror_pixels", "assembly_mm", "assembly_mrad"})
        d = cls()
        return cls(str(t.get("target", d.target)), _int(where, "placements", t.get("placements", d.placements), 1),
                   _int(where, "min_placements", t.get("min_placements", d.min_placements), 2),
                   _int(where, "max_samples", t.get("max_samples", d.max_samples), 100),
                   _int(where, "min_corners", t.get("min_corners", d.min_corners), 6),
                   _int(where, "min_mirror_pixels", t.get("min_mirror_pixels", d.min_mirror_pixels), 10),
                   _num(where, "assembly_mm", t.get("assembly_mm", d.assembly_mm), 0.0, open_low=True),
                   _num(where, "assembly_mrad", t.get("assembly_mrad", d.assembly_mrad), 0.0, open_low=True))


@dataclass(frozen=True)
class MirrorTarget:
    """The reference mirror: a front-surface flat mirror in a printed ChArUco frame (its certificate).

    The print and the mirror's reflecting surface are one plane (the frame is printed on the mirror's
    own glass, around a clear window). Target frame: OpenCV's board frame (origin at the pattern's top-left
    corner, x along its columns, y down its rows, z into the glass), metres.

    Attributes
    ----------
    name : str
    squares : (int, int)
    square_m, marker_m : float
    dictionary : str
    first_id : int
    window_squares : (x0, y0, x1, y1)
        The mirror's clear window, in squares (x1, y1 exclusive): no print there.
    border_m : float
        The white margin printed around the pattern: its outer edge, against the darker surround, gives the
        target's size (and so its distance) far better than its corners.
    scale_u_relative : float
        The print's relative standard uncertainty of scale (certificate).
    flatness_um : float
        The mirror's flatness, peak to valley, micrometres (certificate; a 1 um bow over 0.4 m is a
        focal length of 20 km: nothing the station can see).
    measure_point_m : (float, float)
        Where the range finder aims, target frame (the window's centre by default).
    seating_u_mm, seating_u_mrad : float
        How repeatably it seats on the fixture's locating pins (standard uncertainty): the fixture's pose
        is the seated target's, this much uncertain besides the fit's own.
    source : str
        The file it was read from.
    """

    name: str = "reference mirror"
    squares: tuple = (10, 7)
    square_m: float = 0.100
    marker_m: float = 0.072
    dictionary: str = "DICT_4X4_50"
    first_id: int = 0
    window_squares: tuple = (3, 2, 7, 5)
    border_m: float = 0.04
    scale_u_relative: float = 1e-5
    flatness_um: float = 1.0
    measure_point_m: tuple | None = None
    seating_u_mm: float = 0.05
    seating_u_mrad: float = 0.05
    source: str = ""

    def __post_init__(self):
        x0, y0, x1, y1 = self.window_squares
        nx, ny = self.squares
        if not (0 <= x0 < x1 <= nx and 0 <= y0 < y1 <= ny):
            raise ConfigError(f"mirror target {self.name}: window_squares {list(self.window_squares)} must lie within "
                              f"the {nx} x {ny} squares")

    @property
    def window_m(self) -> tuple[float, float, float, float]:
        """The window (x0, y0, x1, y1), target frame, metres."""
        return tuple(float(v) * self.square_m for v in self.window_squares)

    @property
    def window_centre_m(self) -> np.ndarray:
        x0, y0, x1, y1 = self.window_m
        return np.array([0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.0])

    @property
    def measure_point(self) -> np.ndarray:
        """The range finder's point, target frame (x, y), metres."""
        if self.measure_point_m is None:
            return self.window_centre_m[:2]
        return np.asarray(self.measure_point_m, dtype=np.float64)

    def to_dict(self) -> dict:
        return {"name": self.name, "squares": list(self.squares), "square_m": self.square_m, "marker_m": self.marker_m,
                "dictionary": self.dictionary, "first_id": self.first_id, "window_squares": list(self.window_squares),
                "border_m": self.border_m,
                "scale_u_relative": self.scale_u_relative, "flatness_um": self.flatness_um,
                "measure_point_m": [float(v) for v in self.measure_point], "seating_u_mm": self.seating_u_mm,
                "seating_u_mrad": self.seating_u_mrad, "source": self.source}


_TARGET_KEYS = {"name", "squares", "square_mm", "marker_mm", "dictionary", "first_id", "window_squares", "border_mm",
                "scale_u_relative", "flatness_um", "measure_point_mm", "seating_u_mm", "seating_u_mrad"}


def load_mirror_target(path: str | Path) -> MirrorTarget:
    """Read a reference mirror's certificate (a ``[mirror]`` table); ConfigError naming the file and key."""
    path = Path(path)
    table = read_toml(path, "reference mirror file").get("mirror")
    where = f"{path} [mirror]"
    if not isinstance(table, dict):
        raise ConfigError(f"reference mirror file {path} has no [mirror] table")
    t = _keys(where, table, _TARGET_KEYS)
    for key in ("squares", "square_mm", "marker_mm", "window_squares"):
        if key not in t:
            raise ConfigError(f"{where} is missing {key}")
    window = t["window_squares"]
    if not isinstance(window, (list, tuple)) or len(window) != 4:
        raise ConfigError(f"{where} window_squares must be [x0, y0, x1, y1] in squares")
    mp = t.get("measure_point_mm")
    if mp is not None and (not isinstance(mp, (list, tuple)) or len(mp) != 2):
        raise ConfigError(f"{where} measure_point_mm must be [x, y] in millimetres")
    square = _num(where, "square_mm", t["square_mm"], 0.0, open_low=True) / 1e3
    marker = _num(where, "marker_mm", t["marker_mm"], 0.0, open_low=True) / 1e3
    if marker >= square:
        raise ConfigError(f"{where} marker_mm must be smaller than square_mm")
    return MirrorTarget(
        name=str(t.get("name", path.stem)), squares=_pair(where, "squares", t["squares"], 3), square_m=square,
        marker_m=marker, dictionary=str(t.get("dictionary", "DICT_4X4_50")),
        first_id=_int(where, "first_id", t.get("first_id", 0), 0),
        window_squares=tuple(_int(where, "window_squares", v, 0) for v in window),
        border_m=_num(where, "border_mm", t.get("border_mm", 40.0), 0.0) / 1e3,
        scale_u_relative=_num(where, "scale_u_relative", t.get("scale_u_relative", 1e-5), 0.0),
        flatness_um=_num(where, "flatness_um", t.get("flatness_um", 1.0), 0.0),
        measure_point_m=None if mp is None else tuple(_num(where, "measure_point_mm", v) / 1e3 for v in mp),
        seating_u_mm=_num(where, "seating_u_mm", t.get("seating_u_mm", 0.05), 0.0),
        seating_u_mrad=_num(where, "seating_u_mrad", t.get("seating_u_mrad", 0.05), 0.0), source=str(path))


def commission_settings(raw: dict, base: Path, where: str) -> tuple[ScreenSettings, PoseSettings]:
    """The ``[calibration.screen]`` and ``[calibration.pose]`` tables of a station file (its *raw* TOML;
    *base* its folder, for the target's relative path)."""
    cal = raw.get("calibration", {})
    screen = ScreenSettings.from_table(cal.get("screen", {}), f"{where} [calibration.screen]")
    pose = PoseSettings.from_table(cal.get("pose", {}), f"{where} [calibration.pose]")
    target = Path(pose.target)
    if not target.is_absolute():
        # relative to the station file; else the shipped certificates of the project (fixtures/targets)
        shipped = Path(__file__).resolve().parents[2] / target
        target = base / target if (base / target).exists() or not shipped.exists() else shipped
    return screen, replace(pose, target=str(target))
