"""Capture helpers: the sequence with its four-step check and retake, and the crop (its box is the job's: job/).

The station analyses exactly the frames it archives: the capture is cropped to the facet's region
(plus a margin for the edge and corner windows), and the analysis runs on the crop restored into an
otherwise black frame, so a data dump, which keeps only the crop, reprocesses to the same bits.
"""

from __future__ import annotations

import logging

import numpy as np

from ..fringes import FringeSet
from ..measure.mask import facet_region
from ..measure.phase import frame_noise, phase_and_modulation

log = logging.getLogger(__name__)

def crop(frames: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    r0, c0, r1, c1 = box
    return np.ascontiguousarray(frames[:, r0:r1, c0:c1])


def restore(cropped: np.ndarray, box: tuple[int, int, int, int], shape: tuple[int, int]) -> np.ndarray:
    """The full frames: the crop in place, zero elsewhere."""
    r0, c0, r1, c1 = box
    out = np.zeros((cropped.shape[0], *shape), dtype=cropped.dtype)
    out[:, r0:r1, c0:c1] = cropped
    return out


def inconsistent_fractions(frames: np.ndarray, fringes: FringeSet, idx: np.ndarray, sigmas: float = 6.0
                           ) -> dict[tuple[str, int], float]:
    """Per four-step set, the fraction of the given pixels failing I0 + I2 = I1 + I3 (a frame captured
    before the display finished showing it), on a fixed stride of at most 20,000 pixels.

    The noise is estimated from all sets pooled: a half-drawn frame spoils its own set's residuals
    systematically, and judged by its own scatter it would look like noise.
    """
    sample = idx[:: max(1, idx.size // 20_000)]
    flat = frames.reshape(frames.shape[0], -1)
    sets = {(axis, k): phase_and_modulation(flat[sl][:, sample])
            for axis, slices in fringes.slices().items() for k, sl in enumerate(slices)}
    # A display response left nonlinear adds a phase-following harmonic to every residual: removed here,
    # so that it is reported by the analysis as what it is, not retaken as half-drawn frames.
    noise = frame_noise(*([s[i] for s in sets.values()] for i in range(3)),
                        level=flat[1, sample].astype(np.float32) - flat[0, sample].astype(np.float32))
    limit = sigmas * 2.0 * noise.frame_noise_dn + 1.0
    return {key: float(np.mean(np.abs(c) > limit)) for key, c in zip(sets, noise.residuals)}


def capture_sequence(display, camera, fringes: FringeSet, threshold_dn: float, retake_limit: float = 0.05,
                     timeout_s: float = 2.0, progress=None) -> tuple[np.ndarray, list[str]]:
    """Show every pattern and grab a frame; retake once any four-step set that fails its check.

    Returns the frames (n, rows, columns) and notes on retakes (for the record).
    """
    patterns = fringes.patterns()
    frames = None
    for i, pattern in enumerate(patterns):
        display.show(pattern)
        frame = camera.grab(timeout_s)
        if frames is None:
            frames = np.empty((len(patterns), *frame.shape), dtype=frame.dtype)
        frames[i] = frame
        if progress:
            progress(i + 1, len(patterns))
    notes = []
    if not any(fringes.slices().values()):     # a fixed pattern's capture: no four-step set to check
        return frames, notes
    idx = np.flatnonzero(facet_region(frames[0], frames[1], threshold_dn))
    if idx.size < 100:
        return frames, notes
    before = inconsistent_fractions(frames, fringes, idx)
    retaken = [key for key, frac in before.items() if frac > retake_limit]
    for axis, k in retaken:
        sl = fringes.slices()[axis][k]
        log.warning("%s set %d fails the four-step check at %.1f %% of the facet: retaking it", axis, k + 1,
                    100 * before[(axis, k)])
        for j in range(sl.start, sl.stop):
            display.show(patterns[j])
            frames[j] = camera.grab(timeout_s)
    if retaken:
        after = inconsistent_fractions(frames, fringes, idx)
        notes = [f"{axis} set {k + 1} retaken ({100 * before[(axis, k)]:.1f} % -> {100 * after[(axis, k)]:.1f} % "
                 "inconsistent)" for axis, k in retaken]
    return frames, notes
