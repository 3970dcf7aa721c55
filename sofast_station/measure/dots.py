"""A dot target's 3-D dot locations from photographs that also show ArUco markers of known position.

The fixed-pattern (dot grid) method needs where every dot of its target is, in the markers' frame. The
target is photographed from a few places; each photograph shows the dots and some of the markers
(:mod:`sofast_station.measure.markers`). Steps, each a function here:

1. :func:`find_dots`: candidate dots (OpenCV's ``SimpleBlobDetector``), each centred to a fraction of a pixel
   by its background-subtracted intensity moments over a disc re-centred until it stops moving;
2. :func:`index_dots`: the dots' lattice indices (i, j), counted from the dot nearest a given origin pixel,
   i along the image's columns and j along its rows, by walking the lattice: each next dot is looked for
   where its two predecessors on the same row or column say it should be;
3. :func:`locate_dots`: a bundle adjustment of reprojection errors (pixels) over every photograph's camera
   pose and every dot's position, the markers' corners known points that fix the frame; the noise of each
   kind of observation (marker corners, dots) is estimated from its residuals, outliers beyond 5 sigma are
   dropped, and each dot's covariance (the poses' uncertainty included) comes from the normal equations,
   reduced to the poses by the Schur complement (a dot's 3 x 3 block is independent of the others'
   given the poses, so 4000 dots cost no more than 4000 small inversions);
4. the indices are turned so that x index grows along the markers' frame's +x axis (or the first of its
   axes the lattice runs along) and y index along the next: :class:`DotLocations`, the (rows, columns, 3)
   grid OpenCSP's ``DotLocationsFixedPattern`` holds, with x and y index vectors.

Pure functions of arrays (numpy, OpenCV, scipy); no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ..geometry import CameraIntrinsics, Pose
from .bundle import camera_vector, moved, pose_derivative, project
from .camera import pixel_rays
from .kernels import dot_centroids, label_moments, laplacian_median, lattice_walk
from .markers import solve_camera_pose


# -- the grid --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DotLocations:
    """A dot target's 3-D dot locations on its index grid (OpenCSP's ``DotLocationsFixedPattern``).

    Attributes
    ----------
    x_index : (C,) int array
        The x index of each grid column, increasing by one.
    y_index : (R,) int array
        The y index of each grid row, increasing by one.
    xyz_m : (R, C, 3) float array
        Dot (x index ``x_index[c]``, y index ``y_index[r]``) at ``xyz_m[r, c]``, metres, in the markers'
        frame; NaN where the dot was not located.
    xyz_U_m : (R, C, 3) float array or None
        Expanded uncertainty (k = 2) of each coordinate, metres; None when unknown (OpenCSP's files).
    covariance_m2 : (R, C, 3, 3) float array or None
        Each dot's covariance, square metres.
    """

    x_index: np.ndarray
    y_index: np.ndarray
    xyz_m: np.ndarray
    xyz_U_m: np.ndarray | None = None
    covariance_m2: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self):
        x = np.asarray(self.x_index).astype(np.int64).ravel()
        y = np.asarray(self.y_index).astype(np.int64).ravel()
        xyz = np.asarray(self.xyz_m, np.float64)
        if x.size == 0 or y.size == 0 or np.any(np.diff(x) != 1) or np.any(np.diff(y) != 1):
            raise ValueError("dot indices must be consecutive integers, increasing by one")
        if xyz.shape != (y.size, x.size, 3):
            raise ValueError(f"dot locations must be (rows, columns, 3) = ({y.size}, {x.size}, 3), got {xyz.shape}")
        object.__setattr__(self, "x_index", x)
        object.__setattr__(self, "y_index", y)
        object.__setattr__(self, "xyz_m", xyz)
        if self.xyz_U_m is not None:
            u = np.asarray(self.xyz_U_m, np.float64)
            if u.shape != xyz.shape:
                raise ValueError(f"dot uncertainties must have the locations' shape {xyz.shape}, got {u.shape}")
            object.__setattr__(self, "xyz_U_m", u)

    @property
    def located(self) -> np.ndarray:
        """(R, C) bool: the dots that were located."""
        return np.all(np.isfinite(self.xyz_m), axis=2)

    def dot(self, x_index: int, y_index: int) -> np.ndarray:
        """The location (3,) of one dot, metres (NaN when it was not located); IndexError outside the grid."""
        c, r = int(x_index) - int(self.x_index[0]), int(y_index) - int(self.y_index[0])
        if not (0 <= c < self.x_index.size and 0 <= r < self.y_index.size):
            raise IndexError(f"dot ({x_index}, {y_index}) is outside the grid x {self.x_index[0]}..{self.x_index[-1]}, "
                             f"y {self.y_index[0]}..{self.y_index[-1]}")
        return self.xyz_m[r, c]


def dot_grid(indices: np.ndarray, xyz_m: np.ndarray, covariance_m2: np.ndarray | None = None) -> DotLocations:
    """Scattered dots -> the index grid OpenCSP's fixed-pattern files hold.

    Parameters
    ----------
    indices : (N, 2) int array
        Each dot's (x index, y index), each pair once.
    xyz_m : (N, 3) array
        Its location, metres.
    covariance_m2 : (N, 3, 3) array, optional
        Its covariance: the grid then carries each coordinate's expanded uncertainty (k = 2) too.

    Returns
    -------
    DotLocations
        Spanning the smallest and largest indices; NaN where no dot was given.
    """
    indices = np.asarray(indices, np.int64).reshape(-1, 2)
    xyz_m = np.asarray(xyz_m, np.float64).reshape(-1, 3)
    if indices.shape[0] == 0 or indices.shape[0] != xyz_m.shape[0]:
        raise ValueError(f"need as many indices as dots (and at least one), got {indices.shape[0]} and "
                         f"{xyz_m.shape[0]}")
    if np.unique(indices, axis=0).shape[0] != indices.shape[0]:
        raise ValueError("each dot index (x, y) may be given once")
    lo, hi = indices.min(axis=0), indices.max(axis=0)
    shape = (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    xyz = np.full(shape + (3,), np.nan)
    rows, cols = indices[:, 1] - lo[1], indices[:, 0] - lo[0]
    xyz[rows, cols] = xyz_m
    cov = u = None
    if covariance_m2 is not None:
        cov = np.full(shape + (3, 3), np.nan)
        cov[rows, cols] = np.asarray(covariance_m2, np.float64).reshape(-1, 3, 3)
        u = 2.0 * np.sqrt(np.clip(np.diagonal(cov, axis1=2, axis2=3), 0.0, None))
    return DotLocations(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1), xyz, u, cov)


# -- finding and indexing --------------------------------------------------------------------------------------
def _centroids(image: np.ndarray, starts: np.ndarray, radius_px: float, dark: bool, iterations: int = 10,
               details: bool = False):
    """Background-subtracted intensity centroids of the dots near *starts*, each over a disc of 1.5 typical
    radii (plus a pixel) re-centred until it stops moving; the background is the median of a ring two
    pixels wide around the starting disc.

    Noise in the disc pulls a centroid toward the disc's centre, which converges onto the dot's, so the
    fixed point carries no bias from it. Returns the centres (N, 2) and a mask of those found (a dot too
    near the image's edge, or with no signal, is not); with *details* also a dict of (N, ...) arrays (NaN
    where not found): ``cov_unit_px2`` (N, 2, 2), the centroid's covariance per unit pixel-noise variance
    (the centroid c = sum w x / W moves by -(x - c) / W for a unit change of a pixel of weight w > 0, and the
    pixels' noise is independent: sum over the disc's pixels of weight above 0 of (x - c)(x - c)^T / W^2;
    a pixel clipped to weight 0 moves nothing), ``background_dn`` (the ring's median), ``ring_sigma_dn``
    (the ring's scatter, 1.4826 times its median absolute deviation: the image's noise beside the dot) and
    ``depth_dn`` (the largest background-subtracted signal in the disc)."""
    centres, ok, cov, background, ring_sigma, depth = dot_centroids(image, np.asarray(starts, np.float64),
                                                                     radius_px, dark, iterations)
    if not details:
        return centres, ok
    return centres, ok, {"cov_unit_px2": cov, "background_dn": background, "ring_sigma_dn": ring_sigma,
                         "depth_dn": depth}


def find_dots(image: np.ndarray, *, dark: bool = True, min_area_px: float = 3.0, max_area_px: float = 2000.0,
              min_circularity: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """Round dots in a grey photograph, each centred to a fraction of a pixel.

    Parameters
    ----------
    image : (H, W) uint8 array
    dark : bool
        Dark dots on a light target (the default), else light dots on a dark one.
    min_area_px, max_area_px : float
        Accepted blob areas, square pixels.
    min_circularity : float
        4 pi area / perimeter^2 of an accepted blob (1 for a disc).

    Returns
    -------
    centres_px : (N, 2) array
        (column, row), pixels (centres at integers).
    diameters_px : (N,) array
        OpenCV's blob diameters, pixels.
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"find_dots needs a grey uint8 image, got {img.dtype} {img.shape}")
    if not 0 < min_area_px < max_area_px:
        raise ValueError(f"need 0 < min_area_px < max_area_px, got {min_area_px}, {max_area_px}")
    params = cv2.SimpleBlobDetector_Params()
    # thresholds beyond the image's median grey find no dark dot a lattice walk needs (they sit on a lighter
    # target) and cost half the detector's time; light dots: the thresholds start at the median
    median = float(np.median(img[::4, ::4]))
    if dark:
        params.maxThreshold = float(np.clip(median + 10.0, params.minThreshold + 20.0, 250.0))
    else:
        params.minThreshold = float(np.clip(median - 10.0, 5.0, params.maxThreshold - 20.0))
    params.filterByColor = True
    params.blobColor = 0 if dark else 255
    params.minDistBetweenBlobs = 2.0
    params.filterByArea = True
    params.minArea = float(min_area_px)
    params.maxArea = float(max_area_px)
    params.filterByCircularity = True
    params.minCircularity = float(min_circularity)
    params.filterByConvexity = False
    params.filterByInertia = False
    keypoints = cv2.SimpleBlobDetector_create(params).detect(img)
    if not keypoints:
        return np.zeros((0, 2)), np.zeros(0)
    starts = np.array([k.pt for k in keypoints], np.float64)
    sizes = np.array([k.size for k in keypoints], np.float64)
    # a blob far larger or smaller than the typical one is not one of the dots
    typical = float(np.median(sizes))
    keep = (sizes <= 2.0 * typical) & (sizes >= 0.5 * typical)
    starts, sizes = starts[keep], sizes[keep]
    centres, found = _centroids(img, starts, max(typical / 2.0, 1.0), dark)
    return centres[found], sizes[found]


@dataclass(frozen=True)
class PatternDots:
    """The dots of a lit dot pattern in one frame (:func:`find_pattern_dots`).

    Attributes
    ----------
    centres_px : (N, 2) array
        Sub-pixel centres (column, row), pixels (pixel centres at integers).
    cov_px2 : (N, 2, 2) array
        Each centre's covariance from the image's noise (``noise_dn``), square pixels.
    area_px : (N,) int array
        Pixels of each dot's blob (beyond the detection threshold).
    depth_dn : (N,) array
        How far each dot goes below its background (dark dots; above it for light ones), DN.
    background_dn : (N,) array
        The lit pattern's level around each dot, DN.
    noise_dn : float
        The image's noise beside the dots (the median of the dots' rings' robust scatter), DN.
    merged : int
        Blobs dropped as more than one dot (longer than wide by :data:`MERGED_ELONGATION`, or over
        :data:`MERGED_AREA` times the typical dot's area: neighbours run together, a scratch).
    small : int
        Blobs dropped as too small to be a dot (under :data:`SMALL_AREA` of the typical area: noise, dust).
    unmeasured : int
        Blobs whose centre could not be measured (too near the image's edge, or its centroid ran off).
    diameter_px : float
        The typical dot's diameter (that of a disc of the median area), pixels.
    """

    centres_px: np.ndarray
    cov_px2: np.ndarray
    area_px: np.ndarray
    depth_dn: np.ndarray
    background_dn: np.ndarray
    noise_dn: float
    merged: int = 0
    small: int = 0
    unmeasured: int = 0
    diameter_px: float = float("nan")


#: A blob more than this many times the typical dot's area is several dots run together (a dot magnified by
#: the mirror stays under it: up to 2.2 times in OpenCSP's capture).
MERGED_AREA = 3.5
#: A blob whose longest axis is this many times its shortest is dots run together (two touching discs: 2;
#: a dot seen obliquely in a curved mirror: under 1.4 in OpenCSP's capture).
MERGED_ELONGATION = 1.6
#: A blob under this fraction of the typical dot's area is not a dot.
SMALL_AREA = 0.3


def otsu_level(values: np.ndarray) -> float:
    """Otsu's threshold of *values* (OpenCV's, on the values scaled to 0..255): the level between a bimodal
    set's two modes (a lit facet and its dark surroundings, dots and their lit background)."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if not hi > lo:
        return hi
    scaled = np.round((values - lo) * (255.0 / (hi - lo))).astype(np.uint8).reshape(-1, 1)
    level, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return lo + float(level) * (hi - lo) / 255.0


def pattern_background(image: np.ndarray, max_diameter_px: float, dark: bool = True) -> np.ndarray:
    """The lit pattern with its dots filled in: a grey closing (dark dots; an opening for light ones) with a
    square of 2 *max_diameter_px* + 1 pixels, float32. A straight or convex edge of the lit area is where it
    was (the closing moves it out by the square's half width and back), a dot or a notch narrower than the
    square is filled with its surroundings' level."""
    k = 2 * int(np.ceil(max_diameter_px)) + 1
    op = cv2.MORPH_CLOSE if dark else cv2.MORPH_OPEN
    img = np.asarray(image)
    if img.dtype not in (np.uint8, np.uint16):
        img = img.astype(np.float32)
    return cv2.morphologyEx(img, op, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))).astype(np.float32)


def find_pattern_dots(image: np.ndarray, mask: np.ndarray | None = None, *, dark: bool = True,
                      max_diameter_px: float = 24.0, min_area_px: float = 3.0,
                      background: np.ndarray | None = None) -> PatternDots:
    """The dots of a lit dot pattern (a display's, or a lit target's, seen in a mirror), each centred to a
    fraction of a pixel with its covariance.

    Unlike :func:`find_dots` (photographs of a target under room light, OpenCV's blob detector over
    many thresholds: a second for a two-megapixel frame), the pattern's lit background is filled in over
    the dots (:func:`pattern_background`), the dots' depth below it thresholded once (Otsu's threshold of
    the depth over *mask*), and each connected blob is a candidate: a blob far larger than the typical one,
    or much longer than wide, is dropped as merged dots, one far smaller as noise; each kept blob is centred
    by its background-subtracted intensity moments over a disc (:func:`_centroids`), which also gives its
    covariance from the image's noise.

    Parameters
    ----------
    image : (H, W) integer array
        The frame, camera counts (DN).
    mask : (H, W) bool array, optional
        Where the pattern is seen (a facet's region): only blobs centred there count, and the work is done
        on its bounding box.
    dark : bool
        Dark dots on a lit background (the default), else lit dots on a dark one.
    max_diameter_px : float
        The largest dot diameter expected in the image, pixels (the filling square is twice that).
    min_area_px : float
        Smaller blobs are never dots, square pixels.
    background : (H, W) float32 array, optional
        :func:`pattern_background` of *image* when the caller has it already.

    Returns
    -------
    PatternDots
        Empty (no centres) when no dot stands out from the background.
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype.kind not in "ui":
        raise ValueError(f"find_pattern_dots needs a grey integer image, got {img.dtype} {img.shape}")
    h, w = img.shape
    margin = 2 * int(np.ceil(max_diameter_px)) + 2
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != img.shape:
            raise ValueError(f"the mask is {mask.shape}, the image {img.shape}")
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if rows.size == 0:
            return _no_dots()
        r0, r1 = max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)
        c0, c1 = max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)
    else:
        r0, r1, c0, c1 = 0, h, 0, w
    box = img[r0:r1, c0:c1]
    bg = pattern_background(box, max_diameter_px, dark) if background is None else background[r0:r1, c0:c1]
    depth = (bg - box) if dark else (box - bg)
    inside = np.ones(box.shape, bool) if mask is None else mask[r0:r1, c0:c1]
    if not inside.any():
        return _no_dots()
    # Otsu's threshold between the dots and their background, but never within the image's noise (a lit area
    # without dots has a depth of noise only, which Otsu's threshold would split all the same)
    level = max(otsu_level(depth[inside]), 6.0 * image_noise_dn(box, inside))
    binary = ((depth > level) & (depth > 0)).astype(np.uint8)
    # the labelling alone; each blob's area, centroid and second moments from one compiled pass over it (OpenCV's
    # statistics cost three times the labelling; its centroids are the same integer sums over the area)
    n, labels = cv2.connectedComponents(binary, connectivity=8)
    if n <= 1:
        return _no_dots()
    moments = label_moments(labels, n)
    elongation = _elongation(moments)[1:]
    count = moments[0, 1:]
    centroids = np.column_stack([moments[2, 1:] / count, moments[1, 1:] / count])
    centre_px = np.round(centroids).astype(np.int64)
    on = inside[np.clip(centre_px[:, 1], 0, box.shape[0] - 1), np.clip(centre_px[:, 0], 0, box.shape[1] - 1)]
    area = count[on].astype(np.int64)
    elongation = elongation[on]
    starts = centroids[on] + [c0, r0]
    big = area >= min_area_px
    if not big.any():
        return _no_dots()
    typical = float(np.median(area[big]))
    # A dot seen through a curved mirror is magnified where the mirror is (its image up to twice the typical
    # area in OpenCSP's capture), but stays round; dots run together are as long as two.
    merged = big & ((elongation > MERGED_ELONGATION) | (area > MERGED_AREA * typical))
    small = ~big | (area < SMALL_AREA * typical)
    keep = ~merged & ~small
    # each dot centred over a disc of its own blob's size, in classes of half a pixel of radius
    radius = np.maximum(np.round(2.0 * np.sqrt(area[keep] / np.pi)) / 2.0, 1.0)
    centres, found = np.full((int(keep.sum()), 2), np.nan), np.zeros(int(keep.sum()), bool)
    info = {k: np.full((int(keep.sum()),) + shape, np.nan)
            for k, shape in (("cov_unit_px2", (2, 2)), ("background_dn", ()), ("ring_sigma_dn", ()), ("depth_dn", ()))}
    for r in np.unique(radius):
        sel = np.flatnonzero(radius == r)
        c, ok, part = _centroids(img, starts[keep][sel], float(r), dark, details=True)
        centres[sel], found[sel] = c, ok
        for k in info:
            info[k][sel] = part[k]
    noise = float(np.nanmedian(info["ring_sigma_dn"][found])) if found.any() else float("nan")
    return PatternDots(centres[found], noise ** 2 * info["cov_unit_px2"][found], area[keep][found],
                       info["depth_dn"][found], info["background_dn"][found], noise, int(merged.sum()),
                       int(small.sum()), int((~found).sum()), 2.0 * np.sqrt(typical / np.pi))


def _elongation(moments: np.ndarray) -> np.ndarray:
    """Per connected component of a labelling (its :func:`~.kernels.label_moments`), the ratio of its longest
    to its shortest axis from its pixels' second moments (1 for a disc, 2 for two discs side by side; a
    one-pixel-wide line: its length over 0.29)."""
    count, s_r, s_c, s_rr, s_cc, s_rc = moments
    count = np.maximum(count, 1.0)
    mean_r = s_r / count
    mean_c = s_c / count
    # a pixel is a unit square: 1/12 of spread on each axis of its own
    var_r = s_rr / count - mean_r ** 2 + 1.0 / 12.0
    var_c = s_cc / count - mean_c ** 2 + 1.0 / 12.0
    cov = s_rc / count - mean_r * mean_c
    half_sum, root = 0.5 * (var_r + var_c), np.sqrt(0.25 * (var_r - var_c) ** 2 + cov ** 2)
    return np.sqrt((half_sum + root) / np.maximum(half_sum - root, 1e-12))


def image_noise_dn(image: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The image's pixel noise (DN, one standard deviation) from its 4-neighbour Laplacian: for independent noise
    of sigma its variance is 20 sigma^2, and its median absolute value is little moved by edges and dots that
    cover less than half of *mask*."""
    if np.asarray(image).dtype in (np.uint8, np.uint16):
        # whole counts: their Laplacians counted in one compiled pass, the median read from the counts (numpy's
        # median of the same values below, in float32: the same bits, a fifth of the time)
        inside = np.ones(np.shape(image), bool) if mask is None else mask
        return float(1.4826 * np.float32(laplacian_median(image, inside)) / np.sqrt(20.0))
    img = np.asarray(image, np.float32)
    # every other row and column: the median of a quarter of the values is as good, for a quarter of the time
    # (the Laplacian is formed at those pixels only: the same values as every pixel's, subsampled)
    c = img[1:-1:2, 1:-1:2]
    lap = 4.0 * c - img[:-2:2, 1:-1:2][:c.shape[0], :c.shape[1]] - img[2::2, 1:-1:2][:c.shape[0], :c.shape[1]] \
        - img[1:-1:2, :-2:2][:c.shape[0], :c.shape[1]] - img[1:-1:2, 2::2][:c.shape[0], :c.shape[1]]
    values = lap if mask is None else lap[np.asarray(mask)[1:-1:2, 1:-1:2]]
    if values.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(values)) / np.sqrt(20.0))


def _no_dots() -> PatternDots:
    return PatternDots(np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0, np.int64), np.zeros(0), np.zeros(0),
                       float("nan"))


def index_dots(centres_px: np.ndarray, origin_px, tolerance: float = 0.3, return_which: bool = False):
    """Lattice indices of dots, counted from the dot nearest *origin_px*.

    i grows along the image's columns and j along its rows (the lattice's two directions nearest to them).
    From the origin the walk goes breadth-first, in waves (every place next to the dots indexed so far is
    looked for at once); the next dot in a direction is predicted from the last two dots on that line (or,
    at the start of a line, from a neighbouring line's step) and accepted when one lies within *tolerance*
    of a lattice step of the prediction and is not taken (a dot two places claim goes to the nearer
    prediction). Dots whose neighbours on either side do not lie on a smooth line (a second difference
    beyond half *tolerance* of the two steps: a stray blob taken for a dot) are dropped.

    Parameters
    ----------
    centres_px : (N, 2) array
    origin_px : (2,) sequence
        Pixel near the dot whose index is (0, 0).
    tolerance : float
        Fraction of the local lattice step.

    return_which : bool
        Also return which of *centres_px* each indexed dot is.

    Returns
    -------
    indices : (M, 2) int array
        (i, j) of the indexed dots.
    points_px : (M, 2) array
        Their centres.
    which : (M,) int array
        With *return_which*: each indexed dot's row in *centres_px*.

    Raises
    ------
    ValueError
        No dot near the origin (within half a lattice step), or too few dots around it to start.
    """
    # lazy: scipy.spatial, ~470 ms CPU; recipes.py loads this (via fixed.py) at every start
    from scipy.spatial import cKDTree

    pts = np.asarray(centres_px, np.float64).reshape(-1, 2)
    if pts.shape[0] < 9:
        raise ValueError(f"only {pts.shape[0]} dots found: a lattice needs at least a 3 x 3 block")
    if not np.isfinite(pts).all():
        raise ValueError("the dots' centres must be finite pixels (drop the dots that were not centred)")
    tree = cKDTree(pts)
    origin = np.asarray(origin_px, np.float64).ravel()
    dist, first = tree.query(origin)
    near_d, near_i = tree.query(pts[first], k=9)
    step = float(np.median(near_d[1:5]))
    if dist > 0.5 * step:
        raise ValueError(f"no dot within half a lattice step ({0.5 * step:.1f} px) of the origin ({origin[0]:.1f}, "
                         f"{origin[1]:.1f}): the nearest is {dist:.1f} px away")
    vecs = pts[near_i[1:5]] - pts[first]
    unit = vecs / np.linalg.norm(vecs, axis=1)[:, None]
    e_i, e_j = vecs[int(np.argmax(unit[:, 0]))], vecs[int(np.argmax(unit[:, 1]))]
    if abs(np.dot(e_i, e_j)) > 0.5 * np.linalg.norm(e_i) * np.linalg.norm(e_j):
        raise ValueError(f"the dots around the origin ({origin[0]:.1f}, {origin[1]:.1f}) do not form a square lattice")
    # the walk, in waves (every place next to the indexed ones is looked for at once), compiled: a wave's
    # arrays are a few hundred dots, where numpy's calls cost more than their work
    span = int(np.ceil(4 * np.sqrt(pts.shape[0]))) + 8
    extent = float(np.max(np.ptp(pts, axis=0)))
    grid, who = lattice_walk(pts, int(first), np.array([e_i, -e_i, e_j, -e_j]), float(tolerance),
                             max(step, extent / 1024.0, 1e-3), span)
    # a stray blob taken for a dot bends its row or column: drop dots whose second difference is off (on the
    # indexed places' box only, with a free place on every side: the grid is mostly empty)
    filled = np.nonzero(~np.isnan(grid[:, :, 0]))
    r0, r1 = filled[0].min() - 1, filled[0].max() + 2
    c0, c1 = filled[1].min() - 1, filled[1].max() + 2
    box = grid[r0:r1, c0:c1]
    bad = np.zeros(box.shape[:2], bool)
    for axis in (0, 1):
        prev, nxt = np.roll(box, 1, axis=axis), np.roll(box, -1, axis=axis)
        second = np.linalg.norm(prev - 2 * box + nxt, axis=2)
        span_ = np.linalg.norm(nxt - prev, axis=2)
        with np.errstate(invalid="ignore"):
            bad |= second > tolerance * 0.5 * span_
    keep = ~np.isnan(box[:, :, 0]) & ~bad
    rows, cols = np.nonzero(keep)
    rows, cols = rows + r0, cols + c0
    out = np.column_stack([rows - span, cols - span]).astype(np.int64), grid[rows, cols]
    return (*out, who[rows, cols]) if return_which else out


# -- the bundle adjustment -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DotView:
    """One photograph's observations.

    Attributes
    ----------
    name : str
    marker_world_m : (K, 3) array
        Known marker corners it shows (world, metres) ...
    marker_px : (K, 2) array
        ... and where it shows them, pixels.
    dot_indices : (N, 2) int array
        Lattice indices of the dots it shows (the same dot has the same index in every view) ...
    dot_px : (N, 2) array
        ... and where, pixels.
    """

    name: str
    marker_world_m: np.ndarray
    marker_px: np.ndarray
    dot_indices: np.ndarray
    dot_px: np.ndarray


@dataclass
class DotSolution:
    """What :func:`locate_dots` found.

    Attributes
    ----------
    locations : DotLocations
        The dots on their grid (x and y index as turned into the markers' frame), with U (k = 2).
    index_map : (2, 3) int array
        How view indices (i, j, 1) became (x index, y index): ``[x, y] = index_map @ [i, j, 1]``.
    poses : list of Pose
        Each view's world -> camera pose.
    pose_std : list of (6,) arrays
        Standard uncertainty of each pose's small motion about and along its own axes (rad, m).
    sigma_px : dict
        Noise per kind of observation ("markers", "dots"), estimated from the residuals, pixels.
    rms_px : dict
        RMS residual per kind (per coordinate), pixels.
    views : list of dict
        Per view: name, marker corners and dots used, their RMS residuals, outliers dropped.
    dots_used : int
        Dots located (seen, after outliers, in at least ``min_views`` views).
    dots_dropped : int
        Dots indexed but not located (seen in fewer views).
    outliers : int
        Observations dropped as outliers.
    iterations : int
        Gauss-Newton steps over all rounds.
    dot_residuals_px : (D, V, 2) array
        Each located dot's residual in each view (NaN where not seen or dropped), in the order of
        ``dot_indices``.
    dot_indices : (D, 2) int array
        The located dots' (x index, y index).
    """

    locations: DotLocations
    index_map: np.ndarray
    poses: list
    pose_std: list
    sigma_px: dict
    rms_px: dict
    views: list
    dots_used: int
    dots_dropped: int
    outliers: int
    iterations: int
    dot_residuals_px: np.ndarray
    dot_indices: np.ndarray


class _Observations:
    """Flat arrays of the observations: markers (view, world point, pixel) and dots (view, dot, pixel)."""

    def __init__(self, views: list[DotView], dot_keys: list[tuple[int, int]], min_views: int):
        self.min_views = min_views
        lookup = {k: n for n, k in enumerate(dot_keys)}
        mv, mw, mp, dv, dd, dp = [], [], [], [], [], []
        for v, view in enumerate(views):
            mv.append(np.full(len(view.marker_px), v))
            mw.append(view.marker_world_m)
            mp.append(view.marker_px)
            for key, px in zip(map(tuple, view.dot_indices.tolist()), view.dot_px):
                if key in lookup:
                    dv.append(v)
                    dd.append(lookup[key])
                    dp.append(px)
        self.m_view = np.concatenate(mv).astype(np.int64)
        self.m_world = np.concatenate(mw).reshape(-1, 3)
        self.m_px = np.concatenate(mp).reshape(-1, 2)
        self.d_view = np.asarray(dv, np.int64)
        self.d_dot = np.asarray(dd, np.int64)
        self.d_px = np.asarray(dp, np.float64).reshape(-1, 2)
        self.m_keep = np.ones(len(self.m_view), bool)
        self.d_keep = np.ones(len(self.d_view), bool)


def _residuals(cam: np.ndarray, poses: list[Pose], dots: np.ndarray, obs: _Observations, derivatives: bool):
    """Marker and dot residuals (projected - measured, pixels) and, with *derivatives*, their Jacobians:
    markers d/d(pose) (M, 2, 6); dots d/d(pose) (N, 2, 6) and d/d(dot) (N, 2, 3)."""
    out = []
    for which, views, world, px in (("m", obs.m_view, obs.m_world, obs.m_px),
                                    ("d", obs.d_view, dots[obs.d_dot] if len(obs.d_dot) else np.zeros((0, 3)),
                                     obs.d_px)):
        r = np.zeros((len(views), 2))
        jp = np.zeros((len(views), 2, 6)) if derivatives else None
        jx = np.zeros((len(views), 2, 3)) if derivatives else None
        for v, pose in enumerate(poses):
            sel = np.flatnonzero(views == v)
            if sel.size == 0:
                continue
            pc = pose.apply(world[sel])
            if derivatives:
                pix, d_pt, _ = project(cam, pc, derivatives=True)
                jp[sel] = np.matmul(d_pt, pose_derivative(pose, world[sel]))
                jx[sel] = d_pt @ pose.rotation
            else:
                pix = project(cam, pc)
            r[sel] = pix - px[sel]
        out.append((r, jp, jx))
    return out


def _gram(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per observation ``a^T b`` of (n, 2, p) and (n, 2, q) Jacobians: (n, p, q) (written out: einsum and
    matmul over thousands of tiny matrices are ten times slower)."""
    return a[:, 0, :, None] * b[:, 0, None, :] + a[:, 1, :, None] * b[:, 1, None, :]


def _normal_equations(obs, res, w_m: float, w_d: float, n_views: int, n_dots: int):
    """The normal equations' blocks: poses (V, 6, 6) and gradient (V, 6), dots (D, 3, 3) and (D, 3), and the
    pose-dot coupling (D, V, 6, 3). A view sees a dot once, so per view every index is distinct. A dot left
    with too few observations (outliers dropped) gets a unit block: it stays where it is and is not
    reported."""
    (rm, jpm, _), (rd, jpd, jxd) = res
    hpp = np.zeros((n_views, 6, 6))
    gp = np.zeros((n_views, 6))
    hdd = np.zeros((n_dots, 3, 3))
    gd = np.zeros((n_dots, 3))
    hpd = np.zeros((n_dots, n_views, 6, 3))
    for v in range(n_views):
        m = np.flatnonzero((obs.m_view == v) & obs.m_keep)
        d = np.flatnonzero((obs.d_view == v) & obs.d_keep)
        jm, jp, jx = jpm[m].reshape(-1, 6), jpd[d], jxd[d]
        hpp[v] = w_m * jm.T @ jm + w_d * jp.reshape(-1, 6).T @ jp.reshape(-1, 6)
        gp[v] = w_m * jm.T @ rm[m].ravel() + w_d * jp.reshape(-1, 6).T @ rd[d].ravel()
        dots = obs.d_dot[d]
        hdd[dots] += w_d * _gram(jx, jx)
        gd[dots] += w_d * (jx[:, 0, :] * rd[d, 0, None] + jx[:, 1, :] * rd[d, 1, None])
        hpd[dots, v] = w_d * _gram(jp, jx)
    dead = np.bincount(obs.d_dot[obs.d_keep], minlength=n_dots) < obs.min_views
    hdd[dead] = np.eye(3)
    gd[dead] = 0.0
    hpd[dead] = 0.0
    return hpp, gp, hdd, gd, hpd


def _reduce(b: np.ndarray, hdd_inv: np.ndarray) -> np.ndarray:
    """``sum_d b_d H_dd^-1 b_d^T`` for b (D, 6V, 3): the dots' share of the Schur complement."""
    t = np.matmul(b, hdd_inv)                                            # (D, 6V, 3)
    n = b.shape[1]
    return t.transpose(1, 0, 2).reshape(n, -1) @ b.transpose(1, 0, 2).reshape(n, -1).T


def _block_diagonal(blocks: np.ndarray) -> np.ndarray:
    n = blocks.shape[0]
    out = np.zeros((6 * n, 6 * n))
    for v in range(n):
        out[6 * v:6 * v + 6, 6 * v:6 * v + 6] = blocks[v]
    return out


def _quadratic(j: np.ndarray, c: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Per observation ``trace(j c k^T)`` for j (n, 2, p), c (n, p, q), k (n, 2, q)."""
    return np.sum(np.matmul(j, c) * k, axis=(1, 2))


def locate_dots(camera: CameraIntrinsics, views: list[DotView], *, min_views: int = 2, refine_poses: bool = True,
                outlier_sigmas: float = 5.0, max_iterations: int = 60, progress=None) -> DotSolution:
    """Every dot's 3-D location, and its covariance, from several photographs (see the module docstring).

    Parameters
    ----------
    camera : CameraIntrinsics
        The camera that took every photograph.
    views : list of DotView
        At least two; each with at least 4 known marker corners (its pose's start comes from them).
    min_views : int
        A dot is located when at least this many views see it (2 at the least).
    refine_poses : bool
        Adjust the poses with the dots too (a bundle adjustment). False: each pose is its markers' alone
        (what OpenCSP does), its uncertainty still carried into the dots'.
    outlier_sigmas : float
        Observations whose normalised residual exceeds this are dropped (and counted).
    progress : callable, optional
        ``progress(text)`` for a line per round.

    Raises
    ------
    ValueError
        Fewer than two views, a view without enough markers, no dot in enough views.
    """
    if len(views) < 2:
        raise ValueError(f"locating dots needs photographs from at least 2 places, got {len(views)}")
    min_views = max(2, int(min_views))
    say = progress or (lambda text: None)
    cam = camera_vector(camera)
    poses, marker_fits = [], []
    for view in views:
        if len(view.marker_px) < 4:
            raise ValueError(f"{view.name}: {len(view.marker_px)} known marker corners; a camera pose needs at "
                             "least 4 (one whole marker), better 3 markers or more spread over the photograph")
        fit = solve_camera_pose(camera, view.marker_world_m, view.marker_px)
        poses.append(fit.world_to_camera)
        marker_fits.append(fit)
    counts: dict[tuple[int, int], int] = {}
    for view in views:
        for key in map(tuple, np.asarray(view.dot_indices).tolist()):
            counts[key] = counts.get(key, 0) + 1
    keys = sorted(k for k, n in counts.items() if n >= min_views)
    dropped_dots = len(counts) - len(keys)
    if not keys:
        raise ValueError(f"no dot is seen in {min_views} photographs: are the origins the same dot in every "
                         "photograph?")
    obs = _Observations(views, keys, min_views)
    n_views, n_dots = len(views), len(keys)
    # start: each dot where its rays (from the markers' poses) cross
    normal, rhs = np.zeros((n_dots, 3, 3)), np.zeros((n_dots, 3))
    for v, pose in enumerate(poses):
        sel = np.flatnonzero(obs.d_view == v)
        if sel.size == 0:
            continue
        u = pixel_rays(camera, obs.d_px[sel, 0], obs.d_px[sel, 1]).T @ pose.rotation     # world directions
        p = np.eye(3) - u[:, :, None] * u[:, None, :]
        normal[obs.d_dot[sel]] += p
        rhs[obs.d_dot[sel]] += p @ pose.inverse().translation
    dots = np.linalg.solve(normal, rhs[:, :, None])[:, :, 0]
    sigma = {"markers": max(float(np.median([f.sigma_px for f in marker_fits])), 0.01), "dots": 0.1}
    iterations = 0
    outliers = 0
    for round_ in range(8):
        w_m, w_d = 1.0 / sigma["markers"] ** 2, 1.0 / sigma["dots"] ** 2
        lam = 1e-3
        res = _residuals(cam, poses, dots, obs, True)

        def cost(rs):
            return w_m * np.sum(rs[0][0][obs.m_keep] ** 2) + w_d * np.sum(rs[1][0][obs.d_keep] ** 2)

        current = cost(res)
        for _ in range(max_iterations):
            iterations += 1
            hpp, gp, hdd, gd, hpd = _normal_equations(obs, res, w_m, w_d, n_views, n_dots)
            damp_d = hdd + lam * np.einsum("nii->ni", hdd)[:, :, None] * np.eye(3)
            hdd_inv = np.linalg.inv(damp_d)
            b = hpd.reshape(n_dots, n_views * 6, 3)
            if refine_poses:
                damp_p = hpp + lam * np.einsum("nii->ni", hpp)[:, :, None] * np.eye(6)
                s = _block_diagonal(damp_p) - _reduce(b, hdd_inv)
                rhs = -gp.ravel() + np.matmul(b, np.matmul(hdd_inv, gd[:, :, None])).sum(axis=0).ravel()
                dp = np.linalg.solve(s, rhs)
                dx = -np.matmul(hdd_inv, (gd + np.matmul(dp, b))[:, :, None])[:, :, 0]
            else:
                dp = np.zeros(n_views * 6)
                dx = -np.matmul(hdd_inv, gd[:, :, None])[:, :, 0]
            if np.max(np.abs(dp), initial=0.0) < 1e-9 and np.max(np.abs(dx)) < 1e-9:
                break                        # converged: steps of a nanometre (poses: a nanoradian)
            trial_poses = [moved(p, dp[6 * v:6 * v + 6]) for v, p in enumerate(poses)]
            trial_dots = dots + dx
            trial = _residuals(cam, trial_poses, trial_dots, obs, True)
            new = cost(trial)
            if new <= current:
                gain = current - new
                poses, dots, res, current = trial_poses, trial_dots, trial, new
                lam = max(lam / 10.0, 1e-9)
                if gain <= 1e-10 * current:
                    break                    # no cost left to gain
            else:
                lam *= 10.0
                if lam > 1e8:
                    break
        # covariance, redundancy and the noise of each kind
        hpp, gp, hdd, gd, hpd = _normal_equations(obs, res, w_m, w_d, n_views, n_dots)
        hdd_inv = np.linalg.inv(hdd)
        b = hpd.reshape(n_dots, n_views * 6, 3)
        (rm, jpm, _), (rd, jpd, jxd) = res
        if refine_poses:
            cpp = np.linalg.inv(_block_diagonal(hpp) - _reduce(b, hdd_inv))
        else:
            # each pose from its markers alone: its covariance from the markers' normal equations
            hm = np.stack([w_m * jpm[(obs.m_view == v) & obs.m_keep].reshape(-1, 6).T
                           @ jpm[(obs.m_view == v) & obs.m_keep].reshape(-1, 6) for v in range(n_views)])
            cpp = _block_diagonal(np.linalg.inv(hm))
        cpd = -np.matmul(np.matmul(cpp, b), hdd_inv)                          # (D, 6V, 3)
        cdd = hdd_inv - np.matmul(hdd_inv, np.matmul(b.transpose(0, 2, 1), cpd))
        # hat-matrix diagonal per observation: how much of it the parameters absorb
        blocks = np.stack([cpp[6 * v:6 * v + 6, 6 * v:6 * v + 6] for v in range(n_views)])
        hm_ = w_m * _quadratic(jpm, blocks[obs.m_view], jpm)
        v_, d_ = obs.d_view, obs.d_dot
        cvd = cpd.reshape(n_dots, n_views, 6, 3)[d_, v_]
        if refine_poses:
            hd_ = w_d * (_quadratic(jpd, blocks[v_], jpd) + 2 * _quadratic(jpd, cvd, jxd)
                         + _quadratic(jxd, cdd[d_], jxd))
        else:                                   # the dots do not move the poses: only their own parameters count
            hd_ = w_d * _quadratic(jxd, hdd_inv[d_], jxd)
        red_m = 2 * obs.m_keep.sum() - hm_[obs.m_keep].sum()
        red_d = 2 * obs.d_keep.sum() - hd_[obs.d_keep].sum()
        ssr_m = float(np.sum(rm[obs.m_keep] ** 2))
        ssr_d = float(np.sum(rd[obs.d_keep] ** 2))
        new_sigma = {"markers": float(np.sqrt(ssr_m / red_m)) if red_m > 0.5 else sigma["markers"],
                     "dots": float(np.sqrt(ssr_d / red_d)) if red_d > 0.5 else sigma["dots"]}
        # outliers, judged with the new noise
        norm_m = np.linalg.norm(rm, axis=1) / new_sigma["markers"]
        norm_d = np.linalg.norm(rd, axis=1) / new_sigma["dots"]
        bad_m = obs.m_keep & (norm_m > outlier_sigmas)
        bad_d = obs.d_keep & (norm_d > outlier_sigmas)
        converged = all(abs(new_sigma[k] / sigma[k] - 1) < 0.01 for k in sigma) and not bad_m.any() and not bad_d.any()
        say(f"round {round_ + 1}: marker corners {new_sigma['markers']:.3f} px, dots {new_sigma['dots']:.3f} px "
            f"(noise from the residuals), {int(bad_m.sum() + bad_d.sum())} outlier(s)")
        sigma = new_sigma
        if converged:
            break
        # drop the worst outliers first (one bad point inflates its neighbours' residuals)
        if bad_m.any() or bad_d.any():
            worst = max(norm_m[obs.m_keep].max(initial=0.0), norm_d[obs.d_keep].max(initial=0.0))
            cut = max(outlier_sigmas, 0.5 * worst)
            drop_m = obs.m_keep & (norm_m > cut)
            drop_d = obs.d_keep & (norm_d > cut)
            obs.m_keep &= ~drop_m
            obs.d_keep &= ~drop_d
            outliers += int(drop_m.sum() + drop_d.sum())
            seen = np.bincount(obs.d_dot[obs.d_keep], minlength=n_dots)
            obs.d_keep &= seen[obs.d_dot] >= min_views
    seen = np.bincount(obs.d_dot[obs.d_keep], minlength=n_dots)
    located = seen >= min_views
    (rm, _, _), (rd, _, _) = _residuals(cam, poses, dots, obs, False)
    view_rows = []
    for v, view in enumerate(views):
        mk = (obs.m_view == v) & obs.m_keep
        dk = (obs.d_view == v) & obs.d_keep
        view_rows.append({"name": view.name, "marker_corners": int(mk.sum()), "dots": int(dk.sum()),
                          "marker_rms_px": float(np.sqrt(np.mean(rm[mk] ** 2))) if mk.any() else None,
                          "dot_rms_px": float(np.sqrt(np.mean(rd[dk] ** 2))) if dk.any() else None,
                          "outliers": int(((obs.m_view == v) & ~obs.m_keep).sum()
                                          + ((obs.d_view == v) & ~obs.d_keep).sum())})
    rms = {"markers": float(np.sqrt(np.mean(rm[obs.m_keep] ** 2))),
           "dots": float(np.sqrt(np.mean(rd[obs.d_keep] ** 2))) if obs.d_keep.any() else float("nan")}
    residual_grid = np.full((n_dots, n_views, 2), np.nan)
    residual_grid[obs.d_dot[obs.d_keep], obs.d_view[obs.d_keep]] = rd[obs.d_keep]
    ij = np.asarray(keys, np.int64)[located]
    index_map = orient_indices(np.asarray(keys, np.int64)[located], dots[located])
    xy = (index_map[:, :2] @ ij.T).T + index_map[:, 2]
    grid = dot_grid(xy, dots[located], cdd[located])
    pose_std = [np.sqrt(np.clip(np.diag(cpp[6 * v:6 * v + 6, 6 * v:6 * v + 6]), 0, None)) for v in range(n_views)]
    return DotSolution(grid, index_map, poses, pose_std, sigma, rms, view_rows, int(located.sum()),
                       dropped_dots + int((~located).sum()), outliers, iterations, residual_grid[located], xy)


def orient_indices(indices: np.ndarray, xyz_m: np.ndarray) -> np.ndarray:
    """The (2, 3) integer map turning lattice indices (i, j) into (x index, y index) that grow along the
    world's axes: x index along the world axis the lattice runs along first in the order x, y, z, y index
    along the next, each positive. The origin keeps index (0, 0).

    Raises
    ------
    ValueError
        Fewer than two neighbouring dots along either lattice direction.
    """
    indices = np.asarray(indices, np.int64)
    lookup = {tuple(k): n for n, k in enumerate(indices.tolist())}
    steps = []
    for d in ((1, 0), (0, 1)):
        pairs = [(n, lookup[(k[0] + d[0], k[1] + d[1])]) for k, n in lookup.items()
                 if (k[0] + d[0], k[1] + d[1]) in lookup]
        if not pairs:
            raise ValueError("the located dots have no neighbours along a lattice direction")
        a, b = np.array(pairs).T
        steps.append(np.mean(xyz_m[b] - xyz_m[a], axis=0))
    axis_i = int(np.argmax(np.abs(steps[0])))
    order_j = np.argsort(-np.abs(steps[1]))
    axis_j = int(order_j[0] if order_j[0] != axis_i else order_j[1])
    sign_i, sign_j = int(np.sign(steps[0][axis_i])), int(np.sign(steps[1][axis_j]))
    rows = {axis_i: np.array([sign_i, 0, 0]), axis_j: np.array([0, sign_j, 0])}
    first, second = sorted(rows)
    return np.vstack([rows[first], rows[second]]).astype(np.int64)
