"""Camera intrinsics and distortion from images of a chessboard or ChArUco board (OpenCV).

Every image is either used or rejected with a reason:

* the file cannot be read, or its size differs from the first image's;
* the board is not found (chessboard: no grid that checks out of at least :func:`smallest_part` inner
  corners along each side, see :func:`find_chessboard`; ChArUco: no marker or corner);
* the chessboard found is larger than the board stated (``--squares`` counts squares, not inner corners);
* too few corners (fewer than ``min_corners``; ChArUco: or all on one line);
* blurred: the board's edges are wider than ``max_edge_width_px`` (contrast over the steepest gradients
  near the corners; a focused edge is about 2 px wide, a Gaussian blur of sigma adds about 2.5 sigma);
* after the first calibration, a reprojection RMS more than three times the median of the images (and
  above 0.5 px): the corners were misdetected; the rest is calibrated again.

A chessboard may be partly out of view: the part found is used, its corners numbered from the part's own
first corner (a plain chessboard does not say which part of it is seen; each view has its own pose, so
the intrinsics do not need to know). Images are read and searched in parallel threads (OpenCV releases
the GIL), one line of progress per image.

The model is OpenCV's pinhole with distortion k1, k2, p1, p2, k3 (k3 held at 0 unless asked for: a
long-focus lens cannot tell it from k1 and k2; k2 too may be held at 0). The result is stored as a camera
record under ``data_dir/calibration/camera/`` with the reprojection RMS, the standard deviation of every
parameter and the verdict on every image.

The calibration judges itself (:func:`judge_calibration`, thresholds below, argued in
docs/calibration.md): ``pass``, ``warn`` (recorded, with the warnings) or ``refused`` (no record: the
parameters are not determined by the views) from the reprojection RMS, OpenCV's standard deviations of
the parameters (focal length relative, principal point against the image width, distortion as the
displacement it leaves uncertain at the image's corners) and how the views' points cover the image.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import ConfigError
from ..geometry import CameraIntrinsics
from .errors import CalibrationError
from .store import write_record

log = logging.getLogger(__name__)

SCHEMA = 1

#: Verdict thresholds (warn, refuse) of :func:`judge_calibration`; docs/calibration.md argues them.
#: Reprojection RMS over the used images, pixels (a sharp board on a good lens gives 0.05-0.2 px).
RMS_PX = (0.3, 1.0)
#: Standard deviation of each focal length over the focal length.
FOCAL_RELATIVE = (1e-3, 5e-3)
#: Standard deviation of each principal point coordinate over the image width.
PRINCIPAL_OF_WIDTH = (5e-3, 2e-2)
#: Displacement the distortion terms' standard deviations leave at the image's corners, pixels.
DISTORTION_CORNER_PX = (0.5, 2.0)
#: Coverage: the image is cut into COVERAGE_GRID cells (across, down); warn under this fraction holding
#: a point of some view, and when a corner zone (CORNER_ZONE of the width and height from a corner)
#: holds none.
COVERAGE_GRID = (8, 6)
MIN_COVERAGE = 0.6
CORNER_ZONE = 0.2

#: Chessboard search (:func:`find_chessboard`): the smallest part of the board accepted, as a fraction of
#: its inner corners along its shorter side (the same count along both sides, so that the detector takes
#: the part in either orientation), at least MIN_PART corners: a board partly out of view. The detector
#: grows the part it finds as a rectangle of the board's squares, so a board cut diagonally by the image's
#: edge gives it a part much smaller than what is in view (a quarter of the shorter side lets it take one).
PARTIAL_FRACTION = 0.25
MIN_PART = 4
#: Local contrast equalisation before the search (OpenCV's CLAHE: clip limit, tiles across x down): a
#: board lit unevenly, whose weak corners the detector's global tests reject (docs/calibration.md).
CLAHE_CLIP = 3.0
CLAHE_TILES = (8, 8)
#: The image is searched at full size, then halved again and again (down to MIN_SEARCH_SIDE pixels along
#: its shorter side) until the whole board is found: the detector, asked for a part of a board whose
#: squares are large (a board seen close, reaching past the image's edge), grows grids that skip every
#: other row or column; on the image made smaller, where the squares are about 10 to 20 px, it grows the
#: right one.
MIN_SEARCH_SIDE = 150
#: A grid found is a chessboard's only within these (:func:`grid_deviation`): the bend of a run of four
#: corners over its length, and its cross-ratio's relative error (docs/calibration.md gives what true and
#: wrong grids show).
MAX_BEND = 0.1
MAX_CROSS_RATIO_ERROR = 0.1
#: ... and its corners within this many local spacings of where their neighbours put them
#: (:func:`grid_outliers`; the outer rows holding one are dropped).
MAX_OFF_SPACING = 0.25


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board.

    Attributes
    ----------
    kind : str
        ``"chessboard"`` or ``"charuco"``.
    squares_x, squares_y : int
        Squares along the board's width and height (a chessboard has (squares_x - 1) x (squares_y - 1)
        inner corners).
    square_m : float
        Side of a square, metres.
    marker_m : float
        Side of a ChArUco marker, metres.
    dictionary : str
        ChArUco marker dictionary (an OpenCV name, e.g. ``"DICT_5X5_100"``).
    legacy : bool
        ChArUco boards printed with OpenCV before 4.6 (even row counts differ).
    """

    kind: str
    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"
    legacy: bool = False

    def __post_init__(self):
        if self.kind not in ("chessboard", "charuco"):
            raise ConfigError(f"board kind must be 'chessboard' or 'charuco', got {self.kind!r}")
        if int(self.squares_x) < 3 or int(self.squares_y) < 3:
            raise ConfigError(f"a board needs at least 3 x 3 squares, got {self.squares_x} x {self.squares_y}")
        if not (np.isfinite(self.square_m) and 0 < self.square_m < 1):
            raise ConfigError(f"square size must be metres in (0, 1), got {self.square_m}")
        if self.kind == "charuco" and not (0 < self.marker_m < self.square_m):
            raise ConfigError(f"a ChArUco marker must be smaller than its square ({self.square_m} m), got "
                              f"{self.marker_m} m")
        object.__setattr__(self, "squares_x", int(self.squares_x))
        object.__setattr__(self, "squares_y", int(self.squares_y))

    @property
    def n_corners(self) -> int:
        """Inner corners of the board."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    def chessboard_points(self) -> np.ndarray:
        """Board-frame points (n_corners, 3), metres, in OpenCV's chessboard corner order (rows of x)."""
        return grid_points(self.squares_x - 1, self.squares_y - 1, self.square_m)

    def charuco(self):
        """The OpenCV CharucoBoard."""
        name = self.dictionary
        if not hasattr(cv2.aruco, name):
            raise ConfigError(f"unknown ArUco dictionary {name!r}; use an OpenCV name such as DICT_5X5_100")
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m,
                                       cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)))
        board.setLegacyPattern(bool(self.legacy))
        return board

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ImageResult:
    """What became of one image.

    Attributes
    ----------
    name : str
    accepted : bool
    reason : str
        Why it was rejected ("" when used).
    corners : int
        Corners found.
    edge_width_px : float or None
        Median edge width near the corners, pixels.
    rms_px : float or None
        Reprojection RMS of its corners after calibration, pixels.
    grid : tuple of int or None
        Chessboard: the inner corners found, across x down (the board's, or a part of it, maybe turned).
    partial : bool
        Chessboard: only a part of the board was found (partly out of view).
    shape : tuple of int or None
        The image's (height, width), pixels.
    """

    name: str
    accepted: bool = False
    reason: str = ""
    corners: int = 0
    edge_width_px: float | None = None
    rms_px: float | None = None
    grid: tuple[int, int] | None = None
    partial: bool = False
    shape: tuple[int, int] | None = None
    object_points: np.ndarray | None = field(default=None, repr=False)
    image_points: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {"name": self.name, "accepted": self.accepted, "reason": self.reason, "corners": self.corners,
                "edge_width_px": self.edge_width_px, "rms_px": self.rms_px,
                "grid": list(self.grid) if self.grid else None, "partial": self.partial}

    def describe(self) -> str:
        """One line: the corners found and the edge width, or why the image was rejected."""
        if not self.accepted:
            return f"rejected: {self.reason}"
        part = (f" (a {self.grid[0]} x {self.grid[1]} part of the board: partly out of view)" if self.partial
                else "")
        width = "" if self.edge_width_px is None else f", edges {self.edge_width_px:.1f} px"
        return f"{self.corners} corners{part}{width}"


@dataclass
class CameraCalibration:
    """The calibrated camera and the verdict on every image.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
    rms_px : float
        Reprojection RMS over the used images, pixels.
    std_intrinsics : dict
        Standard deviations of fx, fy, cx, cy (pixels) and the distortion terms, from OpenCV.
    images : list of ImageResult
    board : BoardSpec
    fix_k3 : bool
    fix_k2 : bool
        k2 (and k3) held at 0.
    quality : dict
        :func:`judge_calibration`'s verdict, reasons, measures and advice.
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    std_intrinsics: dict
    images: list
    board: BoardSpec
    fix_k3: bool
    fix_k2: bool = False
    quality: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return self.quality.get("verdict", "pass")

    @property
    def used(self) -> int:
        return sum(1 for r in self.images if r.accepted)


def edge_width_px(image: np.ndarray, points: np.ndarray, spacing_px: float, max_points: int = 40) -> float:
    """Median width of the board's edges near the given corners, pixels.

    For each corner (at most *max_points*, evenly picked), in a window of about a third of the corner
    spacing: the local contrast (95th - 5th percentile) over the mean of the steepest gradients (central
    differences). A sharp edge is about 2 px wide; a Gaussian blur of sigma px makes it about 2.5 sigma.
    """
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    half = int(max(3, min(40, round(0.35 * spacing_px))))
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pick = pts[np.linspace(0, len(pts) - 1, min(max_points, len(pts))).astype(int)] if len(pts) else pts
    widths = []
    for x, y in pick:
        c, r = int(round(x)), int(round(y))
        if r - half < 1 or c - half < 1 or r + half >= h - 1 or c + half >= w - 1:
            continue
        patch = img[r - half:r + half + 1, c - half:c + half + 1]
        gy, gx = np.gradient(patch)
        grad = np.hypot(gx, gy).ravel()
        lo, hi = np.percentile(patch, [5, 95])
        top = np.sort(grad)[-half:].mean()
        if top > 0 and hi - lo > 10:
            widths.append((hi - lo) / top)
    return float(np.median(widths)) if widths else float("nan")


def _spacing(points: np.ndarray) -> float:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return 20.0
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _refine_half(corners: np.ndarray, clear_fraction: float = 0.5) -> int:
    """Half-width (pixels) of :func:`_refine`'s window: half of *clear_fraction* of the corner spacing,
    2 to 11 px."""
    return int(np.clip(round(0.5 * clear_fraction * _spacing(corners)), 2, 11))


def _refine(img: np.ndarray, corners: np.ndarray, clear_fraction: float = 0.5) -> np.ndarray:
    """Saddle-point refinement of chessboard corners.

    The sector-based chessboard detector places corners to about 0.15 px; the classic refinement, in a
    window reaching half of *clear_fraction* of the corner spacing (at most 11 px) from the corner, brings
    that to a few hundredths.
    """
    pts = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    half = _refine_half(pts, clear_fraction)
    out = cv2.cornerSubPix(img, pts.copy(), (half, half), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    return out.reshape(-1, 2).astype(np.float32)


def grid_points(cols: int, rows: int, square_m: float) -> np.ndarray:
    """Board-frame points (cols * rows, 3), metres, of a grid of cols x rows corners one square apart, row
    after row (x along a row), the first at (square_m, square_m): a chessboard's inner corners."""
    j, i = np.mgrid[1:rows + 1, 1:cols + 1]
    return np.column_stack([i.ravel() * square_m, j.ravel() * square_m, np.zeros(i.size)]).astype(np.float32)


def smallest_part(inner: tuple[int, int]) -> int:
    """Inner corners along each side of the smallest part of a chessboard that :func:`find_chessboard`
    accepts (:data:`PARTIAL_FRACTION` of the shorter side, at least :data:`MIN_PART`, at most the side)."""
    return min(min(inner), max(MIN_PART, math.ceil(PARTIAL_FRACTION * min(inner))))


def cells_alternate(image: np.ndarray, corners: np.ndarray, grid: tuple[int, int]) -> bool:
    """Whether a grid of corners is a chessboard's: every cell one square, alternately dark and light.

    Each cell (four neighbouring corners) is sampled at its centre and at four points 30 % and 70 % of the
    way along both of its sides (bilinearly between its corners); its value is their mean, its spread their
    range. The grid is a chessboard's when every pair of neighbouring cells differs with the sign the
    chessboard's parity gives, by at least a quarter of the median difference, and more than twice the
    spread of either cell. A grid that skips a row of corners (cells of two squares), or whose outer row
    lies on the board's border, fails: the sector-based detector, asked for a part of a board, grows such
    grids on boards seen close and cut diagonally by the image's edge.

    Parameters
    ----------
    image : (H, W) uint8 array
    corners : (cols * rows, 2) array
        Pixels, row after row.
    grid : (cols, rows)
    """
    # lazy: scipy.ndimage costs ~250 ms CPU; config.py loads this module's record reader at every start
    from scipy.ndimage import map_coordinates

    cols, rows = grid
    if cols < 2 or rows < 2:
        return False
    g = np.asarray(corners, dtype=np.float64).reshape(rows, cols, 2)
    p00, p01, p10, p11 = g[:-1, :-1], g[:-1, 1:], g[1:, :-1], g[1:, 1:]
    samples = []
    for a, b in ((0.5, 0.5), (0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7)):
        pt = (1 - a) * (1 - b) * p00 + a * (1 - b) * p01 + (1 - a) * b * p10 + a * b * p11
        samples.append(map_coordinates(np.asarray(image, dtype=np.float64), [pt[..., 1].ravel(), pt[..., 0].ravel()],
                                       order=1, mode="nearest").reshape(pt.shape[:2]))
    samples = np.stack(samples)
    value, spread = samples.mean(axis=0), np.ptp(samples, axis=0)
    parity = np.where((np.add.outer(np.arange(rows - 1), np.arange(cols - 1)) % 2) == 0, 1.0, -1.0)
    # parity-corrected differences of neighbouring cells (across, then down): one sign on a chessboard
    diffs = [(value[:, :-1] - value[:, 1:]) * parity[:, :-1], (value[:-1, :] - value[1:, :]) * parity[:-1, :]]
    spreads = [np.maximum(spread[:, :-1], spread[:, 1:]), np.maximum(spread[:-1, :], spread[1:, :])]
    d = np.concatenate([x.ravel() for x in diffs])
    sp = np.concatenate([x.ravel() for x in spreads])
    if d.size == 0:
        return False
    d = d * np.sign(np.median(d))
    typical = float(np.median(d))
    return bool(typical > 0 and np.all(d >= 0.25 * typical) and np.all(d > 2.0 * sp))


def grid_deviation(corners: np.ndarray, grid: tuple[int, int]) -> tuple[float, float]:
    """How far a grid of corners is from a chessboard's seen through a lens: the largest bend and the
    largest cross-ratio error over every run of four neighbouring corners along a row or a column.

    A projection keeps straight lines straight and the cross-ratio of four equally spaced points at
    4/3, however strong the perspective; a lens's distortion bends a run of four corners only a little.
    A corner given the wrong place in the grid (a row shifted by one corner, two grid places on one
    corner, a row skipped) breaks one or the other by a large fraction.

    Returns
    -------
    (bend, cross_ratio_error)
        Largest distance of a run's middle corners from the line through its ends, over that line's
        length; largest ``|cross-ratio / (4/3) - 1|`` (infinite where a run's corners are not in order).
    """
    cols, rows = grid
    g = np.asarray(corners, dtype=np.float64).reshape(rows, cols, 2)
    bend, error = 0.0, 0.0
    for run in (g, g.transpose(1, 0, 2)):
        if run.shape[1] < 4:
            continue
        p0, p1, p2, p3 = (run[:, k:run.shape[1] - 3 + k] for k in range(4))
        chord = p3 - p0
        length = np.linalg.norm(chord, axis=2)
        u = chord / np.maximum(length, 1e-9)[..., None]
        t1, t2 = (np.sum((p - p0) * u, axis=2) for p in (p1, p2))
        s1, s2 = (np.abs(u[..., 0] * (p - p0)[..., 1] - u[..., 1] * (p - p0)[..., 0]) for p in (p1, p2))
        bend = max(bend, float(np.max(np.maximum(s1, s2) / np.maximum(length, 1e-9))))
        ordered = (t1 > 0) & (t2 > t1) & (length > t2)
        if not np.all(ordered):
            return bend, float("inf")
        ratio = t2 * (length - t1) / (length * (t2 - t1))
        error = max(error, float(np.max(np.abs(ratio / (4.0 / 3.0) - 1.0))))
    return bend, error


def _trim(grid_pts: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """The grid (rows, cols, 2) without the outer rows and columns that hold *bad* corners (rows, cols),
    one at a time, the side with the most first; empty when a bad corner is not on the grid's edge."""
    g, b = grid_pts, bad
    while g.shape[0] and g.shape[1] and b.any():
        sides = {"top": b[0].sum(), "bottom": b[-1].sum(), "left": b[:, 0].sum(), "right": b[:, -1].sum()}
        worst = max(sides, key=sides.get)
        if sides[worst] == 0:
            return g[:0]
        cut = {"top": np.s_[1:, :], "bottom": np.s_[:-1, :], "left": np.s_[:, 1:], "right": np.s_[:, :-1]}[worst]
        g, b = g[cut], b[cut]
    return g


def grid_outliers(corners: np.ndarray, grid: tuple[int, int], reach: int = 2) -> np.ndarray:
    """How far each corner lies from where its neighbours put it, in local corner spacings (rows, cols).

    For each corner, a homography from grid to image fitted to the corners within *reach* places of it
    (itself left out, at least a 3 x 3 spread) predicts it; the distance to the prediction is divided by
    the predicted distance to the next corner. A homography holds over a few squares through any lens a
    calibration meets: on true grids the largest value is under 0.17 (docs/calibration.md); a corner
    refined onto the board's border, or given another's place, is half a spacing or more off. NaN where
    too few neighbours.
    """
    cols, rows = grid
    g = np.asarray(corners, dtype=np.float64).reshape(rows, cols, 2)
    jj, ii = np.mgrid[0:rows, 0:cols]
    out = np.full((rows, cols), np.nan)
    for r in range(rows):
        for c in range(cols):
            near = (np.abs(jj - r) <= reach) & (np.abs(ii - c) <= reach)
            near[r, c] = False
            src = np.column_stack([ii[near], jj[near]]).astype(np.float64)
            if len(src) < 6 or np.ptp(src[:, 0]) < 2 or np.ptp(src[:, 1]) < 2:
                continue
            h, _ = cv2.findHomography(src, g[near], 0)
            if h is None:
                continue
            p = h @ np.array([[c, c + 1, c], [r, r, r + 1], [1.0, 1.0, 1.0]])
            p = (p[:2] / p[2]).T
            spacing = min(np.linalg.norm(p[1] - p[0]), np.linalg.norm(p[2] - p[0]))
            out[r, c] = np.linalg.norm(p[0] - g[r, c]) / spacing
    return out


def find_chessboard(image: np.ndarray, inner: tuple[int, int],
                    notes: list[str] | None = None) -> tuple[np.ndarray, tuple[int, int]] | None:
    """The inner corners of a chessboard in a grey image, or of the largest part of it in view.

    OpenCV's sector-based detector (``findChessboardCornersSBWithMeta``) with ``CALIB_CB_EXHAUSTIVE`` and
    ``CALIB_CB_LARGER``, asked for a grid of at least m x m corners (:func:`smallest_part`) so that it
    returns the whole board or the largest part of it it can grow, on the image locally equalised (CLAHE:
    a board lit unevenly, whose weaker corners fail the detector's global tests, see docs/calibration.md)
    and on the image as it is with ``CALIB_CB_NORMALIZE_IMAGE`` (global equalisation: squares larger than
    CLAHE's tiles), at full size, then halved again and again (:data:`MIN_SEARCH_SIDE`), until the whole
    board is found. The largest grid that checks out wins; its corners are refined on the full image.

    The detector, asked for a part of a board, sometimes grows a wrong grid (skipping a row of corners,
    or taking the board's border for a row) on a board seen close and cut by the image's edge: a grid is
    taken only when its cells alternate dark and light (:func:`cells_alternate`) and its corners, refined
    (:func:`_refine`), lie where their neighbours put them (:func:`grid_outliers`; an outer row or column
    holding one is dropped, as one reaching outside the image is) and keep straight runs and their
    cross-ratios (:func:`grid_deviation`).

    Parameters
    ----------
    image : (H, W) uint8 array
    inner : (int, int)
        The board's inner corners, across x down.
    notes : list, optional
        Receives why a grid the detector found was not taken.

    Returns
    -------
    (corners, grid) or None
        Refined corners (n, 2) float32, pixels, row after row of a grid (cols, rows) = ``grid``, which may be
        larger than *inner* (the caller judges that), or the board turned; None when no grid was found.
    """
    m = smallest_part(inner)
    whole = inner[0] * inner[1]
    best = None
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_LARGER
    clahe = cv2.createCLAHE(clipLimit=CLAHE_CLIP, tileGridSize=CLAHE_TILES)
    h, w = image.shape[:2]
    note = notes.append if notes is not None else (lambda text: None)
    scales = [0.5 ** k for k in range(8) if 0.5 ** k * min(h, w) >= MIN_SEARCH_SIDE] or [1.0]
    for scale, equalise in ((scale, equalise) for scale in scales for equalise in (True, False)):
        img = image if scale == 1 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        found, corners, meta = cv2.findChessboardCornersSBWithMeta(
            clahe.apply(img) if equalise else img, (m, m), flags | (0 if equalise else cv2.CALIB_CB_NORMALIZE_IMAGE))
        if not found or corners is None or meta is None:
            continue
        rows, cols = meta.shape[:2]
        # back to the full image's pixels (pixel centres at whole numbers in both)
        pts = ((np.asarray(corners, dtype=np.float64).reshape(-1, 2) + 0.5) / scale - 0.5).astype(np.float32)
        if len(pts) != rows * cols:
            continue
        g = pts.reshape(rows, cols, 2)
        kept = _trim(g, ~np.all((g >= 0) & (g <= (w - 1, h - 1)), axis=2))
        if min(kept.shape[:2]) < m:
            note(f"a {cols} x {rows} grid reaching outside the image")
            continue
        rows, cols = kept.shape[:2]
        pts = np.ascontiguousarray(kept.reshape(-1, 2))
        if not cells_alternate(image, pts, (cols, rows)):
            note(f"a {cols} x {rows} grid whose cells are not alternately dark and light")
            continue
        pts = _refine(image, pts)
        # a corner refined off its place (onto the board's border, at the image's edge): its row goes
        off = np.nan_to_num(grid_outliers(pts, (cols, rows)))      # NaN: too few neighbours to judge
        kept = _trim(pts.reshape(rows, cols, 2), off > MAX_OFF_SPACING)
        if min(kept.shape[:2]) < m:
            note(f"a {cols} x {rows} grid with corners off their neighbours' lines (by {off.max():.2f} spacings)")
            continue
        rows, cols = kept.shape[:2]
        pts = np.ascontiguousarray(kept.reshape(-1, 2))
        bend, ratio_error = grid_deviation(pts, (cols, rows))
        if bend > MAX_BEND or ratio_error > MAX_CROSS_RATIO_ERROR:
            note(f"a {cols} x {rows} grid whose corners are out of line (bend {bend:.2f}, cross-ratio error "
                 f"{ratio_error:.2f})")
            continue
        if best is None or len(pts) > len(best[0]):
            best = (pts, (int(cols), int(rows)))
        if len(pts) >= whole:
            break
    return best


def detect_board(image: np.ndarray, board: BoardSpec, name: str = "", min_corners: int = 12,
                 max_edge_width_px: float = 4.0) -> ImageResult:
    """Find the board's corners in a grey image and judge the image.

    Parameters
    ----------
    image : (H, W) uint8 array
    board : BoardSpec
    name : str
        For messages.
    min_corners : int
        Fewest corners accepted (a chessboard partly out of view; ChArUco).
    max_edge_width_px : float
        Images whose edges are wider are rejected as blurred, pixels.

    Returns
    -------
    ImageResult
        ``accepted`` with object and image points, or a reason.
    """
    out = ImageResult(name)
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        raise CalibrationError(f"{name}: board images must be 8-bit, got {img.dtype}")
    out.shape = img.shape[:2]
    if board.kind == "chessboard":
        inner = (board.squares_x - 1, board.squares_y - 1)
        notes: list[str] = []
        found = find_chessboard(img, inner, notes)
        if found is None:
            m = smallest_part(inner)
            seen = f"; not taken: {', '.join(dict.fromkeys(notes))}" if notes else ""
            out.reason = (f"board not found: no chessboard grid of {m} x {m} inner corners or more (the board has "
                          f"{inner[0]} x {inner[1]}){seen}; the board, or a good part of it, must be in view, in "
                          "focus and lit")
            return out
        corners, out.grid = found
        cols, rows = out.grid
        out.corners = cols * rows
        if not ((cols <= inner[0] and rows <= inner[1]) or (cols <= inner[1] and rows <= inner[0])):
            out.reason = (f"board larger than stated: {cols} x {rows} inner corners found, but a {board.squares_x} x "
                          f"{board.squares_y}-square board has {inner[0]} x {inner[1]}; --squares counts squares, not "
                          f"inner corners (a board of {cols} x {rows} inner corners has {cols + 1} x {rows + 1} "
                          "squares)")
            return out
        out.partial = cols * rows < board.n_corners
        obj_pts = grid_points(cols, rows, board.square_m)
        # a corner whose refinement window leaves the image (a board partly out of view) would be refined
        # on replicated border pixels: leave it out
        half = _refine_half(corners) + 1
        h, w = img.shape
        keep = ((corners[:, 0] >= half) & (corners[:, 0] <= w - 1 - half) & (corners[:, 1] >= half)
                & (corners[:, 1] <= h - 1 - half))
        obj_pts, img_pts = obj_pts[keep], corners[keep]
        if len(img_pts) < min_corners:
            out.corners = len(img_pts)
            out.reason = (f"too few corners: {len(img_pts)} of {board.n_corners} clear of the image's edge, at least "
                          f"{min_corners} needed")
            return out
    else:
        cb = board.charuco()
        detector = cv2.aruco.CharucoDetector(cb)
        ch_corners, ch_ids, _, marker_ids = detector.detectBoard(img)
        n = 0 if ch_ids is None else len(ch_ids)
        if n == 0:
            out.reason = ("board not found (no ChArUco corner; markers seen: "
                          f"{0 if marker_ids is None else len(marker_ids)})")
            return out
        if n < min_corners:
            out.corners = n
            out.reason = f"too few corners: {n} of {board.n_corners} found, at least {min_corners} needed"
            return out
        if cb.checkCharucoCornersCollinear(ch_ids):
            out.corners = n
            out.reason = f"too few corners: the {n} corners found lie on one line"
            return out
        # (the detector refines its interpolated corners itself, in a window clear of the markers)
        obj_pts, img_pts = cb.matchImagePoints(ch_corners, ch_ids)
        obj_pts = obj_pts.reshape(-1, 3).astype(np.float32)
        img_pts = img_pts.reshape(-1, 2).astype(np.float32)
    out.corners = len(img_pts)
    out.edge_width_px = edge_width_px(img, img_pts, _spacing(img_pts))
    if not np.isfinite(out.edge_width_px):
        out.reason = "blurred: no edge near the corners has enough contrast"
        return out
    if out.edge_width_px > max_edge_width_px:
        out.reason = (f"blurred: edges {out.edge_width_px:.1f} px wide (at most {max_edge_width_px:g} px accepted); "
                      "focus the lens, or hold the board still")
        return out
    out.accepted = True
    out.object_points, out.image_points = obj_pts, img_pts
    return out


def coverage(points: list[np.ndarray], width_px: int, height_px: int, grid: tuple[int, int] = COVERAGE_GRID,
             corner_zone: float = CORNER_ZONE) -> dict:
    """How the detected points of all views cover the image.

    Returns
    -------
    dict
        ``cells``: fraction of the grid's cells holding a point; ``corners``: how many of the image's four
        corner zones (*corner_zone* of the width and height from each corner) hold one; ``border``:
        fraction of the grid's outer ring of cells holding one; ``grid``.
    """
    gx, gy = grid
    pts = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points]) if points else np.empty((0, 2))
    hit = np.zeros((gy, gx), dtype=bool)
    if len(pts):
        cx = np.clip((pts[:, 0] / width_px * gx).astype(int), 0, gx - 1)
        cy = np.clip((pts[:, 1] / height_px * gy).astype(int), 0, gy - 1)
        hit[cy, cx] = True
    ring = np.ones_like(hit)
    ring[1:-1, 1:-1] = False
    zx, zy = corner_zone * width_px, corner_zone * height_px
    corners = 0
    for left in (True, False):
        for top in (True, False):
            inx = pts[:, 0] < zx if left else pts[:, 0] > width_px - zx
            iny = pts[:, 1] < zy if top else pts[:, 1] > height_px - zy
            corners += int(np.any(inx & iny))
    return {"cells": float(hit.mean()), "border": float(hit[ring].mean()), "corners": corners, "grid": [gx, gy]}


def distortion_corner_px(intrinsics: CameraIntrinsics, std_distortion) -> float:
    """Displacement (pixels) at the image's farthest corner that one standard deviation of each distortion
    term leaves, combined in quadrature (radial terms k r^2, k r^4, k r^6 of the normalised radius r,
    tangential p about 3 r^2)."""
    k = intrinsics.matrix
    f = 0.5 * (k[0, 0] + k[1, 1])
    w, h = intrinsics.width_px, intrinsics.height_px
    dx = max(k[0, 2], w - k[0, 2])
    dy = max(k[1, 2], h - k[1, 2])
    r = float(np.hypot(dx, dy) / f)
    s = np.zeros(5)
    sd = np.asarray(std_distortion, float).ravel()[:5]
    s[:sd.size] = np.nan_to_num(sd)
    k1, k2, p1, p2, k3 = s
    radial = np.hypot(np.hypot(k1 * r ** 2, k2 * r ** 4), k3 * r ** 6) * r
    tangential = np.hypot(p1, p2) * 3.0 * r ** 2
    return float(f * np.hypot(radial, tangential))


def judge_calibration(intrinsics: CameraIntrinsics, rms_px: float, std: dict, points: list[np.ndarray], *,
                      fix_k2: bool = False, fix_k3: bool = True) -> dict:
    """The calibration's verdict: ``pass``, ``warn`` or ``refused`` (parameters not determined).

    Each measure is compared with its (warn, refuse) thresholds (module constants); the coverage only
    warns (it explains a refusal, it does not make one).

    Returns
    -------
    dict
        ``verdict``, ``reasons`` (what is beyond a threshold), ``measures`` (rms_px, focal_relative,
        principal_of_width, distortion_corner_px, coverage), ``thresholds`` and ``advice`` (what to do).
    """
    k = intrinsics.matrix
    w = intrinsics.width_px
    focal_rel = max(std["fx"] / k[0, 0], std["fy"] / k[1, 1])
    principal = max(std["cx"], std["cy"]) / w
    dist_px = distortion_corner_px(intrinsics, std["distortion"])
    cov = coverage(points, intrinsics.width_px, intrinsics.height_px)
    measures = {"rms_px": float(rms_px), "focal_relative": float(focal_rel), "principal_of_width": float(principal),
                "distortion_corner_px": dist_px, "coverage": cov}
    thresholds = {"rms_px": RMS_PX, "focal_relative": FOCAL_RELATIVE, "principal_of_width": PRINCIPAL_OF_WIDTH,
                  "distortion_corner_px": DISTORTION_CORNER_PX, "min_coverage": MIN_COVERAGE,
                  "corner_zone": CORNER_ZONE}
    text = {
        "rms_px": lambda v, t: f"reprojection RMS {v:.3f} px (over {t:g} px)",
        "focal_relative": lambda v, t: (f"focal length +- {100 * v:.2f} % (fx +- {std['fx']:.2f}, fy +- "
                                        f"{std['fy']:.2f} px; over {100 * t:g} %)"),
        "principal_of_width": lambda v, t: (f"principal point +- ({std['cx']:.1f}, {std['cy']:.1f}) px, "
                                            f"{100 * v:.2f} % of the image width (over {100 * t:g} %)"),
        "distortion_corner_px": lambda v, t: (f"distortion uncertain by {v:.2f} px at the image corners "
                                              f"(k1 +- {std['distortion'][0]:.3g}, k2 +- {std['distortion'][1]:.3g}; "
                                              f"over {t:g} px)"),
    }
    refuse, warn = [], []
    for key, (t_warn, t_refuse) in (("rms_px", RMS_PX), ("focal_relative", FOCAL_RELATIVE),
                                    ("principal_of_width", PRINCIPAL_OF_WIDTH),
                                    ("distortion_corner_px", DISTORTION_CORNER_PX)):
        v = measures[key]
        if not np.isfinite(v) or v > t_refuse:
            refuse.append(text[key](v, t_refuse))
        elif v > t_warn:
            warn.append(text[key](v, t_warn))
    cover = (f"the views' points cover {100 * cov['cells']:.0f} % of the image ({cov['grid'][0]} x {cov['grid'][1]} "
             f"cells) and reach {cov['corners']} of its 4 corners")
    if cov["cells"] < MIN_COVERAGE or cov["corners"] < 4:
        warn.append(cover + f" (at least {100 * MIN_COVERAGE:g} % and all 4 wanted)")
    advice = []
    if cov["cells"] < MIN_COVERAGE or cov["corners"] < 4:
        advice.append("take views with the board reaching into the image's corners and along its edges")
    if refuse or warn:
        advice.append("take more views (15-25), the board tilted 20-40 degrees about both of its axes, "
                      "at several distances")
    if (measures["distortion_corner_px"] > DISTORTION_CORNER_PX[0] or principal > PRINCIPAL_OF_WIDTH[0]) \
            and not fix_k2:
        advice.append("for a long lens, whose small distortion the views cannot separate from the principal "
                      "point, hold k2 at 0 (--fix-k2)" + ("" if fix_k3 else " and k3 (leave out --k3)"))
    if principal > PRINCIPAL_OF_WIDTH[1]:
        fov = float(np.degrees(2 * np.arctan(0.5 * w / k[0, 0])))
        advice.append(f"a lens whose field of view is narrow ({fov:.1f} degrees across) locates its principal point "
                      "poorly whatever the views: if more views do not help, keep the [camera] table's values "
                      "and state their uncertainty in [uncertainty] camera_principal_px")
    if rms_px > RMS_PX[0]:
        advice.append("check --squares and --square-mm against the board, its flatness, and the focus")
    verdict = "refused" if refuse else ("warn" if warn else "pass")
    return {"verdict": verdict, "reasons": refuse + warn, "refuse_reasons": refuse, "warnings": warn,
            "measures": measures, "thresholds": thresholds, "advice": advice, "coverage_text": cover}


def read_image(path: str | Path) -> np.ndarray | None:
    """A grey 8-bit image from a file, or None when OpenCV cannot read it.

    A deeper image (a 12-bit camera's 16-bit PNG or TIFF) is scaled to 8 bits by its own brightness (its
    99.9th percentile reads 255): OpenCV's plain 8-bit reading divides by 256, which leaves 12-bit data
    the values 0..15.
    """
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE | cv2.IMREAD_ANYDEPTH)
    if img is None or img.dtype == np.uint8:
        return img
    values = np.nan_to_num(img.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    top = float(np.percentile(values, 99.9))
    top = top if top > 0 else float(values.max())
    if top <= 0:
        return np.zeros(values.shape, dtype=np.uint8)
    return np.clip(np.round(values * (255.0 / top)), 0, 255).astype(np.uint8)


def judge_images(images: list[tuple[str, np.ndarray | str | Path | None]], board: BoardSpec, *, min_corners: int = 12,
                 max_edge_width_px: float = 4.0, workers: int | None = None,
                 progress: Callable[[str], None] | None = None) -> list[ImageResult]:
    """Read and search the board images in parallel threads (OpenCV releases the GIL).

    Parameters
    ----------
    images : list of (name, image)
        A grey uint8 array, a file to read (:func:`read_image`), or None (a file that could not be read).
    board : BoardSpec
    min_corners, max_edge_width_px : see :func:`detect_board`
    workers : int, optional
        Threads (default: the machine's cores).
    progress : callable, optional
        Receives one line per image, in the given order, as it is judged (default: the log):
        ``image 3/10 DSC0003.png: 414 corners, edges 2.8 px`` or ``...: rejected: <reason>``.

    Returns
    -------
    list of ImageResult
        In the given order; an image whose size differs from the first readable one's is rejected.
    """
    say = progress or log.info
    items = list(images)

    def judge(item) -> ImageResult:
        name, img = item
        if isinstance(img, (str, os.PathLike)):
            img = read_image(img)
        if img is None:
            return ImageResult(name, reason="cannot be read as an image")
        return detect_board(img, board, name, min_corners, max_edge_width_px)

    results: list[ImageResult] = []
    size = None
    with ThreadPoolExecutor(max_workers=max(1, workers or os.cpu_count() or 1)) as pool:
        for k, res in enumerate(pool.map(judge, items), 1):
            if res.shape is not None:
                size = size or res.shape
                if res.shape != size:
                    res = ImageResult(res.name, reason=f"size {res.shape[1]} x {res.shape[0]} differs from the first "
                                                       f"image's {size[1]} x {size[0]}", shape=res.shape)
            say(f"image {k}/{len(items)} {res.name}: {res.describe()}")
            results.append(res)
    return results


def calibrate_camera_images(images: list[tuple[str, np.ndarray | str | Path | None]], board: BoardSpec, *,
                            fix_k3: bool = True, min_images: int = 5, min_corners: int = 12,
                            max_edge_width_px: float = 4.0, outlier_factor: float = 3.0, fix_k2: bool = False,
                            refuse: bool = True, workers: int | None = None,
                            progress: Callable[[str], None] | None = None) -> CameraCalibration:
    """Intrinsics and distortion from board images.

    Parameters
    ----------
    images : list of (name, image)
        Grey uint8 images, files to read, or None (the file could not be read): :func:`judge_images`.
    board : BoardSpec
    fix_k3 : bool
        Hold k3 at 0.
    min_images : int
        Fewest usable images.
    min_corners, max_edge_width_px : see :func:`detect_board`
    outlier_factor : float
        Images whose reprojection RMS exceeds this times the median (and 0.5 px) are dropped once.
    fix_k2 : bool
        Hold k2 (and k3) at 0.
    refuse : bool
        Raise when :func:`judge_calibration` refuses (else the refused calibration is returned, its
        ``quality`` saying so).
    workers, progress : see :func:`judge_images`

    Returns
    -------
    CameraCalibration
        With ``quality`` (:func:`judge_calibration`).

    Raises
    ------
    CalibrationError
        Fewer than *min_images* usable images (the message lists why each was rejected), or parameters not
        determined (the message says which and what to do).
    """
    results = judge_images(images, board, min_corners=min_corners, max_edge_width_px=max_edge_width_px,
                           workers=workers, progress=progress)
    size = next((r.shape for r in results if r.accepted), None)

    def solve(used: list[ImageResult]):
        flags = cv2.CALIB_FIX_K3 if (fix_k3 or fix_k2) else 0
        flags |= cv2.CALIB_FIX_K2 if fix_k2 else 0
        return cv2.calibrateCameraExtended([r.object_points for r in used], [r.image_points for r in used],
                                           (size[1], size[0]), None, None, flags=flags)

    def need(used):
        if len(used) < min_images:
            lines = "\n".join(f"  {r.name}: {r.reason or 'used'}" for r in results)
            raise CalibrationError(f"only {len(used)} usable board image(s), at least {min_images} needed:\n{lines}")

    used = [r for r in results if r.accepted]
    need(used)
    rms, k, dist, _, _, std_int, _, per_view = solve(used)
    per_view = per_view.ravel()
    median = float(np.median(per_view))
    bad = [r for r, e in zip(used, per_view) if e > outlier_factor * median and e > 0.5]
    if bad:
        for r, e in zip(used, per_view):
            if r in bad:
                r.accepted = False
                r.reason = (f"reprojection RMS {e:.2f} px, more than {outlier_factor:g} x the median {median:.2f} px: "
                            "corners misdetected")
        used = [r for r in used if r.accepted]
        need(used)
        rms, k, dist, _, _, std_int, _, per_view = solve(used)
        per_view = per_view.ravel()
    for r, e in zip(used, per_view):
        r.rms_px = float(e)
    d = np.zeros(5)
    d[:min(5, dist.size)] = dist.ravel()[:5]
    intrinsics = CameraIntrinsics(size[1], size[0], k, d)
    s = std_int.ravel()
    std = {"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3]),
           "distortion": [float(v) for v in s[4:9]]}
    quality = judge_calibration(intrinsics, float(rms), std, [r.image_points for r in used], fix_k2=fix_k2,
                                fix_k3=fix_k3)
    cal = CameraCalibration(intrinsics, float(rms), std, results, board, fix_k3 or fix_k2, fix_k2, quality)
    if quality["verdict"] == "refused":
        if refuse:
            raise CalibrationError(refusal_text(cal))
        log.warning("camera calibration refused: %s", "; ".join(quality["refuse_reasons"]))
    return cal


def refusal_text(cal: CameraCalibration) -> str:
    """Why a calibration was refused and what to do (no record is written)."""
    q = cal.quality
    k = cal.intrinsics.matrix
    d = cal.intrinsics.distortion
    lines = [f"camera calibration refused: the parameters are not determined by the {cal.used} view(s) used "
             f"(fx {k[0, 0]:.1f}, principal point ({k[0, 2]:.1f}, {k[1, 2]:.1f}) px, k1 {d[0]:+.4g}, k2 {d[1]:+.4g}); "
             "no record was written:"]
    lines += [f"  - {r}" for r in q["refuse_reasons"]]
    lines += [f"  - {r}" for r in q["warnings"]]
    if not any(r.startswith(q["coverage_text"]) for r in q["warnings"]):
        lines.append(f"  ({q['coverage_text']})")
    lines.append("What to do: " + "; ".join(q["advice"]) + ".")
    return "\n".join(lines)


def read_images(paths: list[str | Path]) -> list[tuple[str, np.ndarray | None]]:
    """Read image files as grey uint8 (None for a file OpenCV cannot read): :func:`read_image`."""
    return [(str(p), read_image(p)) for p in paths]


def save_camera(data_dir: str | Path, cal: CameraCalibration, source: str, folder: str = "camera",
                station: dict | None = None) -> Path:
    """Write a camera record under ``data_dir/calibration/<folder>/``; returns its path. *folder* is
    ``camera`` (the station camera's records) or ``handheld`` (the second camera of ``calibrate screen``,
    never taken for the station camera); *station*, the identity of the station it is made on
    (:func:`~sofast_station.calibrate.store.write_record`).

    A refused calibration (parameters not determined) is never written: CalibrationError saying why."""
    if cal.verdict == "refused":
        raise CalibrationError(refusal_text(cal))
    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": "camera", "record_id": record_id, "created": created, "source": source,
                "camera": cal.intrinsics.to_dict(), "rms_px": cal.rms_px, "std_intrinsics": cal.std_intrinsics,
                "fix_k3": cal.fix_k3, "fix_k2": cal.fix_k2, "quality": cal.quality, "board": cal.board.to_dict(),
                "images": [r.to_dict() for r in cal.images]}
    if folder not in ("camera", "handheld"):
        raise ValueError(f"camera records go to 'camera' or 'handheld', not {folder!r}")
    path, _ = write_record(data_dir, folder, build, station=station)
    return path


def load_camera_record(path: str | Path) -> tuple[CameraIntrinsics, dict]:
    """Read a camera record: the intrinsics and the whole record; ConfigError naming the file otherwise."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"camera calibration record {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"camera calibration record {path} is corrupt ({exc}); rerun the calibration") from None
    if not isinstance(d, dict) or d.get("kind") != "camera" or d.get("schema") != SCHEMA:
        raise ConfigError(f"{path} is not a camera calibration record of schema {SCHEMA}")
    try:
        return CameraIntrinsics.from_dict(d["camera"]), d
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"camera calibration record {path} is incomplete ({exc}); rerun the calibration") from None


def summary_text(cal: CameraCalibration, path: Path | None = None) -> str:
    """A readable summary of a camera calibration."""
    k = cal.intrinsics.matrix
    s = cal.std_intrinsics
    lines = [f"Camera calibration from {len(cal.images)} image(s) of a {cal.board.squares_x} x {cal.board.squares_y} "
             f"{cal.board.kind}: {cal.used} used" + (f"; record {path}" if path else ""),
             f"  reprojection RMS {cal.rms_px:.3f} px",
             f"  fx {k[0, 0]:.2f} +- {s['fx']:.2f} px, fy {k[1, 1]:.2f} +- {s['fy']:.2f} px, "
             f"principal point ({k[0, 2]:.2f}, {k[1, 2]:.2f}) +- ({s['cx']:.2f}, {s['cy']:.2f}) px",
             "  distortion k1 k2 p1 p2 k3: " + " ".join(f"{v:+.5f}" for v in cal.intrinsics.distortion)
             + "  +- " + " ".join(f"{v:.5f}" for v in s["distortion"])]
    q = cal.quality
    if q:
        m = q["measures"]
        lines.append(f"  verdict: {q['verdict'].upper()} (focal length +- {100 * m['focal_relative']:.3f} %, principal "
                     f"point +- {100 * m['principal_of_width']:.2f} % of the width, distortion +- "
                     f"{m['distortion_corner_px']:.2f} px at the corners; {q['coverage_text']})")
        lines += [f"    - {r}" for r in q["reasons"]]
        if q["verdict"] != "pass" and q["advice"]:
            lines.append("    what to do: " + "; ".join(q["advice"]))
    for r in cal.images:
        if r.accepted:
            part = f" (a {r.grid[0]} x {r.grid[1]} part of the board)" if r.partial else ""
            lines.append(f"  {r.name}: used, {r.corners} corners{part}, RMS {r.rms_px:.3f} px, edges "
                         f"{r.edge_width_px:.1f} px")
        else:
            lines.append(f"  {r.name}: rejected: {r.reason}")
    return "\n".join(lines)
