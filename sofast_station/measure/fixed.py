"""The fixed-pattern (dot grid) method: the facet measured from one frame of a grid of dots whose 3-D locations
are known, instead of the fringes' eighteen (OpenCSP's SOFAST Fixed; docs/method.md, "The fixed-pattern
method").

The frame shows the facet reflecting a dot grid: a printed target located by photogrammetry
(``calibrate dots``, :class:`~sofast_station.measure.dots.DotLocations`) or a grid the station's own display
draws (:class:`LcdDotGrid`, located by :func:`lcd_dot_locations` from the screen's pixel grid and its
commissioned shape). The steps:

1. the facet's region and outline from the same frame, its dots filled in with the lit background around
   them (:func:`~sofast_station.measure.dots.pattern_background`), or from a white (and a dark) frame when the
   recipe takes one (:func:`dot_region`);
2. the dots, each centred to a fraction of a pixel with its covariance from the image's noise
   (:func:`~sofast_station.measure.dots.find_pattern_dots`);
3. their lattice indices, counted from the pattern's origin: the origin mark's pixel (OpenCSP's capture stores
   it; :func:`find_origin_mark` finds a mark brighter than the lit pattern beside the origin dot, as in
   OpenCSP's capture), the walk of :func:`~sofast_station.measure.dots.index_dots` in the image's directions,
   turned into the pattern's index directions: +y is where the origin mark lies from the origin dot, x the
   other way a mirror's picture of the grid runs (:func:`mark_index_axes`), or both as the nominal geometry
   predicts them when there is no mark (:func:`predicted_index_axes`). A dot that cannot be indexed is
   dropped and counted, never guessed; a grid seen twice is refused: dots closer together than its pitch
   allows (two grids interleaved, :func:`check_spacing`), or a second lattice among the dots left over
   (:func:`second_lattice`);
4. each indexed dot's 3-D location (:func:`dot_screen`: a screen model on the grid of dot locations, each
   position a dot's column and row in it) and the ray through its sub-pixel centre; from there the reduction
   is the fringe method's own, unchanged (:func:`~.pipeline.corners_and_pose`,
   :func:`~.pipeline.shape_and_boresight`, :func:`~.pipeline.fit_models`, :func:`~.pipeline.report_figures`
   and the uncertainty, :func:`~.analysis.finish_analysis`) through the stages' objects:
   :class:`~.pipeline.Region` with one point per dot (``points_px`` the centres, ``idx`` the pixel each lies
   in, raster order) and :class:`DotPhases` in place of the fringes' phases (the dots' grid positions, their
   position noise from the centroids' covariance, what the capture says about itself).

:func:`analyse_fixed` runs it all; :func:`reduce_fixed` stops before the uncertainty. Pure functions of
arrays and plain records: no file, no hardware, no state.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import ClassVar

import cv2
import numpy as np

from ..errors import (
    CaptureError,
    ConfigError,
    DotsNotFoundError,
    DoubleLatticeError,
    OriginNotFoundError,
    TooFewDotsError,
)
from ..facet import FacetDesign
from ..geometry import Pose, StationGeometry
from . import checks
from . import corners as corners_mod
from .analysis import finish_analysis
from .camera import pixel_rays, project
from .dots import DotLocations, PatternDots, find_pattern_dots, index_dots, otsu_level, pattern_background
from .mask import facet_region
from .metrics import neighbour_difference_ms, neighbour_pairs
from .pipeline import (
    Analysis,
    AnalysisSettings,
    Reduction,
    Region,
    _outline_of,
    _Serial,
    _Timer,
    corners_and_pose,
    fit_models,
    outline_image_points,
    report_figures,
    screen_points_and_rays,
    shape_and_boresight,
    thread_pool,
)
from .screen import InterpolatedScreen
from .slope_noise import slope_covariance
from .stats import median


@dataclass(frozen=True)
class FixedSettings:
    """What the fixed-pattern method needs besides the analysis's own settings (:class:`~.pipeline.AnalysisSettings`:
    the corners, the fits and the boresight are the fringe method's).

    Attributes
    ----------
    dark_dots : bool
        Dark dots on a lit background (OpenCSP's targets and patterns). Light dots on a dark background need a
        white frame for the facet's region.
    max_dot_diameter_px : float
        The largest dot diameter expected in the image, pixels (the dots are filled in with a square twice
        as wide, :func:`~.dots.pattern_background`).
    index_tolerance : float
        A dot is indexed when it lies within this fraction of a lattice step of where its neighbours on the
        same row or column put it (:func:`~.dots.index_dots`). A facet's slope errors move the reflected dots
        (1 mrad of slope moves one by 2 mrad times the distance to the screen: half a step on OpenCSP's
        capture, where 0.3 left 5 % of the dots unindexed and 0.45 half a percent).
    min_dots : int
        Fewer dots indexed, located and clear of the facet's edge: :class:`~sofast_station.errors.TooFewDotsError`.
    origin_index : (int, int)
        The (x index, y index) of the dot the origin mark marks.
    index_axes : (2, 2) int array or None
        How the image's lattice directions (i along its columns, j along its rows) run on the pattern's
        indices: ``(x, y) = origin_index + index_axes @ (i, j)``; None: predicted from the nominal geometry
        (:func:`predicted_index_axes`).
    second_lattice_fraction : float
        Dots left unindexed on the facet beyond this fraction of the indexed ones are checked for a second
        lattice (:func:`second_lattice`).
    subsample_step : int
        Every n-th dot (raster order) is used while iterating shape and boresight: 1, every dot (a few
        thousand points cost nothing; OpenCSP's fixed processing uses every dot too).
    edge_margin_px : float
        A dot is used when its centre lies this much more than the blur's reach and its own radius inside the
        facet's outline (a dot the edge cuts is centred off its true centre), pixels.
    """

    dark_dots: bool = True
    max_dot_diameter_px: float = 24.0
    index_tolerance: float = 0.45
    min_dots: int = 100
    origin_index: tuple = (0, 0)
    index_axes: np.ndarray | None = None
    second_lattice_fraction: float = 0.2
    subsample_step: int = 1
    edge_margin_px: float = 1.0

    def __post_init__(self):
        if not 0.1 <= float(self.index_tolerance) <= 0.5:
            raise ConfigError(f"the fixed pattern's index_tolerance must lie in 0.1..0.5 lattice steps, got "
                              f"{self.index_tolerance!r}")
        if int(self.min_dots) < 9:
            raise ConfigError(f"the fixed pattern's min_dots must be at least 9, got {self.min_dots!r}")
        if self.index_axes is not None:
            axes = np.asarray(self.index_axes)
            if axes.shape != (2, 2) or not np.all(np.isin(axes, (-1, 0, 1))) or abs(round(np.linalg.det(axes))) != 1:
                raise ConfigError(f"the fixed pattern's index_axes must be a 2 x 2 matrix of -1, 0, 1 that swaps or "
                                  f"flips the axes, got {self.index_axes!r}")

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["origin_index"] = [int(v) for v in self.origin_index]
        d["index_axes"] = None if self.index_axes is None else np.asarray(self.index_axes).tolist()
        return d


@dataclass(frozen=True)
class DotPattern:
    """What a fixed-pattern capture showed, in the place the fringe method's
    :class:`~sofast_station.fringes.FringeSet` has: what the uncertainty's cached sensitivities depend on besides
    the dot locations themselves (the screen model's fingerprint)."""

    settings: FixedSettings = FixedSettings()

    def to_dict(self) -> dict:
        return {"method": "fixed", **self.settings.to_dict()}


# -- the dots' screen model --------------------------------------------------------------------------------------
def dot_screen(dots: DotLocations, screen_to_camera: Pose, centre_m=(0.0, 0.0, 0.0)) -> InterpolatedScreen:
    """The dot locations as a screen model: position (u, v) is the dot at column u and row v of *dots*' grid
    (``dots.xyz_m[v, u]``, exactly), between dots linear over the grid's cells. *screen_to_camera* takes the
    dots' frame into the camera's (OpenCSP's dot locations are in its screen frame, that of its
    ``SpatialOrientation``; a target's, in its markers' frame); *centre_m* is the range finder's origin in that
    frame.

    Only located dots are ever looked up (the others are dropped before); the model also needs a position's
    neighbourhood, for the slopes' derivatives with respect to it (the noise propagation,
    :func:`~.slope_noise.slope_jacobian`), so the grid is made whole for that: a dot not located takes the mean
    of its located neighbours (repeated until none is left), and a node is added beyond each edge, continuing
    the last two linearly. A screen model can be moved, stretched and displaced as itself, so the
    uncertainty's rows of the screen's pose and scale (:mod:`~sofast_station.measure.uncertainty`) move the
    grid whole.
    """
    xyz = np.array(dots.xyz_m, np.float64)
    located = dots.located
    if int(located.sum()) < 9:
        raise ConfigError(f"the dot locations hold only {int(located.sum())} located dots")
    known = located.copy()
    while not known.all():
        total, count = np.zeros_like(xyz), np.zeros(known.shape)
        for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            shifted = np.roll(np.where(known[..., None], xyz, 0.0), (dr, dc), axis=(0, 1))
            ok = np.roll(known, (dr, dc), axis=(0, 1))
            # np.roll wraps around: a neighbour across the grid's edge is none
            if dr:
                ok[0 if dr > 0 else -1, :] = False
            else:
                ok[:, 0 if dc > 0 else -1] = False
            total += np.where(ok[..., None], shifted, 0.0)
            count += ok
        fill = ~known & (count > 0)
        if not fill.any():
            break
        xyz[fill] = total[fill] / count[fill][:, None]
        known |= fill
    padded = np.pad(xyz, ((1, 1), (1, 1), (0, 0)))
    padded[0, 1:-1], padded[-1, 1:-1] = 2 * xyz[0] - xyz[1], 2 * xyz[-1] - xyz[-2]
    padded[:, 0], padded[:, -1] = 2 * padded[:, 1] - padded[:, 2], 2 * padded[:, -2] - padded[:, -3]
    rows, cols = np.mgrid[-1:xyz.shape[0] + 1, -1:xyz.shape[1] + 1]
    uv = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float64)
    # a whole grid: the cells are split along their main diagonals (no triangulation to build)
    split = np.ones((rows.shape[0] - 1, rows.shape[1] - 1), dtype=bool)
    return InterpolatedScreen(float(dots.x_index.size), float(dots.y_index.size), uv, padded.reshape(-1, 3),
                              screen_to_camera, centre_m, split=split)


# -- the LCD's own dot grid -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class LcdDotGrid:
    """A dot grid the station's display draws: dots every ``pitch_px`` display pixels across the active area,
    the middle one the origin (index (0, 0)), x index along the display's columns and y index down its rows
    (OpenCSP's ``PatternSofastFixed``). The origin mark is a disc at full white, ``mark_offset`` of a pitch
    below the origin dot, on a background drawn at ``background`` so that the mark stands out brighter than
    the pattern (as the mark of OpenCSP's capture does: :func:`find_origin_mark`).

    Attributes
    ----------
    width_px, height_px : int
        The display's active area, pixels.
    pitch_px : int
        Dot spacing, display pixels (at least 6).
    diameter_px : float
        Dot diameter, display pixels.
    background : int
        The command of the lit background (0..255).
    mark_diameter_px, mark_offset : float
        The origin mark's diameter (display pixels) and its distance below the origin dot (pitches).
    """

    width_px: int
    height_px: int
    pitch_px: int
    diameter_px: float
    background: int = 170
    mark_diameter_px: float | None = None
    mark_offset: float = 0.4

    def __post_init__(self):
        if int(self.pitch_px) < 6 or not 2.0 <= float(self.diameter_px) <= 0.6 * int(self.pitch_px):
            raise ConfigError(f"a dot grid needs a pitch of at least 6 display pixels and dots of 2 pixels to 0.6 of "
                              f"the pitch across, got pitch {self.pitch_px!r} and diameter {self.diameter_px!r}")
        if not 20 <= int(self.background) <= 230:
            raise ConfigError(f"the dot grid's background command must lie in 20..230 (the origin mark is drawn at "
                              f"255 above it), got {self.background!r}")

    @property
    def mark_diameter(self) -> float:
        return float(self.mark_diameter_px) if self.mark_diameter_px else 0.6 * float(self.diameter_px)

    @property
    def centre_columns(self) -> np.ndarray:
        """The display column each dot column is centred on (its pixel's centre), in x index order."""
        n = (int(self.width_px) - 1) // int(self.pitch_px) // 2
        return int(self.width_px) // 2 + int(self.pitch_px) * np.arange(-n, n + 1)

    @property
    def centre_rows(self) -> np.ndarray:
        n = (int(self.height_px) - 1) // int(self.pitch_px) // 2
        return int(self.height_px) // 2 + int(self.pitch_px) * np.arange(-n, n + 1)

    @property
    def x_index(self) -> np.ndarray:
        n = self.centre_columns.size // 2
        return np.arange(-n, n + 1)

    @property
    def y_index(self) -> np.ndarray:
        n = self.centre_rows.size // 2
        return np.arange(-n, n + 1)

    def image(self) -> np.ndarray:
        """The display image (rows, columns) uint8: the background, dark dots (each display pixel whose centre
        lies within half a diameter of a dot's centre, so each dot is symmetric about its centre) and the
        origin mark at 255."""
        img = np.full((int(self.height_px), int(self.width_px)), int(self.background), np.uint8)
        r = 0.5 * float(self.diameter_px)
        reach = int(np.ceil(r))
        off = np.arange(-reach, reach + 1)
        disc = (off[:, None] ** 2 + off[None, :] ** 2) <= r * r
        dr, dc = np.nonzero(disc)
        dr, dc = dr - reach, dc - reach
        rows, cols = np.meshgrid(self.centre_rows, self.centre_columns, indexing="ij")
        rr = (rows.ravel()[:, None] + dr[None, :]).ravel()
        cc = (cols.ravel()[:, None] + dc[None, :]).ravel()
        inside = (rr >= 0) & (rr < img.shape[0]) & (cc >= 0) & (cc < img.shape[1])
        img[rr[inside], cc[inside]] = 0
        m = 0.5 * self.mark_diameter
        row0 = int(self.height_px) // 2 + self.mark_offset * int(self.pitch_px)
        col0 = int(self.width_px) // 2
        grid_r, grid_c = np.mgrid[0:img.shape[0], 0:img.shape[1]]
        near = (np.abs(grid_r - row0) <= m + 1) & (np.abs(grid_c - col0) <= m + 1)
        img[near & ((grid_r - row0) ** 2 + (grid_c - col0) ** 2 <= m * m)] = 255
        return img


def lcd_dot_locations(grid: LcdDotGrid, screen) -> DotLocations:
    """The 3-D locations of *grid*'s dots as the station's display shows them: each dot's centre (the centre
    of the display pixel it is drawn about) at its screen position, through the screen model *screen* (the
    commissioned shape, ``calibrate screen``'s, or the flat screen of the stated pitch:
    :func:`~.pipeline.default_screen`), in the screen's frame (origin at the active area's centre, +x along
    the columns, +y up; docs/conventions.md#screen-frame), metres.

    Display column c is centred at u_x = (c + 1/2) W / width_px from the left edge, row r at
    u_y = H - (r + 1/2) H / height_px from the bottom (the screen model's positions; W and H its extents).
    """
    if float(screen.width_m) <= 0 or float(screen.height_m) <= 0:
        raise ConfigError("the screen model has no extent")
    pitch_x = float(screen.width_m) / int(grid.width_px)
    pitch_y = float(screen.height_m) / int(grid.height_px)
    cols, rows = np.meshgrid(grid.centre_columns, grid.centre_rows)
    u_x = (cols.ravel() + 0.5) * pitch_x
    u_y = float(screen.height_m) - (rows.ravel() + 0.5) * pitch_y
    cam = screen.points_camera(u_x, u_y)
    to_screen = screen.screen_to_camera.inverse()
    xyz = to_screen.apply(cam.T)
    return DotLocations(grid.x_index, grid.y_index, xyz.reshape(rows.shape + (3,)))


# -- region, origin, indices ---------------------------------------------------------------------------------
def dot_region(image: np.ndarray, background: np.ndarray, geometry: StationGeometry, design: FacetDesign,
               settings: AnalysisSettings, white: np.ndarray | None = None,
               dark: np.ndarray | None = None, box: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The facet's region and the contrast image its outline is fitted on: from a white (and a dark) frame
    when given, else from the dot frame's lit background with its dots filled in (*background*,
    :func:`~.dots.pattern_background`: the edge stays where it is). Without a dark frame the region is what is
    brighter than Otsu's threshold of the lit background (the facet against its dark surroundings, as OpenCSP
    takes it), at least ``mask_threshold_dn``. Returns (region, contrast (float32, DN)).

    Raises
    ------
    FacetNotFoundError
        The region is cut off at the image's border or much smaller than the design's (:func:`~.checks.check_region`).
    """
    h, w = np.shape(image)
    # (only where the lit area is when no white frame says otherwise: *box*, :func:`lit_background`'s)
    r0, r1, c0, c1 = box if box is not None and white is None else (0, h, 0, w)
    lit = np.asarray((background if white is None else white)[r0:r1, c0:c1], np.float32)
    base = 0.0 if dark is None else np.asarray(dark[r0:r1, c0:c1], np.float32)
    contrast = np.zeros((h, w), np.float32)
    part = contrast[r0:r1, c0:c1]
    np.subtract(lit, base, out=part)
    threshold = float(settings.mask_threshold_dn)
    if dark is None:
        whole = np.asarray(background if white is None else white, np.float32)
        threshold = max(threshold, otsu_level(whole[::2, ::2].ravel()))
    # whole counts in the camera's own type take facet_region's fast path (OpenCV's subtraction)
    kind = np.uint8 if float(part.max(initial=0.0)) <= 255 else np.uint16
    counts = np.clip(np.round(part), 0, np.iinfo(kind).max).astype(kind)
    region = np.zeros((h, w), bool)
    region[r0:r1, c0:c1] = facet_region(np.zeros(counts.shape, kind), counts, threshold, settings.max_hole_px)
    nominal = outline_image_points(design, geometry.camera, geometry.fixture_to_camera)
    checks.check_region(region, float(np.count_nonzero(checks.projected_outline_mask(geometry.camera.shape, nominal))),
                        min_area_fraction=0.5 if design.outline_known else 0.0)
    return region, contrast


def lit_background(image: np.ndarray, max_diameter_px: float, dark: bool = True) -> tuple[np.ndarray, tuple]:
    """:func:`~.dots.pattern_background` of *image* where it is lit, the image itself elsewhere (float32), and
    that lit box (row 0, row 1, column 0, column 1): the lit area is found first on a picture four times
    smaller (its box widened by the filling square), so the filling of a two-megapixel frame costs what the
    facet's box costs."""
    img = np.asarray(image)
    h, w = img.shape
    k = 2 * int(np.ceil(max_diameter_px)) + 1
    out = img.astype(np.float32)
    if min(h, w) < 64:
        return pattern_background(img, max_diameter_px, dark), (0, h, 0, w)
    # (the frame cut to whole blocks of 4 x 4 first: OpenCV's block average, a third of its general area
    # resampling's time when a side is not a multiple of 4; the last 1-3 rows or columns only widen the box)
    small = cv2.resize(img[:h // 4 * 4, :w // 4 * 4], (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    small_bg = pattern_background(small, max(max_diameter_px / 4.0, 1.0), dark)
    lit = small_bg > otsu_level(small_bg.ravel())
    rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
    if rows.size == 0:
        return out, (0, h, 0, w)
    r0, r1 = max(4 * rows[0] - 2 * k, 0), min(4 * rows[-1] + 4 + 2 * k, h)
    c0, c1 = max(4 * cols[0] - 2 * k, 0), min(4 * cols[-1] + 4 + 2 * k, w)
    out[r0:r1, c0:c1] = pattern_background(img[r0:r1, c0:c1], max_diameter_px, dark)
    return out, (int(r0), int(r1), int(c0), int(c1))


def find_origin_mark(image: np.ndarray, region: np.ndarray, background: np.ndarray, diameter_px: float,
                     noise_dn: float) -> np.ndarray | None:
    """The pixel (column, row) of the origin mark: a spot on the facet brighter than the lit pattern around it
    (OpenCSP's capture: a spot 4 px beside the origin dot, 1.7 times the background's level; :class:`LcdDotGrid`
    draws one at 255 on a background drawn lower), or None when there is none.

    The lit pattern's level without the spot is the dots' filled background (*background*) opened with a
    square of 4 dot diameters (which removes bright spots smaller than that); a spot is where the background
    stands above that by a quarter of the level and by 8 times the image's noise *noise_dn*, on the facet and
    clear of its edge by the square's size; the brightest such spot's intensity-weighted centre.
    """
    k = 2 * int(np.ceil(2.0 * max(diameter_px, 1.0))) + 1
    rr, cc = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
    if rr.size == 0:
        return None
    r0, r1 = max(rr[0] - k, 0), min(rr[-1] + k + 1, region.shape[0])
    c0, c1 = max(cc[0] - k, 0), min(cc[-1] + k + 1, region.shape[1])
    bg = np.asarray(background[r0:r1, c0:c1], np.float32)
    square = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    level = cv2.morphologyEx(bg, cv2.MORPH_OPEN, square)
    excess = bg - level
    inner = cv2.erode(region[r0:r1, c0:c1].astype(np.uint8), square).astype(bool)
    spot = inner & (excess > np.maximum(0.25 * level, 8.0 * max(noise_dn, 0.5)))
    if not spot.any():
        return None
    n, labels, stats, _ = cv2.connectedComponentsWithStats(spot.astype(np.uint8), connectivity=8)
    strength = np.bincount(labels.ravel(), weights=np.where(spot, excess, 0.0).ravel(), minlength=n)
    best = int(np.argmax(strength[1:])) + 1
    rows, cols = np.nonzero(labels == best)
    # the spot's own light above the pattern: the image itself (the background keeps the spot's top only)
    w = np.clip(np.asarray(image, np.float64)[r0 + rows, c0 + cols] - level[rows, cols], 0.0, None)
    if not w.sum() > 0:
        w = excess[rows, cols].astype(np.float64)
    return np.array([c0 + float(np.sum(w * cols) / np.sum(w)), r0 + float(np.sum(w * rows) / np.sum(w))])


def lattice_steps(indices: np.ndarray, points_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per dot, the image's steps (pixels) to its next dots along the two lattice directions: (N, 2) each, the
    central difference where both neighbours are indexed, else one-sided, else the median step."""
    indices = np.asarray(indices, np.int64)
    lo = indices.min(axis=0) - 1
    shape = tuple(indices.max(axis=0) - lo + 2)
    grid = np.full(shape + (2,), np.nan)                   # positions by index, a free place on every side
    a, b = (indices - lo).T
    grid[a, b] = points_px
    out = []
    for d in ((1, 0), (0, 1)):
        fwd, back = grid[a + d[0], b + d[1]], grid[a - d[0], b - d[1]]
        step = np.where(np.isnan(fwd), points_px - back, fwd - points_px)
        both = ~np.isnan(fwd[:, 0]) & ~np.isnan(back[:, 0])
        step[both] = 0.5 * (fwd[both] - back[both])
        missing = np.isnan(step[:, 0])
        if missing.all():
            raise DotsNotFoundError("the indexed dots have no neighbours along a lattice direction")
        step[missing] = np.median(step[~missing], axis=0)
        out.append(step)
    return out[0], out[1]


def dots_plane(dots: DotLocations, screen) -> tuple:
    """The located dots' best plane in the camera frame and the affine map from it to their grid column and row:
    (centre (3,), basis (3, 3) rows: in-plane x, y and the normal, affine (3, 2))."""
    rows, cols = np.nonzero(dots.located)
    uv = np.column_stack([cols, rows]).astype(np.float64)
    pts = screen.points_camera(uv[:, 0], uv[:, 1])
    centre = pts.mean(axis=1)
    _, _, vt = np.linalg.svd((pts - centre[:, None]).T, full_matrices=False)
    local = vt[:2] @ (pts - centre[:, None])
    affine, *_ = np.linalg.lstsq(np.column_stack([local.T, np.ones(local.shape[1])]), uv, rcond=None)
    return centre, vt, affine


def predicted_grid_jacobian(geometry: StationGeometry, design: FacetDesign, plane: tuple) -> np.ndarray:
    """(2, 2): how far the dot grid's column and row move per pixel (column, row) of the image at the facet's
    centroid, as the nominal geometry predicts it: the design facet at the fixture's nominal pose reflects the
    camera's rays there and a pixel along each image axis onto the dots' grid (*plane*: :func:`dots_plane`)."""
    cam, f2c = geometry.camera, geometry.fixture_to_camera
    c = design.centroid_m
    p0 = project(cam, f2c, np.array([[c[0], c[1], float(design.z(*c))]]))[0]
    h = 2.0
    pix = np.array([p0, p0 + [h, 0.0], p0 + [0.0, h]])
    rays = pixel_rays(cam, pix[:, 0], pix[:, 1])                       # (3, 3) camera frame
    to_facet = f2c.inverse()
    origin = to_facet.translation
    d = to_facet.rotation @ rays
    # the design surface z = (x^2 + y^2) / (4 f): a few fixed-point steps from the plane z = 0
    t = -origin[2] / d[2]
    for _ in range(8):
        x, y = origin[0] + t * d[0], origin[1] + t * d[1]
        t = (design.z(x, y) - origin[2]) / d[2]
    x, y = origin[0] + t * d[0], origin[1] + t * d[1]
    n = np.vstack([-x / (2.0 * design.focal_length_m), -y / (2.0 * design.focal_length_m), np.ones_like(x)])
    n /= np.linalg.norm(n, axis=0)
    r = d - 2.0 * np.sum(d * n, axis=0) * n
    hit = np.vstack([x, y, design.z(x, y)])
    # into the camera frame, onto the plane of the dots
    q, r_cam = f2c.rotation @ hit + f2c.translation[:, None], f2c.rotation @ r
    centre, vt, affine = plane
    s = ((centre - q.T) @ vt[2]) / (r_cam.T @ vt[2])
    on = q + s * r_cam
    grid = np.column_stack([(vt[:2] @ (on - centre[:, None])).T, np.ones(3)]) @ affine      # (3, 2) column, row
    return np.column_stack([grid[1] - grid[0], grid[2] - grid[0]]) / h


#: A prediction of the grid's picture is trusted when a design focal length 2 % longer or shorter changes its
#: scale by less than this share: near the centre of curvature the facet's own curvature decides the scale.
STEADY_PREDICTION = 0.1


def grid_prediction(geometry: StationGeometry, design: FacetDesign, dots: DotLocations, screen) -> tuple:
    """(jac, steady): the nominal geometry's grid Jacobian (:func:`predicted_grid_jacobian`) and whether it
    can be trusted: whether the design's focal length 2 % longer and shorter changes the predicted grid step in
    the image by less than :data:`STEADY_PREDICTION` (far from the facet's centre of curvature, as OpenCSP's
    10 m to a 100 m facet; at the station's fringe layout, the centre of curvature between camera and screen,
    a facet pictures the grid at a scale and even orientation its own curvature decides)."""
    plane = dots_plane(dots, screen)
    jac = predicted_grid_jacobian(geometry, design, plane)
    step = np.linalg.norm(np.linalg.inv(jac), axis=0)
    steady = True
    for k in (1.02, 1.0 / 1.02):
        other = predicted_grid_jacobian(geometry, dataclasses.replace(design, focal_length_m=design.focal_length_m * k),
                                        plane)
        change = np.abs(np.linalg.norm(np.linalg.inv(other), axis=0) / step - 1.0)
        steady &= bool(np.all(change < STEADY_PREDICTION))
    return jac, steady


@dataclass(frozen=True)
class GridPrediction:
    """:func:`grid_prediction`'s (jac, steady) as a caller's cache keeps it (:func:`kept_grid_prediction`);
    *jac* read-only. The same for every capture of a recipe (``per_recipe``: an import's one-analysis cache
    shares it with its caller's, as the sensitivities)."""

    jac: np.ndarray
    steady: bool
    per_recipe: ClassVar[bool] = True


def grid_prediction_key(geometry: StationGeometry, design: FacetDesign, dots: DotLocations, screen) -> tuple:
    """What :func:`grid_prediction` depends on, as a key of a caller's cache: ``("grid prediction", hash)``,
    the hash (16 hex digits) of the geometry and the design (their ``to_dict``, as the sensitivities' key),
    the dots' grid and locations, and the screen model (its type, shape fingerprint and pose). By content,
    not by identity: a recipe's objects rebuilt equal (a station's worker builds them per capture) find it."""
    h = hashlib.sha256(json.dumps({"geometry": geometry.to_dict(), "design": design.to_dict()}, sort_keys=True,
                                  default=str).encode())
    for a in (dots.x_index, dots.y_index, dots.xyz_m):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(repr(type(screen)).encode())
    if hasattr(screen, "fingerprint"):
        h.update(screen.fingerprint().encode())
    pose = getattr(screen, "screen_to_camera", None)
    if pose is not None:
        h.update(np.ascontiguousarray(pose.rotation, np.float64).tobytes())
        h.update(np.ascontiguousarray(pose.translation, np.float64).tobytes())
    return "grid prediction", h.hexdigest()[:16]


def kept_grid_prediction(geometry: StationGeometry, design: FacetDesign, dots: DotLocations, screen,
                         cache: dict | None = None) -> tuple:
    """:func:`grid_prediction`, kept in *cache* (a caller's dict, e.g. :func:`analyse_fixed`'s
    *sensitivity_cache*) under :func:`grid_prediction_key` as a :class:`GridPrediction`: the same for every
    capture of a recipe (3-4 ms each). Without *cache*, computed."""
    if cache is None:
        return grid_prediction(geometry, design, dots, screen)
    key = grid_prediction_key(geometry, design, dots, screen)
    kept = cache.get(key)
    if not isinstance(kept, GridPrediction):
        jac, steady = grid_prediction(geometry, design, dots, screen)
        jac.setflags(write=False)           # shared by every capture that finds it
        kept = cache[key] = GridPrediction(jac, steady)
    return kept.jac, kept.steady


def predicted_index_axes(jac: np.ndarray, step_i_px: np.ndarray, step_j_px: np.ndarray) -> np.ndarray:
    """(2, 2) integer matrix turning the image's lattice steps (i, j: :func:`~.dots.index_dots`) into the
    pattern's index steps, ``(x, y) = origin + axes @ (i, j)``, as the nominal geometry predicts them: the
    grid's Jacobian *jac* (:func:`predicted_grid_jacobian`) turns each image lattice step into a step on the
    grid, which must lie within 35 degrees of one of the grid's axes. A mirror turns and flips the grid's
    picture (beyond its focus, it is upside down), which is why the image's directions alone cannot say.

    Raises
    ------
    ConfigError
        A lattice step falls between the grid's axes (a camera turned 45 degrees about its axis): give
        ``FixedSettings.index_axes``.
    """
    axes = np.zeros((2, 2), np.int64)
    for k, step in enumerate((np.median(step_i_px, axis=0), np.median(step_j_px, axis=0))):
        g = jac @ step
        if not 1.0 / 3.0 <= np.linalg.norm(g) <= 3.0:
            raise ConfigError(f"the nominal geometry cannot predict the dot grid's picture here: a lattice step "
                              f"of {np.linalg.norm(step):.1f} px is {np.linalg.norm(g):.3g} grid steps by it (a facet "
                              "near its centre of curvature pictures the grid at a scale its own curvature decides): "
                              "show the origin mark, or give the fixed pattern's index_axes")
        j = int(np.argmax(np.abs(g)))
        if not np.abs(g[j]) >= np.cos(np.radians(35.0)) * np.linalg.norm(g):
            raise ConfigError(f"the dot grid's picture runs between its axes (a lattice step of {step.round(2)} px "
                              f"moves {g.round(3)} columns and rows of the grid): give the fixed pattern's "
                              "index_axes")
        axes[j, k] = int(np.sign(g[j]))
    if abs(round(np.linalg.det(axes))) != 1:
        raise ConfigError("the dot grid's picture has both lattice directions along one of its axes: give the fixed "
                          "pattern's index_axes")
    return axes


#: Dots closer together than this share of the step the nominal geometry predicts are a grid seen twice.
MIN_STEP_SHARE = 0.75

#: Standard uncertainty (pixels, per axis) of a dot's centroid as the image of its screen centre, beyond the
#: image's noise: the dot's picture is the disc's pre-image through the facet's local slopes, sampled by the
#: pixels and centred over a window, so its centroid is not exactly the picture of the disc's centre. The
#: error is the dot's own (its edge pixels, the slopes under its footprint), independent from dot to dot,
#: and the same with or without noise. On noise-free frames of the methods study's stations (nominal
#: geometry, seed 0, stations 0-11: heliostat and flat, every edge model) each dot's centroid against the
#: pixel where the twin images the dot's centre was 0.05-0.16 px RMS per axis (0.09 over the 12 stations,
#: neighbouring dots' errors correlated -0.3 to 0.3); a uniform disc of radius R px sampled at pixel centres
#: alone gives sqrt(1 / (12 pi R)), 0.11 px at R = 2.4. docs/uncertainty.md, "Dot centroid model".
CENTROID_MODEL_PX = 0.10

#: Standard uncertainty (pixels, per coordinate) of each corner the dot frame's outline gives, beyond the
#: outline fit's own covariance: the sides are fitted on the dot frame's lit background with its dots
#: filled in (:func:`~.dots.pattern_background`), not on a white frame, and their corners are off the
#: twin's true corner pixels by more than the fit states. On ``study methods`` (seed 0, 59 captures of 12
#: stations, every edge model) they were 0.17 px RMS per coordinate off against 0.07 stated (chi-square of
#: the 8 coordinates: median 106); less each capture's common shift and scale of the four (which move the
#: placement in mm and the range, not the turn), 0.10 px. With the twin's true corners the boresight x was
#: covered 100 % (RMS of error / (U / 2) 0.59), with the found ones 74.6 % (1.69). Added in quadrature to
#: every corner coordinate's variance, independent from corner to corner (docs/uncertainty.md, "Dot
#: frame's corners").
CORNER_MODEL_PX = 0.10


def with_corner_model(pose):
    """*pose* (:class:`~.pipeline.CornerPoseResult`) with :data:`CORNER_MODEL_PX` added to its corners'
    covariance (and their median standard uncertainty); unchanged without a covariance (a mirror of unknown
    outline, placed by its region's centroid)."""
    cov = getattr(pose, "corner_cov_px2", None)
    if cov is None or len(pose.corners_px) < 3:
        return pose
    cov = np.asarray(cov, np.float64) + CORNER_MODEL_PX ** 2 * np.eye(len(cov))
    sigma = None if pose.corner_sigma_px is None else float(np.hypot(pose.corner_sigma_px, CORNER_MODEL_PX))
    return dataclasses.replace(pose, corner_cov_px2=cov, corner_sigma_px=sigma)


def check_spacing(centres_px: np.ndarray, jac: np.ndarray) -> None:
    """Refuse dots closer together than :data:`MIN_STEP_SHARE` of the shorter grid step the nominal geometry
    predicts (*jac*: :func:`predicted_grid_jacobian`; its inverse is pixels per grid step): two grids
    interleaved (a second one half a step off looks like one finer grid, which indexing would follow)."""
    # lazy: scipy.spatial, ~470 ms CPU; recipes.py loads this at every station start
    from scipy.spatial import cKDTree

    if len(centres_px) < 9:
        return
    d, _ = cKDTree(centres_px).query(centres_px, k=2)
    spacing = float(np.median(d[:, 1]))
    predicted = float(np.min(np.linalg.norm(np.linalg.inv(jac), axis=0)))
    if spacing < MIN_STEP_SHARE * predicted:
        raise DoubleLatticeError(f"the dots lie {spacing:.1f} px apart where the grid's pitch puts them "
                                 f"{predicted:.1f} px apart: the dot grid is seen twice (interleaved), or the frame "
                                 "shows another, finer grid")


def second_lattice(points_px: np.ndarray, step_px: float, min_points: int) -> int:
    """How many of *points_px* (dots left unindexed on the facet) form a lattice of their own: the largest
    number :func:`~.dots.index_dots` indexes from any of a few starting dots near their middle, 0 when they
    do not (scattered dust, stray blobs); a step within a factor 1.5 of the indexed lattice's *step_px*."""
    if len(points_px) < max(min_points, 9):
        return 0
    # lazy: scipy.spatial, ~470 ms CPU; recipes.py loads this at every station start
    from scipy.spatial import cKDTree

    tree = cKDTree(points_px)
    d, _ = tree.query(points_px, k=2)
    near = np.abs(d[:, 1] / step_px - 1.0) < 0.5
    if near.sum() < 9:
        return 0
    middle = np.median(points_px[near], axis=0)
    starts = np.flatnonzero(near)[np.argsort(np.linalg.norm(points_px[near] - middle, axis=1))[:5]]
    best = 0
    for s in starts:
        try:
            ij, _ = index_dots(points_px, points_px[s], 0.3)
        except ValueError:
            continue
        best = max(best, len(ij))
    return best if best >= min_points else 0


# -- the phases' stand-in --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DotPhases:
    """Stage 2 of a fixed pattern, in the place of the fringes' :class:`~.pipeline.Phases`: each dot's position
    on its grid and which dots to keep. Per-dot arrays follow ``Region.idx``.

    Attributes
    ----------
    positions_m : dict
        ``{"x": (M,), "y": (M,)}``: each dot's column and row in the dot locations' grid (the positions of
        :func:`dot_screen`; grid steps, not metres).
    ok : (M,) bool array
        Dots located and clear of the facet's edge.
    position_sigma_m : dict
        ``{"x": (M,), "y": (M,)}``: each dot's position noise on the grid (grid steps) from its centroid's
        covariance: a centre seen delta off makes the dot's ray the one that sees the grid J delta away (J the
        grid steps per pixel there, from the dot's neighbours), so the centre's covariance C gives J C J^T;
        the two axes' correlation (the lattice's shear in the image) is left out.
    noise_dn : float
        The image's noise beside the dots, DN.
    lattice_index : (M, 2) int array
        Each dot's (x index, y index).
    index_per_px : (M, 2, 2) array
        Each dot's grid steps (x, y) per pixel (column, row) there: how far a centre seen off by a pixel moves
        the grid point its ray truly sees (from the dot's neighbours in the image).
    depth_dn : (M,) array
        Each dot's depth below its background, DN.
    dropped : dict
        Dots dropped, by cause.
    found : dict
        The detection's counts (dots found, indexed, merged, too small, unmeasured), the origin and the axes.
    position_model_sigma_m : dict or None
        ``{"x": (M,), "y": (M,)}``: each dot's position error on the grid (grid steps) from its centroid's model
        error (:data:`CENTROID_MODEL_PX`), carried as *position_sigma_m* is: independent from dot to dot, so the
        fits' covariance holds it; not part of the slope noise floor (it is partly the footprint's smoothing,
        which lowers a slope RMS rather than raising it).
    """

    positions_m: dict
    ok: np.ndarray
    position_sigma_m: dict
    noise_dn: float
    lattice_index: np.ndarray
    index_per_px: np.ndarray
    depth_dn: np.ndarray
    dropped: dict
    found: dict = field(default_factory=dict)
    #: No four-step fringe sets: no display response or frame brightness for the uncertainty to consider.
    four_step = False
    noise = None
    set_offsets_dn: dict = field(default_factory=dict)
    position_model_sigma_m: dict | None = None

    def capture_figures(self, region: Region, rays, fits, geometry: StationGeometry, curl) -> dict:
        """What the capture says about itself (the fringe method's keys, :data:`~.pipeline.CAPTURE_KEYS`, and the
        dots' own): dots kept and dropped and why, their contrast (``median_modulation_dn``: the dots' median
        depth below their background), the image's noise, the slope curl on the dots' lattice. No display
        response (no fringes: None) and no unwrapping (0 disagreements); ``slope_residual_neighbour_ms_mrad2``
        None: each dot is centred on its own image, so the lens's blur does not average neighbouring dots'
        slopes (what that figure measures for the uncertainty's blur term)."""
        on_facet = int(self.ok.size - self.dropped.get("near_edge", 0))
        # the lattice's neighbour pairs once for every model and axis (the uncertainty's shape reruns call this
        # dozens of times per capture: sorting the lattice six times was a tenth of the analysis's CPU)
        pairs = self._pairs(rays)
        return {
            "valid_fraction": float(rays.vidx.size / max(on_facet, 1)),
            "facet_pixels": int(region.region.sum()),
            "median_modulation_dn": median(self.depth_dn[rays.ok]),
            "intensity_noise_dn": float(self.noise_dn),
            "slope_curl": curl,
            "display_response": None,
            "dropped": {**self.dropped, "outside_screen_model": int(rays.off_model)},
            "unwrap_disagreements": 0,
            "slope_residual_neighbour_ms_mrad2": None,
            "method": "fixed",
            "dots": {**self.found, "used": int(rays.vidx.size),
                     "lattice_neighbour_ms_mrad2": {m: {a: neighbour_difference_ms(e[i], pairs)
                                                        for i, a in enumerate(("x", "y"))}
                                                    for m, e in fits.residuals_mrad.items()},
                     "centroid_sigma_px": self.found.get("centroid_sigma_px")},
        }

    def _order(self, rays) -> tuple[np.ndarray, np.ndarray, int]:
        """The valid dots' flat indices on their lattice, the permutation that sorts them, the lattice's width."""
        ij = self.lattice_index[rays.ok]
        lo = ij.min(axis=0)
        width = int(ij[:, 0].max() - lo[0] + 1)
        flat = (ij[:, 1] - lo[1]) * width + (ij[:, 0] - lo[0])
        return flat, np.argsort(flat, kind="stable"), width

    def _pairs(self, rays) -> tuple:
        """The valid dots' lattice neighbours, as :func:`~.metrics.neighbour_pairs` gives pixels', in the valid
        dots' own order."""
        flat, perm, width = self._order(rays)
        pairs = neighbour_pairs(flat[perm], width)
        return tuple((perm[a], perm[b]) for a, b in pairs)

    def slope_curl(self, region: Region, rays, shape, screen) -> dict:
        """The slope-curl check (:func:`~.checks.slope_curl`) on the dots' lattice: each dot a "pixel" of the
        lattice, its neighbours the dots beside it, against each dot's slope noise."""
        flat, perm, width = self._order(rays)
        height = int(flat.max() // width + 1)
        valid = np.zeros((height, width), dtype=bool)
        valid.ravel()[flat] = True
        stages = Reduction(region, self, rays, None, shape, None, {})

        def cov(points):
            return slope_covariance(stages, None, screen, perm[np.asarray(points, dtype=np.intp)])

        return checks.slope_curl(valid, shape.points_m[:, perm], shape.slopes[:, perm], slope_cov=cov)


# -- the whole reduction ---------------------------------------------------------------------------------------
def _check_frame(image: np.ndarray, shape: tuple[int, int], name: str = "dot frame") -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype.kind not in "ui":
        raise CaptureError(f"the {name} must be one grey image of camera counts, got {img.dtype} {img.shape}")
    if img.shape != tuple(shape):
        raise CaptureError(f"the {name} is {img.shape[1]} x {img.shape[0]} px, the camera {shape[1]} x {shape[0]}")
    return img


def _index_pattern(found: PatternDots, origin_px, jac: np.ndarray, steady: bool, fixed: FixedSettings):
    """Indices of the found dots from the origin: (indices (M, 2), which of found (M,), image steps i and j
    per indexed dot, axes, where the axes came from); *jac* the nominal geometry's grid Jacobian, *steady*
    whether it can be trusted (:func:`grid_prediction`)."""
    try:
        ij, pts, which = index_dots(found.centres_px, origin_px, fixed.index_tolerance, return_which=True)
    except ValueError as exc:
        if "origin" in str(exc):
            raise OriginNotFoundError(f"no dot beside the dot grid's origin at ({origin_px[0]:.1f}, "
                                      f"{origin_px[1]:.1f}) px: {exc}; is the origin mark on the facet?") from None
        raise DotsNotFoundError(f"the dots do not form a lattice from the origin: {exc}") from None
    if len(ij) < 9:
        raise TooFewDotsError(f"only {len(ij)} dots follow a lattice from the origin at ({origin_px[0]:.1f}, "
                              f"{origin_px[1]:.1f}) px")
    step_i, step_j = lattice_steps(ij, pts)
    if fixed.index_axes is not None:
        axes, how = np.asarray(fixed.index_axes, np.int64), "given"
    else:
        origin_dot = pts[np.flatnonzero(np.all(ij == 0, axis=1))[0]]
        axes = mark_index_axes(np.asarray(origin_px, np.float64) - origin_dot, step_i, step_j, jac)
        how = "mark"
        if axes is None:
            if not steady:
                raise ConfigError("the dot grid's picture cannot be predicted here (the facet is near its centre of "
                                  "curvature, where its own curvature turns the picture) and the origin was given on "
                                  "a dot, not beside it: show the origin mark, or give the fixed pattern's "
                                  "index_axes")
            axes, how = predicted_index_axes(jac, step_i, step_j), "predicted"
    index = np.asarray(fixed.origin_index, np.int64)[None, :] + ij @ axes.T
    return index, which, step_i, step_j, axes, how


def mark_index_axes(mark_from_dot_px: np.ndarray, step_i_px: np.ndarray, step_j_px: np.ndarray,
                    jac: np.ndarray) -> np.ndarray | None:
    """The index axes (as :func:`predicted_index_axes`) from the origin mark: it lies beside the origin dot along
    the grid's +y (OpenCSP's capture: 4 px below it, a third of a step; :class:`LcdDotGrid` draws it so), so the
    image's vector from the dot to the mark (*mark_from_dot_px*) names the lattice direction that is +y; the
    other is x, its sign that of a mirror's picture of the grid (the sign of the nominal geometry's Jacobian
    *jac*'s determinant: one reflection, whether the picture is upright or upside down). None when the mark
    does not lie clearly along one lattice direction (a pixel given on the origin dot itself)."""
    m = np.column_stack([np.median(step_i_px, axis=0), np.median(step_j_px, axis=0)])
    c = np.linalg.solve(m, np.asarray(mark_from_dot_px, np.float64))       # the mark in lattice steps
    k = int(np.argmax(np.abs(c)))
    if not (abs(c[k]) >= 0.15 and abs(c[1 - k]) <= 0.5 * abs(c[k])):
        return None
    s_y = int(np.sign(c[k]))
    hand = int(np.sign(np.linalg.det(jac))) or 1
    axes = np.zeros((2, 2), np.int64)
    axes[1, k] = s_y
    axes[0, 1 - k] = hand * s_y if k == 1 else -hand * s_y
    return axes


def reduce_fixed(image: np.ndarray, dots: DotLocations, geometry: StationGeometry, design: FacetDesign,
                 measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
                 fixed: FixedSettings = FixedSettings(), *, origin_px=None, white: np.ndarray | None = None,
                 dark: np.ndarray | None = None, screen: InterpolatedScreen | None = None,
                 screen_centre_m=(0.0, 0.0, 0.0), cache: dict | None = None) -> tuple[Reduction, dict]:
    """Every stage of the fixed-pattern reduction (:func:`analyse_fixed` without the uncertainty); returns the
    stages' outputs and their timings, seconds.

    Parameters
    ----------
    image : (rows, columns) integer array
        The frame of the facet reflecting the dot grid, camera counts (DN).
    dots : DotLocations
        The grid's 3-D dot locations, in the frame ``geometry.screen_to_camera`` takes into the camera's.
    geometry : StationGeometry
        Camera, the dots' frame in the camera's (``screen_to_camera``) and the fixture's nominal facet pose.
    design : FacetDesign
    measured_distance_m : float
        From the dots' frame's point *screen_centre_m* (the screen centre) to ``design.measure_point_m``.
    settings : AnalysisSettings
        The analysis's (corners, fits, boresight); ``min_valid_px`` and ``subsample_step`` are *fixed*'s.
    fixed : FixedSettings
    origin_px : (2,) sequence, optional
        Pixel of the grid's origin mark (OpenCSP's capture stores it); found in the frame when not given
        (:func:`find_origin_mark`).
    white, dark : (rows, columns) arrays, optional
        A white (and a dark) frame for the facet's region and corners, when the recipe takes them.
    screen : InterpolatedScreen, optional
        :func:`dot_screen` of *dots* when the caller keeps it.
    cache : dict, optional
        Where the grid's predicted picture is kept between captures (:func:`kept_grid_prediction`; the caller's,
        e.g. :func:`analyse_fixed`'s *sensitivity_cache*); without it, computed for this capture.

    Raises
    ------
    DotsNotFoundError, OriginNotFoundError, TooFewDotsError, DoubleLatticeError
        The capture shows no dot grid, no dot at its origin, too few dots on the facet, or the grid twice.
    FacetNotFoundError, CaptureError
        As the fringe method: the facet's region or corners, a saturated frame.
    """
    cam = geometry.camera
    img = _check_frame(image, cam.shape)
    white = None if white is None else _check_frame(white, cam.shape, "white frame")
    dark = None if dark is None else _check_frame(dark, cam.shape, "dark frame")
    if not fixed.dark_dots and white is None:
        raise ConfigError("light dots on a dark background need a white frame for the facet's region")
    settings = fixed_settings_for(settings, fixed)
    screen = dot_screen(dots, geometry.screen_to_camera, screen_centre_m) if screen is None else screen
    with thread_pool(settings.threads) as pool:
        timer = _Timer()
        background, box = lit_background(img, fixed.max_dot_diameter_px, fixed.dark_dots)
        region_mask, contrast = dot_region(img, background, geometry, design, settings, white, dark, box)
        outline = pool.submit(_outline_of, contrast, region_mask, geometry, design, settings) \
            if design.outline_known else _Serial._Done((None, None))
        top = np.iinfo(img.dtype).max
        saturated = float(np.count_nonzero((img >= top) & region_mask)) / max(np.count_nonzero(region_mask), 1)
        if saturated > settings.max_saturated_fraction:
            raise CaptureError(f"{100 * saturated:.1f} % of the facet's pixels are saturated ({top} DN) in the dot "
                               "frame: lower the exposure or gain, or dim the room light")
        timer.lap("mask")
        found = find_pattern_dots(img, region_mask, dark=fixed.dark_dots, max_diameter_px=fixed.max_dot_diameter_px,
                                  background=background)
        if len(found.centres_px) < 9:
            raise DotsNotFoundError(f"no dot grid on the facet: {len(found.centres_px)} dot(s) found ({found.merged} "
                                    "blobs too large or long, "
                                    f"{found.small} too small): is the dot pattern shown and in focus, and are the "
                                    "dots dark on a lit background?")
        jac, steady = kept_grid_prediction(geometry, design, dots, screen, cache)
        if steady:
            check_spacing(found.centres_px, jac)
        if origin_px is None:
            origin_px = find_origin_mark(img, region_mask, background, found.diameter_px, found.noise_dn)
            if origin_px is None:
                raise OriginNotFoundError("no origin mark on the facet (a spot brighter than the lit pattern beside "
                                          "the origin dot): is it shown, and does the facet reflect it?")
            origin_from = "mark"
        else:
            origin_px = np.asarray(origin_px, np.float64).ravel()
            origin_from = "given"
        index, which, step_i, step_j, axes, axes_from = _index_pattern(found, origin_px, jac, steady, fixed)
        timer.lap("dots")
        step = float(np.median(np.linalg.norm(np.vstack([step_i, step_j]), axis=1)))
        left = np.ones(len(found.centres_px), bool)
        left[which] = False
        second = second_lattice(found.centres_px[left], step,
                                max(9, int(fixed.second_lattice_fraction * len(which))))
        if second:
            raise DoubleLatticeError(f"the dot grid is seen twice: {second} dots left over from the {len(which)} "
                                     "indexed form a lattice of their own (a second reflection: a back-silvered "
                                     "mirror's front surface, or a second screen); the capture cannot tell which "
                                     "dot is which")
        # each indexed dot's place in the grid of locations, and its pixel (raster order)
        centres = found.centres_px[which]
        col = index[:, 0] - dots.x_index[0]
        row = index[:, 1] - dots.y_index[0]
        in_grid = (col >= 0) & (col < dots.x_index.size) & (row >= 0) & (row < dots.y_index.size)
        located = in_grid.copy()
        located[in_grid] = dots.located[row[in_grid], col[in_grid]]
        pix = np.round(centres).astype(np.int64)
        flat = pix[:, 1] * cam.width_px + pix[:, 0]
        order = np.argsort(flat, kind="stable")
        if np.any(np.diff(flat[order]) == 0):
            raise DotsNotFoundError("two dots were found in one pixel: the dots are too small or too close together "
                                    "for this camera")
        outline, outline_error = outline.result()
        if outline is not None:
            radius = 0.5 * found.diameter_px * 1.5 + 1.0 + float(fixed.edge_margin_px)
            inset = corners_mod.edge_inset_px(outline.edge_blur_px) + radius
            clear = corners_mod.inside_outline(outline, centres[:, 0], centres[:, 1], inset)
        else:
            clear = np.ones(len(which), bool)
        # position noise on the grid from the centroids' covariance, through each dot's local grid steps
        m = np.stack([step_i, step_j], axis=2)                       # pixels per (i, j) step
        per_index = m @ np.linalg.inv(axes).astype(np.float64)       # pixels per (x, y) index step
        jac = np.linalg.inv(per_index)                              # index steps per pixel
        cov_pos = jac @ found.cov_px2[which] @ np.swapaxes(jac, 1, 2)
        sigma = {"x": np.sqrt(np.clip(cov_pos[:, 0, 0], 0, None)), "y": np.sqrt(np.clip(cov_pos[:, 1, 1], 0, None))}
        # the centroids' model error, independent per dot (CENTROID_MODEL_PX), through the same grid steps
        cov_mod = CENTROID_MODEL_PX ** 2 * jac @ np.swapaxes(jac, 1, 2)
        model_sigma = {"x": np.sqrt(cov_mod[:, 0, 0]), "y": np.sqrt(cov_mod[:, 1, 1])}
        ok = located & clear
        dropped = {"not_indexed": int(left.sum()), "merged": int(found.merged), "too_small": int(found.small),
                   "unmeasured": int(found.unmeasured), "no_location": int((~located).sum()),
                   "near_edge": int((located & ~clear).sum())}
        if int(ok.sum()) < fixed.min_dots:
            raise TooFewDotsError(f"only {int(ok.sum())} dots on the facet could be used (of {len(found.centres_px)} "
                                  f"found: {dropped}); at least {fixed.min_dots} are needed: a finer grid, or a larger "
                                  "facet in the image")
        s = order
        region = Region(region=region_mask, idx=flat[s], stack=None, contrast=contrast, outline=outline,
                        outline_error=outline_error, clear_of_edge=clear[s], points_px=centres[s])
        phases = DotPhases(
            positions_m={"x": col[s].astype(np.float64), "y": row[s].astype(np.float64)}, ok=ok[s],
            position_sigma_m={a: v[s] for a, v in sigma.items()}, noise_dn=float(found.noise_dn),
            position_model_sigma_m={a: v[s] for a, v in model_sigma.items()},
            lattice_index=index[s], index_per_px=jac[s], depth_dn=found.depth_dn[which][s], dropped=dropped,
            found={"found": int(len(found.centres_px)), "indexed": int(len(which)), "origin_px": origin_px.tolist(),
                   "origin_from": origin_from, "origin_index": [int(v) for v in fixed.origin_index],
                   "index_axes": axes.tolist(), "index_axes_from": axes_from, "step_px": step,
                   "diameter_px": float(found.diameter_px), "centroid_model_px": CENTROID_MODEL_PX,
                   "corner_model_px": CORNER_MODEL_PX,
                   "centroid_sigma_px": float(np.sqrt(np.median(0.5 * np.trace(found.cov_px2[which], axis1=1,
                                                                               axis2=2))))})
        timer.lap("phase")
        rays = screen_points_and_rays(region, phases, cam, screen, pool=pool, min_valid_px=int(fixed.min_dots))
        timer.lap("rays")
        # the dot frame's corners carry their model error (CORNER_MODEL_PX) besides the outline fit's
        pose = with_corner_model(corners_and_pose(region, rays, geometry, design, measured_distance_m, settings))
        timer.lap("pose")
        shape = shape_and_boresight(rays, pose, design, measured_distance_m, settings, pool, timer)
        fits = fit_models(shape, design, pool)
        timer.lap("fit")
        figures = report_figures(region, phases, rays, pose, shape, fits, geometry, design, measured_distance_m,
                                 settings, fringes=DotPattern(fixed), screen=screen)
        timer.lap("report")
    return Reduction(region, phases, rays, pose, shape, fits, figures), dict(timer.timings)


def fixed_settings_for(settings: AnalysisSettings, fixed: FixedSettings) -> AnalysisSettings:
    """The analysis settings a fixed-pattern reduction runs with (its own point count and iteration subsample)."""
    return dataclasses.replace(settings, min_valid_px=int(fixed.min_dots), subsample_step=int(fixed.subsample_step))


def analyse_fixed(image: np.ndarray, dots: DotLocations, geometry: StationGeometry, design: FacetDesign,
                  measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
                  fixed: FixedSettings = FixedSettings(), *, origin_px=None, white: np.ndarray | None = None,
                  dark: np.ndarray | None = None, uncertainty=None, sensitivity_cache: dict | None = None,
                  screen: InterpolatedScreen | None = None, screen_centre_m=(0.0, 0.0, 0.0)) -> Analysis:
    """One fixed-pattern capture reduced to the reported figures, with every figure's expanded uncertainty when
    *uncertainty* (the station inputs' :class:`~.uncertainty.InputUncertainties`) is given: the stages of
    :func:`reduce_fixed`, then :func:`~.analysis.finish_analysis`, as the fringe method's :func:`~.analysis.analyse`.

    The parameters are :func:`reduce_fixed`'s, and *uncertainty* and *sensitivity_cache* :func:`~.analysis.analyse`'s;
    *sensitivity_cache* also keeps the grid's predicted picture (:func:`kept_grid_prediction`). The figures carry
    ``method = "fixed"`` and ``dots`` (found, indexed, used, the origin, the lattice's axes).
    """
    screen = dot_screen(dots, geometry.screen_to_camera, screen_centre_m) if screen is None else screen
    reduction, timings = reduce_fixed(image, dots, geometry, design, measured_distance_m, settings, fixed,
                                      origin_px=origin_px, white=white, dark=dark, screen=screen,
                                      cache=sensitivity_cache)
    return finish_analysis(reduction, timings, fringes=DotPattern(fixed), geometry=geometry, design=design,
                           measured_distance_m=measured_distance_m, settings=fixed_settings_for(settings, fixed),
                           screen=screen, uncertainty=uncertainty, sensitivity_cache=sensitivity_cache)


# -- a recipe's fixed pattern on the station's display -------------------------------------------------------------
@dataclass(frozen=True)
class FixedCapture:
    """How a station measures a facet with the fixed-pattern method: the dot grid its display shows, the
    method's settings, and whether the recipe allows a dark and a white frame before the dot frame (the
    facet's region and corners from them: two more frames, a sharper edge).

    Attributes
    ----------
    grid : LcdDotGrid
    settings : FixedSettings
    white_frame : bool
        Dark, white, then the dots (3 frames); False: the dot frame alone.
    """

    grid: LcdDotGrid
    settings: FixedSettings = FixedSettings()
    white_frame: bool = False

    @property
    def n_frames(self) -> int:
        return 3 if self.white_frame else 1

    def to_dict(self) -> dict:
        return {"grid": dataclasses.asdict(self.grid), "settings": self.settings.to_dict(),
                "white_frame": bool(self.white_frame)}

    @classmethod
    def from_dict(cls, d: dict) -> "FixedCapture":
        s = dict(d["settings"])
        s["origin_index"] = tuple(s.get("origin_index", (0, 0)))
        if s.get("index_axes") is not None:
            s["index_axes"] = np.asarray(s["index_axes"], np.int64)
        return cls(LcdDotGrid(**d["grid"]), FixedSettings(**s), bool(d.get("white_frame", False)))


#: Fewest camera pixels between neighbouring dots' pictures the method is set up for: the dots are filled in
#: and centred over windows of about a pitch; closer, neighbouring dots run together.
MIN_SPACING_PX = 7.0


def grid_spacing_px(geometry: StationGeometry, design: FacetDesign, grid: LcdDotGrid, screen) -> tuple[float, bool]:
    """(spacing, steady): how many camera pixels apart the nominal facet pictures *grid*'s neighbouring dots
    (the smaller of its two directions, at the facet's centroid) and whether that picture can be predicted
    (:func:`grid_prediction`: far enough from the facet's centre of curvature that its own slope errors do
    not scramble the lattice). *screen*: the display's model (:func:`~.pipeline.default_screen`)."""
    dots = lcd_dot_locations(grid, screen)
    jac, steady = grid_prediction(geometry, design, dots, dot_screen(dots, geometry.screen_to_camera))
    return float(np.min(np.linalg.norm(np.linalg.inv(jac), axis=0))), steady


def check_fixed_layout(geometry: StationGeometry, design: FacetDesign, grid: LcdDotGrid, screen,
                       where: str = "the recipe") -> float:
    """The camera pixels between the dots' pictures (:func:`grid_spacing_px`); a ConfigError naming what to
    change when the station's layout cannot index the dot grid: the facet near its centre of curvature (the
    dish stations' layout, where a dot moves by twice the distance times the local slope error: half a pitch
    per mrad) or the dots' pictures closer than :data:`MIN_SPACING_PX`."""
    spacing, steady = grid_spacing_px(geometry, design, grid, screen)
    if not steady:
        raise ConfigError(f"{where}: the fixed-pattern method cannot index the dot grid on this station's layout: "
                          f"facet {design.name!r} is seen near its centre of curvature, where its own slope errors "
                          "scramble the dots' lattice; measure it with method = \"fringe\", or lay the station out "
                          "for the fixed pattern (the screen well inside or beyond the centre of curvature, as the "
                          "heliostat station is: docs/method.md)")
    if spacing < MIN_SPACING_PX:
        need = int(np.ceil(int(grid.pitch_px) * MIN_SPACING_PX / max(spacing, 1e-9)))
        raise ConfigError(f"{where}: the fixed pattern's dots would be only {spacing:.1f} camera pixels apart on "
                          f"the facet (pitch {grid.pitch_px} display pixels); at least {MIN_SPACING_PX:g} are "
                          f"needed: set fixed.pitch_px to {need} or more")
    return spacing


def pitch_for_spacing(geometry: StationGeometry, design: FacetDesign, width_px: int, height_px: int, screen,
                      spacing_px: float) -> int:
    """The display pitch (pixels) that puts the dots' pictures about *spacing_px* camera pixels apart on the
    nominal facet: the picture's spacing is proportional to the pitch (the dots' screen positions are), so one
    trial grid's spacing scales it."""
    trial = LcdDotGrid(int(width_px), int(height_px), 40, 16.0)
    got, _ = grid_spacing_px(geometry, design, trial, screen)
    return max(6, int(round(40 * float(spacing_px) / max(got, 1e-9))))
