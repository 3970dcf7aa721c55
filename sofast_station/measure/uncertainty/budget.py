"""The combination (GUM): each figure's expanded uncertainty U = k u_c, k = 2, from the systematic
sensitivities scaled by the capture's own evidence, the intensity noise and the corner pose's Monte Carlo;
the noise floor of the slope RMS values; and the budget table, input group against figure.
:func:`uncertainty_figures` is what :func:`~sofast_station.measure.analysis.analyse` calls.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from .capture_evidence import (FRAME_POOL_CAPTURES, capture_scales, display_response_u, frame_brightness_dn,
                               pooled_frame_brightness)
from .corner_pose import CAMERA_DRAWN, POSE_DRAWS, POSE_GROUPS, POSE_PATHS, pose_monte_carlo
from .inputs import (COVERAGE_FACTOR, POSE_ROWS, RMS_AXES, InputUncertainties, get_path, path_name,
                     pose_row_covariance)
from .intensity_noise import NoisePropagation, noise_propagation, with_frame_brightness
from .shape_pose import DIFFERENCE_PATH, beyond_linear, pose_fields, shape_monte_carlo
from .systematic import Sensitivities, sensitivities


def _nest(values: dict, figures: dict) -> dict:
    """``{path: value}`` -> ``{"name_U": structure like figures[name]}``."""
    out: dict = {}
    for path, v in values.items():
        top = path[0]
        if len(path) == 1:
            out[f"{top}_U"] = v
            continue
        template = figures[top]
        if template is None:            # a figure this measurement does not report (an unknown outline's)
            out[f"{top}_U"] = None
            continue
        cur = out.setdefault(f"{top}_U", _empty_like(template))
        for p in path[1:-1]:
            cur = cur[p]
        cur[path[-1]] = v
    return out


def _empty_like(template):
    if isinstance(template, dict):
        return {k: _empty_like(v) for k, v in template.items()}
    if isinstance(template, (list, tuple)):
        return [None] * len(template)
    return None


def _projected_normal_quantile(d: float, level: float = 0.95) -> float:
    """The *level* quantile of |theta| (rad) for theta = atan2(Y, d + X), X and Y independent standard
    normal: the direction of a 2-D vector known to within a unit isotropic spread at distance d from the
    origin. Its density is (1 / 2 pi) exp(-d^2 sin^2 theta / 2) (exp(-a^2 / 2) + a sqrt(2 pi) Phi(a)),
    a = d cos theta, integrated on a fine grid."""
    from scipy.special import ndtr  # lazy: scipy.special costs ~0.5 s at import (measured after this module)

    theta = np.linspace(0.0, np.pi, 4001)
    a = d * np.cos(theta)
    f = np.exp(-0.5 * (d * np.sin(theta)) ** 2) * (np.exp(-0.5 * a * a) + a * np.sqrt(2 * np.pi) * ndtr(a)) / np.pi
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (f[1:] + f[:-1]) * np.diff(theta))])
    return float(np.interp(level * cdf[-1], cdf, theta))


_AXIS_U_LIN = np.geomspace(1e-3, 10.0, 121)
#: The axis angle's 95 % quantile (rad) at each linear standard uncertainty of :data:`_AXIS_U_LIN`:
#: ``0.5 * _projected_normal_quantile(1 / (2 u))``, computed once and written here (computing it and loading
#: scipy.special for it took 0.08 s of every command's start; tests/measure/test_uncertainty.py recomputes it).
_AXIS_U_95 = np.array([
    0.001993794495957339, 0.002173799097534489, 0.0023189904516899675, 0.0025148974826551883,
    0.0026966944825701222, 0.0029184008160447585, 0.0031261427677634975, 0.003389766272655606,
    0.003651643271087982, 0.003923905581552547, 0.0042456005294526184, 0.004584918642989408, 0.004947889196135047,
    0.005338877503666769, 0.005760397014355283, 0.006213310093903175, 0.006702632751407578, 0.00724340142635505,
    0.007813068252185727, 0.008440244702966185, 0.009108229008094713, 0.009829614475975, 0.010612842735079092,
    0.011462054822657202, 0.012377768506885175, 0.013358738484070815, 0.014427744137735779, 0.01557847007159265,
    0.016819160093845723, 0.01816130641660561, 0.019608156417075282, 0.021172946465834345, 0.022863843293228374,
    0.02468790658288246, 0.026658511365781807, 0.028788131094199792, 0.031086213256273358, 0.03357029905573965,
    0.03625205314144927, 0.03914927941806155, 0.04227923558201609, 0.045660534045510306, 0.04931443680370336,
    0.05326245034314764, 0.05752935752500199, 0.0621409999013075, 0.06712638301780897, 0.07251834431195789,
    0.07834936887837057, 0.08465755602889849, 0.09148369796479755, 0.09887504016223292, 0.10688020258322767,
    0.11555564524122264, 0.12496300502252936, 0.13517201482470478, 0.14626103010488598, 0.15831822932776918,
    0.17144589230566232, 0.18576016360071518, 0.20139878068894268, 0.21852292933390036, 0.23732623222902163,
    0.2580445657596351, 0.280968380108965, 0.30645575599110386, 0.33494886844600547, 0.3669868548588617,
    0.40321148436314347, 0.44436334845429903, 0.49124899610041656, 0.5446614505889902, 0.6052134278583906,
    0.6730504116895719, 0.7474539965966346, 0.8264804546224318, 0.9069472736884486, 0.9850257594686018,
    1.057261594120794, 1.121414970294405, 1.1766737126955713, 1.223331940685603, 1.2623001428162735,
    1.2947072747485788, 1.3216645187043956, 1.3441572495705585, 1.363013630425188, 1.37891004316794,
    1.3923910166984792, 1.4038922937940224, 1.413762203980888, 1.4222797341301463, 1.4296692297939235,
    1.4361119869371313, 1.4417553616635763, 1.4467197971676427, 1.4511043786259625, 1.4549910758653677,
    1.458448124756625, 1.4615326444148686, 1.4642927137629769, 1.4667690230430777, 1.4689961844636839,
    1.4710037788073753, 1.4728172129465262, 1.4744583966422136, 1.4759463113976934, 1.477297461933964,
    1.4785262588149293, 1.4796453256666298, 1.480665759704659, 1.4815973468905033, 1.482448746426328,
    1.4832276397226383, 1.4839408602128417, 1.4845945019740432, 1.4851940133225812, 1.4857442789227346,
    1.4862496822150295, 1.4867141695565342, 1.4871412986927552,
])


def axis_angle_u(u_linear: float) -> float:
    """The axis angle's expanded uncertainty (95 %, rad) from its linear standard uncertainty.

    The axis angle is half the direction of the vector (A - B, E). Linearised, its standard uncertainty is
    sigma / (2 rho) (rho the vector's length, sigma its spread across it); that holds while sigma is small
    against rho. On a nearly round facet (f_x close to f_y, little twist: a heliostat's, a flat one's) it is
    not: the direction is then anywhere, and k times the linear value, small against pi / 2, covered 69-79 %
    of the twin's true angles. Here the 95 % quantile of the half-direction of a vector d = rho / sigma =
    1 / (2 u) from the origin with a unit isotropic spread, the linear k u where that is larger: pi / 2 x 0.95
    when the vector is lost in its spread; never more than pi / 2 (an axis is a direction modulo pi).
    """
    u = float(u_linear)
    if np.isnan(u) or u <= 0:
        return COVERAGE_FACTOR * u if np.isfinite(u) else u
    if not np.isfinite(u):
        return 0.5 * np.pi
    # an axis is a direction modulo pi: no error exceeds pi / 2
    return min(0.5 * np.pi, max(COVERAGE_FACTOR * u, float(np.interp(np.log(u), np.log(_AXIS_U_LIN), _AXIS_U_95))))


def _axis_angle_floor(figures: dict, paths: list, u: np.ndarray, u_difference: float | None = None) -> float:
    """The axis angle's expanded uncertainty (k = 2, rad) that the curvatures' and the twist's own standard
    uncertainties *u* imply, the twist's error taken as independent of theirs.

    *u_difference*: the standard uncertainty of kappa_x - kappa_y itself (1/m; :func:`_difference_u`), with the
    rows that move both curvatures alike cancelled; without it the curvatures' errors are taken as independent,
    which on a dish (the range and the camera's focal length move both alike) stated the axis angle's U 2.5
    times its errors' spread (RMS of error / (U/2) 0.40 on the population's dishes at fcbd89e).

    The angle is half the direction of v = (A - B, E), A - B = (kappa_x - kappa_y) / 4 and E = twist / 1000.
    The vectors within k standard deviations of the measured one (an ellipse of half-axes k sigma) turn
    it by at most the largest half-direction change over that ellipse's boundary; when the ellipse holds
    the origin the direction is not known at all: pi / 2. Linearised (what the budget's own rows give),
    a nearly round facet's |A - B| inflated by its noise looked like a known axis: a flat facet whose
    measured A - B was 2 of its standard deviations from 0 had its axis stated to 0.03 rad and was pi / 2
    off. The budget's rows also miss what moves kappa_x and kappa_y apart without a row of its own (the
    facet's own slope errors over the pixels kept). 0 when a figure is missing."""
    try:
        jx, jy, jt = (paths.index((n,)) for n in ("curvature_x_per_m", "curvature_y_per_m", "twist_mrad_per_m"))
        kx, ky, tw = (float(figures[n]) for n in ("curvature_x_per_m", "curvature_y_per_m", "twist_mrad_per_m"))
    except (ValueError, KeyError, TypeError):
        return 0.0
    d, e = 0.25 * (kx - ky), 1e-3 * tw
    k = COVERAGE_FACTOR
    u_d = float(np.hypot(u[jx], u[jy])) if u_difference is None else float(u_difference)
    r_d, r_e = k * 0.25 * u_d, k * 1e-3 * float(u[jt])
    if not np.isfinite(r_d + r_e) or not np.isfinite(d + e):
        return 0.0
    if r_d <= 0.0 or r_e <= 0.0:
        return 0.0
    if (d / r_d) ** 2 + (e / r_e) ** 2 <= 1.0:
        return 0.5 * np.pi
    t = np.linspace(0.0, 2.0 * np.pi, 256, endpoint=False)
    turn = 0.5 * (np.arctan2(e + r_e * np.sin(t), d + r_d * np.cos(t)) - np.arctan2(e, d))
    turn = (turn + 0.5 * np.pi) % np.pi - 0.5 * np.pi
    return float(min(np.max(np.abs(turn)), 0.5 * np.pi))


def _difference_u(sens: Sensitivities, linear: np.ndarray, scales: np.ndarray, kinds: np.ndarray,
                  noise_col: np.ndarray, shape_mc: dict | None, pose_mc: dict | None) -> tuple:
    """The standard uncertainty of kappa_x - kappa_y (1/m), total and random, from the budget's signed rows
    (*linear*: their columns differenced, so a row that moves both curvatures alike cancels) and the shape
    Monte Carlo's own difference where it stands for its groups; (None, None) where the curvatures are not
    both in the budget, or the pose Monte Carlo stands for them (its draws are not differenced)."""
    kx, ky = ("curvature_x_per_m",), ("curvature_y_per_m",)
    if kx not in sens.paths or ky not in sens.paths or kx in (pose_mc or {}) or ky in (pose_mc or {}):
        return None, None
    jx, jy = sens.paths.index(kx), sens.paths.index(ky)
    lin = linear[:, jx] - linear[:, jy]
    cur = (sens.curvature[:, jx] - sens.curvature[:, jy]) * scales ** 2
    con2 = lin ** 2 + 2.0 * cur ** 2
    mc = (shape_mc or {}).get(DIFFERENCE_PATH) if (kx in (shape_mc or {}) and ky in (shape_mc or {})) else None
    use = np.ones(len(kinds), bool) if mc is None else np.array([i.group not in SHAPE_GROUPS for i in sens.inputs])
    sysm, randm = use & (kinds == "systematic"), use & (kinds == "random")
    rand2 = float(np.nansum(con2[randm])) + float(noise_col[jx] ** 2 + noise_col[jy] ** 2)
    sys2 = float(np.nansum(con2[sysm])) + float(np.nansum(cur[sysm])) ** 2
    ms_all, ms_corners = mc if mc is not None else (0.0, 0.0)
    return float(np.sqrt(sys2 + rand2 + ms_all)), float(np.sqrt(rand2 + ms_corners))


def _clean(v: float):
    return None if v is None or not np.isfinite(v) else float(v)


#: Each focal length's path and its focal power's (f = 1 / kappa).
FOCAL_POWER_PATHS = {("focal_length_x_m",): ("curvature_x_per_m",), ("focal_length_y_m",): ("curvature_y_per_m",),
                     ("principal_focal_lengths_m", 0): ("principal_curvatures_per_m", 0),
                     ("principal_focal_lengths_m", 1): ("principal_curvatures_per_m", 1)}


def _focal_from_power(figures: dict, paths: list, columns: tuple, contrib: np.ndarray, offset: np.ndarray) -> None:
    """Each focal length's uncertainty from its focal power's, in place: u(f) = u(kappa) / kappa^2 in every
    column of *columns* (1-D, one value per path) and every row of *contrib* (rows x paths); its part of
    *offset* likewise, with the sign of f's (df = -dkappa / kappa^2).

    f = 1 / kappa. The budget's rows and the shape Monte Carlo's responses of f itself are differences of f over
    a step of each input; on a nearly flat facet (f tens of km) the step moves kappa by as much as kappa, f leaps
    (through infinity where kappa changes sign) and those differences are noise: on the population (seed 0, 2000
    points in the shape Monte Carlo's fields) a flat facet's second principal focal length read 72 times its
    U / 2 from the truth by its power. kappa's responses are smooth, so f's U is taken from them, linear where it
    means anything (result/focal.py writes kappa's interval mapped through 1 / kappa where it does not); kappa's
    coverage is then f's by construction."""
    for f_path, k_path in FOCAL_POWER_PATHS.items():
        if f_path not in paths or k_path not in paths:
            continue
        kappa = get_path(figures, k_path)
        if kappa is None or get_path(figures, f_path) is None or not np.isfinite(kappa) or kappa == 0:
            continue
        jf, jk = paths.index(f_path), paths.index(k_path)
        scale = 1.0 / (kappa * kappa)
        for col in columns:
            col[jf] = col[jk] * scale
        contrib[:, jf] = contrib[:, jk] * scale
        offset[jf] = -offset[jk] * scale


#: Budget groups of the camera intrinsics (the Monte Carlo draws them for the corner pose only).
CAMERA_GROUPS = ("camera focal length", "camera principal point", "camera distortion")
#: Budget groups the shape figures' Monte Carlo stands for (:func:`~.shape_pose.shape_monte_carlo`): the
#: corners and the camera, through the corner pose and the rays.
SHAPE_GROUPS = ("corner location", *CAMERA_GROUPS)


def boresight_ray_path(sens: Sensitivities, contrib: np.ndarray) -> dict:
    """The camera intrinsics' contribution (standard, mrad) to the boresight through the rays alone:
    ``{("boresight_mrad", a): u}``, for reading (the budget's ``pose_monte_carlo.boresight_camera_rays``).

    The boresight is the rotation from the corner pose to the frame the measured surface defines. The
    Monte Carlo draws how the intrinsics move the corner pose; they also turn the measured surface's frame,
    since every pixel's ray turns with them (by 1 / f per pixel of the principal point). The optical tilt
    is that frame's tilt in the fixture, in which the corner pose's own tilt cancels, so the camera rows'
    contributions to ``optical_tilt_mrad`` (finite differences of the whole reduction) are this path. The
    Monte Carlo carries it draw by draw with the corner pose (:func:`boresight_ray_coefficients`).
    """
    rows = np.array([inp.group in CAMERA_GROUPS for inp in sens.inputs])
    out = {}
    for a in ("x", "y"):
        if ("optical_tilt_mrad", a) in sens.paths and rows.any():
            j = sens.paths.index(("optical_tilt_mrad", a))
            out[("boresight_mrad", a)] = float(np.sqrt(np.nansum(contrib[rows, j] ** 2)))
    return out


def screen_pose_coefficients(sens: Sensitivities) -> dict:
    """Each corner-pose figure's change per mrad and mm of the screen's pose (the screen rows' linear parts per
    unit, in the order of :data:`~.inputs.POSE_ROWS`' first six; 0 for a row the budget leaves out),
    ``{path: (6,) array}``, for :func:`~.corner_pose.pose_monte_carlo` to add draw by draw with the fixture's
    draws where the pose record correlates them."""
    names = [inp.name for inp in sens.inputs]
    out = {}
    for p in POSE_PATHS:
        if p not in sens.paths:
            continue
        j = sens.paths.index(p)
        coef = np.zeros(6)
        for k, name in enumerate(POSE_ROWS[:6]):
            if name in names:
                i = names.index(name)
                coef[k] = sens.linear[i, j] / sens.inputs[i].u if np.isfinite(sens.linear[i, j]) else 0.0
        out[p] = coef
    return out


def boresight_ray_coefficients(sens: Sensitivities) -> dict:
    """The boresight's turn through the rays per standard deviation of each camera input the corner pose's
    Monte Carlo draws (:data:`~.corner_pose.CAMERA_DRAWN`), mrad: the camera rows' linear parts of the
    optical tilt (:func:`boresight_ray_path`), ``{("boresight_mrad", a): (9,) array}``, for
    :func:`~.corner_pose.pose_monte_carlo` to add draw by draw.

    Until 2026-12-05 this path was added to the Monte Carlo's U in quadrature, as independent of the corner
    pose's: on the dish it nearly is (the corner pose follows the principal point by 0.01-0.02 mrad per px,
    the rays by 0.29), but a facet whose corners are not at one depth (the heliostat and the nearly flat
    facet of the population) reads part of the principal point's shift as a turn, the same way the rays
    turn, and the boresight's U was 2-3 times its errors' spread there (RMS of error / (U / 2) 0.3-0.55)."""
    out = {}
    for a in ("x", "y"):
        if ("optical_tilt_mrad", a) not in sens.paths:
            continue
        j = sens.paths.index(("optical_tilt_mrad", a))
        coef = np.zeros(len(CAMERA_DRAWN))
        for i, inp in enumerate(sens.inputs):
            if inp.name in CAMERA_DRAWN and np.isfinite(sens.linear[i, j]):
                coef[CAMERA_DRAWN.index(inp.name)] = sens.linear[i, j]
        out[("boresight_mrad", a)] = coef
    return out


def covariance_factor(cov: np.ndarray) -> np.ndarray:
    """M with M M^T = *cov*, lower triangular (Cholesky) where *cov* is positive definite: component k then
    holds input k's part not explained by the inputs before it, so a budget table's group of the first
    inputs carries what the later ones share with them. Else (semi-definite) from its eigenvectors."""
    cov = 0.5 * (cov + cov.T)
    try:
        return np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(cov)
        return v * np.sqrt(np.clip(w, 0.0, None))[None, :]


def correlated_rows(sens: Sensitivities, rows: list, factor: np.ndarray) -> np.ndarray:
    """The linear contributions of correlated inputs *rows* as independent rows: with C = M M^T their
    covariance (*factor* M, in the inputs' units) and J the sensitivities per unit, the rows M^T J, whose
    root sum of squares is sqrt(J^T C J) for every figure (the budget still adds up)."""
    u_ref = np.array([sens.inputs[i].u for i in rows])
    jac = sens.linear[rows] / u_ref[:, None]                               # figure per unit of the input
    return factor.T @ np.nan_to_num(jac)


def displaced_slope_squared(linear: np.ndarray, curvature: np.ndarray, own: np.ndarray) -> np.ndarray:
    """The rows' squared linear parts (rows, figures) with what the measured point's own displacement adds to
    them taken out: per figure, the rows *own* marks (one input's own row, *linear* c and *curvature* q per unit
    standard deviation) scaled by max(S_c - 4 S_q, 0) / S_c (S_c their sum of c^2, S_q of q^2); the others (rows
    mixed by a covariance) as they are.

    The sensitivities are differences about the measured point, which the inputs' own errors have moved from
    the truth by z standard deviations. For a response f(z) = g z + q z^2 the slope there is g + 2 q z, so its
    square is g^2 + 4 q^2 on average, while the error f(z) - f(0) spreads by g^2 + 2 q^2 about its mean q (which
    the budget's offset term carries). A figure that any error raises (a slope RMS with no true gradient, g = 0:
    the design residual x of a round facet) had each row stated as sqrt(6) q instead of sqrt(2) q. The excess
    is taken out of the rows' sum, not row by row: clipped at 0 row by row it comes back on the rows whose z
    happened to be large (six quadratic inputs drawn 100,000 times: RMS of error / (U / 2) 0.73 without, 0.81
    row by row, 0.86 from the sum; a linear figure is unchanged). Like
    :func:`~.shape_pose.displaced_gradient_factor` for the corner pose's draws; the terms between inputs (one
    input's slope moved by another's error) are not measured by one-at-a-time differences and stay in."""
    c2 = np.asarray(linear, float) ** 2
    mask = np.asarray(own, bool)
    s_c = np.nansum(c2[mask], axis=0)
    s_q = np.nansum(np.asarray(curvature, float)[mask] ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(s_c > 0, np.maximum(s_c - 4.0 * s_q, 0.0) / s_c, 1.0)
    out = c2.copy()
    out[mask] = c2[mask] * factor[None, :]
    return out


def corrected_rms_u(measured: float, corrected: float, measured_u: float) -> float:
    """The expanded uncertainty of a noise-corrected slope RMS c = sqrt(r^2 - s^2) from the measured RMS r's
    *measured_u* (mrad; noise floor s, its spread in r's).

    The correction is monotone in r, so r's interval r +- U(r) maps onto c's exactly: from
    sqrt((r - U)^2 - s^2) (0 where r - U lies below the floor) to sqrt((r + U)^2 - s^2), and the half-width is
    the larger side. Where c is well above its uncertainty that is (r / c) U(r): the correction magnifies r's
    uncertainty by r / c (1.7 on a nearly flat facet whose noise floor is as large as its figure). Where the
    interval reaches below the floor the value is known only to lie between 0 and the upper end.

    (Until 2026-12-07 the interval was taken in c^2 as c^2 +- 2 r U(r), which leaves out U(r)^2 and so reached
    lower than r's own interval does: on the population's heliostats with a low figure (c 0.26 mrad, c^2 within
    0.65 of 2 r U) that side was 1.25 times r / c U(r), and their corrected design slope RMS x's RMS of error /
    (U / 2) 0.48. Stated as r's own U, the corrected values on the population's flat facets were covered 88-95 %
    with RMS of error / (U / 2) 1.2-4.0: docs/uncertainty.md.)
    """
    floor2 = max(measured * measured - corrected * corrected, 0.0)     # s^2
    low_r, high_r = measured - measured_u, measured + measured_u
    low = np.sqrt(low_r * low_r - floor2) if low_r > 0.0 and low_r * low_r > floor2 else 0.0
    high = np.sqrt(high_r * high_r - floor2)
    return float(max(corrected - low, high - corrected))


def combine(figures: dict, sens: Sensitivities, noise: NoisePropagation, inputs: InputUncertainties,
            scales: np.ndarray | None = None, corner_cov: np.ndarray | None = None,
            pose_mc: dict | None = None, shape_mc: dict | None = None) -> dict:
    """The figures' expanded uncertainties, the noise floor and the budget, as figure keys to add.

    Returns ``{"name_U": ..., "name_U_random": ..., "coverage_factor": 2, "slope_rms_noise_mrad": ...,
    "slope_rms_noise_mrad_U": ..., "slope_rms_corrected_mrad": ..., "slope_rms_corrected_mrad_U": ...,
    "uncertainty_budget": ...}``.
    The measured slope RMS's U also covers the noise's bias b (the measured value minus the noise-corrected
    one), which the measured value does not remove, as every uncorrected offset here: U = k sqrt(u^2 + b^2).
    (Added linearly, U = k u + b, it over-stated the slope RMS x's U by about 6 % on the twin: 1000 captures
    covered 97.3 % with U / std 2.23; in quadrature 96.0 % and 2.10.)

    *corner_cov* (2n x 2n, pixels squared, the corners' coordinates in budget order): the corner rows'
    linear parts are then carried with their correlations, as sqrt(J^T C J) with J the sensitivities per
    pixel, split into independent rows (C = M M^T, row contributions M^T J) so the budget still adds up.
    The screen's and the fixture's pose rows alike where *inputs* holds the pose record's joint covariance
    (:func:`~.inputs.pose_row_covariance`): the pose calibration finds the fixture through the mirror seated
    in it, seen through the screen pose it finds, so their errors largely cancel in the optical tilt.

    *pose_mc* (:func:`pose_monte_carlo`): for the corner-pose figures, the mean square errors it drew stand
    for the rows of the groups it names (:data:`POSE_GROUPS`, and the screen's pose where it drew it with the
    fixture's) (the other rows are added to them in quadrature; for the boresight
    the Monte Carlo holds the camera intrinsics' path through the rays too, :func:`boresight_ray_coefficients`).

    *shape_mc* (:func:`~.shape_pose.shape_monte_carlo`): for the shape figures it names, the mean square change
    the corner pose's draws give stands for the corner rows (random); the other rows as they are.
    """
    sc = np.ones(len(sens.inputs)) if scales is None else np.asarray(scales, float)
    linear = (sens.linear * sc[:, None]).copy()
    own = np.ones(len(sens.inputs), bool)           # rows that are still one input's own (not mixed below)
    rows = [i for i, inp in enumerate(sens.inputs) if inp.group == "corner location"]
    if corner_cov is not None and np.shape(corner_cov) == (len(rows), len(rows)) and rows \
            and np.all(np.isfinite(corner_cov)):
        w, v = np.linalg.eigh(0.5 * (corner_cov + corner_cov.T))
        linear[rows] = correlated_rows(sens, rows, v * np.sqrt(np.clip(w, 0.0, None))[None, :])
        own[rows] = False
    joint = pose_row_covariance(inputs, sens.inputs)
    if joint is not None:
        linear[joint[0]] = correlated_rows(sens, joint[0], covariance_factor(joint[1]))
        own[joint[0]] = False
    curv = sens.curvature * (sc ** 2)[:, None]
    contrib = np.sqrt(displaced_slope_squared(linear, curv, own) + 2.0 * curv ** 2)
    kinds = np.array([i.kind for i in sens.inputs])
    u_sys2 = np.nansum(contrib[kinds == "systematic"] ** 2, axis=0)
    # A response that curves (q != 0) does not only spread the figure: for a normal input its mean moves by q
    # (E[c z + q z^2] = q), and the reported value does not remove that offset. The systematic inputs'
    # offsets add with their signs and count as one more term (U = k sqrt(u^2 + b^2), the usual way to state
    # an uncorrected bias); c^2 + 2 q^2 above is the spread about that mean.
    offset = np.nansum(sens.curvature[kinds == "systematic"] * (sc[kinds == "systematic"] ** 2)[:, None], axis=0)
    u_sys2 = u_sys2 + offset ** 2
    u_cor2 = np.nansum(contrib[kinds == "random"] ** 2, axis=0)
    noise_col = np.array([noise.sigma.get(p, 0.0) for p in sens.paths])
    u_rand = np.sqrt(u_cor2 + noise_col ** 2)
    u = np.sqrt(u_sys2 + u_rand ** 2)
    rays = boresight_ray_path(sens, contrib) if pose_mc else {}
    if pose_mc:
        drawn_groups = pose_mc.get("groups", POSE_GROUPS)
        other = np.array([inp.group not in drawn_groups for inp in sens.inputs])
        sys_o, rand_o = other & (kinds == "systematic"), other & (kinds == "random")
        off_o = np.nansum(sens.curvature[sys_o] * (sc[sys_o] ** 2)[:, None], axis=0)
        u_sys_o2 = np.nansum(contrib[sys_o] ** 2, axis=0) + off_o ** 2
        u_rand_o2 = np.nansum(contrib[rand_o] ** 2, axis=0) + noise_col ** 2
        for j, p in enumerate(sens.paths):
            if p in pose_mc:
                ms_all, ms_corners = pose_mc[p]
                u_rand[j] = np.sqrt(ms_corners + u_rand_o2[j])
                u[j] = max(np.sqrt(ms_all + u_sys_o2[j] + u_rand_o2[j]), u_rand[j])
    if shape_mc:
        drawn = np.array([inp.group in SHAPE_GROUPS for inp in sens.inputs])
        sys_o, rand_o = ~drawn & (kinds == "systematic"), ~drawn & (kinds == "random")
        off_o = np.nansum(sens.curvature[sys_o] * (sc[sys_o] ** 2)[:, None], axis=0)
        u_sys_o2 = np.nansum(contrib[sys_o] ** 2, axis=0) + off_o ** 2
        u_rand_o2 = np.nansum(contrib[rand_o] ** 2, axis=0) + noise_col ** 2
        for j, p in enumerate(sens.paths):
            if p in shape_mc and p not in (pose_mc or {}):
                ms_all, ms_corners = shape_mc[p]
                u_rand[j] = np.sqrt(ms_corners + u_rand_o2[j])
                u[j] = max(np.sqrt(ms_all + u_sys_o2[j] + u_rand_o2[j]), u_rand[j])
    _focal_from_power(figures, sens.paths, (u, u_rand, noise_col), contrib, offset)
    u_diff = _difference_u(sens, linear, sc, kinds, noise_col, shape_mc, pose_mc)
    k = COVERAGE_FACTOR
    values = {p: get_path(figures, p) for p in sens.paths}
    total, random = {}, {}
    for j, p in enumerate(sens.paths):
        if values[p] is None:
            total[p] = random[p] = None
            continue
        if p == ("axis_angle_rad",):
            floor, floor_rand = (_axis_angle_floor(figures, sens.paths, v, w) for v, w in zip((u, u_rand), u_diff))
            total[p] = _clean(max(axis_angle_u(u[j]), floor))
            random[p] = _clean(max(axis_angle_u(u_rand[j]), floor_rand))
            continue
        total[p] = _clean(k * u[j])
        random[p] = _clean(k * u_rand[j])
    # Noise floor: the slope noise the capture explains, and the RMS with it removed in quadrature.
    noise_mrad = {m: dict(noise.slope_noise_mrad) for m in figures["slope_rms_mrad"]}
    corrected, corrected_u = {}, {}
    for m, rms in figures["slope_rms_mrad"].items():
        corrected[m], corrected_u[m] = {}, {}
        for a in RMS_AXES:
            r, s = rms[a], noise_mrad[m][a]
            corrected[m][a] = None if r is None else float(np.sqrt(max(r * r - s * s, 0.0)))
            p = ("slope_rms_mrad", m, a)
            corrected_u[m][a] = total.get(p)
            if total.get(p) is not None and r is not None:
                # what a lens's blur smooths away lowers the measured and the noise-corrected value alike
                blur = k * float(np.hypot(blur_bias_mrad(figures, m, a, noise_mrad[m]),
                                          footprint_bias_mrad(figures, m, a, noise_mrad[m])))
                corrected_u[m][a] = float(np.hypot(corrected_rms_u(r, corrected[m][a], total[p]), blur))
                # the noise's bias, uncorrected in the measured value: in quadrature
                total[p] = float(np.hypot(np.hypot(total[p], k * (r - corrected[m][a])), blur))
    out = _nest(total, figures)
    out.update({k2 + "_random": v for k2, v in _nest(random, figures).items()})
    out.update(_subsample_fit_u(figures, sens.paths, u, u_rand, noise_col))
    out["coverage_factor"] = 2
    out["slope_rms_noise_mrad"] = noise_mrad
    floor_u = getattr(noise, "slope_noise_u_mrad", None)
    if floor_u:
        # the noise floor is a figure too: its U as the slope noise this capture's points carry
        out["slope_rms_noise_mrad_U"] = {m: {a: _clean(k * floor_u[a]) for a in RMS_AXES} for m in noise_mrad}
    out["slope_rms_corrected_mrad"] = corrected
    out["slope_rms_corrected_mrad_U"] = corrected_u
    out["uncertainty_budget"] = budget_table(sens, contrib, noise_col, u, u_rand, inputs, sc, offset)
    if shape_mc:
        out["uncertainty_budget"]["shape_monte_carlo"] = {
            "figures": [path_name(p) for p in sens.paths if p in shape_mc], "groups": list(SHAPE_GROUPS),
            "draws": POSE_DRAWS}
    if pose_mc:
        out["uncertainty_budget"]["pose_monte_carlo"] = {
            "figures": [path_name(p) for p in sens.paths if p in pose_mc],
            "groups": list(pose_mc.get("groups", POSE_GROUPS)),
            "draws": POSE_DRAWS,
            "boresight_camera_rays": {path_name(p): _sig(v) for p, v in rays.items()}}
    return out


#: The first-order estimate of what a blur smooths away of the slope residuals, from the blurred field's own
#: gradient, understates it by the factor x e^-x / (1 - e^-x) (x = sigma^2 k^2 of the field's wavenumbers
#: k, for a Gaussian blur of standard deviation sigma), which is near 1 for fields much longer than the blur.
#: It was stated twice over until 2026-12-06; on the population's blurred and defocused stations (seed 0,
#: stations 8-42 with those edge models, 55 captures) that made every slope RMS's U too large (RMS of
#: error / (U / 2) 0.59-0.88, the dish's 0.52-0.58), and stated once 0.76-1.07 with the same coverage
#: (95-100 %): the population's slope errors are 2-4 cm long, the blur a few pixels of 1-3 mm.
BLUR_LOSS_FACTOR = 1.0


def blur_bias_mrad(figures: dict, model: str, axis: str, noise_mrad: dict) -> float:
    """How much lower than the facet's own the slope RMS *axis* of *model* may read because the lens's blur
    averages neighbouring slopes (mrad; 0 for a sharp edge), an uncorrected bias added to U in quadrature.

    A blur of standard deviation s pixels (``edge_blur_px``, measured on the facet's edge) lowers a field's
    mean square by about s^2 times its mean square gradient per pixel, which is twice the neighbours' mean
    square difference (``slope_residual_neighbour_ms_mrad2``) less the noise's share (2 sigma^2 for
    independent pixel noise sigma, *noise_mrad*); stated :data:`BLUR_LOSS_FACTOR` times over. The bias is
    sqrt(rms^2 + loss) - rms.
    """
    blur = figures.get("edge_blur_px") or 0.0
    diffs = (figures.get("slope_residual_neighbour_ms_mrad2") or {}).get(model)
    rms = get_path(figures, ("slope_rms_mrad", model, axis))
    if blur <= 0 or not diffs or rms is None:
        return 0.0
    axes = ("x", "y") if axis == "magnitude" else (axis,)
    loss = sum(BLUR_LOSS_FACTOR * blur ** 2 * 2.0 * max(diffs[a] - 2.0 * noise_mrad[a] ** 2, 0.0) for a in axes)
    return float(np.sqrt(rms * rms + loss) - rms)


#: The dots' lattice differences, a dot step h apart, understate the slope residuals' mean square gradient
#: by x / (1 - e^-x), x = h^2 / (2 l^2), for a field correlated as exp(-d^2 / (2 l^2)): 2.5 at the methods
#: study's step (12 px, about 4 cm of facet) and l = 2 cm, the shortest correlation the population's slope errors
#: have; and the first-order loss understates the smoothing by up to 2 (:data:`BLUR_LOSS_FACTOR`). On the methods
#: study (seed 0, 59 captures) the twin's loss (the truth's mean square less that of the truth averaged over
#: each dot's footprint) was 3.5 times the first-order estimate on average: it is stated 4 times over.
FOOTPRINT_LOSS_FACTOR = 4.0


def footprint_bias_mrad(figures: dict, model: str, axis: str, noise_mrad: dict) -> float:
    """How much lower than the facet's own the slope RMS *axis* of *model* may read because each dot of a fixed
    pattern measures the slopes averaged over its footprint (mrad; 0 without dots), an uncorrected bias added to
    U in quadrature, as :func:`blur_bias_mrad` for the lens's blur.

    A dot's picture, a disc of diameter D px (``dots.diameter_px``), is the pre-image of the dot through the
    facet's slopes; its centroid is the picture of the dot's centre to first order only, which makes the slope
    found there the average over the disc, variance D^2 / 16 px^2 per axis. That lowers the mean square by
    about D^2 / 16 times the mean square gradient per pixel, estimated from the dots' lattice neighbours h px
    apart (``dots.step_px``) as 2 (d - 2 sigma^2) / h^2 (d their mean square difference,
    ``dots.lattice_neighbour_ms_mrad2``; sigma the slope noise, *noise_mrad*); stated
    :data:`FOOTPRINT_LOSS_FACTOR` times over. The bias is sqrt(rms^2 + loss) - rms.
    """
    dots = figures.get("dots") or {}
    diffs = (dots.get("lattice_neighbour_ms_mrad2") or {}).get(model)
    d, h = dots.get("diameter_px"), dots.get("step_px")
    rms = get_path(figures, ("slope_rms_mrad", model, axis))
    if not diffs or not d or not h or rms is None:
        return 0.0
    axes = ("x", "y") if axis == "magnitude" else (axis,)
    loss = sum(FOOTPRINT_LOSS_FACTOR * d * d / 16.0 * 2.0 * max(diffs[a] - 2.0 * noise_mrad[a] ** 2, 0.0) / (h * h)
               for a in axes)
    return float(np.sqrt(rms * rms + loss) - rms)


def _subsample_fit_u(figures: dict, paths: list, u: np.ndarray, u_rand: np.ndarray, noise_col: np.ndarray) -> dict:
    """``subsample_fit_U`` and ``subsample_fit_U_random`` (k = 2) of the focal lengths fitted on every n-th
    point (``subsample_fit``, what OpenCSP's SOFAST reports).

    The station inputs, the frame brightness and the corners move every slope smoothly over the facet, so the
    fit on every n-th point follows them as the fit on all points does: those contributions are the same.
    The intensity noise is independent from pixel to pixel, so its contribution to a least-squares fit grows
    as the square root of the points it leaves out: u_sub^2 = u^2 + (N / n - 1) u_noise^2 (N points in
    the reported fit, n in the subsample's). Exact for the plain fit; for the robust fit as far as its
    weights are the same on both (the noise propagation makes that approximation for the full fit too).
    """
    sub = figures.get("subsample_fit")
    n_all = figures.get("n_points")
    if not isinstance(sub, dict) or not sub.get("n_points") or not n_all:
        return {}
    more = max(float(n_all) / float(sub["n_points"]) - 1.0, 0.0)
    total, random = {"n_points": None}, {"n_points": None}     # the figure's shape; a count has no U
    for key in ("focal_length_x_m", "focal_length_y_m"):
        if (key,) not in paths or sub.get(key) is None:
            total[key] = random[key] = None
            continue
        j = paths.index((key,))
        total[key] = _clean(COVERAGE_FACTOR * np.sqrt(u[j] ** 2 + more * noise_col[j] ** 2))
        random[key] = _clean(COVERAGE_FACTOR * np.sqrt(u_rand[j] ** 2 + more * noise_col[j] ** 2))
    order = list(sub)
    return {"subsample_fit_U": {k: total.get(k) for k in order},
            "subsample_fit_U_random": {k: random.get(k) for k in order}}


def _sig(v: float, digits: int = 3):
    v = _clean(v)
    return None if v is None else float(f"{v:.{digits}g}")


def budget_table(sens: Sensitivities, contrib: np.ndarray, noise_col: np.ndarray, u: np.ndarray,
                 u_rand: np.ndarray, inputs: InputUncertainties, scales: np.ndarray,
                 offset: np.ndarray | None = None) -> dict:
    """The budget as one table, input group against figure: standard-uncertainty contributions (k = 1,
    figure units, root sum of squares within a group), the combined standard uncertainty, its random part,
    and the coverage factor (JSON-ready, 3 significant digits)."""
    groups: dict[str, dict] = {}
    for r, inp in enumerate(sens.inputs):
        g = groups.setdefault(inp.group, {"group": inp.group, "kind": inp.kind, "inputs": [], "sq": 0.0})
        g["inputs"].append(f"{inp.name} ({inp.u * scales[r]:.3g} {inp.unit})")
        g["sq"] = g["sq"] + np.nan_to_num(contrib[r]) ** 2
    rows = [{"group": g["group"], "kind": g["kind"], "inputs": g["inputs"],
             "contributions": [_sig(c) for c in np.sqrt(g["sq"])]} for g in groups.values()]
    if offset is not None:
        # After the systematic groups: the mean the systematic inputs' curved responses leave (see combine).
        at = sum(1 for r in rows if r["kind"] == "systematic")
        rows.insert(at, {"group": "curved-response offset", "kind": "systematic",
                         "inputs": ["sum of the systematic inputs' q"],
                         "contributions": [_sig(abs(c)) for c in np.nan_to_num(offset)]})
    rows.append({"group": "intensity noise", "kind": "random", "inputs": ["the capture's own noise"],
                 "contributions": [_sig(c) for c in noise_col]})
    return {"figures": [path_name(p) for p in sens.paths], "rows": rows, "coverage_factor": 2,
            "combined_standard": [_sig(c) for c in u], "random_standard": [_sig(c) for c in u_rand],
            "sensitivity_points": sens.n_points}


def uncertainty_figures(reduction, *, fringes, geometry, design, measured_distance_m: float, settings,
                        inputs: InputUncertainties, screen=None, cache: dict | None = None,
                        cache_key=None, pool=None) -> dict:
    """Everything :func:`combine` adds to a reduction's figures; sensitivities come from *cache* under
    *cache_key* (geometry + recipe + inputs) when present, else are computed and stored there. On a *pool*
    (an executor) the corner pose's Monte Carlo runs beside the rest (the same values)."""
    sens = None if cache is None or cache_key is None else cache.get(cache_key)
    fresh = sens is None
    if sens is None:
        sens = sensitivities(reduction, fringes=fringes, geometry=geometry, design=design,
                             measured_distance_m=measured_distance_m, settings=settings, inputs=inputs, screen=screen)
        if cache is not None and cache_key is not None:
            cache[cache_key] = sens
    rays = boresight_ray_coefficients(sens)
    screen_paths = screen_pose_coefficients(sens)
    frames: dict = {}
    pose_task = None if pool is None else pool.submit(pose_monte_carlo, reduction, geometry=geometry, design=design,
                                                      inputs=inputs, ray_paths=rays, frames=frames,
                                                      screen_paths=screen_paths)
    noise = noise_propagation(reduction, fringes=fringes, geometry=geometry, design=design, settings=settings,
                              screen=screen)
    pool = None
    if cache is not None and cache_key is not None:
        pool = cache.setdefault(("frame brightness", cache_key), deque(maxlen=FRAME_POOL_CAPTURES))
    # The pool as this capture found it: kept with the sensitivities (a dump's), so that a re-analysis of the
    # capture pools it with the same earlier captures and states the same U (the line's pool is its own).
    pool_before = None if pool is None else [list(entry) for entry in pool]
    own_dn, own_dof = frame_brightness_dn(reduction)
    frame = pooled_frame_brightness(own_dn, own_dof, pool)
    # The room light's change between frames spreads the slopes as pixel noise does: part of the noise floor.
    # This capture's own estimate (not widened: the floor's U carries its spread), not the pool's: the floor is
    # the noise this capture carries, and a figure reprocessed from its frames alone (the pool is not dumped)
    noise = with_frame_brightness(noise, own_dn, own_dof)
    response = display_response_u(reduction, inputs)
    pose_mc = (pose_monte_carlo(reduction, geometry=geometry, design=design, inputs=inputs, ray_paths=rays,
                                frames=frames, screen_paths=screen_paths) if pose_task is None else pose_task.result())
    shape_mc = {}
    if beyond_linear(frames):
        fields = pose_fields(reduction, fringes=fringes, geometry=geometry, design=design,
                             measured_distance_m=measured_distance_m, settings=settings, inputs=inputs, screen=screen)
        shape_mc = shape_monte_carlo(fields, frames)
    out = combine(reduction.figures, sens, noise, inputs,
                  capture_scales(reduction, sens, inputs, frame["sigma_dn"], response["u_rad"]),
                  getattr(reduction.pose, "corner_cov_px2", None), pose_mc, shape_mc)
    out["uncertainty_budget"]["frame_brightness"] = {k: (_sig(v, 4) if isinstance(v, float) else v)
                                                     for k, v in frame.items()}
    out["uncertainty_budget"]["display_response"] = {k: (_sig(v, 4) if isinstance(v, float) else v)
                                                     for k, v in response.items()}
    # Not figures (a timing, the pool): :func:`~sofast_station.measure.analysis.analyse` takes them out.
    out["_sensitivity_seconds"] = sens.seconds if fresh else 0.0
    out["_frame_pool"] = pool_before
    return out
