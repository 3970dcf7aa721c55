"""The systematic part: sensitivity of each figure to each station input (measured distance, camera
intrinsics and distortion, camera-to-screen pose, screen pitch, display response, fixture pose), by finite
differences of the whole reduction (:func:`~sofast_station.measure.pipeline.rerun`) at plus and minus one
standard uncertainty: the linear part ``(f(+u) - f(-u)) / 2`` and the curvature part
``(f(+u) + f(-u)) / 2 - f(0)`` combine to the standard deviation ``sqrt(c^2 + 2 q^2)`` of the figure for
a normal input (the curvature part matters for slope RMS values, which a perturbation raises whatever its
sign).

Sensitivities depend on the station's geometry and the recipe, not on the facet (:func:`sensitivity_key`
says on what): they are computed once on a decimated copy of one reduction and reused; the caller keeps
the cache.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from dataclasses import dataclass

import numpy as np

from ...errors import AnalysisError, StationError
from ..fit import BISQUARE_C
from ..phase import drawn_gain
from ..pipeline import default_screen, expected_corners_px, pose_from_corners, rerun
from .inputs import (RECORD_DERIVED_KEYS, SCALAR_PATHS, Input, InputUncertainties, budget_inputs, get_path,
                     input_key, screen_shape_inputs, small_motion)


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


def decimated(reduction, max_points: int = 30_000, *, nearest: bool = False):
    """A copy of *reduction* whose phases keep every n-th valid pixel (about *max_points* of them): the
    figures' dependence on the station's inputs is smooth, so sensitivities need no more. n is the valid
    pixels over *max_points* rounded down (at least *max_points* kept), or with *nearest* rounded to the
    nearest whole step (as near *max_points* as a step comes: 3,537 points and 2,000 keep every second)."""
    ok = reduction.rays.ok
    kept = np.flatnonzero(ok)
    step = max(1, int(round(kept.size / max_points)) if nearest else kept.size // max_points)
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
    elif name.startswith("screen shape"):
        # a measured shape's independent uncertainty field (its record's), one standard deviation per unit
        screen = screen.displaced(int(name.split()[-1]) - 1, step)
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
                shift = _phase_error_shift(moved[ok], length, p, step, harmonic, quadrature)
                # the drawn fringes' correction passes a phase error on with its gain (1 - e'(phi))
                gain = drawn_gain(fringes, axis, moved[ok], length, phases.footprint_px)
                moved[ok] += shift if gain is None else gain * shift
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
                     settings=settings, screen=screen, pose=pose, with_curl=False, warm=True)
    else:
        raise ValueError(f"unknown input {name!r}")
    return rerun(red, start, fringes=fringes, geometry=g, design=design, measured_distance_m=distance,
                 settings=settings, screen=screen, phases=phases, with_curl=False, warm=True)


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
    nominal_corners = expected_corners_px(design, geometry)
    nominal_pose = pose_from_corners(nominal_corners, base.region, base.rays, geometry, design, measured_distance_m,
                                     settings, agreement=base.pose.outline_agreement)
    base = rerun(base, "shape", fringes=fringes, geometry=geometry, design=design,
                 measured_distance_m=measured_distance_m, settings=settings, screen=screen, pose=nominal_pose,
                 with_curl=False)
    f0 = np.array([_value(base.figures, p) for p in SCALAR_PATHS])
    rows = (budget_inputs(inputs, len(reduction.pose.corners_px), four_step_sets(reduction))
            + screen_shape_inputs(screen))
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


def four_step_sets(reduction) -> bool:
    """Whether *reduction*'s capture has four-step fringe sets (whose phase a display response or a frame's
    brightness can shift): a phase stage says so when it has none (``four_step = False``: a fixed pattern's
    one frame)."""
    return bool(getattr(reduction.phases, "four_step", True))


def _value(figures: dict, path: tuple) -> float:
    v = get_path(figures, path)
    return np.nan if v is None else v

def sensitivity_key(geometry, design, fringes, settings, inputs: InputUncertainties, screen=None) -> str:
    """What the sensitivities depend on (geometry, recipe, input uncertainties), as a short hash."""
    blob = {"geometry": geometry.to_dict(), "design": design.to_dict(), "fringes": fringes.to_dict(),
            "settings": {k: v for k, v in settings.to_dict().items() if k != "threads"},
            # Not the record-derived values: the sensitivities are computed at the table's reference
            # values, so a re-analysis without the record (reprocess) finds the station's own.
            "inputs": {k: v for k, v in inputs.to_dict().items() if k not in RECORD_DERIVED_KEYS},
            # A measured screen's shape too (two display models at one pose are different stations).
            "screen": None if screen is None else repr(type(screen)) + (
                f" {screen.fingerprint()}" if hasattr(screen, "fingerprint") else "")}
    return hashlib.sha256(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:16]
