"""Does a rim declared dark show the screen? The fringes' answer, side by side of the facet's outline.

A facet design may declare its glass rim dark (``FacetDesign.edge_rim_dark``: a ground seam, a steep
bevel): the edge found in the white - dark image is then the rim's inner edge, and the outline is put the
rim's width outside it (:func:`~sofast_station.measure.corners.fit_outline`). Were the rim lit after all,
that places the side up to the rim's width too far out, and the white - dark image cannot tell (a dark rim
of width w beside an edge at x looks like a lit rim's edge at x + w). The fringes can: a lit rim reflects
another part of the screen, so the screen position decoded in the pixel on the found edge jumps away from
where the mirror's pixels just inside it point; beside a dark rim that pixel sees mirror (and the dark
rim, which adds no fringe), so it continues their trend.

Per side, in the middle 80 % of its length, each step along the found edge compares the decoded screen
position of the pixel on the edge with the straight line through the pixels 2 and 4 px inside it (the
*edge residual*), and the pixel 2 px inside with the line through those 4 and 6 px inside (the *inner
residual*: the capture's own noise and the position field's curvature, no rim in it), both along the way
the screen position moves across the side (a rim turned outward moves its reflection that way; along the
side, a partly covered pixel's position may lean by a fraction of a pixel's worth without any rim). A lit
rim moves every edge pixel's position the same way, so the side's mean edge residual less its mean inner
residual, the *jump*, grows with the rim's share of the pixel and its tilt, while the noise averages out
over the side's hundreds of steps. The means are trimmed (:data:`TRIM` cut at either end: a
mostly-background edge pixel has little modulation, and now and then a whole fringe's error); steps whose
inner pixels are dim (under :data:`FULL_LIGHT` of the facet's median: the facet reflects the screen's
border there) are left out. The rim is lit when the jump is larger than both :data:`LIT_JUMP_SCATTER`
times the inner residuals' median size (the pixel-to-pixel scatter) and :data:`LIT_JUMP_SIGMAS` times its
own standard error.

Pure numpy: the outline, the pixels' flat indices and their decoded positions in, side numbers out.
"""

from __future__ import annotations

import numpy as np

from .corners import OutlineFit, side_number

#: A side's rim is lit when its jump exceeds this many times the median inner residual (chosen on the
#: population's bevelled stations, seeds 5, 6 and 8 as drawn (dark), 7 and 9 with the rims turned only
#: 3-50 mrad: no side of the 363 a dark placement puts within 0.05 px flagged, 228 of the 295 it puts more
#: than 0.1 px wrong flagged; on seeds 10-12, one side of 203 and 95 of 120; docs/uncertainty.md, "Corners")
LIT_JUMP_SCATTER = 2.0
#: ... and this many times its own standard error.
LIT_JUMP_SIGMAS = 5.0
#: A step along a side is used where the pixels 2 and 6 px inside its edge are lit (white - dark) at least
#: this fraction of the facet's median: dimmer, the edge reflects the screen's border (the twin's strongest
#: vignetting leaves 0.4 at the image's corners).
FULL_LIGHT = 0.5
#: Fraction of a side's residuals cut at either end before they are averaged.
TRIM = 0.2
#: Depths inside the found edge, pixels, at which each step along a side samples the positions.
SAMPLE_DEPTHS_PX = (0.0, 2.0, 4.0, 6.0)
#: Fewest steps along a side with all four samples decoded for the side to be judged.
MIN_SAMPLES = 20


def rim_jumps(outline: OutlineFit, found_shift_px: np.ndarray, shape: tuple[int, int], idx: np.ndarray,
              positions_m: np.ndarray, contrast: np.ndarray | None = None) -> np.ndarray:
    """Each side's jump, its standard error and its inner residuals' median length, metres on the screen:
    (n_sides, 3), NaN where fewer than :data:`MIN_SAMPLES` steps had all four samples decoded.

    Parameters
    ----------
    outline : OutlineFit
        The fitted outline (its ``sides`` as placed, i.e. a known-dark rim's width outside the found edge).
    found_shift_px : (n_sides,) array
        How far outside the found edge each side was placed, pixels (the rim's width; 0 for none).
    shape : (rows, columns)
        The image's shape.
    idx : (M,) int array
        Sorted flat indices of the pixels with decoded positions (the facet region).
    positions_m : (2, M) array
        Their decoded screen positions (x, y), metres; NaN where not decoded.
    contrast : (rows, columns) array or None
        White - dark, DN. Given, a step is used only where the pixels 2 and 6 px inside the edge are lit at
        least :data:`FULL_LIGHT` times the facet's median: where the facet reflects the screen's own border,
        its pixels see part of the screen and part of its frame, dimly, and their positions bend towards the
        screen's inside without any rim.
    """
    rows_n, cols_n = shape
    corners = np.asarray(outline.corners_px, float)
    centroid = corners.mean(axis=0)
    n = len(outline.sides)
    out = np.full((n, 3), np.nan)
    bright = FULL_LIGHT * float(np.median(contrast.ravel()[idx])) if contrast is not None and idx.size else 0.0
    for i, curve in enumerate(np.asarray(outline.sides, float)):
        o, t = curve[:2], curve[2:4]
        normal = np.array([-t[1], t[0]])
        a, b, c = curve[4:]
        s0, s1 = sorted(((corners[i] - o) @ t, (corners[(i + 1) % n] - o) @ t))
        margin = 0.1 * (s1 - s0)
        s = np.arange(s0 + margin, s1 - margin)
        if s.size < MIN_SAMPLES:
            continue
        inward = 1.0 if normal @ (centroid - (o + 0.5 * (s0 + s1) * t)) > 0 else -1.0
        shift = float(found_shift_px[i])
        found = o + s[:, None] * t + ((a + b * s + c * s * s) + inward * shift)[:, None] * normal
        pos, depth, light = [], [], []
        for d in SAMPLE_DEPTHS_PX:
            px = np.rint(found + inward * d * normal)
            col, row = px[:, 0].astype(np.int64), px[:, 1].astype(np.int64)
            inside = (col >= 0) & (col < cols_n) & (row >= 0) & (row < rows_n)
            flat = np.where(inside, row * cols_n + col, -1)
            k = np.clip(np.searchsorted(idx, flat), 0, max(idx.size - 1, 0))
            hit = inside & (idx[k] == flat) if idx.size else np.zeros(inside.shape, bool)
            pos.append(np.where(hit[None, :], positions_m[:, k] if idx.size else np.nan, np.nan))
            if contrast is not None:
                light.append(np.where(inside, contrast[np.clip(row, 0, rows_n - 1), np.clip(col, 0, cols_n - 1)],
                                      np.nan))
            # the pixel centre's own depth inside the found edge (rounding moved it by up to half a pixel)
            rel = px - o
            sc = rel @ t
            depth.append(inward * (rel @ normal - (a + b * sc + c * sc * sc)) - shift)
        edge = _residual(pos[0], depth[0], pos[1], depth[1], pos[2], depth[2])
        inner = _residual(pos[1], depth[1], pos[2], depth[2], pos[3], depth[3])
        good = np.all(np.isfinite(edge), axis=0) & np.all(np.isfinite(inner), axis=0)
        if contrast is not None:
            with np.errstate(invalid="ignore"):
                good &= (light[1] >= bright) & (light[3] >= bright)
        k = int(np.count_nonzero(good))
        if k < MIN_SAMPLES:
            continue
        # Only the residuals' part along the way the screen position moves across the side counts: a rim
        # turned outward moves its reflection that way; along the side, a partly covered pixel's position
        # may lean by a fraction of a pixel's worth (the screen's own border, the lens) without any rim.
        across = np.median(pos[1][:, good] - pos[2][:, good], axis=1)
        norm = np.hypot(*across)
        if not norm > 0:
            continue
        across = across / norm
        edge, inner = across @ edge[:, good], across @ inner[:, good]
        # trimmed means, not means: an edge pixel that is mostly background has little modulation, and now
        # and then a whole fringe's error
        (mid_e, se_e), (mid_i, se_i) = _trimmed_mean(edge), _trimmed_mean(inner)
        out[i] = abs(mid_e - mid_i), float(np.hypot(se_e, se_i)), float(np.median(np.abs(inner)))
    return out


def _trimmed_mean(values: np.ndarray, trim: float = TRIM) -> tuple[float, float]:
    """The mean of *values* (1-D) with the *trim* fraction cut at either end, and that mean's standard error
    (the winsorised variance over (1 - 2 trim)^2 K, Tukey and McLaughlin)."""
    v = np.sort(values)
    k = v.size
    g = int(trim * k)
    kept = v[g:k - g]
    wins = np.clip(v, kept[0], kept[-1])
    return float(kept.mean()), float(np.sqrt(wins.var(ddof=1) / ((1.0 - 2.0 * g / k) ** 2 * k)))


def _residual(p0, d0, p1, d1, p2, d2) -> np.ndarray:
    """p0 less the line through (d1, p1), (d2, p2) at d0: how far the first sample leaves the trend of the
    next two (positions (2, K) metres, depths (K,) pixels), (2, K); NaN where a sample is missing."""
    span = np.where(d2 - d1 == 0, np.nan, d2 - d1)
    return p0 - (p1 + (p2 - p1) * ((d0 - d1) / span)[None, :])


def lit_rim_flags(jumps: np.ndarray) -> np.ndarray:
    """(n_sides,) bool: which sides' jump (:func:`rim_jumps`) exceeds both :data:`LIT_JUMP_SCATTER` times
    their inner scatter and :data:`LIT_JUMP_SIGMAS` times its standard error (False where not judged)."""
    jump, se, scatter = np.asarray(jumps, float).T
    with np.errstate(invalid="ignore"):
        return np.isfinite(jump) & (jump > LIT_JUMP_SCATTER * scatter) & (jump > LIT_JUMP_SIGMAS * se)


def lit_rim_sides(jumps: np.ndarray, design_sides: np.ndarray | None) -> list[int]:
    """The sides (the design's numbering from 1, else the outline's) that :func:`lit_rim_flags` flags: a
    rim declared dark that shows the screen."""
    return sorted(side_number(design_sides, i) for i in np.flatnonzero(lit_rim_flags(jumps)))
