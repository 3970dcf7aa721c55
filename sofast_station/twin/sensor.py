"""The camera's sensor: exposure and gain, the display's flicker, read and shot noise, the knee, rounding.

:class:`TwinSensor` takes the light each pixel gathers as linear DN at the reference exposure and gain 1
(:class:`~sofast_station.twin.render.TwinRenderer`) and reads it out as a uint8 frame: DN = black level +
(exposure / reference exposure) x gain x (the light, times the flicker factor); read noise x gain and shot
noise (variance signal x gain / ``electrons_per_dn``) are added, then the knee, rounding and clipping to
0..255 (:class:`~sofast_station.twin.parameters.TwinOptics`).

A frame is finished in two halves side by side (numpy releases the GIL while it draws and computes), each
with its own generator seeded from the caller's, block of rows by block of rows (a block's float32 working
arrays stay in the core's cache between passes): the sensor noise dominates a frame's cost.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import DisplayError
from .noise import scratch_f32, standard_normal_f32
from .parameters import TwinOptics

#: A captured frame is drawn and finished in blocks of rows of about this many pixels: a block's float32
#: working arrays (a few hundred kB each) stay in the core's cache between passes.
_BLOCK_PX = 96_000

#: The thread that finishes half of every captured frame (shared by all twins of the process).
_FINISHER: ThreadPoolExecutor | None = None
_FINISHER_LOCK = threading.Lock()


def _finisher() -> ThreadPoolExecutor:
    """The one extra thread that finishes half of each frame (created on first use)."""
    global _FINISHER
    with _FINISHER_LOCK:
        if _FINISHER is None:
            _FINISHER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="twin-frame")
        return _FINISHER


def exposure_scale(optics: TwinOptics, exposure_s: float | None = None, gain: float | None = None) -> float:
    """Signal multiplier of an exposure and gain relative to the reference (``white_dn`` holds at 1).

    Parameters
    ----------
    optics : TwinOptics
        Its ``reference_exposure_s``.
    exposure_s : float or None
        Exposure time, seconds; None is ``optics.reference_exposure_s``.
    gain : float or None
        Linear gain factor; None is 1.

    Returns
    -------
    float
        ``(exposure_s / reference_exposure_s) * gain``.

    Raises
    ------
    DisplayError
        If the exposure is not a positive time or the gain not a positive factor.
    """
    exposure = optics.reference_exposure_s if exposure_s is None else float(exposure_s)
    g = 1.0 if gain is None else float(gain)
    if not (math.isfinite(exposure) and exposure > 0):
        raise DisplayError(f"exposure must be a positive time in seconds, got {exposure_s!r}")
    if not (math.isfinite(g) and g > 0):
        raise DisplayError(f"gain must be a positive factor, got {gain!r}")
    return exposure / optics.reference_exposure_s * g


def flicker_factor(optics: TwinOptics, exposure_s: float | None = None, phase: float | None = None) -> float:
    """Mean backlight factor seen by an exposure starting at *phase* of a refresh period.

    The display's light is ``L (1 + m cos(2 pi (f t + phase)))`` (m ``optics.flicker_depth``, f
    ``optics.refresh_hz``); averaged over an exposure of T seconds it is
    ``1 + m (sin(2 pi (phase + f T)) - sin(2 pi phase)) / (2 pi f T)``: exactly 1 when f T is a whole
    number (within 1e-6 periods), otherwise off by up to ``m / (pi f T)`` depending on the phase.

    Parameters
    ----------
    optics : TwinOptics
    exposure_s : float or None
        Exposure time, seconds (None: the reference exposure).
    phase : float or None
        Phase of the refresh cycle at the start of the exposure, in periods (0..1); None is 0.
    """
    exposure = optics.reference_exposure_s if exposure_s is None else float(exposure_s)
    periods = exposure * optics.refresh_hz
    if optics.flicker_depth == 0 or (round(periods) >= 1 and abs(periods - round(periods)) < 1e-6):
        return 1.0
    p0 = 0.0 if phase is None else float(phase)
    two_pi = 2.0 * math.pi
    return 1.0 + optics.flicker_depth * (math.sin(two_pi * (p0 + periods)) - math.sin(two_pi * p0)) / (two_pi * periods)


class TwinSensor:
    """The camera's sensor: reads a frame's linear signal out as uint8 counts.

    Parameters
    ----------
    optics : TwinOptics
        Black level (``camera_offset_dn``), read noise, electrons per DN, knee, reference exposure,
        refresh rate and flicker depth.
    dark_dn : (H, W) float32 array
        The signal of a pixel that gets no light from the display and no ambient light (the renderer's
        ``dn_base``): what a :class:`~sofast_station.twin.render.BoxedSignal` is outside its box. Its noise
        deviation is kept per gain.
    """

    def __init__(self, optics: TwinOptics, dark_dn: np.ndarray):
        self.optics = optics
        self.dark_dn = dark_dn
        self._dark_sigmas: dict = {}        # gain -> noise deviation at the dark level (_dark_sigma)

    def scale(self, exposure_s: float | None = None, gain: float | None = None) -> float:
        """:func:`exposure_scale` of this sensor's optics."""
        return exposure_scale(self.optics, exposure_s, gain)

    def flicker_factor(self, exposure_s: float | None = None, phase: float | None = None) -> float:
        """:func:`flicker_factor` of this sensor's optics."""
        return flicker_factor(self.optics, exposure_s, phase)

    def is_noisy(self, rng: np.random.Generator | None) -> bool:
        """Whether a frame read out with *rng* gets sensor noise (a generator, and read or shot noise)."""
        return rng is not None and (self.optics.read_noise_dn > 0 or self.optics.electrons_per_dn > 0)

    def read_out(self, signal, rng: np.random.Generator | None, gain: float | None = None) -> np.ndarray:
        """The uint8 frame of *signal*: sensor noise, knee, rounding and clipping.

        Parameters
        ----------
        signal : (H, W) float32 array or BoxedSignal
            The linear DN (black level included); an array is changed in place.
        rng : numpy Generator or None
            Source of the noise (:meth:`is_noisy`): two seeds are drawn from it, one per half of the frame,
            each half's noise drawn from its own generator, so the two halves are drawn in parallel and a
            given *rng* state still gives the same frame. None: no noise.
        gain : float or None
            The linear gain the noise scales with; None is 1.
        """
        g = 1.0 if gain is None else float(gain)
        height, width = self.dark_dn.shape
        out = np.empty((height, width), dtype=np.uint8)
        seeds = rng.integers(0, 2**63, size=2) if self.is_noisy(rng) else (None, None)
        if isinstance(signal, np.ndarray):
            job = (self._finish_rows, signal)
        else:
            # The signal is formed, block by block, on the box of pixels that see the screen only: outside
            # it every pixel has its constant dark level (no light, no ambient) and its noise deviation is
            # kept per gain. The same noise draws, the same arithmetic per pixel: the same frame.
            if seeds[0] is None:
                raise ValueError("a boxed signal is read out with noise only")
            job = (self._finish_boxed, signal)
        half = height // 2
        first = _finisher().submit(self._finish, job, out, 0, half, seeds[0], g)
        self._finish(job, out, half, height, seeds[1], g)
        first.result()
        return out

    def _finish(self, job: tuple, out: np.ndarray, a: int, b: int, seed, g: float) -> None:
        """Rows ``a .. b`` of the frame *out*: sensor noise, knee, rounding and clipping, block by block.

        A block of rows (about ``_BLOCK_PX`` pixels) is drawn and finished before the next: its working
        arrays stay in the core's cache from one pass to the next, where a pass over a whole frame would
        run at the speed of memory. The noise comes from a generator seeded with *seed* (None: no noise),
        drawn block after block. *job* is ``(method, *arguments)``: :meth:`_finish_rows` or
        :meth:`_finish_boxed`, called for each block.
        """
        width = out.shape[1]
        step = max(1, _BLOCK_PX // max(width, 1))
        # SFC64: the cheapest of numpy's bit generators per raw word, of the same statistical quality
        gen = None if seed is None else np.random.Generator(np.random.SFC64(int(seed)))
        method, *args = job
        for start in range(a, b, step):
            stop = min(start + step, b)
            noise = None
            if gen is not None:
                n = (stop - start) * width
                noise = standard_normal_f32(gen, n, out=scratch_f32("twin.noise", n)).reshape(stop - start, width)
            method(*args, out, start, stop, noise, g)

    def _finish_rows(self, dn: np.ndarray, out: np.ndarray, a: int, b: int, noise: np.ndarray | None,
                     g: float) -> None:
        """Rows ``a .. b`` of *out* from the frame's linear signal *dn* (changed in place) and their standard
        normal *noise* (None: no noise)."""
        if noise is None:
            self._round(dn[a:b], out[a:b])
        else:
            self._noisy_round(dn[a:b], noise, out[a:b], g)

    def _finish_boxed(self, signal, out: np.ndarray, a: int, b: int, noise: np.ndarray, g: float) -> None:
        """:meth:`_finish_rows` of the rows ``a .. b`` of a :class:`~sofast_station.twin.render.BoxedSignal`:
        the dark level outside its box's rows, the signal's own rows on them; the same noise draws and
        per-pixel arithmetic, so the same counts."""
        width = out.shape[1]
        r0, r1, _, _ = signal.box
        i0, i1 = min(max(r0, a), b), max(min(r1, b), a)          # the box's rows within these rows
        # Whole rows throughout: numpy's passes over a block of whole rows are contiguous, several times
        # faster per pixel than over the strips beside the box.
        sigma = self._dark_sigma(g)
        for lo, hi in ((a, i0), (i1, b)):
            if hi > lo:
                # rows without the box: dn + noise x sigma with dn the dark level, the sum in the other
                # order (the same bits)
                block = noise[lo - a:hi - a]
                block *= sigma[lo:hi] if sigma.ndim else sigma
                block += self.dark_dn[lo:hi]
                self._round(block, out[lo:hi])
        if i1 > i0:
            dn = signal.rows(i0, i1, scratch_f32("twin.box", (i1 - i0, width)))
            self._noisy_round(dn, noise[i0 - a:i1 - a], out[i0:i1], g)

    def _noisy_round(self, dn: np.ndarray, noise: np.ndarray, out: np.ndarray, g: float) -> None:
        """dn + noise x (the noise deviation at dn), then the knee, rounding and clipping into *out* (*dn*
        and *noise* are overwritten)."""
        noise *= self._sigma(dn, g, scratch_f32("twin.sigma", dn.shape))
        dn += noise
        self._round(dn, out)

    def _sigma(self, dn: np.ndarray, g: float, out: np.ndarray) -> np.ndarray:
        """The noise deviation at the signal *dn*, DN: sqrt(read noise^2 x gain^2 + max(dn - black level, 0)
        x gain / ``electrons_per_dn``) (read and shot noise), into *out*; a float32 scalar when there is no
        shot noise.

        Formed as sqrt(max(dn k + (r - b k), r)) with k = gain / electrons per DN, r the read variance and b
        the black level: four passes (the same value as the formula, to float rounding).
        """
        optics = self.optics
        read_var = np.float32((optics.read_noise_dn * g) ** 2)
        if optics.electrons_per_dn <= 0:
            return np.sqrt(read_var)
        k = np.float32(g / optics.electrons_per_dn)
        sigma = np.multiply(dn, k, out=out)
        sigma += np.float32(read_var - k * np.float32(optics.camera_offset_dn))
        np.maximum(sigma, read_var, out=sigma)
        np.sqrt(sigma, out=sigma)
        return sigma

    def _dark_sigma(self, g: float) -> np.ndarray:
        """The noise deviation of every pixel at its dark level (the signal outside a boxed signal's box),
        DN: what :meth:`_sigma` computes there, kept per gain (float32, camera shape; a scalar without shot
        noise)."""
        key = float(g)
        sigma = self._dark_sigmas.get(key)
        if sigma is None:
            sigma = self._sigma(self.dark_dn, g, np.empty(self.dark_dn.shape, dtype=np.float32))
            if sigma.ndim:
                sigma.setflags(write=False)
            self._dark_sigmas[key] = sigma
        return sigma

    def _round(self, dn: np.ndarray, out: np.ndarray) -> None:
        """The knee, then clipping and rounding of *dn* (in place) into the uint8 *out*."""
        optics = self.optics
        if optics.knee_dn is not None:
            knee = np.float32(optics.knee_dn)
            room = np.float32(255.0 - optics.knee_dn)
            over = dn > knee
            dn[over] = knee + room * -np.expm1(-(dn[over] - knee) / room)
        # Clipping to the whole counts 0 and 255 commutes with rounding: clip, then round straight into
        # the uint8 frame (one pass fewer than rounding, clipping and converting; the same counts).
        np.clip(dn, 0, 255, out=dn)
        np.rint(dn, out=out, casting="unsafe")
