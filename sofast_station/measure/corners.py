"""Facet corners from the mask: rough outline, sub-pixel edges, their intersections.

The white-minus-dark contrast of a pixel straddling the facet edge is proportional to the part of the
pixel the facet covers. Summed across the edge along one image row (or column), the covered fractions
give the edge position to a small fraction of a pixel, whatever the blur; a curve through a few hundred
such positions locates each side to about a hundredth of a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import FacetNotFoundError
from ..geometry import Pose
from .camera import project

#: Half-width (pixels) of the window across an edge over which coverage is summed (default).
EDGE_HALF_WIDTH_PX = 5
#: Plateau and background are read this far beyond the window (pixels), on either side.
PLATEAU_RANGE_PX = (3, 9)
#: Pixels left out at either end of a side (the rough outline's corners are good to a pixel or two).
END_TRIM_PX = 2
#: An edge point's samples (its window and plateaus) keep at least this far (pixels) from every other side
#: of the rough outline: that outline is good to a pixel or so, and a blurred side spreads its light a
#: couple of pixels.
NEIGHBOUR_MARGIN_PX = 3.5
#: A side is quantised (sampled by whole sub-pixel rays, not by area) when no more than this fraction of
#: its edge points has a pixel whose coverage lies off the multiples of 1/n^2 (n = 1: point sampling,
#: a staircase; n = 2..4: a coarse sub-ray grid).
QUANTISED_FRACTION = 0.1
#: Largest sub-ray grid (n x n per pixel) recognised as quantised sampling; finer grids are area-like.
MAX_QUANTISED_GRID = 4
#: Fewest steps a quantised side's staircase needs for its ends to be pinned well inside a pixel: with 0 or
#: 1 the lines through every row's interval still turn by up to a pixel at the ends (the population study:
#: sides with 2 or more steps had corners within 0.012 px, sides with fewer up to 0.46 px off).
MIN_STAIRCASE_STEPS = 2
#: Standard deviation of a known-dark rim's width about the design's, as a fraction of it (a ground seam's
#: width wanders along the edge; the design gives its nominal width): the model error of a side placed
#: the rim's width outside the found edge (:func:`fit_outline`, ``rim_dark``).
RIM_WIDTH_SIGMA = 0.1
#: Standard deviation of a side's bow (its image's departure from a straight line at its ends, pixels)
#: about the design's when :func:`fit_outline` is given no ``bow_sigma_px``.
BOW_SIGMA_PX = 0.1
#: How far a facet may lie from the fixture's nominal pose (radians about, metres along each axis) for
#: the bow's standard deviation (:func:`outline_hints`).
PLACEMENT_SPAN = (0.01, 0.01)
#: Degree of the polynomial that models the lit facet's smooth brightness (:func:`shading`).
SHADING_DEGREE = 4
#: Systematic error of an area-sampled or blurred side's offset and of its end-to-end tilt, pixels
#: (standard uncertainty; the corner finder's own model error, added to each side's fit): on the twin's
#: area-like edge models (exact area, Gaussian and disk blur, vignetting) corners are 0.005-0.016 px RMS
#: per coordinate from the true ones (tests/station/test_corner_models.py, the population study); 0.02 px
#: stated them three times that, and over-covered the corner pose's rotation about x (99 % in 500 captures).
SIDE_MODEL_SIGMA_PX = 0.01
#: How far the lens's blur reaches across the facet's edge, in standard deviations of its line-spread
#: function (:func:`edge_blur_px`): a Gaussian's light beyond it is 0.13 %, and a defocus disk of radius r
#: (standard deviation r / 2) ends at 2 of them.
EDGE_REACH_SIGMAS = 3.0
#: Margin (pixels) kept beyond the blur's reach and the pixel's own half width (:func:`edge_inset_px`).
EDGE_MARGIN_PX = 0.5
#: A blur (standard deviation, pixels) from which the pixel's own half width and the margin are kept in
#: full; a sharper edge keeps that share of them (a sharp edge's partly covered pixels only mix in the
#: dark background: on OpenCSP's 85-pixel-wide facet leaving out that ring moved f_y by 1 %).
EDGE_SHARP_PX = 0.25


@dataclass(frozen=True)
class OutlineFit:
    """Sub-pixel outline of the facet in the image.

    Attributes
    ----------
    corners_px : (N, 2) float array
        Corner image positions (column, row), in the order of the rough outline.
    sides : (N, 7) float array
        Side i (from corner i to corner i+1) as the curve (o_x, o_y, t_x, t_y, a, b, c): points
        o + s t + (a + b s + c s^2) n with n = (-t_y, t_x).
    edge_rms_px : (N,) float array
        RMS distance of each side's edge points from its fitted curve, pixels.
    n_edge_points : (N,) int array
    corner_cov_px2 : (2N, 2N) float array or None
        Covariance of the corners' coordinates (c0 column, c0 row, c1 column, ...), pixels squared, from
        the covariance of each side's fitted curve (:func:`side_covariance`) carried to its two corners
        (:func:`corner_covariance`). Corners sharing a side are correlated: a side's offset moves both,
        its tilt moves them in opposite directions. It holds the noise and :attr:`corner_model_cov_px2`.
    corner_model_cov_px2 : (2N, 2N) float array or None
        The part of :attr:`corner_cov_px2` that is the corner finder's own model error, not noise: each
        side's systematic offset and tilt (:data:`SIDE_MODEL_SIGMA_PX`) or, for a quantised side, where
        in its intervals the edge lies (:func:`_quantised_side`).
    quantised : (N,) int array or None
        Each side's sub-ray grid n (1: point sampled, a staircase) or 0 (area-like; :func:`quantisation`).
    edge_blur_px : float
        Standard deviation of the edge's blur beyond the pixel's own square, pixels (:func:`edge_blur_px`).
    steps : (N,) int array or None
        Each quantised side's steps (how many times its staircase moves to the next row or column), -1 for
        an area-like side. A quantised side with fewer than :data:`MIN_STAIRCASE_STEPS` lies along the pixel
        grid: the image places it only within its interval (up to 1/n pixel) at its ends, whatever the fit
        (:func:`staircase_sides`).
    design_sides : (N,) int array or None
        The design outline's side (0-based: from its corner i to i + 1) each side was matched to, -1 where
        no design outline was given or none matched.
    """

    corners_px: np.ndarray
    sides: np.ndarray
    edge_rms_px: np.ndarray
    n_edge_points: np.ndarray
    corner_cov_px2: np.ndarray | None = None
    corner_model_cov_px2: np.ndarray | None = None
    quantised: np.ndarray | None = None
    edge_blur_px: float = 0.0
    steps: np.ndarray | None = None
    design_sides: np.ndarray | None = None


def rough_outline(region: np.ndarray, n_corners: int) -> np.ndarray:
    """Integer-pixel polygon with *n_corners* vertices approximating the region's outer contour.

    Raises
    ------
    FacetNotFoundError
        When the region is empty or no simplification of its contour has *n_corners* vertices.
    """
    contours, _ = cv2.findContours(region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        raise FacetNotFoundError("no facet outline found in the mask; check that a facet is in the fixture "
                                 "and the screen lights it")
    contour = max(contours, key=cv2.contourArea)
    perimeter = cv2.arcLength(contour, True)
    counts = []
    for frac in (0.01, 0.005, 0.015, 0.02, 0.03, 0.04, 0.05, 0.003):
        poly = cv2.approxPolyDP(contour, frac * perimeter, True)
        counts.append(len(poly))
        if len(poly) == n_corners:
            return poly.reshape(-1, 2).astype(np.float64)
    raise FacetNotFoundError(
        f"the facet's outline in the mask does not have the design's {n_corners} corners (simplified "
        f"outlines had {sorted(set(counts))}); the facet may be partly lit, partly hidden or not the "
        "recipe's facet type")


def _segment_distance(points: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Distance (pixels) of points (..., 2) from the segment q0 -> q1."""
    d = q1 - q0
    t = np.clip(((points - q0) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(points - (q0 + t[..., None] * d), axis=-1)


def _segments_distance(a0: np.ndarray, a1: np.ndarray, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Distance (pixels) between each segment a0[i] -> a1[i] ((M, 2) each) and the segment q0 -> q1: 0
    where they cross, else the least of their ends' distances to the other segment."""
    def side(p, r0, r1):
        return ((r1[..., 0] - r0[..., 0]) * (p[..., 1] - r0[..., 1])
                - (r1[..., 1] - r0[..., 1]) * (p[..., 0] - r0[..., 0]))

    crossing = (np.sign(side(q0, a0, a1)) != np.sign(side(q1, a0, a1))) \
        & (np.sign(side(a0, q0, q1)) != np.sign(side(a1, q0, q1)))
    ends = np.minimum(_segment_distance(a0, q0, q1), _segment_distance(a1, q0, q1))
    d = a1 - a0
    for q in (q0, q1):
        t = np.clip(np.sum((q - a0) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-12), 0.0, 1.0)
        ends = np.minimum(ends, np.linalg.norm(q - (a0 + t[:, None] * d), axis=1))
    return np.where(crossing, 0.0, ends)


def shading(contrast: np.ndarray, region: np.ndarray, degree: int = SHADING_DEGREE) -> np.ndarray | None:
    """The facet's smooth brightness in the contrast image: coefficients of a polynomial in the image
    coordinates fitted to the region's inside (away from its edge), or None for a small region.

    Vignetting, the screen's and the lens's fall-off make the lit facet brighter in one place than in
    another; across an edge that slope biases a coverage sum read against a flat plateau (0.08 px at a
    fall-off of 1.5 % over the window). A polynomial fitted to tens of thousands of pixels gives that
    slope with next to no noise, where each point's own plateau would give it with a lot.
    """
    h, w = contrast.shape
    any_rows, any_cols = np.flatnonzero(region.any(axis=1)), np.flatnonzero(region.any(axis=0))
    if any_rows.size < 20 or any_cols.size < 20:
        return None
    r0, r1, c0, c1 = any_rows[0], any_rows[-1] + 1, any_cols[0], any_cols[-1] + 1
    # every step-th pixel of the region's box (about 10,000), where the region holds 4 px on every side
    step = max(1, int(np.sqrt((r1 - r0) * (c1 - c0) / 10_000)))
    inner = cv2.erode(region[r0:r1, c0:c1].astype(np.uint8), np.ones((9, 9), np.uint8),
                      borderType=cv2.BORDER_CONSTANT, borderValue=0)[::step, ::step] > 0
    rows, cols = np.nonzero(inner)
    if rows.size < 200:
        return None
    rows, cols = r0 + step * rows, c0 + step * cols
    values = contrast[rows, cols].astype(np.float64)
    basis = _shading_basis(cols, rows, h, w, degree)
    keep = np.ones(values.size, dtype=bool)
    for _ in range(2):             # dust, a dent's dark ring: leave the outliers out
        b = basis[keep]
        # (normal equations: the monomials of coordinates in [-1, 1] are well enough conditioned)
        coef = np.linalg.solve(b.T @ b, b.T @ values[keep])
        res = values - basis @ coef
        keep = np.abs(res) < 4.0 * 1.4826 * np.median(np.abs(res[keep])) + 1e-9
    return coef


def _shading_basis(cols, rows, h: int, w: int, degree: int) -> np.ndarray:
    """Monomials x^i y^j (i + j <= degree) of the image coordinates scaled to [-1, 1]."""
    x = (np.asarray(cols, float) - 0.5 * (w - 1)) / (0.5 * w)
    y = (np.asarray(rows, float) - 0.5 * (h - 1)) / (0.5 * h)
    xp, yp = [np.ones_like(x)], [np.ones_like(y)]
    for _ in range(degree):
        xp.append(xp[-1] * x)
        yp.append(yp[-1] * y)
    return np.stack([xp[i] * yp[d - i] for d in range(degree + 1) for i in range(d + 1)], axis=-1)


def _edge_points(contrast: np.ndarray, p0: np.ndarray, p1: np.ndarray, inside_sign: int,
                 half_width: int = EDGE_HALF_WIDTH_PX, others: tuple = (), shade=None) -> tuple:
    """Sub-pixel edge positions along the rough side p0 -> p1.

    One edge point per image column (near-horizontal side) or row: the coverage summed over a window
    across the rough edge, each pixel's coverage its contrast between the background's and the facet's
    level there. Those levels are the medians of plateaus beyond the window on either side; the facet's
    is carried over the window along the facet's smooth brightness (*shade*, :func:`shading`'s
    coefficients), so a vignetted or unevenly lit facet does not bias the sum. Points whose window or
    plateaus come within :data:`NEIGHBOUR_MARGIN_PX` of another side of the rough outline (*others*,
    segments (q0, q1)) are left out.

    Returns
    -------
    points : (M, 2) array
        (column, row) of each edge point.
    coverage : (M, 2 half_width + 1) array
        The window's coverages, in the order across the edge.
    sigma : float
        Standard deviation of one point's edge position from the contrast's noise, pixels.
    """
    empty = (np.empty((0, 2)), np.empty((0, 2 * half_width + 1)), 0.0)
    h, w = contrast.shape
    d = p1 - p0
    along_x = abs(d[0]) >= abs(d[1])          # near-horizontal side: one edge point per column
    a0, a1 = (p0[0], p1[0]) if along_x else (p0[1], p1[1])
    lo, hi = sorted((a0, a1))
    s = np.arange(np.ceil(lo + END_TRIM_PX), np.floor(hi - END_TRIM_PX) + 1)
    if s.size < 3:
        return empty
    # Rough edge crossing of each row/column, from the rough line.
    slope = (d[1] / d[0]) if along_x else (d[0] / d[1])
    base = p0[1] if along_x else p0[0]
    start = p0[0] if along_x else p0[1]
    cross = base + slope * (s - start)
    centre = np.round(cross).astype(np.int64)
    k = np.arange(-half_width, half_width + 1)
    far = np.arange(half_width + PLATEAU_RANGE_PX[0], half_width + PLATEAU_RANGE_PX[1] + 1)
    limit = (h if along_x else w) - 1
    ok = (centre - far[-1] >= 0) & (centre + far[-1] <= limit)
    if others:
        # each point's samples span a segment across the side, from -far[-1] to +far[-1]
        ends = [np.column_stack([s, centre + o]) if along_x else np.column_stack([centre + o, s])
                for o in (-far[-1], far[-1])]
        ends = [e.astype(np.float64) for e in ends]
        clearance = np.min([_segments_distance(ends[0], ends[1], q0, q1) for q0, q1 in others], axis=0)
        ok &= clearance >= NEIGHBOUR_MARGIN_PX
    s, centre = s[ok].astype(np.int64), centre[ok]
    if s.size < 3:
        return empty

    def sample(offsets):
        idx = centre[:, None] + offsets[None, :]
        return contrast[idx, s[:, None]] if along_x else contrast[s[:, None], idx]

    def smooth(offsets):
        """The shading polynomial at the pixels *offsets* across the edge of every point, (M, len)."""
        across = (centre[:, None] + offsets[None, :]).astype(np.float64)
        along = np.broadcast_to(s[:, None], across.shape).astype(np.float64)
        cols, rows = (along, across) if along_x else (across, along)
        return _shading_basis(cols, rows, h, w, SHADING_DEGREE) @ shade

    window = sample(k)
    in_values, out_values = sample(inside_sign * far), sample(-inside_sign * far)
    inside = np.repeat(np.median(in_values, axis=1)[:, None], k.size, axis=1)
    outside = np.repeat(np.median(out_values, axis=1)[:, None], k.size, axis=1)
    if shade is not None:
        both = smooth(np.concatenate([k, inside_sign * far]))
        inside = inside + both[:, :k.size] - np.median(both[:, k.size:], axis=1)[:, None]
    scale = inside - outside
    centre_scale = np.median(scale, axis=1)
    # (a median at or below 0 is an obstructed edge: no point of it is good)
    good = (centre_scale > 0.25 * np.median(centre_scale)) & (centre_scale > 0)
    coverage = (window - outside) / np.where(good[:, None], scale, 1.0)
    total = coverage.sum(axis=1)
    if inside_sign > 0:   # facet on the high side: edge = last window pixel's upper boundary - covered
        edge = centre + half_width + 0.5 - total
    else:                 # facet on the low side: edge = first window pixel's lower boundary + covered
        edge = centre - half_width - 0.5 + total
    # one point's noise: the noisier plateau's scatter (median absolute deviation, over every 4th point;
    # the lit facet has the shot noise) through the window's sum
    spread = max(float(np.median(np.abs(v - np.median(v, axis=1, keepdims=True)))) for v in
                 (in_values[::4], out_values[::4]))
    sigma = float(1.4826 * spread * np.sqrt(k.size) / max(float(np.median(centre_scale)), 1e-9))
    edge, s, coverage = edge[good], s[good], coverage[good]
    if inside_sign < 0:
        coverage = coverage[:, ::-1]
    points = np.column_stack([s, edge]) if along_x else np.column_stack([edge, s])
    return points, coverage, sigma


def _fit_side(points: np.ndarray, rounds: int = 4, degree: int = 2, with_cov: bool = False,
              bow_points: np.ndarray | None = None, bow_sigma_px: float = BOW_SIGMA_PX) -> tuple:
    """Quadratic curve through one side's edge points, with robust rejection of stray points.

    A straight edge on a curved facet is a curve in space: its corners stand nearer the camera than its
    middle, so its image bows by a tenth of a pixel or so (half a pixel on a gore), and the lens's
    distortion bends it too. A quadratic d = a + b s + c s^2 across the side's chord (s along it, d across
    it) follows that bow, where a line would put the corners inside the true ones. With *bow_points* (the
    design outline's side projected at the fixture's nominal pose) the bow is drawn toward the design's
    (a prior of *bow_sigma_px* at the side's ends): a long side's many points still fit their own,
    but a short side's few cannot swing its ends by a pixel.

    *degree* 1 fits a line (for a few points).

    Returns
    -------
    curve : (7,) array
        (o_x, o_y, t_x, t_y, a, b, c): origin o, unit direction t along the side, normal n = (-t_y, t_x).
    rms : float
        RMS distance of the kept points from the curve, pixels.
    n_kept : int
    cov : (4,) tuple, only with *with_cov*
        :func:`side_covariance` of the fit: (mid, half, 3 x 3 covariance of (a, b, c) in the side's own s).
    """
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    t = vt[0]
    n = np.array([-t[1], t[0]])
    s = (points - centre) @ t
    d = (points - centre) @ n
    half = max(0.5 * float(np.ptp(s)), 1.0)
    u = s / half
    prior = None
    if bow_points is not None and len(bow_points) >= 3:
        prior = float(np.polyfit(((bow_points - centre) @ t) / half, (bow_points - centre) @ n, 2)[0])
        degree = 2
    keep = np.ones(len(points), dtype=bool)
    design = np.column_stack([np.ones_like(u), u, u * u])[:, :degree + 1]
    sigma = 0.05
    for _ in range(rounds):
        x, y = design[keep], d[keep]
        if prior is not None:
            # the prior as one more equation, weighted as the points' scatter against its own
            w = sigma / bow_sigma_px
            x = np.vstack([x, [0.0, 0.0, w]])
            y = np.append(y, w * prior)
        coef = np.linalg.lstsq(x, y, rcond=None)[0]
        res = d - design @ coef
        sigma = 1.4826 * np.median(np.abs(res[keep])) + 1e-6
        new_keep = np.abs(res) < max(4.0 * sigma, 0.05)
        if np.array_equal(new_keep, keep) or new_keep.sum() < 10:
            break
        keep = new_keep
    rms = float(np.sqrt(np.mean(res[keep] ** 2)))
    coef = np.concatenate([coef, np.zeros(3 - coef.size)])      # a line has c = 0
    curve = np.array([centre[0], centre[1], t[0], t[1], coef[0], coef[1] / half, coef[2] / half ** 2])
    if not with_cov:
        return curve, rms, int(keep.sum())
    mid, half, cov = side_covariance(s[keep], res[keep], np.ones(int(keep.sum())), degree, 0.0, half)
    if prior is not None and np.all(np.isfinite(cov)):
        # the data's information on (a, b, c) and the prior's on the bow together
        info = np.linalg.pinv(cov)
        info[2, 2] += 1.0 / bow_sigma_px ** 2
        cov = np.linalg.inv(info)
    return curve, rms, int(keep.sum()), (mid, half, cov)


def quantisation(coverage: np.ndarray, sigma_px: float) -> int:
    """Whether a side's edge pixels were sampled by whole sub-pixel rays: the grid n, or 0.

    A renderer (or a sensor) that samples each pixel at n x n points, not over its area, gives every
    pixel a coverage that is a multiple of 1/n^2 (n = 1, point sampling: each pixel facet or background,
    a staircase). Then each row's edge position is known only to within 1/(2n) pixel, and the side must
    be located from where those intervals overlap (:func:`_quantised_side`), not fitted as if the
    positions were noisy samples of the edge.

    A side aligned with the pixel grid has the same few coverages in every row: a sharp area-sampled or
    blurred edge there can look like a multiple of 1/n^2 by chance. n = 1 (no partial pixel at all) stands
    on its own: an area-sampled edge exactly on a pixel boundary says no more than a point-sampled one. n >= 2
    needs the evidence of a grid: rows whose coverage sums differ (at least two sums, each in a tenth of
    the rows: the edge crosses the grid's sub-pixel lines) and no more than two partial pixels in a row (a
    blurred edge has more).

    Parameters
    ----------
    coverage : (M, window) array
        The side's window coverages (:func:`_edge_points`).
    sigma_px : float
        One edge point's noise, pixels (its pixels' coverage noise is this over sqrt(window)).

    Returns
    -------
    int
        The smallest n (1 to :data:`MAX_QUANTISED_GRID`) for which no more than
        :data:`QUANTISED_FRACTION` of the points has a pixel off the multiples of 1/n^2, else 0 (area-like).
    """
    if coverage.shape[0] < 10:
        return 0
    for n in range(1, MAX_QUANTISED_GRID + 1):
        level = on_grid(coverage, sigma_px, n)
        if level is None:                 # the noise hides multiples this fine
            break
        if level is False:
            continue
        if n == 1:
            return n
        partial = (level > 0) & (level < n * n)
        _, rows_with = np.unique(level.sum(axis=1), return_counts=True)
        if np.sum(rows_with >= 0.1 * coverage.shape[0]) >= 2 and np.mean(partial.sum(axis=1) <= 2) >= 0.9:
            return n
    return 0


def on_grid(coverage: np.ndarray, sigma_px: float, n: int):
    """Whether a side's window coverages (:func:`_edge_points`; *sigma_px* one point's noise) are multiples of
    1/n^2 (an n x n sub-ray grid): no more than :data:`QUANTISED_FRACTION` of its points has a pixel off them
    beyond the noise. Returns each pixel's multiple (an int-valued array) when they are, False when not, None
    when the noise hides multiples that fine (or the side has under 10 points)."""
    if coverage.shape[0] < 10:
        return None
    # a pixel's coverage noise is sigma_px / sqrt(window), and the plateaus' levels add about half as much
    # again; the largest of a window's pixels then stays within 6 of it
    tol = max(6.0 * sigma_px / np.sqrt(coverage.shape[1]), 0.02)
    q = 1.0 / (n * n)
    if tol > q / 3.0:
        return None
    level = np.round(coverage / q)
    off = np.abs(coverage / q - level) * q
    return False if np.mean(np.any(off > tol, axis=1)) > QUANTISED_FRACTION else level


def _convex_clip(poly: np.ndarray, normal: np.ndarray, bound: float) -> np.ndarray:
    """The convex polygon (K, 2) cut to the half-plane normal . x <= bound."""
    if len(poly) == 0:
        return poly
    val = poly @ normal - bound
    inside = val <= 0
    if inside.all():
        return poly
    if not inside.any():
        return poly[:0]
    nxt = np.roll(np.arange(len(poly)), -1)
    out = []
    for i in range(len(poly)):
        j = nxt[i]
        if inside[i]:
            out.append(poly[i])
        if inside[i] != inside[j]:
            f = val[i] / (val[i] - val[j])
            out.append(poly[i] + f * (poly[j] - poly[i]))
    return np.array(out)


def _polygon_moments(poly: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Area, centroid (2,) and covariance (2, 2) of the uniform distribution on a simple polygon."""
    x, y = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x, -1), np.roll(y, -1)
    cross = x * y1 - x1 * y
    area = 0.5 * float(cross.sum())
    if abs(area) < 1e-300:
        return 0.0, poly.mean(axis=0), np.zeros((2, 2))
    cx = float(np.sum((x + x1) * cross)) / (6 * area)
    cy = float(np.sum((y + y1) * cross)) / (6 * area)
    ixx = float(np.sum((x * x + x * x1 + x1 * x1) * cross)) / (12 * area)
    iyy = float(np.sum((y * y + y * y1 + y1 * y1) * cross)) / (12 * area)
    ixy = float(np.sum((x * y1 + 2 * x * y + 2 * x1 * y1 + x1 * y) * cross)) / (24 * area)
    cov = np.array([[ixx - cx * cx, ixy - cx * cy], [ixy - cx * cy, iyy - cy * cy]])
    return abs(area), np.array([cx, cy]), cov


def _feasible_lines(u: np.ndarray, lo: np.ndarray, hi: np.ndarray, pick: np.ndarray) -> np.ndarray:
    """The convex polygon of (A, B) with lo_i <= A + B u_i <= hi_i for the points *pick*, (K, 2)."""
    a0 = float(np.median(0.5 * (lo + hi)))
    poly = np.array([[a0 - 10.0, -20.0], [a0 + 10.0, -20.0], [a0 + 10.0, 20.0], [a0 - 10.0, 20.0]])
    for i in pick:
        poly = _convex_clip(poly, np.array([1.0, u[i]]), hi[i])
        poly = _convex_clip(poly, np.array([-1.0, -u[i]]), -lo[i])
        if len(poly) == 0:
            break
    return poly


def _quantised_side(points: np.ndarray, along_x: bool, n: int, sigma_px: float,
                    bow_points: np.ndarray | None = None, with_cov: bool = False,
                    bow_sigma_px: float = BOW_SIGMA_PX) -> tuple:
    """:func:`_fit_side` for a side sampled by whole sub-pixel rays (:func:`quantisation` n).

    Each row's (or column's) edge position e then says only that the edge passes within 1/(2n) pixel of
    it (plus the noise). The side is e = A + B u + C u^2 in the image's sampling frame (rows as a function
    of columns for a near-horizontal side, u the position along the side scaled to [-1, 1]); for a given
    bow C, the (A, B) that pass within all those intervals form a convex polygon. The side is the mean
    of the lines that do, over the bow's prior (the design's, *bow_sigma_px*) as well: polygons on
    a grid of C, each weighted by its area and the prior; its covariance (a uniform distribution on each
    polygon, and the spread between them) is the side's uncertainty. A side with many steps is pinned to
    a small fraction of a pixel; one nearly aligned with the pixel grid only to its interval, whatever
    the fit: that is what its image says.

    Returns :func:`_fit_side`'s tuple and, last, the side's steps (how many times its edge positions
    move to the next row or column; :func:`staircase_sides`).
    """
    s, e = (points[:, 0], points[:, 1]) if along_x else (points[:, 1], points[:, 0])
    order = np.argsort(s)
    s, e = s[order], e[order]
    mid, half = 0.5 * (s.min() + s.max()), max(0.5 * (s.max() - s.min()), 1.0)
    u = (s - mid) / half
    c0 = 0.0
    if bow_points is not None and len(bow_points) >= 3:
        bs, be = (bow_points[:, 0], bow_points[:, 1]) if along_x else (bow_points[:, 1], bow_points[:, 0])
        c0 = float(np.polyfit((bs - mid) / half, be, 2)[0])
    # The binding intervals are those either side of each step and at the ends; every 32nd point besides.
    change = np.flatnonzero(np.abs(np.diff(e)) > 1e-9)
    pick = np.unique(np.concatenate([[0, u.size - 1], change, change + 1, np.arange(0, u.size, 32)]))
    z = np.linspace(-2.5, 2.5, 11)
    bows = c0 + bow_sigma_px * z
    for widen in (1.0, 1.5, 2.5):
        h = 0.5 / n + widen * (3.0 * sigma_px + 0.005)
        slices = []
        for c, prior in zip(bows, np.exp(-0.5 * z * z)):
            poly = _feasible_lines(u, e - c * u * u - h, e - c * u * u + h, pick)
            if len(poly) >= 3:
                area, centroid, cov_ab = _polygon_moments(poly)
                if area > 0:
                    slices.append((area * prior, np.array([centroid[0], centroid[1], c]), cov_ab))
        if slices:
            break
    if slices:
        w = np.array([sl[0] for sl in slices])
        w /= w.sum()
        means = np.array([sl[1] for sl in slices])
        mean = w @ means
        spread = means - mean
        cov = np.einsum("k,ki,kj->ij", w, spread, spread)
        cov[:2, :2] += np.einsum("k,kij->ij", w, np.array([sl[2] for sl in slices]))
        big_a, big_b, big_c = mean
    else:
        # no line passes through every interval (noise or a bent edge): least squares on the positions,
        # each uncertain by the interval's uniform spread
        x = np.column_stack([np.ones_like(u), u])
        big_a, big_b = np.linalg.lstsq(x, e - c0 * u * u, rcond=None)[0]
        big_c = c0
        cov = np.diag([h * h / 3.0, h * h / 3.0, bow_sigma_px ** 2])   # anywhere in the interval
    res = e - (big_a + big_b * u + big_c * u * u)
    # back to e = a + b s + c s^2
    a = big_a - big_b * mid / half + big_c * mid * mid / half ** 2
    b = big_b / half - 2 * big_c * mid / half ** 2
    c = big_c / half ** 2
    rms = float(np.sqrt(np.mean(res ** 2)))
    if along_x:      # point = s (1, 0) + d (0, 1): t = (1, 0), n = (0, 1)
        curve = np.array([0.0, 0.0, 1.0, 0.0, a, b, c])
    else:            # point = s (0, 1) + d' (-1, 0) with d' = -(a + b s + c s^2): t = (0, 1), n = (-1, 0)
        curve = np.array([0.0, 0.0, 0.0, 1.0, -a, -b, -c])
    if not with_cov:
        return curve, rms, int(s.size), int(change.size)
    # (A, B, C) in u = (s - mid) / half: a covariance, so the sign of d' drops out
    return curve, rms, int(s.size), (mid, half, cov), int(change.size)


def _lag1_inflation(res: np.ndarray) -> float:
    """Variance factor (1 + rho) / (1 - rho) for residuals with lag-1 autocorrelation rho (in the order
    along the side; rho taken in [0, 0.8]): neighbouring edge points share blur and pixel sampling, so
    their errors are not independent and a fit's coefficients vary more than white noise would say."""
    if res.size < 10:
        return 1.0
    r = res - res.mean()
    den = float(r @ r)
    rho = float(np.clip((r[:-1] @ r[1:]) / den, 0.0, 0.8)) if den > 0 else 0.0
    return (1.0 + rho) / (1.0 - rho)


def side_covariance(s: np.ndarray, res: np.ndarray, weights: np.ndarray, degree: int = 2,
                    mid: float | None = None, half: float | None = None, correlated: bool = True) -> tuple:
    """Covariance of a side curve d = a + b u + c u^2 (u = (s - mid) / half) fitted by (weighted) least
    squares to edge points at positions *s* (pixels along the side, sorted or not) with residuals *res*.

    The residuals' scatter sets the noise (its weighted RMS, with the fit's degrees of freedom), inflated by
    their lag-1 autocorrelation along the side (:func:`_lag1_inflation`) when *correlated* (not for a
    staircase, whose rows' sawtooth residual is quantisation, not noise).

    Returns
    -------
    (mid, half, cov) : cov is the 3 x 3 covariance of (a, b, c), pixels squared (zero row and column for c
    when *degree* is 1).
    """
    mid = float(np.mean(s)) if mid is None else float(mid)
    half = max(0.5 * float(np.ptp(s)), 1.0) if half is None else float(half)
    u = (np.asarray(s, float) - mid) / half
    order = np.argsort(u)
    x = np.column_stack([np.ones_like(u), u, u * u])[:, :degree + 1]
    w = np.asarray(weights, float)
    n, k = u.size, degree + 1
    wr = (w * res)[order]
    sigma2 = float(wr @ wr) / max(n - k, 1)
    xw = x * w[:, None]
    cov = np.zeros((3, 3))
    try:
        cov[:k, :k] = np.linalg.inv(xw.T @ xw) * sigma2 * (_lag1_inflation(wr) if correlated else 1.0)
    except np.linalg.LinAlgError:
        cov[:k, :k] = np.nan
    return mid, half, cov


def _side_residual(curve: np.ndarray, p: np.ndarray) -> tuple[float, np.ndarray]:
    """Signed distance-like residual of point *p* from a side curve, and its gradient."""
    o, t = curve[:2], curve[2:4]
    n = np.array([-t[1], t[0]])
    a, b, c = curve[4:]
    s = (p - o) @ t
    return float((p - o) @ n - (a + b * s + c * s * s)), n - (b + 2 * c * s) * t


def _intersect_sides(c1: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Point on both side curves, by Newton's method from the intersection of their chords."""
    p = None
    for k in range(12):
        f1, g1 = _side_residual(c1, p if p is not None else c1[:2])
        f2, g2 = _side_residual(c2, p if p is not None else c2[:2])
        if p is None:
            # chords: n.(p - o) = a  (straight-line start)
            m = np.array([[-c1[3], c1[2]], [-c2[3], c2[2]]])
            rhs = np.array([m[0] @ c1[:2] + c1[4], m[1] @ c2[:2] + c2[4]])
            if abs(np.linalg.det(m)) < 1e-6:
                raise FacetNotFoundError("two neighbouring sides of the facet outline are parallel; the outline "
                                         "does not look like the design")
            p = np.linalg.solve(m, rhs)
            continue
        step = np.linalg.solve(np.array([g1, g2]), -np.array([f1, f2]))
        p = p + step
        if np.hypot(*step) < 1e-9:
            break
    return p


def _nominal_side(nominal_px: np.ndarray | None, n_corners: int, p0: np.ndarray, p1: np.ndarray):
    """The design side (points of *nominal_px*, n_corners equal blocks each starting at its corner) whose
    corners lie nearest the rough side p0 -> p1 (either way round), and its index; (None, None) when none
    lies within half the side's length."""
    if nominal_px is None:
        return None, None
    blocks = np.asarray(nominal_px, dtype=np.float64).reshape(n_corners, -1, 2)
    starts = blocks[:, 0]
    ends = np.roll(starts, -1, axis=0)
    forward = np.linalg.norm(starts - p0, axis=1) + np.linalg.norm(ends - p1, axis=1)
    backward = np.linalg.norm(starts - p1, axis=1) + np.linalg.norm(ends - p0, axis=1)
    dist = np.minimum(forward, backward)
    j = int(np.argmin(dist))
    if dist[j] > 0.5 * np.linalg.norm(p1 - p0):
        return None, None
    return np.vstack([blocks[j], ends[j][None, :]]), j


def area_sampled(edges: list, grids: list, fits: list) -> bool:
    """Whether the sides of one image, with their :func:`quantisation` grids and fits (steps last), say the
    camera integrates each pixel's area: some side has coverages off the multiples of a whole pixel in more
    than :data:`QUANTISED_FRACTION` of its points, beyond the noise (a point-sampling renderer never gives
    those), and no quantised side steps like a staircase (:data:`MIN_STAIRCASE_STEPS` or more: an area-sampled
    edge that crosses pixel rows gives partial coverages)."""
    if any(g >= 1 and f[5] >= MIN_STAIRCASE_STEPS for g, f in zip(grids, fits)):
        return False
    for edge, g in zip(edges, grids):
        coverage, sigma = edge[4], edge[5]
        if g or coverage.shape[0] < 10:
            continue
        tol = max(6.0 * sigma / np.sqrt(coverage.shape[1]), 0.02)
        if tol > 1.0 / 3.0:
            continue
        off = np.abs(coverage - np.round(coverage))
        if np.mean(np.any(off > tol, axis=1)) > QUANTISED_FRACTION:
            return True
    return False


def fit_outline(contrast: np.ndarray, region: np.ndarray, n_corners: int,
                half_width_px: int = EDGE_HALF_WIDTH_PX, nominal_px: np.ndarray | None = None,
                bow_sigma_px: np.ndarray | None = None, rim_px: np.ndarray | None = None,
                rim_dark: bool | np.ndarray = False) -> OutlineFit:
    """Sub-pixel corners of the facet outline.

    Parameters
    ----------
    contrast : (H, W) float array
        White minus dark, DN.
    region : (H, W) bool array
        The facet region (see :func:`~sofast_station.measure.mask.facet_region`).
    n_corners : int
        Corners of the design outline.
    half_width_px : int
        Half-width of the window summed across each edge: wide enough for the rough outline's error and the
        edge's blur; plateau and background are read from 3 to 9 px beyond it.
    nominal_px : (n_corners * k, 2) array or None
        The design outline projected at the fixture's nominal pose (column, row), k points per side in the
        design's order, each side's block starting at its corner: each side's bow (its image's curvature,
        from the facet's curvature and the lens's distortion) is taken from it. None: fitted per side.
    bow_sigma_px : (n_corners,) array or None
        Standard deviation of each design side's bow about *nominal_px*'s (:func:`outline_hints`), pixels;
        None: :data:`BOW_SIGMA_PX`.
    rim_px : (n_corners,) array or None
        Width in the image, pixels, of the rim along each design side (in *nominal_px*'s order) that may not
        reflect like the mirror (``FacetDesign.edge_rim_m``): lit, the found edge is the outline; dark, it
        is the rim's inner edge. The side is put midway, and the rim's width, as a uniform spread, joins
        its model error.
    rim_dark : bool or (n_corners,) bool array
        The rim is known dark (``FacetDesign.edge_rim_dark``), on every side or on each design side (in
        *nominal_px*'s order) where True: the side is put the rim's width outside the found edge, uncertain
        by :data:`RIM_WIDTH_SIGMA` of that width.
    """
    rough = rough_outline(region, n_corners)
    centroid = rough.mean(axis=0)
    contrast = contrast.astype(np.float64, copy=False)
    shade = shading(contrast, region)
    edges = []
    for i in range(n_corners):
        p0, p1 = rough[i], rough[(i + 1) % n_corners]
        d = p1 - p0
        along_x = abs(d[0]) >= abs(d[1])
        mid = 0.5 * (p0 + p1)
        # Which way across the edge (increasing row for a near-horizontal side) is the facet?
        inside_sign = 1 if ((centroid - mid)[1] if along_x else (centroid - mid)[0]) > 0 else -1
        others = tuple((rough[j], rough[(j + 1) % n_corners]) for j in range(n_corners) if j != i)
        pts, coverage, sigma = _edge_points(contrast, p0, p1, inside_sign, half_width_px, others, shade)
        if len(pts) < 10:
            raise FacetNotFoundError(
                f"side {i + 1} of the facet outline is too short or too close to the image border to locate "
                "(the facet may be cut off or too small in the image)")
        bow, j = _nominal_side(nominal_px, n_corners, p0, p1)
        edges.append((along_x, mid, inside_sign, pts, coverage, sigma, bow, j))

    def fit_one(edge, grid):
        along_x, mid, inside_sign, pts, coverage, sigma, bow, j = edge
        bow_sigma = BOW_SIGMA_PX if bow_sigma_px is None or j is None else float(bow_sigma_px[j])
        if grid:
            # Its pixels' coverages are multiples of 1/n^2 to well within the noise (the test above): rounded
            # to them, the positions lose their noise.
            q = 1.0 / (grid * grid)
            excess = (np.round(coverage / q) * q - coverage).sum(axis=1)
            pts = pts.copy()
            pts[:, 1 if along_x else 0] -= inside_sign * excess
            curve, r, n, model, k = _quantised_side(pts, along_x, grid, 0.0, bow, with_cov=True,
                                                    bow_sigma_px=bow_sigma)
            noise = (model[0], model[1], np.zeros((3, 3)))
        else:
            k = -1
            curve, r, n, noise = _fit_side(pts, with_cov=True, bow_points=bow, bow_sigma_px=bow_sigma)
            model = (noise[0], noise[1], np.diag([SIDE_MODEL_SIGMA_PX ** 2, SIDE_MODEL_SIGMA_PX ** 2, 0.0]))
        return curve, r, n, noise, model, k

    grids = [quantisation(e[4], e[5]) for e in edges]
    fits = [fit_one(e, g) for e, g in zip(edges, grids)]
    if area_sampled(edges, grids, fits):
        # A camera samples the whole image one way. Where another side shows coverages off the multiples of
        # whole pixels and no side steps like a staircase, the image is area-sampled: a side whose pixels are
        # all whole (0 steps) then lies on a pixel boundary to within its coverages' noise, not anywhere in a
        # pixel's interval. Taken as a staircase it was stated to 1/sqrt(12) px (0.29 against errors of
        # 0.01-0.1 px on the population's area-sampled dish stations), and the corner pose's U 5-20 times its
        # error (RMS of error / (U / 2) 0.1-0.5 for the placement's and boresight's rotations).
        for i, (g, f) in enumerate(zip(grids, fits)):
            if g == 1 and f[5] < MIN_STAIRCASE_STEPS:
                grids[i] = 0
                fits[i] = fit_one(edges[i], 0)
    else:
        # Likewise a coarse sub-ray grid's image (n >= 2, shown by a side that steps through it): a side all of
        # whose pixels are whole lies between two of its sub-ray lines, 1/n of a pixel apart, not anywhere in
        # a pixel's interval. So does a side along the pixel grid whose pixels are all multiples of 1/n^2 but
        # for which :func:`quantisation` saw no evidence of a grid (one coverage sum in every row): fitted as
        # area-like, its corners were stated to 0.01-0.03 px and were 0.07-0.22 px off (the population's 2 x 2
        # grid on the gore, seed 0: chi-square of the 8 corner coordinates 24-147 on 5 of 20 captures).
        image_grid = max((g for g, f in zip(grids, fits) if g >= 2 and f[5] >= MIN_STAIRCASE_STEPS), default=0)
        for i, (g, f) in enumerate(zip(grids, fits)):
            if not image_grid or g >= 2 or (g == 1 and f[5] >= MIN_STAIRCASE_STEPS):
                continue
            if g == 1 or isinstance(on_grid(edges[i][4], edges[i][5], image_grid), np.ndarray):
                grids[i] = image_grid
                fits[i] = fit_one(edges[i], image_grid)
    curves, rms, counts, noise_covs, model_covs, steps, sides = [], [], [], [], [], [], []
    for edge, (curve, r, n, noise, model, k) in zip(edges, fits):
        along_x, mid, inside_sign, pts, coverage, sigma, bow, j = edge
        sides.append(-1 if j is None else int(j))
        steps.append(k)
        if rim_px is not None and j is not None and rim_px[j] > 0:
            # the outline lies between the found edge (rim lit) and a rim's width outward (rim dark)
            w = float(rim_px[j])
            normal = np.array([-curve[3], curve[2]])
            outward = 1.0 if normal @ (mid - centroid) > 0 else -1.0
            curve = curve.copy()
            dark = bool(rim_dark if np.ndim(rim_dark) == 0 else rim_dark[j])
            shift, spread2 = (w, (RIM_WIDTH_SIGMA * w) ** 2) if dark else (0.5 * w, w * w / 12.0)
            curve[4] += outward * shift
            model = (model[0], model[1], model[2] + np.diag([spread2, 0.0, 0.0]))
        curves.append(curve)
        noise_covs.append(noise)
        model_covs.append(model)
        rms.append(r)
        counts.append(n)
    profiles = [e[4] for e in edges]
    corners = np.array([_intersect_sides(curves[i - 1], curves[i]) for i in range(n_corners)])
    model_cov = corner_covariance(corners, curves, model_covs)
    cov = corner_covariance(corners, curves, noise_covs) + model_cov
    return OutlineFit(corners, np.array(curves), np.array(rms), np.array(counts), cov, model_cov,
                      np.array(grids), edge_blur_px(np.vstack(profiles)), np.array(steps), np.array(sides))


def staircase_sides(outline: OutlineFit) -> list[int]:
    """The sides sampled as a staircase that lies along the pixel grid: quantised, with fewer than
    :data:`MIN_STAIRCASE_STEPS` steps; numbered as the design outline's sides (1: from its first corner to
    its second) where the side was matched to one, else in the outline's own order. Their corners are known
    only to within the side's interval at its ends (up to a pixel for point sampling; the corner model's
    covariance holds it); turning the camera a degree or two about its axis gives every side steps."""
    if outline.steps is None or outline.quantised is None:
        return []
    return sorted(side_number(outline.design_sides, i) for i, (n, k) in enumerate(zip(outline.quantised, outline.steps))
                  if n > 0 and 0 <= k < MIN_STAIRCASE_STEPS)


def side_number(design_sides: np.ndarray | None, i: int) -> int:
    """How the figures and the verdict number the outline's side *i*: its design side from 1 (from the
    design outline's corner 1 to corner 2 is side 1), or the outline's own number where it was matched to
    none (*design_sides*: ``OutlineFit.design_sides``)."""
    j = -1 if design_sides is None else int(design_sides[i])
    return (j if j >= 0 else int(i)) + 1


def edge_blur_px(coverage: np.ndarray, trim: float = 0.1) -> float:
    """Standard deviation of the facet edge's blur (the lens's line-spread function), pixels, from the edge
    points' coverage profiles.

    Each profile's steps (coverage 0 beyond the window outside, 1 inside) are the edge's line-spread
    function sampled at the pixel boundaries; their second moment about the profile's own edge position
    (their first moment) is the blur's variance plus the pixel square's 1/12 plus the sampling's 1/12
    (Sheppard's correction; exactly 1/6 on average for a sharp area-sampled edge, 0 for a point-sampled
    step). The moments are linear in the coverages, so noise averages out over the points: their mean,
    the outer *trim* fraction at either end left out (points spoiled by a neighbouring side or dust).
    What it measures is only the profile, whichever way it was formed (no model of the lens).

    Parameters
    ----------
    coverage : (M, 2 h + 1) array
        Coverage profiles across the edge, outside to inside (:func:`_edge_points`).
    trim : float
        Fraction of the points left out at either end of the sorted second moments.

    Returns
    -------
    float
        The blur's standard deviation beyond the pixel's own square, pixels (0 for a sharp edge).
    """
    coverage = np.asarray(coverage, dtype=np.float64)
    if coverage.ndim != 2 or coverage.shape[0] == 0:
        return 0.0
    m, n = coverage.shape
    half = (n - 1) / 2.0
    steps = np.diff(np.concatenate([np.zeros((m, 1)), coverage, np.ones((m, 1))], axis=1), axis=1)
    bounds = np.arange(n + 1) - half - 0.5
    first = steps @ bounds
    second = np.sort(np.einsum("ij,ij->i", steps, (bounds[None, :] - first[:, None]) ** 2))
    cut = int(trim * m)
    variance = float(np.mean(second[cut:m - cut])) if m - 2 * cut > 0 else float(np.median(second))
    return float(np.sqrt(max(variance - 1.0 / 6.0, 0.0)))


def edge_inset_px(blur_px: float) -> float:
    """How far inside the outline (pixels) a pixel's centre must lie for none of its light to come from
    beyond the edge through the lens's blur: :data:`EDGE_REACH_SIGMAS` of the blur (*blur_px*, its standard
    deviation), plus its own half width and :data:`EDGE_MARGIN_PX` for a blurred edge. A sharp edge's
    partly covered pixels see the facet and the dark background only (no light of another phase), so
    below :data:`EDGE_SHARP_PX` of blur that share fades to 0: the centre inside the outline suffices."""
    blur = max(float(blur_px), 0.0)
    return EDGE_REACH_SIGMAS * blur + min(1.0, blur / EDGE_SHARP_PX) * (0.5 + EDGE_MARGIN_PX)


def inside_outline(outline: OutlineFit, cols: np.ndarray, rows: np.ndarray, inset_px: float) -> np.ndarray:
    """Whether each pixel centre (*cols*, *rows*) lies at least *inset_px* inside the fitted outline.

    The distance to a convex outline from inside is the least distance to its sides' curves, each measured
    along the side's normal (the curves' bow is a fraction of a pixel over the side).
    """
    cols, rows = np.asarray(cols, np.float64).ravel(), np.asarray(rows, np.float64).ravel()
    centre = outline.corners_px.mean(axis=0)
    keep = np.ones(cols.size, dtype=bool)
    for o_x, o_y, t_x, t_y, a, b, c in outline.sides:

        def offset(x, y):              # along the side's normal (-t_y, t_x), less the side's curve
            dx, dy = x - o_x, y - o_y
            s = dx * t_x + dy * t_y
            return dy * t_x - dx * t_y - (a + b * s + c * s * s)
        inward = 1.0 if offset(centre[0], centre[1]) > 0 else -1.0
        keep &= inward * offset(cols, rows) >= inset_px
    return keep


def corner_covariance(corners: np.ndarray, curves: list, covs: list) -> np.ndarray:
    """Covariance (2N x 2N, pixels squared) of corners ``i`` = intersection of sides ``i - 1`` and ``i``.

    A change dd of a side's curve moves a corner on it by dp with g . dp = dd (g the side residual's
    gradient there); the two sides through a corner give dp = G^-1 (dd_1, dd_2). Each side's dd at its two
    corners is correlated through its fit's covariance (*covs*: :func:`side_covariance` tuples).
    """
    n = len(corners)
    # jac[i]: (2, 2N_side_offsets) map from the side offsets at the corners to corner i's (column, row).
    # The side offsets: for side j, its offset at corner j (start) and at corner j + 1 (end) -> index 2j, 2j+1.
    jac = np.zeros((2 * n, 2 * n))
    basis = np.zeros((2 * n, 3))
    side_of = np.zeros(2 * n, dtype=int)
    for i in range(n):
        prev, cur = (i - 1) % n, i
        p = corners[i]
        _, g1 = _side_residual(curves[prev], p)
        _, g2 = _side_residual(curves[cur], p)
        g_inv = np.linalg.inv(np.array([g1, g2]))
        # offset of side prev at its end (corner i) and side cur at its start (corner i)
        jac[2 * i:2 * i + 2, 2 * prev + 1] = g_inv[:, 0]
        jac[2 * i:2 * i + 2, 2 * cur] = g_inv[:, 1]
        for j, slot in ((prev, 2 * prev + 1), (cur, 2 * cur)):
            o, t = curves[j][:2], curves[j][2:4]
            mid, half, _ = covs[j]
            u = ((p - o) @ t - mid) / half
            basis[slot] = (1.0, u, u * u)
            side_of[slot] = j
    offsets = np.zeros((2 * n, 2 * n))
    for a in range(2 * n):
        for b in range(2 * n):
            if side_of[a] == side_of[b]:
                offsets[a, b] = basis[a] @ covs[side_of[a]][2] @ basis[b]
    return jac @ offsets @ jac.T


def outline_points_px(design, camera, facet_to_camera, per_side: int = 64) -> np.ndarray:
    """Image points (column, row) along the design outline on the design surface, *per_side* per side
    (each side's block starting at its corner), seen through *camera* with the facet at *facet_to_camera*."""
    corners = design.outline_m
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)[:, None]
    xy = np.concatenate([corners[i] + t * (corners[(i + 1) % len(corners)] - corners[i])
                         for i in range(len(corners))])
    return project(camera, facet_to_camera, np.column_stack([xy, design.z(xy[:, 0], xy[:, 1])]))


def _bows_px(points_px: np.ndarray, n_corners: int) -> np.ndarray:
    """Each side's bow: its image's quadratic departure from its chord at the side's ends, pixels."""
    out = []
    for block in np.asarray(points_px).reshape(n_corners, -1, 2):
        t = block[-1] - block[0]
        t = t / np.linalg.norm(t)
        s = (block - block[0]) @ t
        d = (block - block[0]) @ np.array([-t[1], t[0]])
        half = 0.5 * float(np.ptp(s))
        out.append(float(np.polyfit((s - s.mean()) / half, d, 2)[0]))
    return np.array(out)


def outline_hints(design, camera, fixture_to_camera, per_side: int = 64) -> dict:
    """:func:`fit_outline`'s ``nominal_px``, ``bow_sigma_px``, ``rim_px`` and ``rim_dark`` for a facet design in
    a fixture.

    The design outline on the design surface at the fixture's nominal pose gives each side's bow; how
    much that bow changes when the facet lies up to :data:`PLACEMENT_SPAN` off (turned about, or moved
    along, each of the facet frame's axes at its middle) is the bow's standard deviation (at least
    0.01 px): a gore's long sides change by 0.1 px per 10 mrad, a dish's by a hundredth of that. The rim
    (``design.edge_rim_m``), in pixels along each side, is its width over the side's metres times the
    side's pixels.
    """
    key = (design.outline_m.tobytes(), float(design.focal_length_m), float(design.edge_rim_m),
           bool(design.edge_rim_dark),
           np.asarray(camera.matrix, np.float64).tobytes(), np.asarray(camera.distortion, np.float64).tobytes(),
           fixture_to_camera.rotation.tobytes(), fixture_to_camera.translation.tobytes(), int(per_side))
    hit = _HINTS.get(key)
    if hit is None:
        if len(_HINTS) > 16:
            _HINTS.clear()
        hit = _HINTS[key] = _outline_hints(design, camera, fixture_to_camera, per_side)
    return dict(hit)


#: :func:`outline_hints` of the last few (design, camera, fixture pose): the same for every capture of a
#: station (read-only arrays).
_HINTS: dict = {}


def _outline_hints(design, camera, fixture_to_camera, per_side: int) -> dict:
    nominal = outline_points_px(design, camera, fixture_to_camera, per_side)
    n = len(design.outline_m)
    coarse = _bows_px(outline_points_px(design, camera, fixture_to_camera, 16), n)
    mx, my = design.middle_m
    middle = np.array([mx, my, float(design.z(mx, my))])
    rot_rad, shift_m = PLACEMENT_SPAN
    spread = np.zeros(n)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            rvec = np.zeros(3)
            rvec[axis] = sign * rot_rad
            r = _rotation(rvec)
            turned = Pose(r, middle - r @ middle)
            moved = Pose(np.eye(3), sign * shift_m * np.eye(3)[axis])
            for off in (turned, moved):
                other = outline_points_px(design, camera, fixture_to_camera.compose(off), 16)
                spread = np.maximum(spread, np.abs(_bows_px(other, n) - coarse))
    rim = None
    if design.edge_rim_m > 0:
        starts = nominal.reshape(n, -1, 2)[:, 0]
        length_px = np.linalg.norm(np.roll(starts, -1, axis=0) - starts, axis=1)
        length_m = np.linalg.norm(np.roll(design.outline_m, -1, axis=0) - design.outline_m, axis=1)
        rim = design.edge_rim_m * length_px / length_m
        rim.setflags(write=False)
    nominal.setflags(write=False)
    sigma = np.maximum(spread, 0.01)
    sigma.setflags(write=False)
    return {"nominal_px": nominal, "bow_sigma_px": sigma, "rim_px": rim, "rim_dark": bool(design.edge_rim_dark)}


def _rotation(rvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, np.float64))[0]


def match_corners(found_px: np.ndarray, expected_px: np.ndarray, tolerance_px: float) -> np.ndarray:
    """Reorder *found_px* to correspond to *expected_px* (the design corners projected nominally).

    Raises
    ------
    FacetNotFoundError
        When a found corner is farther than *tolerance_px* from every expected one or two share one.
    """
    dist = np.linalg.norm(found_px[None, :, :] - expected_px[:, None, :], axis=2)
    order = np.argmin(dist, axis=1)
    worst = float(dist[np.arange(len(expected_px)), order].max())
    if len(set(order.tolist())) != len(expected_px) and worst <= tolerance_px:
        raise FacetNotFoundError(
            f"the outline found in the mask is not the facet's: two of its corners are nearest the same design "
            f"corner (all within {worst:.0f} px of where the fixture puts them): the facet is partly hidden or "
            "obstructed, or it is not the recipe's facet type")
    if len(set(order.tolist())) != len(expected_px) or worst > tolerance_px:
        raise FacetNotFoundError(
            f"the facet's corners are up to {worst:.0f} px from where the fixture puts them (tolerance "
            f"{tolerance_px:.0f} px); the facet is misplaced in the fixture or the station geometry is wrong")
    return found_px[order]


def mask_outline_corners(region: np.ndarray, n_corners: int, end_fraction: float = 0.15) -> tuple[np.ndarray, float]:
    """Corners of a region's outline from its boundary pixels alone: a straight line fitted (total least
    squares) to each side's boundary pixels, moved half a pixel outward (a boundary pixel's centre lies half
    a pixel inside the edge it marks), and adjacent lines intersected. The coarse route, for an outline too
    near the image's border for :func:`fit_outline`'s edge profiles (they read the background up to 12 px
    beyond the edge): what OpenCSP does with its masks.

    Returns
    -------
    (corners, sigma_px)
        (n_corners, 2) corners (column, row) in :func:`rough_outline`'s order, and each corner coordinate's
        standard uncertainty: the sides' boundary pixels scatter about their lines by at least a pixel's
        quantisation (1/sqrt(12)), and a line's end moves by that over the square root of its points, three
        times (a line's end point, as for :func:`fit_outline`'s sides), pixels.
    """
    rough = rough_outline(region, n_corners)
    contours, _ = cv2.findContours(region.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contour = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    centroid = rough.mean(axis=0)
    lines, sigmas = [], []
    for i in range(n_corners):
        p0, p1 = rough[i], rough[(i + 1) % n_corners]
        d = p1 - p0
        length = float(np.hypot(*d))
        t = (contour - p0) @ d / (length * length)
        off = np.abs((contour - p0) @ np.array([-d[1], d[0]]) / length)
        pts = contour[(t > end_fraction) & (t < 1.0 - end_fraction) & (off < 3.0)]
        if len(pts) < 5:
            raise FacetNotFoundError("the outline's side is too short to locate in the mask (the mirror is too small "
                                     "in the image)")
        mean = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - mean, full_matrices=False)
        normal = vt[1]
        if (centroid - mean) @ normal > 0:          # outward
            normal = -normal
        res = (pts - mean) @ normal
        lines.append((normal, float(mean @ normal) + 0.5))
        sigmas.append(3.0 * max(float(np.sqrt(np.mean(res * res))), 1.0 / np.sqrt(12.0)) / np.sqrt(len(pts)))
    corners = []
    for i in range(n_corners):
        (n1, c1), (n2, c2) = lines[i - 1], lines[i]
        corners.append(np.linalg.solve(np.array([n1, n2]), np.array([c1, c2])))
    return np.array(corners), float(np.median(sigmas))
