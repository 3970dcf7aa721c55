"""A heliostat's measurement (several facets in one capture): :class:`HeliostatJob`, and its optics.

The analysis itself is :func:`~sofast_station.measure.heliostat.analyse_heliostat`; the optics
:func:`~sofast_station.optics.heliostat.heliostat_optics`; what an assembler does with the canting errors
:mod:`sofast_station.report.canting`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..ensemble import EnsembleDesign, load_ensemble
from ..errors import ConfigError
from ..files import safe_name
from ..measure.heliostat import HeliostatSettings, analyse_heliostat
from ..measure.pipeline import AnalysisSettings
from ..optics.facet import OpticsSettings, outline_area_m2
from ..optics.heliostat import FacetSurface, HeliostatOptics, heliostat_optics
from ..report.canting import canting_instructions
from ..result.heliostat import heliostat_record
from ..result.verdict import Limits, Quality
from .base import Capture, Outcome, merged_timings


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


def heliostat_crop_box(dark: np.ndarray, white: np.ndarray, threshold_dn: float, margin_px: int = 32) -> tuple:
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


def canting_design(ensemble: EnsembleDesign, folder, serial: str | None) -> tuple[EnsembleDesign, dict]:
    """The design heliostat *serial* is judged against: its canting prescription ``folder/SERIAL.toml``
    (``sofast-station field prescription``, docs/field.md) when the folder has one, else *ensemble* (the recipe's
    design); and what the record says of it (``canting_reference``).

    The prescription must be the same heliostat (its facets' labels, designs and places on the frame) with only
    the canting changed: the capture is laid out for the recipe's. Its name stays the recipe's design's (the
    record's ``facet``, the station's truth), only the canting changes.

    Returns
    -------
    (EnsembleDesign, dict)
        The design; ``{"source": "prescription", "file", "serial"}`` or ``{"source": "design", "design",
        "note"}`` (why no prescription applied).

    Raises
    ------
    ConfigError
        The prescription file does not load, or is another heliostat's layout.
    """
    folder = Path(folder)
    design = {"source": "design", "design": ensemble.name}
    if not serial:
        return ensemble, {**design, "note": "no serial: the recipe's design"}
    if safe_name(serial, 200) != serial:
        return ensemble, {**design, "note": f"the serial {serial!r} is not a plain file name: no prescription is "
                                            f"looked up in {folder}"}
    path = folder / f"{serial}.toml"
    if not path.is_file():
        return ensemble, {**design, "note": f"{path.name} is not in {folder}: the serial is not in the field layout"}
    prescribed = load_ensemble(path)
    theirs = {f.label: f for f in prescribed.facets}
    for f in ensemble.facets:
        g = theirs.get(f.label)
        if (g is None or len(theirs) != len(ensemble.facets) or g.design.name != f.design.name
                or not np.allclose(g.position_m[:2], f.position_m[:2], atol=1e-3)):
            raise ConfigError(f"canting prescription {path} is not the heliostat {ensemble.name!r} of the recipe "
                              f"(facet {f.label}: its label, design or place on the frame differs): write it from the "
                              "same heliostat file ('sofast-station field prescription') or correct the recipe")
    prescribed = dataclasses.replace(prescribed, name=ensemble.name)
    return prescribed, {"source": "prescription", "file": str(path), "serial": serial}


def write_pictures(record: dict, ensemble: EnsembleDesign, traced: HeliostatOptics | None, folder,
                   limit_mrad: float | None) -> dict:
    """The heliostat's PNGs in *folder*: the map of its facets and, with its optics, its flux maps; returns
    ``{"facet_map": path, "flux_maps": path}`` (as text)."""
    # lazy: Matplotlib, ~360 ms CPU; job/__init__.py loads this for every inspect and reprocess, only pictures need it
    from ..report.heliostat import save_facet_map, save_heliostat_flux

    folder = Path(folder)
    stem = f"{safe_name(record['serial'], 64)}-{record['time'][:19].replace(':', '')}"
    title = f"{ensemble.name} {record['serial']}: {record['verdict'].upper()}"
    out = {"facet_map": str(save_facet_map(record, ensemble, folder / f"{stem}-facets.png", limit_mrad, title))}
    if traced is not None:
        out["flux_maps"] = str(save_heliostat_flux(traced, folder / f"{stem}-flux.png", title))
    return out


@dataclass(frozen=True)
class HeliostatJob:
    """A heliostat's facets in one capture: its design (the ensemble), how its facets are told apart
    (``[heliostat]``), every facet's analysis settings, the limits and quality it is judged by (the canting
    limit, ``limits.max_canting_mrad``, among them) and its optics (None: none)."""

    ensemble: EnsembleDesign
    heliostat: HeliostatSettings
    analysis: AnalysisSettings
    limits: Limits = Limits()
    quality: Quality = Quality()
    optics: OpticsSettings | None = None
    #: What the canting is judged against when the recipe names prescriptions (:func:`canting_design`): the
    #: record's ``canting_reference``; None: the design, unsaid.
    canting_reference: dict | None = None
    kind: ClassVar[str] = "heliostat"

    @property
    def name(self) -> str:
        return self.ensemble.name

    def shows(self, fringes):
        """What the capture shows: the station's fringe set."""
        return fringes

    def crop_box(self, dark: np.ndarray, white: np.ndarray) -> tuple[int, int, int, int]:
        """The box around every facet (:func:`heliostat_crop_box`), not the largest region's."""
        return heliostat_crop_box(dark, white, self.analysis.mask_threshold_dn)

    def analyse(self, capture: Capture, *, uncertainty=None, sensitivity_cache: dict | None = None,
                design_traces=None, attempt: int = 0) -> Outcome:
        """Every facet's analysis and canting (:func:`~sofast_station.measure.heliostat.analyse_heliostat`),
        the heliostat's optics and the canting instructions: the record's parts (``heliostat``, ``facets``,
        ``optics``, ``canting_instructions``, ``timings_s``); the sensitivities by facet label."""
        res = analyse_heliostat(capture.frames, capture.fringes, capture.geometry, self.ensemble, capture.distance_m,
                                self.analysis, self.heliostat, rays_cam=capture.rays_cam, uncertainty=uncertainty,
                                sensitivity_cache=sensitivity_cache)
        t = time.perf_counter()
        traced = None if self.optics is None else analysis_optics(res, self.ensemble, self.optics)
        figures = {"heliostat": res.figures["heliostat"], "facets": res.figures["facets"],
                   "optics": None if traced is None else traced.figures,
                   "canting_instructions": canting_instructions(res.figures, self.ensemble,
                                                                self.limits.max_canting_mrad),
                   "timings_s": {**res.timings_s, "optics": time.perf_counter() - t}}
        sensitivities = {self.ensemble.facets[i].label: a.sensitivities for i, a in res.analyses.items()
                         if a.sensitivities is not None}
        return Outcome(figures, res.valid, sensitivities or None, None, (res, traced))

    def record(self, head, figures: dict, truth: dict | None = None, timings: dict | None = None, **extra) -> dict:
        """The heliostat's record, one entry per facet (:func:`~sofast_station.result.heliostat.heliostat_record`)."""
        return heliostat_record(head, figures, self.ensemble, self.limits, self.quality, truth=truth,
                                optics=figures.get("optics"), instructions=figures.get("canting_instructions"),
                                timings=merged_timings(timings, figures), canting_reference=self.canting_reference,
                                **extra)

    def preview(self, outcome: Outcome) -> dict | None:
        """A heliostat has no operator's map of one facet's slope errors."""
        return None

    def dumped(self) -> dict:
        """What a data dump keeps of the job beside the heliostat's layout design (``design`` of dump schema 2:
        ``ensemble``, ``heliostat``, ``max_canting_mrad``, and ``canting_reference`` when it has one;
        :func:`heliostat_job_of`)."""
        out = {"ensemble": self.ensemble.to_dict(), "heliostat": self.heliostat.to_dict(),
               "max_canting_mrad": self.limits.max_canting_mrad}
        if self.canting_reference is not None:
            out["canting_reference"] = self.canting_reference
        return out

    def pictures(self, record: dict, outcome: Outcome, folder) -> dict | None:
        """The map of its facets and its flux maps as PNG in *folder* (:func:`write_pictures`), from the same
        process's outcome (None when it has no detail: the worker's)."""
        if outcome.detail is None:
            return None
        _, traced = outcome.detail
        return write_pictures(record, self.ensemble, traced, folder, self.limits.max_canting_mrad)


def heliostat_job_of(dumped: dict, analysis: AnalysisSettings, limits: Limits = Limits(), quality: Quality = Quality(),
                     optics: OpticsSettings | None = None) -> HeliostatJob:
    """The :class:`HeliostatJob` of a dump's design entry (:meth:`HeliostatJob.dumped`), its canting limit the
    dumped one."""
    limits = dataclasses.replace(limits, max_canting_mrad=dumped.get("max_canting_mrad", limits.max_canting_mrad))
    return HeliostatJob(EnsembleDesign.from_dict(dumped["ensemble"]), HeliostatSettings(**dumped["heliostat"]),
                        analysis, limits, quality, optics, canting_reference=dumped.get("canting_reference"))
