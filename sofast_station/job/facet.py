"""One facet's measurement: :class:`FacetJob`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ..facet import FacetDesign
from ..measure.analysis import analyse
from ..measure.mask import facet_region
from ..measure.pipeline import AnalysisSettings
from ..optics import OpticsSettings
from ..optics.uncertainty import sensitivities_to_record
from ..result.optical_figures import add_optics
from ..result.record import build_record
from ..result.verdict import Limits, Quality, judge
from .base import Capture, Outcome, merged_timings

#: Pixels kept around the facet region: the corner windows reach 14 px beyond the edge.
CROP_MARGIN_PX = 32


def facet_crop_box(dark: np.ndarray, white: np.ndarray, threshold_dn: float, margin_px: int = CROP_MARGIN_PX
                   ) -> tuple[int, int, int, int]:
    """(row0, col0, row1, col1), end-exclusive: the facet region's bounding box widened by *margin_px*,
    clipped to the image. The whole image when nothing responds (the analysis then says why)."""
    region = facet_region(dark, white, threshold_dn)
    h, w = dark.shape
    if not region.any():
        return 0, 0, h, w
    rows = np.flatnonzero(region.any(axis=1))
    cols = np.flatnonzero(region.any(axis=0))
    return (max(0, int(rows[0]) - margin_px), max(0, int(cols[0]) - margin_px),
            min(h, int(rows[-1]) + 1 + margin_px), min(w, int(cols[-1]) + 1 + margin_px))


def preview(a, most: int = 6000) -> dict:
    """A thinned copy of an analysis's per-pixel results for the operator's slope-error map: every k-th camera
    row and column (at most about *most* points), as float32; a few hundred kB, a few ms."""
    rows, cols = np.nonzero(a.valid)
    k = max(1, int(np.ceil(np.sqrt(rows.size / most))))
    pick = (rows % k == 0) & (cols % k == 0)
    return {"step_px": k, "rows": rows[pick].astype(np.int32), "cols": cols[pick].astype(np.int32),
            "points_xy_m": np.asarray(a.points_facet_m[:2, pick], dtype=np.float32),
            "residuals_mrad": {m: np.asarray([e[0][pick], e[1][pick]], dtype=np.float32)
                               for m, e in a.residuals_mrad.items()},
            "corners_px": np.asarray(a.corners_px, dtype=np.float32)}


def with_optics_sensitivities(a, traced) -> dict | None:
    """The analysis *a*'s sensitivities as records, with the optical figures' (*traced*'s) when it has them."""
    sensitivities = a.sensitivities
    if sensitivities is not None and traced is not None and traced.sensitivities is not None:
        # the optical figures' too (those of the first facet of the type, on the line): a dump's re-analysis
        # states the line's optical U with them
        sensitivities = {**sensitivities, "optics": sensitivities_to_record(traced.sensitivities)}
    return sensitivities


@dataclass(frozen=True)
class FacetJob:
    """One facet: its design, the analysis's settings, the limits and quality it is judged by, and the optics
    its optical figures are traced with (None: none).

    A mirror of unknown outline (``design.outline_known`` False) and the plano model
    (``analysis.surface``) are this job with those options."""

    design: FacetDesign
    analysis: AnalysisSettings
    limits: Limits = Limits()
    quality: Quality = Quality()
    optics: OpticsSettings | None = None
    kind: ClassVar[str] = "facet"

    @property
    def name(self) -> str:
        return self.design.name

    def shows(self, fringes):
        """What the capture shows: the station's fringe set (dark, white, the fringes)."""
        return fringes

    def crop_box(self, dark: np.ndarray, white: np.ndarray) -> tuple[int, int, int, int]:
        """The facet region's box and a margin (:func:`facet_crop_box`)."""
        return facet_crop_box(dark, white, self.analysis.mask_threshold_dn)

    def analyse(self, capture: Capture, *, uncertainty=None, sensitivity_cache: dict | None = None,
                design_traces=None, attempt: int = 0) -> Outcome:
        """:func:`~sofast_station.measure.analysis.analyse` of the capture, then its optical figures."""
        a = analyse(capture.frames, capture.fringes, capture.geometry, self.design, capture.distance_m, self.analysis,
                    rays_cam=capture.rays_cam, uncertainty=uncertainty, sensitivity_cache=sensitivity_cache)
        traced = add_optics(a, self.design, self.optics, design_traces)
        return Outcome(a.figures, a.valid, with_optics_sensitivities(a, traced), None, a)

    def preview(self, outcome: Outcome) -> dict | None:
        """The operator's thinned slope-error map of *outcome* (:func:`preview`; 0.1-0.2 s at full resolution,
        so only the line's worker asks for it)."""
        return None if outcome.detail is None else preview(outcome.detail)

    def record(self, head, figures: dict, truth: dict | None = None, timings: dict | None = None, **extra) -> dict:
        """The facet's record (:func:`~sofast_station.result.record.build_record`), judged by
        :func:`~sofast_station.result.verdict.judge`."""
        return build_record(head, figures=figures, verdict=judge(figures, self.design, self.limits, self.quality),
                            truth=truth, timings=merged_timings(timings, figures), **extra)

    def dumped(self) -> None:
        """A facet's dump keeps its design and settings themselves: nothing more."""
        return None

    def pictures(self, record: dict, outcome: Outcome, folder) -> dict | None:
        """A facet writes no pictures with its record (the operator's map is drawn from its preview)."""
        return None
