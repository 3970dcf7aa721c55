"""Shape fit nested with the electronic boresight (docs/conventions.md#boresight, #iteration).

The camera/screen assembly, known in the facet frame from the corner pose, is moved rigidly by
R = R_y(beta) R_x(alpha) about the alignment point P_a = (x_a, y_a, z_design(x_a, y_a)) and then by t_z
along z; no x or y translation and no rotation about z (those stay where the corner pose put them).
Four unknowns meet four conditions:

* F (the model's constant) gives the design z at (x_a, y_a);
* t_z keeps the measured distance from the screen centre to the measure point on the model (on a nearly
  flat facet, on the facet's surface: the model plus what it misses there, :func:`close_on_all_points`);
* (alpha, beta) make the fitted parabola's normal at (x_a, y_a) the design normal.

Shape and boresight are iterated alternately: each outer step re-fits the shape to convergence for the
current assembly position, then corrects (alpha, beta) by the angle between fitted and design normals
(rotating the assembly by R_y(beta) lowers every measured atan(s_x) by beta; R_x(alpha) raises
atan(s_y) by alpha), then solves t_z.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import GeometryError
from ..facet import FacetDesign
from ..geometry import Pose
from .fit import ParabolaFit, fit_surface
from .kernels import moved, reflect
from .surface import surface_slopes, surface_z


def rotation_yx(alpha_rad: float, beta_rad: float) -> np.ndarray:
    """R = R_y(beta) @ R_x(alpha)."""
    ca, sa = np.cos(alpha_rad), np.sin(alpha_rad)
    cb, sb = np.cos(beta_rad), np.sin(beta_rad)
    r_x = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    r_y = np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]])
    return r_y @ r_x


@dataclass(frozen=True)
class Assembly:
    """The measurement's geometry in the facet frame: what the boresight moves.

    Attributes
    ----------
    camera_m : (3,) array
        Camera centre, metres.
    rays : (3, N) array
        Unit pixel rays.
    screen_m : (3, N) array
        Screen point seen by each pixel, metres.
    screen_centre_m : (3,) array
        Screen centre (the range finder's origin), metres.
    """

    camera_m: np.ndarray
    rays: np.ndarray
    screen_m: np.ndarray
    screen_centre_m: np.ndarray

    def moved(self, motion: "Motion") -> "Assembly":
        # rays and screen points in one compiled pass each (the same bits as Motion's numpy arithmetic)
        r = motion.rotation
        return Assembly(motion.point(self.camera_m), moved(self.rays, r, motion.pivot_m, 0.0, False),
                        moved(self.screen_m, r, motion.pivot_m, motion.t_z_m, True),
                        motion.point(self.screen_centre_m))


@dataclass(frozen=True)
class Motion:
    """The boresight motion: rotate by R_y(beta) R_x(alpha) about *pivot_m*, then shift by t_z along z."""

    alpha_rad: float
    beta_rad: float
    t_z_m: float
    pivot_m: np.ndarray

    @property
    def rotation(self) -> np.ndarray:
        return rotation_yx(self.alpha_rad, self.beta_rad)

    def vectors(self, v: np.ndarray) -> np.ndarray:
        r = self.rotation
        return np.stack([r[i, 0] * v[0] + r[i, 1] * v[1] + r[i, 2] * v[2] for i in range(3)])

    def points(self, p: np.ndarray) -> np.ndarray:
        q = self.vectors(p - self.pivot_m[:, None]) + self.pivot_m[:, None]
        q[2] += self.t_z_m
        return q

    def point(self, p: np.ndarray) -> np.ndarray:
        return self.points(np.asarray(p, np.float64)[:, None])[:, 0]

    def as_pose(self) -> Pose:
        """The motion as a Pose acting on facet-frame points."""
        r = self.rotation
        return Pose(r, self.pivot_m - r @ self.pivot_m + np.array([0.0, 0.0, self.t_z_m]))


@dataclass(frozen=True)
class ShapeSolution:
    """Converged shape model and assembly position.

    Attributes
    ----------
    coefficients : (6,) array
        (A, B, C, D, E, F) of the parabola the points were last intersected with, E = (E1 + E2)/2: the
        subsample's fit from :func:`solve_shape`, the all-point fit after :func:`close_on_all_points`.
    motion : Motion
    shape_iterations : int
        Shape fits done, over all boresight steps.
    boresight_iterations : int
    converged : bool
    fit : ParabolaFit or None
        The last slope fit on the subsample (with a robust fit's weights and residual scale).
    subsample_coefficients : (6,) array or None
        After :func:`close_on_all_points`: the subsample's converged coefficients (what a program that stops
        at the subsample reports); None before, when they are *coefficients*.
    surface_height_m : float
        After :func:`close_on_all_points` on a nearly flat facet far from the screen: the measured surface's
        height above the model at the measure point, metres (0 otherwise).
    """

    coefficients: np.ndarray
    motion: Motion
    shape_iterations: int
    boresight_iterations: int
    converged: bool
    fit: ParabolaFit | None = None
    subsample_coefficients: np.ndarray | None = None
    surface_height_m: float = 0.0


_IDENTITY = np.eye(3)
_ZERO = np.zeros(3)


def _solve_t_z(assembly: Assembly, rotation_only: Motion, measure_point_m: np.ndarray, distance_m: float) -> float:
    """t_z that puts the moved screen centre *distance_m* from the measure point."""
    w = rotation_only.point(assembly.screen_centre_m) - measure_point_m
    disc = w[2] * w[2] - float(w @ w) + distance_m * distance_m
    if disc < 0:
        raise GeometryError(f"the measured distance {distance_m:.4f} m cannot be met by moving the station along "
                            f"the facet axis (closest approach {np.hypot(w[0], w[1]):.4f} m); re-measure the "
                            "distance or check the facet recipe's measure point")
    roots = (-w[2] + np.sqrt(disc), -w[2] - np.sqrt(disc))
    return float(min(roots, key=abs))


#: Relative change of the mean squared residual at which a robust fit's reweighting stops while the
#: assembly is still being moved (the fits only steer it there), and at the end (the reported fit).
#: Steering at 1e-5 takes about half the reweightings of iterating every fit to 1e-9; the result moves
#: by far less than the loop's own convergence limits (1e-6 in kappa, 1e-6 rad in the boresight).
STEERING_TOLERANCE = 1e-5
FINAL_TOLERANCE = 1e-9


#: The shape's convergence: the relative change of kappa_x and kappa_y between two steps below which the
#: fitted shape no longer changes (:func:`kappa_converged`).
KAPPA_TOLERANCE = 1e-6


def kappa_converged(new: np.ndarray, old: np.ndarray, tolerance: float = KAPPA_TOLERANCE) -> bool:
    """|delta kappa| < *tolerance* max(|kappa|, 1e-3 /m) for both kappa_x = 4A and kappa_y = 4B."""
    dk = 4.0 * np.abs(new[:2] - old[:2])
    return bool(np.all(dk < tolerance * np.maximum(4.0 * np.abs(new[:2]), 1e-3)))


def model_coefficients(fit: ParabolaFit, design: FacetDesign) -> np.ndarray:
    """The fit's (A, B, C, D, E, F), F putting the model at the design height at the alignment point."""
    xa, ya = (float(v) for v in design.alignment_point_m)
    coeffs = fit.coefficients()
    coeffs[5] = float(design.z(xa, ya)) - surface_z(coeffs, xa, ya)
    return coeffs


def _design_turn(coeffs: np.ndarray, design: FacetDesign) -> tuple[float, float]:
    """(d_alpha, d_beta), radians: the turn of the assembly that brings the model's normal at the alignment
    point onto the design's (R_y(beta) lowers every atan(s_x) by beta, R_x(alpha) raises atan(s_y) by alpha)."""
    xa, ya = (float(v) for v in design.alignment_point_m)
    fx, fy = surface_slopes(coeffs, xa, ya)
    dx, dy = (float(v) for v in surface_slopes(design.coefficients, xa, ya))
    return -float(np.arctan(fy) - np.arctan(dy)), float(np.arctan(fx) - np.arctan(dx))


def _t_z_for(assembly: Assembly, alpha: float, beta: float, pivot: np.ndarray, coeffs: np.ndarray,
             design: FacetDesign, distance_m: float, height_m: float = 0.0) -> float:
    """:func:`_solve_t_z` with the assembly turned by (alpha, beta) and the measure point: the model's, raised
    by *height_m* (the facet's own height above the model there)."""
    xm, ym = (float(v) for v in design.measure_point_m)
    return _solve_t_z(assembly, Motion(alpha, beta, 0.0, pivot),
                      np.array([xm, ym, float(surface_z(coeffs, xm, ym)) + float(height_m)]), distance_m)


#: A facet whose design focal power times the squared measured distance is below this (metres) is
#: intersected with its measured surface, not with the model alone (:func:`close_on_all_points`): there a
#: height error of 1 um moves its focal length by more than 1 ppm (delta kappa = 2 dz / D^2). The heliostat
#: facet of f 100 m at 4 m is 0.16 m, at 10 m 1 m; the dish at its centre of curvature 22 m.
SURFACE_HEIGHT_LEVERAGE_M = 2.0
#: The heights a nearly flat facet's slope residuals integrate to are taken as settled when their value at
#: the measure point changes by less than this between two steps, metres.
SURFACE_HEIGHT_TOLERANCE_M = 1e-8
#: The model's constant is moved by this to find how each pixel's slope changes with the height it is
#: intersected at, metres.
HEIGHT_STEP_M = 1e-6


#: A facet whose rays meet it this far off its frame's axis is intersected with its measured surface too
#: (:func:`uses_surface_heights`): the slope error per metre of height error, radians per metre, that the
#: point's shift along its ray gives (the ray's mean inclination to the facet frame's z axis times the
#: design's slope gradient, half its focal power). The population's gore (viewed along its normal 3.75 m off
#: its parent's axis, its rays inclined 0.31 on average in its frame) has 0.03 /m; the dish, viewed on its axis
#: (0.024), 0.002 /m; the heliostat and flat facets 0.001 and 0.0002 /m (the population's stations, measured).
#: At 0.01 /m, 100 um of height above the model moves a slope by 1 urad.
OFF_AXIS_SLOPE_PER_M = 0.01


def uses_surface_heights(design: FacetDesign, distance_m: float, ray_inclination: float = 0.0) -> bool:
    """Whether a facet is intersected with its measured surface: its focal power times the squared distance
    is below :data:`SURFACE_HEIGHT_LEVERAGE_M` (a height error turns the reflection), or its rays'
    mean inclination to the facet frame's z axis (*ray_inclination*, the tangent) times half the design's
    focal power is above :data:`OFF_AXIS_SLOPE_PER_M` (a height error moves the point along its ray,
    sideways across the facet, where the model's slope differs: on the gore the surface's departure from
    its best parabola, tilted 0.3 mrad in y by the fit's uneven twist, sheared the points by 0.1 mm per
    metre and raised the parabola's slope RMS y by 0.005-0.009 mrad on the population's gore stations, whose
    U is 0.002-0.007 there; tests/station/test_gore_surface_heights.py)."""
    f = design.focal_length_m
    power = 0.0 if f is None or not np.isfinite(f) else 1.0 / abs(float(f))
    return bool(power * float(distance_m) ** 2 < SURFACE_HEIGHT_LEVERAGE_M
                or 0.5 * power * float(ray_inclination) > OFF_AXIS_SLOPE_PER_M)


def solve_shape(assembly: Assembly, design: FacetDesign, measured_distance_m: float,
                max_iterations: int = 20, robust: bool = False, pool=None, surface: str = "parabolic") -> ShapeSolution:
    """Iterate shape fit and boresight to convergence (docs/conventions.md#iteration).

    Parameters
    ----------
    assembly : Assembly
        The subsample's geometry in the corner-pose facet frame.
    design : FacetDesign
    measured_distance_m : float
        Screen centre to the measure point, metres.
    max_iterations : int
        Limit for the shape loop inside each boresight step, and for the boresight steps.
    robust : bool
        Bisquare-weighted slope fits (see :func:`~sofast_station.measure.fit.fit_parabola`): their
        reweighting is iterated to :data:`STEERING_TOLERANCE` until the loop converges, then the loop
        runs on with it iterated to :data:`FINAL_TOLERANCE` until it converges again.
    pool : executor, optional
        Where a robust fit's second slope equation runs beside the first (the same bits either way).
    surface : str
        The shape model (:data:`~.fit.SURFACES`): the parabola, or a plane (the design's shape then only
        starts the iteration).
    """
    xa, ya = (float(v) for v in design.alignment_point_m)
    z_align = float(design.z(xa, ya))
    pivot = np.array([xa, ya, z_align])
    coeffs = design.coefficients.copy()
    coeffs[5] = z_align - surface_z(coeffs, xa, ya)
    alpha = beta = t_z = 0.0
    shape_total = 0
    converged = False
    outer = 0
    fit = None
    # A robust fit's weights are iterated loosely while the assembly moves; once the loop has converged
    # it runs once more with the weights iterated to the final tolerance (which then also has to hold).
    tolerance = STEERING_TOLERANCE if robust else FINAL_TOLERANCE
    n = assembly.rays.shape[1]
    pts, slopes = np.empty((3, n)), np.empty((2, n))
    for outer in range(1, max_iterations + 1):
        motion = Motion(alpha, beta, t_z, pivot)
        moved = assembly.moved(motion)
        shape_done = False
        for inner in range(1, max_iterations + 1):
            # intersect_quadratic and normal_slopes in one compiled pass (the same bits)
            reflect(moved.rays, moved.screen_m, _IDENTITY, _ZERO, coeffs, pts, slopes, 0, n, origin=moved.camera_m)
            sx, sy = slopes
            # A robust fit starts from the previous fit's weights: the same points, moved very little.
            fit = fit_surface(surface, pts[0], pts[1], sx, sy, robust=robust, start=fit, pool=pool,
                              robust_tolerance=tolerance)
            new = model_coefficients(fit, design)
            shape_total += 1
            stable = kappa_converged(new, coeffs)
            coeffs = new
            if stable:
                shape_done = True
                break
        d_alpha, d_beta = _design_turn(coeffs, design)
        alpha += d_alpha
        beta += d_beta
        t_z = _t_z_for(assembly, alpha, beta, pivot, coeffs, design, measured_distance_m)
        if shape_done and inner == 1 and max(abs(d_alpha), abs(d_beta)) < 1e-6:
            if tolerance > FINAL_TOLERANCE:
                tolerance = FINAL_TOLERANCE
                continue
            converged = True
            break
    return ShapeSolution(coeffs, Motion(alpha, beta, t_z, pivot), shape_total, outer, converged, fit)


def close_on_all_points(solution: ShapeSolution, design: FacetDesign, measured_distance_m: float,
                        assembly: Assembly, reduce_all, fit_all, max_iterations: int = 20, heights_of=None,
                        raise_all=None, kappa_tolerance: float = KAPPA_TOLERANCE,
                        height_tolerance_m: float = SURFACE_HEIGHT_TOLERANCE_M):
    """The boresight's conditions met by the parabola fitted to every valid pixel, not the subsample's.

    The iteration converges on the subsample (:func:`solve_shape`); the reported parabola is then fitted
    to every pixel, and on a facet that is not a parabola (a gore: its slope residuals against any
    parabola are structured, about 1 mrad) the two fits' normals at the alignment point differ by up to a
    few tenths of a mrad. That tilt is not noise: it moved the frame by as much and the design residual's
    RMS by up to 5 %, outside their U, against the definition's (and the twin's truth's) parabola fitted to
    all the kept pixels. Here shape and boresight go on from the subsample's solution with every
    pixel: ``reduce_all(motion, coefficients)`` intersects every ray with the model in the moved assembly
    (points (3, N), slopes (2, N)); ``fit_all(points, slopes)`` is the reported fit (a ParabolaFit). Each
    step re-fits and turns the assembly by the fitted normal's angle from the design's, then solves t_z,
    until the fitted shape no longer changes (:func:`kappa_converged`) and the turn is below 1 microradian;
    usually two steps.

    **A nearly flat facet far from the screen** (*heights_of* given, :func:`uses_surface_heights`): each
    pixel is intersected with the facet's surface, not the model. The surface departs from the parabola
    by the heights its slope residuals integrate to (0.3 mrad of slope error over 4 cm is 10-15 um, up to
    50 um on the population's heliostat facets), and a pixel intersected that far off gets a slope error
    that grows across the facet (the reflection's directions turn by height / distance): delta kappa =
    2 dz / D^2 about, which a facet of f 100 m at 4 m reads as 125 ppm of f per 10 um. Two parts:
    the range finder measures to the surface, so t_z keeps the distance to the model plus the surface's
    height above it at the measure point (the model through the surface's mean, not through one bump of
    it: f of the f 600 m facet at 3.5 m was 0.24 % short for a 28 um dip under its measure point); and
    each pixel's point and slope are moved to its height above the model, to first order (its slope's
    change per metre of height from a second intersection with the model's constant moved by
    :data:`HEIGHT_STEP_M`). ``heights_of(points, slopes, coefficients)`` returns the heights above the
    model at the points and at the measure point, metres (zero mean over the points).
    ``raise_all(motion, coefficients, points, slopes, scale)``, when given, does the second intersection and
    the move in one: *points* and *slopes* moved in place to ``base + (raised - base) * scale``, numpy's
    arithmetic here (the same bits; :func:`~.kernels.reflect_blend`).

    Parameters
    ----------
    assembly : Assembly
        The subsample's geometry in the corner-pose facet frame (:func:`solve_shape`'s): its screen centre
        places t_z.

    Returns
    -------
    (solution, points_m, slopes, fit)
        The solution with the final motion, the model the points were intersected with and the added
        steps counted in its ``boresight_iterations``; the points and slopes of every pixel in the
        final frame; the fit of those points (the reported parabola, F not yet set).
    """
    motion, coeffs = solution.motion, np.asarray(solution.coefficients, float)
    converged = False
    height = solution.surface_height_m        # the surface's height above the model at the measure point
    for step in range(1, max_iterations + 1):
        points, slopes = reduce_all(motion, coeffs)
        settled = True
        if heights_of is not None:
            at_points, at_measure = heights_of(points, slopes, coeffs)
            raised = coeffs.copy()
            raised[5] += HEIGHT_STEP_M
            scale = at_points / HEIGHT_STEP_M
            if raise_all is not None:
                raise_all(motion, raised, points, slopes, scale)
            else:
                points_up, slopes_up = reduce_all(motion, raised)
                points = points + (points_up - points) * scale
                slopes = slopes + (slopes_up - slopes) * scale
            settled = abs(at_measure - height) < height_tolerance_m
            height = at_measure
        fit = fit_all(points, slopes)
        new = model_coefficients(fit, design)
        d_alpha, d_beta = _design_turn(new, design)
        if max(abs(d_alpha), abs(d_beta)) < 1e-6 and kappa_converged(new, coeffs, kappa_tolerance) and settled:
            converged = True
            break
        if step == max_iterations:           # not converged: keep the frame these points are in
            break
        alpha, beta = motion.alpha_rad + d_alpha, motion.beta_rad + d_beta
        t_z = _t_z_for(assembly, alpha, beta, motion.pivot_m, new, design, measured_distance_m, height)
        motion, coeffs = Motion(alpha, beta, t_z, motion.pivot_m), new
    out = ShapeSolution(coeffs, motion, solution.shape_iterations + step, solution.boresight_iterations + step,
                        solution.converged and converged, solution.fit, np.asarray(solution.coefficients, float),
                        height)
    return out, points, slopes, fit
