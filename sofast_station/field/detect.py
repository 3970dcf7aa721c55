"""Facet corners by edge detection in a photograph of a heliostat seen from far away.

The steps follow the DLR method (Röger, Prahl and Ulmer: the colour plane with the best contrast, a
threshold that tells the facets from what lies around them, connected regions assigned to the design's
facets, each facet's edges as straight lines, corners where they cross), with sub-pixel edges in place of
the Hough transform:

1. **The facets' colour.** DLR take the colour plane with the best contrast (mostly blue: the mirrors show
   the sky). No one plane always parts a facet from both the ground and the steel behind its gaps (in red
   the sky-lit facet is as dark as the beams, in blue as bright as sandy ground), so here each pixel's
   distance in colour from the facets' own colour is used: one of the main colours around the heliostat
   (k-means), the one whose regions match the layout best.
2. **The regions.** Otsu's threshold of that distance (or a half or a quarter of it: the steel behind the
   gaps may lie between the facets' colour and the ground's) around where the heliostat should be (its design
   projected at the commanded orientation, :func:`detect_facets`' *predicted_px*), a morphological opening
   (a thin bridge between two facets is no gap; widened until the facets stand apart), connected regions.
3. **Which facet is which.** The predicted layout slides over the regions: the shift that puts the most
   predicted facet centres on region centroids (a neighbour's facets never line up with the layout's grid
   as the heliostat's own do), then an affine map from predicted to found centres takes up the zoom's and
   the roll's error. A region holding the centres of two facets is *merged*; one much smaller than its
   prediction *partly hidden*; one that touches the photo's edge *cut off*; each is named with its reason
   and left out.
4. **Sub-pixel edges.** Across each side of a facet's rough outline, the colour gradient's size (each
   channel Gaussian smoothed and differentiated, sampled every quarter pixel along the side's normal) peaks
   where the edge is: the 50 % level of a symmetric blur whatever the colours on either side, so a dark
   beam or the lit ground behind a gap, or
   a neighbouring facet two pixels away, leave it in place. The points are taken to the ideal (undistorted)
   image, where a straight edge is a straight line; a line through them (total least squares, outliers
   dropped), and the corners where adjacent lines cross.
5. **Uncertainty.** Each line's offset and direction from its points' scatter (inflated by the scatter's
   correlation along the side: the smoothing makes neighbouring points share noise), carried to its two
   corners; and a floor of :data:`CORNER_MODEL_PX` per coordinate for what the straight-edge model misses.

Pure numpy, scipy and OpenCV; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..errors import CaptureError, FacetNotFoundError
from ..geometry import CameraIntrinsics

#: Standard deviation of the Gaussian smoothing before the derivative, pixels (at most: narrow gaps get less).
SMOOTHING_PX = 1.0
#: Half-width of the search across a rough side, pixels (the rough outline is good to a pixel or two).
SEARCH_HALF_WIDTH_PX = 3.5
#: Half-width of the search across a side placed by the layout's homography, pixels.
SECOND_HALF_WIDTH_PX = 2.0
#: A facet whose corners stray further than this from the layout's homography through the others is fitted
#: again, narrower, from where the homography puts it (pixels; a neighbour's edge beside it may have been
#: taken), and left out when they still stray further than LAYOUT_TOLERANCE_PX (a canting error of 10 mrad
#: moves a 1 m facet's corners by 5 mm out of the layout's plane).
REFIT_PX = 0.75
LAYOUT_TOLERANCE_PX = 2.5
#: Sampling step across a side, pixels.
ACROSS_STEP_PX = 0.25
#: Pixels left out at either end of a side (the neighbouring side's edge blurs into the corner).
END_TRIM_PX = 5.0
#: An edge point's derivative peak must exceed this many standard deviations of the derivative's noise.
MIN_PEAK_SIGMAS = 6.0
#: The corner's model error (standard uncertainty per coordinate, pixels) added to its fit's: what the
#: straight-edge model and the derivative's peak leave (the twin's population: tests/field/).
CORNER_MODEL_PX = 0.05
#: A facet's region must hold this share of its predicted area, at least and at most.
AREA_RATIO = (0.7, 1.4)
#: Fewest edge points a side needs, and the least share of its length they must cover (a side mostly hidden
#: by something in front places its line poorly: the facet is left out as partly hidden).
MIN_EDGE_POINTS = 8
MIN_SIDE_SHARE = 0.5
#: Gaps between facets narrower than this in the photo (pixels) cannot part them (the edge search spans
#: SEARCH_HALF_WIDTH_PX either side, the blur a pixel or so).
MIN_GAP_PX = 2.5
#: Fewest facets, as a share of the design's, for a photo to count as showing the heliostat.
MIN_FOUND_FRACTION = 0.5
#: A facet whose pixels are at the sensor's top level for more than this share is overexposed.
SATURATED_FACET_SHARE = 0.3


@dataclass(frozen=True)
class FacetFound:
    """One facet's corners in a photo.

    Attributes
    ----------
    label : str
    corners_px : (N, 2) array
        In the photo (distorted), column and row, in the design outline's order.
    ideal_px : (N, 2) array
        The same corners in the ideal (undistorted) image: pixels of a pinhole camera with the photo's camera
        matrix.
    cov_px2 : (2N, 2N) array
        Covariance of *ideal_px* (corner 0 column, corner 0 row, corner 1 column, ...), pixels squared.
    edge_rms_px : (N,) array
        RMS of each side's edge points about its line, pixels (side i runs from corner i to i + 1).
    n_edge_points : (N,) int array
    saturated_share : float
        Share of its pixels at the sensor's top level.
    """

    label: str
    corners_px: np.ndarray
    ideal_px: np.ndarray
    cov_px2: np.ndarray
    edge_rms_px: np.ndarray
    n_edge_points: np.ndarray
    saturated_share: float = 0.0


@dataclass(frozen=True)
class Detection:
    """What :func:`detect_facets` found.

    Attributes
    ----------
    facets : dict
        Label -> :class:`FacetFound`, in the design's order.
    left_out : dict
        Label -> why that facet is not among them (not found, merged with ..., partly hidden, cut off,
        overexposed, edges not found).
    facet_colour : tuple
        The facets' colour (one value per channel) whose distance was segmented and differentiated.
    shift_px : (2,) array
        How far the heliostat lies from where it was predicted (the affine map's move of its middle), pixels.
    scale : float
        Its size against the prediction (the affine map's).
    threshold : float
        Otsu's threshold of the colour distance.
    saturated_fraction : float
        Share of the found facets' pixels at the sensor's top level.
    placed_px : dict
        Label -> (N, 2) where the layout's map put each facet's corners (its found ones where it was found):
        where a facet left out should have been.
    """

    facets: dict
    left_out: dict
    facet_colour: tuple
    shift_px: np.ndarray
    scale: float
    threshold: float
    saturated_fraction: float
    placed_px: dict = None


def check_photo(image: np.ndarray, camera: CameraIntrinsics, what: str = "the photo") -> np.ndarray:
    """The photo as an (H, W) or (H, W, 3) array whose size is the camera's; CaptureError otherwise."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 4:
        image = image[..., :3]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3) or image.size == 0:
        raise CaptureError(f"{what} is not a grey or colour picture (array of shape {image.shape})")
    h, w = image.shape[:2]
    if (w, h) != (camera.width_px, camera.height_px):
        raise CaptureError(f"{what} is {w} x {h} pixels but the camera's intrinsics are for {camera.width_px} x "
                           f"{camera.height_px}: give the intrinsics of the camera (and zoom) that took it, or the "
                           "photo as the camera wrote it (not resized or cropped)")
    return image


def _distance(colours: np.ndarray, colour) -> np.ndarray:
    """Each pixel's distance (Euclidean over the channels) from *colour*: a pixel that mixes the facet's colour f
    with another b by a fraction a lies a (b - f) away, so the distance is linear in the mixing across an edge
    (its derivative peaks at the edge's middle, whatever lies beside the facet)."""
    d = colours - np.asarray(colour, dtype=np.float32)
    return np.sqrt(np.sum(d * d, axis=-1)).astype(np.float32)


def _candidate_colours(colours: np.ndarray, k: int = 4) -> list:
    """The main colours around the heliostat (k-means over a sample of the pixels), most common first: one of
    them is the facets'."""
    pix = colours.reshape(-1, colours.shape[-1])
    pix = pix[:: max(1, pix.shape[0] // 20000)].astype(np.float32)
    k = min(k, len(np.unique(pix, axis=0)))
    if k < 2:
        return [pix.mean(axis=0)]
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.5)
    cv2.setRNGSeed(0)                 # the same photo gives the same clusters
    _, lab, centres = cv2.kmeans(pix, k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
    counts = np.bincount(lab.ravel(), minlength=k)
    return [centres[i] for i in np.argsort(-counts)]


def _gradients(colours: np.ndarray, roi, smoothing: float = SMOOTHING_PX) -> tuple:
    """Each channel's derivatives along columns and rows (Gaussian smoothed, Sobel), lists of C (H, W) arrays,
    and the noise of the colour gradient's size across an edge (the channels' robust spreads in quadrature)."""
    gx, gy, var = [], [], 0.0
    for c in range(colours.shape[-1]):
        smooth = cv2.GaussianBlur(np.ascontiguousarray(colours[..., c]), (0, 0), smoothing)
        gx.append(cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3) / 8.0)
        gy.append(cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3) / 8.0)
        g = np.concatenate([gx[-1][roi].ravel(), gy[-1][roi].ravel()])
        var += (1.4826 * float(np.median(np.abs(g - np.median(g))))) ** 2
    return gx, gy, math.sqrt(var) + 1e-6


def _top_level(image: np.ndarray) -> float:
    if image.dtype == np.uint8:
        return 255.0
    if image.dtype == np.uint16:
        return float(max(int(image.max()), 1)) if image.max() > 4095 else 4095.0
    return float(np.max(image))


def _otsu(values: np.ndarray) -> tuple[float, float]:
    """Otsu's threshold of *values* and its separability (between-class over total variance)."""
    lo, hi = float(values.min()), float(values.max())
    if hi <= lo:
        return lo, 0.0
    scaled = np.round((values - lo) / (hi - lo) * 255.0).astype(np.uint8).reshape(-1, 1)
    t, _ = cv2.threshold(scaled, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    above = scaled[:, 0] > t
    w1 = float(np.mean(above))
    if w1 in (0.0, 1.0):
        return lo + (hi - lo) * t / 255.0, 0.0
    m1, m0 = float(np.mean(values.ravel()[above])), float(np.mean(values.ravel()[~above]))
    between = w1 * (1.0 - w1) * (m1 - m0) ** 2
    return lo + (hi - lo) * (t + 0.5) / 255.0, between / max(float(np.var(values)), 1e-12)


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _affine(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The affine map (2, 3) taking *src* points to *dst* (least squares)."""
    a = np.column_stack([src, np.ones(len(src))])
    return np.linalg.lstsq(a, dst, rcond=None)[0].T


def _apply(m: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ m[:, :2].T + m[:, 2]


def detect_facets(image: np.ndarray, camera: CameraIntrinsics, predicted_px: dict, *,
                  search_px: float | None = None, min_found_fraction: float = MIN_FOUND_FRACTION) -> Detection:
    """Every facet's corners in a photo of one heliostat (module docstring).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        The photo (RGB for colour), 8 or 16 bit.
    camera : CameraIntrinsics
        The camera (and zoom) that took it.
    predicted_px : dict
        Label -> (N, 2) pixels where the facet's design corners should be (the design at the commanded
        orientation seen by the camera as it is thought to point), in the design outline's order.
    search_px : float, optional
        How far from its prediction the heliostat may be, pixels (default: half its size, at least 40).
    min_found_fraction : float
        Fewer facets found than this share of the predicted ones: the photo does not show the heliostat.

    Raises
    ------
    CaptureError
        The photo is not the camera's size, or is overexposed.
    FacetNotFoundError
        No heliostat where it should be, or too few of its facets (the reasons named: merged, hidden...).
    """
    image = check_photo(image, camera)
    if not predicted_px:
        raise FacetNotFoundError("no facet of the heliostat faces the camera at the commanded orientation: "
                                 "there is nothing to look for (is the heliostat seen from behind?)")
    labels = list(predicted_px)
    pred = {k: np.asarray(v, dtype=np.float64) for k, v in predicted_px.items()}
    centres = np.array([pred[k].mean(axis=0) for k in labels])
    areas = np.array([_area(pred[k]) for k in labels])
    allc = np.vstack(list(pred.values()))
    extent = float(np.max(np.ptp(allc, axis=0)))
    margin = max(0.5 * extent, 40.0) if search_px is None else float(search_px)
    h, w = image.shape[:2]
    (x0, y0), (x1, y1) = allc.min(axis=0) - margin, allc.max(axis=0) + margin
    c0, r0, c1, r1 = int(max(x0, 0)), int(max(y0, 0)), int(min(x1, w - 1)), int(min(y1, h - 1))
    where = f"({centres.mean(axis=0)[0]:.0f}, {centres.mean(axis=0)[1]:.0f})"
    if c1 - c0 < 8 or r1 - r0 < 8:
        raise FacetNotFoundError(f"the heliostat should be at pixels {where}, outside the {w} x {h} photo: is the "
                                 "camera pointed at it, and are its position and the camera's right?")
    roi = (slice(r0, r1 + 1), slice(c0, c1 + 1))
    top = _top_level(image)
    colours = image.astype(np.float32).reshape(h, w, -1)
    # 1.-3. the facets' colour, the regions of that colour opened until facets stand apart, matched to the layout
    facet_px = math.sqrt(float(np.median(areas)))
    best_match = None
    good = 0.8 * len(labels)
    for colour in _candidate_colours(colours[roi]):
        sub = _distance(colours[roi], colour)
        otsu, _ = _otsu(sub)
        # Otsu's threshold parts the facets' colour from the farthest (the ground); the steel behind the gaps may
        # lie between: nearer thresholds part the facets from it too
        for threshold in (otsu, 0.5 * otsu, 0.25 * otsu):
            binary = (sub < threshold).astype(np.uint8)
            for size in (3, 5, 9, 15, 25):
                if size > 0.4 * facet_px and size > 3:
                    break
                opened = cv2.morphologyEx(binary, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                                                             (size, size)))
                _, lab, stats, cents = cv2.connectedComponentsWithStats(opened, connectivity=4)
                match = _match(lab, stats, cents, centres - [c0, r0], areas, (c0, r0))
                if best_match is None or match["score"] > best_match["score"]:
                    best_match = dict(match, colour=colour, threshold=threshold)
                if match["score"] >= good:
                    break
            if best_match["score"] >= good:
                break
        if best_match["score"] >= good:
            break
    m = best_match
    if m["score"] < max(3.0, 0.5 * min_found_fraction * len(labels)):
        raise FacetNotFoundError(f"no heliostat found near pixels {where} of the photo (within {margin:.0f} px): "
                                 f"nothing there looks like its {len(labels)} facets (is the camera pointed at it; "
                                 "is it in the photo; are its position, design and the camera's intrinsics right?)")
    # 4.-5. each facet's edges, from its outline where the layout's map puts it: the colour gradient
    gray = _distance(colours, m["colour"])
    threshold = m["threshold"]
    # the smoothing: a Gaussian of SMOOTHING_PX, narrower where the gaps are narrow (a gap's two edges, each
    # blurred, pull each other's derivative peak towards the gap's middle once the gap is under about 2.5
    # of their widths: a 4 px gap with 1 px smoothing and 1 px blur moves the edges by about 0.1 px)
    smoothing = float(np.clip(_gap_px(pred) / 6.0, 0.5, SMOOTHING_PX))
    gx, gy, noise = _gradients(colours, roi, smoothing)
    # which facets share a region (at the lightest opening): merged unless an edge between them is found
    binary = (gray < threshold).astype(np.uint8)
    _, lab_full = cv2.connectedComponents(cv2.morphologyEx(binary, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)),
                                          connectivity=4)
    hom = m["homography"]
    owners: dict = {}
    for label in labels:
        c = np.round(_homography(hom, pred[label].mean(axis=0)[None])[0]).astype(int)
        if 0 <= c[0] < w and 0 <= c[1] < h and lab_full[c[1], c[0]] > 0:
            owners.setdefault(int(lab_full[c[1], c[0]]), []).append(label)
    shared = {lab: [x for x in members if x != lab] for members in owners.values() if len(members) > 1
              for lab in members}
    facets, left_out, sat_of = {}, {}, {}
    sat_pixels = total_pixels = 0

    def fit(label, rough, half_width):
        others = shared.get(label)
        try:
            found = _fit_facet(label, gx, gy, rough, noise, camera, sat_of.get(label, 0.0), half_width)
        except FacetNotFoundError as exc:
            left_out[label] = (f"merged with {', '.join(others)} (no gap seen)" if others else str(exc))
            return
        facets[label] = found
        left_out.pop(label, None)

    for label in labels:
        rough = _homography(hom, pred[label])
        margin = SEARCH_HALF_WIDTH_PX + 3.0 * SMOOTHING_PX + 2.0     # the edge search and its smoothing
        if np.any(rough < margin) or np.any(rough[:, 0] > w - 1 - margin) or np.any(rough[:, 1] > h - 1 - margin):
            left_out[label] = "cut off by the photo's edge"
            continue
        inside = np.zeros((h, w), dtype=np.uint8)
        cv2.fillPoly(inside, [np.round(rough * 16).astype(np.int32)], 1, shift=4)
        vals = colours[inside.astype(bool)].max(axis=-1)
        sat = sat_of[label] = float(np.mean(vals >= top)) if vals.size else 0.0
        sat_pixels += int(np.sum(vals >= top))
        total_pixels += int(vals.size)
        if sat > SATURATED_FACET_SHARE:
            left_out[label] = f"overexposed ({100 * sat:.0f} % of its pixels at the sensor's top level)"
            continue
        fit(label, rough, SEARCH_HALF_WIDTH_PX)
    # The layout's homography again, from the corners found (a planar layout's corners to within its canting's
    # millimetres): a facet whose corners stray from it by more than LAYOUT_TOLERANCE_PX was misled by something
    # beside it and is fitted again, narrower, from where it puts it.
    if len(facets) >= 2:
        src = np.vstack([pred[k] for k in facets])
        dst = np.vstack([facets[k].corners_px for k in facets])
        hom2, _ = cv2.findHomography(src, dst, cv2.RANSAC, 1.0)
        if hom2 is not None:
            for label in labels:
                if label in left_out and not left_out[label].startswith(("merged", "its edges", "the edges")):
                    continue
                guess = _homography(hom2, pred[label])
                if label in facets and np.max(np.hypot(*(facets[label].corners_px - guess).T)) <= REFIT_PX:
                    continue
                facets.pop(label, None)
                fit(label, guess, SECOND_HALF_WIDTH_PX)
                if label in facets and np.max(np.hypot(*(facets[label].corners_px - guess).T)) > LAYOUT_TOLERANCE_PX:
                    del facets[label]
                    left_out[label] = (f"its corners stray from the heliostat's layout by more than "
                                       f"{LAYOUT_TOLERANCE_PX:g} px (an edge of something beside it taken?)")
    saturated = sat_pixels / max(total_pixels, 1)
    over = [k for k, v in left_out.items() if v.startswith("overexposed")]
    if len(facets) < max(3, min_found_fraction * len(labels)):
        if len(over) >= 0.5 * len(labels):
            raise CaptureError(f"the photo is overexposed: {len(over)} of the heliostat's {len(labels)} facets have "
                               f"more than {100 * SATURATED_FACET_SHARE:.0f} % of their pixels at the sensor's top "
                               "level (the sun's reflection?); take it again with a shorter exposure or when the "
                               "facets do not mirror the sun towards the camera")
        merged = sorted(k for k, v in left_out.items() if v.startswith("merged"))
        gap = _gap_px(pred)
        if gap < MIN_GAP_PX:
            raise FacetNotFoundError(f"facets merged: the gaps between the heliostat's facets are about {gap:.1f} px "
                                     f"in the photo, too narrow to part them (only {len(facets)} of {len(labels)} "
                                     "found): the heliostat is too small in the photo; zoom in")
        if merged and len(merged) >= 0.5 * (len(labels) - len(facets)):
            named = ", ".join(merged[:6]) + ("..." if len(merged) > 6 else "")
            raise FacetNotFoundError(f"facets merged: {len(merged)} of the heliostat's {len(labels)} facets show no "
                                     f"gap to their neighbours ({named}): the heliostat is too small in the photo, "
                                     "or blurred; zoom in or focus")
        reasons = "; ".join(f"{k}: {v}" for k, v in list(left_out.items())[:6])
        raise FacetNotFoundError(f"only {len(facets)} of the heliostat's {len(labels)} facets found ({reasons}): too "
                                 "few to measure it")
    mid = centres.mean(axis=0)
    moved = _homography(hom, mid[None])[0]
    scale = math.sqrt(abs(np.linalg.det(_jacobian(hom, mid))))
    return Detection(facets={k: facets[k] for k in labels if k in facets},
                     left_out={k: left_out[k] for k in labels if k in left_out},
                     facet_colour=tuple(float(v) for v in m["colour"]), shift_px=moved - mid, scale=float(scale),
                     threshold=float(threshold), saturated_fraction=float(saturated),
                     placed_px={k: _homography(hom, pred[k]) for k in labels})


def _gap_px(pred: dict) -> float:
    """The gaps between the facets in the predicted picture: the median, over the facets, of the distance from
    a corner to the nearest corner of another facet (the gap's diagonal at a shared corner), pixels."""
    labels = list(pred)
    if len(labels) < 2:
        return math.inf
    pts = np.vstack([pred[k] for k in labels])
    owner = np.repeat(np.arange(len(labels)), [len(pred[k]) for k in labels])
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    d[owner[:, None] == owner[None, :]] = np.inf
    return float(np.median(d.min(axis=1)) / math.sqrt(2.0))


def _jacobian(hom: np.ndarray, p: np.ndarray) -> np.ndarray:
    """d(homography(p)) / dp, (2, 2)."""
    e = 1e-3
    cols = []
    for step in ([e, 0.0], [0.0, e]):
        cols.append((_homography(hom, (p + step)[None])[0] - _homography(hom, (p - step)[None])[0]) / (2 * e))
    return np.column_stack(cols)


def _match(lab, stats, cents, centres, areas, offset) -> dict:
    """Where the layout lies among the regions (module docstring, step 3): the shift that puts most predicted
    centres on region centroids, then a homography (an affine map with fewer than 4 pairs) from the
    predicted centres to the centroids they met, in the photo's pixels."""
    n_comp = stats.shape[0]
    idx = np.arange(1, n_comp)
    comp_area = stats[idx, cv2.CC_STAT_AREA]
    big = idx[(comp_area > 0.3 * np.median(areas)) & (comp_area < 2.5 * np.max(areas))]
    off = np.asarray(offset, dtype=np.float64)
    if big.size == 0:
        return {"score": 0.0, "homography": np.eye(3)}
    pitch = math.sqrt(float(np.median(areas)))
    pts = cents[big]
    tree = cKDTree(pts)

    def score(mapped):
        d, _ = tree.query(mapped)
        return float(np.sum(np.clip(1.0 - d / (0.3 * pitch), 0.0, None)))

    extent = float(np.max(np.ptp(centres, axis=0))) + pitch
    shifts = (pts[:, None, :] - centres[None, :, :]).reshape(-1, 2)
    d, _ = tree.query((centres[None, :, :] + shifts[:, None, :]).reshape(-1, 2))
    votes = np.clip(1.0 - d.reshape(len(shifts), -1) / (0.3 * pitch), 0.0, None).sum(axis=1)
    votes -= np.hypot(shifts[:, 0], shifts[:, 1]) / (50.0 * extent)      # the nearer of equal shifts
    best_t = shifts[int(np.argmax(votes))]
    aff = np.hstack([np.eye(2), best_t[:, None]])
    for _ in range(3):                           # an affine map from the pairs it gives
        d, j = tree.query(_apply(aff, centres))
        ok = d < 0.3 * pitch
        if ok.sum() < 3:
            break
        aff = _affine(centres[ok], pts[j[ok]])
    hom = np.vstack([aff, [0.0, 0.0, 1.0]])
    d, j = tree.query(_apply(aff, centres))
    ok = d < 0.3 * pitch
    if ok.sum() >= 5:
        got, _ = cv2.findHomography(centres[ok], pts[j[ok]], cv2.RANSAC, 0.1 * pitch)
        if got is not None:
            hom = got
            d, j = tree.query(_homography(hom, centres))
            ok = d < 0.3 * pitch
    # each region counts once, for the facet nearest its centroid
    used = len(set(j[ok].tolist()))
    s = min(score(_homography(hom, centres)), float(used))
    # the map in the photo's pixels (it was found in the search window's)
    return {"score": s, "homography": _shift(off) @ hom @ _shift(-off)}


def _shift(t) -> np.ndarray:
    return np.array([[1.0, 0.0, t[0]], [0.0, 1.0, t[1]], [0.0, 0.0, 1.0]])


def _order_like(rough: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """The rough corners in the order (and turning sense) of the predicted ones."""
    n = len(predicted)
    best, best_d = rough, math.inf
    for seq in (rough, rough[::-1]):
        for k in range(n):
            cand = np.roll(seq, -k, axis=0)
            d = float(np.sum(np.hypot(*(cand - predicted).T)))
            if d < best_d:
                best, best_d = cand, d
    return best


def _sample(planes: list, pts: np.ndarray) -> np.ndarray:
    """Bilinear samples of each (H, W) array of *planes* at (..., 2) pixel positions: (..., C)."""
    shape = pts.shape[:-1]
    p = pts.reshape(-1, 2).astype(np.float32)
    out = [cv2.remap(plane, p[:, 0].reshape(-1, 1), p[:, 1].reshape(-1, 1), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).reshape(shape) for plane in planes]
    return np.stack(out, axis=-1)


def _edge_points(gx, gy, p0, p1, inward, noise, half_width=SEARCH_HALF_WIDTH_PX) -> np.ndarray:
    """Sub-pixel edge points (M, 2) along the rough side p0 -> p1 (module docstring, step 4): across the side,
    the peak of the derivative's size nearest the rough line (either sign: a facet beside a brighter
    neighbour's has its edge all the same; a narrow gap's far edge is the farther peak)."""
    d = p1 - p0
    length = float(np.hypot(*d))
    t = d / length
    n_out = -inward
    s = np.arange(END_TRIM_PX, length - END_TRIM_PX + 1e-9, 1.0)
    if s.size < MIN_EDGE_POINTS:
        return np.empty((0, 2))
    o = np.arange(-half_width, half_width + 1e-9, ACROSS_STEP_PX)
    pts = p0 + s[:, None, None] * t + o[None, :, None] * n_out
    # the colour gradient's size along the normal: for a pixel mixing two colours f and b by a fraction a, each
    # channel's derivative is (f - b) da/dn, so the size is |f - b| |da/dn|: it peaks where a does, whatever
    # the two colours
    prof = np.sqrt(np.sum((_sample(gx, pts) * n_out[0] + _sample(gy, pts) * n_out[1]) ** 2, axis=-1))
    inner = prof[:, 1:-1]
    is_peak = (inner >= prof[:, :-2]) & (inner > prof[:, 2:]) & (inner > MIN_PEAK_SIGMAS * noise)
    dist = np.where(is_peak, np.abs(o[1:-1])[None, :], np.inf)
    k = np.argmin(dist, axis=1) + 1
    ok = np.isfinite(dist.min(axis=1))
    if ok.sum() < MIN_EDGE_POINTS:
        return np.empty((0, 2))
    rows = np.flatnonzero(ok)
    a, b, c = prof[rows, k[rows] - 1], prof[rows, k[rows]], prof[rows, k[rows] + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        la, lb, lc = np.log(np.maximum(a, 1e-12)), np.log(b), np.log(np.maximum(c, 1e-12))
        gauss = 0.5 * (la - lc) / (la - 2 * lb + lc)
        para = 0.5 * (a - c) / (a - 2 * b + c)
    frac = np.where((a > 0) & (c > 0) & np.isfinite(gauss), gauss, para)
    frac = np.clip(np.nan_to_num(frac), -0.5, 0.5)
    offset = o[k[rows]] + frac * ACROSS_STEP_PX
    return p0 + s[rows, None] * t + offset[:, None] * n_out


def _undistort(camera: CameraIntrinsics, pts: np.ndarray) -> np.ndarray:
    if not np.any(camera.distortion):
        return np.asarray(pts, dtype=np.float64)
    out = cv2.undistortPoints(np.asarray(pts, np.float64).reshape(-1, 1, 2), camera.matrix, camera.distortion,
                              P=camera.matrix)
    return out.reshape(-1, 2)


def distort(camera: CameraIntrinsics, ideal_px: np.ndarray) -> np.ndarray:
    """Photo pixels of ideal (undistorted) pixels: the lens's distortion applied."""
    ideal_px = np.asarray(ideal_px, dtype=np.float64).reshape(-1, 2)
    if not np.any(camera.distortion):
        return ideal_px.copy()
    k = camera.matrix
    xy = np.column_stack([(ideal_px[:, 0] - k[0, 2]) / k[0, 0], (ideal_px[:, 1] - k[1, 2]) / k[1, 1],
                          np.ones(len(ideal_px))])
    out, _ = cv2.projectPoints(xy, np.zeros(3), np.zeros(3), k, camera.distortion)
    return out.reshape(-1, 2)


def _fit_line(pts: np.ndarray) -> tuple:
    """Total-least-squares line through *pts* with outliers dropped: (centroid, unit normal, rms, count,
    var(offset), var(angle))."""
    keep = np.ones(len(pts), dtype=bool)
    for _ in range(4):
        m = pts[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(pts[keep] - m, full_matrices=False)
        t, n = vt[0], vt[1]
        res = (pts - m) @ n
        sigma = 1.4826 * float(np.median(np.abs(res[keep]))) + 1e-4
        new = np.abs(res) < max(3.5 * sigma, 0.05)
        if new.sum() < MIN_EDGE_POINTS or np.array_equal(new, keep):
            break
        keep = new
    r = res[keep]
    s = (pts[keep] - m) @ t
    order = np.argsort(s)
    r_sorted = r[order]
    rho = 0.0
    if len(r_sorted) > 3 and np.var(r_sorted) > 0:
        rho = float(np.clip(np.corrcoef(r_sorted[:-1], r_sorted[1:])[0, 1], 0.0, 0.95))
    inflation = (1.0 + rho) / (1.0 - rho)
    var_r = float(np.mean(r ** 2)) * len(r) / max(len(r) - 2, 1) * inflation
    return m, n, float(np.sqrt(np.mean(r ** 2))), int(keep.sum()), var_r / len(r), var_r / float(np.sum(s ** 2))


def _intersect(l1, l2) -> np.ndarray:
    (m1, n1), (m2, n2) = l1, l2
    a = np.array([n1, n2])
    if abs(np.linalg.det(a)) < 1e-6:
        raise FacetNotFoundError("two neighbouring sides of its outline are parallel")
    return np.linalg.solve(a, [n1 @ m1, n2 @ m2])


def _homography(hom: np.ndarray, pts: np.ndarray) -> np.ndarray:
    p = np.column_stack([pts, np.ones(len(pts))]) @ hom.T
    return p[:, :2] / p[:, 2:3]


def _fit_facet(label, gx, gy, rough, noise, camera, sat, half_width) -> FacetFound:
    n = len(rough)
    centre = rough.mean(axis=0)
    lines, rms, counts, variances = [], [], [], []
    for i in range(n):
        p0, p1 = rough[i], rough[(i + 1) % n]
        mid = 0.5 * (p0 + p1)
        t = (p1 - p0) / np.hypot(*(p1 - p0))
        normal = np.array([-t[1], t[0]])
        inward = normal if normal @ (centre - mid) > 0 else -normal
        pts = _edge_points(gx, gy, p0, p1, inward, noise, half_width)
        if len(pts) < MIN_EDGE_POINTS:
            raise FacetNotFoundError(f"the edges of side {i + 1} were not found (too little contrast, or hidden)")
        expected = max(float(np.hypot(*(p1 - p0))) - 2.0 * END_TRIM_PX, 1.0)
        if len(pts) < MIN_SIDE_SHARE * expected:
            share = 100 * len(pts) / expected
            raise FacetNotFoundError(f"partly hidden (side {i + 1}: {share:.0f} % of its edge seen)")
        m, nn, r, c, v_off, v_ang = _fit_line(_undistort(camera, pts))
        lines.append((m, nn))
        rms.append(r)
        counts.append(c)
        variances.append((v_off, v_ang))
    corners = np.array([_intersect(lines[i - 1], lines[i]) for i in range(n)])
    # covariance: each line's offset and angle about its centroid, carried to its corners by differences
    cov = np.eye(2 * n) * CORNER_MODEL_PX ** 2
    for i in range(n):
        m, nn = lines[i]
        for which, var in ((0, variances[i][0]), (1, variances[i][1])):
            h = 1e-4
            if which == 0:
                moved = (m + h * nn, nn)
            else:
                c, s = math.cos(h), math.sin(h)
                moved = (m, np.array([c * nn[0] - s * nn[1], s * nn[0] + c * nn[1]]))
            trial = list(lines)
            trial[i] = moved
            jac = np.zeros(2 * n)
            for k in (i, (i + 1) % n):          # the corners of side i: corner i and corner i + 1
                jac[2 * k:2 * k + 2] = (_intersect(trial[k - 1], trial[k]) - corners[k]) / h
            cov += var * np.outer(jac, jac)
    return FacetFound(label=label, corners_px=distort(camera, corners), ideal_px=corners, cov_px2=cov,
                      edge_rms_px=np.array(rms), n_edge_points=np.array(counts), saturated_share=sat)
