"""Expanded uncertainty (k = 2) of the optical figures (docs/uncertainty.md, "Optical figures").

Two parts, combined per GUM (root sum of squares of standard uncertainties, U = 2 u):

* **propagated** -- the optical figures depend on the measured surface through its focal power and its
  slope errors; the measurement's own standard uncertainties of the curvatures (``curvature_x_per_m``,
  ``curvature_y_per_m``) and of the slope RMS against the fitted parabola (``slope_rms_mrad.parabola.
  magnitude``) are carried to the optical figures by re-tracing the measured surface with its slopes
  changed by +-h: the curvature about the alignment point (where the boresight holds the slope fixed),
  the residual slopes against a fitted quadric scaled so their RMS moves by h. Every re-trace uses the
  SAME sun-shape samples as the unperturbed one (common random numbers), so the differences are the
  surface's effect, not sampling noise. With ``c = (y(+h) - y(-h)) / 2`` and
  ``q = (y(+h) + y(-h)) / 2 - y(0)`` at a step h large enough to move rays across the aperture's edge,
  the contribution at the input's own u is ``sqrt((c u/h)^2 + 2 (q (u/h)^2)^2)`` (as in
  :mod:`sofast_station.measure.uncertainty`).
* **sampling** -- the Monte Carlo error of the trace itself, from the rays of the unperturbed trace:
  delta-method variances of the power-weighted ratio (intercept), mean (centroid) and quantile (spot
  radius), and the design trace's for the power ratio.

Pure numpy: no file, no hardware, no global state.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .trace import Hits, spot_figures, trace

#: Relative steps of the re-traces: the curvature by 2 % of the design's focal power, the residual slopes'
#: RMS by 10 %; large enough that thousands of rays move, small enough to stay near-linear.
CURVATURE_STEP = 0.02
RMS_STEP = 0.10
#: At most this many points and rays in the re-traces (the figures' dependence on the surface is smooth).
MAX_POINTS = 20_000
RAYS = 100_000
#: The sampling error's sums over rays use at most this many (every k-th) rays.
SAMPLED_RAYS = 200_000

#: The scalar optical figures that get an uncertainty, as paths into ``facet_optics``'s figures.
PATHS = (("intercept",), ("spot_radius_m",), ("centroid_offset_mrad", "x"), ("centroid_offset_mrad", "y"),
         ("power_ratio_vs_design",))


@dataclass(frozen=True)
class SurfaceUncertainty:
    """The measured surface's standard uncertainties (k = 1) the optical figures are propagated from.

    Attributes
    ----------
    curvature_x_per_m, curvature_y_per_m : float
        u of the measured curvatures (1/f), 1/m.
    slope_rms_mrad : float
        u of the slope RMS against the fitted parabola (magnitude), mrad.
    curvature_x_random_per_m, curvature_y_random_per_m, slope_rms_random_mrad : float
        Their random parts (from the capture's noise), for the figures' ``_U_random``.
    """

    curvature_x_per_m: float
    curvature_y_per_m: float
    slope_rms_mrad: float
    curvature_x_random_per_m: float = 0.0
    curvature_y_random_per_m: float = 0.0
    slope_rms_random_mrad: float = 0.0

    @classmethod
    def from_figures(cls, figures: dict) -> SurfaceUncertainty | None:
        """From an analysis's figures with their ``_U`` siblings (k = 2); None without them."""
        try:
            kx, ky = figures["curvature_x_per_m_U"], figures["curvature_y_per_m_U"]
            rms = figures["slope_rms_mrad_U"]["parabola"]["magnitude"]
        except (KeyError, TypeError):
            return None
        if kx is None or ky is None or rms is None:
            return None

        def rand(key, *sub):
            v = figures.get(f"{key}_U_random")
            for s in sub:
                v = v.get(s) if isinstance(v, dict) else None
            return 0.0 if v is None else 0.5 * float(v)

        return cls(0.5 * kx, 0.5 * ky, 0.5 * rms, rand("curvature_x_per_m"), rand("curvature_y_per_m"),
                   rand("slope_rms_mrad", "parabola", "magnitude"))


def _get(figures: dict, path: tuple):
    v = figures
    for p in path:
        v = v.get(p) if isinstance(v, dict) else None
    return None if v is None else float(v)


def _quadric_slopes(points_m: np.ndarray, slopes: np.ndarray) -> np.ndarray:
    """The slopes of the least-squares quadric z = A x^2 + B y^2 + C x + D y + E xy through the slopes."""
    x, y = points_m[0], points_m[1]
    one, zero = np.ones_like(x), np.zeros_like(x)
    # s_x = 2A x + C + E y ; s_y = 2B y + D + E x ; unknowns (A, B, C, D, E)
    m = np.vstack([np.stack([2 * x, zero, one, zero, y], axis=1), np.stack([zero, 2 * y, zero, one, x], axis=1)])
    coef = np.linalg.lstsq(m, np.concatenate([slopes[0], slopes[1]]), rcond=None)[0]
    a, b, c, d, e = coef
    return np.stack([2 * a * x + c + e * y, 2 * b * y + d + e * x])


def sampling_u(hits: Hits, figures: dict, aperture, slant_range_m: float, fraction: float = 0.9) -> dict:
    """Standard uncertainties of one trace's figures from its own rays (Monte Carlo sampling error).

    Delta-method estimates for independent rays: the intercept I = sum(w 1_in) / W has
    ``u^2 = sum(w^2 (1_in - I)^2) / W^2``; a centroid coordinate ``sum(w^2 (x - c)^2) / (sum w)^2``; the
    radius r holding the fraction q has ``u^2 = q (1 - q) / (n_eff F'(r)^2)`` with n_eff the effective
    number of rays and F' the density of the power fraction in radius at r. They treat the rays of one point
    as independent of its other rays and of other points', which overstates the error of a stratified trace
    a little (conservative).
    """
    total = hits.reflected_w
    out = dict.fromkeys(("intercept", "spot_radius_m", "centroid_x_m", "centroid_y_m", "intercepted_w"), None)
    if hits.power_w.size == 0 or total <= 0:
        return out
    # The sums over rays are estimated from every k-th ray (at most SAMPLED_RAYS of them), scaled by k.
    k = max(1, hits.power_w.size // SAMPLED_RAYS)
    w = hits.power_w[::k].astype(np.float64)
    x, y = hits.x_m[::k].astype(np.float64), hits.y_m[::k].astype(np.float64)
    inside = aperture.contains(x, y)
    i = figures["intercept"]
    out["intercepted_w"] = float(np.sqrt(k * np.sum((w * (inside - i)) ** 2)))
    out["intercept"] = out["intercepted_w"] / total
    on = float(hits.power_w.sum())
    cx, cy = figures["centroid_m"]["x"], figures["centroid_m"]["y"]
    out["centroid_x_m"] = float(np.sqrt(k * np.sum((w * (x - cx)) ** 2)) / on)
    out["centroid_y_m"] = float(np.sqrt(k * np.sum((w * (y - cy)) ** 2)) / on)
    r90 = figures.get("spot_radius_m")
    if r90:
        r = np.hypot(x - cx, y - cy)
        n_eff = on * on / (k * float(np.sum(w * w)))
        for half in (0.02, 0.05, 0.1):      # a window holding enough rays for the density
            lo, hi = r90 * (1 - half), r90 * (1 + half)
            sel = (r > lo) & (r <= hi)
            if np.count_nonzero(sel) >= 50:
                break
        density = k * float(np.sum(w[sel])) / total / (hi - lo)       # power fraction per metre of radius
        if density > 0:
            out["spot_radius_m"] = math.sqrt(fraction * (1 - fraction) / n_eff) / density
    return out


#: The inputs the optical figures are propagated from: (name, SurfaceUncertainty field, its random part).
INPUTS = (("curvature x", "curvature_x_per_m", "curvature_x_random_per_m"),
          ("curvature y", "curvature_y_per_m", "curvature_y_random_per_m"),
          ("slope RMS", "slope_rms_mrad", "slope_rms_random_mrad"))


def optics_sensitivities(points_m: np.ndarray, slopes: np.ndarray, area_m2: np.ndarray, design, settings, scene,
                         design_figures: dict, slope_rms_mrad: float, fraction: float = 0.9) -> dict:
    """Linear (c, per input unit) and curvature (q, per input unit squared) sensitivities of the optical
    figures to the measured surface's curvatures and slope RMS, by re-tracing the surface at +-h with the
    same sun samples (common random numbers). A decimated copy (at most :data:`MAX_POINTS` points,
    :data:`RAYS` rays) is traced: 6 traces.

    Returns ``{input name: {".".join(path): (c, q)}}`` for the names of :data:`INPUTS`.
    """
    slant = scene.target.slant_range_m
    step = max(1, points_m.shape[1] // MAX_POINTS)
    p, s, a = points_m[:, ::step], slopes[:, ::step], area_m2[::step] * step
    rays_per_point = max(1.0, RAYS / max(p.shape[1], 1))
    fit = _quadric_slopes(p, s)
    resid = s - fit
    x_a, y_a = (float(c) for c in design.alignment_point_m)

    def figures_of(slopes_):
        rng = np.random.default_rng([settings.seed, 7])
        hits = trace(p, slopes_, a, scene.target, settings.sun, rng, rays_per_point=rays_per_point,
                     dni_w_m2=settings.dni_w_m2, reflectivity=settings.reflectivity)
        f = spot_figures(hits, scene.aperture, slant, fraction)
        d_int = design_figures["intercepted_w"]
        return {"intercept": f["intercept"], "spot_radius_m": f["spot_radius_m"],
                "centroid_offset_mrad": f["centroid_offset_mrad"],
                "power_ratio_vs_design": f["intercepted_w"] / d_int if d_int > 0 else None}

    h_k = CURVATURE_STEP * design.curvature_per_m
    h_r = RMS_STEP * max(slope_rms_mrad, 1e-3)
    rms_resid = 1e3 * float(np.sqrt(np.mean(np.sum(resid * resid, axis=0))))
    zero = np.zeros_like(p[0])
    moves = {  # slope change per unit of each input: the curvature about the alignment point (1/f = 2 d s/dx)
        "curvature x": (h_k, lambda sg: s + np.stack([0.5 * sg * h_k * (p[0] - x_a), zero])),
        "curvature y": (h_k, lambda sg: s + np.stack([zero, 0.5 * sg * h_k * (p[1] - y_a)])),
        "slope RMS": (h_r, lambda sg: fit + resid * max(0.0, 1.0 + sg * h_r / max(rms_resid, 1e-6))),
    }
    # The seven traces are independent (each draws its own sun samples from the same seed): two at once.
    slopes_of = [s] + [moved(sign) for _, moved in moves.values() for sign in (+1.0, -1.0)]
    with ThreadPoolExecutor(2) as pool:
        traced = list(pool.map(figures_of, slopes_of))
    base = traced[0]
    out = {}
    for i, (name, (h, _)) in enumerate(moves.items()):
        plus, minus = traced[1 + 2 * i], traced[2 + 2 * i]
        out[name] = {}
        for path in PATHS:
            y0, yp, ym = _get(base, path), _get(plus, path), _get(minus, path)
            if None not in (y0, yp, ym):
                out[name][".".join(path)] = (0.5 * (yp - ym) / h, (0.5 * (yp + ym) - y0) / (h * h))
    return out


def sensitivities_to_record(sens: dict) -> dict:
    """:func:`optics_sensitivities`' ``{input: {path: (c, q)}}`` as JSON-ready lists (a dump keeps the line's:
    its facets' optical U were computed with those of the first facet of their type). Floats go through JSON
    as their shortest round-tripping text, and a NaN as null, so :func:`sensitivities_from_record` gives
    the same bits back."""
    def num(v):
        v = float(v)
        return None if math.isnan(v) else v
    return {str(name): {str(path): [num(c), num(q)] for path, (c, q) in by_path.items()}
            for name, by_path in sens.items()}


def sensitivities_from_record(record) -> dict | None:
    """The sensitivities of a record of :func:`sensitivities_to_record`; None for anything else."""
    def num(v):
        return math.nan if v is None else float(v)
    try:
        return {str(name): {str(path): (num(c), num(q)) for path, (c, q) in by_path.items()}
                for name, by_path in record.items()}
    except (AttributeError, TypeError, ValueError):
        return None


def optics_uncertainty(sens: dict, scene, measured_hits: Hits, measured_figures: dict, design_hits: Hits,
                       design_figures: dict, surface_u: SurfaceUncertainty, fraction: float = 0.9) -> dict:
    """The ``_U`` and ``_U_random`` siblings (k = 2) of the optical figures of one traced facet.

    Parameters
    ----------
    sens : dict
        From :func:`optics_sensitivities` (for this facet, or one of the same design and settings).
    scene : Scene
    measured_hits, measured_figures : the reported trace of the measured surface and its spot figures.
    design_hits, design_figures : the design's trace and its spot figures.
    surface_u : SurfaceUncertainty

    Returns
    -------
    dict
        ``intercept_U``, ``spot_radius_m_U``, ``spot_radius_mrad_U``, ``centroid_offset_mrad_U`` {x, y,
        magnitude}, ``power_ratio_vs_design_U``, each with a ``_U_random`` sibling, and
        ``uncertainty_rows`` (each input's standard contribution per figure).
    """
    slant = scene.target.slant_range_m
    ms = 1000.0 / slant
    var = {path: 0.0 for path in PATHS}
    var_random = {path: 0.0 for path in PATHS}
    rows = {}
    for name, field_u, field_r in INPUTS:
        u, u_rand = getattr(surface_u, field_u), getattr(surface_u, field_r)
        rows[name] = {}
        for path in PATHS:
            cq = sens.get(name, {}).get(".".join(path))
            if cq is None:
                continue
            c, q = cq
            var[path] += (c * u) ** 2 + 2 * (q * u * u) ** 2
            var_random[path] += (c * u_rand) ** 2 + 2 * (q * u_rand * u_rand) ** 2
            rows[name][".".join(path)] = math.sqrt((c * u) ** 2 + 2 * (q * u * u) ** 2)
    # The Monte Carlo error of the reported (full) trace and of the design's.
    mc = sampling_u(measured_hits, measured_figures, scene.aperture, slant, fraction)
    mc_d = sampling_u(design_hits, design_figures, scene.aperture, slant, fraction)
    ratio = None
    if design_figures["intercepted_w"] > 0 and mc["intercepted_w"] is not None and mc_d["intercepted_w"] is not None:
        r = measured_figures["intercepted_w"] / design_figures["intercepted_w"]
        rel_m = mc["intercepted_w"] / max(measured_figures["intercepted_w"], 1e-300)
        rel_d = mc_d["intercepted_w"] / design_figures["intercepted_w"]
        ratio = r * math.hypot(rel_m, rel_d)
    sampling = {("intercept",): mc["intercept"], ("spot_radius_m",): mc["spot_radius_m"],
                ("centroid_offset_mrad", "x"): None if mc["centroid_x_m"] is None else mc["centroid_x_m"] * ms,
                ("centroid_offset_mrad", "y"): None if mc["centroid_y_m"] is None else mc["centroid_y_m"] * ms,
                ("power_ratio_vs_design",): ratio}
    rows["trace sampling"] = {".".join(k): v for k, v in sampling.items()}
    total, random = {}, {}
    for path in PATHS:
        if _get(measured_figures_for(measured_figures, design_figures), path) is None:
            total[path] = random[path] = None
            continue
        mc_u = sampling[path] or 0.0
        total[path] = 2.0 * math.sqrt(var[path] + mc_u ** 2)
        random[path] = 2.0 * math.sqrt(var_random[path] + mc_u ** 2)
    out = {}
    for suffix, vals in (("_U", total), ("_U_random", random)):
        out["intercept" + suffix] = vals[("intercept",)]
        sr = vals[("spot_radius_m",)]
        out["spot_radius_m" + suffix] = sr
        out["spot_radius_mrad" + suffix] = None if sr is None else sr * ms
        ux, uy = vals[("centroid_offset_mrad", "x")], vals[("centroid_offset_mrad", "y")]
        off = measured_figures["centroid_offset_mrad"]
        out["centroid_offset_mrad" + suffix] = {"x": ux, "y": uy, "magnitude": _magnitude_u(off, ux, uy)}
        out["power_ratio_vs_design" + suffix] = vals[("power_ratio_vs_design",)]
    out["uncertainty_rows"] = rows
    return out


def measured_figures_for(measured: dict, design: dict) -> dict:
    """The reported figures' values by the paths of :data:`PATHS` (power ratio included)."""
    ratio = measured["intercepted_w"] / design["intercepted_w"] if design["intercepted_w"] > 0 else None
    return {**measured, "power_ratio_vs_design": ratio}


def _magnitude_u(off: dict, ux, uy):
    """U of |(x, y)| from the U of x and y: first order when the offset is well above its U; near zero
    (where |.| is not linear) the larger bound hypot(U_x, U_y)."""
    if ux is None or uy is None:
        return None
    m = off.get("magnitude") or 0.0
    bound = math.hypot(ux, uy)
    if m > 2.0 * bound:
        return math.sqrt((off["x"] * ux) ** 2 + (off["y"] * uy) ** 2) / m
    return bound
