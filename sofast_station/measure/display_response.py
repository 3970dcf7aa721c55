"""The display's response checked on every facet's own frames: the fringes' mean level against the white's.

The radiometric calibration's lookup table makes the fringes linear in camera counts: a fringe drawn at level
y (``floor_level`` to ``max_level``, 0 the response to command 0, 1 the response at the top) is seen at
``D + y (W - D)`` at a pixel whose dark (command 0) frame reads D and whose white frame reads W. Over the
``phase_steps`` quarter-period shifts of a set the cosine cancels at every pixel, so the mean of
``(I_k - D) / (W - D)`` is ``(floor_level + max_level) / 2`` wherever the facet reflects the screen, whatever
its reflectance, slope, blur or the room's light (the dark frame holds the room's light and the display's floor;
the ratio cancels the reflectance and the vignetting). A display whose response moved since the table was
made (its gamma or picture mode changed, its backlight's spectrum aged unevenly, a warm panel) draws the
fringes at other levels: the mean moves, and the fringes are no longer sinusoids, which bends every phase by
their third harmonic. The check costs a few array means over a subsample of the facet's pixels.

What it cannot see: a response that moved symmetrically about the mean level (no change of the mean), and the
display's geometry (a screen that moved in space: the reference check and the fixture marks see that, docs/
reliability.md#the-station-checks-itself).

Pure functions of arrays; no I/O.
"""

from __future__ import annotations

import numpy as np

#: At most this many pixels (a regular grid over the frame) enter the means: the per-pixel ratio's noise (a few
#: per cent) leaves its median over the facet's share of them known to a few 1e-4, below the frames' common
#: flicker (up to 0.003 on the twin), and the check costs about a millisecond at any resolution.
MAX_PIXELS = 5000


def fringe_mean_levels(frames: np.ndarray, slices: dict, min_span_dn: float, saturation_dn: float = 254.0,
                       max_pixels: int = MAX_PIXELS) -> dict:
    """The fringes' mean level relative to the dark and white frames, per phase-step set.

    Parameters
    ----------
    frames : (n, rows, columns) array
        A cycle's frames in capture order (:meth:`~sofast_station.fringes.FringeSet.patterns`): dark (command 0),
        white (command 255), then the phase-step sets; DN.
    slices : dict
        ``{"x": [slice, ...], "y": [...]}``: each set's frame indices (:meth:`FringeSet.slices`).
    min_span_dn : float
        Pixels whose white exceeds their dark by less are left out (the background, the facet's edge), DN.
    saturation_dn : float
        Pixels whose white or any fringe frame reaches this are left out (a clipped white reads low), DN.
    max_pixels : int
        Every k-th pixel of every k-th row enters, k the smallest that leaves at most this many: the work stays
        bounded at full resolution.

    Returns
    -------
    dict
        ``levels``: per set (``"x0"``, ``"x1"``, ``"y0"``, ...) the median over the pixels of
        ``mean_k (I_k - D) / (W - D)``; ``level``: the median of the sets'; ``spread``: half the range of the
        sets' levels; ``n_pixels``: how many pixels entered (0: none usable, the levels None).
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] < 3:
        raise ValueError(f"frames must be (n >= 3, rows, columns), got shape {frames.shape}")
    # a regular grid of every step-th pixel holds at most about max_pixels; copied once, (n, pixels)
    step = max(1, int(np.ceil(np.sqrt(frames.shape[1] * frames.shape[2] / float(max_pixels)))))
    grid = np.ascontiguousarray(frames[:, ::step, ::step]).reshape(frames.shape[0], -1)
    dark = grid[0].astype(np.float32)
    white = grid[1].astype(np.float32)
    span = white - dark
    usable = np.flatnonzero((span > float(min_span_dn)) & (white < float(saturation_dn)))
    levels: dict = {}
    if usable.size == 0:
        return {"levels": levels, "level": None, "spread": None, "n_pixels": 0}
    names = [f"{axis}{i}" for axis in ("x", "y") for i in range(len(slices.get(axis, [])))]
    index = np.array([np.arange(frames.shape[0])[sl] for axis in ("x", "y") for sl in slices.get(axis, [])])
    stack = grid[:, usable][index]                               # (sets, steps, pixels)
    ok = ~np.any(stack >= saturation_dn, axis=(0, 1))            # a clipped fringe reads low
    n = int(np.count_nonzero(ok))
    if n == 0:
        return {"levels": levels, "level": None, "spread": None, "n_pixels": 0}
    means = stack[:, :, ok].mean(axis=1, dtype=np.float32)       # (sets, pixels)
    ratio = (means - dark[usable][ok]) / span[usable][ok]
    values = np.median(ratio, axis=1)
    levels = {name: float(v) for name, v in zip(names, values)}
    return {"levels": levels, "level": float(np.median(values)),
            "spread": float(0.5 * (values.max() - values.min())), "n_pixels": n}


def expected_mean_level(floor_level: float, max_level: float) -> float:
    """The fringes' mean level the lookup table draws: halfway between its floor and its top (module docstring)."""
    return 0.5 * (float(floor_level) + float(max_level))
