"""A result record in words: the one summary of a facet's (or a heliostat's) record.

``inspect`` prints :func:`record_text`; the slope-error maps' detail page (``report DUMP``) shows
:func:`figure_lines` of the reprocessed record, and ``reprocess`` heads its comparison with :func:`head_line`.
Every figure is written by :func:`~sofast_station.result.formatting.figure_text` (``value ± U``, GUM 7.2.6),
the rule the console line, the page, the workbook, ``report diff`` and the certificate follow too, so a
figure reads the same wherever it is shown (``tests/reanalysis/test_one_truth.py``).

Pure text: a record (JSON-ready dict) in, lines out.
"""

from __future__ import annotations

from ..result.formatting import aperture_text, figure_decimals, figure_parts, figure_text, with_u
from ..result.verdict import LONG_FOCAL_LENGTH_M
from .canting import instructions_text

#: The slope-error models, in the order they are shown (the paper's Figs. 8-10).
MODELS = ("design", "parabola", "higher_order")


def head_line(rec: dict) -> str:
    """``Facet SIM-0002 (dish-5.33) on STATION, TIME`` (``Heliostat ...`` for a heliostat's record)."""
    what = "Heliostat" if isinstance(rec.get("facets"), list) else "Facet"
    return f"{what} {rec.get('serial', '?')} ({rec.get('facet', '?')}) on {rec.get('station', '?')}, " \
           f"{rec.get('time', '?')}"


def verdict_lines(rec: dict) -> list[str]:
    """The verdict, each reason and each warning, one a line."""
    return [f"  verdict: {str(rec.get('verdict', '?')).upper()}"] + [f"    - {r}" for r in rec.get("reasons", [])] \
        + [f"    warning: {w}" for w in rec.get("warnings", [])]


def long_focus(rec: dict) -> bool:
    """Whether the record's focal lengths are long (beyond 20 m, or infinite): then its focal powers are shown."""
    f = [rec.get(k) for k in ("focal_length_x_m", "focal_length_y_m")]
    return any(v is None or abs(v) > LONG_FOCAL_LENGTH_M for v in f)


def main_figures(rec: dict) -> list[tuple[str, str, str]]:
    """(label, dotted key, unit) of a facet record's main figures: its focal lengths (its focal powers when they
    are long), its twist, the slope error RMS magnitude against each model."""
    if long_focus(rec):
        rows = [("kappa x", "curvature_x_per_m", "1/m"), ("kappa y", "curvature_y_per_m", "1/m")]
    else:
        rows = [("f x", "focal_length_x_m", "m"), ("f y", "focal_length_y_m", "m")]
    rows.append(("twist", "twist_mrad_per_m", "mrad/m"))
    rms = rec.get("slope_rms_mrad") or {}
    rows += [(f"slope RMS {m}", f"slope_rms_mrad.{m}.magnitude", "mrad") for m in MODELS if rms.get(m)]
    return rows


def figure_lines(rec: dict) -> str:
    """The main figures of a record (:func:`main_figures`), one a line, ``value ± U unit``, and its verdict: the
    text beside the slope-error maps."""
    lines = [f"{label:<22} {figure_text(rec, key, ' ' + unit)}" for label, key, unit in main_figures(rec)]
    if rec.get("coverage_factor"):
        lines.append(f"(± U: expanded uncertainty, k = {rec['coverage_factor']})")
    if rec.get("verdict"):
        lines.append(f"{'verdict':<22} {str(rec['verdict']).upper()}")
    return "\n".join(lines)


def _truth_text(truth: dict | None, key: str, unit: str, decimals: int, scale: float = 1.0) -> str:
    """``   (truth 5.42060 m)``: the twin's truth of *key* at the figure's shown decimals; "" without a truth."""
    if truth is None:
        return ""
    node = truth
    for part in key.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    return f"   (truth {'-' if node is None else f'{node * scale:.{decimals}f}{unit}'})"


def _shown_decimals(rec: dict, key: str, scale: float = 1.0) -> int:
    """The decimals the figure at *key* is shown with (its U's, else :func:`figure_decimals`), for its truth."""
    parts = figure_parts(rec, key, scale=scale)
    if parts is None:
        return figure_decimals(key)
    return len(parts[0].split(".")[1]) if "." in parts[0] else 0


def optics_lines(opt: dict | None, truth: dict | None = None) -> list[str]:
    """The optical figures of a record (``optics``), each with its U and the twin's truth when present."""
    if not opt:
        return []
    c = opt["conditions"]
    d = opt["design"]

    def show(key, unit="", scale=1.0, sign=False):
        return figure_text(opt, key, unit, scale=scale, sign=sign)

    def extra(key, scale=1.0, unit=""):
        return _truth_text(truth, key, unit, _shown_decimals(opt, key, scale), scale)

    spot_design = "-" if d["spot_radius_m"] is None else f"{1000 * d['spot_radius_m']:.2f}"
    return [f"  optics: {c['sun']['shape']} sun, DNI {c['dni_w_m2']:g} W/m^2, reflectivity {c['reflectivity']:g}, "
            f"target at {c['slant_range_m']:.3f} m, aperture {aperture_text(c['aperture'])}",
            f"    intercept factor        {show('intercept'):>17}   (design {d['intercept']:.4f}){extra('intercept')}",
            f"    90 % spot radius        {show('spot_radius_m', ' mm', 1000.0):>20}   (design {spot_design} mm; "
            f"analytic {1000 * opt['analytic_spot_radius_m']:.2f} mm){extra('spot_radius_m', 1000.0, ' mm')}",
            f"    centroid offset         {show('centroid_offset_mrad.magnitude', ' mrad'):>22} "
            f"(x {show('centroid_offset_mrad.x', sign=True)}, y {show('centroid_offset_mrad.y', sign=True)})"
            f"{extra('centroid_offset_mrad.magnitude', unit=' mrad')}",
            f"    power / design's        {show('power_ratio_vs_design'):>17}{extra('power_ratio_vs_design')}"]


def _facet_text(rec: dict) -> list[str]:
    """A facet's record: its figures (with U and the twin's truth), the optics, the points and the times."""
    truth = rec.get("truth")
    lines = []
    if rec.get("coverage_factor") is not None:
        lines.append(f"  figures are value ± U, the expanded uncertainty (k={rec['coverage_factor']:g})")

    def row(label, key, unit):
        extra = _truth_text(truth, key, f" {unit}", _shown_decimals(rec, key))
        lines.append(f"  {label:<26}{figure_text(rec, key, ' ' + unit):>24}{extra}")

    f_keys = (("focal length x", "focal_length_x_m", "m"), ("focal length y", "focal_length_y_m", "m"))
    k_keys = (("focal power x", "curvature_x_per_m", "1/m"), ("focal power y", "curvature_y_per_m", "1/m"))
    for label, key, unit in (k_keys + f_keys) if long_focus(rec) else f_keys:
        row(label, key, unit)
    row("twist", "twist_mrad_per_m", "mrad/m")
    row("twist E1 / E2", "twist_e1_mrad_per_m", "mrad/m")
    row("", "twist_e2_mrad_per_m", "mrad/m")
    lines.append(f"  slope error RMS (mrad) {'x':>17} {'y':>17} {'magnitude':>17}")
    for model, rms in (rec.get("slope_rms_mrad") or {}).items():
        cells = [figure_text(rec, f"slope_rms_mrad.{model}.{a}") for a in ("x", "y", "magnitude")]
        text = f"    {model:<20}" + "".join(f"{c:>18}" for c in cells)
        t = ((truth or {}).get("slope_rms_mrad") or {}).get(model)
        if t:
            text += f"   (truth {t['x']:.3f} {t['y']:.3f} {t['magnitude']:.3f})"
        lines.append(text)
    noise, corrected = rec.get("slope_rms_noise_mrad"), rec.get("slope_rms_corrected_mrad")
    if noise and corrected:
        model = next(iter(noise))
        # with its own U (slope_rms_noise_mrad_U) where the record carries one
        lines.append(f"    {'noise explained':<20}" + "".join(
            f"{figure_text(rec, f'slope_rms_noise_mrad.{model}.{a}'):>18}" for a in ("x", "y", "magnitude"))
            + "   (slope noise the capture's own noise explains)")
        lines.append("    with that noise removed in quadrature:")
        for model, c in corrected.items():
            # with its own U (slope_rms_corrected_mrad_U) where the record carries one
            lines.append(f"    {model:<20}" + "".join(
                f"{'-' if c[a] is None else figure_text(rec, f'slope_rms_corrected_mrad.{model}.{a}'):>18}"
                for a in ("x", "y", "magnitude")))

    def pair(label, key, unit, note=""):
        if not rec.get(key):
            return
        tt = (truth or {}).get(key)
        extra = f"   (truth {tt['x']:.3f}, {tt['y']:.3f})" if tt else ""
        lines.append(f"  {label:<28}{figure_text(rec, f'{key}.x')}, {figure_text(rec, f'{key}.y')} {unit}"
                     f"{note}{extra}")

    pair("boresight rotation (x, y)", "boresight_mrad", "mrad", "   (from the corner pose)")
    for key, why in (rec.get("not_measured") or {}).items():        # an unknown outline's, the plano model's
        lines.append(f"  {key.replace('_', ' '):<26} not measured: {why}")
    pair("optical tilt in fixture", "optical_tilt_mrad", "mrad")
    if rec.get("placement"):
        lines.append("  placement in fixture       " + placement_text(rec))
    lines.extend(optics_lines(rec.get("optics"), (truth or {}).get("optics")))
    if "n_points" in rec and rec.get("method") == "fixed":        # one point per dot (docs/method.md)
        lines.append(f"  dots (fixed pattern)      {rec['n_points']:>14,}   "
                     f"({100 * rec['valid_fraction']:.1f} % of the dots on the facet)")
        lines.append(f"  median dot depth          {rec['median_modulation_dn']:>11.1f} DN")
    elif "n_points" in rec:
        lines.append(f"  points                    {rec['n_points']:>14,}   "
                     f"({100 * rec['valid_fraction']:.1f} % of the facet's pixels)")
        lines.append(f"  median modulation         {rec['median_modulation_dn']:>11.1f} DN")
    it = rec.get("iterations")
    if it:
        lines.append(f"  iterations                {it['shape']:>9} shape, {it['boresight']} boresight "
                     f"({'converged' if it['converged'] else 'NOT converged'})")
    return lines


def placement_text(rec: dict) -> str:
    """The facet's (or heliostat's) placement in the fixture: ``x, y, z mm, rx, ry, rz mrad``, each ± U."""
    pl = rec["placement"]
    pu = rec.get("placement_U") or {"mm": [None] * 3, "mrad": [None] * 3}
    d = figure_decimals("placement")
    return (", ".join(with_u(v, u, "", d) for v, u in zip(pl["mm"], pu["mm"])) + " mm, "
            + ", ".join(with_u(v, u, "", d) for v, u in zip(pl["mrad"], pu["mrad"])) + " mrad")


def _heliostat_text(rec: dict) -> list[str]:
    """A heliostat's record: the heliostat, one line per facet (its canting, focal powers and slope error, with
    the twin's truth where there is one), its optics and what to turn."""
    h = rec["heliostat"]
    lines = ["  figures are value ± U, the expanded uncertainty (k=2)",
             f"  {h['n_measured']} of {h['n_facets']} facets measured"
             + (f", {h['n_missing']} missing" if h.get("n_missing") else ""),
             "  placement in fixture      " + placement_text(h),
             f"  facets' common tilt       {figure_text(h, 'common_tilt_mrad.x')}, "
             f"{figure_text(h, 'common_tilt_mrad.y')} mrad (against its corners: where it points, not canting)",
             f"  canting RMS {h['canting_rms_mrad']:.3f} mrad, largest {h['canting_max_mrad']:.3f} mrad "
             f"({h['canting_max_facet']})"]
    truth_shown = any("truth" in f for f in rec["facets"])
    lines.append(f"  {'facet':<8} {'verdict':<14} {'canting x (mrad)':>17}  {'canting y (mrad)':>17}   "
                 f"{'focal power x, y (1/m)':<34} {'slope RMS (mrad)':>17}"
                 + ("   truth: canting x, y" if truth_shown else ""))
    for f in rec["facets"]:
        if "canting_mrad" not in f:
            lines.append(f"  {f['label']:<8} {f.get('verdict', f['status']).upper():<14} {f['status']}: "
                         f"{f.get('reason', '')}")
            continue
        power = f"{figure_text(f, 'curvature_x_per_m')}, {figure_text(f, 'curvature_y_per_m')}"
        text = (f"  {f['label']:<8} {f['verdict'].upper():<14} {figure_text(f, 'canting_mrad.x', sign=True):>17}"
                f"  {figure_text(f, 'canting_mrad.y', sign=True):>17}   {power:<34} "
                f"{figure_text(f, 'slope_rms_mrad.parabola.magnitude'):>17}")
        t = (f.get("truth") or {}).get("canting_mrad")
        if t:
            text += f"   {t['x']:+.3f}, {t['y']:+.3f}"
        lines.append(text)
    o = rec.get("optics")
    if o:
        m, d, c = o["measured"], o["design"], o["corrected"]
        cond = o["conditions"]
        lines.append(f"  optics at {cond['slant_range_m']:.1f} m, aperture {aperture_text(cond['aperture'])}:")
        lines.append(f"    intercept: measured {figure_text(m, 'intercept')}, design {d['intercept']:.4f}, re-canted "
                     f"{figure_text(c, 'intercept')}")
        lines.append(f"    90 % spot radius: measured {figure_text(m, 'spot_radius_mrad')} mrad, design "
                     f"{d['spot_radius_mrad']:.3f}, re-canted {figure_text(c, 'spot_radius_mrad')} mrad")
    if rec.get("canting_instructions"):
        lines.append("")
        lines.extend("  " + ln if ln else "" for ln in instructions_text(rec["canting_instructions"]).splitlines())
    return lines


def record_text(rec: dict) -> str:
    """The readable summary of one result record, a facet's or a heliostat's (``value ± U`` where the record
    has ``NAME_U``, k = 2): its head, verdict, figures (with the twin's truth on a simulated station), optics,
    a heliostat's facets and canting instructions, its times and pictures."""
    lines = [head_line(rec), *verdict_lines(rec)]
    if rec.get("verdict") != "fault" or "slope_rms_mrad" in rec or "heliostat" in rec:
        lines += _heliostat_text(rec) if isinstance(rec.get("facets"), list) else _facet_text(rec)
    t = rec.get("timings_s") or {}
    if {"capture", "analysis", "total"} <= set(t):
        lines.append(f"  time: capture {t['capture']:.2f} s, analysis {t['analysis']:.2f} s, total {t['total']:.2f} s")
    for kind, path in (rec.get("pictures") or {}).items():
        lines.append(f"  {kind}: {path}")
    return "\n".join(lines)
