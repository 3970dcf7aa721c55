"""The slope noise each pixel's intensity noise explains: what the uncertainty's random part and the
slope-curl check (:func:`~sofast_station.measure.checks.slope_curl`) both start from.

A pixel's frame noise (at its own brightness) gives its screen-position noise through the finest phase's
modulation (:func:`~sofast_station.measure.phase.position_sigma_m`), and the law of reflection's
derivative with respect to the screen position turns that into slope noise. Pure functions of a
reduction's stages (:mod:`sofast_station.measure.pipeline`).
"""

from __future__ import annotations

import numpy as np

from .camera import to_frame
from .kernels import normal_slopes  # surface.normal_slopes in one compiled pass
from .phase import drawn_gain, noise_at_level, noise_by_level, position_sigma_m


def pixel_noise_dn(phases, stack, take: np.ndarray) -> np.ndarray | float:
    """The frame noise (DN, rounding included) of the region's pixels *take* (indices into the phases'
    arrays), each at its own brightness (white - dark) by the capture's noise-against-brightness line
    (:func:`~.phase.noise_by_level`, fitted on its cleaned four-step residuals); the capture's one noise
    figure where there is no such line.

    Parameters
    ----------
    phases : Phases
        The phase stage of the reduction.
    stack : (n_frames, M) array or None
        The region's frames (``Region.stack``), camera counts.
    take : (n,) int array
        Indices into the region's pixels.
    """
    if phases.noise is None or not phases.noise.residuals or stack is None or len(stack) < 2:
        return phases.noise_dn
    level = np.subtract(stack[1], stack[0], dtype=np.float32)
    model = noise_by_level(phases.noise.residuals, level, phases.noise_dn)
    return noise_at_level(model, level[take])


def position_sigmas_m(phases, stack, take: np.ndarray, fringes, screen_size_m: tuple[float, float],
                      noise_dn=None) -> dict:
    """``{"x": (n,), "y": (n,)}``: the screen-position noise (metres) of the region's pixels *take*, from
    the finest set's modulation and each pixel's own frame noise (:func:`pixel_noise_dn`), through the drawn
    fringes' correction (:func:`~.phase.drawn_gain`); for a stage that
    measured its points' position noise itself (``position_sigma_m``: a fixed pattern's dots, from their
    centroids' covariance, in the units of its positions) that. *noise_dn*: the pixels' frame noise when the
    caller has it already (:func:`pixel_noise_dn` of the same *take*)."""
    own = getattr(phases, "position_sigma_m", None)
    if own is not None:
        return {a: np.asarray(own[a])[take] for a in ("x", "y")}
    if noise_dn is None:
        noise_dn = pixel_noise_dn(phases, stack, take)
    out = {}
    for a, length in zip("xy", screen_size_m):
        sigma = position_sigma_m(phases.finest_modulation_dn[a][take], noise_dn, getattr(fringes, f"periods_{a}")[-1],
                                 length)
        # the drawn fringes' correction passes the phase noise on with its gain (1 - e'(phi))
        gain = drawn_gain(fringes, a, phases.positions_m[a][take], length, getattr(phases, "footprint_px", None))
        out[a] = sigma if gain is None else sigma * np.abs(gain)
    return out


def slope_jacobian(points_m: np.ndarray, camera_to_frame, screen, u_x: np.ndarray, u_y: np.ndarray,
                   delta_m: float = 1e-4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Slopes at surface *points_m* (3, n; the frame of *camera_to_frame*) for the screen positions
    (*u_x*, *u_y*, metres) and their derivatives with respect to those positions, the surface point held
    (finite differences of *delta_m*).

    Returns
    -------
    s0, d_ux, d_uy : (2, n) arrays
        The slopes (s_x, s_y), d(s_x, s_y)/du_x and d(s_x, s_y)/du_y (1/m).
    """
    camera_m = camera_to_frame.translation
    s0 = normal_slopes(points_m, camera_m, to_frame(camera_to_frame, screen.points_camera(u_x, u_y)))
    s_dx = normal_slopes(points_m, camera_m, to_frame(camera_to_frame, screen.points_camera(u_x + delta_m, u_y)))
    s_dy = normal_slopes(points_m, camera_m, to_frame(camera_to_frame, screen.points_camera(u_x, u_y + delta_m)))
    return s0, (s_dx - s0) / delta_m, (s_dy - s0) / delta_m


def slope_covariance(reduction, fringes, screen, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each valid point's slope noise from its intensity noise: the variances of s_x and s_y and their
    covariance (slope units squared) at *points* (indices into the valid points, ``Rays.vidx`` order), in
    the boresighted facet frame of ``reduction.shape``.

    *reduction* needs ``region``, ``phases``, ``rays`` and ``shape`` (a
    :class:`~sofast_station.measure.pipeline.Reduction` or any object with them).
    """
    points = np.asarray(points, dtype=np.intp)
    take = np.flatnonzero(reduction.rays.ok)[points]          # the same pixels in the phases' arrays
    phases = reduction.phases
    sig = position_sigmas_m(phases, getattr(reduction.region, "stack", None), take, fringes,
                            (screen.width_m, screen.height_m))
    cam_to_b = reduction.shape.boresighted_to_camera.inverse()
    _, gx, gy = slope_jacobian(reduction.shape.points_m[:, points], cam_to_b, screen,
                               phases.positions_m["x"][take], phases.positions_m["y"][take])
    vx, vy = sig["x"] ** 2, sig["y"] ** 2
    return (gx[0] ** 2 * vx + gy[0] ** 2 * vy, gx[1] ** 2 * vx + gy[1] ** 2 * vy,
            gx[0] * gx[1] * vx + gy[0] * gy[1] * vy)
