"""The twin's camera images for the glare's camera route: the sun through a neutral density filter, and a
glare source (a mirror showing the sun), with their truth.

A disc of angular radius ``radius_px`` pixels centred at ``centre_px`` (column, row), uniform or limb-darkened
(``1 - u (1 - sqrt(1 - (r/R)^2))``, the classic linear law with coefficient u), each pixel the mean of 4 x 4
samples, over a sky level, blurred by the lens (a Gaussian of ``blur_px``), with shot and read noise,
quantised to ``bits`` (12 by default) and clipped there: ``peak`` above 1 overexposes it. A flat mirror of
reflectivity rho seen through the same camera shows the same disc, rho times as bright: :func:`mirror_image`.
Nothing here is shared with ``sofast_station.field``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def disc_radiance(shape: tuple, centre_px, radius_px: float, limb: float = 0.0) -> np.ndarray:
    """The disc's relative radiance per pixel (1 at the centre), 4 x 4 samples per pixel."""
    rows, cols = shape
    out = np.zeros(shape)
    for dy in (np.arange(4) + 0.5) / 4 - 0.5:
        for dx in (np.arange(4) + 0.5) / 4 - 0.5:
            yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
            q = ((xx + dx - centre_px[0]) ** 2 + (yy + dy - centre_px[1]) ** 2) / radius_px ** 2
            inside = q <= 1.0
            out += np.where(inside, 1.0 - limb * (1.0 - np.sqrt(np.clip(1.0 - q, 0.0, 1.0))), 0.0)
    return out / 16.0


def camera_image(radiance: np.ndarray, rng: np.random.Generator, *, peak: float = 0.6, sky: float = 0.02,
                 blur_px: float = 0.8, gain_e_per_dn: float = 4.0, read_noise_dn: float = 2.0,
                 bits: int = 12, scale: float = 1.0) -> np.ndarray:
    """Counts of *radiance* (relative) on the camera: ``scale`` x radiance at ``peak`` of full scale for 1, over
    the sky's level, blurred, noisy, quantised and clipped (uint16)."""
    full = 2 ** bits - 1
    signal = (sky + peak * scale * radiance) * full
    if blur_px > 0:
        signal = ndimage.gaussian_filter(signal, blur_px)
    counts = rng.poisson(np.clip(signal, 0, None) * gain_e_per_dn) / gain_e_per_dn
    counts = counts + read_noise_dn * rng.standard_normal(signal.shape)
    return np.clip(np.round(counts), 0, full).astype(np.uint16)


def mirror_image(sun_radiance: np.ndarray, reflectivity: float, rng: np.random.Generator, **camera) -> np.ndarray:
    """A flat mirror larger than the sun's image, photographed with the sun image's camera and settings: the
    sun's disc, *reflectivity* times as bright."""
    return camera_image(sun_radiance, rng, scale=reflectivity, **camera)
