"""What the budget is about: the station's inputs with their standard uncertainties (``[uncertainty]`` in
station.toml and the calibration records in force), the budget's rows, and the scalar figures that get an
expanded uncertainty (docs/uncertainty.md).

Plain records and pure functions.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ...errors import ConfigError
from ...geometry import Pose


COVERAGE_FACTOR = 2.0
MODELS = ("design", "parabola", "higher_order")
RMS_AXES = ("x", "y", "magnitude")

#: Every scalar figure that gets an uncertainty, as a path into the figures dict.
SCALAR_PATHS: tuple[tuple, ...] = (
    ("focal_length_x_m",), ("focal_length_y_m",), ("curvature_x_per_m",), ("curvature_y_per_m",),
    ("twist_mrad_per_m",), ("twist_e1_mrad_per_m",), ("twist_e2_mrad_per_m",),
    ("principal_focal_lengths_m", 0), ("principal_focal_lengths_m", 1), ("principal_curvatures_per_m", 0),
    ("principal_curvatures_per_m", 1), ("axis_angle_rad",),
    *[("slope_rms_mrad", m, a) for m in MODELS for a in RMS_AXES],
    ("boresight_mrad", "x"), ("boresight_mrad", "y"), ("optical_tilt_mrad", "x"), ("optical_tilt_mrad", "y"),
    *[("placement", "mm", i) for i in range(3)], *[("placement", "mrad", i) for i in range(3)],
)


def path_name(path: tuple) -> str:
    """``("slope_rms_mrad", "design", "x")`` -> ``"slope_rms_mrad.design.x"``."""
    return ".".join(str(p) for p in path)


def get_path(figures: dict, path: tuple):
    v = figures
    for p in path:
        if v is None:
            return None
        v = v[p]
    return None if v is None else float(v)


def _rotation(rx: float, ry: float, rz: float) -> np.ndarray:
    """R_z(rz) R_y(ry) R_x(rx), radians."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return r_z @ r_y @ r_x


def small_motion(rotation_mrad=(0.0, 0.0, 0.0), translation_mm=(0.0, 0.0, 0.0)) -> Pose:
    """A small rigid motion from rotations (mrad) and a translation (mm)."""
    return Pose(_rotation(*(1e-3 * np.asarray(rotation_mrad, float))), 1e-3 * np.asarray(translation_mm, float))


#: Fields of :class:`InputUncertainties` that come from records, not from ``[uncertainty]``.
RECORD_DERIVED_KEYS = ("response_record_rad", "pose_covariance")
#: The budget's rows of the screen's and the fixture's pose, in the order of ``pose_covariance`` (the pose
#: record's ``joint_covariance``, :data:`~sofast_station.calibrate.pose.JOINT_PARAMETERS`).
POSE_ROWS = ("screen rx", "screen ry", "screen rz", "screen tx", "screen ty", "screen tz",
             "fixture rx", "fixture ry", "fixture rz", "fixture tx", "fixture ty", "fixture tz")


def lut_phase_error_rad(lut, floor_level: float, max_level: float, samples_per_period: float) -> float:
    """Amplitude (rad) of the 4-times-phase error a four-step phase shows when full-depth fringes are drawn
    through the lookup table *lut* (command / 255 against linear response level 0..1) with whole 8-bit
    commands, on a display whose response the table inverts exactly.

    Rounding to whole commands leaves a fixed error pattern over each fringe period, the same at every
    period when a period is a whole number of display pixels; a four-step phase sees it as a phase error
    that repeats with the phase. Only its cos/sin(4 phase) part has the shape the budget's display-response
    rows carry (the rest, of higher order, is a fine ripple along the screen). The display samples each
    pixel at its centre: *samples_per_period* pixels per period, phases 2 pi (i + 1/2) / n.
    """
    lut = np.asarray(lut, dtype=np.float64)
    n = max(int(round(samples_per_period)), 8)
    phi = 2.0 * np.pi * (np.arange(n) + 0.5) / n
    grid = np.linspace(0.0, 1.0, lut.size)
    seen = []
    for k in range(4):
        level = floor_level + (max_level - floor_level) * 0.5 * (1.0 + np.cos(phi - 0.5 * np.pi * k))
        command = np.rint(255.0 * np.interp(level, grid, lut))
        seen.append(np.interp(command / 255.0, lut, grid))
    error = np.angle(np.exp(1j * (np.arctan2(seen[1] - seen[3], seen[0] - seen[2]) - phi)))
    x = np.column_stack([np.cos(4.0 * phi), np.sin(4.0 * phi), np.ones(n)])
    coef = np.linalg.lstsq(x, error, rcond=None)[0]
    return float(np.hypot(coef[0], coef[1]))


@dataclass(frozen=True)
class InputUncertainties:
    """Standard uncertainties (k = 1) of the station's inputs (``[uncertainty]`` in station.toml).

    Defaults and their justification: docs/uncertainty.md.

    Attributes
    ----------
    distance_mm : float
        Measured distance screen centre -> measure point, mm.
    camera_focal_px : float
        Each of the camera's focal lengths f_x, f_y, pixels.
    camera_principal_px : float
        Each coordinate of the principal point, pixels.
    camera_distortion : tuple of 5 floats
        k1, k2, p1, p2, k3 (dimensionless).
    screen_rotation_mrad, screen_translation_mm : tuple of 3 floats
        Camera-to-screen pose: rotations about and shifts along the screen's own x, y, z through its centre.
    screen_pitch_relative : float
        Relative pixel pitch of the display, each axis.
    response_phase_rad : float
        Phase error left by the display's linearised response (amplitude of the 4-times-phase harmonic
        a residual nonlinearity leaves in four-step phases), radians: the value the sensitivities are
        computed at and the one used when a capture gives no evidence of its own; each capture's own
        estimate replaces it (:func:`display_response_u`). 0 leaves the display response out.
    fixture_rotation_mrad, fixture_translation_mm : tuple of 3 floats
        Where the fixture (nominal facet frame) sits in the camera frame: about/along the fixture axes.
    corner_px : float
        Location noise of each found corner coordinate, pixels (random: it changes with each placement).
    response_record_rad : float or None
        Not a station.toml key: the 4-times-phase error the radiometric record in force leaves with 8-bit
        display commands (:func:`lut_phase_error_rad`), set from the record (:meth:`with_radiometric_record`);
        None when there is none.
    pose_covariance : tuple of 12 tuples of 12 floats, or None
        Not a station.toml key: the pose record's joint covariance of the screen's and the fixture's poses
        (:data:`POSE_ROWS`, mrad and mm), set from the record (:meth:`with_commission_records`); its
        correlations join the twelve rows (:func:`pose_row_covariance`). None: the rows are independent (no
        record, a record made before it was kept, or a geometry record's fixture pose in force).
    """

    distance_mm: float = 0.5
    camera_focal_px: float = 1.0
    camera_principal_px: float = 1.0
    camera_distortion: tuple = (2e-3, 1e-2, 5e-5, 5e-5, 0.0)
    screen_rotation_mrad: tuple = (0.5, 0.5, 0.5)
    screen_translation_mm: tuple = (0.5, 0.5, 0.5)
    screen_pitch_relative: float = 1e-4
    response_phase_rad: float = 0.003
    fixture_rotation_mrad: tuple = (0.5, 0.5, 0.5)
    fixture_translation_mm: tuple = (0.5, 0.5, 0.5)
    corner_px: float = 0.1
    response_record_rad: float | None = None
    pose_covariance: tuple | None = None

    def to_dict(self) -> dict:
        return {f.name: (_listed(v) if isinstance(v, tuple) else v)
                for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}

    @classmethod
    def from_table(cls, table: dict, where: str = "[uncertainty]") -> "InputUncertainties":
        """From station.toml's ``[uncertainty]`` table (every key optional), validated."""
        known = {f.name: f for f in dataclasses.fields(cls) if f.name not in RECORD_DERIVED_KEYS}
        unknown = sorted(set(table) - set(known))
        if unknown:
            raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(known))}")
        values = {}
        for key, value in table.items():
            default = getattr(cls(), key)
            n = len(default) if isinstance(default, tuple) else None
            items = value if n is not None else [value]
            if (n is not None and (not isinstance(value, (list, tuple)) or len(value) != n)) or not all(
                    isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v >= 0
                    for v in items):
                what = f"a list of {n} non-negative numbers" if n else "a non-negative number"
                raise ConfigError(f"{where} {key} must be {what} (a standard uncertainty, k = 1), got {value!r}")
            values[key] = tuple(float(v) for v in value) if n is not None else float(value)
        return cls(**values)

    @classmethod
    def from_dict(cls, d: dict) -> "InputUncertainties":
        """From :meth:`to_dict` (e.g. handed to the analysis worker): the table's keys validated as in
        :meth:`from_table`, the record-derived ones taken as they are."""
        out = cls.from_table({k: v for k, v in d.items() if k not in RECORD_DERIVED_KEYS})
        record = d.get("response_record_rad")
        if record is not None:
            out = dataclasses.replace(out, response_record_rad=float(record))
        if d.get("pose_covariance") is not None:
            out = dataclasses.replace(out, pose_covariance=_frozen_matrix(d["pose_covariance"]))
        return out

    def with_camera_record(self, record: dict | None) -> "InputUncertainties":
        """Where the camera record in force states its parameters' standard deviations (``std``: the
        record's ``std_intrinsics`` with ``fx``, ``fy``, ``cx``, ``cy``, ``distortion``), use them instead of
        the ``[uncertainty]`` values."""
        std = (record or {}).get("std") if isinstance(record, dict) else None
        if not isinstance(std, dict):
            return self
        out = self
        try:
            if "fx" in std and "fy" in std:
                out = dataclasses.replace(out, camera_focal_px=float(max(std["fx"], std["fy"])))
            if "cx" in std and "cy" in std:
                out = dataclasses.replace(out, camera_principal_px=float(max(std["cx"], std["cy"])))
            if "distortion" in std and len(std["distortion"]) == 5:
                out = dataclasses.replace(out, camera_distortion=tuple(float(v) for v in std["distortion"]))
        except (TypeError, ValueError):
            return self
        return out


    def with_radiometric_record(self, lut, floor_level: float, max_level: float,
                                samples_per_period) -> "InputUncertainties":
        """The 4-times-phase error the radiometric record's lookup table leaves with 8-bit commands
        (:func:`lut_phase_error_rad`, the largest over the finest sets' *samples_per_period*) as
        ``response_record_rad``: the part of the display response a capture's second harmonic does not
        show (:func:`display_response_u`)."""
        try:
            value = max(lut_phase_error_rad(lut, float(floor_level), float(max_level), float(n))
                        for n in samples_per_period)
        except (TypeError, ValueError):
            return self
        return dataclasses.replace(self, response_record_rad=float(value)) if np.isfinite(value) else self

    def with_commission_records(self, std: dict | None) -> "InputUncertainties":
        """Where the screen and pose records in force (``calibrate screen``, ``calibrate pose``) state the
        standard uncertainties of the camera-to-screen pose (``screen_rotation_mrad``,
        ``screen_translation_mm``), the pitch (``screen_pitch_relative``) and the fixture pose
        (``fixture_rotation_mrad``, ``fixture_translation_mm``), use them instead of the ``[uncertainty]``
        values: measured, not typed in. The pose record's joint covariance of the screen's and the fixture's
        poses (``pose_covariance``, (12, 12), mrad and mm: :data:`POSE_ROWS`), where it has one, correlates
        their rows."""
        if not isinstance(std, dict) or not std:
            return self
        out = self
        try:
            for key in ("screen_rotation_mrad", "screen_translation_mm", "fixture_rotation_mrad",
                        "fixture_translation_mm"):
                if key in std and len(std[key]) == 3:
                    out = dataclasses.replace(out, **{key: tuple(float(v) for v in std[key])})
            if "screen_pitch_relative" in std:
                out = dataclasses.replace(out, screen_pitch_relative=float(std["screen_pitch_relative"]))
            if std.get("pose_covariance") is not None:
                out = dataclasses.replace(out, pose_covariance=_frozen_matrix(std["pose_covariance"]))
        except (TypeError, ValueError):
            return self
        return out

    def with_geometry_record(self, std: dict | None) -> "InputUncertainties":
        """Where the geometry record in force (``calibrate geometry``, within tolerance, made with the
        present geometry) states what it determined (``fixture_translation_mm``, ``fixture_rotation_mrad``:
        3 standard uncertainties each; ``distance_mm``), use them: the fixture pose's replace the
        ``[uncertainty]`` values; the distance's is how well the check confirmed the range finder, which
        does not make one reading better than the instrument's own accuracy, so the larger is kept."""
        if not isinstance(std, dict) or not std:
            return self
        out = self
        try:
            for key in ("fixture_translation_mm", "fixture_rotation_mrad"):
                if key in std and len(std[key]) == 3:
                    # another measurement's fixture pose, not correlated with the pose record's screen
                    out = dataclasses.replace(out, pose_covariance=None,
                                              **{key: tuple(float(v) for v in std[key])})
            if "distance_mm" in std:
                out = dataclasses.replace(out, distance_mm=max(out.distance_mm, float(std["distance_mm"])))
        except (TypeError, ValueError):
            return self
        return out


def _listed(value):
    """A tuple (of tuples) as lists, JSON-ready."""
    return [_listed(v) if isinstance(v, tuple) else v for v in value]


def _frozen_matrix(value) -> tuple:
    """A (12, 12) covariance (mrad, mm) as a tuple of tuples (the dataclass is frozen and hashed);
    ValueError when it is not a finite symmetric one."""
    cov = np.asarray(value, dtype=np.float64)
    if cov.shape != (len(POSE_ROWS), len(POSE_ROWS)) or not np.all(np.isfinite(cov)) \
            or not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
        raise ValueError("pose_covariance must be a finite, symmetric 12 x 12 matrix")
    return tuple(tuple(float(v) for v in row) for row in cov)


def pose_row_covariance(inputs: "InputUncertainties", rows: list) -> tuple[list, np.ndarray] | None:
    """Where the budget's *rows* (:class:`Input`) hold the screen's and the fixture's pose rows and *inputs* a
    joint covariance of them: their indices in *rows* and their covariance in the rows' units (mrad, mm),
    the record's correlations at the rows' own standard uncertainties (they are the record's, so the matrix
    is the record's). None: no joint covariance, or fewer than two of those rows (independent, as before)."""
    cov = pose_covariance_mrad_mm(inputs)
    names = [r.name for r in rows]
    at = [(names.index(n), k) for k, n in enumerate(POSE_ROWS) if n in names]
    if cov is None or len(at) < 2:
        return None
    idx, k = (list(v) for v in zip(*at))
    return idx, cov[np.ix_(k, k)]


def pose_covariance_mrad_mm(inputs: "InputUncertainties") -> np.ndarray | None:
    """The (12, 12) covariance of the screen's and the fixture's pose rows (:data:`POSE_ROWS`, mrad and mm):
    the record's correlations at *inputs*' standard uncertainties (the record's own, where they are in force,
    so the record's matrix). None without a joint covariance, or where the record states a zero one."""
    if inputs.pose_covariance is None:
        return None
    cov = np.asarray(inputs.pose_covariance, dtype=np.float64)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if np.any(sd <= 0.0):
        return None
    u = np.concatenate([inputs.screen_rotation_mrad, inputs.screen_translation_mm, inputs.fixture_rotation_mrad,
                        inputs.fixture_translation_mm]).astype(np.float64)
    return cov / np.outer(sd, sd) * np.outer(u, u)


@dataclass(frozen=True)
class Input:
    """One row of the budget: a station input, its standard uncertainty and unit, and its kind."""

    name: str
    group: str
    u: float
    unit: str
    kind: str = "systematic"


def input_key(inp: Input) -> str | None:
    """The ``[uncertainty]`` key that states *inp*'s standard uncertainty (None: the capture's own)."""
    if inp.name.startswith("fixture r"):
        return "fixture_rotation_mrad"
    if inp.name.startswith("fixture t"):
        return "fixture_translation_mm"
    return {"measured distance": "distance_mm", "camera focal length": "camera_focal_px",
            "camera principal point": "camera_principal_px", "camera distortion": "camera_distortion",
            "camera-to-screen rotation": "screen_rotation_mrad",
            "camera-to-screen translation": "screen_translation_mm",
            "screen pitch": "screen_pitch_relative", "display response": "response_phase_rad",
            "corner location": "corner_px"}.get(inp.group)


def screen_shape_inputs(screen) -> list[Input]:
    """The rows of a measured screen's shape (``calibrate screen``): one per independent uncertainty field the
    screen carries (:meth:`~sofast_station.measure.screen.InterpolatedScreen.displaced`), each at one standard
    deviation; none for a flat screen."""
    return [Input(f"screen shape {k + 1}", "screen shape", 1.0, "sd") for k in range(getattr(screen, "n_modes", 0))]


def budget_inputs(inputs: InputUncertainties, n_corners: int, four_step: bool = True) -> list[Input]:
    """The systematic and corner rows of the budget for *inputs* (zero-uncertainty inputs are left out).

    *four_step* False: a capture without four-step fringe sets (a fixed pattern's one frame) has no phase,
    so no display-response or frame-to-frame brightness rows."""
    rows = [Input("distance", "measured distance", inputs.distance_mm, "mm"),
            Input("camera fx", "camera focal length", inputs.camera_focal_px, "px"),
            Input("camera fy", "camera focal length", inputs.camera_focal_px, "px"),
            Input("camera cx", "camera principal point", inputs.camera_principal_px, "px"),
            Input("camera cy", "camera principal point", inputs.camera_principal_px, "px")]
    rows += [Input(f"camera {k}", "camera distortion", u, "1")
             for k, u in zip(("k1", "k2", "p1", "p2", "k3"), inputs.camera_distortion)]
    rows += [Input(f"screen r{a}", "camera-to-screen rotation", u, "mrad")
             for a, u in zip("xyz", inputs.screen_rotation_mrad)]
    rows += [Input(f"screen t{a}", "camera-to-screen translation", u, "mm")
             for a, u in zip("xyz", inputs.screen_translation_mm)]
    rows += [Input("screen pitch x", "screen pitch", inputs.screen_pitch_relative, "1"),
             Input("screen pitch y", "screen pitch", inputs.screen_pitch_relative, "1"),
             Input("display response cos", "display response", inputs.response_phase_rad if four_step else 0.0, "rad"),
             Input("display response sin", "display response", inputs.response_phase_rad if four_step else 0.0, "rad")]
    rows += [Input(f"fixture r{a}", "fixture pose", u, "mrad") for a, u in zip("xyz", inputs.fixture_rotation_mrad)]
    rows += [Input(f"fixture t{a}", "fixture pose", u, "mm") for a, u in zip("xyz", inputs.fixture_translation_mm)]
    rows += [Input(f"corner {i} {c}", "corner location", inputs.corner_px, "px", "random")
             for i in range(n_corners) for c in "uv"]
    # Scaled per capture by the amplitude its own consistency residuals give (:func:`capture_scales`).
    rows += [Input(f"frame brightness {a} {q}", "frame-to-frame brightness", FRAME_PHASE_REF_RAD, "rad", "random")
             for a in "xy" for q in ("cos", "sin") if four_step]
    return [r for r in rows if r.u > 0]


#: Phase-error amplitude (rad) at which the frame-brightness sensitivities are computed; each capture
#: scales them by its own amplitude.
FRAME_PHASE_REF_RAD = 0.005
