"""The daily radiometric calibration, on any camera and display (the method paper's "Camera calibration",
Andraka et al. 2009; docs/calibration.md).

It sees the hardware only through the :class:`~sofast_station.devices.protocols.Display` (uniform screens,
``Pattern("uniform", command=v)``, and its ``settle_s``) and :class:`~sofast_station.devices.protocols.Camera`
(exposure, gain, grab) protocols. The steps, in order:

1. **Active pixels**: dark and full-white frames at the longest allowed exposure and the minimum gain,
   with a generous settle; a pixel is active when white - dark exceeds ``mask_threshold_dn``.
2. **Display latency**: with no settle, the screen is switched between dark and white and the frames
   that still show the previous image are counted (the largest count over ``latency_repeats`` changes).
   The settle time is that many frame intervals plus one refresh period; the rest of the routine, and the
   station afterwards, use it.
3. **Exposure**: flicker-safe exposures are whole numbers k of display refresh periods (an LCD's light is
   modulated at its refresh rate; only whole periods integrate the modulation away). The longest k up to
   ``max_exposure_periods`` whose full white, at the minimum gain, stays at or below the target
   (``target_percentile`` of the active pixels at most ``target_dn``, at most ``max_saturated_fraction``
   saturated), found by binary search over k. "Unsaturated" is taken in this sense, which leaves the gain
   step room to reach the target.
4. **Gain**: binary search (geometric) for the gain at which full white reads ``target_dn`` at
   ``target_percentile`` of the active pixels with under ``max_saturated_fraction`` of them saturated,
   to a bracket ``gain_step`` wide; the result is the bracket's geometric middle. Every full-white
   measurement here and in step 3 averages ``search_frames`` frames, and its percentile is taken after a
   ``percentile_smoothing_px`` box mean within the active pixels, so that it measures the signal and not
   the temporal noise (which would raise the 99.5th percentile by a few DN); saturation is counted on
   the raw frames. Our cameras are monochrome; a colour camera would repeat the search per channel
   (white balance), which the Camera protocol does not expose.
5. **Dark level** at the chosen settings: the whole frame's mean (the reference for the drift check).
6. **Ramp**: uniform screens at commands 0, ``ramp_step``, ..., 255; the mean response of the active pixels
   (and of their dimmest tenth, for the record), and the saturated fraction at each. Each level averages
   enough frames (``frames_per_level`` to ``max_frames_per_level``) for its mean to be known to
   ``ramp_noise_dn``, judged from how much the full-white mean varied from frame to frame in step 4
   (room light and flicker move the whole image together; averaging pixels does not remove that).
7. **Top and floor**: the top is the highest command not saturated and still rising; the floor is the
   lowest command from which the response rises at every step up to the top by more than
   ``floor_rise_fraction`` of the mean step (and more than three times the noise of a step).
8. **Fit**: a polynomial of ``fit_order`` (11; the paper uses 7, see :class:`RadiometricSettings`) in the
   command over floor..top, least squares, in the Chebyshev basis; if it is not increasing everywhere on
   that range, the same polynomial fitted with its derivative constrained positive (SLSQP); if that fails
   too, a monotone piecewise-cubic (PCHIP) through the isotonic regression of the data. The record says
   which.
9. **Lookup table**: level 0 is the response to command 0 (measured), level 1 the fitted response at the
   top; ``lut(level) = command / 255`` inverts the fit, so fringes drawn from ``floor_level`` to
   ``max_level`` (= 1) through it are linear in camera counts. Below the floor the table runs linearly to
   command 0 (never used by fringes).

Each step is a function of its own: ``_active_pixels`` (1), ``_display_latency`` (2),
``_flicker_safe_exposure`` (3), ``_gain_for_target`` and ``_frames_per_level`` (4), ``_ramp`` (6),
:func:`find_top_and_floor` (7), :func:`fit_monotone_response` (8) and :func:`build_lut` (9), all driving the
devices through ``_Rig``. :func:`calibrate_radiometric` runs them in order and returns the result;
:func:`save_radiometric` writes the dated record and its PNG plot under ``data_dir``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import uniform_filter
from scipy.optimize import minimize

from ..fringes import Pattern
from .errors import CalibrationError
from .records import RadiometricRecord, load_radiometric
from .settings import RadiometricSettings
from .store import write_record

log = logging.getLogger(__name__)

#: Fewer active pixels than this: nothing meaningful responds to the display.
MIN_ACTIVE_PIXELS = 100


# -- fitting (pure functions) -------------------------------------------------------------------------
def isotonic_increasing(y: np.ndarray) -> np.ndarray:
    """Least-squares non-decreasing sequence closest to *y* (pool-adjacent-violators)."""
    blocks: list[list[float]] = []          # [mean, weight]
    for v in np.asarray(y, dtype=np.float64):
        blocks.append([float(v), 1.0])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            m2, w2 = blocks.pop()
            m1, w1 = blocks.pop()
            blocks.append([(m1 * w1 + m2 * w2) / (w1 + w2), w1 + w2])
    return np.concatenate([np.full(int(w), m) for m, w in blocks])


@dataclass(frozen=True)
class ResponseFit:
    """A response curve fitted over [lo, hi] (commands), increasing there.

    Attributes
    ----------
    method : str
        ``"polynomial"``, ``"polynomial-constrained"`` or ``"pchip-isotonic"``.
    order : int
        Polynomial order (3 for PCHIP pieces).
    domain : (float, float)
        Commands the fit covers.
    coefficients : list of float
        Chebyshev coefficients on the domain mapped to [-1, 1] (polynomials), else empty.
    knots, values : list of float
        PCHIP knots (commands) and values (DN), else empty.
    """

    method: str
    order: int
    domain: tuple[float, float]
    coefficients: list = field(default_factory=list)
    knots: list = field(default_factory=list)
    values: list = field(default_factory=list)

    def __call__(self, command) -> np.ndarray:
        """Response, DN, at *command* (within the domain)."""
        v = np.asarray(command, dtype=np.float64)
        if self.method == "pchip-isotonic":
            return PchipInterpolator(self.knots, self.values, extrapolate=True)(v)
        return np.polynomial.Chebyshev(self.coefficients, domain=list(self.domain))(v)

    def to_dict(self) -> dict:
        return {"method": self.method, "order": self.order, "domain": list(self.domain),
                "coefficients": list(self.coefficients), "knots": list(self.knots), "values": list(self.values)}

    @classmethod
    def from_dict(cls, d: dict) -> "ResponseFit":
        return cls(d["method"], int(d["order"]), tuple(d["domain"]), list(d.get("coefficients", [])),
                   list(d.get("knots", [])), list(d.get("values", [])))


def _increasing(fit: ResponseFit, lo: float, hi: float, n: int = 4096) -> bool:
    grid = np.linspace(lo, hi, n)
    return bool(np.all(np.diff(fit(grid)) > 0))


def fit_monotone_response(commands: np.ndarray, response_dn: np.ndarray, order: int = 7) -> ResponseFit:
    """Fit the response over the given points, increasing over their range.

    Parameters
    ----------
    commands : (n,) array
        Display commands, increasing (floor..top).
    response_dn : (n,) array
        Mean active response at each, DN.
    order : int
        Polynomial order; at most n // 2 (two points per coefficient).

    Returns
    -------
    ResponseFit
        Least-squares polynomial if it increases over the range; else the polynomial with its derivative
        constrained positive on a grid; else PCHIP through the isotonic regression.
    """
    v = np.asarray(commands, dtype=np.float64)
    r = np.asarray(response_dn, dtype=np.float64)
    if v.ndim != 1 or v.shape != r.shape or v.size < 3 or np.any(np.diff(v) <= 0):
        raise ValueError("commands must be an increasing 1-D array of at least 3 points matching response_dn")
    order = int(max(1, min(order, v.size // 2)))
    lo, hi = float(v[0]), float(v[-1])
    cheb = np.polynomial.Chebyshev.fit(v, r, order, domain=[lo, hi])
    fit = ResponseFit("polynomial", order, (lo, hi), [float(c) for c in cheb.coef])
    if _increasing(fit, lo, hi):
        return fit
    log.info("the %d-order response polynomial is not increasing over commands %g..%g: constraining it", order, lo, hi)
    t = (v - lo) / (hi - lo) * 2 - 1
    a = np.polynomial.chebyshev.chebvander(t, order)
    grid = np.linspace(-1, 1, 256)
    d = np.stack([np.polynomial.chebyshev.chebval(grid, np.polynomial.chebyshev.chebder(np.eye(order + 1)[k]))
                  for k in range(order + 1)], axis=1)
    eps = 1e-4 * (r[-1] - r[0]) / 2
    scale = max(float(np.abs(r).max()), 1.0)
    res = minimize(lambda c: 0.5 * np.sum((a @ c - r / scale) ** 2), cheb.coef / scale,
                   jac=lambda c: a.T @ (a @ c - r / scale), method="SLSQP",
                   constraints=[{"type": "ineq", "fun": lambda c: d @ c - eps / scale, "jac": lambda c: d}],
                   options={"maxiter": 500, "ftol": 1e-12})
    if res.success:
        fit = ResponseFit("polynomial-constrained", order, (lo, hi), [float(c) * scale for c in res.x])
        if _increasing(fit, lo, hi):
            return fit
    log.info("the constrained polynomial did not converge to an increasing curve: monotone PCHIP instead")
    iso = isotonic_increasing(r)
    iso = iso + np.linspace(0.0, 1e-6 * max(r[-1] - r[0], 1e-3), iso.size)     # strictly increasing
    return ResponseFit("pchip-isotonic", 3, (lo, hi), [], [float(x) for x in v], [float(y) for y in iso])


def find_top_and_floor(commands: np.ndarray, response_dn: np.ndarray, saturated_fraction: np.ndarray,
                       max_saturated_fraction: float, floor_rise_fraction: float,
                       step_noise_dn: float = 0.0) -> tuple[int, int, float]:
    """Indices of the top and the floor of a ramp, and the rise a step needs to count as rising (DN).

    The top is the highest command at most ``max_saturated_fraction`` saturated, lowered while the step
    into it does not rise; the floor the lowest command from which every step up to the top rises by more
    than ``max(floor_rise_fraction * mean step, 3 * step_noise_dn)``.

    Raises
    ------
    CalibrationError
        No unsaturated command, or the response does not rise over at least three steps.
    """
    r = np.asarray(response_dn, dtype=np.float64)
    ok = np.flatnonzero(np.asarray(saturated_fraction) <= max_saturated_fraction)
    if ok.size == 0:
        raise CalibrationError("every ramp level is saturated: the gain search went wrong; lower the maximum gain "
                               "(--gain-max G, or gain_max in [calibration.routine] of the station file)")
    top = int(ok.max())
    mean_step = (r[top] - r[0]) / max(top, 1)
    rise_min = max(floor_rise_fraction * mean_step, 3.0 * step_noise_dn, 1e-9)
    rises = np.diff(r)
    while top > 0 and rises[top - 1] <= rise_min:
        top -= 1
    floor = top
    while floor > 0 and rises[floor - 1] > rise_min:
        floor -= 1
    if top - floor < 3:
        raise CalibrationError(f"the response rises over only {top - floor} ramp steps (commands "
                               f"{commands[floor]}..{commands[top]}): is the screen reflected onto the camera?")
    return top, floor, float(rise_min)


def build_lut(fit: ResponseFit, dark_dn: float, floor_command: float, top_command: float,
              size: int = 1024) -> tuple[np.ndarray, float, float]:
    """The linearising lookup table from a fitted response.

    Level 0 is the response to command 0 (*dark_dn*), level 1 the fitted response at the top.

    Returns
    -------
    lut : (size,) array
        Command / 255 as a function of level 0..1, non-decreasing.
    floor_level, max_level : float
        Levels of the floor command and of the top (1).
    """
    top_dn = float(fit(top_command))
    span = top_dn - dark_dn
    if not span > 0:
        raise CalibrationError(f"the fitted response at the top ({top_dn:.2f} DN) is not above the dark response "
                               f"({dark_dn:.2f} DN)")
    grid_v = np.linspace(floor_command, top_command, 16384)
    grid_r = np.maximum.accumulate(fit(grid_v))
    floor_level = float(np.clip((grid_r[0] - dark_dn) / span, 0.0, 0.999))
    levels = np.linspace(0.0, 1.0, int(size))
    above = levels >= floor_level
    lut = np.empty(levels.size)
    lut[above] = np.interp(dark_dn + levels[above] * span, grid_r, grid_v) / 255.0
    lut[~above] = (levels[~above] / floor_level * floor_command / 255.0) if floor_level > 0 else 0.0
    lut = np.clip(np.maximum.accumulate(lut), 0.0, 1.0)
    return lut, floor_level, 1.0


# -- the routine --------------------------------------------------------------------------------------
@dataclass
class RadiometricResult:
    """What the routine found (before it is written as a record).

    Attributes
    ----------
    exposure_s, gain : float
    exposure_periods : int
    lut : (N,) array
    floor_level, max_level : float
    dark_level_dn : float
        Whole-frame mean with the screen dark, DN.
    latency_frames : int
    settle_s : float
    refresh_hz : float
    curve : dict
        Measurements, fit and search history (JSON data).
    active_mask : (H, W) bool array
    fit : ResponseFit
    """

    exposure_s: float
    gain: float
    exposure_periods: int
    lut: np.ndarray
    floor_level: float
    max_level: float
    dark_level_dn: float
    latency_frames: int
    settle_s: float
    refresh_hz: float
    curve: dict
    active_mask: np.ndarray
    fit: ResponseFit

    def record(self, record_id: str, created: str, source: str) -> RadiometricRecord:
        return RadiometricRecord(record_id, created, source, self.lut, self.floor_level, self.max_level,
                                 self.exposure_s, self.gain, dark_level_dn=self.dark_level_dn,
                                 latency_frames=self.latency_frames, settle_s=self.settle_s,
                                 refresh_hz=self.refresh_hz, curve=self.curve)


class _Rig:
    """The display and camera as the routine drives them: averaged grabs, settings, statistics."""

    def __init__(self, display, camera, settings: RadiometricSettings):
        self.display, self.camera, self.s = display, camera, settings
        self.exposure_s = self.gain = None
        self.grabs = 0

    def set_settle(self, seconds: float) -> None:
        # ``settle_s`` is not part of the Display protocol; both backends have it. Without it the latency
        # is counted on top of the display's own settle time.
        if hasattr(self.display, "settle_s"):
            self.display.settle_s = float(seconds)
        elif not getattr(self, "_warned_settle", False):
            self._warned_settle = True
            log.warning("%s has no settle_s: the display latency is measured on top of its own settle time",
                        type(self.display).__name__)

    def set_camera(self, exposure_s: float, gain: float) -> None:
        if exposure_s != self.exposure_s:
            self.camera.set_exposure(exposure_s)
        if gain != self.gain:
            self.camera.set_gain(gain)
        changed = (exposure_s, gain) != (self.exposure_s, self.gain)
        self.exposure_s, self.gain = exposure_s, gain
        if changed:
            for _ in range(self.s.discard_frames):
                self.grab()

    def show(self, command: int) -> None:
        self.display.show(Pattern("uniform", command=int(command)))

    def grab(self) -> np.ndarray:
        self.grabs += 1
        return self.camera.grab()

    def frames(self, n: int | None = None) -> np.ndarray:
        n = self.s.frames_per_level if n is None else n
        return np.stack([self.grab() for _ in range(n)])

    def white_stats(self, mask: np.ndarray) -> dict:
        """Full-white statistics of the active pixels (the screen must show white).

        The percentile is taken of the signal, not of its noise: the frames' mean, smoothed over
        ``percentile_smoothing_px`` within the active pixels (the temporal noise of a single pixel would
        otherwise push the upper percentiles up by a few DN). Saturation is counted on the raw frames.
        """
        frames = self.frames(self.s.search_frames)
        mean = frames.mean(axis=0)
        smooth = smooth_within(mean, mask, self.s.percentile_smoothing_px)
        raw = frames[:, mask]
        return {"percentile_dn": float(np.percentile(smooth[mask], self.s.target_percentile)),
                "saturated_fraction": float(np.mean(raw >= self.s.saturation_dn)),
                "mean_dn": float(mean[mask].mean()),
                "frame_means_dn": [float(m) for m in raw.mean(axis=1, dtype=np.float64)], "white": mean}


def smooth_within(image: np.ndarray, mask: np.ndarray, size_px: int) -> np.ndarray:
    """Box mean of *image* over a ``size_px`` square, using only pixels inside *mask* (normalised convolution)."""
    if size_px <= 1:
        return np.asarray(image, dtype=np.float64)
    weight = uniform_filter(mask.astype(np.float64), size_px, mode="constant")
    total = uniform_filter(np.where(mask, image, 0.0).astype(np.float64), size_px, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(weight > 0, total / np.maximum(weight, 1e-12), 0.0)


def _measure_latency(rig: _Rig, mask: np.ndarray, dark_dn: float, white_dn: float) -> tuple[int, list[int], float]:
    """Frames still showing the previous image after a change, largest over the repeats; frame interval."""
    s = rig.s
    rig.set_settle(0.0)
    counts, intervals = [], []
    target_white = True
    for _ in range(s.latency_repeats):
        target_white = not target_white if counts else False      # white is on the screen now: go dark first
        level, other = (white_dn, dark_dn) if target_white else (dark_dn, white_dn)
        rig.show(255 if target_white else 0)
        t_prev = time.perf_counter()
        for n in range(s.latency_max_frames + 1):
            mean = float(rig.grab()[mask].mean(dtype=np.float64))
            now = time.perf_counter()
            intervals.append(now - t_prev)
            t_prev = now
            if abs(mean - level) < abs(mean - other):
                counts.append(n)
                break
        else:
            raise CalibrationError(f"the display change was not seen within {s.latency_max_frames} frames: is the "
                                   "display showing what it is asked (right monitor, not asleep)?")
    return max(counts), counts, float(np.median(intervals)) if intervals else 0.0


def _active_pixels(rig: _Rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 1: the pixels that see the display, from a dark and a full-white frame at the brightest the
    routine may use (the longest exposure, the minimum gain, a generous settle).

    Returns
    -------
    (mask, dark, white): the active pixels (bool, camera size) and the two mean frames, DN.
    """
    s = rig.s
    rig.set_settle(s.initial_settle_s)
    rig.set_camera(s.max_exposure_periods * s.refresh_period_s, s.gain_min)
    rig.show(0)
    dark = rig.frames().mean(axis=0)
    rig.show(255)
    white = rig.frames().mean(axis=0)
    mask = (white - dark) > s.mask_threshold_dn
    n_active = int(mask.sum())
    if n_active < MIN_ACTIVE_PIXELS:
        raise CalibrationError(f"only {n_active} pixels respond to the display by more than {s.mask_threshold_dn:g} DN "
                               f"at {s.max_exposure_periods} refresh periods and gain {s.gain_min:g}: is the reference "
                               "mirror in the fixture, the lens cap off, the display on?")
    return mask, dark, white


@dataclass
class Latency:
    """Step 2's answer: how long the display takes to show a new image.

    Attributes
    ----------
    frames : int
        Frames that still show the previous image after a change (the largest over the repeats).
    counts : list of int
        That count for each change.
    frame_interval_s : float
        Time between two grabs, seconds.
    settle_s : float
        The settle time the routine and the station use from now on: ``frames`` frame intervals plus one
        refresh period, seconds.
    """

    frames: int
    counts: list
    frame_interval_s: float
    settle_s: float


def _display_latency(rig: _Rig, mask: np.ndarray, dark0: np.ndarray, white0: np.ndarray) -> Latency:
    """Step 2: the display's latency at one refresh period (the finest flicker-safe time step), or at the
    brightest settings when one period shows too little (*dark0*, *white0*: step 1's frames); leaves the
    display's settle time at the measured one."""
    s = rig.s
    period = s.refresh_period_s
    rig.set_settle(s.initial_settle_s)
    rig.set_camera(period, s.gain_min)
    rig.show(0)
    dark_dn = float(rig.frames()[:, mask].mean(dtype=np.float64))
    rig.show(255)
    white_dn = float(rig.frames()[:, mask].mean(dtype=np.float64))
    if white_dn - dark_dn < 2.0:
        rig.set_camera(s.max_exposure_periods * period, s.gain_min)
        dark_dn, white_dn = float(dark0[mask].mean()), float(white0[mask].mean())
    frames, counts, wall_interval = _measure_latency(rig, mask, dark_dn, white_dn)
    frame_interval = max(rig.exposure_s, period, wall_interval)
    settle_s = frames * frame_interval + period
    rig.set_settle(settle_s)
    return Latency(frames, counts, frame_interval, settle_s)


def _white_ok(rig: _Rig, mask: np.ndarray, exposure_s: float, gain: float) -> tuple[bool, dict]:
    """Full white at these settings, and whether it stays at or below the target (percentile and saturation)."""
    s = rig.s
    rig.set_camera(exposure_s, gain)
    st = rig.white_stats(mask)
    return st["percentile_dn"] <= s.target_dn and st["saturated_fraction"] <= s.max_saturated_fraction, st


def _flicker_safe_exposure(rig: _Rig, mask: np.ndarray) -> tuple[int, dict, list[dict]]:
    """Step 3: the longest exposure of whole refresh periods (up to ``max_exposure_periods``) at which full
    white, at the minimum gain, stays at or below the target; binary search over the number of periods.

    Returns
    -------
    (periods, white statistics there, the search's tries as JSON data)
    """
    s = rig.s
    period = s.refresh_period_s
    rig.show(255)
    tries: list[dict] = []
    stats_at: dict[int, dict] = {}

    def exposure_ok(k: int) -> bool:
        ok, st = _white_ok(rig, mask, k * period, s.gain_min)
        stats_at[k] = st
        tries.append({"periods": k, "exposure_s": k * period, "percentile_dn": st["percentile_dn"],
                      "saturated_fraction": st["saturated_fraction"], "ok": ok})
        log.debug("exposure %d period(s): white p%g %.1f DN, %.3f %% saturated", k, s.target_percentile,
                  st["percentile_dn"], 100 * st["saturated_fraction"])
        return ok

    if not exposure_ok(1):
        st = stats_at[1]
        raise CalibrationError(
            f"full white reads {st['percentile_dn']:.0f} DN at the {s.target_percentile:g}th percentile of the active "
            f"pixels ({100 * st['saturated_fraction']:.2f} % saturated) already at one refresh period "
            f"({1e3 * period:.1f} ms) and the minimum gain {s.gain_min:g}: close the lens aperture (or dim the "
            "display)")
    lo, hi = 1, s.max_exposure_periods
    if hi > 1 and exposure_ok(hi):
        lo = hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if exposure_ok(mid):
            lo = mid
        else:
            hi = mid
    return lo, stats_at[lo], tries


def _gain_for_target(rig: _Rig, mask: np.ndarray, exposure_s: float, base: dict) -> tuple[float, dict, list[dict]]:
    """Step 4: the gain at which full white reads the target (geometric binary search to a bracket
    ``gain_step`` wide, then the bracket's geometric middle unless that saturates); *base*: full white at
    the minimum gain (step 3). Leaves the camera at the chosen exposure and gain.

    Returns
    -------
    (gain, {gain: white statistics} of every gain measured, the search's tries as JSON data)
    """
    s = rig.s
    tries: list[dict] = []
    stats: dict[float, dict] = {s.gain_min: base}

    def gain_ok(g: float) -> bool:
        ok, st = _white_ok(rig, mask, exposure_s, g)
        stats[g] = st
        tries.append({"gain": g, "percentile_dn": st["percentile_dn"], "saturated_fraction": st["saturated_fraction"],
                      "ok": ok})
        log.debug("gain %.4f: white p%g %.1f DN, %.3f %% saturated", g, s.target_percentile, st["percentile_dn"],
                  100 * st["saturated_fraction"])
        return ok

    g_lo, g_hi = s.gain_min, None
    if s.gain_max > s.gain_min:
        # A linear first guess (the black level makes it a little high), bracketed by a few steps each way.
        guess = s.gain_min * s.target_dn / max(base["percentile_dn"], 1e-6)
        trial = float(np.clip(guess * (1 + 2 * s.gain_step), s.gain_min, s.gain_max))
        while trial > g_lo:
            if gain_ok(trial):
                g_lo = trial
                if trial >= s.gain_max:
                    break
                trial = min(trial * (1 + 8 * s.gain_step), s.gain_max)
            else:
                g_hi = trial
                break
        if g_hi is not None:
            down = g_hi / (1 + 8 * s.gain_step)
            if down > g_lo and gain_ok(down):
                g_lo = down
            elif down > g_lo:
                g_hi = down
        while g_hi is not None and g_hi / g_lo > 1 + s.gain_step:
            mid = math.sqrt(g_lo * g_hi)
            if gain_ok(mid):
                g_lo = mid
            else:
                g_hi = mid
    gain = g_lo
    if g_hi is not None:
        # The crossing lies in [g_lo, g_hi]: its geometric middle is within half a step of it, unless the
        # middle saturates.
        mid = math.sqrt(g_lo * g_hi)
        rig.set_camera(exposure_s, mid)
        st = rig.white_stats(mask)
        if st["saturated_fraction"] <= s.max_saturated_fraction:
            gain, stats[mid] = mid, st
    rig.set_camera(exposure_s, gain)
    if g_hi is None and s.gain_max > s.gain_min and gain >= s.gain_max:
        log.warning("full white reaches only %.1f DN at the maximum gain %g: open the lens aperture, allow a "
                    "longer exposure (--max-exposure-periods N) or a higher gain (--gain-max G); or set "
                    "max_exposure_periods, gain_max in [calibration.routine] of the station file",
                    stats[gain]["percentile_dn"], s.gain_max)
    return gain, stats, tries


def _frames_per_level(white_stats: list[dict], s: RadiometricSettings) -> tuple[int, float]:
    """How many frames each ramp level averages so that its mean is known to ``ramp_noise_dn``, from how much
    the active pixels' mean varied from frame to frame in the full-white measurements (*white_stats*,
    pooled: room light and flicker move the whole image together, so averaging pixels does not remove it).

    Returns
    -------
    (frames per level, the pooled frame-to-frame standard deviation, DN)
    """
    groups = [np.asarray(st["frame_means_dn"]) for st in white_stats if len(st["frame_means_dn"]) > 1]
    dof = sum(g.size - 1 for g in groups)
    frame_noise = math.sqrt(sum(float(np.sum((g - g.mean()) ** 2)) for g in groups) / dof) if dof else 0.0
    frames = int(np.clip(math.ceil((frame_noise / s.ramp_noise_dn) ** 2), s.frames_per_level,
                         max(s.frames_per_level, s.max_frames_per_level)))
    if frame_noise / math.sqrt(frames) > s.ramp_noise_dn:
        log.warning("the ramp levels will be known to %.2f DN only (ramp_noise_dn %.2f DN with at most %d frames): "
                    "steady the room light, or allow more frames (--max-frames N, or max_frames_per_level in "
                    "[calibration.routine] of the station file)", frame_noise / math.sqrt(frames), s.ramp_noise_dn,
                    frames)
    return frames, frame_noise


@dataclass
class Ramp:
    """Step 6's measurements, one entry per command of the ramp.

    Attributes
    ----------
    commands : list of int
        0, ``ramp_step``, ..., 255.
    mean_dn, dim_dn : list of float
        Mean response of the active pixels, and of their dimmest tenth (for the record), DN.
    saturated : list of float
        Fraction of the active pixels' samples at or above ``saturation_dn``.
    step_noise_dn : float
        Standard deviation of the difference of two levels' means, DN (from their frame-to-frame scatter).
    """

    commands: list
    mean_dn: list
    dim_dn: list
    saturated: list
    step_noise_dn: float


def ramp_commands(step: int) -> list[int]:
    """The ramp's display commands: 0, *step*, 2 *step*, ... and 255."""
    commands = list(range(0, 256, step))
    return commands if commands[-1] == 255 else commands + [255]


def _ramp(rig: _Rig, mask: np.ndarray, response_white: np.ndarray, frames_per_level: int, say) -> Ramp:
    """Step 6: uniform screens at every ``ramp_step``-th command, each averaged over *frames_per_level* frames;
    the dimmest tenth of the active pixels is chosen by their full-white response *response_white*."""
    s = rig.s
    n_active = int(mask.sum())
    order = np.argsort(response_white[mask], kind="stable")
    dim = np.zeros(n_active, dtype=bool)
    dim[order[:max(1, n_active // 10)]] = True
    commands = ramp_commands(s.ramp_step)
    mean_dn, dim_dn, sat, noise = [], [], [], []
    for i, v in enumerate(commands):
        rig.show(v)
        frames = rig.frames(frames_per_level)
        active = frames[:, mask].astype(np.float32)
        per_frame = active.mean(axis=1, dtype=np.float64)
        mean_dn.append(float(per_frame.mean()))
        dim_dn.append(float(active[:, dim].mean(dtype=np.float64)))
        sat.append(float(np.mean(active >= s.saturation_dn)))
        if per_frame.size > 1:
            noise.append(float(np.std(per_frame, ddof=1) / math.sqrt(per_frame.size)))
        if (i + 1) % 13 == 0 or i + 1 == len(commands):
            say("ramp: %d/%d levels (command %d: %.1f DN)", i + 1, len(commands), v, mean_dn[-1])
    step_noise = math.sqrt(2.0) * float(np.median(noise)) if noise else 0.0
    return Ramp(commands, mean_dn, dim_dn, sat, step_noise)


def calibrate_radiometric(display, camera, settings: RadiometricSettings = RadiometricSettings(),
                          progress: Callable[[str], None] | None = None) -> RadiometricResult:
    """Run the daily radiometric calibration (module docstring, steps 1-9) on a display and a camera.

    Parameters
    ----------
    display : Display
        Shows ``Pattern("uniform", command=v)``; its ``settle_s`` (seconds) is set to 0 while the latency
        is timed and to the measured settle time afterwards (left so).
    camera : Camera
        Exposure (seconds), gain (linear, the camera's unit) and grab; left at the chosen settings.
    settings : RadiometricSettings
    progress : callable, optional
        Called with a line of text at each step (also logged at INFO).

    Returns
    -------
    RadiometricResult

    Raises
    ------
    CalibrationError
        Nothing responds to the display, full white is too bright even at one refresh period and the
        minimum gain, the display change is never seen, or the response does not rise.
    """
    s = settings
    period = s.refresh_period_s
    rig = _Rig(display, camera, s)
    t_start = time.perf_counter()

    def say(message: str, *args) -> None:
        text = message % args if args else message
        log.info("%s", text)
        if progress is not None:
            progress(text)

    mask, dark0, white0 = _active_pixels(rig)
    n_active = int(mask.sum())
    say("active pixels: %d (%.1f %% of the frame), white - dark > %g DN", n_active, 100 * n_active / mask.size,
        s.mask_threshold_dn)

    latency = _display_latency(rig, mask, dark0, white0)
    say("display latency: %d frame(s) (%s over %d changes, frame interval %.1f ms): settle %.1f ms", latency.frames,
        ", ".join(map(str, latency.counts)), len(latency.counts), 1e3 * latency.frame_interval_s,
        1e3 * latency.settle_s)

    k, base, exposure_tries = _flicker_safe_exposure(rig, mask)
    exposure_s = k * period
    say("exposure: %d refresh period(s) = %.2f ms (white p%g %.1f DN at gain %g)", k, 1e3 * exposure_s,
        s.target_percentile, base["percentile_dn"], s.gain_min)

    gain, gain_stats, gain_tries = _gain_for_target(rig, mask, exposure_s, base)
    final = gain_stats[gain]
    frame_means = np.asarray(final["frame_means_dn"])
    flicker = float(np.std(frame_means) / np.mean(frame_means)) if frame_means.size > 1 else 0.0
    say("gain: %.4f (search step %.2f %%): white p%g %.1f DN, %.3f %% saturated", gain, 100 * s.gain_step,
        s.target_percentile, final["percentile_dn"], 100 * final["saturated_fraction"])
    frames_per_level, frame_noise = _frames_per_level(list(gain_stats.values()), s)

    # 5. dark level at the chosen settings (the reference of the station's drift check)
    rig.show(0)
    dark_frames = rig.frames()
    dark_level_dn = float(dark_frames.mean(dtype=np.float64))

    say("ramp: %d levels, %d frame(s) each (the active mean varies by %.2f DN from frame to frame)",
        len(ramp_commands(s.ramp_step)), frames_per_level, frame_noise)
    ramp = _ramp(rig, mask, final["white"] - dark_frames.mean(axis=0), frames_per_level, say)
    commands, commands_a, mean_a = ramp.commands, np.asarray(ramp.commands, dtype=np.float64), np.asarray(ramp.mean_dn)

    # 7. top and floor, 8. fit, 9. table
    top, floor, rise_min = find_top_and_floor(commands_a, mean_a, np.asarray(ramp.saturated),
                                              s.max_saturated_fraction, s.floor_rise_fraction, ramp.step_noise_dn)
    if top < len(commands) - 1:
        log.warning("the response stops rising or saturates above command %d: fringes will stop there (max_level); "
                    "check the gain", commands[top])
    fit = fit_monotone_response(commands_a[floor:top + 1], mean_a[floor:top + 1], s.fit_order)
    residual = mean_a[floor:top + 1] - fit(commands_a[floor:top + 1])
    lut, floor_level, max_level = build_lut(fit, mean_a[0], commands[floor], commands[top], s.lut_size)
    say("response: floor at command %d (level %.4f), top at %d; %s fit of order %d, residual RMS %.3f DN "
        "(max %.3f DN)", commands[floor], floor_level, commands[top], fit.method, fit.order,
        float(np.sqrt(np.mean(residual ** 2))), float(np.abs(residual).max()))

    curve = {
        "commands": commands, "response_dn": ramp.mean_dn, "response_dim_tenth_dn": ramp.dim_dn,
        "saturated_fraction": ramp.saturated, "step_noise_dn": ramp.step_noise_dn, "rise_min_dn": rise_min,
        "floor_command": commands[floor], "top_command": commands[top], "dark_active_dn": ramp.mean_dn[0],
        "fit": fit.to_dict(), "fit_residual_rms_dn": float(np.sqrt(np.mean(residual ** 2))),
        "fit_residual_max_dn": float(np.abs(residual).max()),
        "active_pixels": n_active, "exposure_periods": k,
        "white_percentile_dn": final["percentile_dn"], "white_saturated_fraction": final["saturated_fraction"],
        "white_frame_to_frame": flicker, "frame_noise_dn": frame_noise, "frames_per_level": frames_per_level,
        "latency_counts": latency.counts, "frame_interval_s": latency.frame_interval_s,
        "search": {"exposure": exposure_tries, "gain": gain_tries},
        "grabs": rig.grabs, "duration_s": time.perf_counter() - t_start,
        "settings": dataclasses.asdict(s),
    }
    return RadiometricResult(exposure_s=exposure_s, gain=gain, exposure_periods=k, lut=lut, floor_level=floor_level,
                             max_level=max_level, dark_level_dn=dark_level_dn, latency_frames=latency.frames,
                             settle_s=latency.settle_s, refresh_hz=s.refresh_hz, curve=curve, active_mask=mask, fit=fit)


# -- the record and its plot ----------------------------------------------------------------------------
def save_radiometric(data_dir: str | Path, result: RadiometricResult, source: str,
                     plot: bool = True, station: dict | None = None) -> RadiometricRecord:
    """Write *result* as a new dated record under ``data_dir/calibration/radiometric/`` (and its PNG plot);
    *station*: the identity of the station it is made on.

    Returns
    -------
    RadiometricRecord
        As read back from the file (``path`` set).
    """
    path, _ = write_record(data_dir, "radiometric",
                           lambda rid, created: result.record(rid, created, source).to_dict(curve=True),
                           station=station)
    record = load_radiometric(path)
    if plot:
        try:
            plot_radiometric(record, path.with_suffix(".png"))
        except ImportError as exc:          # matplotlib is optional for the station itself
            log.warning("no plot of %s: %s (pip install matplotlib)", record.record_id, exc)
    return record


def plot_radiometric(record: RadiometricRecord, out: str | Path) -> Path:
    """PNG of the measured and fitted response, the fit residuals and the lookup table."""
    c = record.curve or {}
    if "commands" not in c:
        raise ValueError(f"record {record.record_id} holds no measured response to plot")
    v = np.asarray(c["commands"], dtype=float)
    r = np.asarray(c["response_dn"], dtype=float)
    fit = ResponseFit.from_dict(c["fit"])
    lo, hi = fit.domain
    grid = np.linspace(lo, hi, 512)
    fig = Figure(figsize=(11, 4), layout="constrained")
    FigureCanvasAgg(fig)
    ax1, ax2, ax3 = fig.subplots(1, 3)
    ax1.plot(v, r, "o", ms=3, label="measured (active pixels)")
    ax1.plot(grid, fit(grid), "-", label=f"fit: {fit.method}, order {fit.order}")
    ax1.axvline(c["floor_command"], color="0.5", ls="--", lw=0.8, label=f"floor {c['floor_command']}")
    ax1.axvline(c["top_command"], color="0.5", ls=":", lw=0.8, label=f"top {c['top_command']}")
    ax1.set(xlabel="display command", ylabel="camera response, DN", title="end-to-end response")
    ax1.legend(fontsize=7)
    sel = (v >= lo) & (v <= hi)
    ax2.axhline(0, color="0.7", lw=0.8)
    ax2.plot(v[sel], r[sel] - fit(v[sel]), "o-", ms=3)
    ax2.set(xlabel="display command", ylabel="measured - fit, DN",
            title=f"residuals (RMS {c.get('fit_residual_rms_dn', float('nan')):.3f} DN)")
    levels = np.linspace(0, 1, record.lut.size)
    ax3.plot(levels, 255 * record.lut)
    ax3.axvline(record.floor_level, color="0.5", ls="--", lw=0.8)
    ax3.set(xlabel="linear response level", ylabel="display command", title="lookup table")
    fig.suptitle(f"{record.record_id}: exposure {1e3 * record.exposure_s:.2f} ms, gain {record.gain:.3f}, "
                 f"latency {record.latency_frames} frame(s), dark {record.dark_level_dn or 0:.2f} DN", fontsize=9)
    out = Path(out)
    fig.savefig(out, dpi=110)
    return out


def summary_text(record: RadiometricRecord, path: Path | None = None) -> str:
    """A readable summary of a radiometric record."""
    c = record.curve or {}
    lines = [f"Radiometric calibration {record.record_id} ({record.created})"]
    if path is not None:
        png = path.with_suffix(".png")
        lines.append(f"  record: {path}" + (f"  plot: {png}" if png.exists() else ""))
    periods = c.get("exposure_periods")
    lines.append(f"  exposure: {1e3 * record.exposure_s:.3f} ms" + (f" ({periods} refresh period(s) at "
                                                                      f"{record.refresh_hz:g} Hz)" if periods else ""))
    if c:
        pct = c.get("settings", {}).get("target_percentile", 99.5)
        lines.append(f"  gain: {record.gain:.4f}; full white p{pct:g} {c['white_percentile_dn']:.1f} DN, "
                     f"{100 * c['white_saturated_fraction']:.3f} % saturated, {c['active_pixels']} active pixels")
        lines.append(f"  floor: command {c['floor_command']} (level {record.floor_level:.4f}); top: command "
                     f"{c['top_command']}; fit {c['fit']['method']} order {c['fit']['order']}, residual RMS "
                     f"{c['fit_residual_rms_dn']:.3f} DN")
    else:
        lines.append(f"  gain: {record.gain:.4f}; floor level {record.floor_level:.4f}, max level "
                     f"{record.max_level:.4f}")
    if record.latency_frames is not None:
        lines.append(f"  display latency: {record.latency_frames} frame(s) -> settle "
                     f"{1e3 * (record.settle_s or 0):.1f} ms")
    if record.dark_level_dn is not None:
        lines.append(f"  dark level: {record.dark_level_dn:.2f} DN")
    if "duration_s" in c:
        lines.append(f"  {c['grabs']} frames in {c['duration_s']:.1f} s")
    return "\n".join(lines)
