"""From captured frames to reported figures: the method paper's data reduction
(docs/conventions.md#data-reduction; Andraka et al. 2009), as named stages of pure functions.

:func:`reduce_stages` runs them all (facet region, phase and unwrapping, screen points and rays, corners
and pose, shape and boresight, fits and figures) and :func:`rerun` redoes them from any stage with one
input changed; :func:`~sofast_station.measure.analysis.analyse` adds the figures' uncertainty and returns
an :class:`Analysis`. They read no file, touch no hardware and keep no state, so a data dump reprocesses
to the same bits.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ..errors import AnalysisError, CaptureError, ConfigError, FacetNotFoundError
from ..facet import FacetDesign
from ..fringes import FringeSet
from ..geometry import Pose, StationGeometry
from . import checks
from . import corners as corners_mod
from . import deblur
from . import rim as rim_mod
from .boresight import (
    Assembly,
    ShapeSolution,
    KAPPA_TOLERANCE,
    SURFACE_HEIGHT_TOLERANCE_M,
    close_on_all_points,
    model_coefficients,
    solve_shape,
    uses_surface_heights,
)
from .camera import pixel_rays, project, to_frame
from .fit import SURFACES, CubicFit, ParabolaFit, fit_cubic, fit_parabola, fit_plane, reweight_parabola
from .heights import height_grid
from .jumps import isolated_jumps
from .kernels import consistency_set, gather_runs, halves, model_residuals, reflect, reflect_blend, to_frame_every
from .mask import facet_region
from .metrics import (focal_length_m, neighbour_difference_ms, neighbour_pairs, principal_axes,
                      principal_curvatures, rms_summary)
from .phase import (
    FrameNoise,
    drawn_error_at,
    drawn_table,
    frame_noise,
    phase_and_modulation,
    phase_error_between_periods,
    pixel_footprint_px,
    position_sigma_m,
    unwrap_positions,
)
from .pose import (departure_from_design_m, fix_range, mask_centroid_px, placement, pose_facing, refine_corner_pose,
                   solve_corner_pose)
from .screen import FlatScreen, InterpolatedScreen, ScreenModel
from .slope_noise import slope_covariance
from .stats import median


@dataclass(frozen=True)
class AnalysisSettings:
    """Thresholds and limits of the analysis (``[analysis]`` in station.toml).

    Attributes
    ----------
    mask_threshold_dn : float
        A pixel belongs to the facet when white - dark exceeds this, DN.
    min_modulation_dn : float
        Pixels whose fringe amplitude b is below this in any set are dropped, DN.
    consistency_sigmas : float
        A pixel fails the I_0 + I_2 = I_1 + I_3 check when the residual exceeds this many of its noise
        standard deviations (2 sigma_I) plus one DN of quantisation allowance.
    guard_sigmas : float
        Screen-edge guard band in units of the finest position noise (>= 4).
    subsample_step : int
        Every n-th valid pixel in raster order is used while iterating.
    max_iterations : int
    max_range_shift_m : float
        Largest accepted disagreement between the corner pose's range and the measured distance, metres.
    corner_tolerance_px : float
        Largest accepted distance of a found corner from its nominal image position, pixels.
    max_hole_px : int
        Holes in the facet region up to this area are filled, pixels.
    max_saturated_fraction : float
        A capture with more of the facet's pixels at the camera's top count than this is refused.
    max_corner_rms_px : float
        Corners farther than this (RMS, pixels) from the design outline under the best pose are refused.
    edge_window_px : int
        Half-width of the window summed across a facet edge to locate it, pixels (smaller for small images).
    robust_fit : bool
        Fit the parabola by bisquare-weighted least squares, so outlying pixels (a facet edge that saw
        past the screen) do not pull the shape; residuals are still reported over every point.
    min_valid_px : int
        A capture with fewer pixels of trusted screen position is refused (a facet too small in the image,
        or a capture without contrast); lower it only for small facets of a heliostat seen whole.
    surface : str
        The shape model fitted to the slopes (:data:`~.fit.SURFACES`): ``"parabolic"`` (the paper's), or
        ``"plano"`` (constant slopes: a flat mirror, or only where a mirror points; its focal lengths and
        twist are not fitted, and are reported as not measured).
    threads : int
        Threads for the independent parts of the analysis (the x and y phases and unwrapping, the fits,
        the residuals of each model). Each part does the same arithmetic on any thread, so the figures
        do not depend on this (docs/conventions.md#determinism); 1 runs everything in the calling thread.
    """

    mask_threshold_dn: float = 20.0
    min_modulation_dn: float = 4.0
    consistency_sigmas: float = 6.0
    guard_sigmas: float = 4.0
    subsample_step: int = 10
    max_iterations: int = 20
    max_range_shift_m: float = 0.25
    corner_tolerance_px: float = 80.0
    max_hole_px: int = 2000
    max_saturated_fraction: float = 0.005
    max_corner_rms_px: float = 2.0
    robust_fit: bool = False
    edge_window_px: int = 5
    threads: int = 2
    surface: str = "parabolic"
    min_valid_px: int = 1000

    def __post_init__(self):
        if self.surface not in SURFACES:
            raise ConfigError(f"[analysis] surface must be one of {', '.join(SURFACES)}, got {self.surface!r}")

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        # (absent at their defaults: settings and hashes from before them)
        if d["surface"] == "parabolic":
            del d["surface"]
        if d["min_valid_px"] == 1000:
            del d["min_valid_px"]
        return d


@dataclass
class Analysis:
    """The result of one analysis: reported figures plus the per-pixel data behind them.

    ``figures`` is JSON-ready (docs/conventions.md#reported-figures); arrays are for plots and re-analysis.
    Per-point arrays follow the raster order of ``valid``; points (3, N) and slopes (2, N) hold their
    components in rows.
    """

    figures: dict
    valid: np.ndarray
    points_facet_m: np.ndarray
    slopes: np.ndarray
    residuals_mrad: dict
    facet_to_camera: Pose
    corners_px: np.ndarray
    coefficients: np.ndarray
    timings_s: dict = field(default_factory=dict)
    #: The uncertainty's sensitivities this analysis used, as a record
    #: (:func:`~sofast_station.measure.sensitivity_record.to_record`), when they were kept in a cache:
    #: what a data dump stores so that re-analysis can reuse them.
    sensitivities: dict | None = None


class _Timer:
    def __init__(self):
        self.timings: dict[str, float] = {}
        self._t = time.perf_counter()

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.timings[name] = self.timings.get(name, 0.0) + (now - self._t)
        self._t = now


class _Serial:
    """Stand-in for a thread pool that runs each task at once in the calling thread."""

    class _Done:
        def __init__(self, value):
            self._value = value

        def result(self):
            return self._value

    def submit(self, fn, *args, **kwargs):
        return self._Done(fn(*args, **kwargs))

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


#: The analyses' thread pools, one per thread count, created on first use and kept for the process (with
#: the process id that made them: a forked child has none of their threads).
_POOLS: dict = {}
_POOLS_LOCK = threading.Lock()


def thread_pool(threads: int):
    """A pool for independent tasks: numpy releases the GIL in its loops, so two threads use two cores.

    A context manager giving the process's pool of *threads* workers, kept from one analysis to the next
    (its threads are started once; leaving the ``with`` does not shut it down). Tasks never wait on other
    tasks of the pool, so analyses in several threads of one process may share it (they queue)."""
    if threads < 1:
        raise ValueError(f"[analysis] threads must be at least 1, got {threads}")
    if threads == 1:
        return _Serial()
    with _POOLS_LOCK:
        pid, pool = _POOLS.get(threads, (None, None))
        if pid != os.getpid():
            pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="analyse")
            _POOLS[threads] = (os.getpid(), pool)
    return contextlib.nullcontext(pool)


def _phase_sets(stack: np.ndarray, sets: list[slice]):
    """Phase, modulation and consistency residual of each four-step set of one axis (gathered pixels)."""
    out = [phase_and_modulation(stack[sl]) for sl in sets]
    return [o[0] for o in out], [o[1] for o in out], [o[2] for o in out]


def outline_image_points(design: FacetDesign, camera, facet_to_camera: Pose, per_side: int = 64) -> np.ndarray:
    """Image points (column, row) along the design outline on the design surface, *per_side* per side."""
    return corners_mod.outline_points_px(design, camera, facet_to_camera, per_side)


@dataclass(frozen=True)
class Region:
    """Stage 1, the facet region: which pixels see the facet lit by the white screen.

    Attributes
    ----------
    region : (rows, columns) bool array
    idx : (M,) int array
        Flat indices (raster order) of the region's pixels; every per-pixel array of the later stages
        follows this order (or a subset of it).
    stack : (n, M) array
        The frames at those pixels, camera counts (DN).
    contrast : (rows, columns) float32 array
        White minus dark, DN (what the corners are found in).
    outline : OutlineFit or None
        The facet's sub-pixel outline (:func:`~sofast_station.measure.corners.fit_outline`), found here
        because the edge's blur it measures decides which pixels the shape may use; None when it could
        not be found (*outline_error* then says why, raised by the corner stage).
    outline_error : Exception or None
    clear_of_edge : (M,) bool array or None
        Which of the region's pixels (``idx`` order) lie far enough inside the outline that none of their
        light comes from beyond it (:func:`~sofast_station.measure.corners.edge_inset_px`); only they may
        be used for the shape. None: no outline.
    lit_rim_sides : tuple of int
        Sides of the outline (the design's numbering from 1) whose rim the design declares dark but whose
        fringes show it lit (:func:`check_dark_rim`); the outline was refitted with those rims put midway.
    points_px : (M, 2) array or None
        Where the region's points are seen when they are not the pixels' centres, (column, row) pixels: a
        fixed pattern's dots (:mod:`~sofast_station.measure.fixed`), one per dot, ``idx`` then the pixel
        each centre lies in. The rays (:func:`screen_points_and_rays`) go through these points; ``stack``
        is None (there are no frames per point).
    """

    region: np.ndarray
    idx: np.ndarray
    stack: np.ndarray | None
    contrast: np.ndarray
    outline: corners_mod.OutlineFit | None = None
    outline_error: Exception | None = None
    clear_of_edge: np.ndarray | None = None
    lit_rim_sides: tuple = ()
    points_px: np.ndarray | None = None


@dataclass(frozen=True)
class Phases:
    """Stage 2, phase and unwrapping: the screen position each region pixel sees, and which pixels to keep.

    Per-pixel arrays follow ``Region.idx``.

    Attributes
    ----------
    positions_m : dict
        ``{"x": (M,), "y": (M,)}`` unwrapped screen positions, metres.
    ok : (M,) bool array
        Pixels with a trusted position in both axes (before the screen model's coverage).
    noise_dn : float
        Per-frame intensity noise the phases see (camera noise and rounding to whole counts), estimated
        from the capture's own four-step consistency residuals, DN.
    noise : FrameNoise or None
        The full estimate: the camera's own noise (rounding removed), the display's residual
        nonlinearity and the phase error it may cause (:func:`~sofast_station.measure.phase.frame_noise`).
    finest_modulation_dn : dict
        ``{"x": (M,), "y": (M,)}`` fringe amplitude of the finest set of each axis, DN.
    min_modulation_dn : (M,) array
        The smallest fringe amplitude over all sets, DN.
    dropped : dict
        Counts of dropped pixels by cause.
    unwrap : dict
        ``{"x": UnwrapResult, "y": UnwrapResult}``.
    set_offsets_dn : dict
        ``{"x": [...], "y": [...]}`` per four-step set, the mean consistency residual I0 + I2 - I1 - I3
        over the consistent pixels, DN: frame-to-frame brightness changes (room light, display), which
        the uncertainty turns into a phase error (:mod:`sofast_station.measure.uncertainty`).
    footprint_px : dict
        ``{"x": (a, b), "y": (a, b)}``: the camera pixels' footprint on the screen along each axis, display
        pixels (:func:`~.phase.pixel_footprint_px`), with which the drawn fringes' correction was seen; empty
        when the fringes do not say how they are drawn.
    roughness_shift_m : dict or None
        ``{"x": (M,), "y": (M,)}``: what a blurring lens's smoothing of the positions' fine structure moved
        each pixel's position by, metres (:func:`~.deblur.roughness_shift_m`), which only the figures' fit
        takes off (:func:`sharpened_fit`); None for a sharp lens.
    """

    positions_m: dict
    ok: np.ndarray
    noise_dn: float
    finest_modulation_dn: dict
    min_modulation_dn: np.ndarray
    dropped: dict
    unwrap: dict
    noise: FrameNoise | None = None
    set_offsets_dn: dict = field(default_factory=dict)
    footprint_px: dict = field(default_factory=dict)
    roughness_shift_m: dict | None = None


@dataclass(frozen=True)
class Rays:
    """Stage 3, screen points and rays in the camera frame for the valid pixels (raster order).

    Attributes
    ----------
    vidx : (N,) int array
        Flat indices of the valid pixels.
    ok : (M,) bool array
        ``Phases.ok`` less the positions the screen model does not cover; ``Region.idx[ok] == vidx``.
    rays : (3, N) array
        Unit pixel rays.
    screen_cam_m : (3, N) array
        Screen point each pixel sees, metres.
    screen_centre_cam_m : (3,) array
        Screen centre (the range finder's origin), metres.
    off_model : int
        Pixels whose screen position the screen model does not cover.
    """

    vidx: np.ndarray
    ok: np.ndarray
    rays: np.ndarray
    screen_cam_m: np.ndarray
    screen_centre_cam_m: np.ndarray
    off_model: int


@dataclass(frozen=True)
class CornerPoseResult:
    """Stage 4, corners and pose: the facet's corners in the image and its pose with the range fixed.

    Attributes
    ----------
    corners_px : (n, 2) array
        Found corners (column, row) in design order.
    reprojection_rms_px : float
    facet_to_camera : Pose
        Corner pose with its range made to agree with the measured distance.
    range_shift_m : float
    outline_agreement : float
    corner_sigma_px : float or None
        Standard uncertainty of each corner coordinate from the scatter of its sides' edge points about
        their fitted curves (3 x RMS / sqrt(points): a quadratic's end point), pixels; None when the
        corners were given.
    corner_cov_px2 : (2n, 2n) array or None
        Covariance of the corners' coordinates (c0 column, c0 row, c1 column, ...) in design order, pixels
        squared, from the sides' fits (:func:`~sofast_station.measure.corners.corner_covariance`); None
        when the corners were given.
    """

    corners_px: np.ndarray
    reprojection_rms_px: float
    facet_to_camera: Pose
    range_shift_m: float
    outline_agreement: float
    corner_sigma_px: float | None = None
    corner_cov_px2: np.ndarray | None = None


@dataclass(frozen=True)
class Shape:
    """Stage 5, shape and boresight: the converged subsample solution and every valid pixel's point and slope
    in the boresighted facet frame.

    Attributes
    ----------
    solution : ShapeSolution
    boresighted_to_camera : Pose
    points_m : (3, N) array
    slopes : (2, N) array
        (s_x, s_y), dimensionless.
    """

    solution: ShapeSolution
    boresighted_to_camera: Pose
    points_m: np.ndarray
    slopes: np.ndarray
    #: The parabola fitted to every point, the reported one (its F not yet set), from the boresight's
    #: closing steps (:func:`~.boresight.close_on_all_points`); None with the subsample only.
    fit: ParabolaFit | None = None


@dataclass(frozen=True)
class Fits:
    """Stage 6a, the all-points fits and the slope residuals of each model.

    Attributes
    ----------
    parabola : ParabolaFit
    coefficients : (6,) array
        Parabola's A..F with F set so the model passes through the design z at the alignment point.
    cubic : CubicFit
    residuals_mrad : dict
        ``{model: (e_x, e_y)}`` slope residuals, mrad.
    """

    parabola: ParabolaFit
    coefficients: np.ndarray
    cubic: CubicFit
    residuals_mrad: dict


def find_region(frames: np.ndarray, fringes: FringeSet, geometry: StationGeometry, design: FacetDesign,
                settings: AnalysisSettings, pool=None, fit_outline: bool = True) -> Region:
    """Stage 1: check the capture and find the facet region from dark and white (refuses what cannot be
    analysed).

    On a *pool*, the frame-order check, the contrast image and half of the frames' gathering run beside
    the rest; a fault of the frame order is still the one reported when several checks fail. *fit_outline*
    False: the caller gives the corners (no outline is fitted)."""
    pool = pool if pool is not None else _Serial()
    cam = geometry.camera
    checks.check_frames(frames, fringes, cam.shape)
    dark, white = frames[0], frames[1]
    order = pool.submit(checks.check_order, frames, fringes, settings.mask_threshold_dn)
    contrast = pool.submit(np.subtract, white, dark, dtype=np.float32)    # white - dark in float32 (exact)
    try:
        checks.check_response(dark, white, settings.mask_threshold_dn)
        region = facet_region(dark, white, settings.mask_threshold_dn, settings.max_hole_px)
        nominal_outline = outline_image_points(design, cam, geometry.fixture_to_camera)
        # (a mirror of unknown outline: its outline_m is only its expected extent, so its area is a guess;
        # the region must still be whole and in view)
        checks.check_region(region, float(np.count_nonzero(checks.projected_outline_mask(cam.shape, nominal_outline))),
                            min_area_fraction=0.5 if design.outline_known else 0.0)
    except Exception:
        order.result()          # frames out of order explain the rest: that is the fault to report
        raise
    order.result()
    idx = np.flatnonzero(region)
    # The outline on a pool thread while the frames are gathered: its edge profiles say how far the
    # lens's blur reaches inside the facet. A mirror of unknown outline has none to fit.
    outline = pool.submit(_outline_of, contrast.result(), region, geometry, design, settings) \
        if design.outline_known and fit_outline else _Serial._Done((None, None))
    flat = frames.reshape(frames.shape[0], -1)
    stack = np.empty((flat.shape[0], idx.size), dtype=flat.dtype)
    half = flat.shape[0] // 2
    # Each half of the frames gathered on its own thread (the same values)
    runs = _runs(idx)
    first = pool.submit(_gather_runs, flat[:half], idx, runs, stack[:half])
    _gather_runs(flat[half:], idx, runs, stack[half:])
    first.result()
    outline, error = outline.result()
    return Region(region=region, idx=idx, stack=stack, contrast=contrast.result(), outline=outline,
                  outline_error=error, clear_of_edge=_clear_of_edge(outline, idx, cam.width_px))


def _clear_of_edge(outline, idx: np.ndarray, width_px: int) -> np.ndarray | None:
    """``Region.clear_of_edge`` of an outline (None without one)."""
    if outline is None:
        return None
    rows, cols = np.divmod(idx, width_px)
    return corners_mod.inside_outline(outline, cols, rows, corners_mod.edge_inset_px(outline.edge_blur_px))


def check_dark_rim(region: Region, phases: Phases, geometry: StationGeometry, design: FacetDesign,
                   settings: AnalysisSettings) -> Region:
    """Stage 2b: does a rim the design declares dark (``FacetDesign.edge_rim_dark``) show the screen?

    The outline was placed the rim's width outside the edge found in the image; where the decoded screen
    positions on that edge jump away from the mirror's beside them (:func:`~.rim.rim_jumps`), the rim is
    lit on that side and the outline is refitted with it put midway, as for a rim of unknown kind (its
    width / sqrt(12) in the corners' U), the sides named in ``lit_rim_sides`` (the verdict warns). The
    region is returned unchanged otherwise."""
    outline = region.outline
    if outline is None or not design.edge_rim_dark or outline.design_sides is None:
        return region
    hints = corners_mod.outline_hints(design, geometry.camera, geometry.fixture_to_camera)
    sides = np.asarray(outline.design_sides)
    shift = np.where(sides >= 0, hints["rim_px"][np.maximum(sides, 0)], 0.0)
    positions = np.vstack([phases.positions_m["x"], phases.positions_m["y"]])
    jumps = rim_mod.rim_jumps(outline, shift, region.region.shape, region.idx, positions, region.contrast)
    flags = rim_mod.lit_rim_flags(jumps) & (sides >= 0)      # a side matched to no design side has no rim
    if not flags.any():
        return region
    lit = rim_mod.lit_rim_sides(jumps[flags], sides[flags])
    dark = np.ones(len(design.outline_m), dtype=bool)
    dark[sides[flags]] = False
    refit = corners_mod.fit_outline(region.contrast, region.region, len(design.outline_m), settings.edge_window_px,
                                    **{**hints, "rim_dark": dark})
    return dataclasses.replace(region, outline=refit, lit_rim_sides=tuple(lit),
                               clear_of_edge=_clear_of_edge(refit, region.idx, geometry.camera.width_px))


def _outline_of(contrast: np.ndarray, region: np.ndarray, geometry: StationGeometry, design: FacetDesign,
                settings: AnalysisSettings) -> tuple:
    """(outline, None), or (None, the error) when the facet's outline cannot be found: that is reported by
    the corner stage, after the phase stage's checks, as before the outline moved into stage 1."""
    try:
        return corners_mod.fit_outline(contrast, region, len(design.outline_m), settings.edge_window_px,
                                       **corners_mod.outline_hints(design, geometry.camera,
                                                                   geometry.fixture_to_camera)), None
    except FacetNotFoundError as exc:
        return None, exc


def _runs(idx: np.ndarray) -> tuple[list, list]:
    """Where the sorted flat indices *idx* run on without a gap: (starts, ends) in *idx*, as lists."""
    if idx.size == 0:
        return [], []
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    return [0, *breaks.tolist()], [*breaks.tolist(), int(idx.size)]


def _gather_runs(flat: np.ndarray, idx: np.ndarray, runs: tuple[list, list], out: np.ndarray) -> None:
    """``out[:] = flat[:, idx]`` copied run by run: a facet's pixels are a few hundred runs of whole row
    segments (:func:`~.kernels.gather_runs`: compiled, without the GIL, so the two halves of the frames
    are copied at once; a Python loop of slice copies held the GIL between its hundreds of small copies)."""
    gather_runs(flat, idx, runs, out)


def measure_phases(region: Region, fringes: FringeSet, screen_size_m: tuple[float, float],
                   settings: AnalysisSettings, pixel_mask: np.ndarray | None = None, pool=None) -> Phases:
    """Stage 2: phase, modulation, consistency and unwrapping of the region's pixels.

    *screen_size_m* is the displayed area's (width, height), metres; *pixel_mask* (rows, columns) limits
    the pixels that may be used for the shape. Without one, the pixels within the edge's blur
    (``Region.clear_of_edge``) are left out; with one, the mask alone decides.
    """
    pool = pool if pool is not None else _Serial()
    idx, stack = region.idx, region.stack
    if pixel_mask is not None and pixel_mask.shape != region.region.shape:
        raise CaptureError(f"pixel_mask has shape {pixel_mask.shape}, expected the camera's {region.region.shape}")
    checks.check_saturation(stack, settings.max_saturated_fraction)
    slices = fringes.slices()
    tasks = {axis: pool.submit(_phase_sets, stack, slices[axis]) for axis in ("x", "y")}
    checks.check_repeats(stack, fringes)
    raw = {axis: task.result() for axis, task in tasks.items()}
    # Noise and display nonlinearity from the four-step residuals; the consistency check then sees the
    # residuals without the harmonic a nonlinear display adds (that is judged on its own, in the verdict).
    noise = frame_noise(*([*raw["x"][i], *raw["y"][i]] for i in range(3)),
                        level=np.subtract(stack[1], stack[0], dtype=np.float32), pool=pool)
    noise_dn = noise.frame_noise_dn
    n_x = len(raw["x"][2])
    cleaned = {"x": noise.residuals[:n_x], "y": noise.residuals[n_x:]}
    lengths = {"x": screen_size_m[0], "y": screen_size_m[1]}

    sigma = {}                          # each axis's finest position noise, metres: the guard band's, the faults'

    def unwrap_axis(axis):
        periods = getattr(fringes, f"periods_{axis}")
        sigma[axis] = position_sigma_m(raw[axis][1][-1], noise_dn, periods[-1], lengths[axis])
        return unwrap_positions(raw[axis][0], periods, lengths[axis], sigma[axis], settings.guard_sigmas)

    # Unwrapping needs only the phases and the noise: it runs on the pool while the consistency check
    # and the modulation limit go over the sets here.
    tasks = {axis: pool.submit(unwrap_axis, axis) for axis in ("x", "y")}
    ok = np.ones(idx.size, dtype=bool)
    min_mod = np.full(idx.size, np.inf)
    inconsistent = np.zeros(idx.size, dtype=bool)
    cons_limit = settings.consistency_sigmas * 2.0 * noise_dn + 1.0
    inconsistent_fraction = {}
    offsets: dict = {"x": [], "y": []}
    for axis in ("x", "y"):
        for p, b, r, r_raw in zip(getattr(fringes, f"periods_{axis}"), raw[axis][1], cleaned[axis], raw[axis][2]):
            # the modulation limit, |r| > limit, and the mean raw residual of the consistent pixels (before
            # the fitted offsets are removed: they are what is measured here), in one compiled pass
            n_bad, good_sum = consistency_set(b, r, r_raw, cons_limit, min_mod, inconsistent)
            inconsistent_fraction[f"{axis} p={p:g}"] = float(n_bad) / idx.size
            n_good = idx.size - n_bad
            offsets[axis].append(good_sum / n_good if n_good else 0.0)
    low_mod = min_mod < settings.min_modulation_dn
    ok &= ~low_mod & ~inconsistent
    excluded = 0
    if pixel_mask is not None:
        allowed = pixel_mask.ravel()[idx]
        excluded = int(np.count_nonzero(ok & ~allowed))
        ok &= allowed
    near_edge = 0
    if region.clear_of_edge is not None and pixel_mask is None:
        # pixels within the blur of the facet's edge see light from both sides of it: left out (a caller's
        # own pixel mask, e.g. another program's pixels for a like-with-like comparison, decides alone)
        near_edge = int(np.count_nonzero(~region.clear_of_edge))
        ok &= region.clear_of_edge
    positions, unwrap_stats = {}, {}
    for axis, task in tasks.items():
        res = task.result()
        positions[axis] = res.position_m
        unwrap_stats[axis] = res
        ok &= res.valid
    checks.check_phase_sets(inconsistent_fraction,
                            {a: unwrap_stats[a].disagreements / idx.size for a in ("x", "y")})
    # The response's phase error as the coarse and fine sets show it (any shape of response), where they can.
    # Each set's error as the display draws it (the fringes' rounding), where the station's record says it, as
    # the camera's pixels see it: each averages the display over its footprint on the screen.
    footprint = {}
    if fringes.drawn:
        footprint = pixel_footprint_px(region.region.shape, idx, ok, positions, dict(zip("xy", fringes.drawn[3:5])),
                                       lengths)
    drawn = {a: (drawn_table(fringes, a, getattr(fringes, f"periods_{a}")[0], footprint),
                 drawn_table(fringes, a, getattr(fringes, f"periods_{a}")[-1], footprint)) for a in ("x", "y")}
    known = all(t is not None for a in ("x", "y") for t in drawn[a])
    measured = phase_error_between_periods(
        [(raw[a][0][0], raw[a][0][-1], raw[a][1][0], raw[a][1][-1], getattr(fringes, f"periods_{a}")[0],
          getattr(fringes, f"periods_{a}")[-1], *((drawn[a],) if known else ())) for a in ("x", "y")],
        noise_dn, mask=[ok, ok], pool=pool)
    noise = noise.with_period_error(measured)
    if known and measured is not None:
        positions = {a: corrected_positions(positions[a], raw[a][0][-1], measured, drawn[a][1],
                                            getattr(fringes, f"periods_{a}")[-1], lengths[a]) for a in ("x", "y")}
    # a pixel whose position leaps from all its neighbours' (a wrong fringe order on the rim) is no surface
    jumps = isolated_jumps(region.region.shape, idx, ok, positions, sigma)
    ok &= ~jumps
    # a lens that blurs the facet's edge blurs the fringes too: the positions' first-order shift taken off
    blur = region.outline.edge_blur_px if region.outline is not None else 0.0
    roughness = None
    if blur >= deblur.MIN_BLUR_PX:
        rows, cols = np.divmod(idx, region.region.shape[1])
        positions = {a: positions[a] - deblur.blur_shift_m(cols, rows, ok, positions[a], raw[a][1][-1], blur)
                     for a in ("x", "y")}
        # and what it smoothed of their fine structure, for the figures' fit alone (sharpened_fit)
        roughness = {a: deblur.roughness_shift_m(cols, rows, ok, positions[a], blur) for a in ("x", "y")}
    dropped = {"low_modulation": int(low_mod.sum()), "inconsistent_frames": int(inconsistent.sum()),
               "excluded_by_pixel_mask": excluded, "near_edge": near_edge, "isolated_jump": int(jumps.sum())}
    return Phases(positions_m=positions, ok=ok, noise_dn=noise_dn,
                  finest_modulation_dn={a: raw[a][1][-1] for a in ("x", "y")}, min_modulation_dn=min_mod,
                  dropped=dropped, unwrap=unwrap_stats, noise=noise,
                  set_offsets_dn=offsets, footprint_px=footprint, roughness_shift_m=roughness)


def corrected_positions(position_m: np.ndarray, fine_phase_rad: np.ndarray, measured, drawn_table,
                        fine_periods: float, length_m: float) -> np.ndarray:
    """Screen positions with the four-step phase's known errors taken out (metres along one axis).

    The position comes from the finest phase, so a phase error e(phi_f) moves it by L e / (2 pi p_f): a
    ripple along the screen with a quarter of the finest period and its multiples. Two parts, both fixed
    functions of the phase: the fringes' rounding to whole 8-bit commands as the display draws them
    (*drawn_table*, :func:`~.phase.drawn_phase_error`, from the station's radiometric record), and what a
    response not quite linearised adds (a gamma missed, a camera's knee), which the coarse and fine sets
    measure once the drawn part is taken off their disagreement (*measured*,
    :func:`~.phase.phase_error_between_periods`). The ripple's projection on a straight line over the screen
    patch a facet reflects is a scale error of the positions, which a nearly flat facet far from the screen
    reads as focal power: f of the 1.2 m heliostat facet at 10 m was 50-110 ppm off with the ripple left in
    (issue 47; docs/method.md, "Nearly flat facets far from the screen").
    """
    e = measured.error_at(fine_phase_rad) + drawn_error_at(drawn_table, fine_phase_rad)
    return position_m - (length_m / (2.0 * np.pi * float(fine_periods))) * e


def screen_points_and_rays(region: Region, phases: Phases, camera, screen: ScreenModel,
                           rays_cam: np.ndarray | None = None, pool=None, min_valid_px: int = 1000) -> Rays:
    """Stage 3: screen points and pixel rays in the camera frame for the pixels with a trusted position.

    A region whose points are not pixel centres (``Region.points_px``: a fixed pattern's dots) has each
    point's ray computed through the camera model at its own sub-pixel position (*rays_cam* is not used).
    A measured screen model may not cover every position; those pixels are dropped. On a *pool*, the
    pixel rays and half of the screen points are formed beside the other half: each point and each ray
    on its own, and the points in the same two halves on one thread or two, so the same values.
    """
    pool = pool if pool is not None else _Serial()
    ok = phases.ok.copy()
    idx = region.idx
    points_px = getattr(region, "points_px", None)
    if points_px is not None:
        # points seen between pixel centres (a fixed pattern's dots): their own rays, through the camera model
        rays_cam = None
        rays_task = pool.submit(pixel_rays, camera, points_px[ok, 0], points_px[ok, 1])
        table = True
    else:
        table = rays_cam is None or (hasattr(rays_cam, "take") and not isinstance(rays_cam, np.ndarray))
        rays_task = pool.submit(_rays_of, camera, rays_cam, idx[ok]) if table else None
    u_x, u_y = phases.positions_m["x"][ok], phases.positions_m["y"][ok]
    half = u_x.size // 2
    first = pool.submit(screen.points_camera, u_x[:half], u_y[:half])
    screen_cam = np.concatenate([first.result(), screen.points_camera(u_x[half:], u_y[half:])], axis=1)
    covered = np.all(np.isfinite(screen_cam), axis=0)
    off_model = int(np.count_nonzero(~covered))
    if off_model:
        ok[np.flatnonzero(ok)[~covered]] = False
        screen_cam = screen_cam[:, covered]
    vidx = idx[ok]
    if vidx.size < min_valid_px:
        raise AnalysisError(f"only {vidx.size} pixels have a valid screen position (of {idx.size} facet "
                            "pixels); check fringe contrast, exposure and the display")
    if table:
        rays = rays_task.result()
        if off_model:
            rays = rays[:, covered]
    else:
        if rays_cam.shape != (3, *camera.shape):
            raise CaptureError(f"precomputed rays have shape {rays_cam.shape}, expected {(3, *camera.shape)}")
        rays = rays_cam.reshape(3, -1)[:, vidx]
    return Rays(vidx=vidx, ok=ok, rays=rays, screen_cam_m=screen_cam, screen_centre_cam_m=screen.centre_camera(),
                off_model=off_model)


def _rays_of(camera, table, vidx: np.ndarray) -> np.ndarray:
    """(3, N) unit rays of the flat pixel indices *vidx*: from the ray *table* (a RayTable) or computed."""
    if table is None:
        rows, cols = np.divmod(vidx, camera.width_px)
        return pixel_rays(camera, cols, rows)
    return table.take(vidx)


def corners_and_pose(region: Region, rays: Rays, geometry: StationGeometry, design: FacetDesign,
                     measured_distance_m: float, settings: AnalysisSettings,
                     pixel_mask: np.ndarray | None = None, corners_px: np.ndarray | None = None,
                     corner_sigma_px: float | None = None) -> CornerPoseResult:
    """Stage 4: the facet's corners in the image, its pose from them, and the pose's range fixed by the
    measured distance.

    A mirror of unknown outline is placed by its lit region's centroid, or with *pixel_mask* (the pixels the
    caller allows, e.g. another program's for a like-with-like comparison) by the centroid of the region's
    pixels it allows: the pixels measured are then the mirror. *corners_px* ((n, 2), design order) are
    corners the caller found otherwise (a heliostat's facet whose own edges are not seen, placed by the
    heliostat's outline), standard uncertainty *corner_sigma_px* per coordinate."""
    cam = geometry.camera
    if corners_px is not None:
        result = pose_from_corners(np.asarray(corners_px, np.float64), region, rays, geometry, design,
                                   measured_distance_m, settings)
        return dataclasses.replace(result, corner_sigma_px=corner_sigma_px)
    if not design.outline_known:
        # a mirror of unknown outline is placed by its lit region's centroid (pose_from_corners)
        lit = region.region if pixel_mask is None else region.region & pixel_mask
        centroid, cov = mask_centroid_px(lit)
        result = pose_from_corners(centroid[None, :], region, rays, geometry, design, measured_distance_m, settings)
        return dataclasses.replace(result, corner_sigma_px=float(np.sqrt(0.5 * np.trace(cov))), corner_cov_px2=cov)
    if region.outline is None:
        raise region.outline_error if region.outline_error is not None else \
            FacetNotFoundError("no facet outline was fitted")
    outline = region.outline
    corners_3d = design.corners_3d()
    expected = project(cam, geometry.fixture_to_camera, corners_3d)
    found = corners_mod.match_corners(outline.corners_px, expected, settings.corner_tolerance_px)
    result = pose_from_corners(found, region, rays, geometry, design, measured_distance_m, settings)
    sigma = 3.0 * np.asarray(outline.edge_rms_px, float) / np.sqrt(np.maximum(outline.n_edge_points, 1))
    cov = None
    if outline.corner_cov_px2 is not None:
        order = [int(np.flatnonzero(np.all(outline.corners_px == f, axis=1))[0]) for f in found]
        idx = np.array([[2 * j, 2 * j + 1] for j in order]).ravel()
        cov = outline.corner_cov_px2[np.ix_(idx, idx)]
    return dataclasses.replace(result, corner_sigma_px=float(np.median(sigma)), corner_cov_px2=cov)


def expected_corners_px(design: FacetDesign, geometry: StationGeometry) -> np.ndarray:
    """Where the fixture's nominal pose puts the design's corners in the image, (n, 2) pixels; for a mirror of
    unknown outline its one "corner", the middle of its frame (:func:`pose_from_corners`)."""
    points = design.corners_3d() if design.outline_known else np.zeros((1, 3))
    return project(geometry.camera, geometry.fixture_to_camera, points)


def pose_from_corners(found: np.ndarray, region: Region, rays: Rays, geometry: StationGeometry,
                      design: FacetDesign, measured_distance_m: float,
                      settings: AnalysisSettings, agreement: float | None = None) -> CornerPoseResult:
    """Stage 4b: the pose from found corners (column, row) in design order, with its range fixed.

    The outline's agreement with the region is measured unless *agreement* is given (a rerun that
    changes no pixel).

    A mirror of unknown outline (``design.outline_known`` False) has one "corner", the lit region's centroid
    (:func:`~.pose.mask_centroid_px`): its frame is placed there at the measured distance, facing camera
    and screen (:func:`~.pose.pose_facing`); the range then needs no correction, and there is no outline to
    agree with (``outline_agreement`` None)."""
    cam = geometry.camera
    if not design.outline_known:
        pose = pose_facing(cam, found[0], rays.screen_centre_cam_m, measured_distance_m)
        return CornerPoseResult(corners_px=np.asarray(found, np.float64), reprojection_rms_px=0.0,
                                facet_to_camera=pose, range_shift_m=0.0, outline_agreement=None)
    corners_3d = design.corners_3d()
    corner_pose = solve_corner_pose(cam, found, corners_3d, geometry.fixture_to_camera)
    if corner_pose.reprojection_rms_px > settings.max_corner_rms_px:
        raise FacetNotFoundError(
            f"the corners found in the mask do not fit the design outline ({corner_pose.reprojection_rms_px:.1f} px "
            "RMS): the facet is partly lit or obstructed, or it is not the recipe's facet type")
    measure_point = np.array([*design.measure_point_m, float(design.z(*design.measure_point_m))])
    facet_to_camera, range_shift = fix_range(corner_pose.facet_to_camera, measure_point, rays.screen_centre_cam_m,
                                             measured_distance_m, settings.max_range_shift_m)
    if agreement is None:
        agreement = checks.outline_agreement(region.region, outline_image_points(design, cam, facet_to_camera))
    return CornerPoseResult(corners_px=found, reprojection_rms_px=corner_pose.reprojection_rms_px,
                            facet_to_camera=facet_to_camera, range_shift_m=range_shift, outline_agreement=agreement)


def shape_and_boresight(rays: Rays, pose: CornerPoseResult, design: FacetDesign, measured_distance_m: float,
                        settings: AnalysisSettings, pool=None, timer=None, subsample_only: bool = False,
                        start=None, kappa_tolerance: float = KAPPA_TOLERANCE,
                        height_tolerance_m: float = SURFACE_HEIGHT_TOLERANCE_M) -> Shape:
    """Stage 5: shape and boresight iterated on the subsample, then every valid pixel's point and slope in
    the boresighted facet frame. *subsample_only*: stop after the subsample (the converged solution and the
    boresighted frame; ``points_m`` and ``slopes`` None), for a caller that only needs where the facet
    points before it reduces every pixel (a heliostat's first pass, :mod:`~sofast_station.measure.heliostat`).
    *start*: a converged :class:`~.boresight.ShapeSolution` of nearly the same capture (its corner pose or
    camera moved a little, as the uncertainty's reruns move them): the subsample's iteration is skipped and
    the all-pixel one (:func:`~.boresight.close_on_all_points`, the same convergence tests) starts from
    *start*'s motion and model; the solution's subsample coefficients stay *start*'s."""
    pool = pool if pool is not None else _Serial()
    camera_to_facet = pose.facet_to_camera.inverse()
    step = settings.subsample_step
    # every step-th ray and screen point, gathered and taken into the facet frame in one compiled pass each
    subsample = Assembly(camera_to_facet.translation,
                         to_frame_every(rays.rays, camera_to_facet.rotation, camera_to_facet.translation, step,
                                        translate=False),
                         to_frame_every(rays.screen_cam_m, camera_to_facet.rotation, camera_to_facet.translation,
                                        step),
                         to_frame(camera_to_facet, rays.screen_centre_cam_m[:, None])[:, 0])
    if start is None:
        solution = solve_shape(subsample, design, measured_distance_m, settings.max_iterations,
                               robust=settings.robust_fit, pool=pool if settings.robust_fit else None,
                               surface=settings.surface)
    else:                                 # nearly there already: on to every pixel from where *start* ended
        solution = dataclasses.replace(start, shape_iterations=0, boresight_iterations=0)
    if timer is not None:
        timer.lap("iterate")
    # Every valid pixel, taken from the camera frame straight into the boresighted facet frame, in one
    # compiled pass (element-wise, half of the points on the pool: the same bits as numpy's chain).
    if subsample_only:
        to_moved = solution.motion.as_pose().compose(camera_to_facet)
        return Shape(solution=solution, boresighted_to_camera=to_moved.inverse(), points_m=None, slopes=None)
    n = rays.rays.shape[1]
    # without a pool, one kernel call per step, not two halves in turn (the uncertainty's reruns: the same values)
    split = None if isinstance(pool, _Serial) else pool

    def frame(motion):
        # motion.as_pose().compose(camera_to_facet)'s rotation and translation, the same arithmetic without
        # the two Poses' checks (twice a step, 60 steps per capture in the uncertainty's reruns)
        r = motion.rotation
        shift = motion.pivot_m - r @ motion.pivot_m + np.array([0.0, 0.0, motion.t_z_m])
        return r @ camera_to_facet.rotation, r @ camera_to_facet.translation + shift

    def reduce_all(motion, coefficients):
        points, slopes = np.empty((3, n)), np.empty((2, n))
        halves(split, reflect, n, rays.rays, rays.screen_cam_m, *frame(motion), coefficients, points, slopes)
        finite = np.isfinite(slopes[0]) & np.isfinite(slopes[1])
        if not np.all(finite):
            raise AnalysisError(f"{int((~finite).sum())} pixel rays miss the fitted surface; the fit diverged")
        return points, slopes

    def raise_all(motion, coefficients, points, slopes, scale):
        # reduce_all's intersection with *coefficients*, each pixel's point and slope moved toward it in place
        # (close_on_all_points' first-order move to its height), in one compiled pass per half
        missed = sum(halves(split, reflect_blend, n, rays.rays, rays.screen_cam_m, *frame(motion), coefficients,
                            scale, points, slopes))
        if missed:
            raise AnalysisError(f"{missed} pixel rays miss the fitted surface; the fit diverged")

    heights_of = None
    r = subsample.rays
    inclination = float(np.mean(np.hypot(r[0], r[1]) / np.maximum(np.abs(r[2]), 1e-12))) if r.shape[1] else 0.0
    if uses_surface_heights(design, measured_distance_m, inclination) and settings.surface == "parabolic":
        def heights_of(p, s, c):
            return surface_heights(p, s, c, design)
    solution, points, slopes, fit = close_on_all_points(
        solution, design, measured_distance_m, subsample, reduce_all,
        lambda p, s: all_points_parabola(p, s, solution.fit, settings, pool), settings.max_iterations,
        heights_of=heights_of, raise_all=raise_all, kappa_tolerance=kappa_tolerance,
        height_tolerance_m=height_tolerance_m)
    if start is not None:
        solution = dataclasses.replace(solution, subsample_coefficients=start.subsample_coefficients)
    to_moved = solution.motion.as_pose().compose(camera_to_facet)
    return Shape(solution=solution, boresighted_to_camera=to_moved.inverse(), points_m=points, slopes=slopes,
                 fit=fit)


#: Points :func:`surface_heights` integrates at most (every k-th of the facet's valid pixels), and about
#: how many of them each grid cell gets: with fewer the grid is coarser (empty cells carry the heights on
#: flat, which biases them); a camera's pixel lattice leaves no cell empty from 2 a cell (a cell of 1.4
#: pitches), and 2.5 keeps a margin for a lattice turned and foreshortened on the facet.
HEIGHT_POINTS = 60_000
HEIGHT_POINTS_PER_CELL = 2.5
#: The most cells along the facet: 144 on the population's heliostat (1.2 m, 47,500 pixels, 8.3 mm cells).
HEIGHT_CELLS = 144


def surface_heights(points: np.ndarray, slopes: np.ndarray, coefficients: np.ndarray,
                    design: FacetDesign) -> tuple[np.ndarray, float]:
    """The facet's heights above the model *coefficients*: at every point (N,) and at the design's measure
    point, metres, with zero mean over the points. The slope residuals of at most :data:`HEIGHT_POINTS`
    points integrate to them on a grid (:func:`~.heights.height_grid`, each cell's mean slope moved to its
    centre) of up to :data:`HEIGHT_CELLS` cells along the facet and about :data:`HEIGHT_POINTS_PER_CELL`
    points per cell, read at each point by bilinear interpolation.

    On seed 0's 13 population heliostat stations (f 100 m at 10 m, 0.2-0.6 mrad of slope error of 2-6 cm
    correlation; noise-free frames the camera did not round, the twin's true screen positions and pose), f was
    12.6 ppm RMS and up to 51 ppm off like-for-like truth with 96 cells of uncentred means; 3.5 and 10.2 ppm with
    these (docs/method.md)."""
    x, y = points[0], points[1]
    step = max(1, x.size // HEIGHT_POINTS)
    cells = int(min(HEIGHT_CELLS, max(8, np.sqrt(x.size / step / HEIGHT_POINTS_PER_CELL))))
    # the slope residuals from the model formed as they are gridded (surface_slopes' arithmetic, one pass)
    grid = height_grid(x[::step], y[::step], slopes[0, ::step], slopes[1, ::step], cells=cells, model=coefficients)
    at_points = grid.at(x, y)
    mean = float(np.sum(at_points) / at_points.size)
    at_points -= mean
    xm, ym = (float(v) for v in design.measure_point_m)
    return at_points, float(grid.at(xm, ym)) - mean


def all_points_parabola(points: np.ndarray, slopes: np.ndarray, subsample_fit, settings: AnalysisSettings, pool=None):
    """The reported parabola fitted to every valid pixel: plain, or for a robust analysis one Newton step of
    the bisquare estimate from the subsample's converged robust fit (:func:`~.fit.reweight_parabola`)."""
    x, y, s_x, s_y = points[0], points[1], slopes[0], slopes[1]
    if settings.surface == "plano":
        return fit_plane(x, y, s_x, s_y, robust=settings.robust_fit)
    return (reweight_parabola(x, y, s_x, s_y, subsample_fit, pool=pool) if settings.robust_fit
            else fit_parabola(x, y, s_x, s_y))


def fit_models(shape: Shape, design: FacetDesign, pool=None) -> Fits:
    """Stage 6a: the all-points parabola (the boresight's closing fit, ``shape.fit``, its F through the
    design z at the alignment point) and the cubic, and the slope residuals against design, parabola and
    cubic."""
    pool = pool if pool is not None else _Serial()
    x, y = shape.points_m[0], shape.points_m[1]
    s_x, s_y = shape.slopes[0], shape.slopes[1]
    cubic_task = pool.submit(fit_cubic, x, y, s_x, s_y)
    fit = shape.fit
    coeffs = model_coefficients(fit, design)
    cubic = cubic_task.result()
    # Every model's residuals in one compiled pass over the points (half of them on the pool).
    e = np.empty((6, x.size))
    halves(pool, model_residuals, x.size, x, y, s_x, s_y,
           [design.coefficients, coeffs], [cubic.x0, cubic.y0, cubic.h, *np.concatenate(cubic.slope_coefficients())],
           e)
    residuals = {"design": e[0:2], "parabola": e[2:4], "higher_order": e[4:6]}
    return Fits(parabola=fit, coefficients=coeffs, cubic=cubic, residuals_mrad=residuals)


#: The parabola's figures the blur's sharpening corrects (:func:`sharpened_fit`), dotted paths: every scalar of
#: :func:`parabola_figures` but the axis angle (a difference of curvatures' direction, which the correction's
#: size does not bound).
SHARPENED_PATHS = ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
                   "twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m.0",
                   "principal_focal_lengths_m.1", "principal_curvatures_per_m.0", "principal_curvatures_per_m.1")


def figure_at(figures: dict, path: str):
    """The figure at dotted *path* of :data:`SHARPENED_PATHS`' form (``"principal_focal_lengths_m.0"``: a list's
    element), or None."""
    head, *rest = path.split(".")
    v = figures.get(head)
    return v[int(rest[0])] if rest and isinstance(v, (list, tuple)) else v


def sharpened_fit(reduction: Reduction, *, geometry: StationGeometry, design: FacetDesign,
                  measured_distance_m: float, settings: AnalysisSettings, screen: ScreenModel | None = None,
                  pool=None) -> Reduction:
    """*reduction* with its parabola's figures fitted to the positions with the blur's smoothing of their fine
    structure taken off (``Phases.roughness_shift_m``, :func:`~.deblur.roughness_shift_m`), and what that
    moved each of :data:`SHARPENED_PATHS` by in ``figures["lens_blur_sharpening"]`` (figure units); unchanged
    for a sharp lens, a plano analysis or an unfinished reduction.

    Only the fit sees the sharpened positions: the shape stage's all-points closing reruns from the
    reduction's own solution with the same pixels, corner pose and rays, each pixel's screen point moved
    (a point the screen model does not cover moved keeps its own). The slope residuals, their maps and RMS keep
    the positions as measured, whose noise the sharpening would multiply by about 1 + 2 sigma^2.

    On seed 0's blurred heliostat stations (34: Gaussian, 0.65 px; 42: defocused, 0.79 px; f 100 m at 4 m, seven
    drawn facets each, noise-free unrounded frames) f was 45 and 83 ppm RMS from the like-for-like truth
    without it and 21 and 33 with it. What it leaves, about half the correction's size (RMS over those 28 values),
    the budget carries as a row (:func:`~.analysis.add_sharpening_row`; docs/method.md)."""
    shift = getattr(reduction.phases, "roughness_shift_m", None)
    shape = reduction.shape
    if shift is None or settings.surface != "parabolic" or shape is None or shape.points_m is None \
            or reduction.figures is None:
        return reduction
    pool = pool if pool is not None else _Serial()
    screen = screen if screen is not None else default_screen(geometry)
    rays, ok = reduction.rays, reduction.rays.ok          # the pixels the screen model covers: rays.vidx
    moved = screen.points_camera(reduction.phases.positions_m["x"][ok] - shift["x"][ok],
                                 reduction.phases.positions_m["y"][ok] - shift["y"][ok])
    moved = np.where(np.isfinite(moved), moved, rays.screen_cam_m)
    sharp = shape_and_boresight(dataclasses.replace(rays, screen_cam_m=moved), reduction.pose, design,
                                measured_distance_m, settings, pool, start=shape.solution)
    plain, sharpened = reduction.figures, parabola_figures(sharp.fit)     # plain: report_figures' parabola_figures
    moved = {path: (figure_at(sharpened, path), figure_at(plain, path)) for path in SHARPENED_PATHS}
    figures = {**plain, **sharpened, "coefficients": dict(zip("ABCDEF", model_coefficients(sharp.fit, design))),
               "lens_blur_sharpening": {path: None if a is None or b is None else float(a - b)
                                        for path, (a, b) in moved.items()}}
    return dataclasses.replace(reduction, figures=figures)


#: The cubic :func:`quadratic_residuals` gives :func:`~.kernels.model_residuals` (no slope, unit scale): its
#: rows are not read.
_NO_CUBIC = np.array([0.0, 0.0, 1.0] + [0.0] * 12)


def quadratic_residuals(shape: Shape, design: FacetDesign) -> dict:
    """:func:`fit_models`' slope residuals against the design and the all-points parabola alone (the same
    bits; mrad, ``{model: (2, N)}``), without the cubic's fit: what the uncertainty's shape reruns read."""
    x, y = shape.points_m[0], shape.points_m[1]
    e = np.empty((6, x.size))
    model_residuals(x, y, shape.slopes[0], shape.slopes[1],
                    [design.coefficients, model_coefficients(shape.fit, design)], _NO_CUBIC, e, 0, x.size)
    return {"design": e[0:2], "parabola": e[2:4]}


def pose_on_measured_surface(pose: CornerPoseResult, fits: Fits, rays: Rays, geometry: StationGeometry,
                             design: FacetDesign, measured_distance_m: float, settings: AnalysisSettings) -> Pose:
    """The corner pose again (range fixed), with the design's corners and measure point lifted onto the
    measured surface (the higher-order model): the facet frame in which that surface touches the design at
    the outline's centroid (:func:`~.pose.departure_from_design_m`), the frame ``placement`` and
    ``boresight_mrad`` are stated in.

    The corners alone cannot tell a facet's twist or curvature from its tilt: on the gore, turned 20 mrad
    about its normal on the twin, a twist of 0.42 mrad/m left the corners at design height turned by
    1.29 mrad about x (1.1 times its U) where their image positions were within 0.02 px; on the measured
    surface, -0.10 mrad (docs/method.md, "The corner pose on the measured surface"). The shape was measured
    in the first pose's frame; the boresight frame, which the surface defines, does not depend on it. A
    mirror of unknown outline has no corners: its pose is returned as it is.
    """
    if not design.outline_known:
        return pose.facet_to_camera
    cubic = fits.cubic
    points = np.vstack([design.outline_m, design.measure_point_m])
    lift = departure_from_design_m(design, cubic.height, cubic.slopes, points)
    corners_3d = design.corners_3d()
    corners_3d[:, 2] += lift[:-1]
    measure_point = np.array([*design.measure_point_m, float(design.z(*design.measure_point_m)) + lift[-1]])
    # from the first pose: the same valley of the reprojection error, a few tenths of a mrad along it
    lifted = refine_corner_pose(geometry.camera, pose.corners_px, corners_3d, pose.facet_to_camera)
    facet_to_camera, _ = fix_range(lifted, measure_point, rays.screen_centre_cam_m,
                                   measured_distance_m, settings.max_range_shift_m)
    return facet_to_camera


def boresight_from(facet_to_camera: Pose, boresighted_to_camera: Pose) -> dict:
    """``boresight_mrad`` of the boresight frame relative to the facet frame *facet_to_camera*: the (alpha,
    beta) of M = R_y(beta) R_x(alpha) with M the rotation taking the facet frame's axes to the boresight
    frame's (:class:`~.boresight.Motion`), read as ``placement`` reads its rx, ry."""
    m = boresighted_to_camera.rotation.T @ facet_to_camera.rotation
    return {"x": 1000.0 * float(np.arctan2(m[2, 1], m[2, 2])),
            "y": -1000.0 * float(np.arcsin(np.clip(m[2, 0], -1.0, 1.0)))}


def report_figures(region: Region, phases: Phases, rays: Rays, pose: CornerPoseResult, shape: Shape, fits: Fits,
                   geometry: StationGeometry, design: FacetDesign, measured_distance_m: float,
                   settings: AnalysisSettings, with_curl: bool = True, curl=None, fringes: FringeSet | None = None,
                   screen: ScreenModel | None = None) -> dict:
    """Stage 6b: the reported figures (JSON-ready) from the stages' outputs.

    *with_curl* False leaves out the slope-curl check (``slope_curl`` None): it judges the capture, not the
    geometry, so the uncertainty's perturbed reruns, which only read the figures, need not pay for it.
    *curl*, a future of :func:`slope_curl_of` already started (on another thread), is used instead of
    computing the check here; *fringes* and *screen* let it judge the curl against each pixel's slope noise.
    """
    fit, coeffs, cubic, solution = fits.parabola, fits.coefficients, fits.cubic, shape.solution
    vidx = rays.vidx
    # The boresight frame's tilt in the fixture: where the facet's optical axis at the alignment point
    # points, to the precision of the slopes (the corner pose's own tilt errors cancel).
    tilt = placement(geometry.fixture_to_camera, shape.boresighted_to_camera, design)["mrad"]
    # The corners where the measured surface puts them, not on the design surface: placement and boresight.
    facet_to_camera = pose_on_measured_surface(pose, fits, rays, geometry, design, measured_distance_m, settings)
    if not with_curl:
        curl = None
    elif curl is None:
        curl = slope_curl_of(region, rays, shape, phases, fringes, screen)
    else:
        curl = curl.result()
    # What the capture says about itself (points kept and dropped, contrast, noise, curl) is the method's:
    # a fixed pattern's stage knows its own (``DotPhases.capture_figures``), the fringes' is below.
    own = getattr(phases, "capture_figures", None)
    capture = (own(region, rays, fits, geometry, curl) if own is not None
               else fringe_capture_figures(region, phases, rays, fits, geometry, curl))
    figures = {
        **parabola_figures(fit),
        "coefficients": {"A": coeffs[0], "B": coeffs[1], "C": coeffs[2], "D": coeffs[3], "E": coeffs[4],
                         "F": coeffs[5]},
        "slope_rms_mrad": {name: rms_summary(*e) for name, e in fits.residuals_mrad.items()},
        "n_points": int(vidx.size),
        **{k: capture.pop(k) for k in CAPTURE_KEYS},
        "iterations": {"shape": solution.shape_iterations, "boresight": solution.boresight_iterations,
                       "converged": solution.converged},
        "boresight_mrad": ({"x": 1000.0 * solution.motion.alpha_rad, "y": 1000.0 * solution.motion.beta_rad}
                           if facet_to_camera is pose.facet_to_camera
                           else boresight_from(facet_to_camera, shape.boresighted_to_camera)),
        "placement": placement(geometry.fixture_to_camera, facet_to_camera, design),
        "optical_tilt_mrad": {"x": tilt[0], "y": tilt[1]},
        "higher_order": cubic.to_dict(),
        # The converged fit on the subsample (every n-th valid pixel), before the all-points fit: what
        # programs that stop there (OpenCSP's SOFAST) report.
        "subsample_fit": {"focal_length_x_m": focal_length_m(4.0 * float(solution.subsample_coefficients[0])),
                          "focal_length_y_m": focal_length_m(4.0 * float(solution.subsample_coefficients[1])),
                          "n_points": int(-(-vidx.size // settings.subsample_step))},
        "corner_reprojection_rms_px": pose.reprojection_rms_px,
        # the facet edge's blur (pixels) and what it may have smoothed away of the slope residuals: their
        # neighbouring pixels' mean square difference (the uncertainty's blur term, budget.combine)
        "edge_blur_px": region.outline.edge_blur_px if region.outline is not None else None,
        # sides whose staircase edge lies along the pixel grid: their corners only to within a pixel
        "outline_staircase_sides": corners_mod.staircase_sides(region.outline) if region.outline is not None else [],
        # sides whose rim the design declares dark but whose fringes show it lit: put midway
        "outline_lit_rim_sides": list(region.lit_rim_sides),
        "slope_residual_neighbour_ms_mrad2": capture.pop("slope_residual_neighbour_ms_mrad2"),
        "outline_agreement": pose.outline_agreement,
        "range_correction_m": pose.range_shift_m,
        "measured_distance_m": float(measured_distance_m),
        **capture,
    }
    if not design.outline_known:
        figures.update(unknown_outline_figures(pose))
    if settings.surface != "parabolic":
        figures.update(plano_figures(figures))
    return figures


def parabola_figures(fit: ParabolaFit) -> dict:
    """The reported figures the all-points parabola *fit* alone gives (before :func:`plano_figures`): focal
    lengths (metres), curvatures (1/m), twists (mrad/m), the principal focal lengths and powers and the
    shorter's axis angle (radians); :func:`report_figures`' and the uncertainty's reruns' (which need no more)."""
    kx, ky = 4.0 * fit.a, 4.0 * fit.b
    principal, angle = principal_axes(fit.a, fit.b, fit.e)
    return {"focal_length_x_m": focal_length_m(kx), "focal_length_y_m": focal_length_m(ky),
            "curvature_x_per_m": kx, "curvature_y_per_m": ky, "twist_mrad_per_m": 1000.0 * fit.e,
            "twist_e1_mrad_per_m": 1000.0 * fit.e1, "twist_e2_mrad_per_m": 1000.0 * fit.e2,
            "principal_focal_lengths_m": principal,
            "principal_curvatures_per_m": principal_curvatures(fit.a, fit.b, fit.e), "axis_angle_rad": angle}


#: The capture's own figures, in the order the figures list them (after ``n_points``).
CAPTURE_KEYS = ("valid_fraction", "facet_pixels", "median_modulation_dn", "intensity_noise_dn", "slope_curl",
                "display_response", "dropped", "unwrap_disagreements")


def fringe_capture_figures(region: Region, phases: Phases, rays: Rays, fits: Fits, geometry: StationGeometry,
                           curl: dict | None) -> dict:
    """What a fringe capture says about itself (:data:`CAPTURE_KEYS` and the slope residuals' neighbour
    differences): the pixels kept and dropped and why, the fringes' contrast, the frames' noise, the display's
    response, the slope-curl check's result *curl*."""
    idx, vidx = region.idx, rays.vidx
    unwrap_stats = phases.unwrap
    pairs = neighbour_pairs(vidx, geometry.camera.width_px)
    return {
        # of the pixels clear of the edge's blur (the others are left out by design, not for a fault)
        "valid_fraction": float(vidx.size / max(idx.size - phases.dropped.get("near_edge", 0), 1)),
        "facet_pixels": int(idx.size),
        "median_modulation_dn": median(phases.min_modulation_dn[rays.ok]),
        "intensity_noise_dn": phases.noise.noise_dn,
        # A slope field that curls is no surface's: x and y fringe sets swapped (checked in the verdict).
        "slope_curl": curl,
        "display_response": {"harmonic_ratio": phases.noise.harmonic_ratio,
                             "signed_harmonic_ratio": phases.noise.signed_harmonic_ratio,
                             "phase_error_rad": phases.noise.phase_error_rad,
                             "phase_error_rms_rad": phases.noise.phase_error_rms_rad,
                             "phase_error_from": phases.noise.phase_error_from},
        "dropped": {"low_modulation": phases.dropped["low_modulation"],
                    "inconsistent_frames": phases.dropped["inconsistent_frames"],
                    "outside_screen_model": rays.off_model,
                    "excluded_by_pixel_mask": phases.dropped["excluded_by_pixel_mask"],
                    "near_edge": phases.dropped.get("near_edge", 0),
                    "isolated_jump": phases.dropped.get("isolated_jump", 0),
                    **{f"{k}_{a}": getattr(unwrap_stats[a], k) for a in ("x", "y")
                       for k in ("coarse_out_of_range", "disagreements", "edge_guard")}},
        "unwrap_disagreements": int(unwrap_stats["x"].disagreements + unwrap_stats["y"].disagreements),
        "slope_residual_neighbour_ms_mrad2": {
            m: {a: neighbour_difference_ms(e[i], pairs) for i, a in enumerate(("x", "y"))}
            for m, e in fits.residuals_mrad.items()},
    }


#: What the plano model does not fit, and why (``not_measured`` in its figures).
NOT_FITTED_BY_A_PLANE = {
    key: "the plano model fits constant slopes (a plane): no curvature or twist"
    for key in ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
                "twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "principal_focal_lengths_m",
                "principal_curvatures_per_m", "axis_angle_rad")}


def plano_figures(figures: dict) -> dict:
    """The figures of the plano model that differ from the parabola's: those it does not fit are None and
    named in ``not_measured``; ``surface`` says which model the residuals and the boresight are of."""
    out = {key: None for key in NOT_FITTED_BY_A_PLANE}
    out.update(surface="plano", not_measured={**(figures.get("not_measured") or {}), **NOT_FITTED_BY_A_PLANE},
               subsample_fit={**figures["subsample_fit"], "focal_length_x_m": None, "focal_length_y_m": None})
    return out


#: What a mirror of unknown outline cannot report, and why (``not_measured`` in its figures).
NOT_MEASURED_WITHOUT_OUTLINE = {
    "placement": "the facet's placement in the fixture is measured by its corners, and the outline is unknown",
    "boresight_mrad": "the boresight is the turn from the corner pose, and there are no corners (the frame is "
                      "placed facing camera and screen, then turned onto the fitted normal)",
    "corner_reprojection_rms_px": "no corners",
}


def unknown_outline_figures(pose: CornerPoseResult) -> dict:
    """The figures of a mirror of unknown outline that differ from a facet's: those measured against its
    corners are None and named, with the reason, in ``not_measured``; ``outline`` says so and
    ``mirror_centre_px`` is where its frame was placed (the lit region's centroid, column and row)."""
    out = {key: None for key in NOT_MEASURED_WITHOUT_OUTLINE}
    out.update(outline="unknown", not_measured=dict(NOT_MEASURED_WITHOUT_OUTLINE),
               mirror_centre_px=[float(v) for v in np.asarray(pose.corners_px, float)[0]])
    return out


def slope_curl_of(region: Region, rays: Rays, shape: Shape, phases: Phases | None = None,
                  fringes: FringeSet | None = None, screen: ScreenModel | None = None) -> dict:
    """The slope-curl check (:func:`~sofast_station.measure.checks.slope_curl`) of a shape's valid pixels;
    with *phases*, *fringes* and *screen*, against the slope noise of each pixel
    (:func:`~sofast_station.measure.slope_noise.slope_covariance`). A stage that knows its own points'
    neighbours (a fixed pattern's dots on their lattice: ``DotPhases.slope_curl``) checks it there."""
    own = getattr(phases, "slope_curl", None)
    if own is not None:
        return own(region, rays, shape, screen)
    valid = np.zeros(region.region.shape, dtype=bool)
    valid.ravel()[rays.vidx] = True
    cov = None
    if phases is not None and fringes is not None and screen is not None:
        stages = Reduction(region, phases, rays, None, shape, None, {})

        def cov(points):
            return slope_covariance(stages, fringes, screen, points)
    return checks.slope_curl(valid, shape.points_m, shape.slopes, slope_cov=cov)


@dataclass
class Reduction:
    """Every stage's output of one analysis, so a stage can be rerun with one input changed
    (:func:`rerun`)."""

    region: Region
    phases: Phases
    rays: Rays
    pose: CornerPoseResult
    shape: Shape
    fits: Fits
    figures: dict


def default_screen(geometry: StationGeometry) -> ScreenModel:
    """The screen of *geometry*: its measured shape when it has one (``calibrate screen``'s, an interpolated
    3-D screen), else the flat screen of its stated pitch."""
    measured = geometry.measured_screen
    if measured is None:
        return FlatScreen(geometry.screen.width_m, geometry.screen.height_m, geometry.screen_to_camera)
    scr = geometry.screen
    pose = geometry.screen_to_camera
    key = (scr.pitch_x_m, scr.pitch_y_m, scr.width_m, scr.height_m, pose.rotation.tobytes(), pose.translation.tobytes())
    # built once per geometry (its triangulation is the expensive part) and kept with the measured screen
    models = measured.__dict__.setdefault("_models", {})
    model = models.get(key)
    if model is None:
        model = InterpolatedScreen(scr.width_m, scr.height_m, measured.nodes_px * [scr.pitch_x_m, scr.pitch_y_m],
                                   measured.nodes_screen_m, pose, modes_m=measured.modes_m)
        if len(models) >= 4:
            models.clear()
        models[key] = model
    return model


def reduce_stages(frames: np.ndarray, fringes: FringeSet, geometry: StationGeometry, design: FacetDesign,
                  measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
                  screen: ScreenModel | None = None, rays_cam: np.ndarray | None = None,
                  pixel_mask: np.ndarray | None = None,
                  stop_after_boresight: bool = False, corners_px: np.ndarray | None = None,
                  corner_sigma_px: float | None = None) -> tuple[Reduction, dict]:
    """Run every stage of the reduction (:func:`~sofast_station.measure.analysis.analyse` without the
    uncertainty); returns the stages' outputs and their timings, seconds.

    *stop_after_boresight*: stop once shape and boresight have converged on the subsample (the shape's
    ``points_m`` and ``slopes``, the fits and the figures None); :func:`rerun` from ``"shape"`` finishes it.
    *corners_px* and *corner_sigma_px*: corners found by the caller (:func:`corners_and_pose`); no outline
    is then fitted, and *pixel_mask* should keep the shape's pixels off the edges."""
    with thread_pool(settings.threads) as pool:
        timer = _Timer()
        if screen is None:
            screen = default_screen(geometry)
        region = find_region(frames, fringes, geometry, design, settings, pool, fit_outline=corners_px is None)
        timer.lap("mask")
        phases = measure_phases(region, fringes, (screen.width_m, screen.height_m), settings, pixel_mask, pool)
        checked = check_dark_rim(region, phases, geometry, design, settings)
        if checked is not region:
            # a lit rim moved the outline inward: the pixels clear of its edge are fewer
            region = checked
            phases = measure_phases(region, fringes, (screen.width_m, screen.height_m), settings, pixel_mask, pool)
        timer.lap("phase")
        rays = screen_points_and_rays(region, phases, geometry.camera, screen, rays_cam, pool, settings.min_valid_px)
        timer.lap("rays")
        pose = corners_and_pose(region, rays, geometry, design, measured_distance_m, settings, pixel_mask, corners_px,
                                corner_sigma_px)
        timer.lap("pose")
        shape = shape_and_boresight(rays, pose, design, measured_distance_m, settings, pool, timer,
                                    subsample_only=stop_after_boresight)
        if stop_after_boresight:
            return Reduction(region, phases, rays, pose, shape, None, None), dict(timer.timings)
        # The slope-curl check needs only the shape: it runs on a pool thread beside the fits.
        curl = pool.submit(slope_curl_of, region, rays, shape, phases, fringes, screen)
        fits = fit_models(shape, design, pool)
        timer.lap("fit")
        figures = report_figures(region, phases, rays, pose, shape, fits, geometry, design, measured_distance_m,
                                 settings, curl=curl)
        timer.lap("report")
        reduction = sharpened_fit(Reduction(region, phases, rays, pose, shape, fits, figures), geometry=geometry,
                                  design=design, measured_distance_m=measured_distance_m, settings=settings,
                                  screen=screen, pool=pool)
        if reduction.figures is not figures:
            timer.lap("sharpen")
    return reduction, dict(timer.timings)


def to_analysis(reduction: Reduction, timings: dict | None = None) -> Analysis:
    """The :class:`Analysis` of a finished reduction."""
    timings = dict(timings or {})
    figures = dict(reduction.figures)
    figures["timings_s"] = dict(timings)
    cam_shape = reduction.region.region.shape
    valid = np.zeros(cam_shape, dtype=bool)
    valid.ravel()[reduction.rays.vidx] = True
    return Analysis(figures=figures, valid=valid, points_facet_m=reduction.shape.points_m,
                    slopes=reduction.shape.slopes, residuals_mrad=reduction.fits.residuals_mrad,
                    facet_to_camera=reduction.shape.boresighted_to_camera, corners_px=reduction.pose.corners_px,
                    coefficients=reduction.fits.coefficients, timings_s=timings)


STAGES = ("region", "phases", "rays", "pose", "shape", "fits", "figures")


def rerun(reduction: Reduction, start: str, *, fringes: FringeSet, geometry: StationGeometry,
          design: FacetDesign, measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
          screen: ScreenModel | None = None, phases: Phases | None = None, pose: CornerPoseResult | None = None,
          pool=None, with_curl: bool = True, warm: bool = False) -> Reduction:
    """Rerun the reduction from stage *start* (one of :data:`STAGES` after ``region``) with the inputs given,
    reusing the earlier stages' outputs of *reduction*.

    E.g. ``rerun(r, "rays", geometry=g2, ...)`` redoes everything from the screen points with a changed
    camera-to-screen pose; ``rerun(r, "rays", phases=p2, ...)`` with changed screen positions;
    ``rerun(r, "shape", pose=p2, ...)`` with a changed corner pose (``pose`` only when *start* is
    ``"shape"``). *with_curl* as in :func:`report_figures`. *warm*: the shape stage iterates from
    *reduction*'s converged solution, not from the design (for inputs moved a little: the same convergence
    tests, a third of the steps; the figures agree with a cold rerun's to the iteration's tolerance).
    """
    if start not in STAGES[1:]:
        raise ValueError(f"start must be one of {STAGES[1:]}, got {start!r}")
    order = STAGES.index(start)
    if screen is None:
        screen = default_screen(geometry)
    region = reduction.region
    if order <= STAGES.index("phases"):
        phases = measure_phases(region, fringes, (screen.width_m, screen.height_m), settings, None, pool)
    elif phases is None:
        phases = reduction.phases
    if order <= STAGES.index("rays"):
        rays = screen_points_and_rays(region, phases, geometry.camera, screen, pool=pool,
                                      min_valid_px=settings.min_valid_px)
    else:
        rays = reduction.rays
    if order <= STAGES.index("pose"):
        pose = pose_from_corners(reduction.pose.corners_px, region, rays, geometry, design, measured_distance_m,
                                 settings, agreement=reduction.pose.outline_agreement)
    elif pose is None:
        pose = reduction.pose
    if order <= STAGES.index("shape"):
        start_from = reduction.shape.solution if warm and reduction.shape is not None else None
        shape = shape_and_boresight(rays, pose, design, measured_distance_m, settings, pool, start=start_from)
    else:
        shape = reduction.shape
    fits = fit_models(shape, design, pool) if order <= STAGES.index("fits") else reduction.fits
    figures = report_figures(region, phases, rays, pose, shape, fits, geometry, design, measured_distance_m,
                             settings, with_curl=with_curl, fringes=fringes, screen=screen)
    return Reduction(region, phases, rays, pose, shape, fits, figures)
