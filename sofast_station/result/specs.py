"""The charted figures of a recipe and their specification limits: what the control charts
(``report spc``), the drift alarms in the line and the certificate show for each facet type.

The recipe's limits (:class:`~sofast_station.result.verdict.Limits`) are the specification limits; beyond
:data:`~sofast_station.result.verdict.LONG_FOCAL_LENGTH_M` the focal powers are charted instead of the
focal lengths (docs/conventions.md).
"""

from __future__ import annotations

from dataclasses import dataclass

from .verdict import LONG_FOCAL_LENGTH_M


@dataclass
class FigureSpec:
    """One charted figure: where it is in a record, its unit, design value and specification limits."""

    key: str                      # dotted path in the record
    label: str
    unit: str
    design: float | None = None
    lsl: float | None = None
    usl: float | None = None


def figure_specs(design_focal_length_m: float, limits) -> list[FigureSpec]:
    """The charted figures of a recipe: f_x, f_y (or kappa_x, kappa_y beyond 20 m), twist, slope RMS vs design
    and vs the fitted parabola, with the recipe's limits as specification limits."""
    f = float(design_focal_length_m)
    out = []
    if f > LONG_FOCAL_LENGTH_M:
        k, tol = 1.0 / f, limits.curvature_tolerance_per_m
        for axis in ("x", "y"):
            out.append(FigureSpec(f"curvature_{axis}_per_m", f"focal power kappa_{axis}", "1/m", k, k - tol, k + tol))
    else:
        tol = limits.focal_length_tolerance
        for axis in ("x", "y"):
            out.append(FigureSpec(f"focal_length_{axis}_m", f"focal length f_{axis}", "m", f, f * (1 - tol),
                                  f * (1 + tol)))
    t = limits.max_twist_mrad_per_m
    out.append(FigureSpec("twist_mrad_per_m", "twist", "mrad/m", 0.0, -t, t))
    for model in ("design", "parabola"):
        out.append(FigureSpec(f"slope_rms_mrad.{model}.magnitude", f"slope error RMS vs {model}", "mrad", None, None,
                              limits.max_slope_rms_mrad.get(model)))
    return out


_MODELS = {"design": "design", "parabola": "fitted parabola", "higher_order": "higher-order fit"}
_COMPONENTS = {"magnitude": "magnitude", "x": "x", "y": "y"}
_NAMED = {
    "focal_length_x_m": ("focal length f_x", "m"), "focal_length_y_m": ("focal length f_y", "m"),
    "curvature_x_per_m": ("focal power kappa_x", "1/m"), "curvature_y_per_m": ("focal power kappa_y", "1/m"),
    "twist_mrad_per_m": ("twist", "mrad/m"), "twist_e1_mrad_per_m": ("twist E_1", "mrad/m"),
    "twist_e2_mrad_per_m": ("twist E_2", "mrad/m"), "valid_fraction": ("valid fraction of the facet", ""),
    "optics.intercept": ("intercept factor", ""),
    "optics.spot_radius_mrad": ("spot radius (90 % of the power)", "mrad"),
    "optics.spot_radius_m": ("spot radius (90 % of the power)", "m"),
    "optics.centroid_offset_mrad": ("beam centroid offset from the aim point", "mrad"),
    "optics.power_ratio_vs_design": ("intercepted power over the design facet's", ""),
}


def figure_name(key: str) -> tuple[str, str]:
    """A record figure's human name and unit, e.g. ``("slope error RMS vs design, magnitude", "mrad")`` for
    ``slope_rms_mrad.design.magnitude``; an unknown key is its own name, with the unit its name ends in."""
    if key in _NAMED:
        return _NAMED[key]
    parts = key.split(".")
    axis = {"0": "x", "1": "y", "2": "z"}
    if parts[0] == "principal_focal_lengths_m" and len(parts) == 2:
        return (f"principal focal length {'shorter' if parts[1] == '0' else 'longer'}", "m")
    if parts[0] == "principal_curvatures_per_m" and len(parts) == 2:
        return (f"principal focal power {'larger' if parts[1] == '0' else 'smaller'}", "1/m")
    if parts[0] in ("optical_tilt_mrad", "boresight_mrad") and len(parts) == 2:
        return (f"{'optical tilt' if parts[0].startswith('optical') else 'boresight rotation'} about "
                f"{parts[1]}", "mrad")
    if parts[0] == "placement" and len(parts) == 3:
        what = "placement offset" if parts[1] == "mm" else "placement rotation"
        return f"{what} {axis.get(parts[2], parts[2])}", parts[1]
    if parts[0] in ("slope_rms_mrad", "slope_rms_corrected_mrad") and len(parts) == 3:
        what = "slope error RMS" + (" (noise-corrected)" if "corrected" in parts[0] else "")
        model, comp = _MODELS.get(parts[1], parts[1]), _COMPONENTS.get(parts[2], parts[2])
        return (f"{what} vs {model}" + ("" if comp == "magnitude" else f", {comp}"), "mrad")
    tail = parts[-1]
    for suffix, unit in (("_mrad_per_m", "mrad/m"), ("_per_m", "1/m"), ("_mrad", "mrad"), ("_mm", "mm"),
                         ("_m", "m"), ("_s", "s")):
        if tail.endswith(suffix):
            return key, unit
    return key, ""
