"""A lens's blur taken off the decoded screen positions, to first order (issue 47, item 1).

A camera whose lens blurs its image by a point-spread function of standard deviation sigma pixels sees, in each
fringe set, the blurred complex fringe signal: the phase steps' sums form z = A exp(i phi) per pixel (A the
fringe amplitude, phi the phase), and the blur, acting on the light, acts on z alike, z_b = G * z = z +
(sigma^2 / 2) lap z + O(sigma^4) for a Gaussian (a defocused lens's disk of radius r has sigma = r / 2). The
decoded phase is then

    arg z_b - phi = (sigma^2 / 2) Im(lap z / z) = (sigma^2 / 2) (lap phi + 2 grad ln A . grad phi),

and the screen position is the finest set's phase times a constant, so a position s moves by the same
expression in s. Both terms vary across the facet: the phase's own curvature (the projection through the
mirror onto the screen), and the amplitude's slope (the lens's vignetting, the facet's reflectance) times the
phase's gradient. Their part that grows linearly across the facet is a scale error of the positions, which a
nearly flat facet reads as focal power: on the population's heliostat stations at 4 m (f about 100 m) with a
blurred lens (0.7-0.8 px), f was 100-230 ppm short of the like-for-like truth with unrounded, noise-free
frames, and within 36 ppm after this correction (docs/method.md, "Nearly flat facets far from the screen").

The correction uses the smooth part of the positions and amplitudes only (a cubic of the pixel coordinates for
each position, a quadratic for the amplitude's logarithm, fitted on up to :data:`FIT_POINTS` pixels): their
derivatives from the pixels themselves would carry the noise, and the blur of the facet's fine slope errors
is not a displacement but a smoothing, which the slope RMS's U carries
(:func:`~.uncertainty.budget.blur_bias_mrad`).

That smoothing still reaches the fitted figures. A rough facet's fine structure, smoothed, no longer projects on
the parabola as the facet's own does: on seed 0's blurred heliostat stations (f 100 m at 4 m, 0.6-0.8 px of blur,
seven drawn facets each, noise-free frames) f scattered 45 and 83 ppm RMS about the like-for-like truth after the
smooth correction, and 3-10 ppm on sharp ones. :func:`roughness_shift_m` is the same first order for the fine
structure, (sigma^2 / 2) lap of each pixel's position less the smooth fit, from the pixel and its four
neighbours. It multiplies a pixel's position noise by about 1 + 2 sigma^2, so it is not taken off the positions:
only the figures' fit sees it (:func:`~.pipeline.sharpened_fit`). The fit's slope weights are linear across the
facet, so by Green's identity the Laplacian's noise reaches the fit only through the rim's pixels.
Pure numpy: arrays in, arrays out.
"""

from __future__ import annotations

import numpy as np

from .fit import monomial_powers, monomials
from .metrics import neighbour_pairs

#: The measured edge blur (pixels, ``Outline.edge_blur_px``: beyond the pixel's own square) below which the
#: positions are left as they are: on the population (seed 0, 500 captures) sharp edges measured up to 0.29 px
#: (pixel-area sampling, vignetting), and a blur that small moves f by a sixth of what 0.7 px does.
MIN_BLUR_PX = 0.3
#: What the figures' sharpening (:func:`roughness_shift_m`, :func:`~.pipeline.sharpened_fit`) leaves of the
#: error it corrects, as a fraction of its own size: on seed 0's blurred heliostat stations 34 and 42 (seven
#: drawn facets each, noise-free unrounded frames) the RMS of f's error after it was 0.52 and 0.51 of the
#: correction's RMS (28 values, f x and y). A facet's own correction is a poor measure of its own remainder (one
#: draw of it, and the remainder has a part the correction does not scale: -18 / -8 ppm of f on average on both
#: stations), so the budget's row "lens blur on the facet's roughness" pools the correction over the two axes and
#: takes this fraction of it as its standard uncertainty (:func:`~.analysis.add_sharpening_row`): its error over
#: the row was 0.85 RMS (aggregate) on those 28 values, and 26 of them within twice the row.
ROUGHNESS_LEFT = 0.6
#: Pixels the smooth fits use at most (every k-th of the trusted ones).
FIT_POINTS = 20_000
#: Degrees of the smooth fits: the positions' (cubic: their curvature may vary across the facet) and the
#: amplitude logarithm's (quadratic: its slope may).
POSITION_DEGREE = 3
AMPLITUDE_DEGREE = 2


def _derivative(coeffs: np.ndarray, powers, u: np.ndarray, v: np.ndarray, du: int, dv: int) -> np.ndarray:
    """The polynomial sum c (u^i v^j) differentiated du times in u and dv times in v, at (u, v)."""
    out = np.zeros_like(u)
    for c, (i, j) in zip(coeffs, powers):
        if i < du or j < dv or c == 0.0:
            continue
        factor = float(np.prod(np.arange(i - du + 1, i + 1))) * float(np.prod(np.arange(j - dv + 1, j + 1)))
        out += (c * factor) * u ** (i - du) * v ** (j - dv)
    return out


def blur_shift_m(columns_px: np.ndarray, rows_px: np.ndarray, ok: np.ndarray, position_m: np.ndarray,
                 amplitude_dn: np.ndarray, sigma_px: float, max_points: int = FIT_POINTS) -> np.ndarray:
    """How far a blur of *sigma_px* (standard deviation, pixels) moved each pixel's decoded position along one
    axis (metres, the module's first-order expression from smooth fits), at every pixel given; 0 where the fits
    have too few trusted pixels (*ok*) to stand on.

    Parameters
    ----------
    columns_px, rows_px : (M,) arrays
        The pixels' image coordinates.
    ok : (M,) bool array
        Pixels whose position and amplitude the fits may use.
    position_m : (M,) array
        The decoded screen positions along the axis, metres.
    amplitude_dn : (M,) array
        The fringe amplitude of the set the positions come from (the finest), DN.
    sigma_px : float
        The blur's standard deviation, pixels.
    """
    u_all = np.asarray(columns_px, np.float64)
    v_all = np.asarray(rows_px, np.float64)
    s_all = np.asarray(position_m, np.float64)
    a_all = np.asarray(amplitude_dn, np.float64)
    if not (u_all.shape == v_all.shape == s_all.shape == a_all.shape == np.shape(ok)):
        raise ValueError("blur_shift_m needs columns, rows, ok, positions and amplitudes of one shape")
    shift = np.zeros(u_all.shape)
    use = np.flatnonzero(np.asarray(ok, bool) & np.isfinite(s_all) & (a_all > 0))
    powers_s, powers_a = monomial_powers(POSITION_DEGREE), monomial_powers(AMPLITUDE_DEGREE)
    if use.size < 4 * len(powers_s) or not sigma_px > 0:
        return shift
    use = use[::max(1, use.size // max_points)]
    # centred and scaled coordinates, so the fits are well conditioned; derivatives taken back to pixels
    u0, v0 = float(np.mean(u_all[use])), float(np.mean(v_all[use]))
    scale = max(float(np.std(u_all[use])), float(np.std(v_all[use])), 1.0)
    un, vn = (u_all[use] - u0) / scale, (v_all[use] - v0) / scale
    cs, *_ = np.linalg.lstsq(monomials(un, vn, POSITION_DEGREE), s_all[use], rcond=None)
    ca, *_ = np.linalg.lstsq(monomials(un, vn, AMPLITUDE_DEGREE), np.log(a_all[use]), rcond=None)
    uu, vv = (u_all - u0) / scale, (v_all - v0) / scale
    lap = (_derivative(cs, powers_s, uu, vv, 2, 0) + _derivative(cs, powers_s, uu, vv, 0, 2)) / scale ** 2
    grad = (_derivative(ca, powers_a, uu, vv, 1, 0) * _derivative(cs, powers_s, uu, vv, 1, 0)
            + _derivative(ca, powers_a, uu, vv, 0, 1) * _derivative(cs, powers_s, uu, vv, 0, 1)) / scale ** 2
    return 0.5 * float(sigma_px) ** 2 * (lap + 2.0 * grad)


def roughness_shift_m(columns_px: np.ndarray, rows_px: np.ndarray, ok: np.ndarray, position_m: np.ndarray,
                      sigma_px: float, max_points: int = FIT_POINTS) -> np.ndarray:
    """How far a blur of *sigma_px* (standard deviation, pixels) moved each pixel's decoded position along one
    axis by smoothing the positions' fine structure (metres): (sigma^2 / 2) times the 5-point Laplacian of the
    position less its smooth cubic fit (the cubic's own Laplacian is :func:`blur_shift_m`'s), at every pixel
    given; 0 where a pixel or one of its four neighbours is not trusted (*ok*, and not given: the rim), or the
    fit has too few pixels to stand on.

    Parameters
    ----------
    columns_px, rows_px : (M,) arrays
        The pixels' image coordinates, whole pixels.
    ok : (M,) bool array
        Pixels whose position may be used.
    position_m : (M,) array
        The decoded screen positions along the axis, metres.
    sigma_px : float
        The blur's standard deviation, pixels.
    """
    u_all = np.rint(np.asarray(columns_px, np.float64)).astype(np.int64)
    v_all = np.rint(np.asarray(rows_px, np.float64)).astype(np.int64)
    s_all = np.asarray(position_m, np.float64)
    if not (u_all.shape == v_all.shape == s_all.shape == np.shape(ok)):
        raise ValueError("roughness_shift_m needs columns, rows, ok and positions of one shape")
    shift = np.zeros(s_all.shape)
    trusted = np.flatnonzero(np.asarray(ok, bool) & np.isfinite(s_all))
    powers = monomial_powers(POSITION_DEGREE)
    if trusted.size < 4 * len(powers) or not sigma_px > 0:
        return shift
    use = trusted[::max(1, trusted.size // max_points)]
    u0, v0 = float(np.mean(u_all[use])), float(np.mean(v_all[use]))
    scale = max(float(np.std(u_all[use])), float(np.std(v_all[use])), 1.0)
    cs, *_ = np.linalg.lstsq(monomials((u_all[use] - u0) / scale, (v_all[use] - v0) / scale, POSITION_DEGREE),
                             s_all[use], rcond=None)
    u, v = u_all[trusted], v_all[trusted]
    fine = s_all[trusted] - monomials((u - u0) / scale, (v - v0) / scale, POSITION_DEGREE) @ cs
    # each trusted pixel's four neighbours among the trusted ones (metrics.neighbour_pairs), on a raster of the
    # pixels' box one column wider than it, so that no pair runs across a row's end
    width = int(u.max() - u.min()) + 2
    key = (v - int(v.min())) * width + (u - int(u.min()))
    order = np.argsort(key, kind="stable")
    fine_sorted = fine[order]
    laplacian = np.zeros(trusted.size)
    complete = np.ones(trusted.size, bool)
    for first, second in neighbour_pairs(key[order], width):
        ahead, behind = np.full(trusted.size, np.nan), np.full(trusted.size, np.nan)
        ahead[first], behind[second] = fine_sorted[second], fine_sorted[first]
        difference = ahead - 2.0 * fine_sorted + behind
        complete[order] &= np.isfinite(difference)
        laplacian[order] += np.nan_to_num(difference)
    shift[trusted[complete]] = 0.5 * float(sigma_px) ** 2 * laplacian[complete]
    return shift

