"""Pass, fail, indeterminate or invalid: the facet's figures against configured limits.

*invalid* means the measurement itself cannot be trusted (too few valid points, poor fringe contrast,
many unwrap disagreements, a corner pose that does not match the mask, an iteration that did not
converge); it is decided first, because limits applied to an untrustworthy figure mean nothing.
*indeterminate* comes only from the guarded decision rule (``[limits] decision_rule = "guarded"``, ISO
14253-1): a figure lies within its expanded uncertainty of its limit, so neither pass nor fail is proven.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from ..errors import ConfigError
from ..facet import FacetDesign
from ..measure.checks import curl_judgement
from .formatting import with_u

#: Above this design focal length (metres) limits are stated on curvature (docs/conventions.md#focal-power).
LONG_FOCAL_LENGTH_M = 20.0


#: What ``[limits] slope_rms_value`` may name, and the figure key each reads.
SLOPE_RMS_VALUES = ("measured", "corrected")
_RMS_KEY = {"measured": "slope_rms_mrad", "corrected": "slope_rms_corrected_mrad"}
#: ``[limits] decision_rule``.
DECISION_RULES = ("simple", "guarded")


@dataclass(frozen=True)
class Limits:
    """Acceptance limits (``[limits]`` in station.toml).

    Attributes
    ----------
    focal_length_tolerance : float
        Largest relative deviation |f / f_design - 1| of f_x and f_y, for design f up to 20 m.
    curvature_tolerance_per_m : float
        Largest |kappa - kappa_design| (1/m) of kappa_x and kappa_y, for design f above 20 m.
    max_twist_mrad_per_m : float
        Largest |twist|, mrad/m.
    max_slope_rms_mrad : dict
        Largest magnitude RMS residual per model ("design", "parabola", "higher_order"), mrad.
    min_intercept : float or None
        Smallest intercept factor (power in the receiver aperture over the power reflected), 0 to 1.
    max_spot_radius_mrad : float or None
        Largest radius holding 90 % of the power, seen from the facet's centre, mrad.
    max_centroid_offset_mrad : float or None
        Largest distance of the beam's centroid from the aim point, seen from the facet's centre, mrad.
    min_power_ratio : float or None
        Smallest intercepted power over the design facet's.
    max_canting_mrad : float or None
        A heliostat's facets: largest canting error (its size, sqrt(x^2 + y^2)), mrad
        (docs/conventions.md#canting); None: not judged.
    slope_rms_value : str
        Which slope RMS the limits apply to: ``"measured"`` (as computed from the measured slopes) or
        ``"corrected"`` (with the slope noise the capture's own noise explains removed in quadrature).
    decision_rule : str
        ``"simple"``: pass when every figure is within its limit. ``"guarded"`` (ISO 14253-1): pass only
        when every figure is within its limit less its expanded uncertainty U, fail when a figure is beyond
        its limit plus U, otherwise ``indeterminate``.
    The optical limits apply to the figures of ``[optics]`` (``optics`` in the result); None: not judged.
    """

    focal_length_tolerance: float = 0.02
    curvature_tolerance_per_m: float = 2e-4
    max_twist_mrad_per_m: float = 1.0
    max_slope_rms_mrad: dict = field(default_factory=lambda: {"design": 3.0, "parabola": 2.0})
    min_intercept: float | None = None
    max_spot_radius_mrad: float | None = None
    max_centroid_offset_mrad: float | None = None
    min_power_ratio: float | None = None
    max_canting_mrad: float | None = None
    slope_rms_value: str = "measured"
    decision_rule: str = "simple"

    @property
    def optical(self) -> dict:
        """The optical limits that are set, by name."""
        return {k: getattr(self, k) for k in OPTICAL_LIMITS if getattr(self, k) is not None}


#: Limits on the optical figures (``optics`` in the result record).
OPTICAL_LIMITS = ("min_intercept", "max_spot_radius_mrad", "max_centroid_offset_mrad", "min_power_ratio")


@dataclass(frozen=True)
class Quality:
    """When a measurement is *invalid* (``[quality]`` in station.toml)."""

    min_valid_fraction: float = 0.9
    min_median_modulation_dn: float = 10.0
    max_unwrap_disagreement_fraction: float = 0.01
    min_outline_agreement: float = 0.95
    max_corner_reprojection_px: float = 1.0
    #: A display response whose second harmonic exceeds this fraction of the fringe's amplitude was not
    #: linearised (gamma 2.2 left uncorrected: about 0.28); between the warning level and this the result
    #: stands with a warning stating the phase error it may cause.
    max_display_harmonic_ratio: float = 0.05
    warn_display_harmonic_ratio: float = 0.01
    #: A real surface's slopes are a gradient: their local fluctuations stretch but do not turn. The x and
    #: y sets were swapped when the turning (antisymmetric) part, less what the slope noise alone gives
    #: it, is beyond that noise by ``slope_curl_sigmas`` standard deviations (the predicted noise known to
    #: ``slope_curl_noise_tolerance`` of its mean square), exceeds ``max_slope_curl_ratio`` of the
    #: stretching part (less its noise too), and the floor ``min_slope_curl_per_m`` (1/m) below which the
    #: fluctuations are too weak to judge (measure/checks.py curl_judgement; docs/method.md).
    max_slope_curl_ratio: float = 0.5
    min_slope_curl_per_m: float = 0.002
    slope_curl_sigmas: float = 5.0
    slope_curl_noise_tolerance: float = 0.05
    #: A facet found farther from its place in the fixture than this (translation of its middle, mm;
    #: rotation about its normal and optical tilt, mrad), by more than the figure's own expanded
    #: uncertainty, is misplaced: the layout (the reflected footprint on the screen, the range finder's
    #: spot) holds for a seated facet only.
    max_placement_mm: float = 20.0
    max_placement_mrad: float = 30.0
    #: The station is laid out for slopes within the facet design's ``layout.max_slope_error_mrad`` (3
    #: mrad when not set) of the design: slopes measured farther from it by more than this factor (RMS
    #: against the design) are no facet of the recipe's type as this station sees it (fringe sets
    #: swapped on a nearly flat facet read as f of 2 m; a wrong recipe).
    max_design_slope_factor: float = 10.0


def _from_table(cls, table: dict, where: str):
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(known))}")
    return cls(**table)


def limits_from_table(table: dict, where: str) -> Limits:
    lim = _from_table(Limits, table, where)
    if lim.slope_rms_value not in SLOPE_RMS_VALUES:
        raise ConfigError(f"{where} slope_rms_value must be one of {', '.join(map(repr, SLOPE_RMS_VALUES))}, "
                          f"got {lim.slope_rms_value!r}")
    if lim.decision_rule not in DECISION_RULES:
        raise ConfigError(f"{where} decision_rule must be one of {', '.join(map(repr, DECISION_RULES))}, "
                          f"got {lim.decision_rule!r}")
    models = {"design", "parabola", "higher_order"}
    if not set(lim.max_slope_rms_mrad) <= models:
        raise ConfigError(f"{where}.max_slope_rms_mrad keys must be among {sorted(models)}")
    for key, value in lim.optical.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
            raise ConfigError(f"{where}: {key} must be a non-negative number, got {value!r}")
    if lim.min_intercept is not None and lim.min_intercept > 1:
        raise ConfigError(f"{where}: min_intercept is a fraction of the reflected power (0 to 1), "
                          f"got {lim.min_intercept}")
    return lim


def quality_from_table(table: dict, where: str) -> Quality:
    return _from_table(Quality, table, where)


def display_response(fig: dict, quality: Quality) -> tuple[list[str], list[str]]:
    """(invalid reasons, warnings) from the display's residual nonlinearity (``fig["display_response"]``)."""
    resp = fig.get("display_response")
    if not resp:
        return [], []
    ratio, error = resp["harmonic_ratio"], resp["phase_error_rad"]
    what = (f"second harmonic {100 * ratio:.1f} % of the fringe amplitude, phase error up to {error:.4f} rad "
            f"({1000 * error:.1f} mrad)")
    if ratio > quality.max_display_harmonic_ratio:
        return [f"display response not linearised: run calibrate radiometric ({what}; limit "
                f"{100 * quality.max_display_harmonic_ratio:g} %)"], []
    if ratio > quality.warn_display_harmonic_ratio:
        return [], [f"display response slightly nonlinear: {what}; rerun calibrate radiometric if it grows"]
    return [], []


def staircase_warning(fig: dict) -> list[str]:
    """A warning when sides of the facet's outline are staircases along the pixel grid (a point-sampled edge,
    or an area-sampled one exactly on a pixel boundary, which its image cannot tell apart;
    ``fig["outline_staircase_sides"]``): their corners are known only to within a pixel, which the corner
    pose's U carries (placement, boresight from corners, optical tilt); a camera turned a degree or two
    about its axis gives every side steps and pins its corners to a few hundredths of a pixel."""
    sides = fig.get("outline_staircase_sides") or []
    if not sides:
        return []
    which = ", ".join(str(k) for k in sides)
    many = len(sides) > 1
    return [f"edge{'s' if many else ''} {which} of the facet (numbered as in its design file) "
            f"{'line' if many else 'lines'} up exactly with the camera's pixel grid, so the facet's corners there "
            "are known only to about one pixel: its position in the fixture is less certain (its U says by how "
            "much); the verdict is not affected. To avoid it, turn the camera a degree or two about its lens axis"]


def lit_rim_warning(fig: dict) -> list[str]:
    """A warning when a rim the facet's design declares dark (``edge_rim_dark``) shows the screen on some
    sides (``fig["outline_lit_rim_sides"]``, :func:`~sofast_station.measure.pipeline.check_dark_rim`): those
    sides were put midway across the rim, their corners known to the rim's width / sqrt(12) (in the corner
    pose's U), not to the few hundredths of a pixel a dark rim allows; the design's declaration is wrong
    for this facet, or something lights its rim."""
    sides = fig.get("outline_lit_rim_sides") or []
    if not sides:
        return []
    which = ", ".join(str(k) for k in sides)
    plural = "s" if len(sides) > 1 else ""
    return [f"the glass rim, which the facet's design file says is dark (edge_rim_dark), shows the screen on "
            f"edge{plural} {which} of the facet (numbered as in its design file): the edge is taken midway across "
            "the rim, so the corners there are known only to the rim's width and the facet's position in the fixture "
            "is less certain (its U says by how much); the verdict is not affected. If this facet type's rim is not "
            "ground dark, set edge_rim_dark = false in its design file"]


def misplacement(fig: dict, quality: Quality) -> list[str]:
    """The reason a facet is misplaced in its fixture (empty when it is seated): a placement coordinate
    beyond ``max_placement_mm`` / ``max_placement_mrad`` by more than its U (k = 2; 0 when not stated).

    The translations and the rotation about the facet's normal are the corner pose's (well resolved); its
    tilts are not (a corner's depth barely moves its image: several mrad on a small camera, and a corner
    found wrongly on an edge of an unusual kind turns them by tens of mrad), so the tilts judged are the
    optical tilt's, the boresight frame's in the fixture, which the slopes fix to a fraction of a mrad."""
    placement, u = fig.get("placement") or {}, fig.get("placement_U") or {}
    tilt, tilt_u = fig.get("optical_tilt_mrad") or {}, fig.get("optical_tilt_mrad_U") or {}
    mm, mm_u = list(placement.get("mm") or []), list(u.get("mm") or [])
    mrad, mrad_u = list(placement.get("mrad") or []), list(u.get("mrad") or [])
    checked = [(f"{a}", v, (mm_u[i] if i < len(mm_u) else None), "mm", quality.max_placement_mm)
               for i, (a, v) in enumerate(zip("xyz", mm))]
    checked += [(f"tilt about {a}", tilt.get(a), tilt_u.get(a), "mrad", quality.max_placement_mrad) for a in "xy"]
    if len(mrad) == 3:
        checked.append(("about z", mrad[2], mrad_u[2] if len(mrad_u) == 3 else None, "mrad",
                        quality.max_placement_mrad))
    beyond = []
    for name, v, ui, unit, limit in checked:
        ui = 0.0 if ui is None else float(ui)
        if v is not None and abs(v) - ui > limit:
            beyond.append(f"{name} {with_u(v, ui or None, ' ' + unit, 1, sign=True)}")
    if not beyond:
        return []
    return [f"the facet is misplaced in the fixture: placement {', '.join(beyond)}, beyond the fixture's limits "
            f"({quality.max_placement_mm:g} mm, {quality.max_placement_mrad:g} mrad: [quality] max_placement_mm, "
            "max_placement_mrad) by more than the placement's U; reseat it and measure again"]


def implausible_shape(fig: dict, design: FacetDesign, quality: Quality) -> list[str]:
    """The reason a measured shape is no facet of the recipe's type (empty when it is): its RMS slope
    deviation from the design beyond ``max_design_slope_factor`` times the layout's largest slope error."""
    rms = ((fig.get("slope_rms_mrad") or {}).get("design") or {}).get("magnitude")
    allowed = float((getattr(design, "layout", None) or {}).get("max_slope_error_mrad", 3.0))
    if rms is None or not rms > quality.max_design_slope_factor * allowed:
        return []
    return [f"the measured slopes depart from the design by {rms:.1f} mrad RMS, {rms / allowed:.0f} times the "
            f"{allowed:g} mrad the station is laid out for (limit {quality.max_design_slope_factor:g} times): this "
            "is no facet of the recipe's type as the station sees it: the x and y fringe sets swapped (y captured "
            "before x?), the wrong recipe, or a facet far out of shape; check the capture order and the recipe"]


def judge(fig: dict, design: FacetDesign, limits: Limits, quality: Quality) -> dict:
    """``{"verdict": "pass" | "fail" | "indeterminate" | "invalid", "reasons": [...], "warnings": [...]}`` for
    one facet's figures; warnings say what weakens a result without invalidating it. The guarded decision
    rule uses the figures' ``name_U`` expanded uncertainties (missing ones count as 0)."""
    invalid, warnings = display_response(fig, quality)
    warnings = warnings + staircase_warning(fig) + lit_rim_warning(fig)
    curl = fig.get("slope_curl")
    turning = curl and curl_judgement(curl, quality.max_slope_curl_ratio, quality.min_slope_curl_per_m,
                                      quality.slope_curl_sigmas, quality.slope_curl_noise_tolerance)
    if turning and turning["turns"]:
        beyond = ("" if turning["sigmas"] is None else
                  f", {turning['sigmas']:.0f} standard deviations beyond what the slope noise gives")
        invalid.append(
            f"the measured slopes are no surface's: they turn as much as they stretch (local curl "
            f"{1000 * turning['antisymmetric_per_m']:.1f} mrad/m RMS against {1000 * turning['symmetric_per_m']:.1f}"
            f"{beyond}): the x and y fringe sets were swapped (y captured before x?) or shown in the wrong order; "
            "capture the sequence in the fringe definition's order")
    if fig["valid_fraction"] < quality.min_valid_fraction:
        invalid.append(f"only {100 * fig['valid_fraction']:.1f} % of the facet's pixels are valid "
                       f"(minimum {100 * quality.min_valid_fraction:.0f} %)")
    if fig["median_modulation_dn"] < quality.min_median_modulation_dn:
        invalid.append(f"fringe contrast too low: median modulation {fig['median_modulation_dn']:.1f} DN "
                       f"(minimum {quality.min_median_modulation_dn:g})")
    disagree = fig["unwrap_disagreements"] / max(fig["facet_pixels"], 1)
    if disagree > quality.max_unwrap_disagreement_fraction:
        invalid.append(f"{100 * disagree:.2f} % of pixels disagree between coarse and fine phase "
                       f"(maximum {100 * quality.max_unwrap_disagreement_fraction:g} %)")
    # (a mirror of unknown outline has neither: no corners, no outline to agree with)
    if fig["outline_agreement"] is not None and fig["outline_agreement"] < quality.min_outline_agreement:
        invalid.append(f"the corner pose does not match the mask (outline agreement {fig['outline_agreement']:.3f}, "
                       f"minimum {quality.min_outline_agreement}): partly lit or obstructed facet?")
    if fig["corner_reprojection_rms_px"] is not None and \
            fig["corner_reprojection_rms_px"] > quality.max_corner_reprojection_px:
        invalid.append(f"corners do not fit the design outline ({fig['corner_reprojection_rms_px']:.2f} px RMS)")
    invalid.extend(misplacement(fig, quality))
    invalid.extend(implausible_shape(fig, design, quality))
    if not fig["iterations"]["converged"]:
        invalid.append(f"shape and boresight iteration did not converge in {fig['iterations']['boresight']} steps")
    if invalid:
        return {"verdict": "invalid", "reasons": invalid, "warnings": warnings}

    guarded = limits.decision_rule == "guarded"
    fail, unsure = [], []

    def check(excess: float, u: float | None, text: str) -> None:
        """*excess* = |deviation| - limit (> 0 beyond the limit); *u* the deviation's expanded uncertainty."""
        if not guarded:
            if excess > 0:
                fail.append(text)
            return
        u = 0.0 if u is None else float(u)
        if excess > u:
            fail.append(f"{text}, beyond the limit by more than its U {u:.3g}")
        elif excess > -u:
            unsure.append(f"{text.split(' (limit')[0]} is within its U {u:.3g} of the limit"
                          f" ({'beyond' if excess > 0 else 'inside'} by {abs(excess):.3g})")

    f_design = design.focal_length_m
    for axis in ("x", "y"):
        kappa = fig[f"curvature_{axis}_per_m"]
        if f_design > LONG_FOCAL_LENGTH_M:
            dk = kappa - 1.0 / f_design
            check(abs(dk) - limits.curvature_tolerance_per_m, fig.get(f"curvature_{axis}_per_m_U"),
                  f"curvature {axis} {kappa:.6f} /m is {dk:+.2e} /m from design "
                  f"(limit {limits.curvature_tolerance_per_m:g})")
        else:
            f = fig[f"focal_length_{axis}_m"]
            rel = float("inf") if f is None else f / f_design - 1.0
            u_f = fig.get(f"focal_length_{axis}_m_U")
            shown = "infinite" if f is None else f"{f:.4f} m"
            check(abs(rel) - limits.focal_length_tolerance, None if u_f is None else u_f / f_design,
                  f"focal length {axis} {shown} is {100 * rel:+.2f} % from design "
                  f"(limit {100 * limits.focal_length_tolerance:g} %)")
    twist = fig["twist_mrad_per_m"]
    check(abs(twist) - limits.max_twist_mrad_per_m, fig.get("twist_mrad_per_m_U"),
          f"twist {twist:.3f} mrad/m (limit {limits.max_twist_mrad_per_m:g})")
    key = _RMS_KEY[limits.slope_rms_value]
    rms_values = fig.get(key) or fig["slope_rms_mrad"]
    label = "" if key == "slope_rms_mrad" else " (noise-corrected)"
    for model, limit in limits.max_slope_rms_mrad.items():
        rms = rms_values[model]["magnitude"]
        u_rms = ((fig.get(f"{key}_U") or {}).get(model) or {}).get("magnitude")
        check(rms - limit, u_rms, f"{model} slope error{label} {rms:.3f} mrad RMS (limit {limit:g})")
    fail.extend(judge_optics(fig.get("optics"), limits))
    if fail:
        return {"verdict": "fail", "reasons": fail + unsure, "warnings": warnings}
    if unsure:
        return {"verdict": "indeterminate", "reasons": unsure, "warnings": warnings}
    return {"verdict": "pass", "reasons": [], "warnings": warnings}


def judge_optics(optics: dict | None, limits: Limits) -> list[str]:
    """Reasons to fail on the optical figures (empty when none of ``limits.optical`` is exceeded)."""
    if not limits.optical:
        return []
    if optics is None:
        return ["optical limits are set but the result has no optical figures ([optics] enabled = false)"]
    fail = []
    checks = (("min_intercept", optics.get("intercept"), "intercept factor", "{:.4f}", -1),
              ("max_spot_radius_mrad", optics.get("spot_radius_mrad"), "90 % spot radius", "{:.3f} mrad", 1),
              ("max_centroid_offset_mrad", (optics.get("centroid_offset_mrad") or {}).get("magnitude"),
               "beam centroid offset", "{:.3f} mrad", 1),
              ("min_power_ratio", optics.get("power_ratio_vs_design"), "intercepted power / design's", "{:.4f}", -1))
    for key, value, label, fmt, sign in checks:
        limit = getattr(limits, key)
        if limit is None:
            continue
        if value is None:
            fail.append(f"{label}: not computed (the spot spills off the target plane), limit {limit:g}")
        elif sign * (value - limit) > 0:
            fail.append(f"{label} {fmt.format(value)} ({'minimum' if sign < 0 else 'maximum'} {limit:g})")
    return fail
