"""Plain data describing a station's geometry: camera intrinsics, screen, and the poses that join them.

These are records, not computations: both the measurement pipeline (as calibration) and the digital twin
(as the true geometry) read them. Frames follow OpenCSP's naming habit: ``screen_to_camera`` maps a point
given in the screen frame to the camera frame.

Frames
------
camera
    OpenCV: origin at the pinhole, +z along the optical axis, +x along image columns, +y down the rows.
screen
    Metres; origin at the centre of the active area, +x along increasing display column, +y up
    (decreasing display row), +z out of the screen toward the facet (docs/conventions.md#screen-frame).
fixture
    The nominal facet frame: where the facet frame lies when the facet sits perfectly in the fixture.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import ConfigError


def _finite_array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != shape:
        raise ConfigError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{name} contains a non-finite value ({arr.ravel().tolist()}); "
                          "recalibrate or correct the record")
    arr.setflags(write=False)
    return arr


_EYE3 = np.eye(3)
#: What ``np.allclose(r @ r.T, I, atol=1e-9)`` allows (atol + rtol |I|, rtol = 1e-5).
_ORTHONORMAL_TOL = 1e-9 + 1e-5 * _EYE3


@dataclass(frozen=True)
class Pose:
    """A rigid motion mapping points of frame *a* into frame *b*: ``x_b = rotation @ x_a + translation``.

    Parameters
    ----------
    rotation : (3, 3) array
        Proper rotation matrix.
    translation : (3,) array
        Origin of frame *a* expressed in frame *b*, metres.
    """

    rotation: np.ndarray
    translation: np.ndarray

    def __post_init__(self):
        r = _finite_array("pose rotation", self.rotation, (3, 3))
        t = _finite_array("pose translation", self.translation, (3,))
        # np.allclose(r r^T, I, atol=1e-9) and det(r) >= 0, without their calls' overhead (a pose is made
        # hundreds of times per heliostat analysis)
        (a, b, c), (d, e, f), (g, h, i) = r.tolist()
        det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
        if not bool((np.abs(r @ r.T - _EYE3) <= _ORTHONORMAL_TOL).all()) or det < 0:
            raise ConfigError("pose rotation is not a proper rotation matrix (R R^T != I or det < 0)")
        object.__setattr__(self, "rotation", r)
        object.__setattr__(self, "translation", t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map points (..., 3) from frame *a* to frame *b*."""
        return points @ self.rotation.T + self.translation

    def apply_vector(self, vectors: np.ndarray) -> np.ndarray:
        """Rotate direction vectors (..., 3) from frame *a* to frame *b* (no translation)."""
        return vectors @ self.rotation.T

    def inverse(self) -> "Pose":
        """The motion from frame *b* back to frame *a*."""
        r_t = self.rotation.T
        return Pose(r_t, -r_t @ self.translation)

    def compose(self, first: "Pose") -> "Pose":
        """The motion ``self ∘ first``: apply *first*, then *self*."""
        return Pose(self.rotation @ first.rotation, self.rotation @ first.translation + self.translation)

    def to_dict(self) -> dict:
        return {"rotation": self.rotation.tolist(), "translation": self.translation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Pose":
        return cls(np.asarray(d["rotation"], float), np.asarray(d["translation"], float))


@dataclass(frozen=True)
class CameraIntrinsics:
    """OpenCV pinhole camera with the 5-term distortion model (k1, k2, p1, p2, k3).

    Pixel (column u, row v) has its centre at image coordinates (u, v), as in OpenCV.
    """

    width_px: int
    height_px: int
    matrix: np.ndarray
    distortion: np.ndarray

    def __post_init__(self):
        if int(self.width_px) <= 0 or int(self.height_px) <= 0:
            raise ConfigError(f"camera size must be positive, got {self.width_px} x {self.height_px}")
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))
        k = _finite_array("camera matrix", self.matrix, (3, 3))
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ConfigError(f"camera focal lengths must be positive pixels, got fx={k[0, 0]}, fy={k[1, 1]}")
        object.__setattr__(self, "matrix", k)
        object.__setattr__(self, "distortion", _finite_array("camera distortion", self.distortion, (5,)))

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (rows, columns)."""
        return (self.height_px, self.width_px)

    def to_dict(self) -> dict:
        return {"width_px": self.width_px, "height_px": self.height_px, "matrix": self.matrix.tolist(),
                "distortion": self.distortion.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "CameraIntrinsics":
        return cls(d["width_px"], d["height_px"], np.asarray(d["matrix"], float),
                   np.asarray(d["distortion"], float))


@dataclass(frozen=True)
class ScreenSpec:
    """A flat display: native resolution and pixel pitch (metres per display pixel).

    ``pitch_m`` is the pitch along x (display columns); ``pitch_y_m`` the pitch along y (display rows),
    the same as ``pitch_m`` when not given (square pixels). A 0.08 % difference between the two, taken as
    square, is a 0.015 % focal-length error.
    """

    width_px: int
    height_px: int
    pitch_m: float
    pitch_y_m: float | None = None

    def __post_init__(self):
        if int(self.width_px) <= 0 or int(self.height_px) <= 0:
            raise ConfigError(f"screen size must be positive, got {self.width_px} x {self.height_px}")
        for name in ("pitch_m", "pitch_y_m"):
            value = getattr(self, name)
            if name == "pitch_y_m" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)) \
                    or not (np.isfinite(value) and 0 < value < 0.1):
                raise ConfigError(f"screen {name} must be a positive length in metres, got {value!r}")
        object.__setattr__(self, "width_px", int(self.width_px))
        object.__setattr__(self, "height_px", int(self.height_px))
        object.__setattr__(self, "pitch_m", float(self.pitch_m))
        object.__setattr__(self, "pitch_y_m", float(self.pitch_m if self.pitch_y_m is None else self.pitch_y_m))

    @property
    def pitch_x_m(self) -> float:
        """Pitch along x (display columns), metres."""
        return self.pitch_m

    @property
    def square(self) -> bool:
        return self.pitch_y_m == self.pitch_m

    @property
    def width_m(self) -> float:
        """Active width W, metres."""
        return self.width_px * self.pitch_m

    @property
    def height_m(self) -> float:
        """Active height H, metres."""
        return self.height_px * self.pitch_y_m

    def to_dict(self) -> dict:
        """``pitch_m`` for square pixels (as station.toml and dumps of schema 1 have it), else
        ``pitch_x_m`` and ``pitch_y_m``."""
        if self.square:
            return {"width_px": self.width_px, "height_px": self.height_px, "pitch_m": self.pitch_m}
        return {"width_px": self.width_px, "height_px": self.height_px, "pitch_x_m": self.pitch_m,
                "pitch_y_m": self.pitch_y_m}

    @classmethod
    def from_dict(cls, d: dict) -> "ScreenSpec":
        """From ``pitch_m`` (square) or ``pitch_x_m`` and ``pitch_y_m``."""
        if "pitch_m" in d:
            return cls(d["width_px"], d["height_px"], d["pitch_m"])
        return cls(d["width_px"], d["height_px"], d["pitch_x_m"], d["pitch_y_m"])


@dataclass(frozen=True, eq=False)
class MeasuredScreen:
    """A measured screen shape (``calibrate screen``): where, in the screen frame, each display position is.

    Nodes on a full rectangular grid over the active area; positions between them are interpolated
    linearly (:class:`~sofast_station.measure.screen.InterpolatedScreen`).

    Parameters
    ----------
    nodes_px : (M, 2) array
        Node positions in display pixels from the active area's left and bottom edges (a position of
        ``u_x`` metres at the stated pitch is ``u_x / pitch_x`` pixels: the nodes do not depend on the pitch
        station.toml states).
    nodes_screen_m : (M, 3) array
        Their screen-frame points, metres (the frame's origin the display's centre point, +z the normal there).
    modes_m : (K, M, 3) array
        The shape's independent uncertainty fields: every node's displacement at one standard deviation of
        each (what the uncertainty budget moves the shape by).
    record_id : str
        The screen record it comes from.
    """

    nodes_px: np.ndarray
    nodes_screen_m: np.ndarray
    modes_m: np.ndarray
    record_id: str = ""

    def __post_init__(self):
        uv = _finite_array("measured screen nodes_px", self.nodes_px, np.shape(self.nodes_px))
        pts = _finite_array("measured screen nodes_screen_m", self.nodes_screen_m, np.shape(self.nodes_screen_m))
        if uv.ndim != 2 or uv.shape[1] != 2 or uv.shape[0] < 4 or pts.shape != (uv.shape[0], 3):
            raise ConfigError(f"a measured screen needs (M, 2) node positions and (M, 3) points, got {uv.shape} and "
                              f"{pts.shape}")
        modes = np.asarray(self.modes_m, dtype=np.float64).reshape(-1, uv.shape[0], 3)
        modes = _finite_array("measured screen modes_m", modes, modes.shape)
        object.__setattr__(self, "nodes_px", uv)
        object.__setattr__(self, "nodes_screen_m", pts)
        object.__setattr__(self, "modes_m", modes)
        object.__setattr__(self, "record_id", str(self.record_id))

    def __eq__(self, other) -> bool:
        return (isinstance(other, MeasuredScreen) and self.record_id == other.record_id
                and all(np.array_equal(getattr(self, k), getattr(other, k))
                        for k in ("nodes_px", "nodes_screen_m", "modes_m")))

    __hash__ = None

    def to_dict(self) -> dict:
        return {"nodes_px": self.nodes_px.tolist(), "nodes_screen_m": self.nodes_screen_m.tolist(),
                "modes_m": self.modes_m.tolist(), "record_id": self.record_id}

    @classmethod
    def from_dict(cls, d: dict) -> "MeasuredScreen":
        return cls(np.asarray(d["nodes_px"], float), np.asarray(d["nodes_screen_m"], float),
                   np.asarray(d.get("modes_m", []), float), d.get("record_id", ""))


@dataclass(frozen=True)
class StationGeometry:
    """Everything geometric the analysis needs besides the facet design.

    ``screen_to_camera`` is the fixed camera/screen assembly; ``fixture_to_camera`` is where the facet
    frame sits when the facet is perfectly placed (used to order the detected corners and to start the
    pose search). ``measured_screen`` is the screen's measured shape when a screen record is in force (a
    flat screen of the stated pitch otherwise).
    """

    camera: CameraIntrinsics
    screen: ScreenSpec
    screen_to_camera: Pose
    fixture_to_camera: Pose
    measured_screen: MeasuredScreen | None = None

    def to_dict(self) -> dict:
        out = {"camera": self.camera.to_dict(), "screen": self.screen.to_dict(),
               "screen_to_camera": self.screen_to_camera.to_dict(),
               "fixture_to_camera": self.fixture_to_camera.to_dict()}
        if self.measured_screen is not None:
            out["measured_screen"] = self.measured_screen.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "StationGeometry":
        measured = d.get("measured_screen")
        return cls(CameraIntrinsics.from_dict(d["camera"]), ScreenSpec.from_dict(d["screen"]),
                   Pose.from_dict(d["screen_to_camera"]), Pose.from_dict(d["fixture_to_camera"]),
                   None if measured is None else MeasuredScreen.from_dict(measured))


@dataclass(frozen=True, eq=False)
class FixtureMarks:
    """Fixed marks on the fixture's frame beside the facet: white discs the camera sees in every frame
    (``[marks]`` in station.toml; docs/reliability.md#the-station-checks-itself).

    Plain data: the station locates them in each cycle's white frame against their commissioned image
    positions (a moved camera moves them all), and the digital twin draws them where they are.

    Parameters
    ----------
    centres_m : (N, 3) array
        Each disc's centre in the fixture frame (the nominal facet frame), metres.
    diameter_m : float
        The discs' diameter, metres. Each disc lies in the plane through its centre normal to the fixture
        frame's z axis (facing the camera and screen, as the facet does).
    """

    centres_m: np.ndarray
    diameter_m: float

    def __post_init__(self):
        centres = np.array(self.centres_m, dtype=np.float64)
        if centres.ndim != 2 or centres.shape[1] != 3 or len(centres) < 3:
            raise ConfigError(f"fixture marks need at least 3 centres of 3 coordinates, got shape {centres.shape}")
        centres = _finite_array("fixture mark centres", centres, centres.shape)
        if not (np.isfinite(self.diameter_m) and 0 < float(self.diameter_m) < 1.0):
            raise ConfigError(f"fixture mark diameter must be a positive length below 1 m, got {self.diameter_m!r}")
        object.__setattr__(self, "centres_m", centres)
        object.__setattr__(self, "diameter_m", float(self.diameter_m))

    def __len__(self) -> int:
        return len(self.centres_m)

    def to_dict(self) -> dict:
        return {"centres_m": self.centres_m.tolist(), "diameter_m": self.diameter_m}

    @classmethod
    def from_dict(cls, d: dict) -> "FixtureMarks":
        return cls(np.asarray(d["centres_m"], float), float(d["diameter_m"]))
