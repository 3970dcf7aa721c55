"""The station's side of a heliostat: its record as the console shows it.

Measuring it is its job's (:class:`~sofast_station.job.heliostat.HeliostatJob`: the analysis, the optics, the
canting instructions and the record).
"""

from __future__ import annotations





def summary_text(rec: dict) -> str:
    """A readable summary of a heliostat's record (``value ± U``, k = 2): the verdict, the heliostat, one line
    per facet (its canting, focal power and slope error, with the twin's truth where there is one), its
    optics and what to turn."""
    from ..report.canting import instructions_text
    from ..result.formatting import with_u

    h = rec["heliostat"]
    lines = [f"Heliostat {rec['serial']} ({rec['facet']}) on {rec['station']}, {rec['time']}",
             f"  verdict: {rec['verdict'].upper()}" + "".join(f"\n    - {r}" for r in rec.get("reasons", []))
             + "".join(f"\n    warning: {w}" for w in rec.get("warnings", [])),
             "  figures are value ± U, the expanded uncertainty (k=2)",
             f"  {h['n_measured']} of {h['n_facets']} facets measured"
             + (f", {h['n_missing']} missing" if h.get("n_missing") else "")]
    pl, pu = h["placement"], h.get("placement_U") or {"mm": [None] * 3, "mrad": [None] * 3}
    lines.append("  placement in fixture      " + ", ".join(with_u(v, u, "", 2) for v, u in zip(pl["mm"], pu["mm"]))
                 + " mm, " + ", ".join(with_u(v, u, "", 2) for v, u in zip(pl["mrad"], pu["mrad"])) + " mrad")
    ct, cu = h["common_tilt_mrad"], h.get("common_tilt_mrad_U") or {}
    lines.append(f"  facets' common tilt       {with_u(ct['x'], cu.get('x'), '', 3)}, "
                 f"{with_u(ct['y'], cu.get('y'), '', 3)} mrad (against its corners: where it points, not canting)")
    lines.append(f"  canting RMS {h['canting_rms_mrad']:.3f} mrad, largest {h['canting_max_mrad']:.3f} mrad "
                 f"({h['canting_max_facet']})")
    truth_shown = any("truth" in f for f in rec["facets"])
    lines.append("  facet    verdict        canting x (mrad)   canting y (mrad)   focal power x, y (1/m)"
                 "     slope RMS (mrad)" + ("   truth: canting x, y" if truth_shown else ""))
    for f in rec["facets"]:
        if "canting_mrad" not in f:
            lines.append(f"  {f['label']:<8} {f.get('verdict', f['status']).upper():<14} {f['status']}: "
                         f"{f.get('reason', '')}")
            continue
        c, u = f["canting_mrad"], f.get("canting_mrad_U") or {}
        rms = f["slope_rms_mrad"]["parabola"]["magnitude"]
        text = (f"  {f['label']:<8} {f['verdict'].upper():<14} {with_u(c['x'], u.get('x'), '', 3, sign=True):>17}"
                f"  {with_u(c['y'], u.get('y'), '', 3, sign=True):>17}"
                f"   {f['curvature_x_per_m']:.5f}, {f['curvature_y_per_m']:.5f}   {rms:10.3f}")
        t = (f.get("truth") or {}).get("canting_mrad")
        if t:
            text += f"   {t['x']:+.3f}, {t['y']:+.3f}"
        lines.append(text)
    o = rec.get("optics")
    if o:
        m, d, c = o["measured"], o["design"], o["corrected"]
        cond = o["conditions"]
        lines.append(f"  optics at {cond['slant_range_m']:.1f} m, aperture {cond['aperture']}:")
        lines.append(f"    intercept: measured {with_u(m['intercept'], m.get('intercept_U'), '', 4)}, design "
                     f"{d['intercept']:.4f}, re-canted {with_u(c['intercept'], c.get('intercept_U'), '', 4)}")
        lines.append("    90 % spot radius: measured "
                     f"{with_u(m['spot_radius_mrad'], m.get('spot_radius_mrad_U'), '', 3)}"
                     f" mrad, design {d['spot_radius_mrad']:.3f}, re-canted "
                     f"{with_u(c['spot_radius_mrad'], c.get('spot_radius_mrad_U'), '', 3)} mrad")
    if rec.get("canting_instructions"):
        lines.append("")
        lines.extend("  " + ln if ln else "" for ln in instructions_text(rec["canting_instructions"]).splitlines())
    t = rec["timings_s"]
    lines.append(f"  time: capture {t['capture']:.2f} s, analysis {t['analysis']:.2f} s, total {t['total']:.2f} s")
    for kind, path in (rec.get("pictures") or {}).items():
        lines.append(f"  {kind}: {path}")
    return "\n".join(lines)
