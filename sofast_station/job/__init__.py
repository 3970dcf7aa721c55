"""What one measurement is, whoever asks for it: a *job* per kind of measurement.

The programs (``inspect``, the production loop and its analysis worker, ``reprocess``) do not analyse, judge
or build records themselves: each takes the job of its recipe (:func:`job_for`; a dump's:
:func:`~sofast_station.reanalysis.reprocess.job_of_dump`), hands it a :class:`Capture` and gets an
:class:`Outcome` (:meth:`analyse`), then asks it for the record (:meth:`record`). So a facet measured by
``inspect``, by the line and again by ``reprocess`` from its dump is one record, bit for bit (timings and
the cycle's own keys aside; tests/job/test_front_doors.py).

The kinds:

* :class:`~.facet.FacetJob`: one facet (its design, analysis settings, limits, quality and optics); a mirror
  of unknown outline (``FacetDesign.outline_known``) and the plano model (``AnalysisSettings.surface``) are
  options of it, not kinds;
* :class:`~.heliostat.HeliostatJob`: a heliostat's facets in one capture, each facet's figures and canting;
* :class:`~.fixed.FixedJob`: one facet by the fixed-pattern (dot grid) method (a recipe's ``method =
  "fixed"``): one frame of a dot grid instead of the fringes; what the capture shows is the job's
  (:meth:`~.base.Job.shows`), so the programs capture, crop and analyse it as any other.

A job is plain data (frozen dataclasses of designs and settings): the analysis worker receives it pickled,
with its ``kind``, and calls the same :meth:`analyse`. The simulated station may wrap a job to inject faults
into the worker (:mod:`sofast_station.station.simulated_faults`); production code has no test hooks.
"""

from __future__ import annotations

from .base import Capture, Job, Outcome
from .facet import FacetJob
from .fixed import FixedJob
from .heliostat import HeliostatJob, canting_design


def job_for(recipe, config, serial: str | None = None) -> Job:
    """The job of *recipe* (:class:`~sofast_station.recipes.Recipe`) on the station of *config*: a heliostat
    recipe's :class:`HeliostatJob` (with the station's ``[heliostat]`` settings), a fixed-pattern recipe's
    :class:`FixedJob`, else a :class:`FacetJob`.

    A heliostat recipe with a ``prescriptions`` folder measures the heliostat *serial* against its own canting
    prescription when the folder holds ``SERIAL.toml`` (:func:`~.heliostat.canting_design`), else against the
    recipe's design; its record's ``canting_reference`` says which."""
    if recipe.ensemble is not None:
        ensemble, reference = recipe.ensemble, None
        if getattr(recipe, "prescriptions", None) is not None:
            ensemble, reference = canting_design(recipe.ensemble, recipe.prescriptions, serial)
        return HeliostatJob(ensemble, config.heliostat, recipe.analysis, recipe.limits, recipe.quality,
                            recipe.optics, canting_reference=reference)
    if getattr(recipe, "fixed", None) is not None:
        return FixedJob(recipe.design, recipe.analysis, recipe.fixed, recipe.limits, recipe.quality, recipe.optics)
    return FacetJob(recipe.design, recipe.analysis, recipe.limits, recipe.quality, recipe.optics)


__all__ = ["Capture", "FacetJob", "FixedJob", "HeliostatJob", "Job", "Outcome", "job_for"]
