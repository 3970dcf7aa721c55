"""How a value with its expanded uncertainty is written, everywhere one is shown: ``5.4183 ± 0.0021 m``.

GUM 7.2.6: the uncertainty is given to (at most) two significant digits, and the value is rounded to the
same decimal place. Every place that shows a figure with its U (the station's console and ``inspect``,
``import-opencsp``, the line's page, ``reprocess``, the flux text, the map titles, the certificate) goes
through :func:`with_u`, so one figure reads the same wherever it is shown. A value without U keeps the
number of decimals its caller chose for it. :func:`budget_text` writes the uncertainty budget as a table.
"""

from __future__ import annotations

from ..gum import MAX_DECIMALS, _fixed, u_decimals, value_and_u, with_u  # noqa: F401 (their public place)


def shown_decimals(value, u, decimals: int = 4) -> int:
    """The decimals :func:`with_u` shows *value* with (for a column beside it, the truth say, to match)."""
    d = u_decimals(u)
    return decimals if d is None or value is None else max(d, 0)


#: Figures shown as columns of ``inspect --budget`` (the record's budget has every scalar figure).
BUDGET_COLUMNS = (("focal_length_x_m", "f x", "m"), ("focal_length_y_m", "f y", "m"),
                  ("twist_mrad_per_m", "twist", "mrad/m"),
                  ("slope_rms_mrad.design.magnitude", "RMS design", "mrad"),
                  ("slope_rms_mrad.parabola.magnitude", "RMS parab.", "mrad"),
                  ("boresight_mrad.x", "bore x", "mrad"), ("optical_tilt_mrad.x", "tilt x", "mrad"),
                  ("placement.mm.0", "place x", "mm"), ("placement.mrad.2", "place rz", "mrad"))


def aperture_text(aperture: dict) -> str:
    """A receiver aperture (the record's ``optics.conditions.aperture``) in words: "a circle of 0.500 m radius",
    "a 1.200 m x 0.800 m rectangle" (never its dict)."""
    if aperture.get("shape") == "rectangle":
        return f"a {aperture['width_m']:.3f} m x {aperture['height_m']:.3f} m rectangle"
    return f"a circle of {aperture['radius_m']:.3f} m radius"


def budget_text(rec: dict, columns=BUDGET_COLUMNS) -> str:
    """The uncertainty budget as one table: input groups against figures, standard-uncertainty
    contributions (k = 1), then the combined standard and expanded uncertainties."""
    b = rec.get("uncertainty_budget")
    if not b:
        return "no uncertainty budget in this record"
    names = b["figures"]
    cols = [(names.index(key), title, unit) for key, title, unit in columns if key in names]

    def cell(v):
        return f"{'-' if v is None else format(v, '.2e'):>11}"

    lines = ["Uncertainty budget: standard-uncertainty contribution of each input to each figure (k=1), "
             "combined per GUM",
             f"  {'input':<30}{'':>10}" + "".join(f"{t:>11}" for _, t, _ in cols),
             f"  {'':<30}{'':>10}" + "".join(f"{u:>11}" for _, _, u in cols)]
    for row in b["rows"]:
        lines.append(f"  {row['group']:<30}{row['kind']:>10}"
                     + "".join(cell(row["contributions"][i]) for i, _, _ in cols))
    lines.append(f"  {'combined standard u':<30}{'':>10}"
                 + "".join(cell(b["combined_standard"][i]) for i, _, _ in cols))
    lines.append(f"  {'  of which random':<30}{'':>10}" + "".join(cell(b["random_standard"][i]) for i, _, _ in cols))
    k = b.get("coverage_factor", 2)
    lines.append(f"  {f'expanded U (k={k})':<30}{'':>10}" + "".join(
        cell(None if b["combined_standard"][i] is None else k * b["combined_standard"][i]) for i, _, _ in cols))
    lines.append("  inputs: " + "; ".join(", ".join(r["inputs"]) for r in b["rows"] if r["kind"] == "systematic"))
    lines.append(f"  sensitivities from {b.get('sensitivity_points')} points, computed once per geometry and "
                 "recipe; docs/uncertainty.md")
    return "\n".join(lines)
