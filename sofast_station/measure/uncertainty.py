"""Expanded uncertainty (k = 2) of every reported figure, and its budget (docs/uncertainty.md).

Two parts, combined per the GUM (root sum of squares of standard-uncertainty contributions, times the
coverage factor 2):

* **random** -- what changes from capture to capture: the intensity noise measured in the capture itself,
  propagated to screen positions (:func:`~sofast_station.measure.phase.position_sigma_m`), to slopes (the
  reflection law's derivative, per pixel) and through the fits (their covariance); and the corners'
  location noise (``corner_px``) through the pose;
* **systematic** -- sensitivity of each figure to each station input (measured distance, camera
  intrinsics and distortion, camera-to-screen pose, screen pitch, display response, fixture pose), by
  finite differences of the whole reduction (:func:`~sofast_station.measure.pipeline.rerun`) at plus and
  minus one standard uncertainty: the linear part ``(f(+u) - f(-u)) / 2`` and the curvature part
  ``(f(+u) + f(-u)) / 2 - f(0)`` combine to the standard deviation ``sqrt(c^2 + 2 q^2)`` of the figure
  for a normal input (the curvature part matters for slope RMS values, which a perturbation raises
  whatever its sign).

Sensitivities depend on the station's geometry and the recipe, not on the facet: they are computed once
on a decimated copy of one reduction (:func:`sensitivities`) and reused (:func:`combine`); the caller
keeps the cache. Pure functions: numpy and records in, numpy and dicts out.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..errors import AnalysisError, ConfigError, StationError
from ..geometry import Pose
from .metrics import principal_axes
from .stats import median

COVERAGE_FACTOR = 2.0
MODELS = ("design", "parabola", "higher_order")
RMS_AXES = ("x", "y", "magnitude")

#: Every scalar figure that gets an uncertainty, as a path into the figures dict.
SCALAR_PATHS: tuple[tuple, ...] = (
    ("focal_length_x_m",), ("focal_length_y_m",), ("curvature_x_per_m",), ("curvature_y_per_m",),
    ("twist_mrad_per_m",), ("twist_e1_mrad_per_m",), ("twist_e2_mrad_per_m",),
    ("principal_focal_lengths_m", 0), ("principal_focal_lengths_m", 1), ("axis_angle_rad",),
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
_NOT_TABLE_KEYS = ("response_record_rad",)


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

    def to_dict(self) -> dict:
        return {f.name: (list(v) if isinstance(v, tuple) else v)
                for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}

    @classmethod
    def from_table(cls, table: dict, where: str = "[uncertainty]") -> "InputUncertainties":
        """From station.toml's ``[uncertainty]`` table (every key optional), validated."""
        known = {f.name: f for f in dataclasses.fields(cls) if f.name not in _NOT_TABLE_KEYS}
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
        out = cls.from_table({k: v for k, v in d.items() if k not in _NOT_TABLE_KEYS})
        record = d.get("response_record_rad")
        return out if record is None else dataclasses.replace(out, response_record_rad=float(record))

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
                    out = dataclasses.replace(out, **{key: tuple(float(v) for v in std[key])})
            if "distance_mm" in std:
                out = dataclasses.replace(out, distance_mm=max(out.distance_mm, float(std["distance_mm"])))
        except (TypeError, ValueError):
            return self
        return out


@dataclass(frozen=True)
class Input:
    """One row of the budget: a station input, its standard uncertainty and unit, and its kind."""

    name: str
    group: str
    u: float
    unit: str
    kind: str = "systematic"


def budget_inputs(inputs: InputUncertainties, n_corners: int) -> list[Input]:
    """The systematic and corner rows of the budget for *inputs* (zero-uncertainty inputs are left out)."""
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
             Input("display response cos", "display response", inputs.response_phase_rad, "rad"),
             Input("display response sin", "display response", inputs.response_phase_rad, "rad")]
    rows += [Input(f"fixture r{a}", "fixture pose", u, "mrad") for a, u in zip("xyz", inputs.fixture_rotation_mrad)]
    rows += [Input(f"fixture t{a}", "fixture pose", u, "mm") for a, u in zip("xyz", inputs.fixture_translation_mm)]
    rows += [Input(f"corner {i} {c}", "corner location", inputs.corner_px, "px", "random")
             for i in range(n_corners) for c in "uv"]
    # Scaled per capture by the amplitude its own consistency residuals give (:func:`capture_scales`).
    rows += [Input(f"frame brightness {a} {q}", "frame-to-frame brightness", FRAME_PHASE_REF_RAD, "rad", "random")
             for a in "xy" for q in ("cos", "sin")]
    return [r for r in rows if r.u > 0]


def input_key(inp: Input) -> str | None:
    """The ``[uncertainty]`` key that states *inp*'s standard uncertainty (None: the capture's own)."""
    if inp.name.startswith("fixture r"):
        return "fixture_rotation_mrad"
    if inp.name.startswith("fixture t"):
        return "fixture_translation_mm"
    return {"measured distance": "distance_mm", "camera focal length": "camera_focal_px",
            "camera principal point": "camera_principal_px", "camera distortion": "camera_distortion",
            "camera-to-screen rotation": "screen_rotation_mrad", "camera-to-screen translation": "screen_translation_mm",
            "screen pitch": "screen_pitch_relative", "display response": "response_phase_rad",
            "corner location": "corner_px"}.get(inp.group)


#: Phase-error amplitude (rad) at which the frame-brightness sensitivities are computed; each capture
#: scales them by its own amplitude.
FRAME_PHASE_REF_RAD = 0.005


def _phase_error_shift(positions: np.ndarray, length_m: float, periods: float, amplitude_rad: float,
                       harmonic: int, quadrature: str) -> np.ndarray:
    """Position error (metres) of a phase error ``amplitude * cos|sin(harmonic * phase)`` in the finest set.

    A display response that is not linear leaves a 4-times-phase harmonic in four-step phases; a brightness
    change between the frames of a set (room light, display) leaves a once-per-period one. Near the
    centre of curvature a facet's slopes map to a small stretch of the screen, where such an error acts as
    a scale on the slope deviations, so it reaches focal lengths and slope RMS values alike.
    """
    phase = 2.0 * np.pi * periods * positions / length_m
    trig = np.cos if quadrature == "cos" else np.sin
    return amplitude_rad * trig(harmonic * phase) * length_m / (2.0 * np.pi * periods)


def decimated(reduction, max_points: int = 30_000):
    """A copy of *reduction* whose phases keep every n-th valid pixel (about *max_points* of them): the
    figures' dependence on the station's inputs is smooth, so sensitivities need no more."""
    from .pipeline import Phases  # noqa: F401  (type only)
    ok = reduction.rays.ok
    kept = np.flatnonzero(ok)
    step = max(1, kept.size // max_points)
    dec_ok = np.zeros_like(ok)
    dec_ok[kept[::step]] = True
    phases = dataclasses.replace(reduction.phases, ok=reduction.phases.ok & dec_ok)
    return dataclasses.replace(reduction, phases=phases)


def robust_inliers(reduction, settings):
    """For a robust (bisquare) analysis, the reduction with only the points its fit keeps (weight above
    zero in both slope equations) and the plain fit: what :func:`sensitivities` differentiates.

    A bisquare fit's figures do not respond smoothly to its inputs: a change of a tenth of a standard
    uncertainty moves some points across the weights' edge (or the residual scale with them), and on a
    real facet with large local slope errors those jumps dominate a finite difference. On OpenCSP's
    NSTTF facet they made the frame-brightness and display-response rows of f x 60 times the plain
    fit's (U(f x) 5.5 % against 1.35 %), although the full capture's robust f x moves by 3 to 10 times
    the plain fit's for a brightness change, jump included. The estimator's smooth response is that of
    least squares on the points it keeps (the weights of the rest are zero; the inliers' weights vary
    slowly across a smooth change): that is what the sensitivities take. A plain analysis is returned
    unchanged.
    """
    if not settings.robust_fit:
        return reduction, settings
    fit = reduction.fits.parabola
    sigma = fit.sigma
    if sigma is None or not all(np.isfinite(sigma)) or min(sigma) <= 0.0:
        return reduction, dataclasses.replace(settings, robust_fit=False)
    from .fit import BISQUARE_C

    x, y = reduction.shape.points_m[0], reduction.shape.points_m[1]
    s_x, s_y = reduction.shape.slopes
    r_x = s_x - (2.0 * fit.a * x + fit.c + fit.e1 * y)
    r_y = s_y - (2.0 * fit.b * y + fit.d + fit.e2 * x)
    kept = (np.abs(r_x) < BISQUARE_C * sigma[0]) & (np.abs(r_y) < BISQUARE_C * sigma[1])
    ok = reduction.phases.ok.copy()
    ok[np.flatnonzero(reduction.rays.ok)[~kept]] = False
    phases = dataclasses.replace(reduction.phases, ok=ok)
    return dataclasses.replace(reduction, phases=phases), dataclasses.replace(settings, robust_fit=False)


def _perturbed_run(red, inp: Input, sign: float, ctx: dict):
    """The reduction rerun with input *inp* moved by *sign* standard uncertainties."""
    from .pipeline import pose_from_corners, rerun

    g, distance, settings = ctx["geometry"], ctx["distance_m"], ctx["settings"]
    fringes, design = ctx["fringes"], ctx["design"]
    screen = ctx["screen"]
    step = sign * inp.u
    phases = red.phases
    start = "rays"
    name = inp.name
    if name == "distance":
        distance = distance + 1e-3 * step
        start = "pose"
    elif name in ("camera fx", "camera fy", "camera cx", "camera cy"):
        k = g.camera.matrix.copy()
        k[{"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}[name.split()[1]]] += step
        g = dataclasses.replace(g, camera=dataclasses.replace(g.camera, matrix=k))
    elif name.startswith("camera "):
        d = g.camera.distortion.copy()
        d[("k1", "k2", "p1", "p2", "k3").index(name.split()[1])] += step
        g = dataclasses.replace(g, camera=dataclasses.replace(g.camera, distortion=d))
    elif name.startswith("screen r") or name.startswith("screen t"):
        axis = "xyz".index(name[-1])
        vec = np.zeros(3)
        vec[axis] = step
        delta = small_motion(rotation_mrad=vec) if name.startswith("screen r") else small_motion(translation_mm=vec)
        # The screen moved as itself (a measured screen keeps its shape); the geometry's pose follows it.
        screen = screen.moved(delta)
        g = dataclasses.replace(g, screen_to_camera=screen.screen_to_camera)
    elif name.startswith("screen pitch"):
        screen = screen.stretched(name[-1], 1.0 + step)
    elif name.startswith("display response") or name.startswith("frame brightness"):
        pos = dict(phases.positions_m)
        quadrature = name.split()[-1]
        harmonic = 4 if name.startswith("display") else 1
        axes = "xy" if harmonic == 4 else name.split()[2]
        ok = phases.ok
        for axis, length in zip("xy", ctx["screen_size_m"]):
            if axis in axes:
                p = getattr(fringes, f"periods_{axis}")[-1]
                moved = pos[axis].copy()
                moved[ok] += _phase_error_shift(moved[ok], length, p, step, harmonic, quadrature)
                pos[axis] = moved
        phases = dataclasses.replace(phases, positions_m=pos)
    elif name.startswith("fixture"):
        axis = "xyz".index(name[-1])
        vec = np.zeros(3)
        vec[axis] = step
        delta = small_motion(rotation_mrad=vec) if name.startswith("fixture r") else small_motion(translation_mm=vec)
        g = dataclasses.replace(g, fixture_to_camera=g.fixture_to_camera.compose(delta))
        start = "pose"
    elif name.startswith("corner "):
        _, i, c = name.split()
        corners = red.pose.corners_px.copy()
        corners[int(i), "uv".index(c)] += step
        pose = pose_from_corners(corners, red.region, red.rays, g, design, distance, settings,
                                 agreement=red.pose.outline_agreement)
        return rerun(red, "shape", fringes=fringes, geometry=g, design=design, measured_distance_m=distance,
                     settings=settings, screen=screen, pose=pose, with_curl=False)
    else:
        raise ValueError(f"unknown input {name!r}")
    return rerun(red, start, fringes=fringes, geometry=g, design=design, measured_distance_m=distance,
                 settings=settings, screen=screen, phases=phases, with_curl=False)


@dataclass
class Sensitivities:
    """Standard-uncertainty contribution of each input to each scalar figure (figure units), from finite
    differences at +-1 u: ``linear`` (c) and ``curvature`` (q); the contribution is sqrt(c^2 + 2 q^2)."""

    inputs: list
    paths: list
    linear: np.ndarray          # (n_inputs, n_paths)
    curvature: np.ndarray       # (n_inputs, n_paths)
    n_points: int
    seconds: float = 0.0

    @property
    def contributions(self) -> np.ndarray:
        return np.sqrt(self.linear ** 2 + 2.0 * self.curvature ** 2)


def sensitivities(reduction, *, fringes, geometry, design, measured_distance_m: float, settings,
                  inputs: InputUncertainties, screen=None, max_points: int = 4_000) -> Sensitivities:
    """Finite-difference sensitivities of every scalar figure to every input of :func:`budget_inputs`,
    on a decimated copy of *reduction* (cost: two partial reruns per input); of a robust analysis, on the
    points its fit keeps, with the plain fit (:func:`robust_inliers`).

    They are taken at the facet's expected pose, not at the one this capture's corners give: the corners
    are replaced by the design corners where the fixture's nominal pose puts them (GUM 5.1.3: sensitivity
    coefficients at the expectations of the inputs). The corner pose of a nearly frontal facet is a
    strongly nonlinear function of the corners and the camera's focal lengths (its rotation about y turns
    2.5 mrad for +1 px of f_x - f_y and 3.2 mrad for -1 px on the 400 x 300 twin); at one capture's noisy
    corners (their own rotation error of about 1.6 mrad) the secant scattered from 2.1 to 2.9 mrad per px
    from capture to capture, and the first facet's value was kept for every later one."""
    import time

    from .camera import project
    from .pipeline import default_screen, pose_from_corners, rerun

    t0 = time.perf_counter()
    screen = screen if screen is not None else default_screen(geometry)
    reduction, settings = robust_inliers(reduction, settings)
    # The reruns move the station's inputs, not the capture: the checks that judge a capture (the corner
    # pose against the outline, the measured distance against the corner pose's range) do not apply to
    # them (a 300 mm distance uncertainty would otherwise ask to re-measure a distance that is fine).
    settings = dataclasses.replace(settings, max_range_shift_m=float("inf"), max_corner_rms_px=float("inf"))
    red = decimated(reduction, max_points)
    ctx = {"geometry": geometry, "distance_m": measured_distance_m, "settings": settings, "fringes": fringes,
           "design": design, "screen": screen, "screen_size_m": (screen.width_m, screen.height_m)}
    base = rerun(red, "rays", fringes=fringes, geometry=geometry, design=design,
                 measured_distance_m=measured_distance_m, settings=settings, screen=screen, with_curl=False)
    nominal_corners = project(geometry.camera, geometry.fixture_to_camera, design.corners_3d())
    nominal_pose = pose_from_corners(nominal_corners, base.region, base.rays, geometry, design, measured_distance_m,
                                     settings, agreement=base.pose.outline_agreement)
    base = rerun(base, "shape", fringes=fringes, geometry=geometry, design=design,
                 measured_distance_m=measured_distance_m, settings=settings, screen=screen, pose=nominal_pose,
                 with_curl=False)
    f0 = np.array([_value(base.figures, p) for p in SCALAR_PATHS])
    rows = budget_inputs(inputs, len(reduction.pose.corners_px))
    lin = np.zeros((len(rows), len(SCALAR_PATHS)))
    cur = np.zeros_like(lin)
    for i, inp in enumerate(rows):
        try:
            fig_plus = _perturbed_run(base, inp, +1.0, ctx).figures
            fig_minus = _perturbed_run(base, inp, -1.0, ctx).figures
        except StationError as exc:
            key = input_key(inp)
            raise AnalysisError(
                f"the uncertainty cannot be computed: with the {inp.name} moved by its standard uncertainty "
                f"({inp.u:g} {inp.unit}{f', [uncertainty] {key}' if key else ''}) the reduction fails ({exc}); "
                f"that uncertainty is not plausible for this station: check {f'[uncertainty] {key}' if key else 'it'}"
            ) from exc
        plus = np.array([_value(fig_plus, p) for p in SCALAR_PATHS])
        minus = np.array([_value(fig_minus, p) for p in SCALAR_PATHS])
        lin[i] = 0.5 * (plus - minus)
        cur[i] = 0.5 * (plus + minus) - f0
    return Sensitivities(rows, list(SCALAR_PATHS), lin, cur, int(base.rays.vidx.size), time.perf_counter() - t0)


def _value(figures: dict, path: tuple) -> float:
    v = get_path(figures, path)
    return np.nan if v is None else v


# ------------------------------------------------------------------------------------------- random part
def _fit_figures(a: float, b: float, e1: float, e2: float) -> dict:
    """The fit's scalar figures as functions of A, B, E1, E2 (for their Jacobian)."""
    e = 0.5 * (e1 + e2)
    (p1, p2), angle = principal_axes(a, b, e)
    kx, ky = 4.0 * a, 4.0 * b
    return {("focal_length_x_m",): 1.0 / kx if kx else np.nan, ("focal_length_y_m",): 1.0 / ky if ky else np.nan,
            ("curvature_x_per_m",): kx, ("curvature_y_per_m",): ky, ("twist_mrad_per_m",): 1000.0 * e,
            ("twist_e1_mrad_per_m",): 1000.0 * e1, ("twist_e2_mrad_per_m",): 1000.0 * e2,
            ("principal_focal_lengths_m", 0): np.nan if p1 is None else p1,
            ("principal_focal_lengths_m", 1): np.nan if p2 is None else p2, ("axis_angle_rad",): angle}


def _line_fit_covariance(u: np.ndarray, v: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Covariance of (k0, k1, k2) in s = k0 (u - mean u) + k1 + k2 (v - mean v) fitted by ordinary least
    squares to slopes with independent noise *sigma* per point."""
    uc, vc = u - u.mean(), v - v.mean()
    x = np.stack([uc, np.ones_like(uc), vc])
    m_inv = np.linalg.inv(x @ x.T)
    b = (x * sigma ** 2) @ x.T
    return m_inv @ b @ m_inv


@dataclass
class NoisePropagation:
    """The capture's own noise carried to the figures.

    Attributes
    ----------
    sigma : dict
        ``{path: standard uncertainty}`` of the scalar figures the noise reaches (fit figures, boresight,
        optical tilt, slope RMS values).
    slope_noise_mrad : dict
        ``{"x", "y", "magnitude"}`` the RMS slope (angle) noise the capture's intensity noise explains, mrad.
    """

    sigma: dict
    slope_noise_mrad: dict


def pixel_noise_dn(reduction, take: np.ndarray) -> np.ndarray | float:
    """The frame noise (DN, rounding included) of the region's pixels *take* (indices into the phases'
    arrays), each at its own brightness: :func:`~.slope_noise.pixel_noise_dn` of *reduction*."""
    from .slope_noise import pixel_noise_dn as of_stages

    return of_stages(reduction.phases, getattr(reduction.region, "stack", None), take)


def noise_propagation(reduction, *, fringes, geometry, design, settings, screen=None,
                      max_points: int = 30_000) -> NoisePropagation:
    """Propagate the capture's intensity noise (``Phases.noise_dn``) to slopes and to the fits.

    Position noise per pixel from the finest phase's modulation and the pixel's own frame noise at its
    brightness (:func:`pixel_noise_dn`: shot noise makes the dim pixels at the facet's edges quieter,
    and one noise figure for all over-stated the fits' noise by 5-8 % whenever the facet's edges cut
    through pixels); the slope noise per pixel from the reflection law's derivative with respect to the
    screen position (finite difference with the surface point held); the fits' covariance by
    least-squares propagation of independent per-pixel noise. Done on every n-th valid pixel (about
    *max_points*) and scaled to all of them.
    """
    from .pipeline import default_screen

    screen = screen if screen is not None else default_screen(geometry)
    red = reduction
    ok = red.rays.ok
    n_all = int(red.rays.vidx.size)
    step = max(1, n_all // max_points)
    sel = slice(None, None, step)
    take = np.flatnonzero(ok)[sel]          # the pixels of [ok][sel], without gathering every valid pixel first
    from .slope_noise import position_sigmas_m, slope_jacobian

    sig_u = position_sigmas_m(red.phases, getattr(red.region, "stack", None), take, fringes,
                              (screen.width_m, screen.height_m))
    # Slopes' derivative with respect to the screen position, surface point held, in the boresight frame.
    points = red.shape.points_m[:, sel]
    s0, gx, gy = slope_jacobian(points, red.shape.boresighted_to_camera.inverse(), screen,
                                red.phases.positions_m["x"][take], red.phases.positions_m["y"][take])
    var = (gx * sig_u["x"]) ** 2 + (gy * sig_u["y"]) ** 2        # (2, n) slope variance
    sig_s = np.sqrt(var)
    angle_sig = 1000.0 * sig_s / (1.0 + s0 ** 2)                 # mrad
    noise = {"x": float(np.sqrt(np.mean(angle_sig[0] ** 2))), "y": float(np.sqrt(np.mean(angle_sig[1] ** 2)))}
    noise["magnitude"] = float(np.hypot(noise["x"], noise["y"]))
    x, y = points[0], points[1]
    scale = points.shape[1] / n_all                              # covariance on all points = scale x subset's
    cov_x = _line_fit_covariance(x, y, sig_s[0]) * scale         # (2A, C', E1)
    cov_y = _line_fit_covariance(y, x, sig_s[1]) * scale         # (2B, D', E2)
    fit = red.fits.parabola
    # Jacobian of the fit figures with respect to (A, B, E1, E2); A = k0/2.
    cov = np.diag([cov_x[0, 0] / 4.0, cov_y[0, 0] / 4.0, cov_x[2, 2], cov_y[2, 2]])
    cov[0, 2] = cov[2, 0] = cov_x[0, 2] / 2.0
    cov[1, 3] = cov[3, 1] = cov_y[0, 2] / 2.0
    p0 = np.array([fit.a, fit.b, fit.e1, fit.e2])
    base = _fit_figures(*p0)
    jac = {}
    for j in range(4):
        h = 1e-6 * max(abs(p0[j]), 1e-6)
        hi = _fit_figures(*(p0 + h * np.eye(4)[j]))
        lo = _fit_figures(*(p0 - h * np.eye(4)[j]))
        for k in base:
            jac.setdefault(k, np.zeros(4))[j] = (hi[k] - lo[k]) / (2 * h)
    sigma = {k: float(np.sqrt(max(J @ cov @ J, 0.0))) for k, J in jac.items()}
    # Boresight and optical tilt: the subsample fit's slope at the alignment point (alpha <- s_y, beta <- s_x).
    xa, ya = (float(c) for c in design.alignment_point_m)
    sub = settings.subsample_step
    va = np.array([xa - x.mean(), 1.0, ya - y.mean()])
    vb = np.array([ya - y.mean(), 1.0, xa - x.mean()])
    s_a = (2 * fit.a * xa + fit.c + fit.e * ya, 2 * fit.b * ya + fit.d + fit.e * xa)
    sig_bx = 1000.0 * np.sqrt(vb @ cov_y @ vb * sub) / (1 + s_a[1] ** 2)
    sig_by = 1000.0 * np.sqrt(va @ cov_x @ va * sub) / (1 + s_a[0] ** 2)
    sigma[("boresight_mrad", "x")] = sigma[("optical_tilt_mrad", "x")] = float(sig_bx)
    sigma[("boresight_mrad", "y")] = sigma[("optical_tilt_mrad", "y")] = float(sig_by)
    # Slope RMS values: mean(e^2) with e = t + n has variance (4 mean(t^2) s^2 + 2 s^4) / N.
    for model in red.fits.residuals_mrad:
        # mean(e^2) from the reported RMS (the same sums; squared back, within a unit of the last place)
        rms = red.figures["slope_rms_mrad"][model]
        ms = {"x": float(rms["x"]) ** 2, "y": float(rms["y"]) ** 2}
        ms["magnitude"] = ms["x"] + ms["y"]
        s2 = {a: noise[a] ** 2 for a in RMS_AXES}
        for a in RMS_AXES:
            var_ms = (4 * max(ms[a] - s2[a], 0.0) * s2[a] + 2 * s2[a] ** 2) / n_all
            sigma[("slope_rms_mrad", model, a)] = float(np.sqrt(var_ms) / (2 * np.sqrt(max(ms[a], 1e-30))))
    return NoisePropagation(sigma, noise)


# ------------------------------------------------------------------------------ the corner pose, by Monte Carlo
#: Figures the corner pose decides (their U comes from :func:`pose_monte_carlo`).
POSE_PATHS: tuple[tuple, ...] = (("boresight_mrad", "x"), ("boresight_mrad", "y"),
                                 *[("placement", "mm", i) for i in range(3)],
                                 *[("placement", "mrad", i) for i in range(3)])
#: Budget groups the Monte Carlo of the corner pose draws (the other groups' contributions are added to it).
POSE_GROUPS = ("measured distance", "camera focal length", "camera principal point", "camera distortion",
               "fixture pose", "corner location")
#: Draws of the Monte Carlo (each solves the 4-corner pose twice: all inputs, corners alone).
POSE_DRAWS = 200


def _rotation_batch(angles: np.ndarray) -> np.ndarray:
    """:func:`_rotation` of each row (rx, ry, rz) of *angles* (n, 3), radians: (n, 3, 3)."""
    c, s = np.cos(angles), np.sin(angles)
    one, zero = np.ones(len(angles)), np.zeros(len(angles))
    r_x = np.stack([one, zero, zero, zero, c[:, 0], -s[:, 0], zero, s[:, 0], c[:, 0]], -1).reshape(-1, 3, 3)
    r_y = np.stack([c[:, 1], zero, s[:, 1], zero, one, zero, -s[:, 1], zero, c[:, 1]], -1).reshape(-1, 3, 3)
    r_z = np.stack([c[:, 2], -s[:, 2], zero, s[:, 2], c[:, 2], zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return r_z @ r_y @ r_x


def _rotations(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of rotation vectors *w* (n, 3), radians (Rodrigues' formula)."""
    theta = np.sqrt(np.sum(w * w, axis=1))
    k = w / np.where(theta < 1e-300, 1.0, theta)[:, None]
    kx = np.zeros((w.shape[0], 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    return np.eye(3) + np.sin(theta)[:, None, None] * kx + (1.0 - np.cos(theta))[:, None, None] * (kx @ kx)


def _project_batch(rotation, translation, points, matrix, distortion, jacobian: bool = False):
    """Image positions (n, m, 2) of *points* (m, 3) under n poses (*rotation* (n, 3, 3), *translation*
    (n, 3)) and n cameras (*matrix* (n, 3, 3), *distortion* (n, 5): k1, k2, p1, p2, k3): the arithmetic of
    OpenCV's projectPoints for the 5-coefficient model. With *jacobian*, also their derivatives (n, m, 2, 6)
    with respect to a rotation w applied on the left (R <- exp(w) R) and to the translation."""
    rp = rotation @ points.T                                        # (n, 3, m): R X
    xc = rp + translation[:, :, None]
    iz = 1.0 / xc[:, 2]
    x, y = xc[:, 0] * iz, xc[:, 1] * iz
    k1, k2, p1, p2, k3 = (distortion[:, i, None] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    fx, s, cx = matrix[:, 0, 0, None], matrix[:, 0, 1, None], matrix[:, 0, 2, None]
    fy, cy = matrix[:, 1, 1, None], matrix[:, 1, 2, None]
    uv = np.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=-1)
    if not jacobian:
        return uv
    d_rad = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))          # d radial / dx = d_rad x
    dxd_dx = radial + d_rad * x * x + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = d_rad * x * y + 2.0 * p1 * x + 2.0 * p2 * y            # = d yd / dx
    dyd_dy = radial + d_rad * y * y + 6.0 * p1 * y + 2.0 * p2 * x
    jac = np.empty(x.shape + (2, 6))
    rpt = np.moveaxis(rp, 1, -1)                                    # (n, m, 3): R X
    for row, (dx, dy) in enumerate(((fx * dxd_dx + s * dxd_dy, fx * dxd_dy + s * dyd_dy),
                                    (fy * dxd_dy, fy * dyd_dy))):
        # d/dXc of x = X/Z, y = Y/Z; then d(exp(w) R X)/dw at w = 0 is -[R X]x, so d/dw = (R X) x d/dXc.
        g = np.stack([dx * iz, dy * iz, -(dx * x + dy * y) * iz], axis=-1)
        jac[..., row, 3:] = g
        jac[..., row, :3] = np.cross(rpt, g)
    return uv, jac


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """The left Jacobian of SO(3) at rotation vectors *phi* (n, 3): exp(phi + d) = exp(J d) exp(phi)."""
    theta = np.sqrt(np.sum(phi * phi, axis=1))[:, None, None]
    k = np.zeros((phi.shape[0], 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = phi[:, 2], -phi[:, 1], phi[:, 0]
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1.0 - np.cos(t)) / t ** 2)
    b = np.where(small, 1.0 / 6.0, (t - np.sin(t)) / t ** 3)
    return np.eye(3) + a * k + b * (k @ k)


#: Levenberg-Marquardt of :func:`solve_poses_batch`: at most this many accepted steps, stopping at a relative
#: parameter change below FLT_EPSILON (the criterion of OpenCV's solvePnP refinement, whose 20 steps stop short
#: of the minimum for some draws; this one goes on to it).
PNP_MAX_ITER = 200
PNP_EPSILON = float(np.finfo(np.float32).eps)


def solve_poses_batch(corners_px: np.ndarray, points: np.ndarray, matrix: np.ndarray, distortion: np.ndarray,
                      rotation0: np.ndarray, translation0: np.ndarray, max_iter: int = PNP_MAX_ITER,
                      epsilon: float = PNP_EPSILON) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n camera-from-object poses at once, each refined from (*rotation0* (3, 3), *translation0* (3,)) so
    that *points* (m, 3) project onto its *corners_px* (n, m, 2) with the least squared reprojection error in
    pixels: what the station's own corner pose (:func:`~sofast_station.measure.pose.solve_corner_pose`,
    OpenCV's ``solvePnP(SOLVEPNP_ITERATIVE)`` from the fixture's nominal pose) minimises, on all n problems
    as arrays (a Monte Carlo's hundreds of 4-point solves then cost one solve's Python overhead).

    Levenberg-Marquardt as in OpenCV's refinement: parameters (Rodrigues vector, translation), the analytic
    Jacobian of the projection (the rotation's through the left Jacobian of SO(3)), Marquardt's damping
    (``J^T J`` with its diagonal times ``1 + 10^l``, l from -3, up by one and the step redone from the same
    point while the error grows, down by one after each accepted step), stopping at a relative parameter
    change below *epsilon*. Not after OpenCV's 20 steps: the four corners of a nearly frontal facet leave
    its pose a long, flat, curved valley of the reprojection error, along which the steps shrink slowly
    (each about 0.6 of the last), and OpenCV stops typically 0.03 mrad (at most 0.3) short of the minimum
    for one capture's corner noise, 1-20 mrad for a draw that lands far along the valley. On the 400 x 300
    twin this solver reaches the minimum (the error at most OpenCV's) and the Monte Carlo's U are 0.3-1.9 %
    above those with OpenCV's stops (20 captures).

    Returns
    -------
    (rotation (n, 3, 3), translation (n, 3), converged (n,) bool: stopped by *epsilon* within *max_iter*)
    """
    import cv2

    n = corners_px.shape[0]
    points = np.asarray(points, np.float64)
    obs = np.asarray(corners_px, np.float64).reshape(n, -1)
    rvec0 = cv2.Rodrigues(np.asarray(rotation0, np.float64))[0].ravel()
    param = np.tile(np.concatenate([rvec0, np.asarray(translation0, np.float64).ravel()]), (n, 1))

    def evaluate(idx, p):
        uv, jac = _project_batch(_rotations(p[:, :3]), p[:, 3:], points, matrix[idx], distortion[idx], jacobian=True)
        jac = jac.reshape(len(idx), -1, 6)
        jac[..., :3] = jac[..., :3] @ _left_jacobian(p[:, :3])
        err = uv.reshape(len(idx), -1) - obs[idx]
        jt = np.swapaxes(jac, 1, 2)
        return np.sqrt(np.sum(err * err, axis=1)), jt @ jac, (jt @ err[..., None])[..., 0]

    everyone = np.arange(n)
    prev_norm, jtj, jte = evaluate(everyone, param)
    prev = param.copy()
    lam_lg = np.full(n, -3)
    iters = np.zeros(n, int)
    active = np.ones(n, bool)
    converged = np.zeros(n, bool)
    eye6 = np.eye(6)
    while active.any():
        idx = np.flatnonzero(active)
        a = jtj[idx] * (1.0 + eye6 * 10.0 ** lam_lg[idx, None, None])
        try:
            step = np.linalg.solve(a, jte[idx][..., None])[..., 0]
        except np.linalg.LinAlgError:       # a draw whose corners leave the pose undetermined
            step = (np.linalg.pinv(a) @ jte[idx][..., None])[..., 0]
        new = prev[idx] - step
        norm, jtj_new, jte_new = evaluate(idx, new)
        worse = ~(norm <= prev_norm[idx])
        lam_lg[idx[worse]] += 1
        take = ~(worse & (lam_lg[idx] <= 16))        # a worse step is redone with more damping, up to 16
        ia = idx[take]
        lam_lg[ia] = np.maximum(lam_lg[ia] - 1, -16)
        iters[ia] += 1
        param[ia] = new[take]
        change = np.linalg.norm(new[take] - prev[ia], axis=1) / np.maximum(np.linalg.norm(prev[ia], axis=1), 1e-300)
        small = change < epsilon
        stop = small | (iters[ia] >= max_iter)
        active[ia[stop]] = False
        converged[ia[small]] = True
        go = ~stop
        on = ia[go]
        prev_norm[on], prev[on] = norm[take][go], new[take][go]
        jtj[on], jte[on] = jtj_new[take][go], jte_new[take][go]
    return _rotations(param[:, :3]), param[:, 3:].copy(), converged


def pose_draws(corners_px: np.ndarray, corner_factor: np.ndarray, geometry, inputs: InputUncertainties,
               draws: int = POSE_DRAWS, seed: int = 12) -> dict:
    """The inputs :func:`pose_monte_carlo` draws: the noise of the *corners_px* (n, 2), ``corner_factor @ z``
    (C = M M^T, the corners' covariance in pixels squared), the camera's focal lengths, principal point and
    distortion, the fixture pose and the measured distance's error from *inputs*.

    Standard normal draws, each input's column moment-matched (mean 0, standard deviation 1 exactly): the
    same draws serve every capture (fixed *seed*), so their sampling error would otherwise be one common
    bias of every U (a few per cent with 200 draws); matched, the linear part is exact.

    Returns
    -------
    dict of arrays over the draws
        ``corner_noise_px`` (draws, n, 2), the camera's ``matrix`` (draws, 3, 3) and ``distortion``
        (draws, 5), ``fixture_rotation`` (draws, 3, 3) and ``fixture_translation`` (draws, 3) of the
        fixture-to-camera pose, ``distance_m`` (draws,): the measured distance's error, metres.
    """
    rng = np.random.default_rng(seed)
    corners = np.asarray(corners_px, np.float64)
    cam, fix0 = geometry.camera, geometry.fixture_to_camera
    z = rng.standard_normal((draws, corners.size + 4 + 5 + 6 + 1))
    z = (z - z.mean(axis=0)) / z.std(axis=0)
    z_c, z_k, z_d, z_f, z_r = np.split(z, np.cumsum([corners.size, 4, 5, 6]), axis=1)
    u_k = np.array([inputs.camera_focal_px, inputs.camera_focal_px, inputs.camera_principal_px,
                    inputs.camera_principal_px])
    k = np.repeat(cam.matrix[None], draws, axis=0)
    k[:, (0, 1, 0, 1), (0, 1, 2, 2)] += z_k * u_k
    # The fixture moved by a small motion (fixture_to_camera.compose(small_motion(...))), on arrays.
    d_rot = _rotation_batch(1e-3 * z_f[:, :3] * np.asarray(inputs.fixture_rotation_mrad))
    return {"corner_noise_px": (z_c @ np.asarray(corner_factor).T).reshape(draws, *corners.shape),
            "matrix": k, "distortion": cam.distortion[None] + z_d * np.asarray(inputs.camera_distortion)[None],
            "fixture_rotation": fix0.rotation @ d_rot,
            "fixture_translation": (fix0.rotation @ (1e-3 * z_f[:, 3:] * np.asarray(inputs.fixture_translation_mm)).T).T
            + fix0.translation,
            "distance_m": 1e-3 * inputs.distance_mm * z_r[:, 0]}


def pose_monte_carlo(reduction, *, geometry, design, inputs: InputUncertainties, draws: int = POSE_DRAWS,
                     seed: int = 12) -> dict:
    """Mean squared error of the corner-pose figures (boresight, placement) when the inputs the corner
    pose depends on are drawn from their distributions (GUM Supplement 1): the corners' noise from their
    covariance (``corner_cov_px2``), the camera's focal lengths, principal point and distortion, the
    fixture pose and the measured distance's error from ``[uncertainty]``.

    Why not the finite differences of :func:`sensitivities`: the pose of a nearly frontal facet from its
    corners is far from linear at the scale of these uncertainties (on the 400 x 300 twin its rotation
    about y moves by -3.2 mrad for f_x - f_y = +1 px and +2.5 mrad for -1 px, and the slope itself shifts
    with the corners' own noise), so a sensitivity taken at one point, once per geometry, made U of the
    rotation about y cover 91 % of the errors instead of 95 %. All draws' 4-point poses are solved at once
    (:func:`solve_poses_batch`: 34-36 ms of CPU per facet against 95-100 ms for OpenCV's solvePnP one at a
    time, on a quiet machine), so it is drawn for every capture, with its own corner covariance, at the
    expected pose (the facet where the fixture's nominal pose puts it; GUM 5.1.3). Not at the capture's found
    corners: their own noise moves that point towards the near-frontal pose's two-fold ambiguity, where
    the pose turns fastest, and U then scattered from 3 to 13 mrad between captures of the same facet and
    covered 88-91 %. A fixed seed keeps the result the same for the same capture, and moment-matched draws
    make its linear part exact; the curved, heavy-tailed rest keeps a sampling error of 5-7 % of U with 200
    draws, common to every capture through the seed (docs/uncertainty.md).

    Each draw is the measurement itself: the facet at the expected pose in the drawn fixture, photographed
    by the drawn camera (its corners projected through the drawn intrinsics and distortion, plus the drawn
    corner noise), its distance read with the drawn error; the analysis's corner pose from those corners
    with the nominal camera, range-fixed with that distance, and its placement in the nominal fixture;
    the error is against the draw's truth. (Until 2026-12-02 the draws perturbed the analysis instead:
    nominal corners solved with the drawn camera. To first order that is the same spread, but the pose's
    curvature in f_x - f_y then has the opposite sign, so its offset of the rotation about y, -0.6 mrad
    on the twin, came out as +0.6 mrad; its U changed by 1-3 %.) Drawing the facet's placement in the
    fixture as well (uniform +-1 mm, +-1 mrad on the twin) changes these U by less than 0.5 %: the pose's
    nonlinearity is in the camera and the corners, not in where within that tolerance the facet sits.

    The boresight is the rotation from the corner pose to the frame the measured surface defines, which
    does not depend on the corner pose: its error is the corner pose's rotation error (about the facet's
    x and y), with the opposite sign.

    Returns
    -------
    dict
        ``{path: (mean square error, mean square error from the corners alone)}`` for :data:`POSE_PATHS`,
        in the figures' units squared; {} when the corners have no covariance.
    """
    pose0 = reduction.pose
    cov = getattr(pose0, "corner_cov_px2", None)
    n_corners = np.asarray(pose0.corners_px, float).size
    if cov is None or np.shape(cov) != (n_corners, n_corners) or not np.all(np.isfinite(cov)):
        return {}
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    m = v * np.sqrt(np.clip(w, 0.0, None))[None, :]
    # The arithmetic of pose.solve_corner_pose, pose.fix_range and pose.placement on arrays, all draws at once.
    corners_3d = np.asarray(design.corners_3d(), np.float64)
    measure = np.array([*design.measure_point_m, float(design.z(*design.measure_point_m))])
    cx, cy = (float(c) for c in design.centroid_m)
    p_mid = np.array([cx, cy, float(design.z(cx, cy))])
    centre = np.asarray(reduction.rays.screen_centre_cam_m, np.float64)
    fix0 = geometry.fixture_to_camera
    cam = geometry.camera

    def nominal(x, n):
        return np.repeat(np.asarray(x, np.float64)[None], n, axis=0)

    def measured(true_r, true_t, k, dist, noise, distance_error):
        """The analysis's corner pose (range-fixed, NaN where it has none) of a facet at (true_r, true_t)
        photographed by camera (k, dist) with corner noise, its distance read with distance_error."""
        n = true_r.shape[0]
        corner_px = _project_batch(true_r, true_t, corners_3d, k, dist) + noise
        distance = np.linalg.norm(true_r @ measure + true_t - centre, axis=1) + distance_error
        r, t, _ = solve_poses_batch(corner_px, corners_3d, nominal(cam.matrix, n), nominal(cam.distortion, n),
                                    fix0.rotation, fix0.translation)
        q = r @ measure + t                         # range fixed along the line of sight to the measure point
        u = q / np.linalg.norm(q, axis=1)[:, None]
        wv = centre - q
        uw = np.sum(u * wv, axis=1)
        disc = uw * uw - np.sum(wv * wv, axis=1) + distance * distance
        root = np.sqrt(np.where(disc >= 0, disc, np.nan))
        mu = np.where(np.abs(uw - root) <= np.abs(uw + root), uw - root, uw + root)
        return r, t + mu[:, None] * u

    def errors(true_r, est):
        r, t = est
        d = np.swapaxes(true_r, -1, -2) @ r         # the pose's rotation error, facet axes
        rf = fix0.rotation.T @ r                    # facet -> nominal fixture: the placement reported
        tf = (fix0.rotation.T @ (r @ p_mid + t - fix0.translation).T).T - p_mid
        # The facet sits at the expected pose in the (drawn) fixture: its true placement is zero.
        return np.column_stack([-1000.0 * d[:, 2, 1], -1000.0 * d[:, 0, 2], 1000.0 * tf,
                                1000.0 * np.arctan2(rf[:, 2, 1], rf[:, 2, 2]),
                                -1000.0 * np.arcsin(np.clip(rf[:, 2, 0], -1.0, 1.0)),
                                1000.0 * np.arctan2(rf[:, 1, 0], rf[:, 0, 0])])

    dr = pose_draws(np.zeros((n_corners // 2, 2)), m, geometry, inputs, draws, seed)
    # In one batch of poses: all inputs drawn, then the corners alone.
    true_r = np.concatenate([dr["fixture_rotation"], nominal(fix0.rotation, draws)])
    true_t = np.concatenate([dr["fixture_translation"], nominal(fix0.translation, draws)])
    est = measured(true_r, true_t, np.concatenate([dr["matrix"], nominal(cam.matrix, draws)]),
                   np.concatenate([dr["distortion"], nominal(cam.distortion, draws)]),
                   np.concatenate([dr["corner_noise_px"], dr["corner_noise_px"]]),
                   np.concatenate([dr["distance_m"], np.zeros(draws)]))
    err = errors(true_r, est)
    d_all, d_corners = err[:draws], err[draws:]
    # A draw whose pose cannot be solved says nothing about the others.
    good = np.all(np.isfinite(d_all), axis=1) & np.all(np.isfinite(d_corners), axis=1)
    n = int(good.sum())
    if n < draws // 2:
        return {}
    sq_all = np.mean(d_all[good] ** 2, axis=0)
    sq_corners = np.mean(d_corners[good] ** 2, axis=0)
    return {p: (float(sq_all[j]), float(sq_corners[j])) for j, p in enumerate(POSE_PATHS)}


# ------------------------------------------------------------------------------------------- combination
def _nest(values: dict, figures: dict) -> dict:
    """``{path: value}`` -> ``{"name_U": structure like figures[name]}``."""
    out: dict = {}
    for path, v in values.items():
        top = path[0]
        if len(path) == 1:
            out[f"{top}_U"] = v
            continue
        template = figures[top]
        cur = out.setdefault(f"{top}_U", _empty_like(template))
        for p in path[1:-1]:
            cur = cur[p]
        cur[path[-1]] = v
    return out


def _empty_like(template):
    if isinstance(template, dict):
        return {k: _empty_like(v) for k, v in template.items()}
    if isinstance(template, (list, tuple)):
        return [None] * len(template)
    return None


def _clean(v: float):
    return None if v is None or not np.isfinite(v) else float(v)


def small_sample_factor(dof: int) -> float:
    """Standard deviation of a Type A quantity estimated from *dof* degrees of freedom, per unit estimate.

    A standard deviation s estimated from nu observations leaves the quantity t-distributed about its
    estimate, with standard deviation s sqrt(nu / (nu - 2)) (GUM Supplement 1, 6.4.9): for the few
    fringe sets of a capture (4 with two periods per axis) that is 1.41 s, without which a k = 2 interval
    covers about 88 % instead of 95 %. At most sqrt(3) (nu = 3) when nu is smaller.
    """
    nu = max(int(dof), 3)
    return float(np.sqrt(nu / (nu - 2.0)))


#: Captures whose frame-brightness estimates are pooled (the most recent ones of a geometry and recipe).
FRAME_POOL_CAPTURES = 50
#: A capture whose own frame-brightness estimate is beyond this quantile of the pooled one (F test) uses
#: its own: the room light changed, or this capture was disturbed.
FRAME_POOL_QUANTILE = 0.99


def frame_brightness_dn(reduction) -> tuple[float, int]:
    """The capture's own frame-to-frame brightness noise sigma_f (DN) and its degrees of freedom: each
    set's mean consistency residual I0 + I2 - I1 - I3 has variance 4 sigma_f^2 (one value per set)."""
    offsets = getattr(reduction.phases, "set_offsets_dn", {}) or {}
    allsets = [v for a in ("x", "y") for v in offsets.get(a, [])]
    if not allsets:
        return 0.0, 0
    return float(np.sqrt(np.mean(np.square(allsets)) / 4.0)), len(allsets)


def pooled_frame_brightness(own_dn: float, dof: int, pool) -> dict:
    """The frame-brightness noise a capture's uncertainty uses: pooled over the recent captures of the same
    geometry and recipe (GUM 4.2.4: a pooled variance of a measurement under statistical control), or the
    capture's own when it is significantly larger (F test at :data:`FRAME_POOL_QUANTILE`).

    *pool* (a deque, or None for no pooling) receives this capture's (sum of squares, dof). The value used
    is widened by :func:`small_sample_factor` of its degrees of freedom.

    Returns
    -------
    dict
        ``sigma_dn`` (used, widened), ``own_dn``, ``pooled_dn``, ``dof`` (of the value used), ``captures``
        (in the pool), ``source`` ("pooled" or "own").
    """
    own = {"sigma_dn": own_dn * small_sample_factor(dof), "own_dn": own_dn, "pooled_dn": None, "dof": dof,
           "captures": 1, "source": "own"}
    if pool is None or dof == 0:
        return own
    pool.append((own_dn ** 2 * dof, dof))
    n = sum(d for _, d in pool)
    pooled = float(np.sqrt(sum(ss for ss, _ in pool) / n))
    if len(pool) == 1:
        return own | {"pooled_dn": pooled}
    # The F distribution's quantile (scipy.stats' f.ppf computes this very function; scipy.stats itself
    # takes a second to import, which the first pooled capture paid)
    from scipy.special import fdtri
    limit = float(fdtri(dof, max(n - dof, 1), FRAME_POOL_QUANTILE))
    if pooled > 0 and own_dn ** 2 / pooled ** 2 > limit:
        return own | {"pooled_dn": pooled, "captures": len(pool)}
    return {"sigma_dn": pooled * small_sample_factor(n), "own_dn": own_dn, "pooled_dn": pooled, "dof": n,
            "captures": len(pool), "source": "pooled"}


def display_response_u(reduction, inputs: InputUncertainties) -> dict:
    """Standard uncertainty (rad) of the display response's phase error for this capture, from the
    capture's own evidence (docs/uncertainty.md, "display response").

    A response left nonlinear puts a second harmonic, correlated with the phase, into every four-step
    residual; :func:`~sofast_station.measure.phase.frame_noise` fits it over all sets (ratio r to the
    fringe's amplitude) and turns it into the largest four-step phase error E it gives for a power-law
    response (:func:`~sofast_station.measure.phase.phase_error_from_harmonic`). The fit's own standard
    uncertainty: each harmonic coefficient of the residual ``b (beta cos 2 phi + gamma sin 2 phi)``,
    fitted to N samples with residual noise 2 sigma (four frames of noise sigma), has standard deviation
    ``2 sigma / (b sqrt(N / 2))``, and r = |(beta, gamma)| / 4, so ``u(r) = sigma / (2 b sqrt(N / 2))``
    and ``u(E) = |dE/dr| u(r)``. The value used is ``sqrt(E^2 + u(E)^2)``: the phase error is not
    corrected, so its estimate counts in full, together with the estimate's uncertainty.

    The second harmonic shows a smooth miss of the response (a gamma not quite inverted), not the rounding
    of the fringes to whole 8-bit commands, whose 4-times-phase part the radiometric record in force
    states (``inputs.response_record_rad``, :func:`lut_phase_error_rad`): it is added in quadrature.

    ``[uncertainty] response_phase_rad`` is used when neither the capture (no four-step sets) nor a record
    says anything, and 0 there leaves the display response out of the budget.

    Returns
    -------
    dict
        ``u_rad`` (used), ``source`` ("capture", "capture and record", "record", "default" or "off"), and
        for a capture's evidence ``estimate_rad`` (E), ``estimate_u_rad`` (u(E)) and ``harmonic_ratio``
        (signed r); ``record_rad`` when a record's value is in it.
    """
    from .phase import MAX_NOISE_SAMPLES, phase_error_from_harmonic

    if inputs.response_phase_rad <= 0:
        return {"u_rad": 0.0, "source": "off"}
    fn = getattr(reduction.phases, "noise", None)
    ratio = getattr(fn, "signed_harmonic_ratio", None)
    sigma = getattr(fn, "frame_noise_dn", None)
    offsets = getattr(reduction.phases, "set_offsets_dn", None) or {}
    n_sets = sum(len(offsets.get(a, [])) for a in ("x", "y"))
    record = inputs.response_record_rad
    mods = []
    if ratio is not None and sigma is not None and n_sets and np.isfinite(ratio):
        ok = reduction.rays.ok
        mods = [np.asarray(reduction.phases.finest_modulation_dn[a])[ok] for a in ("x", "y")]
    if not mods or mods[0].size == 0:
        if record is not None:
            return {"u_rad": float(record), "source": "record", "record_rad": float(record)}
        return {"u_rad": float(inputs.response_phase_rad), "source": "default"}
    b = float(np.sqrt(np.mean(np.concatenate(mods) ** 2)))
    n = min(int(reduction.region.idx.size) * n_sets, MAX_NOISE_SAMPLES)
    u_ratio = float(sigma) / (2.0 * max(b, 1e-9) * np.sqrt(max(n, 2) / 2.0))
    estimate = float(fn.phase_error_rad)
    h = max(u_ratio, 1e-6)
    slope = abs(phase_error_from_harmonic(abs(ratio) + h) - phase_error_from_harmonic(abs(ratio))) / h
    u_estimate = slope * u_ratio
    out = {"u_rad": float(np.hypot(estimate, u_estimate)), "source": "capture", "estimate_rad": estimate,
           "estimate_u_rad": float(u_estimate), "harmonic_ratio": float(ratio)}
    if record is not None:
        # The two are different errors (a smooth miss of the response, the rounding to whole commands).
        out.update(u_rad=float(np.sqrt(out["u_rad"] ** 2 + record ** 2)), source="capture and record",
                   record_rad=float(record))
    return out


def capture_scales(reduction, sens: Sensitivities, inputs: InputUncertainties,
                   frame_sigma_dn: float | None = None, response_u_rad: float | None = None) -> np.ndarray:
    """Per budget row, the factor by which this capture's own estimate scales the cached sensitivity
    (1 for the systematic rows).

    * corner location: each corner coordinate's standard uncertainty from the sides' fits (the diagonal
      of ``CornerPoseResult.corner_cov_px2``; the median ``corner_sigma_px`` without it) over the
      ``corner_px`` the sensitivities were computed at (:func:`combine` also uses the correlations);
    * frame-to-frame brightness: the phase-error amplitude sigma_f / (sqrt(2) b) of each quadrature, with
      sigma_f the frames' brightness noise from the sets' mean consistency residuals
      (I0 + I2 - I1 - I3 has variance 4 sigma_f^2) and b the median finest-set modulation of the axis,
      over the reference amplitude; sigma_f is *frame_sigma_dn* when given (:func:`pooled_frame_brightness`),
      else the capture's own times :func:`small_sample_factor` of its number of sets (it comes from that few
      values);
    * display response: *response_u_rad* (:func:`display_response_u`, the capture's own evidence) over
      ``response_phase_rad``, at which the sensitivities were computed; 1 when not given.
    """
    scales = np.ones(len(sens.inputs))
    sigma_c = getattr(reduction.pose, "corner_sigma_px", None)
    cov = getattr(reduction.pose, "corner_cov_px2", None)
    corner_rows = [i for i, inp in enumerate(sens.inputs) if inp.group == "corner location"]
    per_coordinate = None
    if cov is not None and cov.shape == (len(corner_rows), len(corner_rows)):
        per_coordinate = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if frame_sigma_dn is None:
        own, dof = frame_brightness_dn(reduction)
        sigma_f = own * small_sample_factor(dof)
    else:
        sigma_f = float(frame_sigma_dn)
    ok = reduction.rays.ok
    amp = {}
    for a in ("x", "y"):
        b = float(median(reduction.phases.finest_modulation_dn[a][ok]))
        amp[a] = sigma_f / (np.sqrt(2.0) * max(b, 1e-9))
    for i, inp in enumerate(sens.inputs):
        if inp.group == "corner location" and per_coordinate is not None and inp.u > 0:
            scales[i] = per_coordinate[corner_rows.index(i)] / inp.u
        elif inp.group == "corner location" and sigma_c is not None and inp.u > 0:
            scales[i] = sigma_c / inp.u
        elif inp.group == "frame-to-frame brightness":
            scales[i] = amp[inp.name.split()[2]] / inp.u
        elif inp.group == "display response" and response_u_rad is not None and inp.u > 0:
            scales[i] = response_u_rad / inp.u
    return scales


#: Budget groups of the camera intrinsics (the Monte Carlo draws them for the corner pose only).
CAMERA_GROUPS = ("camera focal length", "camera principal point", "camera distortion")


def boresight_ray_path(sens: Sensitivities, contrib: np.ndarray) -> dict:
    """The camera intrinsics' contribution (standard, mrad) to the boresight through the rays, which the
    corner pose's Monte Carlo does not draw: ``{("boresight_mrad", a): u}``.

    The boresight is the rotation from the corner pose to the frame the measured surface defines. The
    Monte Carlo draws how the intrinsics move the corner pose; they also turn the measured surface's frame,
    since every pixel's ray turns with them (by 1 / f per pixel of the principal point). The optical tilt
    is that frame's tilt in the fixture, in which the corner pose's own tilt cancels, so the camera rows'
    contributions to ``optical_tilt_mrad`` (finite differences of the whole reduction) are this path. On
    the coverage twin (f = 3409 px) the boresight errors minus the placement rotations' follow the principal
    point by +0.29 to +0.30 mrad per px on three seeds; the optical tilt's row is 0.293. The two paths are
    nearly independent (the Monte Carlo's corner pose follows the principal point by 0.01-0.02 mrad per
    px), so this adds in quadrature.
    """
    rows = np.array([inp.group in CAMERA_GROUPS for inp in sens.inputs])
    out = {}
    for a in ("x", "y"):
        if ("optical_tilt_mrad", a) in sens.paths and rows.any():
            j = sens.paths.index(("optical_tilt_mrad", a))
            out[("boresight_mrad", a)] = float(np.sqrt(np.nansum(contrib[rows, j] ** 2)))
    return out


def combine(figures: dict, sens: Sensitivities, noise: NoisePropagation, inputs: InputUncertainties,
            scales: np.ndarray | None = None, corner_cov: np.ndarray | None = None,
            pose_mc: dict | None = None) -> dict:
    """The figures' expanded uncertainties, the noise floor and the budget, as figure keys to add.

    Returns ``{"name_U": ..., "name_U_random": ..., "coverage_factor": 2, "slope_rms_noise_mrad": ...,
    "slope_rms_corrected_mrad": ..., "slope_rms_corrected_mrad_U": ..., "uncertainty_budget": ...}``.
    The measured slope RMS's U also covers the noise's bias b (the measured value minus the noise-corrected
    one), which the measured value does not remove, as every uncorrected offset here: U = k sqrt(u^2 + b^2).
    (Added linearly, U = k u + b, it over-stated the slope RMS x's U by about 6 % on the twin: 1000 captures
    covered 97.3 % with U / std 2.23; in quadrature 96.0 % and 2.10.)

    *corner_cov* (2n x 2n, pixels squared, the corners' coordinates in budget order): the corner rows'
    linear parts are then carried with their correlations, as sqrt(J^T C J) with J the sensitivities per
    pixel, split into independent rows (C = M M^T, row contributions M^T J) so the budget still adds up.

    *pose_mc* (:func:`pose_monte_carlo`): for the corner-pose figures, the mean square errors it drew stand
    for the rows of :data:`POSE_GROUPS` (the other rows are added to them in quadrature, and for the
    boresight the camera intrinsics' path through the rays, :func:`boresight_ray_path`).
    """
    sc = np.ones(len(sens.inputs)) if scales is None else np.asarray(scales, float)
    linear = sens.linear * sc[:, None]
    rows = [i for i, inp in enumerate(sens.inputs) if inp.group == "corner location"]
    if corner_cov is not None and np.shape(corner_cov) == (len(rows), len(rows)) and rows \
            and np.all(np.isfinite(corner_cov)):
        u_ref = np.array([sens.inputs[i].u for i in rows])
        jac = sens.linear[rows] / u_ref[:, None]                           # figure per pixel
        w, v = np.linalg.eigh(0.5 * (corner_cov + corner_cov.T))
        m = v * np.sqrt(np.clip(w, 0.0, None))[None, :]
        linear = linear.copy()
        linear[rows] = m.T @ np.nan_to_num(jac)
    contrib = np.sqrt(linear ** 2 + 2.0 * (sens.curvature * (sc ** 2)[:, None]) ** 2)
    kinds = np.array([i.kind for i in sens.inputs])
    u_sys2 = np.nansum(contrib[kinds == "systematic"] ** 2, axis=0)
    # A response that curves (q != 0) does not only spread the figure: for a normal input its mean moves by q
    # (E[c z + q z^2] = q), and the reported value does not remove that offset. The systematic inputs'
    # offsets add with their signs and count as one more term (U = k sqrt(u^2 + b^2), the usual way to state
    # an uncorrected bias); c^2 + 2 q^2 above is the spread about that mean.
    offset = np.nansum(sens.curvature[kinds == "systematic"] * (sc[kinds == "systematic"] ** 2)[:, None], axis=0)
    u_sys2 = u_sys2 + offset ** 2
    u_cor2 = np.nansum(contrib[kinds == "random"] ** 2, axis=0)
    noise_col = np.array([noise.sigma.get(p, 0.0) for p in sens.paths])
    u_rand = np.sqrt(u_cor2 + noise_col ** 2)
    u = np.sqrt(u_sys2 + u_rand ** 2)
    rays = boresight_ray_path(sens, contrib) if pose_mc else {}
    if pose_mc:
        other = np.array([inp.group not in POSE_GROUPS for inp in sens.inputs])
        sys_o, rand_o = other & (kinds == "systematic"), other & (kinds == "random")
        off_o = np.nansum(sens.curvature[sys_o] * (sc[sys_o] ** 2)[:, None], axis=0)
        u_sys_o2 = np.nansum(contrib[sys_o] ** 2, axis=0) + off_o ** 2
        u_rand_o2 = np.nansum(contrib[rand_o] ** 2, axis=0) + noise_col ** 2
        for j, p in enumerate(sens.paths):
            if p in pose_mc:
                ms_all, ms_corners = pose_mc[p]
                u_rand[j] = np.sqrt(ms_corners + u_rand_o2[j])
                u[j] = max(np.sqrt(ms_all + u_sys_o2[j] + u_rand_o2[j] + rays.get(p, 0.0) ** 2), u_rand[j])
    k = COVERAGE_FACTOR
    values = {p: get_path(figures, p) for p in sens.paths}
    total, random = {}, {}
    for j, p in enumerate(sens.paths):
        if values[p] is None:
            total[p] = random[p] = None
            continue
        total[p] = _clean(k * u[j])
        random[p] = _clean(k * u_rand[j])
    # Noise floor: the slope noise the capture explains, and the RMS with it removed in quadrature.
    noise_mrad = {m: dict(noise.slope_noise_mrad) for m in figures["slope_rms_mrad"]}
    corrected, corrected_u = {}, {}
    for m, rms in figures["slope_rms_mrad"].items():
        corrected[m], corrected_u[m] = {}, {}
        for a in RMS_AXES:
            r, s = rms[a], noise_mrad[m][a]
            corrected[m][a] = None if r is None else float(np.sqrt(max(r * r - s * s, 0.0)))
            p = ("slope_rms_mrad", m, a)
            corrected_u[m][a] = total.get(p)
            if total.get(p) is not None and r is not None:       # the noise's bias, uncorrected: in quadrature
                total[p] = float(np.hypot(total[p], k * (r - corrected[m][a])))
    out = _nest(total, figures)
    out.update({k2 + "_random": v for k2, v in _nest(random, figures).items()})
    out.update(_subsample_fit_u(figures, sens.paths, u, u_rand, noise_col))
    out["coverage_factor"] = 2
    out["slope_rms_noise_mrad"] = noise_mrad
    out["slope_rms_corrected_mrad"] = corrected
    out["slope_rms_corrected_mrad_U"] = corrected_u
    out["uncertainty_budget"] = budget_table(sens, contrib, noise_col, u, u_rand, inputs, sc, offset)
    if pose_mc:
        out["uncertainty_budget"]["pose_monte_carlo"] = {
            "figures": [path_name(p) for p in sens.paths if p in pose_mc], "groups": list(POSE_GROUPS),
            "draws": POSE_DRAWS,
            "boresight_camera_rays": {path_name(p): _sig(v) for p, v in rays.items()}}
    return out


def _subsample_fit_u(figures: dict, paths: list, u: np.ndarray, u_rand: np.ndarray, noise_col: np.ndarray) -> dict:
    """``subsample_fit_U`` and ``subsample_fit_U_random`` (k = 2) of the focal lengths fitted on every n-th
    point (``subsample_fit``, what OpenCSP's SOFAST reports).

    The station inputs, the frame brightness and the corners move every slope smoothly over the facet, so the
    fit on every n-th point follows them as the fit on all points does: those contributions are the same.
    The intensity noise is independent from pixel to pixel, so its contribution to a least-squares fit grows
    as the square root of the points it leaves out: u_sub^2 = u^2 + (N / n - 1) u_noise^2 (N points in
    the reported fit, n in the subsample's). Exact for the plain fit; for the robust fit as far as its
    weights are the same on both (the noise propagation makes that approximation for the full fit too).
    """
    sub = figures.get("subsample_fit")
    n_all = figures.get("n_points")
    if not isinstance(sub, dict) or not sub.get("n_points") or not n_all:
        return {}
    more = max(float(n_all) / float(sub["n_points"]) - 1.0, 0.0)
    total, random = {"n_points": None}, {"n_points": None}     # the figure's shape; a count has no U
    for key in ("focal_length_x_m", "focal_length_y_m"):
        if (key,) not in paths or sub.get(key) is None:
            total[key] = random[key] = None
            continue
        j = paths.index((key,))
        total[key] = _clean(COVERAGE_FACTOR * np.sqrt(u[j] ** 2 + more * noise_col[j] ** 2))
        random[key] = _clean(COVERAGE_FACTOR * np.sqrt(u_rand[j] ** 2 + more * noise_col[j] ** 2))
    order = list(sub)
    return {"subsample_fit_U": {k: total.get(k) for k in order},
            "subsample_fit_U_random": {k: random.get(k) for k in order}}


def _sig(v: float, digits: int = 3):
    v = _clean(v)
    return None if v is None else float(f"{v:.{digits}g}")


def budget_table(sens: Sensitivities, contrib: np.ndarray, noise_col: np.ndarray, u: np.ndarray,
                 u_rand: np.ndarray, inputs: InputUncertainties, scales: np.ndarray,
                 offset: np.ndarray | None = None) -> dict:
    """The budget as one table, input group against figure: standard-uncertainty contributions (k = 1,
    figure units, root sum of squares within a group), the combined standard uncertainty, its random part,
    and the coverage factor (JSON-ready, 3 significant digits)."""
    groups: dict[str, dict] = {}
    for r, inp in enumerate(sens.inputs):
        g = groups.setdefault(inp.group, {"group": inp.group, "kind": inp.kind, "inputs": [], "sq": 0.0})
        g["inputs"].append(f"{inp.name} ({inp.u * scales[r]:.3g} {inp.unit})")
        g["sq"] = g["sq"] + np.nan_to_num(contrib[r]) ** 2
    rows = [{"group": g["group"], "kind": g["kind"], "inputs": g["inputs"],
             "contributions": [_sig(c) for c in np.sqrt(g["sq"])]} for g in groups.values()]
    if offset is not None:
        # After the systematic groups: the mean the systematic inputs' curved responses leave (see combine).
        at = sum(1 for r in rows if r["kind"] == "systematic")
        rows.insert(at, {"group": "curved-response offset", "kind": "systematic",
                         "inputs": ["sum of the systematic inputs' q"],
                         "contributions": [_sig(abs(c)) for c in np.nan_to_num(offset)]})
    rows.append({"group": "intensity noise", "kind": "random", "inputs": ["the capture's own noise"],
                 "contributions": [_sig(c) for c in noise_col]})
    return {"figures": [path_name(p) for p in sens.paths], "rows": rows, "coverage_factor": 2,
            "combined_standard": [_sig(c) for c in u], "random_standard": [_sig(c) for c in u_rand],
            "sensitivity_points": sens.n_points}


def sensitivity_key(geometry, design, fringes, settings, inputs: InputUncertainties, screen=None) -> str:
    """What the sensitivities depend on (geometry, recipe, input uncertainties), as a short hash."""
    import hashlib
    import json

    blob = {"geometry": geometry.to_dict(), "design": design.to_dict(), "fringes": fringes.to_dict(),
            "settings": {k: v for k, v in settings.to_dict().items() if k != "threads"},
            # Not the record-derived values: the sensitivities are computed at the table's reference
            # values, so a re-analysis without the record (reprocess) finds the station's own.
            "inputs": {k: v for k, v in inputs.to_dict().items() if k not in _NOT_TABLE_KEYS},
            # A measured screen's shape too (two display models at one pose are different stations).
            "screen": None if screen is None else repr(type(screen)) + (
                f" {screen.fingerprint()}" if hasattr(screen, "fingerprint") else "")}
    return hashlib.sha256(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:16]


def uncertainty_figures(reduction, *, fringes, geometry, design, measured_distance_m: float, settings,
                        inputs: InputUncertainties, screen=None, cache: dict | None = None,
                        cache_key=None, pool=None) -> dict:
    """Everything :func:`combine` adds to a reduction's figures; sensitivities come from *cache* under
    *cache_key* (geometry + recipe + inputs) when present, else are computed and stored there. On a *pool*
    (an executor) the corner pose's Monte Carlo runs beside the rest (the same values)."""
    sens = None if cache is None or cache_key is None else cache.get(cache_key)
    fresh = sens is None
    if sens is None:
        sens = sensitivities(reduction, fringes=fringes, geometry=geometry, design=design,
                             measured_distance_m=measured_distance_m, settings=settings, inputs=inputs, screen=screen)
        if cache is not None and cache_key is not None:
            cache[cache_key] = sens
    pose_task = None if pool is None else pool.submit(pose_monte_carlo, reduction, geometry=geometry, design=design,
                                                      inputs=inputs)
    noise = noise_propagation(reduction, fringes=fringes, geometry=geometry, design=design, settings=settings,
                              screen=screen)
    pool = None
    if cache is not None and cache_key is not None:
        from collections import deque
        pool = cache.setdefault(("frame brightness", cache_key), deque(maxlen=FRAME_POOL_CAPTURES))
    frame = pooled_frame_brightness(*frame_brightness_dn(reduction), pool)
    response = display_response_u(reduction, inputs)
    pose_mc = (pose_monte_carlo(reduction, geometry=geometry, design=design, inputs=inputs) if pose_task is None
               else pose_task.result())
    out = combine(reduction.figures, sens, noise, inputs,
                  capture_scales(reduction, sens, inputs, frame["sigma_dn"], response["u_rad"]),
                  getattr(reduction.pose, "corner_cov_px2", None), pose_mc)
    out["uncertainty_budget"]["frame_brightness"] = {k: (_sig(v, 4) if isinstance(v, float) else v)
                                                     for k, v in frame.items()}
    out["uncertainty_budget"]["display_response"] = {k: (_sig(v, 4) if isinstance(v, float) else v)
                                                     for k, v in response.items()}
    # Not a figure (a timing): :func:`~sofast_station.measure.pipeline.analyse` moves it to the timings.
    out["_sensitivity_seconds"] = sens.seconds if fresh else 0.0
    return out
