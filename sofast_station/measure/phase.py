"""Phase, modulation and temporal unwrapping (docs/conventions.md#phase, #unwrapping).

Four frames with shifts d_k = k pi/2 show I_k = a + b cos(phi - d_k), so
I_0 - I_2 = 2b cos(phi), I_1 - I_3 = 2b sin(phi) and I_0 + I_2 - I_1 - I_3 = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
    # Integer counts convert exactly to float32, and float32 phase resolves 1e-6 rad: ample, and faster.
    work = np.float32 if np.issubdtype(frames.dtype, np.integer) and frames.itemsize <= 2 else np.float64
    i0, i1, i2, i3 = (frames[k].astype(work) for k in range(4))
    s = i1 - i3
    c = i0 - i2
    phase = _wrap_atan2(np.arctan2(s, c))
    modulation = 0.5 * np.hypot(s, c)
    consistency = (i0 + i2) - (i1 + i3)
    return phase, modulation, consistency


def intensity_noise_dn(consistency: np.ndarray) -> float:
    """Robust estimate of the per-frame intensity noise (DN) from consistency residuals.

    The residual I_0 + I_2 - I_1 - I_3 of four independent frames with noise sigma has standard
    deviation 2 sigma; the median absolute deviation makes the estimate immune to the few pixels a
    half-drawn frame spoils. Never below 8-bit quantisation noise.
    """
    r = np.asarray(consistency, dtype=np.float64).ravel()
    if r.size > 400_000:     # a fixed stride keeps the estimate deterministic and fast
        r = r[:: r.size // 200_000]
    if r.size == 0:
        return QUANTISATION_NOISE_DN
    mad = np.median(np.abs(r - np.median(r)))
    return float(max(1.4826 * mad / 2.0, QUANTISATION_NOISE_DN))


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
    u = big_l * np.asarray(phases[0], dtype=np.float64) / (TWO_PI * periods[0])
    coarse_bad = ~((u >= 0.0) & (u < big_l))
    disagree = np.zeros(u.shape, dtype=bool)
    for phi, p in zip(phases[1:], periods[1:]):
        phi = np.asarray(phi, dtype=np.float64)
        k = np.round((TWO_PI * p * u / big_l - phi) / TWO_PI)
        u_fine = big_l * (phi + TWO_PI * k) / (TWO_PI * p)
        disagree |= np.abs(u_fine - u) > big_l / (4.0 * p)
        u = u_fine
    whole = all(abs(p - round(p)) < 1e-12 for p in periods)
    if whole:
        # Every pattern repeats with period L: 0 and L look alike, so the finest phase decides the side.
        u = np.mod(u, big_l)
        u[u >= big_l] = 0.0
        coarse_bad[:] = False
        guard = guard_sigmas * np.asarray(position_sigma_m, dtype=np.float64)
        near_edge = (u < guard) | (u > big_l - guard)
    else:
        coarse_bad |= ~((u >= 0.0) & (u < big_l))
        near_edge = np.zeros(u.shape, dtype=bool)
    disagree &= ~coarse_bad
    near_edge &= ~(coarse_bad | disagree)
    valid = ~(coarse_bad | disagree | near_edge)
    position = np.where(valid, u, np.nan)
    return UnwrapResult(position, valid, int(coarse_bad.sum()), int(disagree.sum()), int(near_edge.sum()))


def position_sigma_m(modulation_dn: np.ndarray, noise_dn: float, finest_periods: float,
                     length_m: float) -> np.ndarray:
    """Position noise (metres) of the finest phase: L / (2 pi p) * sigma / (sqrt(2) b).

    With four steps, sin and cos estimates each carry noise sqrt(2) sigma against an amplitude 2b, so
    the phase noise is sigma / (sqrt(2) b) radians.
    """
    b = np.maximum(np.asarray(modulation_dn, dtype=np.float64), 1e-9)
    return length_m / (TWO_PI * finest_periods) * noise_dn / (np.sqrt(2.0) * b)
