"""The parts every job shares: the capture it analyses, what it gives back, and what a job must do."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..fringes import FringeSet
from ..geometry import StationGeometry


@dataclass(frozen=True)
class Capture:
    """One capture to analyse.

    Attributes
    ----------
    frames : (n, rows, columns) integer array
        Dark, white, then the fringe frames, camera counts (DN): full size, as the station restores its crop.
    distance_m : float
        The range finder's measured distance, metres.
    fringes : FringeSet
    geometry : StationGeometry
    rays_cam : RayTable, optional
        The camera's pixel rays, kept per process (:func:`~sofast_station.precompute.ray_table`).
    """

    frames: np.ndarray
    distance_m: float
    fringes: FringeSet
    geometry: StationGeometry
    rays_cam: object | None = None


@dataclass
class Outcome:
    """What a job's analysis gives.

    Attributes
    ----------
    figures : dict
        The figures (JSON-ready), with their U when the analysis had input uncertainties; ``timings_s`` holds
        the analysis's own step times.
    valid : (rows, columns) bool array
        The pixels the analysis kept (the twin's truth is stated on them).
    sensitivities : dict or None
        The uncertainty's sensitivities as records (what a dump keeps).
    preview : dict or None
        A thinned copy of the per-pixel results for the operator's map (a facet's; the worker fills it,
        :meth:`Job.preview`).
    detail : object or None
        The analysis itself (per-pixel arrays, a heliostat's traces), for pictures in the same process; never
        sent between processes.
    """

    figures: dict
    valid: np.ndarray
    sensitivities: dict | None = None
    preview: dict | None = None
    detail: object | None = None


class Job(Protocol):
    """A kind of measurement: what the programs call, and nothing else, to analyse, judge and record."""

    #: ``"facet"`` or ``"heliostat"``: says which kind the worker was sent.
    kind: str

    @property
    def name(self) -> str:
        """The design's name (the record's ``facet``, the worker's key for its usual analysis time)."""

    def shows(self, fringes):
        """What the capture shows, in order (the station's *fringes*, a :class:`~sofast_station.fringes.FringeSet`,
        or another set of patterns with ``patterns()``, ``slices()`` and ``n_frames``: a fixed pattern's)."""

    def crop_box(self, dark: np.ndarray, white: np.ndarray) -> tuple[int, int, int, int]:
        """(row0, col0, row1, col1), end-exclusive: what of the capture the station keeps and analyses; the
        programs hand it the capture's first two frames (``*frames[:2]``: one, when the capture is one frame)."""

    def analyse(self, capture: Capture, *, uncertainty=None, sensitivity_cache: dict | None = None,
                design_traces=None, attempt: int = 0) -> Outcome:
        """Reduce *capture* to figures (with their U given the input *uncertainty*). *sensitivity_cache* keeps the
        uncertainty's sensitivities between captures; *design_traces* the design's optical traces; *attempt*
        is 0 for an analysis, 1 for its rerun on the standby worker."""

    def preview(self, outcome: Outcome) -> dict | None:
        """The operator's thinned map of *outcome*'s per-pixel results, or None (what the line's page shows)."""

    def record(self, head, figures: dict, truth: dict | None = None, timings: dict | None = None, **extra) -> dict:
        """The result record of *figures* (an :class:`Outcome`'s) judged against the job's limits, with the
        twin's *truth* where there is one, *timings* (the analysis's own ``timings_s`` are added to them as
        ``analysis_*``) and *extra* keys (``measured_distance_m``, ``capture_notes``...)."""


def merged_timings(timings: dict | None, figures: dict) -> dict:
    """*timings* with the analysis's own step times (``figures["timings_s"]``) added as ``analysis_STEP``."""
    return {**(timings or {}), **{f"analysis_{k}": v for k, v in (figures.get("timings_s") or {}).items()}}
