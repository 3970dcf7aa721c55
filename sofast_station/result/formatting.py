"""How a value with its expanded uncertainty is written, everywhere one is shown: ``5.4183 ± 0.0021 m``.

GUM 7.2.6: the uncertainty is given to (at most) two significant digits, and the value is rounded to the
same decimal place. Every place that shows a figure with its U (the station's console and ``inspect``,
``import-opencsp``, the line's page, ``reprocess``, the flux text, the map titles, the certificate) goes
through :func:`with_u`, so one figure reads the same wherever it is shown; a record's figure by its dotted
key goes through :func:`figure_text` (or :func:`figure_parts` for a table's two columns), which also gives a
figure without U the same decimals everywhere (:func:`figure_decimals`). The workbook shows each figure's
cell with the decimals of its U (:func:`number_format_decimals`). :func:`budget_text` writes the uncertainty
budget as a table.
"""

from __future__ import annotations

from ..gum import MAX_DECIMALS, _fixed, u_decimals, value_and_u, with_u  # noqa: F401 (their public place)
from .focal import interval_text, is_linear
from .record import figure_uncertainty, figure_value


def figure_decimals(key: str) -> int:
    """The decimals a record's figure (dotted *key*, in its own unit) is shown with when it has no U (a U sets
    them: GUM 7.2.6): focal powers (1/m) 6, lengths in metres (focal lengths) 4 (0.1 mm), intercept and power
    ratios 4, placements (mm, mrad) 2, everything else (mrad, mrad/m, rad) 3."""
    head = key.split(".")[0]
    if "curvature" in head:
        return 6
    if head.startswith("placement"):
        return 2
    if head.endswith("_m") and not head.endswith("_per_m") or head.startswith(("intercept", "power_ratio")) \
            or ".intercept" in key or ".power_ratio" in key:
        return 4
    return 3


def figure_parts(record: dict, key: str, *, scale: float = 1.0, sign: bool = False) -> tuple[str, str | None] | None:
    """The figure at dotted *key* of *record* and its U (``NAME_U``, k = 2) as two texts by GUM's rule
    (:func:`value_and_u`; the U text None without U); None when the record has no such figure."""
    interval = _nonlinear_interval(record, key)
    if interval is not None:             # a nearly flat facet's f: its interval, one text
        return interval_text(interval, compact=True), None
    value = figure_value(record, key)
    if value is None:
        return None
    return value_and_u(value, figure_uncertainty(record, key), figure_decimals(key), scale=scale, sign=sign)


#: A focal length and its focal power: with the power measured, a missing focal length is infinite.
_POWER_OF = {"focal_length_x_m": "curvature_x_per_m", "focal_length_y_m": "curvature_y_per_m"}


def _nonlinear_interval(record: dict, key: str) -> list | None:
    """The focal length's exact interval (``NAME_interval``) where its linear U does not stand for it (the
    focal power's U more than a tenth of the power: result/focal.py); None elsewhere."""
    if key not in _POWER_OF or not isinstance(record.get(key + "_interval"), list):
        return None
    power = _POWER_OF[key]
    if is_linear(figure_value(record, power), figure_uncertainty(record, power)):
        return None
    return record[key + "_interval"]


def figure_text(record: dict, key: str, unit: str = "", *, scale: float = 1.0, sign: bool = False,
                missing: str = "-") -> str:
    """``value ± U unit`` of the figure at dotted *key* of *record* (:func:`with_u` with its ``NAME_U`` and
    :func:`figure_decimals`): the one way a record's figure is written on every screen and page; *missing*
    when the record has no value (a focal length of a flat facet is written ``inf``)."""
    value = figure_value(record, key)
    interval = _nonlinear_interval(record, key)
    if interval is not None:             # a nearly flat facet: f's interval from its focal power's U
        return interval_text(interval, unit)
    if value is None and key in _POWER_OF and figure_value(record, _POWER_OF[key]) is not None:
        missing = "inf"                  # a focal power below 4e-9 /m: the focal length is infinite (JSON null)
    return with_u(value, figure_uncertainty(record, key), unit, figure_decimals(key), scale=scale, sign=sign,
                  missing=missing)


def number_format_decimals(value, u) -> int | None:
    """The decimals a workbook cell of a figure with expanded uncertainty *u* shows, so that it reads as the
    console and the page write it (:func:`with_u`: U's two significant digits); None without a U. A U of 100 or
    more (shown to tens) gets 0: a cell's format cannot round to tens."""
    if value is None or u_decimals(u) is None:
        return None
    return max(u_decimals(u), 0)


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


def method_text(record: dict) -> str | None:
    """How a facet was measured and on how many points, as every screen writes it: ``fixed pattern (dot grid),
    289 dots`` or ``fringes, 47,414 points`` (a record's ``method``, absent for the fringes, and ``n_points``);
    None for a record without figures (a fault, a heliostat's)."""
    n = record.get("n_points")
    if not isinstance(n, (int, float)):
        return None
    if record.get("method") == "fixed":
        return f"fixed pattern (dot grid), {int(n):,} dots"
    return f"fringes, {int(n):,} points"
