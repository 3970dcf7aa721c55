"""The fixture's marks in a frame: each located to a fraction of a pixel near its commissioned image position,
and what their common motion says of the camera.

Marks are light discs on the fixture's dark frame beside the facet (``[marks]`` in station.toml). Every cycle
the station finds them in its white frame (:func:`locate_marks`: a window of ``search_px`` around each
commissioned position, its brightest blob of about a mark's size, then the background-subtracted intensity
centroid of :mod:`sofast_station.measure.dots`) and compares them with the positions commissioning recorded
(:func:`mark_motion`): a 2-D similarity (shift, roll, scale) fitted to their displacements, least squares.

What the motion means (:func:`implied_pose_u`): the marks are fixed to the fixture, the facet is not; a
misplaced facet leaves them still, a camera that moved moves them all. Seen from 10 m through a long lens, a
camera turned by theta and one slid sideways by theta D (D its distance to the fixture) shift every mark alike,
by f theta pixels: the marks cannot tell the two apart (the difference is the perspective of a flat set of
marks, under a hundredth of a pixel), nor see a slide along the line of sight (a scale of dz / D, 0.05 px at
the image's edge for 1 mm at 10 m). A shift too small to stop the line is therefore taken as an uncertainty of
the fixture's pose, not corrected: a turn of up to theta about each axis it reaches, and a slide of up to
theta D.

Pure functions of arrays (numpy, scipy); no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .budget_rows import add_budget_row
from .dots import _centroids


@dataclass(frozen=True)
class MarkLocations:
    """Where the marks were found in one frame.

    Attributes
    ----------
    centres_px : (N, 2) array
        (column, row) pixels; NaN for a mark not found.
    found : (N,) bool array
    contrast_dn : (N,) array
        Each mark's peak over its window's background, DN (0 when nothing stood out).
    """

    centres_px: np.ndarray
    found: np.ndarray
    contrast_dn: np.ndarray


def locate_marks(image: np.ndarray, expected_px: np.ndarray, radius_px: float, search_px: float,
                 min_contrast_dn: float = 20.0) -> MarkLocations:
    """Find each mark near its expected image position.

    For each mark, a window of half-width ``search_px + 2 radius_px`` about its expected position: the pixels
    brighter than halfway from the window's median to its peak, split into connected blobs; the blob of a
    mark's size (a quarter to four times its area) that does not touch the window's border (a facet's bright
    image, larger than the window, is not a mark), nearest the expected position, starts the centroid: the
    background-subtracted intensity centroid over a disc of 1.5 radii plus a pixel, re-centred until it stops
    moving (:mod:`sofast_station.measure.dots`; noise pulls it toward the disc's centre, which converges onto
    the mark's, so it carries no bias from the noise).

    Parameters
    ----------
    image : (H, W) uint8 or float array
        The white frame.
    expected_px : (N, 2) array
        Where each mark is expected (its commissioned position), (column, row) pixels.
    radius_px : float
        A mark's image radius, pixels.
    search_px : float
        How far from its expected position a mark is sought, pixels.
    min_contrast_dn : float
        A window whose peak stands less than this above its median holds no mark, DN.

    Returns
    -------
    MarkLocations
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"locate_marks needs a grey image, got shape {img.shape}")
    expected = np.asarray(expected_px, dtype=np.float64).reshape(-1, 2)
    if not (np.isfinite(radius_px) and radius_px > 0 and np.isfinite(search_px) and search_px > 0):
        raise ValueError(f"radius_px and search_px must be positive pixels, got {radius_px}, {search_px}")
    n = len(expected)
    centres = np.full((n, 2), np.nan)
    contrast = np.zeros(n)
    # A camera that has not moved leaves every mark within a pixel or two of its place: the centroid started
    # there converges onto it (a tenth of the search's cost); only the marks it does not find are searched for.
    todo = np.isfinite(expected).all(axis=1)
    if todo.any():
        idx = np.flatnonzero(todo)
        refined, ok = _centroids(img, expected[idx], float(radius_px), dark=False)
        for j, k in enumerate(idx):
            if ok[j]:
                contrast[k] = _contrast(img, refined[j], radius_px)
                if contrast[k] >= min_contrast_dn:
                    centres[k] = refined[j]
        todo &= ~np.isfinite(centres[:, 0])
    if todo.any():
        idx = np.flatnonzero(todo)
        starts = np.full((idx.size, 2), np.nan)
        for j, k in enumerate(idx):
            starts[j], contrast[k] = _search(img, expected[k], radius_px, search_px, min_contrast_dn)
        good = np.isfinite(starts[:, 0])
        if good.any():
            refined, ok = _centroids(img, starts[good], float(radius_px), dark=False)
            centres[idx[good][ok]] = refined[ok]
    found = np.isfinite(centres[:, 0])
    return MarkLocations(centres, found, contrast)


def _rim_median(window: np.ndarray) -> float:
    """The median of a window's outermost rows and columns (its background when a mark sits inside)."""
    return float(np.median(np.concatenate([window[0], window[-1], window[1:-1, 0], window[1:-1, -1]])))


def _contrast(img: np.ndarray, centre_px: np.ndarray, radius_px: float) -> float:
    """A found mark's contrast, DN: the 3 x 3 mean at its centre over the median of a square rim two radii
    and three pixels out (0 when that square leaves the image)."""
    height, width = img.shape
    u, v = int(round(centre_px[0])), int(round(centre_px[1]))
    half = int(math.ceil(2.0 * radius_px + 3.0))
    if u - half < 0 or v - half < 0 or u + half >= width or v + half >= height:
        return 0.0
    window = img[v - half:v + half + 1, u - half:u + half + 1].astype(np.float32)
    return float(window[half - 1:half + 2, half - 1:half + 2].mean()) - _rim_median(window)


def _search(img: np.ndarray, expected: np.ndarray, radius_px: float, search_px: float,
            min_contrast_dn: float) -> tuple[np.ndarray, float]:
    """The start of a mark's centroid within ``search_px`` of *expected* (NaN when none), and the window's peak
    over its background, DN (see :func:`locate_marks`)."""
    none = np.array([np.nan, np.nan])
    height, width = img.shape
    area = math.pi * radius_px * radius_px
    half = int(math.ceil(search_px + 2.0 * radius_px))
    u, v = int(round(expected[0])), int(round(expected[1]))
    c0, r0 = max(u - half, 0), max(v - half, 0)
    c1, r1 = min(u + half + 1, width), min(v + half + 1, height)
    if c1 - c0 < 3 or r1 - r0 < 3:
        return none, 0.0
    window = img[r0:r1, c0:c1].astype(np.float32)
    background = _rim_median(window)
    peak = float(window.max()) - background
    if peak < min_contrast_dn:
        return none, max(peak, 0.0)
    labels, count = ndimage.label(window > background + 0.5 * peak)
    if count == 0:
        return none, peak
    flat = labels.ravel()
    sizes = np.bincount(flat, minlength=count + 1)[1:]
    weight = (window - background).ravel()
    total = np.bincount(flat, weights=weight, minlength=count + 1)[1:]
    rows, cols = np.divmod(np.arange(flat.size), window.shape[1])
    centres = np.column_stack([np.bincount(flat, weights=weight * cols, minlength=count + 1)[1:] / total,
                               np.bincount(flat, weights=weight * rows, minlength=count + 1)[1:] / total])
    border = np.zeros(count + 1, dtype=bool)
    for edge in (labels[0, :], labels[-1, :], labels[:, 0], labels[:, -1]):
        border[edge] = True
    ok = (sizes >= 0.25 * area) & (sizes <= 4.0 * area) & ~border[1:]
    if not ok.any():
        return none, peak
    # window (column, row) -> image; the candidate nearest the expectation
    cand = (centres + np.array([c0, r0], dtype=np.float64))[ok]
    return cand[np.argmin(np.hypot(*(cand - expected).T))], peak


@dataclass(frozen=True)
class MarkMotion:
    """The marks' common motion since commissioning: a 2-D similarity fitted to their displacements.

    ``d_i = shift + [[scale, -roll], [roll, scale]] (p_i - p_mean)`` for the commissioned positions p_i.

    Attributes
    ----------
    shift_px : (2,) array
        The common shift (column, row), pixels, at the marks' mean position.
    roll_rad : float
        Their rotation in the image (from +column toward +row), radians.
    scale : float
        Relative change of their spread (dimensionless).
    residual_rms_px : float
        RMS of what the similarity leaves, per coordinate, pixels (over 2N - 4 degrees of freedom).
    shift_sigma_px : float
        Standard deviation of each coordinate of :attr:`shift_px` that the residuals imply, pixels.
    roll_sigma_rad : float
        Standard deviation of :attr:`roll_rad` that they imply, radians.
    residuals_px : (N, 2) array
        Each used mark's residual (NaN for a mark left out).
    used : (N,) bool array
    """

    shift_px: np.ndarray
    roll_rad: float
    scale: float
    residual_rms_px: float
    shift_sigma_px: float
    roll_sigma_rad: float
    residuals_px: np.ndarray
    used: np.ndarray

    @property
    def shift_norm_px(self) -> float:
        return float(np.hypot(*self.shift_px))


def mark_motion(found_px: np.ndarray, commissioned_px: np.ndarray, use: np.ndarray | None = None) -> MarkMotion:
    """Fit the similarity (:class:`MarkMotion`) to the displacements of the marks found.

    Parameters
    ----------
    found_px, commissioned_px : (N, 2) arrays
        Where each mark is now and where commissioning put it, pixels (NaN: not found).
    use : (N,) bool array, optional
        Marks to use (default: every mark found).

    Raises
    ------
    ValueError
        With fewer than 3 marks to use (4 unknowns need them, and a residual to judge the fit by).
    """
    now = np.asarray(found_px, dtype=np.float64).reshape(-1, 2)
    ref = np.asarray(commissioned_px, dtype=np.float64).reshape(-1, 2)
    ok = np.isfinite(now).all(axis=1) & np.isfinite(ref).all(axis=1)
    if use is not None:
        ok &= np.asarray(use, dtype=bool)
    n = int(ok.sum())
    if n < 3:
        raise ValueError(f"the marks' motion needs at least 3 marks, {n} were found")
    p = ref[ok] - ref[ok].mean(axis=0)
    d = now[ok] - ref[ok]
    # unknowns (tx, ty, scale, roll): d_x = tx + s x - r y, d_y = ty + r x + s y
    a = np.zeros((2 * n, 4))
    a[0::2, 0] = 1.0
    a[1::2, 1] = 1.0
    a[0::2, 2], a[0::2, 3] = p[:, 0], -p[:, 1]
    a[1::2, 2], a[1::2, 3] = p[:, 1], p[:, 0]
    b = d.reshape(-1)
    x, *_ = np.linalg.lstsq(a, b, rcond=None)
    res = (b - a @ x).reshape(-1, 2)
    dof = 2 * n - 4
    rms = float(np.sqrt(np.sum(res ** 2) / dof)) if dof > 0 else 0.0
    residuals = np.full(now.shape, np.nan)
    residuals[ok] = res
    # (A^T A) is diagonal (the positions are centred): n for each shift, sum |p|^2 for the scale and the roll
    spread = float(np.sum(p ** 2))
    return MarkMotion(np.array([x[0], x[1]]), float(x[3]), float(x[2]), rms, rms / math.sqrt(n),
                      rms / math.sqrt(spread) if spread > 0 else math.inf, residuals, ok)


def apparent_turn_rad(motion: MarkMotion, focal_px: tuple[float, float]) -> np.ndarray:
    """The camera turn the marks' shift amounts to, (3,) radians about the camera's x, y and z axes (OpenCV:
    x right, y down, z along the optical axis): a turn about y moves the image along +column by f_x per radian,
    one about x along -row by f_y; the roll is the turn about z."""
    fx, fy = (float(f) for f in focal_px)
    return np.array([-motion.shift_px[1] / fy, motion.shift_px[0] / fx, motion.roll_rad])


def implied_pose_u(turn_rad: np.ndarray, fixture_to_camera_rotation: np.ndarray, distance_m: float) -> dict:
    """The fixture pose's standard uncertainty that an apparent camera turn implies (module docstring).

    The marks cannot tell a turn from a sideways slide, so both are stated: a rotation of the fixture frame of
    up to the turn about each of its axes (the camera's turn, expressed in the fixture's axes) and a
    translation of up to turn x distance along each, each taken as one standard uncertainty.

    Parameters
    ----------
    turn_rad : (3,) array
        :func:`apparent_turn_rad`.
    fixture_to_camera_rotation : (3, 3) array
        The fixture frame's axes in the camera frame.
    distance_m : float
        The camera's distance to the fixture's origin, metres.

    Returns
    -------
    dict
        ``rotation_mrad`` and ``translation_mm``: (3,) lists about / along the fixture's x, y, z.
    """
    r = np.asarray(fixture_to_camera_rotation, dtype=np.float64)
    turn = np.asarray(turn_rad, dtype=np.float64)
    # a rotation vector in camera axes, in the fixture's axes: R^T w; each axis's share taken whole
    rotation = np.abs(r.T @ turn)
    # the slide that shifts the image alike: perpendicular to the line of sight, turn x distance
    slide_cam = float(distance_m) * np.array([abs(turn[1]), abs(turn[0]), 0.0])
    translation = np.abs(r.T) @ slide_cam
    return {"rotation_mrad": (1e3 * rotation).tolist(), "translation_mm": (1e3 * translation).tolist()}


def widen_for_pose(figures: dict, pose_u: dict, coverage_factor: float = 2.0) -> dict:
    """Add the fixture pose *pose_u* leaves unknown (:func:`implied_pose_u`) to the figures' budget, as its
    row ``fixture marks: camera shift`` (:func:`~sofast_station.measure.budget_rows.add_budget_row`), and grow
    the expanded uncertainties it reaches in quadrature: ``U' = sqrt(U^2 + (k u)^2)``. Changes *figures* in
    place; returns what was added to each U (k = 2).

    What it reaches (docs/uncertainty.md: the fixture pose reaches ``placement`` and ``optical_tilt_mrad``
    only): a turn of the fixture frame about its x (y, z) axis turns the facet's placement and the boresight
    frame's tilt in it by as much; a slide moves the placement by as much."""
    rot = [float(v) for v in pose_u.get("rotation_mrad", (0.0, 0.0, 0.0))]
    tra = [float(v) for v in pose_u.get("translation_mm", (0.0, 0.0, 0.0))]
    contributions = {f"placement.mrad.{i}": rot[i] for i in range(3)}
    contributions.update({f"placement.mm.{i}": tra[i] for i in range(3)})
    contributions.update({"optical_tilt_mrad.x": rot[0], "optical_tilt_mrad.y": rot[1]})
    inputs = [f"apparent turn about the fixture's {a} ({r:.3g} mrad)" for a, r in zip("xyz", rot)]
    inputs += [f"its sideways slide along {a} ({t:.3g} mm)" for a, t in zip("xyz", tra)]
    return add_budget_row(figures, "fixture marks: camera shift", inputs, contributions, coverage_factor)
