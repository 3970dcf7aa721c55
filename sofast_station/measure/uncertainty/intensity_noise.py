"""The random part the capture's own intensity noise explains: per pixel to screen positions
(:func:`~sofast_station.measure.phase.position_sigma_m`), to slopes (the reflection law's derivative) and
through the fits (their covariance); also the slope noise floor of the RMS values.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..metrics import principal_axes, principal_curvatures
from ..pipeline import default_screen
from ..slope_noise import pixel_noise_dn as _pixel_noise_dn
from ..slope_noise import position_sigmas_m, slope_jacobian
from .inputs import RMS_AXES


def _fit_figures(a: float, b: float, e1: float, e2: float) -> dict:
    """The fit's scalar figures as functions of A, B, E1, E2 (for their Jacobian)."""
    e = 0.5 * (e1 + e2)
    (p1, p2), angle = principal_axes(a, b, e)
    k1, k2 = principal_curvatures(a, b, e)
    kx, ky = 4.0 * a, 4.0 * b
    return {("focal_length_x_m",): 1.0 / kx if kx else np.nan, ("focal_length_y_m",): 1.0 / ky if ky else np.nan,
            ("curvature_x_per_m",): kx, ("curvature_y_per_m",): ky, ("twist_mrad_per_m",): 1000.0 * e,
            ("twist_e1_mrad_per_m",): 1000.0 * e1, ("twist_e2_mrad_per_m",): 1000.0 * e2,
            ("principal_focal_lengths_m", 0): np.nan if p1 is None else p1,
            ("principal_focal_lengths_m", 1): np.nan if p2 is None else p2,
            ("principal_curvatures_per_m", 0): k1, ("principal_curvatures_per_m", 1): k2, ("axis_angle_rad",): angle}


def _line_fit_covariance(u: np.ndarray, v: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Covariance of (k0, k1, k2) in s = k0 (u - mean u) + k1 + k2 (v - mean v) fitted by ordinary least
    squares to slopes with independent noise *sigma* per point."""
    uc, vc = u - u.mean(), v - v.mean()
    x = np.stack([uc, np.ones_like(uc), vc])
    m_inv = np.linalg.inv(x @ x.T)
    b = (x * sigma ** 2) @ x.T
    return m_inv @ b @ m_inv


@dataclass
class NoisePropagation:
    """The capture's own noise carried to the figures.

    Attributes
    ----------
    sigma : dict
        ``{path: standard uncertainty}`` of the scalar figures the noise reaches (fit figures, boresight,
        optical tilt, slope RMS values).
    slope_noise_mrad : dict
        ``{"x", "y", "magnitude"}`` the RMS slope (angle) noise the capture's intensity noise explains, mrad.
    slope_noise_u_mrad : dict or None
        ``{"x", "y", "magnitude"}``: its standard uncertainty as the slope noise this capture's points carry,
        mrad (:func:`noise_floor_u`).
    slope_noise_per_dn_mrad : dict or None
        ``{"x", "y", "magnitude"}``: the RMS slope noise per DN of noise in every frame, mrad / DN: what a
        brightness change common to each frame (room light between frames) adds to the floor per DN of its
        standard deviation (:func:`with_frame_brightness`). None where the stage measured its positions'
        noise itself.
    """

    sigma: dict
    slope_noise_mrad: dict
    slope_noise_u_mrad: dict | None = None
    slope_noise_per_dn_mrad: dict | None = None


#: The noise model's own relative standard uncertainty (the noise-against-brightness line, the modulation,
#: the reflection law's derivative, the room light's change between frames taken as uniform): what the noise
#: floor misses of the slope noise a capture's points really carry beyond the points' finite number.
#: Measured (2026-12-06) against the slope noise of three captures of the same twin about their mean, on 40
#: drawn stations of seed 0's population (every kind and edge model; 80 axis values): realized / predicted
#: 0.84-1.34, mean 1.001, RMS of the difference 5.9 %. Checked on 24 stations of seed 1: RMS 6.5 %. Each
#: capture against its own floor and U: :func:`with_frame_brightness`; tests/measure/test_noise_floor.py draws
#: others.
NOISE_FLOOR_MODEL_RELATIVE = 0.06


def noise_floor_u(noise_mrad: float, mean_sigma4: float, n_points: int,
                  relative: float = NOISE_FLOOR_MODEL_RELATIVE) -> float:
    """Standard uncertainty (mrad) of a noise floor *noise_mrad* as the RMS slope noise of the capture's
    *n_points* points: the realized mean square of independent noise with each point's own variance spreads
    by sqrt(2 mean(sigma^4) / N) about the predicted s^2 (*mean_sigma4*, mrad^4), so the RMS by that over 2 s;
    and the model's own *relative* error of s, in quadrature."""
    if not (noise_mrad > 0 and n_points > 0):
        return 0.0
    spread = np.sqrt(2.0 * mean_sigma4 / n_points) / (2.0 * noise_mrad)
    return float(np.hypot(spread, relative * noise_mrad))


def pixel_noise_dn(reduction, take: np.ndarray) -> np.ndarray | float:
    """The frame noise (DN, rounding included) of the region's pixels *take* (indices into the phases'
    arrays), each at its own brightness: :func:`~..slope_noise.pixel_noise_dn` of *reduction*."""
    return _pixel_noise_dn(reduction.phases, getattr(reduction.region, "stack", None), take)


def noise_propagation(reduction, *, fringes, geometry, design, settings, screen=None,
                      max_points: int = 30_000) -> NoisePropagation:
    """Propagate the capture's intensity noise (``Phases.noise_dn``) to slopes and to the fits.

    Position noise per pixel from the finest phase's modulation and the pixel's own frame noise at its
    brightness (:func:`pixel_noise_dn`: shot noise makes the dim pixels at the facet's edges quieter,
    and one noise figure for all over-stated the fits' noise by 5-8 % whenever the facet's edges cut
    through pixels); the slope noise per pixel from the reflection law's derivative with respect to the
    screen position (finite difference with the surface point held); the fits' covariance by
    least-squares propagation of independent per-pixel noise. Done on every n-th valid pixel (about
    *max_points*) and scaled to all of them.
    """
    screen = screen if screen is not None else default_screen(geometry)
    red = reduction
    ok = red.rays.ok
    n_all = int(red.rays.vidx.size)
    step = max(1, n_all // max_points)
    sel = slice(None, None, step)
    take = np.flatnonzero(ok)[sel]          # the pixels of [ok][sel], without gathering every valid pixel first
    # the pixels' own frame noise (DN), kept for the noise floor's part per DN of a brightness change common to
    # a frame (room light); None for a stage that measured its positions' noise itself (a fixed pattern's dots)
    noise_dn = None if getattr(red.phases, "position_sigma_m", None) is not None else pixel_noise_dn(red, take)
    sig_u = position_sigmas_m(red.phases, getattr(red.region, "stack", None), take, fringes,
                              (screen.width_m, screen.height_m), noise_dn=noise_dn)
    # Slopes' derivative with respect to the screen position, surface point held, in the boresight frame.
    points = red.shape.points_m[:, sel]
    s0, gx, gy = slope_jacobian(points, red.shape.boresighted_to_camera.inverse(), screen,
                                red.phases.positions_m["x"][take], red.phases.positions_m["y"][take])
    var = (gx * sig_u["x"]) ** 2 + (gy * sig_u["y"]) ** 2        # (2, n) slope variance
    angle_sig = 1000.0 * np.sqrt(var) / (1.0 + s0 ** 2)          # mrad: the noise floor's
    # A fixed pattern's dots also carry their centroids' model error (fixed.CENTROID_MODEL_PX): independent per
    # dot, so the fits hold it as they hold the noise; the noise floor does not (docs/uncertainty.md).
    model = getattr(red.phases, "position_model_sigma_m", None)
    if model is not None:
        var = var + (gx * model["x"][take]) ** 2 + (gy * model["y"][take]) ** 2
    sig_s = np.sqrt(var)
    noise = {"x": float(np.sqrt(np.mean(angle_sig[0] ** 2))), "y": float(np.sqrt(np.mean(angle_sig[1] ** 2)))}
    noise["magnitude"] = float(np.hypot(noise["x"], noise["y"]))
    x, y = points[0], points[1]
    scale = points.shape[1] / n_all                              # covariance on all points = scale x subset's
    cov_x = _line_fit_covariance(x, y, sig_s[0]) * scale         # (2A, C', E1)
    cov_y = _line_fit_covariance(y, x, sig_s[1]) * scale         # (2B, D', E2)
    fit = red.fits.parabola
    # Jacobian of the fit figures with respect to (A, B, E1, E2); A = k0/2.
    cov = np.diag([cov_x[0, 0] / 4.0, cov_y[0, 0] / 4.0, cov_x[2, 2], cov_y[2, 2]])
    cov[0, 2] = cov[2, 0] = cov_x[0, 2] / 2.0
    cov[1, 3] = cov[3, 1] = cov_y[0, 2] / 2.0
    p0 = np.array([fit.a, fit.b, fit.e1, fit.e2])
    base = _fit_figures(*p0)
    jac = {}
    for j in range(4):
        h = 1e-6 * max(abs(p0[j]), 1e-6)
        hi = _fit_figures(*(p0 + h * np.eye(4)[j]))
        lo = _fit_figures(*(p0 - h * np.eye(4)[j]))
        for k in base:
            jac.setdefault(k, np.zeros(4))[j] = (hi[k] - lo[k]) / (2 * h)
    sigma = {k: float(np.sqrt(max(J @ cov @ J, 0.0))) for k, J in jac.items()}
    # Boresight and optical tilt: the subsample fit's slope at the alignment point (alpha <- s_y, beta <- s_x).
    xa, ya = (float(c) for c in design.alignment_point_m)
    sub = settings.subsample_step
    va = np.array([xa - x.mean(), 1.0, ya - y.mean()])
    vb = np.array([ya - y.mean(), 1.0, xa - x.mean()])
    s_a = (2 * fit.a * xa + fit.c + fit.e * ya, 2 * fit.b * ya + fit.d + fit.e * xa)
    sig_bx = 1000.0 * np.sqrt(vb @ cov_y @ vb * sub) / (1 + s_a[1] ** 2)
    sig_by = 1000.0 * np.sqrt(va @ cov_x @ va * sub) / (1 + s_a[0] ** 2)
    sigma[("boresight_mrad", "x")] = sigma[("optical_tilt_mrad", "x")] = float(sig_bx)
    sigma[("boresight_mrad", "y")] = sigma[("optical_tilt_mrad", "y")] = float(sig_by)
    # Slope RMS values: mean(e^2) with e = t + n has variance (4 mean(t^2) s^2 + 2 mean(sigma^4)) / N, the
    # noise power's own spread from each point's sigma (s^4 only when every point is as noisy: the dim rim and
    # the vignetted corners are noisier, and the power of a mixture spreads more).
    quart = {a: float(np.mean(angle_sig[i] ** 4)) for i, a in enumerate("xy")}
    quart["magnitude"] = quart["x"] + quart["y"]          # var(n_x^2 + n_y^2) = 2 sigma_x^4 + 2 sigma_y^4
    for model in red.fits.residuals_mrad:
        # mean(e^2) from the reported RMS (the same sums; squared back, within a unit of the last place)
        rms = red.figures["slope_rms_mrad"][model]
        ms = {"x": float(rms["x"]) ** 2, "y": float(rms["y"]) ** 2}
        ms["magnitude"] = ms["x"] + ms["y"]
        s2 = {a: noise[a] ** 2 for a in RMS_AXES}
        for a in RMS_AXES:
            var_ms = (4 * max(ms[a] - s2[a], 0.0) * s2[a] + 2 * quart[a]) / n_all
            sigma[("slope_rms_mrad", model, a)] = float(np.sqrt(var_ms) / (2 * np.sqrt(max(ms[a], 1e-30))))
    floor_u = {a: noise_floor_u(noise[a], quart[a], n_all) for a in RMS_AXES}
    per_dn = None
    if noise_dn is not None:
        gain = angle_sig / np.maximum(np.broadcast_to(np.asarray(noise_dn, np.float64), angle_sig.shape[1:]), 1e-12)
        per_dn = {a: float(np.sqrt(np.mean(gain[i] ** 2))) for i, a in enumerate("xy")}
        per_dn["magnitude"] = float(np.hypot(per_dn["x"], per_dn["y"]))
    return NoisePropagation(sigma, noise, floor_u, per_dn)


def with_frame_brightness(noise: NoisePropagation, sigma_dn: float, dof: int) -> NoisePropagation:
    """*noise* with the frame-to-frame brightness change added to its noise floor and the floor's U.

    A brightness change common to a frame (the room light between frames, *sigma_dn* per frame, DN, estimated
    with *dof* degrees of freedom: :func:`~.capture_evidence.frame_brightness_dn`) moves every pixel's
    four-step phase as its own noise of that size would; it is common to the frame, so the fits hold it as the
    budget's frame-brightness row, but across the fringe's phases it spreads the slopes as pixel noise does.
    The floor s becomes sqrt(s^2 + (sigma_dn g)^2), g the slope noise per DN
    (``slope_noise_per_dn_mrad``); its U adds that term's own estimate's spread, a variance from *dof* values
    known to sqrt(2 / dof) of itself, and the capture's own draw of it: the finest set's four frames, whose
    change's cosine and sine parts (two degrees of freedom) move the positions, spread its power by as much
    as it is. Each capture against its own floor and U (2026-12-06; its slope noise about the mean of three
    captures of one twin, the pose held): seed 0's 40 stations, 240 values, 95.8 % inside U and RMS of error /
    (U / 2) 1.13 without the draw, 96.7 % and 0.88 with it; seed 1's 24 stations, 144 values, 93.8 % and 1.09
    without, 96.5 % and 0.77 with.

    Measured (2026-12-06, three captures of one twin per station, their slope noise about their mean, the
    frame brightness from the three captures' sets together): on the
    40 drawn stations of seed 0's population the realized noise was 0.95-1.52 times the pixel noise's floor
    alone (mean +3.6 %, RMS 9.7 %; the most at the stations with the most room-light jitter), and 0.84-1.34
    times the floor with this term (mean +0.1 %, RMS 5.9 %); on 24 of seed 1 +8.0 % and 14.8 % alone, +0.1 %
    and 6.5 % with it.
    The rest is mostly where the room light is not uniform over the facet (a strong vignetting) or a
    display's static response is left in the sets' means (a dish): :data:`NOISE_FLOOR_MODEL_RELATIVE`.
    """
    per_dn = noise.slope_noise_per_dn_mrad
    if not per_dn or not (sigma_dn > 0) or dof <= 0:
        return noise
    floor, floor_u = dict(noise.slope_noise_mrad), dict(noise.slope_noise_u_mrad or {})
    for a in RMS_AXES:
        s0, jit2 = floor[a], (sigma_dn * per_dn[a]) ** 2
        total = float(np.sqrt(s0 * s0 + jit2))
        if total > 0:
            # the estimate's spread (2 / dof), and this capture's own draw of the change: only the finest set's
            # four frames move its positions, and their change's two parts the four-step phase sees (its cosine
            # and sine; the mean is the pixel's offset) carry a power known to 2 / 2 of itself
            u_jit = jit2 * np.sqrt(2.0 / dof + 1.0) / (2.0 * total)
            u0 = floor_u.get(a, 0.0) * (s0 / total if s0 > 0 else 0.0)   # the pixel part's, on the new floor
            floor_u[a] = float(np.hypot(u0, u_jit))
        floor[a] = total
    return dataclasses.replace(noise, slope_noise_mrad=floor, slope_noise_u_mrad=floor_u)
