"""One facet measured by the fixed-pattern (dot grid) method: :class:`FixedJob`, and what its capture shows.

The recipe's ``method = "fixed"`` (recipes.py) gives this job instead of :class:`~.facet.FacetJob`: the same
design, settings, limits, quality and optics, and the dot grid its station's display shows
(:class:`~sofast_station.measure.fixed.FixedCapture`). The programs do not tell the two apart: they show
what the job's capture shows (:meth:`FixedJob.shows`: the dot frame, after a dark and a white one when the
recipe allows them), crop as the job crops and hand the frames to :meth:`FixedJob.analyse`
(:func:`~sofast_station.measure.fixed.analyse_fixed`, its dot locations from the display's pixel grid and
the screen's model, :func:`~sofast_station.measure.fixed.lcd_dot_locations`). Its figures carry
``method = "fixed"``, the point count (one point per dot used) and the ``dots`` block.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from typing import ClassVar

import numpy as np

from ..facet import FacetDesign
from ..fringes import DisplayImage, Pattern
from ..measure.dots import DotLocations
from ..measure.fixed import DotPattern, FixedCapture, LcdDotGrid, analyse_fixed, lcd_dot_locations, lit_background
from ..measure.pipeline import AnalysisSettings, default_screen
from ..optics import OpticsSettings
from ..result.optical_figures import add_optics
from ..result.record import build_record
from ..result.verdict import Limits, Quality, judge
from .base import Capture, Outcome, merged_timings
from .facet import CROP_MARGIN_PX, facet_crop_box, preview, with_optics_sensitivities


@lru_cache(maxsize=4)
def grid_image(grid: LcdDotGrid) -> DisplayImage:
    """The display image of *grid* (drawn once per grid: a 2400 x 2400 display's takes a few tenths of a s)."""
    return DisplayImage(grid.image(), f"dot grid {grid.pitch_px} px")


@dataclass(frozen=True)
class DotFrames:
    """What a fixed-pattern capture shows, in the capture's order (the role :class:`~sofast_station.fringes.FringeSet`
    plays for the fringes in :func:`~sofast_station.station.frames.capture_sequence`): a dark and a white frame
    when the recipe allows them, then the dot grid. No four-step sets, so nothing to check and retake."""

    capture: FixedCapture

    @property
    def n_frames(self) -> int:
        return self.capture.n_frames

    def patterns(self) -> list[Pattern]:
        dots = Pattern("image", image=grid_image(self.capture.grid))
        if self.capture.white_frame:
            return [Pattern("uniform", command=0), Pattern("uniform", command=255), dots]
        return [dots]

    def slices(self) -> dict[str, list[slice]]:
        return {"x": [], "y": []}

    def to_dict(self) -> dict:
        return {"method": "fixed", **self.capture.to_dict()}


_LOCATIONS: dict = {}


def dot_locations(grid: LcdDotGrid, geometry) -> DotLocations:
    """*grid*'s dots on the display of *geometry* (its measured screen, or the flat screen of its pitch), kept
    per grid and geometry (a process analyses one station's facets)."""
    key = (grid, json.dumps(geometry.to_dict(), sort_keys=True, default=str))
    if key not in _LOCATIONS:
        if len(_LOCATIONS) >= 8:
            _LOCATIONS.clear()
        _LOCATIONS[key] = lcd_dot_locations(grid, default_screen(geometry))
    return _LOCATIONS[key]


@dataclass(frozen=True)
class FixedJob:
    """One facet by the fixed-pattern method: :class:`~.facet.FacetJob`'s design, settings, limits, quality and
    optics, and the dot grid the display shows (*fixed*)."""

    design: FacetDesign
    analysis: AnalysisSettings
    fixed: FixedCapture
    limits: Limits = Limits()
    quality: Quality = Quality()
    optics: OpticsSettings | None = None
    kind: ClassVar[str] = "facet"
    method: ClassVar[str] = "fixed"

    @property
    def name(self) -> str:
        return self.design.name

    def shows(self, fringes) -> DotFrames:
        """What the capture shows: the dot grid (after a dark and a white frame when the recipe allows them),
        not the station's fringes."""
        return DotFrames(self.fixed)

    def crop_box(self, first: np.ndarray, second: np.ndarray | None = None) -> tuple[int, int, int, int]:
        """(row0, col0, row1, col1), end-exclusive. With a dark and a white frame (*first*, *second*) the facet
        region's box (:func:`~.facet.facet_crop_box`); with the dot frame alone (*first*) its lit area's
        (:func:`~sofast_station.measure.fixed.lit_background`'s box: the lit facet, its dots filled in), widened
        by the same margin."""
        if second is not None and self.fixed.white_frame:
            return facet_crop_box(first, second, self.analysis.mask_threshold_dn)
        h, w = np.shape(first)
        _, (r0, r1, c0, c1) = lit_background(first, self.fixed.settings.max_dot_diameter_px,
                                             self.fixed.settings.dark_dots)
        m = CROP_MARGIN_PX
        return max(0, r0 - m), max(0, c0 - m), min(h, r1 + m), min(w, c1 + m)

    def analyse(self, capture: Capture, *, uncertainty=None, sensitivity_cache: dict | None = None,
                design_traces=None, attempt: int = 0) -> Outcome:
        """:func:`~sofast_station.measure.fixed.analyse_fixed` of the dot frame (the capture's last of its
        :attr:`~DotFrames.n_frames`; the line's worker hands every capture in a buffer of the fringes' size),
        with the dark and white frames when there are, then the optical figures."""
        n = self.fixed.n_frames
        frames = capture.frames[:n]
        dark, white = (frames[0], frames[1]) if self.fixed.white_frame else (None, None)
        dots = dot_locations(self.fixed.grid, capture.geometry)
        a = analyse_fixed(frames[n - 1], dots, capture.geometry, self.design, capture.distance_m, self.analysis,
                          self.fixed.settings, white=white, dark=dark, uncertainty=uncertainty,
                          sensitivity_cache=sensitivity_cache)
        traced = add_optics(a, self.design, self.optics, design_traces)
        return Outcome(a.figures, a.valid, with_optics_sensitivities(a, traced), None, a)

    def preview(self, outcome: Outcome) -> dict | None:
        """The operator's map: one point per dot used (:func:`~.facet.preview`)."""
        return None if outcome.detail is None else preview(outcome.detail)

    def record(self, head, figures: dict, truth: dict | None = None, timings: dict | None = None, **extra) -> dict:
        """The facet's record, as :meth:`~.facet.FacetJob.record` (its figures carry ``method`` and ``dots``)."""
        return build_record(head, figures=figures, verdict=judge(figures, self.design, self.limits, self.quality),
                            truth=truth, timings=merged_timings(timings, figures), **extra)

    def dumped(self) -> dict:
        """What a dump keeps of the job beside the facet's design: the dot grid and the method's settings
        (``fixed`` of dump schema 5; :func:`fixed_job_of`)."""
        return {"method": "fixed", "fixed": self.fixed.to_dict()}

    def pictures(self, record: dict, outcome: Outcome, folder) -> dict | None:
        return None


def fixed_job_of(dumped: dict, design: FacetDesign, analysis: AnalysisSettings, limits: Limits = Limits(),
                 quality: Quality = Quality(), optics: OpticsSettings | None = None) -> FixedJob:
    """The :class:`FixedJob` of a dump's entry (:meth:`FixedJob.dumped`)."""
    return FixedJob(design, analysis, FixedCapture.from_dict(dumped["fixed"]), limits, quality, optics)


__all__ = ["DotFrames", "DotPattern", "FixedJob", "dot_locations", "fixed_job_of", "grid_image"]
