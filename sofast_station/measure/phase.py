"""Phase, modulation and temporal unwrapping (docs/conventions.md#phase, #unwrapping).

Four frames with shifts d_k = k pi/2 show I_k = a + b cos(phi - d_k), so
I_0 - I_2 = 2b cos(phi), I_1 - I_3 = 2b sin(phi) and I_0 + I_2 - I_1 - I_3 = 0.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .kernels import minus_models
from .stats import median, quantile

TWO_PI = 2.0 * np.pi

#: Uniform 8-bit quantisation noise, DN (1/sqrt(12)): the floor of any intensity-noise estimate.
QUANTISATION_NOISE_DN = 1.0 / np.sqrt(12.0)


def wrap_phase(phi: np.ndarray) -> np.ndarray:
    """Wrap radians into [0, 2 pi); an input just below 0 that rounds to 2 pi maps to 0."""
    out = np.mod(phi, TWO_PI)
    out[out >= TWO_PI] = 0.0
    return out


def _wrap_atan2(phi: np.ndarray) -> np.ndarray:
    """Map atan2's (-pi, pi] onto [0, 2 pi) in place (cheaper than np.mod for that range)."""
    phi[phi < 0] += TWO_PI
    phi[phi >= TWO_PI] = 0.0       # -tiny + 2 pi rounds to 2 pi
    return phi


def phase_and_modulation(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase, modulation and consistency residual from four quarter-period-shifted frames.

    Parameters
    ----------
    frames : (4, ...) array
        Intensities I_0..I_3 (DN) with shifts 0, pi/2, pi, 3 pi/2.

    Returns
    -------
    phase : array, radians in [0, 2 pi)
        ``mod(atan2(I_1 - I_3, I_0 - I_2), 2 pi)``.
    modulation : array, DN
        Fringe amplitude b = hypot(I_1 - I_3, I_0 - I_2) / 2.
    consistency : array, DN
        I_0 + I_2 - I_1 - I_3; zero up to noise when the display showed each frame completely.
    """
    frames = np.asarray(frames)
    if frames.shape[0] != 4:
        raise ValueError(f"frames must hold 4 phase steps along axis 0, got shape {frames.shape}")
    if frames.dtype in (np.uint8, np.uint16) and frames[0].size > 0:
        return _phase_and_modulation_counts(frames)
    # Integer counts convert exactly to float32, and float32 phase resolves 1e-6 rad: ample, and faster.
    work = np.float32 if np.issubdtype(frames.dtype, np.integer) and frames.itemsize <= 2 else np.float64
    i0, i1, i2, i3 = (frames[k].astype(work) for k in range(4))
    s = i1 - i3
    c = i0 - i2
    phase = _wrap_atan2(np.arctan2(s, c))
    modulation = 0.5 * np.hypot(s, c)
    consistency = (i0 + i2) - (i1 + i3)
    return phase, modulation, consistency


def _phase_and_modulation_counts(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`phase_and_modulation` of 8- or 16-bit counts in one compiled pass over the pixels
    (:func:`~.kernels.phase_counts`), from the counts without converting whole frames.

    With s = I_1 - I_3 and c = I_0 - I_2 (whole counts, exact):

    * phase: atan2(s, c) wrapped into [0, 2 pi), evaluated in float64 and rounded once to float32 (within
      half a float32 step of the exact value; s = 0 gives 0 where c >= 0 and pi where c < 0). It differs
      from the general path's float32 ``atan2(s, c) + 2 pi`` by at most one float32 step (4.8e-7 rad, a
      thousandth of the phase noise of 1 DN on 50 DN of modulation): checked over every 8-bit (s, c);
    * modulation: sqrt(s^2 + c^2) / 2, the sum exact in float64 and its square root rounded to float32:
      the correctly rounded hypot, as the C library's float hypot computes it;
    * consistency: (I_0 + I_2) - (I_1 + I_3) in integers, exact.
    """
    from .kernels import phase_counts

    shape = frames.shape[1:]
    flat = np.ascontiguousarray(frames).reshape(4, -1)
    phase, modulation, consistency = (np.empty(flat.shape[1], dtype=np.float32) for _ in range(3))
    phase_counts(flat, phase, modulation, consistency)
    return phase.reshape(shape), modulation.reshape(shape), consistency.reshape(shape)


#: Residuals beyond this many standard deviations are trimmed from the noise variance (iteratively).
TRIM_SIGMAS = 4.5
#: Largest number of residuals the noise and harmonic estimates use (a fixed stride beyond it).
MAX_NOISE_SAMPLES = 200_000


def _stride(r: np.ndarray) -> np.ndarray:
    """A fixed stride of at most :data:`MAX_NOISE_SAMPLES` elements: deterministic and fast."""
    return r[:: max(1, -(-r.size // MAX_NOISE_SAMPLES))]


def trimmed_std(r: np.ndarray, trim_sigmas: float = TRIM_SIGMAS, rounds: int = 50) -> float:
    """Standard deviation of *r* with outliers trimmed, consistent for Gaussian data.

    Unlike the median absolute deviation, this keeps its meaning on integer-valued residuals (whose
    median absolute deviation can only take a few values): the variance of the values within
    ``trim_sigmas`` standard deviations, divided by that truncated Gaussian's variance fraction, iterated
    from the 68th percentile of |r| until the kept set stops changing.
    """
    r = np.asarray(r, dtype=np.float64).ravel()
    if r.size == 0:
        return 0.0
    about = median(r)
    a = np.abs(r - about)
    s = max(quantile(a, 0.6827), 0.5)
    c = float(trim_sigmas)
    # Variance of a standard Gaussian truncated to |z| <= c, relative to 1.
    frac = math.erf(c / math.sqrt(2.0))
    shrink = 1.0 - 2.0 * c * np.exp(-0.5 * c * c) / np.sqrt(2.0 * np.pi) / frac
    from .kernels import trim_rounds

    return float(trim_rounds(r, a, c, s, float(shrink), int(rounds), about))


def intensity_noise_dn(consistency: np.ndarray, quantised: bool = True) -> float:
    """Per-frame intensity noise (DN) from consistency residuals I_0 + I_2 - I_1 - I_3 alone.

    The residual of four independent frames with noise sigma has standard deviation
    2 sqrt(sigma^2 + q^2), q^2 = 1/12 DN^2 being the variance of rounding to whole counts (exact on average
    over pixels whose true values have uniformly spread fractions). The trimmed standard deviation keeps
    the estimate immune to the few pixels a half-drawn frame spoils. With *quantised* the rounding
    variance is removed, so the result estimates the camera's own noise; 0 when rounding explains all.
    Residuals carrying a display nonlinearity must be cleaned first (:func:`frame_noise`).
    """
    r = _stride(np.asarray(consistency, dtype=np.float64).ravel())
    if r.size == 0:
        return 0.0
    var = (trimmed_std(r) / 2.0) ** 2 - (QUANTISATION_NOISE_DN ** 2 if quantised else 0.0)
    return float(np.sqrt(max(var, 0.0)))


def _power_law_table(exponents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Second-harmonic ratio and largest four-step phase error (rad) of full-depth fringes seen through a
    power-law response I = (1 + cos theta)^g, for each exponent g (the model behind the phase-error
    estimate of :func:`frame_noise`)."""
    phi = np.linspace(0.0, TWO_PI, 720, endpoint=False)
    ratios, errors = [], []
    for g in exponents:
        i0, i1, i2, i3 = ((1.0 + np.cos(phi - k * np.pi / 2)) ** g for k in range(4))
        s, c = i1 - i3, i0 - i2
        b = 0.5 * np.hypot(s, c)
        x = b * np.cos(2.0 * phi)
        ratios.append(float(x @ (i0 + i2 - i1 - i3)) / float(x @ x) / 4.0)
        errors.append(float(np.abs(np.angle(np.exp(1j * (np.arctan2(s, c) - phi)))).max()))
    return np.array(ratios), np.array(errors)


_EXPONENTS = np.linspace(0.25, 4.0, 301)
_RATIOS, _PHASE_ERRORS = _power_law_table(_EXPONENTS)


def phase_error_from_harmonic(ratio: float) -> float:
    """Largest four-step phase error (rad) that a power-law response with this second-harmonic ratio
    (second-harmonic amplitude over the fundamental's, signed) gives on full-depth fringes."""
    ratio = float(np.clip(ratio, _RATIOS[0], _RATIOS[-1]))
    return float(np.interp(ratio, _RATIOS, _PHASE_ERRORS))


@dataclass(frozen=True)
class FrameNoise:
    """What the four-step residuals say about the capture: noise, and a display response left nonlinear.

    A display whose response is not linear adds harmonics to every fringe. In I_0 + I_2 - I_1 - I_3 the
    fundamental cancels but the second harmonic c_2 cos(2 (phi - d_k) + psi) adds up to
    4 c_2 cos(2 phi + psi): a residual that follows the phase, which noise does not. It is fitted per set
    as r = alpha + b (beta cos 2 phi + gamma sin 2 phi) [+ delta w] (alpha, delta per set: room light or
    exposure changing between frames, w the pixel's white - dark; beta, gamma shared by the sets) and
    removed before the noise is estimated (with the sixth harmonic, which survives the residual too).

    Attributes
    ----------
    noise_dn : float
        Per-frame camera noise, DN, rounding to whole counts removed (see :func:`intensity_noise_dn`).
    frame_noise_dn : float
        Per-frame noise including rounding, sqrt(noise^2 + 1/12), DN: what phases and consistency see.
    harmonic_ratio : float
        The second harmonic's amplitude over the fundamental's (0 for a linear response; about 0.28 for a
        display with gamma 2.2 left uncorrected), fitted over all sets together.
    signed_harmonic_ratio : float
        The same, positive when the response bends upward (gamma above 1), negative when downward.
    phase_error_rad : float
        Largest phase error the response gives the four-step phase, rad: as the capture shows it between
        its coarse and fine sets (:func:`phase_error_between_periods`, ``phase_error_from`` "periods"),
        or, where they cannot tell, from the second harmonic assuming a power law over the fringe's full
        depth (:func:`phase_error_from_harmonic`, "harmonic").
    residuals : list of arrays
        Each set's consistency residual with its fitted harmonic and offset removed, DN.
    phase_error_rms_rad, phase_error_u_rad : float or None
        The phase error's RMS over a period and the standard uncertainty of ``phase_error_rad``, rad (from
        the period sets; None from the harmonic).
    phase_error_from : str
        "periods" or "harmonic".
    """

    noise_dn: float
    frame_noise_dn: float
    harmonic_ratio: float
    signed_harmonic_ratio: float
    phase_error_rad: float
    residuals: list
    phase_error_rms_rad: float | None = None
    phase_error_u_rad: float | None = None
    phase_error_from: str = "harmonic"

    def with_period_error(self, measured: "PeriodPhaseError | None") -> "FrameNoise":
        """This estimate with the phase error the period sets show (:func:`phase_error_between_periods`),
        when they show one; unchanged otherwise."""
        if measured is None:
            return self
        return dataclasses.replace(self, phase_error_rad=measured.max_rad, phase_error_rms_rad=measured.rms_rad,
                                   phase_error_u_rad=measured.u_rad, phase_error_from="periods")


def frame_noise(phases, modulations, residuals, level=None, pool=None) -> FrameNoise:
    """Noise and display nonlinearity from the four-step sets of one capture.

    Parameters
    ----------
    phases, modulations, residuals : sequences of arrays
        Per four-step set, as :func:`phase_and_modulation` returns them (rad, DN, DN), same pixels.
    level : array, optional
        Each pixel's brightness (white - dark, DN), the same pixels. Room light or exposure changing
        between frames changes each pixel in proportion to its brightness: with *level* that part is
        fitted too. (Not the mean of the fringe frames: a half-drawn frame would leak into it.)
    pool : executor, optional
        Where half of the sets' fit samples, scatters and cleaned residuals are formed beside the other
        half (each set's arithmetic is the same on any thread).

    Returns
    -------
    FrameNoise
    """
    n_sets = len(residuals)
    if n_sets == 0:
        return FrameNoise(0.0, QUANTISATION_NOISE_DN, 0.0, [], 0.0, [])
    level = None if level is None else np.asarray(level).ravel()
    per_set = 1 if level is None else 2

    def sample(k):
        """Set k's regressors on every stride-th pixel (double precision): its own offset (and mean level),
        then the shared harmonics (the sixth survives the residual too: its sign alternates with the
        step), and its residuals (:func:`~.kernels.noise_rows`, one compiled pass)."""
        from .kernels import noise_rows

        r = np.asarray(residuals[k]).ravel()
        stride = max(1, -(-r.size * n_sets // MAX_NOISE_SAMPLES))
        return noise_rows(phases[k], modulations[k], r, level, stride)

    samples = _map_halves(pool, sample, range(n_sets))

    def joint_fit(good):
        """One fit over the *good* sets: each its own offset (and level term), the harmonics shared. A set
        whose pixels see only part of a fringe (coarse periods over a small reflected footprint) cannot
        tell a harmonic from an offset on its own; together the sets can. Returns the shared harmonic
        coefficients and every set's own coefficients (those of the others fitted with the harmonic fixed)."""
        coef = _block_lstsq([samples[k] for k in good], first_blocks)
        n_own = per_set * len(good)
        harmonic, own_coefs = coef[n_own:], []
        for k in range(n_sets):
            if k in good:
                j = good.index(k)
                own_coefs.append(coef[per_set * j:per_set * (j + 1)])
            else:
                own, shared, r = samples[k]
                own_coefs.append(_robust_lstsq(own, minus_models(r, shared, harmonic), stride=False))
        return harmonic, own_coefs

    # A set spoiled by a half-drawn frame keeps a large scatter about the shared fit (its error follows
    # the fundamental, and the other sets do not share it): the worst such set is left out and the fit
    # repeated, one set at a time (a spoiled set also pulls the shared terms, so others look worse at first).
    good = list(range(n_sets))
    first_blocks: dict = {}      # each set's sums over all its samples: the same in every refit
    while True:
        harmonic, own_coefs = joint_fit(good)
        scatter = _map_halves(pool, lambda k: trimmed_std(minus_models(samples[k][2], samples[k][1], harmonic,
                                                                       samples[k][0], own_coefs[k])), range(n_sets))
        worst = max(good, key=lambda k: scatter[k])
        if len(good) == 1 or scatter[worst] <= 2.0 * min(scatter[k] for k in good):
            break
        good.remove(worst)
    def clean(k):
        from .kernels import cleaned_residuals

        return cleaned_residuals(residuals[k], phases[k], modulations[k], level, harmonic, own_coefs[k])

    cleaned = _map_halves(pool, clean, range(n_sets))
    # r = 4 c_2 cos(2 phi + psi): the ratio c_2 / b, signed by the cosine part (power laws have psi = 0, pi).
    ratio = 0.25 * float(np.hypot(harmonic[0], harmonic[1])) * (1.0 if harmonic[0] >= 0 else -1.0)
    noise = intensity_noise_dn(np.concatenate([_stride(cleaned[k]) for k in good]))
    return FrameNoise(noise_dn=noise, frame_noise_dn=float(np.hypot(noise, QUANTISATION_NOISE_DN)),
                      harmonic_ratio=abs(ratio), signed_harmonic_ratio=ratio,
                      phase_error_rad=phase_error_from_harmonic(ratio), residuals=cleaned)


#: Harmonics of the phase (k phi) in the four-step phase error a static nonlinearity leaves: the response's
#: 3rd and 5th harmonics alias into the fundamental as a 4 phi error, the 7th and 9th as 8 phi.
PHASE_ERROR_HARMONICS = (4, 8)
#: Fewest pixels :func:`phase_error_between_periods` fits (a capture with fewer says nothing).
MIN_PHASE_ERROR_PIXELS = 500


@dataclass(frozen=True)
class PeriodPhaseError:
    """The four-step phase error a capture shows between its coarse and fine fringe sets.

    Attributes
    ----------
    max_rad, rms_rad : float
        Largest and RMS phase error over a period of the phase, rad (the noise's share of the fitted
        amplitude taken out).
    u_rad : float
        Standard uncertainty of ``max_rad`` from the fit's noise, rad.
    n_pixels : int
        Pixels (of every axis together) the fit used.
    """

    max_rad: float
    rms_rad: float
    u_rad: float
    n_pixels: int


def phase_error_between_periods(sets: list, noise_dn: float = 0.0, mask: list | None = None
                                ) -> PeriodPhaseError | None:
    """The phase error of the four-step phases, measured from the disagreement of two period sets.

    A display (or camera) response that is not linear distorts every fringe alike, so the four-step phase
    of each set is off by the same function of the phase, e(phi), periodic with a quarter of a period
    (:data:`PHASE_ERROR_HARMONICS`: a sum of a_k sin k phi + b_k cos k phi). A pixel's coarse and fine
    phases see one screen point: with r = p_fine / p_coarse a whole number, phi_f - r phi_c (wrapped) is
    e(phi_f) - r e(phi_c) plus noise, whatever the response's shape. The a_k, b_k (and a constant per axis)
    are fitted to that over the pixels of every axis, and e's largest value and RMS over a period reported,
    with the noise's expected share of the fitted amplitude removed. No model of the response is assumed:
    the second harmonic's ratio (:func:`phase_error_from_harmonic`) holds for a power law only, and another
    shape can have a small second and a large third harmonic.

    The regressors sin k phi - r sin k phi_c are formed from the same noisy phases as the disagreement, so
    their noise and its noise are correlated: a least-squares fit would find a phase error of its own
    (about k r^2 sigma_c^2 / (r^2 / 2), 10 mrad at 5 DN of noise). Both first-order terms, the regressors'
    noise against the disagreement's and against itself (sigma = noise / (sqrt(2) b) per phase), are taken
    out of the normal equations.

    Parameters
    ----------
    sets : list of (phase_coarse, phase_fine, modulation_coarse, modulation_fine, p_coarse, p_fine)
        Per axis: the wrapped phases (rad) and modulations (DN) of its coarsest and finest sets (the same
        pixels) and their period counts.
    noise_dn : float
        Per-frame intensity noise, DN.
    mask : list of bool arrays or None
        Per axis, the pixels to use (those whose phases are trusted).

    Returns
    -------
    PeriodPhaseError or None
        None when no axis has a whole-number period ratio above 1, too few pixels, or phases that do not
        spread enough to tell e from a constant.
    """
    ks = np.array(PHASE_ERROR_HARMONICS, dtype=np.float64)
    n_own = 1
    blocks = []
    for i, (phi_c, phi_f, b_c, b_f, p_c, p_f) in enumerate(sets):
        r = float(p_f) / float(p_c)
        if r <= 1.0 or abs(r - round(r)) > 1e-9:
            continue
        # every step-th of the pixels in the mask, gathered straight from the images (not masked first)
        arrays = [np.asarray(v).ravel() for v in (phi_c, phi_f, b_c, b_f)]
        pick = (np.flatnonzero(np.asarray(mask[i], dtype=bool).ravel()) if mask is not None
                else np.arange(arrays[0].size))
        step = max(1, -(-pick.size * len(sets) // MAX_NOISE_SAMPLES))
        phi_c, phi_f, b_c, b_f = (v[pick[::step]].astype(np.float64, copy=False) for v in arrays)
        var_c = (noise_dn / (np.sqrt(2.0) * np.maximum(b_c, 1e-9))) ** 2
        var_f = (noise_dn / (np.sqrt(2.0) * np.maximum(b_f, 1e-9))) ** 2
        m = phi_c.size
        # The axis's own term, a constant (a phase offset between its sets), then the shared harmonics; with
        # each column's derivative by phi_f and by phi_c. (Each set's error at the phase's first harmonic, a
        # frame brighter or dimmer than the others of its set, is not fitted: over the few radians of
        # phase a small facet's coarse set sees, cos and sin phi_c are nearly the constant and the 4 phi_c
        # terms, and the fit came apart; left in, room light jittering by 0.2 % of white from frame to
        # frame adds about 0.7 mrad to the stated error, on the safe side.)
        own = [np.ones(m)]
        own_df = own_dc = [np.zeros(m)]
        kf, kc = ks[None, :] * phi_f[:, None], ks[None, :] * phi_c[:, None]
        harm = np.empty((m, 2 * ks.size))
        sin_f, cos_f, sin_c, cos_c = np.sin(kf), np.cos(kf), np.sin(kc), np.cos(kc)
        harm[:, 0::2] = sin_f - r * sin_c
        harm[:, 1::2] = cos_f - r * cos_c
        h_df, h_dc = np.empty_like(harm), np.empty_like(harm)
        h_df[:, 0::2], h_df[:, 1::2] = ks * cos_f, -ks * sin_f
        h_dc[:, 0::2], h_dc[:, 1::2] = -r * ks * cos_c, r * ks * sin_c
        y = np.angle(np.exp(1j * (phi_f - r * phi_c)))
        blocks.append((np.column_stack(own), np.column_stack(own_df), np.column_stack(own_dc), harm, h_df, h_dc,
                       y, var_f, var_c, r))
    if not blocks or sum(bl[6].size for bl in blocks) < MIN_PHASE_ERROR_PIXELS:
        return None
    n_axes = len(blocks)
    n_const = n_own * n_axes
    n = sum(bl[6].size for bl in blocks)
    x, d_f, d_c = (np.zeros((n, n_const + 2 * ks.size)) for _ in range(3))
    y, var_f, var_c, ratio = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    start = 0
    for j, (own, own_df, own_dc, harm, h_df, h_dc, yb, vf, vc, r) in enumerate(blocks):
        sl = slice(start, start + yb.size)
        cols = slice(n_own * j, n_own * (j + 1))
        x[sl, cols], d_f[sl, cols], d_c[sl, cols] = own, own_df, own_dc
        x[sl, n_const:], d_f[sl, n_const:], d_c[sl, n_const:] = harm, h_df, h_dc
        y[sl], var_f[sl], var_c[sl], ratio[sl] = yb, vf, vc, r
        start += yb.size
    # the regressors' noise: d_f n_f + d_c n_c; the disagreement's: n_f - r n_c
    nf = d_f * np.sqrt(var_f)[:, None]
    nc = d_c * np.sqrt(var_c)[:, None]
    cross = d_f * var_f[:, None] - (ratio * var_c)[:, None] * d_c
    # The normal equations over every pixel once; each round takes out the pixels it leaves out (a few: a
    # coarse phase that slipped a fringe), rather than forming them again over the pixels it keeps (when
    # most are left out, over those kept: a difference of two near-equal sums would lose its digits).
    def normal_equations(rows):
        xr, nfr, ncr = x[rows], nf[rows], nc[rows]
        return xr.T @ xr - nfr.T @ nfr - ncr.T @ ncr, xr.T @ y[rows] - cross[rows].sum(axis=0)

    xtx_all = x.T @ x - nf.T @ nf - nc.T @ nc
    xty_all = x.T @ y - cross.sum(axis=0)
    keep = np.ones(n, dtype=bool)
    for _ in range(3):               # a pixel whose coarse phase slipped a fringe: leave it out
        out = np.flatnonzero(~keep)
        if 2 * out.size > n:
            xtx, xty = normal_equations(np.flatnonzero(keep))
        else:
            xtx_out, xty_out = normal_equations(out)
            xtx, xty = xtx_all - xtx_out, xty_all - xty_out
        if np.linalg.cond(xtx) > 1e10:
            return None
        coef = np.linalg.solve(xtx, xty)
        res = y - x @ coef
        sigma = trimmed_std(res[keep])
        keep = np.abs(res) < TRIM_SIGMAS * max(sigma, 1e-9)
    cov = np.linalg.inv(xtx) * sigma ** 2
    harm = coef[n_const:]
    cov_h = cov[n_const:, n_const:]
    # The fitted coefficients' power holds the noise's (the trace of their covariance): take it out.
    power = float(harm @ harm)
    shrink = np.sqrt(max(power - float(np.trace(cov_h)), 0.0) / power) if power > 0 else 0.0
    phi = np.linspace(0.0, TWO_PI, 720, endpoint=False)
    basis = np.column_stack([f(k * phi) for k in PHASE_ERROR_HARMONICS for f in (np.sin, np.cos)])
    e = basis @ harm
    at = int(np.argmax(np.abs(e)))
    u_max = float(np.sqrt(basis[at] @ cov_h @ basis[at]))
    return PeriodPhaseError(max_rad=float(shrink * np.abs(e[at])), rms_rad=float(shrink * np.sqrt(np.mean(e * e))),
                            u_rad=u_max, n_pixels=int(keep.sum()))


#: Brightness bins of each kind (equal counts, equal widths) over which :func:`noise_by_level` fits the
#: noise's growth.
NOISE_LEVEL_BINS = 12
#: Fewest residuals a brightness bin needs to count in that fit.
NOISE_LEVEL_MIN_SAMPLES = 200


def noise_by_level(residuals, level_dn: np.ndarray, frame_noise_dn: float,
                   bins: int = NOISE_LEVEL_BINS) -> tuple[float, float]:
    """The frame noise's variance as an affine function of the pixel's brightness, sigma^2 = a + b w.

    A camera's noise grows with the light a pixel gathers (shot noise: variance in proportion to the
    signal, on top of the read noise and the rounding), so one noise figure for the whole facet over-states
    the noise of its dim pixels and under-states that of its bright ones. Dim pixels are mostly at the
    facet's edges (vignetting, and pixels the edge only partly covers), where they weigh most in the fits'
    curvature and twist. Each consistency residual I_0 + I_2 - I_1 - I_3 has variance 4 sigma^2 at its
    pixel (the fringe's own term cancels), so the residuals, binned by brightness *level_dn* (white - dark,
    DN, the same pixels as each residual array; *bins* bins of equal counts and *bins* of equal widths),
    give a variance per bin (the mean square of the residuals within 4.5 of the capture's standard
    deviations, so the few spoiled pixels do not count), and a line weighted by each bin's count over its
    variance squared gives a and b.

    The line is then scaled so that its mean over the pixels is *frame_noise_dn* squared: the overall
    level stays the capture's own estimate (:func:`intensity_noise_dn`), and only its spread over the
    pixels comes from here. b = 0 (one level for every pixel) when fewer than three bins have
    :data:`NOISE_LEVEL_MIN_SAMPLES` residuals, when their brightness does not spread, or when the fitted
    noise does not grow with brightness.

    Returns
    -------
    (a, b) : DN^2 and DN (sigma^2 in DN^2 for w in DN; :func:`noise_at_level` evaluates it)
    """
    flat = frame_noise_dn ** 2
    level_dn = np.asarray(level_dn, dtype=np.float64).ravel()
    sets = [np.asarray(r).ravel() for r in residuals]
    if not sets or any(r.size != level_dn.size for r in sets) or level_dn.size == 0:
        return flat, 0.0
    stride = max(1, -(-level_dn.size * len(sets) // MAX_NOISE_SAMPLES))
    w_s = level_dn[::stride]
    finite = np.isfinite(w_s)
    if np.count_nonzero(finite) * len(sets) < 3 * NOISE_LEVEL_MIN_SAMPLES or flat <= 0:
        return flat, 0.0
    # Bins of equal counts (where most pixels are) and of equal width (the few dim ones at the edges,
    # which decide the line's slope when the facet's inside is evenly lit).
    steps = np.linspace(0.0, 1.0, bins + 1)
    wf = w_s[finite]
    edges = np.unique(np.concatenate([np.quantile(wf, steps), wf.min() + steps * (wf.max() - wf.min())]))
    n_bins = max(edges.size - 1, 1)
    which = np.clip(np.searchsorted(edges, np.where(finite, w_s, edges[0]), side="right") - 1, 0, n_bins - 1)
    # Each bin's variance from the residuals within 4.5 of the capture's standard deviations (a spoiled
    # pixel is far beyond; a Gaussian loses 1e-4 of its variance there), summed over the sets.
    limit = (2.0 * TRIM_SIGMAS * np.sqrt(flat)) ** 2
    counts, sums, level_sums = np.zeros(n_bins), np.zeros(n_bins), np.zeros(n_bins)
    for r in sets:
        r2 = np.square(r[::stride], dtype=np.float64)
        keep = finite & (r2 <= limit)
        bin_of = which[keep]
        counts += np.bincount(bin_of, minlength=n_bins)
        sums += np.bincount(bin_of, weights=r2[keep], minlength=n_bins)
        level_sums += np.bincount(bin_of, weights=w_s[keep], minlength=n_bins)
    use = counts >= NOISE_LEVEL_MIN_SAMPLES
    levels = level_sums[use] / counts[use]
    variances = sums[use] / counts[use] / 4.0
    counts = counts[use]
    if levels.size < 3 or np.ptp(levels) <= 0 or np.any(variances <= 0):
        return flat, 0.0
    x, v, weight = levels, variances, counts / np.square(variances)
    xm = float(np.sum(weight * x) / np.sum(weight))
    vm = float(np.sum(weight * v) / np.sum(weight))
    b = float(np.sum(weight * (x - xm) * (v - vm)) / np.sum(weight * (x - xm) ** 2))
    if not np.isfinite(b) or b <= 0:
        return flat, 0.0
    a = vm - b * xm
    mean_var = float(np.mean(np.maximum(a + b * wf, QUANTISATION_NOISE_DN ** 2)))
    scale = flat / mean_var if mean_var > 0 else 1.0
    return float(a * scale), float(b * scale)


def noise_at_level(model: tuple[float, float], level_dn: np.ndarray) -> np.ndarray:
    """Each pixel's frame noise (DN, rounding included) at its brightness *level_dn* (white - dark, DN)
    by the line (a, b) of :func:`noise_by_level`; never below the rounding's 1/sqrt(12) DN."""
    a, b = model
    var = a + b * np.asarray(level_dn, dtype=np.float64)
    return np.sqrt(np.maximum(var, QUANTISATION_NOISE_DN ** 2))


def _map_halves(pool, fn, items) -> list:
    """``[fn(x) for x in items]`` with the first half of the items done on *pool* (an executor, or None)
    beside the rest: each item's arithmetic is the same on any thread, so the same values."""
    items = list(items)
    half = len(items) // 2 if pool is not None else 0
    first = pool.submit(lambda: [fn(x) for x in items[:half]]) if half else None
    rest = [fn(x) for x in items[half:]]
    return (first.result() if first is not None else []) + rest


def _block_lstsq(samples: list, first_blocks: dict | None = None) -> np.ndarray:
    """:func:`_robust_lstsq` of the joint fit without forming its (mostly zero) design matrix.

    *samples*: per set (own rows (m, n_k), shared rows (4, n_k), residuals (n_k,)). The unknowns are every
    set's own coefficients then the four shared ones; the normal equations are assembled block by block
    from each set's own and shared rows (einsum's loops, no BLAS), refitted without residuals beyond 5
    trimmed standard deviations like :func:`_robust_lstsq`.

    The first round keeps every sample, so each set's sums there do not depend on the other sets:
    *first_blocks* (a dict the caller keeps while its samples live) keeps them between fits of different
    groups of the same sets (the same sums, so the same bits).
    """
    m = samples[0][0].shape[0]
    n_own = m * len(samples)
    keeps = [np.ones(r.size, dtype=bool) for _, _, r in samples]
    coef = np.zeros(n_own + 4)
    for round_ in range(3):
        first = round_ == 0
        gram = np.zeros((n_own + 4, n_own + 4))
        rhs = np.zeros(n_own + 4)
        for j, ((own, shared, r), keep) in enumerate(zip(samples, keeps)):
            a = slice(m * j, m * (j + 1))
            blocks = None if first_blocks is None or not first else first_blocks.get(id(r))
            if blocks is None:
                # (row-major copies: numpy's boolean indexing along the second axis returns column-major
                # arrays, on which einsum's sums run several times slower)
                o, sh, y = ((own, shared, r) if keep.all() else
                            (np.ascontiguousarray(own[:, keep]), np.ascontiguousarray(shared[:, keep]), r[keep]))
                blocks = (np.einsum("in,jn->ij", o, o, optimize=False), np.einsum("in,jn->ij", o, sh, optimize=False),
                          np.einsum("in,jn->ij", sh, sh, optimize=False), np.einsum("in,n->i", o, y, optimize=False),
                          np.einsum("in,n->i", sh, y, optimize=False))
                if first and first_blocks is not None:
                    first_blocks[id(r)] = blocks
            oo, cross, ss, oy, sy = blocks
            gram[a, a] = oo
            gram[a, n_own:] = cross
            gram[n_own:, a] = cross.T
            gram[n_own:, n_own:] += ss
            rhs[a] = oy
            rhs[n_own:] += sy
        coef = np.linalg.solve(gram, rhs)
        res = [minus_models(r, own, coef[m * j:m * (j + 1)], shared, coef[n_own:])
               for j, (own, shared, r) in enumerate(samples)]
        all_res = np.concatenate(res)
        limit = 5.0 * max(trimmed_std(all_res), 0.5)
        new_keeps = [np.abs(rr) <= limit for rr in res]
        if all(np.array_equal(a, b) for a, b in zip(new_keeps, keeps)) or \
                sum(int(k.sum()) for k in new_keeps) < (n_own + 4) * 3:
            break
        keeps = new_keeps
    return coef


def _robust_lstsq(design: np.ndarray, r: np.ndarray, rounds: int = 3, stride: bool = True) -> np.ndarray:
    """Least squares of r on the rows of *design* (k, N), refitted without residuals beyond 5 trimmed
    standard deviations (the pixels a half-drawn frame spoils), on a fixed stride of the points."""
    d, y = (design[:, :: max(1, -(-r.size // MAX_NOISE_SAMPLES))], _stride(r)) if stride else (design, r)
    keep = np.ones(y.size, dtype=bool)
    coef = np.zeros(design.shape[0])
    for _ in range(rounds):
        dk, yk = np.ascontiguousarray(d[:, keep]), y[keep]        # (row-major: see _block_lstsq)
        # Normal equations by einsum's own loops: no BLAS call sees pixel-length data (determinism).
        gram = np.einsum("in,jn->ij", dk, dk, optimize=False)
        coef = np.linalg.solve(gram, np.einsum("in,n->i", dk, yk, optimize=False))
        res = minus_models(y, d, coef)
        new_keep = np.abs(res) <= 5.0 * max(trimmed_std(res), 0.5)
        if np.array_equal(new_keep, keep) or new_keep.sum() < design.shape[0] * 3:
            break
        keep = new_keep
    return coef


@dataclass(frozen=True)
class UnwrapResult:
    """Screen positions along one axis.

    Attributes
    ----------
    position_m : array
        Position u along the axis from the left (x) or bottom (y) edge, metres, in [0, L); NaN where
        invalid.
    valid : bool array
    coarse_out_of_range, disagreements, edge_guard : int
        Pixels dropped because the coarsest position fell outside [0, L), because two successive
        positions disagreed by more than a quarter of the finer period, or because they lay within the
        guard band of a screen edge.
    """

    position_m: np.ndarray
    valid: np.ndarray
    coarse_out_of_range: int
    disagreements: int
    edge_guard: int


def unwrap_positions(phases: list[np.ndarray] | tuple[np.ndarray, ...], periods, length_m: float,
                     position_sigma_m: np.ndarray | float = 0.0, guard_sigmas: float = 4.0) -> UnwrapResult:
    """Temporal unwrapping, coarse to fine, into screen positions (docs/conventions.md#unwrapping).

    Parameters
    ----------
    phases : sequence of arrays
        Wrapped phases in [0, 2 pi), one per period count, coarse first.
    periods : sequence of float
        Increasing period counts p_1 < p_2 < ... (cycles across ``length_m``).
    length_m : float
        Active extent L along the axis, metres.
    position_sigma_m : array or float
        Position noise of the finest phase per pixel (metres); sets the edge guard band when every
        period is a whole number.
    guard_sigmas : float
        Guard band half-width in units of ``position_sigma_m`` (at least 4: docs/conventions.md#unwrapping).

    Returns
    -------
    UnwrapResult
    """
    periods = [float(p) for p in periods]
    if len(phases) != len(periods) or not periods:
        raise ValueError(f"need one phase per period, got {len(phases)} phases for periods {periods}")
    if any(b <= a for a, b in zip(periods, periods[1:])) or periods[0] <= 0:
        raise ValueError(f"periods must be positive and increasing, got {periods}")
    if not (np.isfinite(length_m) and length_m > 0):
        raise ValueError(f"length_m must be a positive length, got {length_m}")
    if guard_sigmas < 4.0:
        raise ValueError(f"guard_sigmas must be at least 4 (docs/conventions.md#unwrapping), got {guard_sigmas}")
    big_l = float(length_m)
    whole = all(abs(p - round(p)) < 1e-12 for p in periods)
    from .kernels import unwrap

    shape = np.shape(phases[0])
    sigma = np.asarray(position_sigma_m, dtype=np.float64)
    if sigma.ndim > 0:
        sigma = np.broadcast_to(sigma, shape)
    u, valid, coarse_bad, disagree, near_edge = unwrap(phases, periods, big_l, whole, float(guard_sigmas),
                                                       sigma if sigma.ndim > 0 else float(sigma))
    return UnwrapResult(u.reshape(shape), valid.reshape(shape), coarse_bad, disagree, near_edge)


def position_sigma_m(modulation_dn: np.ndarray, noise_dn: float, finest_periods: float,
                     length_m: float) -> np.ndarray:
    """Position noise (metres) of the finest phase: L / (2 pi p) * sigma / (sqrt(2) b).

    With four steps, sin and cos estimates each carry noise sqrt(2) sigma against an amplitude 2b, so
    the phase noise is sigma / (sqrt(2) b) radians.
    """
    b = np.maximum(modulation_dn, 1e-9, dtype=np.float64)
    scale = length_m / (TWO_PI * finest_periods) * noise_dn
    if np.ndim(b) == 0:
        return scale / (np.sqrt(2.0) * b)
    b *= np.sqrt(2.0)                           # in place: the same values as scale / (sqrt(2) b)
    return np.divide(scale, b, out=b)
