"""The station's side of a heliostat: its optics from an analysis, and its figures as a record.

The analysis itself is :func:`~sofast_station.measure.heliostat.analyse_heliostat`; the optics
:func:`~sofast_station.optics.heliostat.heliostat_optics`; what an assembler does with the canting errors
:mod:`sofast_station.report.canting`.
"""

from __future__ import annotations

import numpy as np

from ..ensemble import EnsembleDesign
from ..optics.facet import OpticsSettings, outline_area_m2
from ..optics.heliostat import FacetSurface, HeliostatOptics, heliostat_optics


def facet_surfaces(result, ensemble: EnsembleDesign) -> list[FacetSurface]:
    """Every measured facet of a :class:`~sofast_station.measure.heliostat.HeliostatAnalysis` as the optics
    trace it: its points and slopes, where it is in the heliostat's optical frame, and its canting U."""
    by_index = {f["index"]: f for f in result.figures["facets"]}
    out = []
    for i in sorted(result.analyses):
        a = result.analyses[i]
        rotation, translation = result.facet_in_heliostat(i)
        corrected, _ = result.facet_in_heliostat(i, corrected=True)
        u = by_index[i].get("canting_mrad_U")
        u = None if u is None or u["x"] is None or u["y"] is None else np.array([u["x"], u["y"]])
        design = ensemble.facets[i].design
        out.append(FacetSurface(label=ensemble.facets[i].label, points_m=a.points_facet_m, slopes=a.slopes,
                                camera_m=a.facet_to_camera.inverse().translation,
                                area_m2=outline_area_m2(design.outline_m), rotation=rotation, translation=translation,
                                corrected_rotation=corrected, canting_u_mrad=u))
    return out


def analysis_optics(result, ensemble: EnsembleDesign, settings: OpticsSettings) -> HeliostatOptics:
    """The heliostat's design, measured and canting-corrected traces of an analysis."""
    return heliostat_optics(facet_surfaces(result, ensemble), ensemble, settings)


def inspect_heliostat(station, serial: str, frames: np.ndarray, distance: float, t_capture: float,
                      pictures_dir=None) -> dict:
    """The record of the heliostat captured in *frames* at the measured *distance* (``facets``, with
    ``truth`` on the twin): :func:`~sofast_station.station.inspection.inspect` for a heliostat station, after
    its capture (which took *t_capture* seconds). With *pictures_dir*, its flux maps and the map of its facets
    are written there as PNG (their paths in the record's ``pictures``)."""
    import time

    from ..measure.heliostat import analyse_heliostat
    from ..result.heliostat import heliostat_record

    config = station.config
    ensemble = config.ensemble
    t0 = time.perf_counter() - t_capture
    t1 = time.perf_counter()
    res = analyse_heliostat(frames, config.fringes, config.geometry, ensemble, distance, config.analysis,
                            config.heliostat, rays_cam=station.rays_cam, uncertainty=config.uncertainty,
                            sensitivity_cache=station.sensitivity_cache)
    t_analysis = time.perf_counter() - t1
    t2 = time.perf_counter()
    from ..report.canting import canting_instructions

    traced = None if config.optics is None else analysis_optics(res, ensemble, config.optics)
    instructions = canting_instructions(res.figures, ensemble, config.limits.max_canting_mrad)
    timings = {"capture": t_capture, "analysis": t_analysis,
               **{f"analysis_{k}": v for k, v in res.timings_s.items()}, "optics": time.perf_counter() - t2}
    record = heliostat_record(station.record_head(serial, facet=ensemble.name), res.figures, ensemble,
                              config.limits, config.quality, truth=station.truth(res.valid),
                              optics=None if traced is None else traced.figures, instructions=instructions,
                              measured_distance_m=distance, timings=timings)
    instructions["serial"] = serial
    if pictures_dir is not None:
        record["pictures"] = write_pictures(record, ensemble, traced, pictures_dir, config.limits.max_canting_mrad)
    record["timings_s"]["total"] = time.perf_counter() - t0
    return record


def write_pictures(record: dict, ensemble: EnsembleDesign, traced: HeliostatOptics | None, folder,
                   limit_mrad: float | None) -> dict:
    """The heliostat's PNGs in *folder*: the map of its facets and, with its optics, its flux maps; returns
    ``{"facet_map": path, "flux_maps": path}`` (as text)."""
    from pathlib import Path

    from ..archive._common import safe_name
    from ..report.heliostat import save_facet_map, save_heliostat_flux

    folder = Path(folder)
    stem = f"{safe_name(record['serial'], 64)}-{record['time'][:19].replace(':', '')}"
    title = f"{ensemble.name} {record['serial']}: {record['verdict'].upper()}"
    out = {"facet_map": str(save_facet_map(record, ensemble, folder / f"{stem}-facets.png", limit_mrad, title))}
    if traced is not None:
        out["flux_maps"] = str(save_heliostat_flux(traced, folder / f"{stem}-flux.png", title))
    return out


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
        lines.append(f"    90 % spot radius: measured {with_u(m['spot_radius_mrad'], m.get('spot_radius_mrad_U'), '', 3)}"
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
