"""The station's side of a heliostat: its optics from an analysis, and its figures as a record.

The analysis itself is :func:`~sofast_station.measure.heliostat.analyse_heliostat`; the optics
:func:`~sofast_station.optics.heliostat.heliostat_optics`; what an assembler does with the canting errors
:mod:`sofast_station.report.canting`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ensemble import EnsembleDesign
from ..measure.heliostat import HeliostatSettings
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


@dataclass(frozen=True)
class HeliostatJob:
    """What the loop's analysis worker needs to analyse a heliostat recipe (sent to it as plain data, in the
    place of a facet design: :meth:`to_dict` carries ``ensemble``, which the worker looks for)."""

    ensemble: EnsembleDesign
    heliostat: HeliostatSettings
    max_canting_mrad: float | None = None

    @property
    def name(self) -> str:
        return self.ensemble.name

    def to_dict(self) -> dict:
        return {"ensemble": self.ensemble.to_dict(), "heliostat": self.heliostat.to_dict(),
                "max_canting_mrad": self.max_canting_mrad}


def analyse_job(frames: np.ndarray, fringes, geometry, job: dict, settings, distance_m: float, rays_cam=None,
                optics: OpticsSettings | None = None, uncertainty=None, sensitivity_cache: dict | None = None):
    """A heliostat's analysis, optics and canting instructions in one call (the loop's worker runs it):
    ``(figures, valid, sensitivities)`` with *figures* the record's parts (``heliostat``, ``facets``,
    ``optics``, ``canting_instructions``, ``timings_s``), *valid* every facet's kept pixels and
    *sensitivities* {label: the record of the facet's sensitivities} (what a dump keeps)."""
    import time

    from ..measure.heliostat import analyse_heliostat
    from ..report.canting import canting_instructions

    ensemble = EnsembleDesign.from_dict(job["ensemble"])
    res = analyse_heliostat(frames, fringes, geometry, ensemble, distance_m, settings,
                            HeliostatSettings(**job["heliostat"]), rays_cam=rays_cam, uncertainty=uncertainty,
                            sensitivity_cache=sensitivity_cache)
    t = time.perf_counter()
    traced = None if optics is None else analysis_optics(res, ensemble, optics)
    figures = {"heliostat": res.figures["heliostat"], "facets": res.figures["facets"],
               "optics": None if traced is None else traced.figures,
               "canting_instructions": canting_instructions(res.figures, ensemble, job.get("max_canting_mrad")),
               "timings_s": {**res.timings_s, "optics": time.perf_counter() - t}}
    sensitivities = {ensemble.facets[i].label: a.sensitivities for i, a in res.analyses.items()
                     if a.sensitivities is not None}
    return figures, res.valid, sensitivities or None


def crop_box(dark: np.ndarray, white: np.ndarray, threshold_dn: float, margin_px: int = 32) -> tuple:
    """(row0, col0, row1, col1), end-exclusive: the box around every pixel that responds to the screen (every
    facet, not only the largest region), widened by *margin_px*, clipped to the image; the whole image when
    nothing responds (the analysis then says why)."""
    responsive = (white.astype(np.int32) - dark.astype(np.int32)) > threshold_dn
    h, w = dark.shape
    rows, cols = np.flatnonzero(responsive.any(axis=1)), np.flatnonzero(responsive.any(axis=0))
    if rows.size == 0:
        return 0, 0, h, w
    return (max(0, int(rows[0]) - margin_px), max(0, int(cols[0]) - margin_px),
            min(h, int(rows[-1]) + 1 + margin_px), min(w, int(cols[-1]) + 1 + margin_px))


def analysis_design(recipe, config):
    """What the loop's worker analyses for *recipe*: its facet design, or a heliostat recipe's
    :class:`HeliostatJob`."""
    if recipe.ensemble is None:
        return recipe.design
    return HeliostatJob(recipe.ensemble, config.heliostat, recipe.limits.max_canting_mrad)


def loop_record(head, figures: dict, recipe, truth: dict | None, **extra) -> dict:
    """The loop's record of a heliostat recipe's facet cycle, from the worker's *figures* (:func:`analyse_job`)."""
    from ..result.heliostat import heliostat_record

    timings = extra.pop("timings", {})
    timings = {**timings, **{f"analysis_{k}": v for k, v in figures.get("timings_s", {}).items()}}
    return heliostat_record(head, figures, recipe.ensemble, recipe.limits, recipe.quality, truth=truth,
                            optics=figures.get("optics"), instructions=figures.get("canting_instructions"),
                            timings=timings, **extra)
