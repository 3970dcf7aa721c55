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

#: Half-width (pixels) of the window across an edge over which coverage is summed (default).
EDGE_HALF_WIDTH_PX = 5
#: Plateau and background are read this far beyond the window (pixels), on either side.
PLATEAU_RANGE_PX = (3, 9)
#: Fraction of each side left out at either end, away from the rough outline's corner error.
SIDE_TRIM = 0.03
#: Pixels left out at either end of a side: the window and plateau of a point there must not reach
#: across the neighbouring side.
END_TRIM_PX = 16
#: A side is a staircase (sharply point-sampled edge) when most of its edge positions lie this close
#: (pixels) to a half-integer: each row or column then says only between which two pixel centres it lies.
STAIRCASE_TOLERANCE_PX = 0.05


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
        its tilt moves them in opposite directions.
    """

    corners_px: np.ndarray
    sides: np.ndarray
    edge_rms_px: np.ndarray
    n_edge_points: np.ndarray
    corner_cov_px2: np.ndarray | None = None


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


def _edge_points(contrast: np.ndarray, p0: np.ndarray, p1: np.ndarray, inside_sign: int,
                 half_width: int = EDGE_HALF_WIDTH_PX) -> np.ndarray:
    """Sub-pixel edge positions along the rough side p0 -> p1, (M, 2) (column, row)."""
    h, w = contrast.shape
    d = p1 - p0
    along_x = abs(d[0]) >= abs(d[1])          # near-horizontal side: one edge point per column
    a0, a1 = (p0[0], p1[0]) if along_x else (p0[1], p1[1])
    lo, hi = sorted((a0, a1))
    span = hi - lo
    trim = max(SIDE_TRIM * span, END_TRIM_PX)
    s = np.arange(np.ceil(lo + trim), np.floor(hi - trim) + 1)
    if s.size < 3:
        return np.empty((0, 2))
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
    s, centre = s[ok].astype(np.int64), centre[ok]
    if s.size < 3:
        return np.empty((0, 2))

    def sample(offsets):
        idx = centre[:, None] + offsets[None, :]
        return contrast[idx, s[:, None]] if along_x else contrast[s[:, None], idx]

    window = sample(k)
    inside = np.median(sample(inside_sign * far), axis=1)
    outside = np.median(sample(-inside_sign * far), axis=1)
    scale = inside - outside
    good = (scale > 0.25 * np.median(scale)) & (scale > 0)      # (a median at or below 0: an obstructed edge)
    coverage = (window - outside[:, None]) / np.where(good, scale, 1.0)[:, None]
    total = coverage.sum(axis=1)
    if inside_sign > 0:   # facet on the high side: edge = last window pixel's upper boundary - covered
        edge = centre + half_width + 0.5 - total
    else:                 # facet on the low side: edge = first window pixel's lower boundary + covered
        edge = centre - half_width - 0.5 + total
    edge, s = edge[good], s[good]
    return np.column_stack([s, edge]) if along_x else np.column_stack([edge, s])


def _fit_side(points: np.ndarray, rounds: int = 4, degree: int = 2,
              with_cov: bool = False) -> tuple[np.ndarray, float, int]:
    """Quadratic curve through one side's edge points, with robust rejection of stray points.

    A straight edge on a curved facet is a curve in space: its corners stand nearer the camera than its
    middle, so its image bows by a tenth of a pixel or so. A quadratic d = a + b s + c s^2 across the
    side's chord (s along it, d across it) follows that bow, where a line would put the corners inside
    the true ones.

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
    keep = np.ones(len(points), dtype=bool)
    design = np.column_stack([np.ones_like(s), s, s * s][:degree + 1])
    for _ in range(rounds):
        coef = np.linalg.lstsq(design[keep], d[keep], rcond=None)[0]
        res = d - design @ coef
        sigma = 1.4826 * np.median(np.abs(res[keep])) + 1e-6
        new_keep = np.abs(res) < max(4.0 * sigma, 0.05)
        if np.array_equal(new_keep, keep) or new_keep.sum() < 10:
            break
        keep = new_keep
    rms = float(np.sqrt(np.mean(res[keep] ** 2)))
    coef = np.concatenate([coef, np.zeros(3 - coef.size)])      # a line has c = 0
    curve = np.array([centre[0], centre[1], t[0], t[1], *coef])
    if not with_cov:
        return curve, rms, int(keep.sum())
    cov = side_covariance(s[keep], res[keep], np.ones(int(keep.sum())), degree)
    return curve, rms, int(keep.sum()), cov


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


def is_staircase(edge: np.ndarray) -> bool:
    """Whether edge positions (pixels, along the sampling axis) come from a point-sampled edge.

    Summed across a point-sampled edge, each row or column counts whole pixels, so its edge position is
    a half-integer (between the last background and the first facet pixel centre).
    """
    off = np.abs(edge - (np.floor(edge) + 0.5))
    return edge.size >= 10 and float(np.mean(off < STAIRCASE_TOLERANCE_PX)) > 0.8


def _staircase_side(points: np.ndarray, along_x: bool, with_cov: bool = False) -> tuple[np.ndarray, float, int]:
    """:func:`_fit_side` for a point-sampled side, weighting the steps of its staircase.

    A row or column of a point-sampled edge only says between which two pixel centres the edge passes
    (its half-integer position is uncertain by 1/sqrt(12) px). Where the staircase steps from one column
    (or row) to the next, the edge crosses a line of pixel centres between the two: a point known to half
    a pixel along the edge, and so, for a side tilted by t pixels per pixel, to about t/2 across it. The
    quadratic is fitted to both by weighted least squares (in the image's sampling frame: rows as a
    function of columns for a near-horizontal side, and the other way round), so a side with many steps
    is located to a small fraction of a pixel, and one with few keeps the shape its rows or columns give.
    A side aligned with the pixel grid has no steps and no sub-pixel information.
    """
    s, e = (points[:, 0], points[:, 1]) if along_x else (points[:, 1], points[:, 0])
    order = np.argsort(s)
    s, e = s[order], e[order]
    k = np.round(e - 0.5)
    nxt = np.flatnonzero((np.diff(s) == 1) & (np.abs(np.diff(k)) == 1))
    steps_s = s[nxt] + 0.5
    steps_d = np.maximum(k[nxt], k[nxt + 1])
    # local tilt (pixels per pixel) from the staircase's overall slope
    tilt = abs(float(np.polyfit(s, e, 1)[0])) if s.size > 2 else 1.0
    sigma_step = max(0.5 * tilt / np.sqrt(3.0), 0.01)
    ss = np.concatenate([s, steps_s])
    dd = np.concatenate([k + 0.5, steps_d])
    w = np.concatenate([np.full(s.size, np.sqrt(12.0)), np.full(steps_s.size, 1.0 / sigma_step)])
    mid, half = 0.5 * (s.min() + s.max()), max(0.5 * (s.max() - s.min()), 1.0)
    u = (ss - mid) / half
    design = np.column_stack([np.ones_like(u), u, u * u])
    coef = np.linalg.lstsq(design * w[:, None], dd * w, rcond=None)[0]
    res = e - (coef[0] + coef[1] * (s - mid) / half + coef[2] * ((s - mid) / half) ** 2)
    a2, b2, c2 = coef
    a, b, c = a2 - b2 * mid / half + c2 * mid * mid / half ** 2, b2 / half - 2 * c2 * mid / half ** 2, c2 / half ** 2
    rms = float(np.sqrt(np.mean(res ** 2)))
    if along_x:      # point = s (1, 0) + d (0, 1): t = (1, 0), n = (0, 1)
        curve = np.array([0.0, 0.0, 1.0, 0.0, a, b, c])
    else:            # point = s (0, 1) + d' (-1, 0) with d' = -(a + b s + c s^2): t = (0, 1), n = (-1, 0)
        curve = np.array([0.0, 0.0, 0.0, 1.0, -a, -b, -c])
    if not with_cov:
        return curve, rms, int(s.size)
    # Weighted residuals of rows/columns and steps alike (each ~1 when the weights are right).
    res_all = dd - design @ coef
    cov = side_covariance(ss, res_all, w, 2, mid, half, correlated=False)
    return curve, rms, int(s.size), cov


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


def fit_outline(contrast: np.ndarray, region: np.ndarray, n_corners: int,
                half_width_px: int = EDGE_HALF_WIDTH_PX) -> OutlineFit:
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
    """
    rough = rough_outline(region, n_corners)
    centroid = rough.mean(axis=0)
    contrast = contrast.astype(np.float64, copy=False)
    curves, rms, counts, covs = [], [], [], []
    for i in range(n_corners):
        p0, p1 = rough[i], rough[(i + 1) % n_corners]
        d = p1 - p0
        along_x = abs(d[0]) >= abs(d[1])
        mid = 0.5 * (p0 + p1)
        # Which way across the edge (increasing row for a near-horizontal side) is the facet?
        inside_sign = 1 if ((centroid - mid)[1] if along_x else (centroid - mid)[0]) > 0 else -1
        pts = _edge_points(contrast, p0, p1, inside_sign, half_width_px)
        if len(pts) < 10:
            raise FacetNotFoundError(
                f"side {i + 1} of the facet outline is too short or too close to the image border to locate "
                "(the facet may be cut off or too small in the image)")
        edge = pts[:, 1] if along_x else pts[:, 0]
        curve, r, n, c = (_staircase_side(pts, along_x, with_cov=True) if is_staircase(edge)
                          else _fit_side(pts, with_cov=True))
        curves.append(curve)
        covs.append(c)
        rms.append(r)
        counts.append(n)
    corners = np.array([_intersect_sides(curves[i - 1], curves[i]) for i in range(n_corners)])
    cov = corner_covariance(corners, curves, covs)
    return OutlineFit(corners, np.array(curves), np.array(rms), np.array(counts), cov)


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
