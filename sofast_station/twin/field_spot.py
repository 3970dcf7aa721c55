"""The twin's spot of a heliostat on the tower's target, and the photograph a beam characterisation system
(BCS) takes of it: the truth ``field spot`` is checked against.

**The spot** (:func:`spot_flux`): the twin's heliostat (:class:`~sofast_station.twin.field.FieldHeliostat`,
its facets at their true poses: design canting, then each facet's canting error) reflects the sun onto the
target plane. Each facet's true surface is ``z = (kx x^2 + ky y^2) / 4`` in its design frame (kx, ky its true
focal powers; 0: flat), sampled on a jittered grid over its outline; each sample reflects rays drawn uniformly
over the sun's disc (half-angle 4.65 mrad, a pillbox), each carrying ``DNI rho cos(theta_i) dA`` over the rays,
by the law of reflection ``r = d - 2 (d.n) n``; where a ray meets the plane is binned into the map. The plane's
axes are docs/field.md's (written again here): ``u_x = z x n / |z x n|`` (level, to the right seen from the
field), ``u_y = n x u_x``, metres from the aim point; the map's cell (j, i) covers y in [y0 + j w, y0 + (j+1) w),
x likewise.

**The photograph** (:func:`bcs_photo`): a rectified view of the target (columns along u_x, rows down along
-u_y, ``pixel_m`` metres per pixel, the aim point at pixel ``aim_px``), each pixel the mean of 3 x 3 samples
of the map (bilinear) on a Lambertian target (brightness proportional to irradiance) over the sunlit
target's own level, blurred by the lens (a Gaussian of ``blur_px``), with shot noise (``gain_e_per_dn``) and
read noise, quantised to ``bits``. :func:`gaussian_flux` gives a map whose figures are closed forms: a round
Gaussian of sigma s holds 90 % of its power within ``s sqrt(2 ln 10)`` of its centre.

Nothing here is shared with ``sofast_station.field`` or ``optics``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from .field import FieldHeliostat
from .station import rotation_zyx

SUN_HALF_ANGLE_RAD = 4.65e-3


def plane_axes(normal) -> tuple[np.ndarray, np.ndarray]:
    """(u_x, u_y) of a target plane with unit *normal* (module docstring)."""
    n = np.asarray(normal, dtype=np.float64)
    x = np.array([-n[1], n[0], 0.0])           # z x n
    x /= np.linalg.norm(x)
    return x, np.cross(n, x)


def tracking(position_m, aim_m, sun) -> tuple[float, float]:
    """(azimuth, elevation) rad of the normal halfway between the sun and the aim point seen from *position_m*."""
    t = np.asarray(aim_m, float) - np.asarray(position_m, float)
    n = np.asarray(sun, float) / np.linalg.norm(sun) + t / np.linalg.norm(t)
    n /= np.linalg.norm(n)
    return math.atan2(n[0], n[1]), math.asin(n[2])


def spot_flux(heliostat: FieldHeliostat, aim_m, normal, sun, *, curvature_per_m=None, dni_w_m2: float = 900.0,
              reflectivity: float = 0.94, samples: int = 3000, rays: int = 16, half_width_m: float = 2.5,
              cells: int = 121, seed: int = 0) -> np.ndarray:
    """The true irradiance map (W/m^2) on the target plane through *aim_m* with *normal* (module docstring).

    *curvature_per_m*: {label: (kx, ky)} of each facet's true focal powers; missing: its design's 1/f.
    """
    rng = np.random.default_rng(seed)
    s = np.asarray(sun, float) / np.linalg.norm(sun)
    n_t = np.asarray(normal, float) / np.linalg.norm(normal)
    ux, uy = plane_axes(n_t)
    aim = np.asarray(aim_m, float)
    r_h, o_h = heliostat.rotation, heliostat.origin_m
    w = 2.0 * half_width_m / cells
    out = np.zeros((cells, cells))
    # an orthonormal pair about the ray towards the sun, for the disc's directions
    a = np.cross(s, [0.0, 0.0, 1.0] if abs(s[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(s, a)
    for f, err in zip(heliostat.ensemble.facets, heliostat.canting_errors_mrad):
        kx, ky = (curvature_per_m or {}).get(f.label, (1.0 / f.design.focal_length_m,) * 2)
        outline = f.design.outline_m
        lo, hi = outline.min(axis=0), outline.max(axis=0)
        side = int(math.ceil(math.sqrt(samples)))
        gx = lo[0] + (np.arange(side)[None, :] + rng.random((side, side))) * (hi[0] - lo[0]) / side
        gy = lo[1] + (np.arange(side)[:, None] + rng.random((side, side))) * (hi[1] - lo[1]) / side
        x, y = gx.ravel(), gy.ravel()
        inside = _inside(x, y, outline)
        x, y = x[inside], y[inside]
        cell_area = (hi[0] - lo[0]) * (hi[1] - lo[1]) / side ** 2
        local = np.stack([x, y, 0.25 * (kx * x * x + ky * y * y)])
        nrm = np.stack([-0.5 * kx * x, -0.5 * ky * y, np.ones_like(x)])
        nrm /= np.linalg.norm(nrm, axis=0)
        # the facet's true pose: its canting error (R_z R_y R_x) about its middle, then its design pose
        cx, cy = (float(v) for v in f.design.centroid_m)
        mid = np.array([cx, cy, 0.25 * (kx * cx * cx + ky * cy * cy)])
        e = rotation_zyx(*(1e-3 * np.asarray(err)))
        to_field = r_h @ f.rotation
        p = (to_field @ (mid[:, None] + e @ (local - mid[:, None]))) + (r_h @ f.position_m + o_h)[:, None]
        nf = to_field @ (e @ nrm)
        cos_i = np.clip(nf.T @ s, 0.0, None)
        # each sample stands for its cell of the facet's x-y plane: on the surface, that over the normal's z
        power = dni_w_m2 * reflectivity * cos_i * (cell_area / np.abs(nrm[2])) / rays
        for _ in range(rays):
            rho = SUN_HALF_ANGLE_RAD * np.sqrt(rng.random(x.size))
            phi = 2.0 * math.pi * rng.random(x.size)
            towards = (s[:, None] + np.tan(rho) * (np.cos(phi) * a[:, None] + np.sin(phi) * b[:, None]))
            d = -towards / np.linalg.norm(towards, axis=0)
            r = d - 2.0 * np.sum(d * nf, axis=0) * nf
            t = np.einsum("i,ij->j", n_t, aim[:, None] - p) / (n_t @ r)
            hit = p + t * r - aim[:, None]
            hx, hy = ux @ hit, uy @ hit
            i = np.floor((hx + half_width_m) / w).astype(int)
            j = np.floor((hy + half_width_m) / w).astype(int)
            ok = (t > 0) & (i >= 0) & (i < cells) & (j >= 0) & (j < cells)
            np.add.at(out, (j[ok], i[ok]), power[ok])
    return out / (w * w)


def _inside(x: np.ndarray, y: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule: which points lie inside the polygon."""
    inside = np.zeros(x.size, dtype=bool)
    px, py = poly[:, 0], poly[:, 1]
    for k in range(len(poly)):
        x1, y1, x2, y2 = px[k], py[k], px[k - 1], py[k - 1]
        cross = ((y1 > y) != (y2 > y)) & (x < (x2 - x1) * (y - y1) / np.where(y2 == y1, 1.0, y2 - y1) + x1)
        inside ^= cross
    return inside


def map_centroid_radius(flux: np.ndarray, half_width_m: float, fraction: float = 0.9) -> tuple[float, float, float]:
    """The map's centroid (x, y) and the radius about it holding *fraction* of its power, by sorting its cells
    (the twin's own reading of its truth)."""
    cells = flux.shape[0]
    w = 2.0 * half_width_m / cells
    c = -half_width_m + (np.arange(cells) + 0.5) * w
    xx, yy = np.meshgrid(c, c)
    total = flux.sum()
    cx, cy = float((flux * xx).sum() / total), float((flux * yy).sum() / total)
    r = np.hypot(xx - cx, yy - cy).ravel()
    order = np.argsort(r)
    cum = np.cumsum(flux.ravel()[order]) / total
    k = int(np.searchsorted(cum, fraction))
    return cx, cy, float(np.interp(fraction, cum[max(k - 1, 0):k + 1], r[order][max(k - 1, 0):k + 1]))


def gaussian_flux(centre_m, sigma_m: float, half_width_m: float, cells: int, peak_w_m2: float = 1e5) -> np.ndarray:
    """A round Gaussian irradiance map centred at *centre_m* (x, y): its 90 % radius is sigma sqrt(2 ln 10)."""
    w = 2.0 * half_width_m / cells
    c = -half_width_m + (np.arange(cells) + 0.5) * w
    xx, yy = np.meshgrid(c, c)
    return peak_w_m2 * np.exp(-((xx - centre_m[0]) ** 2 + (yy - centre_m[1]) ** 2) / (2.0 * sigma_m ** 2))


def bcs_photo(flux: np.ndarray, half_width_m: float, shape: tuple, pixel_m: float, aim_px, rng: np.random.Generator,
              *, level: float = 0.06, peak: float = 0.7, blur_px: float = 1.0, gain_e_per_dn: float = 4.0,
              read_noise_dn: float = 2.0, bits: int = 12) -> np.ndarray:
    """The photograph of the lit target (module docstring): (rows, columns) uint16 counts of *bits*.

    *level*: the unlit target's brightness, *peak*: the spot's brightest, as shares of full scale (> 1 for an
    overexposed photo)."""
    rows, cols = shape
    full = 2 ** bits - 1
    cells = flux.shape[0]
    w = 2.0 * half_width_m / cells
    sub = (np.arange(3) - 1.0) / 3.0
    acc = np.zeros(shape)
    cc, rr = np.meshgrid(np.arange(cols, dtype=float), np.arange(rows, dtype=float))
    for dr in sub:
        for dc in sub:
            x = (cc + dc - aim_px[0]) * pixel_m
            y = -(rr + dr - aim_px[1]) * pixel_m
            fi = (x + half_width_m) / w - 0.5
            fj = (y + half_width_m) / w - 0.5
            acc += ndimage.map_coordinates(flux, [fj, fi], order=1, mode="constant", cval=0.0)
    acc /= 9.0
    if blur_px > 0:
        acc = ndimage.gaussian_filter(acc, blur_px)
    signal = (level + (peak - level) * acc / acc.max()) * full
    electrons = rng.poisson(np.clip(signal, 0, None) * gain_e_per_dn) / gain_e_per_dn
    counts = electrons + read_noise_dn * rng.standard_normal(shape)
    return np.clip(np.round(counts), 0, full).astype(np.uint16)
