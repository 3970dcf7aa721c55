"""Checks that turn bad captures into clear errors instead of silent wrong answers.

Each check names what is wrong and what to do. They run inside :func:`~sofast_station.measure.analysis.analyse`
at the point where the quantity they need exists.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import CaptureError, DisplayNotShowingError, FacetNotFoundError
from ..fringes import FringeSet
from .stats import median, quantile


def check_frames(frames: np.ndarray, fringes: FringeSet, shape: tuple[int, int]) -> None:
    """Raise :class:`CaptureError` unless *frames* is a (n_frames, rows, columns) integer stack."""
    if not isinstance(frames, np.ndarray):
        raise CaptureError(f"frames must be a numpy array, got {type(frames).__name__}")
    if frames.ndim != 3 or frames.shape[0] != fringes.n_frames:
        raise CaptureError(f"expected {fringes.n_frames} frames (dark, white, then {fringes.n_frames - 2} "
                           f"fringe frames) of {shape[1]} x {shape[0]} pixels, got an array of shape "
                           f"{frames.shape}; capture the whole sequence")
    if frames.shape[1:] != shape:
        raise CaptureError(f"frames are {frames.shape[2]} x {frames.shape[1]} pixels but the camera "
                           f"calibration is for {shape[1]} x {shape[0]}; use the calibration of this camera")
    if not np.issubdtype(frames.dtype, np.integer):
        raise CaptureError(f"frames must hold integer camera counts, got dtype {frames.dtype}")


def _saturating(white: np.ndarray, dark: np.ndarray, threshold_dn: float) -> bool:
    """Whether ``cv2.subtract(white, dark)`` (white - dark clipped at zero) decides ``white - dark >
    threshold_dn`` as the true difference does: unsigned 8- or 16-bit counts of one shape, threshold >= 0."""
    return (white.dtype == dark.dtype and white.dtype in (np.uint8, np.uint16) and white.shape == dark.shape
            and threshold_dn >= 0)


def check_response(dark: np.ndarray, white: np.ndarray, threshold_dn: float) -> None:
    """Something must respond to the screen: tell a dark scene from a display that shows nothing."""
    top = np.iinfo(white.dtype).max if np.issubdtype(white.dtype, np.integer) else None
    if top is not None:
        # A capture far too bright clips dark and white alike at the top count: they then look equal.
        clipped = white >= top
        n_clipped = int(np.count_nonzero(clipped))
        if n_clipped >= 50 and float(np.mean(dark[clipped] >= top)) > 0.5:
            raise CaptureError(
                f"the capture is saturated: {n_clipped} pixels are at the top count {top} DN in the white frame "
                f"and {100 * float(np.mean(dark[clipped] >= top)):.0f} % of them in the dark frame too, so the "
                "screen's light cannot be seen; lower the exposure or gain (rerun calibrate radiometric) or dim "
                "the room light")
    brightest = int(white.max())
    if brightest <= threshold_dn:
        raise FacetNotFoundError(
            f"the white frame is dark everywhere (brightest pixel {brightest} DN): no facet in view, the lens "
            "is covered or there is no light; put a facet in the fixture and check the camera")
    # The largest white - dark: from the difference clipped at zero when that exceeds the (non-negative)
    # threshold, as it does in every capture that shows something (one pass, no wider copies).
    if _saturating(white, dark, threshold_dn) and int(cv2.subtract(white, dark).max()) > threshold_dn:
        return
    diff = white.astype(np.int32) - dark.astype(np.int32)
    if int(diff.max()) <= threshold_dn:
        raise DisplayNotShowingError(
            f"the white frame equals the dark frame (largest difference {int(diff.max())} DN, threshold "
            f"{threshold_dn:g} DN): the display is not showing the patterns (off, unplugged or the wrong "
            "monitor), or nothing in view reflects it")


def check_region(region: np.ndarray, expected_area_px: float, min_area_fraction: float = 0.5) -> None:
    """The facet region must be whole: not cut off at the image border, not much smaller than expected."""
    area = int(np.count_nonzero(region))      # (region.sum()'s count, without widening every pixel first)
    # Cut off first: a facet partly out of view is also smaller than expected, but that is not the cause.
    h, w = region.shape
    sides = {"top": region[0].any(), "bottom": region[h - 1].any(), "left": region[:, 0].any(),
             "right": region[:, w - 1].any()}
    cut = [name for name, touches in sides.items() if touches]
    if cut:
        raise FacetNotFoundError(
            f"the facet is cut off at the image's {' and '.join(cut)} edge (out of view; {area} pixels seen of "
            f"about {expected_area_px:.0f}): it is misplaced in the fixture or the camera is aimed wrongly; the "
            "whole outline must be in view")
    if area < min_area_fraction * expected_area_px:
        raise FacetNotFoundError(
            f"the facet covers only {area} pixels where the design in the fixture should cover about "
            f"{expected_area_px:.0f}: the facet is too small in the image, partly hidden, not the recipe's "
            "facet type, or not in the fixture")


def check_saturation(stack: np.ndarray, max_fraction: float) -> None:
    """Too many facet pixels at the camera's top count make phases wrong: refuse the capture.

    *stack* holds the facet's pixels of every frame, (n_frames, n_pixels).
    """
    top = np.iinfo(stack.dtype).max
    for k in range(1, stack.shape[0]):     # the dark frame (0) cannot saturate meaningfully
        if stack[k].max() < top:           # a quick pass for the usual frame with nothing at the top
            continue
        frac = float(np.count_nonzero(stack[k] >= top)) / max(stack.shape[1], 1)
        if frac > max_fraction:
            what = "white frame" if k == 1 else f"fringe frame {k}"
            raise CaptureError(
                f"{100 * frac:.1f} % of the facet's pixels are saturated ({top} DN) in the {what}: lower the "
                "exposure or gain (rerun the radiometric calibration), or dim the room light")


def _masked_means(sample: np.ndarray, mask: np.ndarray, count: int) -> np.ndarray:
    """``sample[:, mask].mean(axis=1, dtype=np.float64)`` of integer counts, the same numbers: each row's
    sum over the mask by OpenCV (counts of up to 16 bits summed exactly, as numpy's float64 sum of
    integers is below 2^53) divided by the count, without gathering the masked values first."""
    if sample.dtype not in (np.uint8, np.uint16, np.int16) or sample.shape[1] * 65535 >= 2**53:
        return sample[:, mask].mean(axis=1, dtype=np.float64)
    m = mask.view(np.uint8).reshape(1, -1)
    sums = [cv2.sumElems(cv2.bitwise_and(row, row, mask=m))[0] for row in sample.reshape(sample.shape[0], 1, -1)]
    return np.array(sums, dtype=np.float64) / count


def check_order(frames: np.ndarray, fringes: FringeSet, threshold_dn: float) -> None:
    """The dark frame must be the darkest and the white frame the brightest of the sequence.

    Judged before anything else, so that swapped or shifted frames are reported as such rather than as a
    dark scene, on the pixels (every n-th row of them) whose value changes by more than *threshold_dn*
    over the sequence: room light drifting between frames moves every pixel a little and must not
    decide the order. When too few pixels respond there is no order to judge; :func:`check_response`
    reports that.
    """
    # The counts themselves (no float copy): the largest minus the smallest cannot wrap around. About
    # 200,000 pixels a frame: every n-th whole row of (n, rows, columns) frames, read contiguously (every
    # n-th pixel touched every cache line of every frame).
    if frames.ndim == 3:
        step = max(1, frames.shape[1] // max(1, 200_000 // frames.shape[2]))
        sample = np.ascontiguousarray(frames[:, ::step]).reshape(frames.shape[0], -1)
    else:
        flat = frames.reshape(frames.shape[0], -1)
        sample = np.ascontiguousarray(flat[:, :: max(1, flat.shape[1] // 200_000)])
    # A pixel that only sees noise also changes over 18 frames, by about 3.6 of its standard deviations
    # and now and then by 7: the bar is raised by 7 times the noise, taken from a four-step set's
    # consistency residual I0 + I2 - I1 - I3 (2 sigma of noise whatever the fringe), at its lower
    # quartile (0.637 of 2 sigma), which stays noise as long as a quarter of the image is still.
    sigma = 0.0
    if fringes.phase_steps == 4:
        k = fringes.slices()["x"][0].start
        residual = (sample[k].astype(np.int32) + sample[k + 2]) - (sample[k + 1].astype(np.int32) + sample[k + 3])
        sigma = quantile(np.abs(residual), 0.25) / (2.0 * 0.637)
    responsive = (sample.max(axis=0) - sample.min(axis=0)) > threshold_dn + 7.0 * sigma
    n_responsive = int(np.count_nonzero(responsive))
    if n_responsive < 50:
        return
    means = _masked_means(sample, responsive, n_responsive)
    # Room light that outshines the display drowns the sequence: frame levels then follow the light's
    # flicker and drift, not the patterns, and would look like frames out of order.
    # The swing between frames includes the room light's own changes, so the bar is half of it: room
    # light giving a third of the brightest frame (the display then at most two thirds) is refused.
    black = quantile(sample, 0.01)      # np.percentile(sample, 1), by counting (integer counts)
    level, swing = float(means.min()) - black, float(means.max() - means.min())
    top = np.iinfo(sample.dtype).max if np.issubdtype(sample.dtype, np.integer) else None
    if level > 0.5 * swing and top is not None:
        # An over-exposed capture clips the white frame at the top count, which shrinks the swing and
        # would read as room light drowning the display. The dark frame tells them apart: over-exposure
        # leaves it below the top (the display's black and the room light, scaled up with everything),
        # where room light that fills the range clips it too (check_response names that saturation).
        white, dark = sample[1][responsive], sample[0][responsive]
        clipped = white >= top
        n_clipped = int(np.count_nonzero(clipped))
        if n_clipped > 0.1 * white.size and np.count_nonzero(dark[clipped] >= top) <= 0.5 * n_clipped:
            dark_level = float(np.median(dark)) - black
            raise CaptureError(
                f"the capture is over-exposed: {100 * n_clipped / white.size:.0f} % of the responding pixels are "
                f"saturated (at the top count {top} DN) in the white frame, while the dark frame is below it "
                f"({dark_level:.0f} DN above the black level: the display's black and the room light, scaled up "
                "with everything else); lower the exposure or gain (rerun calibrate radiometric)")
    if level > 0.5 * swing and level > threshold_dn:
        raise CaptureError(
            f"too much ambient light, too little contrast: even the darkest frame is {level:.0f} DN above the "
            f"black level over the facet, where the display changes it by only {swing:.0f} DN; shade the "
            "station from room light or daylight (or switch it off) and retake")
    if swing <= threshold_dn:
        # Nothing in view follows the display (pixels picked by noise alone): no order to judge here;
        # check_response and the region's checks say what is missing.
        return
    labels = [p.label for p in fringes.patterns()]
    darkest, brightest = int(np.argmin(means)), int(np.argmax(means))
    tie = 0.02 * float(means.max() - means.min())      # a saturated white may tie with a fringe peak
    if means[0] > means[darkest] + tie or means[1] < means[brightest] - tie:
        raise CaptureError(
            f"the frames are out of order: the darkest is frame {darkest} ({labels[darkest]}) and the brightest "
            f"frame {brightest} ({labels[brightest]}), where the dark and white frames must come first; capture "
            "the sequence in the fringe definition's order (a display lagging by a frame also does this: "
            "lengthen the settle time)")


#: A frame that changed by little (median under 2 % of the contrast) repeats its predecessor when at most
#: this fraction of the facet's pixels changed by more than :data:`REPEAT_NOISE_SIGMAS` of the change's own
#: noise (its median absolute deviation, at least 1 DN): a repeated image differs by noise and a common
#: offset (room light, flicker) only.
REPEAT_CHANGED_FRACTION = 0.01
REPEAT_NOISE_SIGMAS = 4.0


def check_repeats(stack: np.ndarray, fringes: FringeSet) -> None:
    """No frame may repeat its predecessor over the facet (a stuck or lagging display).

    *stack*: (n_frames, n_facet_pixels). Consecutive displayed images differ over the facet by a good
    part of the white-minus-dark contrast (a quarter-period shift changes a pixel by about the fringe
    amplitude), a repeated one by the noise only: a frame whose median change is under 2 % of the contrast
    is a repeat unless part of the facet changed beyond the noise (:data:`REPEAT_CHANGED_FRACTION`). That
    part: a facet at its centre of curvature reflects a small patch of the screen, where two different
    patterns can show nearly one level (seed 24 of the population: a good capture of a dish refused, the
    median change 2 DN on 221 DN of contrast, but a twentieth of the facet changed by 12 DN and more). A
    real camera's consistency residuals hold more than noise (display nonlinearity, blur), so they do not
    set this bound.
    """
    sample = stack[:, :: max(1, stack.shape[1] // 20_000)].astype(np.float32)
    contrast = median(sample[1] - sample[0])
    labels = [p.label for p in fringes.patterns()]
    for k in range(1, stack.shape[0]):
        diff = sample[k] - sample[k - 1]
        change = median(np.abs(diff))
        if change >= 0.02 * contrast:
            continue
        centre = median(diff)
        sigma = max(1.4826 * median(np.abs(diff - centre)), 1.0)
        changed = np.count_nonzero(np.abs(diff - centre) > REPEAT_NOISE_SIGMAS * sigma) / diff.size
        if changed <= REPEAT_CHANGED_FRACTION:
            raise CaptureError(
                f"frame {k} ({labels[k]}) repeats frame {k - 1} ({labels[k - 1]}): median change {change:.1f} DN, "
                f"under 2 % of the {contrast:.0f} DN white-minus-dark contrast: the display is stuck or too slow "
                "for the capture; check the display and its settle time")


def check_phase_sets(inconsistent_fraction: dict, disagreement_fraction: dict, limit: float = 0.5) -> None:
    """Whole sets failing the four-step check, or coarse and fine phases disagreeing almost everywhere,
    mean frames shown out of order or not finished, not a poor facet."""
    for name, frac in inconsistent_fraction.items():
        if frac > limit:
            raise CaptureError(
                f"the {name} fringe set fails the check I0 + I2 = I1 + I3 at {100 * frac:.0f} % of the facet: a frame "
                "was captured before the display finished showing it, or the frames are out of order; "
                "lengthen the settle time or check the sequence")
    for axis, frac in disagreement_fraction.items():
        if frac > limit:
            raise CaptureError(
                f"coarse and fine {axis} phases disagree at {100 * frac:.0f} % of the facet: the fringe sets are "
                "out of order or the period list does not match the frames; check the fringe definition")


def projected_outline_mask(shape: tuple[int, int], outline_px: np.ndarray) -> np.ndarray:
    """Filled polygon of the outline's image points (column, row), as a bool mask."""
    mask = np.zeros(shape, dtype=np.uint8)
    pts = np.round(outline_px * 16).astype(np.int32).reshape(-1, 1, 2)
    cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=4)
    return mask.view(bool)                    # (0 and 1 are False and True: no copy of a frame-sized mask)


def outline_agreement(region: np.ndarray, outline_px: np.ndarray) -> float:
    """Intersection over union of the facet region and the design outline projected with the pose."""
    proj = projected_outline_mask(region.shape, outline_px)
    union = np.count_nonzero(region | proj)
    return float(np.count_nonzero(region & proj) / union) if union else 0.0


#: Rows (and columns) of which every n-th gives the pixel spacing in :func:`slope_curl`.
_SPACING_STRIDE = 4


def slope_curl(valid: np.ndarray, points_m: np.ndarray, slopes: np.ndarray, step_m: float = 0.01,
               stride: int | None = None, slope_cov=None, edge_px: int = 1) -> dict:
    """How far the measured slope field is from being a gradient: the local curl, against its noise.

    Slopes of a real surface are a gradient, s = grad z, so ds_x/dy = ds_y/dx everywhere. Fringe sets
    swapped between the axes (y captured before x) exchange and rescale the slope components: the field's
    local fluctuations (slope errors, dents) then turn as much as they stretch. With the pixel grid's
    centred differences over about *step_m* on the facet (long enough for the slope noise to average,
    short against the slope errors' structure) and the chain rule through the facet coordinates, the slope
    gradient G (1/m) is split into its antisymmetric part a = (G_xy - G_yx)/2 and the symmetric parts
    (G_xy + G_yx)/2 and (G_xx - G_yy)/2; each less its median over the facet (the facet's overall shape).

    The differences are taken at centre pixels on a lattice of every *stride*-th row and column (by
    default half the difference's half-baseline k, at least 1), not at every pixel: centres closer than
    the baseline 2k share most of their field (each difference spans 2k pixels of it), so the lattice
    samples the same field at a quarter of its baseline and the RMS values are those of every pixel within
    their sampling scatter, for 1/stride^2 of the work. The slope noise enters each centre through its own
    four pixels, uncorrelated between centres, so its share of each mean square is unbiased either way.
    ``stride=1`` takes every pixel.

    The valid pixels within *edge_px* of the valid region's border (its outline and any hole) are left
    out: a facet's outermost pixels see part facet, part background, or a bevelled rim that reflects the
    screen at another angle, and their few wild slopes would weigh in both parts alike (a 1.0 ratio on a
    good capture of a nearly flat facet with a bevelled edge).

    With *slope_cov*, the mean squares the slope noise alone would give each part are computed too, from
    every centre's four pixels' noise through the same differences (each pixel's noise is its own, so the
    variances add), so that the verdict can judge the parts against their noise and not against each other
    only: ``antisymmetric_noise_per_m`` and ``symmetric_noise_per_m`` (the RMS values a curl-free field of
    that noise gives), and ``antisymmetric_noise_ms_sd_per_m2``, the standard deviation of the
    antisymmetric mean square under the noise alone (each centre's square of a normal value of variance v
    has variance 2 v^2; centres on the lattice share pixels with up to four others, each a quarter of their
    variance, which the 1.25 factor on the variance of the sum allows for). :func:`curl_judgement` judges
    them.

    Parameters
    ----------
    valid : (H, W) bool array
        The pixels whose points and slopes are given, raster order.
    points_m : (3, N) array
        Surface points (facet frame), metres.
    slopes : (2, N) array
        Slopes dz/dx, dz/dy.
    step_m : float
        Half the difference baseline on the facet, metres.
    stride : int, optional
        Spacing of the centre pixels' lattice, pixels.
    edge_px : int
        Valid pixels this close to the valid region's border (4-neighbourhood steps) are not used, pixels.
    slope_cov : callable, optional
        ``slope_cov(indices) -> (var_x, var_y, cov_xy)``: each point's slope noise (slope units squared)
        at the given point indices (into the columns of *points_m*).

    Returns
    -------
    dict
        ``antisymmetric_rms_per_m``, ``symmetric_rms_per_m`` (both symmetric parts together, per
        component), ``step_px`` (k), ``stride_px`` and ``n`` (the centres used); with *slope_cov* also the
        noise figures above (1/m, and sigmas).
    """
    h, w = valid.shape
    rows, cols = np.flatnonzero(valid.any(axis=1)), np.flatnonzero(valid.any(axis=0))
    if rows.size == 0:
        return {"antisymmetric_rms_per_m": 0.0, "symmetric_rms_per_m": 0.0, "step_px": 1, "stride_px": 1, "n": 0}
    # Each valid pixel's place in the per-point arrays (-1 elsewhere), on the valid pixels' box.
    r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    sub = valid[r0:r1, c0:c1]
    kind = np.int32 if points_m.shape[1] < 2**31 else np.intp
    index = np.full(sub.shape, -1, dtype=kind)
    index[sub] = np.arange(points_m.shape[1], dtype=kind)
    if edge_px > 0:
        cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
        inner = cv2.erode(np.ascontiguousarray(sub, dtype=np.uint8), cross, iterations=int(edge_px),
                          borderType=cv2.BORDER_CONSTANT, borderValue=0)
        index[inner == 0] = -1

    def pairs(first, second):
        """The point indices of the pixel pairs (first, second) that are both valid."""
        both = first >= 0
        both &= second >= 0
        return first[both], second[both]

    # Neighbour distances of x along rows, then of y along columns: their median (the pixel's size on the
    # facet, which changes smoothly over the image) turns step_m into k. Every 4th row and column give it
    # to a few parts in 1e4, for a quarter of the work.
    x, y = points_m[0], points_m[1]
    e = _SPACING_STRIDE
    (a1, a2), (b1, b2) = pairs(index[::e, :-1], index[::e, 1:]), pairs(index[:-1, ::e], index[1:, ::e])
    spacing = np.concatenate([np.abs(x[a2] - x[a1]), np.abs(y[b2] - y[b1])])
    k = max(1, int(round(step_m / median(spacing)))) if spacing.size else 1
    m = max(1, k // 2) if stride is None else int(stride)
    if m < 1:
        raise ValueError(f"stride must be at least 1, got {stride}")
    if 4 * k >= min(h, w):
        return {"antisymmetric_rms_per_m": 0.0, "symmetric_rms_per_m": 0.0, "step_px": k, "stride_px": m, "n": 0}
    # Centres (r, c) whose four neighbours (r, c +- k), (r +- k, c) can all be valid: within k of the box
    # and k of the image's edges; every m-th of them from the first, in the box's coordinates (with a
    # margin of 2k, so that every neighbour's index is read from the padded index image).
    pad = 2 * k
    padded = np.full((sub.shape[0] + 2 * pad, sub.shape[1] + 2 * pad), -1, dtype=kind)
    padded[pad:pad + sub.shape[0], pad:pad + sub.shape[1]] = index
    first_r, last_r = max(r0 - k, k), min(r1 + k, h - k)       # image rows of the centres, [first, last)
    first_c, last_c = max(c0 - k, k), min(c1 + k, w - k)
    if first_r >= last_r or first_c >= last_c:
        return {"antisymmetric_rms_per_m": 0.0, "symmetric_rms_per_m": 0.0, "step_px": k, "stride_px": m, "n": 0}

    def at(dr, dc):
        """Point indices of the centres' neighbour (r + dr, c + dc), on the lattice."""
        rr, cc = first_r - r0 + pad + dr, first_c - c0 + pad + dc
        return padded[rr:rr + last_r - first_r:m, cc:cc + last_c - first_c:m]

    right, left, down, up = at(0, k), at(0, -k), at(k, 0), at(-k, 0)
    cells = right >= 0
    for nb in (left, down, up):
        cells &= nb >= 0
    right, left, down, up = right[cells], left[cells], down[cells], up[cells]
    sx, sy = slopes[0], slopes[1]

    def d_col(f):
        return f[right] - f[left]

    def d_row(f):
        return f[down] - f[up]

    # The same operations in the same order as det = xc yr - xr yc, (i00, i01, i10, i11) = (yr, -xr, -yc,
    # xc) / det, g01 = sc i01 + sr i11, g10 = tc i00 + tr i10, g00 = sc i00 + sr i10, g11 = tc i01 + tr i11,
    # formed in place.
    xc, xr, yc, yr = d_col(x), d_row(x), d_col(y), d_row(y)
    det = np.multiply(xc, yr)
    tmp = np.multiply(xr, yc)
    det -= tmp
    with np.errstate(invalid="ignore", divide="ignore"):
        i00 = np.divide(yr, det, out=yr)
        i01 = np.divide(np.negative(xr, out=xr), det, out=xr)
        i10 = np.divide(np.negative(yc, out=yc), det, out=yc)
        i11 = np.divide(xc, det, out=xc)
        noise = None if slope_cov is None else _curl_noise(slope_cov, right, left, down, up, i00, i01, i10, i11)
        sc, sr, tc, tr = d_col(sx), d_row(sx), d_col(sy), d_row(sy)
        g01 = np.multiply(sc, i01, out=det)
        g01 += np.multiply(sr, i11, out=tmp)
        g00 = np.multiply(sc, i00, out=sc)
        g00 += np.multiply(sr, i10, out=tmp)
        g10 = np.multiply(tc, i00, out=i00)
        g10 += np.multiply(tr, i10, out=tmp)
        g11 = np.multiply(tc, i01, out=tc)
        g11 += np.multiply(tr, i11, out=tmp)
    ok = np.isfinite(g00)
    for g in (g01, g10, g11):
        ok &= np.isfinite(g, out=np.empty_like(ok))
    if np.count_nonzero(ok) < 100:
        return {"antisymmetric_rms_per_m": 0.0, "symmetric_rms_per_m": 0.0, "step_px": k, "stride_px": m, "n": 0}

    def half(first, op, second):
        """0.5 (first op second) at the ok cells (the selection, then the halving: the same values)."""
        v = op(first, second, out=tmp)[ok]
        v *= 0.5
        return v

    a = half(g01, np.subtract, g10)
    s = half(g01, np.add, g10)
    d = half(g00, np.subtract, g11)

    def rms(v):
        v -= median(v)           # (v is this function's own array)
        return float(np.sqrt(np.mean(np.multiply(v, v, out=v))))

    out = {"antisymmetric_rms_per_m": rms(a), "symmetric_rms_per_m": float(np.hypot(rms(s), rms(d)) / np.sqrt(2.0)),
           "step_px": k, "stride_px": m, "n": int(np.count_nonzero(ok))}
    if noise is not None:
        var_a, var_s = noise[0][ok], noise[1][ok]
        n = var_a.size
        out["antisymmetric_noise_per_m"] = float(np.sqrt(np.mean(var_a)))
        out["symmetric_noise_per_m"] = float(np.sqrt(np.mean(var_s)))
        out["antisymmetric_noise_ms_sd_per_m2"] = float(np.sqrt(1.25 * 2.0 * np.sum(var_a * var_a)) / n)
    return out


def curl_judgement(curl: dict, max_ratio: float, floor_per_m: float, sigmas: float,
                   noise_tolerance: float) -> dict:
    """Whether a slope field turns (fringe sets swapped), judged against its noise: pure, for the verdict.

    From :func:`slope_curl`'s figures: each part's mean square less what the slope noise alone gives it
    (the parts a noise-free capture would show), ``excess_a`` and ``excess_s``. The field turns when

    * the antisymmetric excess is beyond its noise: above *sigmas* standard deviations of the
      antisymmetric mean square under noise alone, that deviation widened in quadrature by
      *noise_tolerance* times the predicted noise mean square (how well the predicted noise is known);
    * its root exceeds *max_ratio* times the symmetric excess's root (a real surface's slope errors
      stretch, they do not turn: swapped sets turn about as much as they stretch), and *floor_per_m*.

    Without the noise figures (an analysis of older code) the parts are judged as measured, noise included.

    Returns
    -------
    dict
        ``turns`` (bool), ``antisymmetric_per_m`` and ``symmetric_per_m`` (the roots of the excesses, 1/m)
        and ``sigmas`` (the antisymmetric excess over its deviation; None without noise figures).
    """
    anti, sym = curl["antisymmetric_rms_per_m"], curl["symmetric_rms_per_m"]
    noise_a, noise_s = curl.get("antisymmetric_noise_per_m"), curl.get("symmetric_noise_per_m")
    if noise_a is None or noise_s is None:
        turns = anti > max(max_ratio * sym, floor_per_m)
        return {"turns": bool(turns), "antisymmetric_per_m": anti, "symmetric_per_m": sym, "sigmas": None}
    excess_a = anti * anti - noise_a * noise_a
    excess_s = sym * sym - noise_s * noise_s
    sd = float(np.hypot(curl.get("antisymmetric_noise_ms_sd_per_m2", 0.0), noise_tolerance * noise_a * noise_a))
    z = excess_a / sd if sd > 0 else (float("inf") if excess_a > 0 else 0.0)
    root_a, root_s = float(np.sqrt(max(excess_a, 0.0))), float(np.sqrt(max(excess_s, 0.0)))
    turns = z > sigmas and root_a > max(max_ratio * root_s, floor_per_m)
    return {"turns": bool(turns), "antisymmetric_per_m": root_a, "symmetric_per_m": root_s, "sigmas": float(z)}


def _curl_noise(slope_cov, right, left, down, up, i00, i01, i10, i11) -> tuple[np.ndarray, np.ndarray]:
    """Per centre, the variance the slope noise gives the antisymmetric part a = (G_xy - G_yx) / 2 and the
    mean variance of the two symmetric parts (G_xy + G_yx) / 2, (G_xx - G_yy) / 2 (1/m^2).

    With the differences sc = s_x[R] - s_x[L], sr = s_x[D] - s_x[U] (tc, tr of s_y likewise) and
    G_xy = sc i01 + sr i11, G_yx = tc i00 + tr i10, G_xx = sc i00 + sr i10, G_yy = tc i01 + tr i11, every
    part is a weighted sum of the four pixels' slopes; pixels R and L (D and U) enter with opposite weights
    of one size, so each part's variance is the pair's summed covariances through those weights."""
    cells = np.concatenate([right, left, down, up])
    # the points asked for once each, in index order, without sorting (a mark and a lookup over the points)
    size = int(cells.max()) + 1 if cells.size else 0
    mark = np.zeros(size, dtype=bool)
    mark[cells] = True
    unique = np.flatnonzero(mark)
    where = np.empty(size, dtype=np.intp)
    where[unique] = np.arange(unique.size)
    inverse = where[cells]
    vx, vy, cxy = (np.asarray(v, dtype=np.float64)[inverse] for v in slope_cov(unique))
    n = right.size
    pair = {}
    for name, (p, q) in (("rl", (0, 1)), ("du", (2, 3))):
        sl_p, sl_q = slice(p * n, (p + 1) * n), slice(q * n, (q + 1) * n)
        pair[name] = (vx[sl_p] + vx[sl_q], vy[sl_p] + vy[sl_q], cxy[sl_p] + cxy[sl_q])

    def var(w_rl, w_du):
        """Variance of 1/2 (w_x s_x + w_y s_y) summed over the pairs, weights (w_x, w_y) per pair."""
        total = 0.0
        for (wx, wy), (xx, yy, xy) in ((w_rl, pair["rl"]), (w_du, pair["du"])):
            total = total + wx * wx * xx + wy * wy * yy + 2.0 * wx * wy * xy
        return 0.25 * total

    var_a = var((i01, -i00), (i11, -i10))
    var_s = 0.5 * (var((i01, i00), (i11, i10)) + var((i00, -i01), (i10, -i11)))
    return var_a, var_s


def stale_frames(frames: np.ndarray, fringes, mask: np.ndarray, ratio: float = 0.5) -> dict:
    """Four-step sets with a frame captured before the display had changed: ``{"y p=3.9": (k, r), ...}``,
    k the set's frame (0-3) that barely differs from the one before it, r that difference over the set's
    median step (the mean absolute change over the *mask*'s pixels, DN).

    Between consecutive frames of a set the pattern moves by a quarter period, so every step changes the
    image alike (r near 1: 0.77-1.26 on OpenCSP's two real captures); a frame the display had not yet
    updated repeats its predecessor (r = 0.21 on the stale frame of OpenCSP's ensemble capture). Sets with
    a step below *ratio* are named."""
    sl = fringes.slices()
    stack = frames[:, mask].astype(np.float64)
    out = {}
    for axis in ("x", "y"):
        for p, s in zip(getattr(fringes, f"periods_{axis}"), sl[axis]):
            f = stack[s]
            n = f.shape[0]
            steps = np.array([np.mean(np.abs(f[(k + 1) % n] - f[k])) for k in range(n)])
            r = steps / max(float(np.median(steps)), 1e-12)
            k = int(np.argmin(r))
            if r[k] < ratio:
                out[f"{axis} p={p:g}"] = ((k + 1) % n, float(r[k]))
    return out
