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
