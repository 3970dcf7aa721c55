"""Rerun a data dump's analysis from its raw frames and compare it with the archived result.

:func:`reprocess_dump` reads a dump (any schema version this software reads, with or without its
archived result), rebuilds the full frame stack and runs :func:`~sofast_station.measure.analysis.analyse`
on it with the dumped fringe definition, geometry, facet design, analysis settings and measured
distance, unless an :class:`Overrides` replaces one of them. It never returns a stored figure: every
figure of the new record is recomputed from the frames; the archived record is only read to compare.

With no overrides, the same software version on the same platform with BLAS on one thread reproduces
every measured figure of the archived record bit for bit (docs/conventions.md#determinism); the comparison
(:func:`compare_figures`) says so, or lists each figure that differs with both values.

Example::

    from sofast_station.reanalysis.reprocess import Overrides, reprocess_dump
    res = reprocess_dump("SIM-0001_....h5")
    res.exact                    # True: every archived figure reproduced
    res = reprocess_dump("SIM-0001_....h5", Overrides(focal_length_m=5.6))
    res.differences              # {"slope_rms_mrad.design.x": {"archived": ..., "new": ..., "difference": ...}, ...}
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import platform
import time
import tomllib
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..archive.dumps import DumpContent, read_dump
from ..archive.journal import Journal
from ..cache import SensitivityStore, capture_basis
from ..calibrate.records import load_radiometric
from ..errors import ArchiveError, ConfigError, DumpError, StationError
from ..facet import FacetDesign, load_facet
from ..files import json_ready, to_json
from ..job import Capture, FacetJob
from ..job.fixed import fixed_job_of
from ..job.heliostat import heliostat_job_of
from ..measure.pipeline import AnalysisSettings
from ..measure.sensitivity_record import frame_pool_of, from_record
from ..measure.uncertainty import InputUncertainties
from ..measure.uncertainty.capture_evidence import FRAME_POOL_CAPTURES
from ..optics import OpticsSettings
from ..optics.uncertainty import sensitivities_from_record
from ..precompute import ray_table
from ..result.faults import fault_reason
from ..result.optical_figures import DesignTraces, optics_for
from ..result.record import RecordHead, build_record, now_iso
from ..result.verdict import Limits, Quality, limits_from_table, quality_from_table
from ._env import blas_on_one_thread, blas_threads

log = logging.getLogger(__name__)

#: Keys of a result record that describe the cycle rather than measure the facet: not compared.
NOT_FIGURES = frozenset({"cycle_id", "serial", "time", "recipe", "station", "facet", "software_version", "config_hash",
                         "calibration", "camera", "request", "capture_notes", "crop_box", "timings_s", "truth",
                         "reprocess", "dump", "status", "archived", "differences", "error", "error_type",
                         "station_checks"})   # the line's checks of itself (display, temperature, reference)

#: The reported figures (docs/conventions.md#reported-figures; flattened names): the comparison table shows them
#: whether or not they changed, and the other (diagnostic) figures only when they changed.
HEADLINE = ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
            "principal_focal_lengths_m[0]", "principal_focal_lengths_m[1]", "axis_angle_rad", "twist_mrad_per_m",
            "twist_e1_mrad_per_m", "twist_e2_mrad_per_m",
            *(f"slope_rms_mrad.{m}.{c}" for m in ("design", "parabola", "higher_order")
              for c in ("x", "y", "magnitude")),
            "boresight_mrad.x", "boresight_mrad.y",
            *(f"placement.{u}[{i}]" for u in ("mm", "mrad") for i in range(3)),
            "n_points", "valid_fraction", "median_modulation_dn", "unwrap_disagreements",
            *(f"coefficients.{c}" for c in "ABCDEF"), "measured_distance_m", "verdict", "reasons")


# -- overrides -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Overrides:
    """What the engineer changes for a re-analysis; None leaves the dumped value.

    Attributes
    ----------
    facet_path : str or None
        A facet TOML file (``[facet]`` table, see :mod:`sofast_station.facet`) replacing the dumped design:
        its shape, outline, measure point and alignment point.
    focal_length_m : float or None
        Design focal length, metres (after *facet_path*).
    alignment_point_m : (float, float) or None
        (x, y) of the boresight alignment point in the facet frame, metres (after *facet_path*).
    measured_distance_m : float or None
        Distance from the screen centre to the design's measure point, metres.
    mask_threshold_dn : float or None
        A pixel belongs to the facet when white - dark exceeds this, DN.
    radiometric_path : str or None
        A radiometric calibration record (JSON). The frames were captured with the dumped record, so this
        changes only the result's calibration reference (see :func:`calibration_note`).
    """

    facet_path: str | None = None
    focal_length_m: float | None = None
    alignment_point_m: tuple[float, float] | None = None
    measured_distance_m: float | None = None
    mask_threshold_dn: float | None = None
    radiometric_path: str | None = None

    def __post_init__(self):
        for name in ("focal_length_m", "measured_distance_m"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(float(v)) and float(v) > 0):
                raise ConfigError(f"override {name} must be a positive number of metres, got {v}")
        if self.mask_threshold_dn is not None and not (math.isfinite(float(self.mask_threshold_dn))
                                                       and float(self.mask_threshold_dn) >= 0):
            raise ConfigError(f"override mask_threshold_dn must be a number of DN >= 0, got {self.mask_threshold_dn}")
        if self.alignment_point_m is not None:
            p = tuple(float(v) for v in self.alignment_point_m)
            if len(p) != 2 or not all(math.isfinite(v) for v in p):
                raise ConfigError(f"override alignment_point_m must be a finite (x, y) in metres, got "
                                  f"{self.alignment_point_m}")
            object.__setattr__(self, "alignment_point_m", p)
        for name in ("facet_path", "radiometric_path"):
            v = getattr(self, name)
            if v is not None:
                object.__setattr__(self, name, str(Path(v).expanduser().absolute()))

    @property
    def empty(self) -> bool:
        """No override: the dump's own configuration."""
        return all(getattr(self, f.name) is None for f in dataclasses.fields(self))

    @property
    def changes_analysis(self) -> bool:
        """Whether an override can change a measured figure (the calibration record cannot)."""
        return any(getattr(self, f.name) is not None for f in dataclasses.fields(self) if f.name != "radiometric_path")

    def to_dict(self) -> dict:
        """The overrides that are set (JSON-ready)."""
        return {f.name: (list(v) if isinstance(v, tuple) else v) for f in dataclasses.fields(self)
                if (v := getattr(self, f.name)) is not None}

    def check(self) -> None:
        """Read the files the overrides name, so that a bad one is reported once, before any dump.

        Raises
        ------
        ConfigError
            Naming the facet or calibration file and what is wrong with it.
        """
        if self.facet_path is not None:
            load_facet(self.facet_path)
        if self.radiometric_path is not None:
            load_radiometric(self.radiometric_path)

    @classmethod
    def from_dict(cls, d: dict | None) -> "Overrides":
        d = dict(d or {})
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ConfigError(f"unknown override(s) {', '.join(unknown)}")
        return cls(**d)


# -- the result ------------------------------------------------------------------------------------------
@dataclass
class ReprocessResult:
    """One dump reprocessed.

    Attributes
    ----------
    path : Path
        The dump.
    record : dict
        The new result record, recomputed from the frames, with the keys of ``sofast-station inspect
        --json`` (``timings_s`` holds the re-analysis's own timings, seconds) and ``reprocess`` (provenance).
    archived : dict or None
        The archived record (from the dump, or from the journal when the dump lost it); None when
        neither has it.
    differences : dict
        Flattened figure name -> ``{"archived", "new", "difference"}`` (difference = new - archived for
        numbers, else None) for every compared figure or U that is not identical (a U's entry names its
        figure under ``"uncertainty_of"``: :func:`compare_figures`).
    n_compared : int
        Number of figures and U compared.
    notes : list of str
        What the overrides can and cannot change, and anything else the engineer should know.
    analysis : Analysis or None
        The pipeline's full output (per-pixel arrays for plots); None when the analysis refused the
        capture (the record then holds the fault).
    design : FacetDesign
        The design the analysis used (the dumped one, or the overridden one).
    seconds : float
        Wall time of read and analysis, seconds.
    u_missing : list of str
        What of the line's uncertainty the dump does not keep ("its input uncertainties", "the frame-brightness
        pool"; an older dump's): its U may then differ from the archive's, and the notes say why.
    """

    path: Path
    record: dict
    archived: dict | None
    differences: dict
    n_compared: int
    overrides: Overrides
    dump_software_version: str
    schema_version: int
    archived_source: str
    notes: list = field(default_factory=list)
    analysis: object | None = field(default=None, repr=False)
    design: object | None = field(default=None, repr=False)
    seconds: float = 0.0
    u_missing: list = field(default_factory=list)

    @property
    def exact(self) -> bool | None:
        """True when every archived figure and U was reproduced bit for bit; None without an archived record."""
        if self.archived is None:
            return None
        return not self.differences

    @property
    def same_software(self) -> bool:
        return self.dump_software_version == __version__

    @property
    def uncertainty_differences(self) -> dict:
        """The entries of :attr:`differences` that are a figure's U (``name_U``, ``name_U_random``)."""
        return {k: d for k, d in self.differences.items() if "uncertainty_of" in d}

    def summary(self) -> str:
        """One sentence: reproduced exactly, or how many figures and U differ and why that may be."""
        n, k = self.n_compared, len(self.differences)
        n_u = len(self.uncertainty_differences)
        threads = "BLAS on 1 thread" if blas_on_one_thread() else f"BLAS threads {blas_threads()}"
        if self.archived is None:
            return (f"no archived result in the dump or the journal: {n} figures and U computed from the frames, "
                    "nothing to compare")
        where = "" if self.archived_source == "dump" else f" (archived record from {self.archived_source})"
        differ = f"{k} of {n} figures and U differ from the archive{where}" + (
            "" if not n_u else f" ({n_u} of them U)" if n_u < k else " (only U)")
        if not self.overrides.empty:
            if k == 0:
                return (f"no figure changed: all {n} figures and U identical to the archive{where} despite the "
                        "overrides")
            return f"{differ} with the overrides applied"
        if k == 0:
            return (f"reproduced exactly: all {n} archived figures and U identical{where} (sofast-station "
                    f"{__version__}, dump schema {self.schema_version}, {threads})")
        if n_u == k and self.u_missing:
            return (f"{differ}: every value reproduced, but the dump does not keep {' nor '.join(self.u_missing)} "
                    "the line's U came from (see the notes)")
        was, now = self.archived.get("verdict"), self.record.get("verdict")
        if (was == "fault") != (now == "fault"):
            why = "; ".join((self.archived if was == "fault" else self.record).get("reasons", []))
            return f"{differ}: the archive holds verdict {was!r}, reprocessing gives {now!r} ({why})"
        one_sided = [name for name, d in self.differences.items() if _ABSENT in (d["archived"], d["new"])]
        if one_sided:
            return (f"{differ}, and {len(one_sided)} exist on one side only (e.g. {one_sided[0]}): the dump was "
                    f"measured by other analysis code (dump written by sofast-station {self.dump_software_version}, "
                    f"this is {__version__})")
        if self.same_software:
            return (f"NOT reproduced: {differ} although the software version is the same ({__version__}): the "
                    f"platform (CPU, numpy or BLAS build) or the BLAS threads differ ({threads})")
        return (f"{differ}: the versions differ (the dump was measured by sofast-station "
                f"{self.dump_software_version}, this is {__version__})")

    def to_json(self) -> dict:
        """The JSON object of ``reprocess --json`` and of a batch result file (JSON-ready)."""
        out = {"dump": str(self.path), "status": "ok"}
        out.update(self.record)
        out["archived"] = self.archived
        out["differences"] = self.differences
        return json_ready(out)


# -- comparison ------------------------------------------------------------------------------------------
def is_uncertainty_key(key: str) -> bool:
    """Keys of the uncertainty: ``name_U``, ``name_U_random``, a focal length's interval from its focal power's U
    (``focal_length_x_m_interval``, result/focal.py) and the budget (flattened apart from the figures:
    :func:`flatten_figures`, :func:`flatten_uncertainties`)."""
    return key.endswith(("_U", "_U_random", "_interval")) or key == "uncertainty_budget"


def figure_of_uncertainty(name: str) -> str | None:
    """The flat figure name a flat uncertainty name belongs to (``slope_rms_mrad_U.design.x`` ->
    ``slope_rms_mrad.design.x``, ``facets[1].canting_mrad_U.y`` -> ``facets[1].canting_mrad.y``); None for
    a name that is no U (nor a random part ``_U_random``, nor a focal length's interval:
    ``focal_length_x_m_interval[1]`` -> ``focal_length_x_m``)."""
    parts = name.split(".")
    for i, part in enumerate(parts):
        base, bracket, index = part.partition("[")
        for suffix in ("_U", "_U_random", "_interval"):
            if base.endswith(suffix):      # an interval's ends ([0], [1]) are of the one figure
                parts[i] = base[:-len(suffix)] + ("" if suffix == "_interval" else bracket + index)
                return ".".join(parts)
    return None


def flatten_uncertainties(record: dict) -> dict:
    """Every expanded uncertainty of a record (``name_U``) and its random part (``name_U_random``) under a flat
    name (as :func:`flatten_figures` names the figures: ``slope_rms_mrad_U.design.x``), the budget left out
    (a table of three significant digits, derived from them)."""
    figures = flatten_figures(record)
    return {k: v for k, v in flatten_figures(record, uncertainties=True).items()
            if k not in figures and not k.startswith("uncertainty_budget")}


def flatten_figures(record: dict, uncertainties: bool = False) -> dict:
    """Every measured figure of a record under a flat name.

    Nested dicts give dotted names (``slope_rms_mrad.design.x``), lists of numbers one entry per element
    (``principal_focal_lengths_m[0]``); lists of text (``reasons``) stay whole. Keys in
    :data:`NOT_FIGURES` (time, serial, timings, ...) are left out, and so are the uncertainties
    (:func:`is_uncertainty_key`) unless *uncertainties*.

    Parameters
    ----------
    record : dict
        A result record (JSON-ready).
    uncertainties : bool
        Also the ``_U`` figures and the budget.

    Returns
    -------
    dict
        Flat name -> value, in record order.
    """
    out: dict = {}

    def walk(name: str, value) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                if k == "station_checks":                  # a heliostat's facets carry the cycle's checks too
                    continue
                if uncertainties or not is_uncertainty_key(str(k)):     # nested ones too (optics' _U)
                    walk(f"{name}.{k}" if name else str(k), v)
        elif isinstance(value, (list, tuple)) and value and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) or v is None for v in value):
            for i, v in enumerate(value):
                out[f"{name}[{i}]"] = v
        elif isinstance(value, (list, tuple)) and any(isinstance(v, (dict, list, tuple)) for v in value):
            for i, v in enumerate(value):
                walk(f"{name}[{i}]", v)
        else:
            out[name] = list(value) if isinstance(value, tuple) else value

    for key, value in json_ready(record).items():
        if key not in NOT_FIGURES and (uncertainties or not is_uncertainty_key(key)):
            walk(key, value)
    return out


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _same(a, b) -> bool:
    if _is_number(a) and _is_number(b):
        return float(a) == float(b)
    return a == b and type(a) is type(b) or (a is None and b is None)


_ABSENT = "(absent)"


def compare_figures(archived: dict, new: dict) -> tuple[dict, int]:
    """Compare two records figure by figure, and each figure's U (``name_U``, ``name_U_random``), exactly (bit
    for bit for floats): the dump keeps what the line's U came from (its input uncertainties, sensitivities
    and frame-brightness pool), so a re-analysis states the same U, and a U that moved is a difference.

    Parameters
    ----------
    archived, new : dict
        Result records (JSON-ready).

    Returns
    -------
    differences : dict
        Flat name -> ``{"archived": a, "new": b, "difference": b - a or None}`` for every figure or U that is
        not identical; a figure present on one side only has ``"(absent)"`` on the other. A U's entry (its
        name ``..._U...``) also names its figure under ``"uncertainty_of"``.
    n_compared : int
        Number of figures and U compared (the union of both sides).
    """
    fa, fb = flatten_figures(archived), flatten_figures(new)
    ua, ub = flatten_uncertainties(archived), flatten_uncertainties(new)
    names = list(fb) + [k for k in fa if k not in fb]
    u_names = list(ub) + [k for k in ua if k not in ub]
    diffs = {}
    for name, (old, new_) in [*((n, (fa, fb)) for n in names), *((n, (ua, ub)) for n in u_names)]:
        a, b = old.get(name, _ABSENT), new_.get(name, _ABSENT)
        if _same(a, b):
            continue
        d = float(b) - float(a) if _is_number(a) and _is_number(b) else None
        diffs[name] = {"archived": a, "new": b, "difference": d}
        if old is ua:
            diffs[name]["uncertainty_of"] = figure_of_uncertainty(name)
    return diffs, len(names) + len(u_names)


# -- pieces of the re-analysis ---------------------------------------------------------------------------
def _settings(content: DumpContent, overrides: Overrides, notes: list):
    known = {f.name for f in dataclasses.fields(AnalysisSettings)}
    dumped = dict(content.analysis)
    unknown = sorted(set(dumped) - known)
    if unknown:
        notes.append(f"the dump's analysis settings include {', '.join(unknown)}, which this software version "
                     "does not know; they are ignored, so figures may differ")
    settings = AnalysisSettings(**{k: v for k, v in dumped.items() if k in known})
    if overrides.mask_threshold_dn is not None:
        old = settings.mask_threshold_dn
        settings = dataclasses.replace(settings, mask_threshold_dn=overrides.mask_threshold_dn)
        notes.append(f"mask threshold {overrides.mask_threshold_dn:g} DN (archived {old:g} DN)"
                     + ("; the dump keeps only the box around the pixels that responded above the archived "
                        "threshold (plus a margin) and frames are 0 outside it, so a lower threshold can add "
                        "pixels only inside that box" if overrides.mask_threshold_dn < old else ""))
    return settings


def _design(content: DumpContent, overrides: Overrides, notes: list):
    design = content.facet_design()
    if overrides.facet_path is not None:
        old = design
        design = load_facet(overrides.facet_path)
        notes.append(f"facet model {design.name!r} from {overrides.facet_path} (archived {old.name!r}, "
                     f"f {old.focal_length_m:g} m)")
    changes = {}
    if overrides.focal_length_m is not None:
        changes["focal_length_m"] = float(overrides.focal_length_m)
        notes.append(f"design focal length {overrides.focal_length_m:g} m (was {design.focal_length_m:g} m)")
    if overrides.alignment_point_m is not None:
        changes["alignment_point_m"] = list(overrides.alignment_point_m)
        notes.append("alignment point ({:g}, {:g}) m (was ({:g}, {:g}) m)".format(
            *overrides.alignment_point_m, *design.alignment_point_m))
    if changes:
        design = FacetDesign.from_dict({**design.to_dict(), **changes}, source="re-analysis overrides")
    return design


def calibration_note(content: DumpContent, record) -> str:
    """What a calibration-record override can and cannot change, for this dump.

    Parameters
    ----------
    content : DumpContent
    record : RadiometricRecord
        The record the engineer names instead of the dumped one.
    """
    old = content.radiometric
    lut_old = np.asarray(old["lut"], dtype=np.float64)
    level = np.linspace(0.0, 1.0, 1001)
    d_cmd = 255.0 * float(np.max(np.abs(np.interp(level, np.linspace(0, 1, lut_old.size), lut_old)
                                        - np.interp(level, np.linspace(0, 1, record.lut.size), record.lut))))
    return (f"calibration record {record.record_id!r} (archived {old['record_id']!r}): the radiometric record "
            "shaped the fringes the display showed (its lookup table, floor and maximum levels) and set the "
            "camera's exposure and gain; the dumped frames were captured with the archived record and cannot "
            "change. The analysis reads nothing from the record, so every measured figure is recomputed from "
            "the same frames and only the result's calibration reference changes (camera exposure and gain "
            f"stay those of the capture). The two lookup tables differ by up to {d_cmd:.1f} display commands "
            "(of 255); to measure with the new record, capture the facet again")


def _uncertainty_inputs(content: DumpContent, notes: list):
    """The input uncertainties the line used (the dump's own record of them, 0.4.0 on), else those of the dumped
    station.toml's ``[uncertainty]`` (the defaults without one) with what the dumped radiometric record states
    of the display response (as the station derives it: ``config.py``).

    The sensitivities are computed from each dump itself (not shared between dumps), so a dump's
    re-analysis gives the same bits whatever else a batch worker analysed before it."""
    if isinstance(content.uncertainty_inputs, dict):
        try:
            return InputUncertainties.from_dict(content.uncertainty_inputs)
        except (ConfigError, TypeError, ValueError) as exc:
            notes.append(f"the dump's input uncertainties could not be read ({exc}): those of its station.toml are "
                         "used")
    try:
        raw = tomllib.loads(content.station_toml) if content.station_toml.strip() else {}
        out = InputUncertainties.from_table(raw.get("uncertainty", {}), f"station.toml of dump {content.path} "
                                                                         "[uncertainty]")
    except (tomllib.TOMLDecodeError, ConfigError, TypeError) as exc:
        notes.append(f"the dump's [uncertainty] could not be read ({exc}): the default input uncertainties are used")
        out = InputUncertainties()
    rad, fr, scr = content.radiometric, content.fringes, (content.geometry or {}).get("screen", {})
    try:
        samples = (scr["width_px"] / fr["periods_x"][-1], scr["height_px"] / fr["periods_y"][-1])
        return out.with_radiometric_record(rad["lut"], rad["floor_level"], rad["max_level"], samples)
    except (KeyError, TypeError, IndexError, ZeroDivisionError):
        return out


def _cache_entries(record) -> dict:
    """One sensitivity record as entries of an analysis's sensitivity cache: ``{key: Sensitivities}``, and
    the frame-brightness pool the line's analysis found (``{("frame brightness", key): deque}``) when the
    record keeps it; {} for a record this software cannot read."""
    found = from_record(record)
    if found is None:
        return {}
    out = {found[0]: found[1]}
    pool = frame_pool_of(record)
    if pool is not None:
        out[("frame brightness", found[0])] = deque(pool, maxlen=FRAME_POOL_CAPTURES)
    return out


def stored_sensitivities(content: DumpContent) -> dict | None:
    """The dump's own sensitivities as a cache for its analysis (``{key: Sensitivities}``, with the line's
    frame-brightness pool under ``("frame brightness", key)`` when the dump keeps it), or None.

    The analysis uses them only when its inputs hash to the same key (the same geometry, recipe and input
    uncertainties as the station's); otherwise, and for a dump without them, it computes them from the
    dump's capture. The pool is the earlier captures' frame brightness the line pooled this capture with, so
    the re-analysis states the line's U. A fresh dict per dump: nothing carries over from one dump to the
    next, so a dump's result does not depend on the order of a batch or on its worker.
    """
    stored = _cache_entries(content.sensitivities) if content.sensitivities is not None else {}
    return stored or None


def stored_design_traces(content: DumpContent, job):
    """A cache of the design's optical trace holding the optical figures' sensitivities the line used (the
    dump's, kept for the design and optics settings they were computed for), so the optical figures' U is the
    line's; None when the dump keeps none (they are then computed from this capture)."""
    stored = content.sensitivities
    optical = (sensitivities_from_record(stored["optics"]) if isinstance(stored, dict)
               and isinstance(stored.get("optics"), dict) else None)
    if optical is None or getattr(job, "optics", None) is None:
        return None
    traces = DesignTraces(1)
    traces.sensitivities[DesignTraces.key(job.design, job.optics)] = optical
    return traces


def sensitivity_store(content: DumpContent, measured_distance_m: float, disk_cache=None) -> dict:
    """The sensitivity cache of one dump's analysis: the dump's own sensitivities
    (:func:`stored_sensitivities`), then those computed earlier from this dump with the same inputs in the
    station's cache on disk (:class:`~sofast_station.cache.SensitivityStore`; its key names the dump's
    frames, so nothing computed from another dump is used). Without *disk_cache*, a plain dict."""
    def basis():
        return capture_basis(content.frames_cropped, measured_distance_m, crop_box=list(content.crop_box),
                             full_shape=list(content.full_shape))

    stored = stored_sensitivities(content)
    # A dump without sensitivities was analysed without a cache: its frame brightness stays its own.
    return SensitivityStore(disk_cache, basis, initial=stored, pool=stored is not None)


def _judge_settings(content: DumpContent, recipe: str, notes: list):
    """Limits and quality of the dumped station.toml (and of the record's recipe)."""
    if not content.station_toml.strip():
        notes.append("the dump holds no station.toml text: the verdict uses the default limits")
        return Limits(), Quality()
    try:
        raw = tomllib.loads(content.station_toml)
        where = f"station.toml of dump {content.path}"
        limits = limits_from_table(raw.get("limits", {}), f"{where} [limits]")
        quality = quality_from_table(raw.get("quality", {}), f"{where} [quality]")
        table = raw.get("recipes", {}).get(recipe) if recipe and recipe != "default" else None
        if isinstance(table, dict):
            limits = limits_from_table({**dataclasses.asdict(limits), **table.get("limits", {})},
                                       f"{where} [recipes.{recipe}].limits")
            quality = quality_from_table({**dataclasses.asdict(quality), **table.get("quality", {})},
                                         f"{where} [recipes.{recipe}].quality")
        return limits, quality
    except (tomllib.TOMLDecodeError, ConfigError, TypeError) as exc:
        notes.append(f"the dump's station.toml limits could not be read ({exc}): the verdict uses the default "
                     "limits")
        return Limits(), Quality()


def _optics_settings(content: DumpContent, recipe: str, archived: dict | None, overrides: Overrides, notes: list):
    """The optics settings of the dumped station.toml (and recipe), or None when the figures are not wanted.

    A record archived by software without optical figures is compared like for like: no trace then, unless
    the re-analysis changes something anyway (overrides).
    """
    if archived is not None and "optics" not in archived and overrides.empty:
        if archived.get("verdict") != "fault":
            notes.append("the archived record has no optical figures: not traced, so the comparison stays like "
                         "for like")
        return None
    try:
        raw = tomllib.loads(content.station_toml) if content.station_toml.strip() else {}
        return optics_for(raw, f"station.toml of dump {content.path}", recipe)
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        notes.append(f"the dump's [optics] could not be read ({exc}): optical figures with the defaults")
        return OpticsSettings()


def _archived_from_journal(journal: str | Path, cycle_id: str) -> dict | None:
    journal = Path(journal)
    if not journal.is_file():
        raise ArchiveError(f"journal {journal} does not exist")
    j = Journal(journal)
    try:
        row = j.get(cycle_id)
    finally:
        j.close()
    return None if row is None else row.record


def _config_hash(archived_hash: str, overrides: Overrides) -> str:
    if overrides.empty:
        return archived_hash
    blob = json.dumps({"archived": archived_hash, "overrides": overrides.to_dict()}, sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


# -- the re-analysis -------------------------------------------------------------------------------------
def reprocess_content(content: DumpContent, overrides: Overrides | None = None, *, archived: dict | None = None,
                      archived_source: str = "dump", read_s: float = 0.0, disk_cache=None) -> ReprocessResult:
    """Rerun the analysis of a dump already read (with its frames) and compare it with *archived*.

    Parameters
    ----------
    content : DumpContent
        From :func:`~sofast_station.archive.dumps.read_dump` with ``load_frames=True``.
    overrides : Overrides, optional
    archived : dict, optional
        The archived record to compare with; ``content.record`` by default (None when that is empty).
    archived_source : str
        Where *archived* came from, for the summary ("dump", or the journal's path).
    read_s : float
        Time it took to read the dump, seconds (for the record's timings).
    disk_cache : DiskCache, optional
        The station's cache on disk (:func:`~sofast_station.cache.open_cache`): sensitivities the dump does
        not carry are looked for there (computed from this dump, by this code) before they are computed,
        and kept there after. The figures are the same bits with or without it.

    Returns
    -------
    ReprocessResult
    """
    t0 = time.perf_counter()
    overrides = overrides or Overrides()
    if archived is None:
        archived = content.record or None
    notes: list[str] = []
    if archived is None:
        notes.append("the dump holds no archived result (its result group is missing)"
                     + ("" if archived_source == "dump" else f" and the journal {archived_source} has no row for "
                        f"cycle {content.cycle_id}") + ": nothing to compare")
    job, head, distance = job_of_dump(content, overrides, notes, archived)
    heliostat = job.kind == "heliostat"
    u_missing = uncertainty_not_kept(content, archived, notes)
    geometry = content.station_geometry()
    outcome = fault = None
    t1 = time.perf_counter()
    try:
        outcome = job.analyse(Capture(content.frames(), distance, content.fringe_set(), geometry,
                                      ray_table(geometry.camera)),
                              uncertainty=_uncertainty_inputs(content, notes),
                              sensitivity_cache=(_sensitivity_cache(content) if heliostat else
                                                 sensitivity_store(content, distance, disk_cache)),
                              design_traces=None if heliostat else stored_design_traces(content, job))
    except (DumpError, ConfigError):
        raise
    except StationError as exc:              # the analysis refuses the capture: a fault, as on the line
        fault = fault_reason(exc)
    t_analysis = time.perf_counter() - t1
    timings = {"read": read_s, "analysis": t_analysis}
    if outcome is None:
        record = build_record(head, fault=fault, timings=timings)
    else:
        # the twin's truth for the same pixels (simulated stations), when nothing was changed
        truth = archived.get("truth") if overrides.empty and archived and not heliostat else None
        # what the line noted of the capture itself (its retakes) is the capture's: kept
        capture = {"capture_notes": archived["capture_notes"]} if archived and "capture_notes" in archived else {}
        record = job.record(head, outcome.figures, truth, timings, measured_distance_m=distance, **capture)
        if heliostat and overrides.empty and archived and isinstance(archived.get("facets"), list):
            truth = {f.get("label"): f["truth"] for f in archived["facets"] if "truth" in f}
            for f in record["facets"]:
                if f.get("label") in truth:
                    f["truth"] = truth[f["label"]]
            if "truth" in archived:
                record["truth"] = archived["truth"]
    if heliostat:
        design = job.ensemble.layout_design()
        design_note = {"name": job.ensemble.name, "facets": job.ensemble.labels}
    else:
        design = job.design
        design_note = {"name": design.name, "focal_length_m": design.focal_length_m,
                       "alignment_point_m": design.alignment_point_m.tolist(),
                       "measure_point_m": design.measure_point_m.tolist()}
    analysis = None if outcome is None or heliostat else outcome.detail
    return _compared(record, content, overrides, archived, archived_source, notes, design_note,
                     analysis=analysis, design=design, seconds=time.perf_counter() - t0 + read_s, u_missing=u_missing)


def uncertainty_not_kept(content: DumpContent, archived: dict | None, notes: list) -> list[str]:
    """What the line's U came from that *content* (an older dump) does not keep, each said in *notes*: the
    input uncertainties in force (0.4.0 on: ``result/uncertainty_inputs_json``; without them the dumped
    station.toml's ``[uncertainty]`` and radiometric record stand in, and the camera, geometry and
    commissioning records that lent the line's budget are missing), the sensitivities (computed from the
    dump's capture instead of the station's warm-up capture), the optical figures' sensitivities (the first
    facet's of the type, on the line) and the frame-brightness pool (the earlier captures this capture's frame
    brightness was pooled with; without it, the capture's own few degrees of freedom widen or narrow its U).
    Empty for a dump that keeps them all: its U is the line's, bit for bit."""
    if archived is not None and not flatten_uncertainties(archived):
        return []                                  # the line stated no U: nothing to explain
    missing = []
    if not isinstance(content.uncertainty_inputs, dict):
        missing.append("its input uncertainties")
        notes.append("the dump does not keep the input uncertainties the line used (dumps before 0.4.0): they are "
                     "taken from its station.toml's [uncertainty] and its radiometric record; what the station's "
                     "camera, geometry or commissioning records lent the line's budget is not in the dump, so U "
                     "may differ from the archive's")
    stored = content.sensitivities
    records = [] if not isinstance(stored, dict) else [stored] if "version" in stored else list(stored.values())
    if not records:
        missing.append("its sensitivities")
        notes.append("the dump does not keep the uncertainty's sensitivities the line used: they are computed from "
                     "its own capture (the line's came from its warm-up capture), so U may differ from the "
                     "archive's in its last digits")
    elif "optics" in (archived or {}) and isinstance(stored, dict) and "version" in stored \
            and "optics" not in stored:
        missing.append("the optical figures' sensitivities")
        notes.append("the dump does not keep the optical figures' sensitivities the line used (those of the first "
                     "facet of its type): they are computed from its own capture, so the optical figures' U may "
                     "differ from the archive's")
    if records and any(frame_pool_of(r) is None for r in records):
        missing.append("the frame-brightness pool")
        fb = ((archived or {}).get("uncertainty_budget") or {}).get("frame_brightness") or {}
        line = (f": {fb['pooled_dn']} DN from {fb['captures']} captures, {fb['dof']} degrees of freedom"
                if fb.get("source") == "pooled" else "")
        notes.append("the dump does not keep the frame-brightness pool the line's U used (the line pools each "
                     f"capture's frame-to-frame brightness with the earlier captures'{line}); the re-analysis has "
                     "only the capture's own, with fewer degrees of freedom, so U differs from the archive's")
    return missing


def job_of_dump(content, overrides: Overrides, notes: list, archived: dict | None):
    """The job a dump was measured with (:mod:`sofast_station.job`), changed by *overrides*, with the head of
    its new record and the measured distance: ``(job, head, distance)``. Each choice the dump could not
    settle, or an override changed, is a line of *notes*.

    A heliostat's dump takes overrides of the analysis settings, the measured distance and the radiometric
    record; a facet file, focal length or alignment point cannot replace its facets (ConfigError)."""
    if is_heliostat_dump(content):
        if overrides.facet_path is not None or overrides.alignment_point_m is not None \
                or overrides.focal_length_m is not None:
            raise ConfigError(f"dump {content.path} is a heliostat's: its facets' designs and alignment points are "
                              "its heliostat file's; reprocess it without a facet file, focal length or alignment "
                              "point override")
        dumped = {k: content.design[k] for k in ("ensemble", "heliostat", "max_canting_mrad", "canting_reference")
                  if k in content.design}
        settings = _settings(content, overrides, notes)
        name = dumped["ensemble"]["name"]
        design = None
    else:
        design = _design(content, overrides, notes)
        settings = _settings(content, overrides, notes)
        name = design.name
    head, distance = _head_and_distance(content, overrides, archived, notes, name)
    optics = _optics_settings(content, head.recipe, archived, overrides, notes)
    limits, quality = _judge_settings(content, head.recipe, notes)
    if design is None:
        return heliostat_job_of(dumped, settings, limits, quality, optics), head, distance
    if content.design.get("method") == "fixed":
        return fixed_job_of(content.design, design, settings, limits, quality, optics), head, distance
    return FacetJob(design, settings, limits, quality, optics), head, distance


def _head_and_distance(content, overrides, archived: dict | None, notes: list, name: str):
    """The reprocessed record's head (design *name*, the radiometric record an override names) and the
    measured distance (the archived one, or the override's), with a note for each override."""
    distance = content.measured_distance_m
    if overrides.measured_distance_m is not None:
        distance = float(overrides.measured_distance_m)
        notes.append(f"measured distance {distance:.6f} m (archived {content.measured_distance_m:.6f} m)")
    rad = content.radiometric
    rad_id = rad["record_id"]
    if overrides.radiometric_path is not None:
        new_rad = load_radiometric(overrides.radiometric_path)
        notes.append(calibration_note(content, new_rad))
        rad_id = new_rad.record_id
    head = RecordHead(serial=content.serial, time=content.time, station=content.station_name,
                      config_hash=_config_hash(content.config_hash, overrides), calibration={"radiometric": rad_id},
                      camera={"exposure_s": rad["exposure_s"], "gain": rad["gain"]}, facet=name,
                      cycle_id=content.cycle_id, recipe=(archived or {}).get("recipe", "default"))
    return head, distance


def _compared(record: dict, content, overrides, archived: dict | None, archived_source: str, notes: list,
              design_note: dict, *, analysis, design, seconds: float, u_missing: list) -> "ReprocessResult":
    """The reprocessed *record* as a JSON archive holds it, compared with *archived*, with its ``reprocess``
    part (*design_note*: what design it was redone with)."""
    record = json.loads(to_json(record))     # exactly what a JSON archive holds (no numpy scalars)
    differences, n = compare_figures(archived, record) if archived else ({}, len(flatten_figures(record)))
    record["timings_s"]["total"] = seconds
    record["reprocess"] = json_ready({
        "at": now_iso(), "software_version": __version__, "dump_software_version": content.software_version,
        "dump_schema_version": content.schema_version, "dump_created": content.created,
        "design": design_note,
        "archived_from": archived_source if archived else None, "overrides": overrides.to_dict(), "notes": notes,
        "exact": None if not archived else not differences, "figures_compared": n,
        "figures_different": len(differences),
        "uncertainties_different": sum("uncertainty_of" in d for d in differences.values()),
        "blas_threads": blas_threads(),
        "platform": f"{platform.system()} {platform.machine()} Python {platform.python_version()} "
                    f"numpy {np.__version__}",
        "host": platform.node(), "pid": os.getpid()})
    res = ReprocessResult(path=Path(content.path) if content.path else Path(""), record=record, archived=archived,
                          differences=differences, n_compared=n, overrides=overrides,
                          dump_software_version=content.software_version, schema_version=content.schema_version,
                          archived_source=archived_source, notes=notes, analysis=analysis, design=design,
                          seconds=seconds, u_missing=u_missing)
    record["reprocess"]["summary"] = res.summary()
    log.debug("%s: %s", res.path, record["reprocess"]["summary"])
    return res


# -- a heliostat's dump (docs/heliostats.md) ---------------------------------------------------------
def is_heliostat_dump(content) -> bool:
    """Whether a dump's content is a heliostat's (its design carries the heliostat)."""
    return isinstance(content.design, dict) and "ensemble" in content.design


def _sensitivity_cache(content) -> dict | None:
    """The dump's per-facet sensitivities as one cache (``{key: Sensitivities}``, with each facet's frame-
    brightness pool where the dump keeps it: :func:`stored_sensitivities`), or None."""
    stored = content.sensitivities
    if not isinstance(stored, dict) or "version" in stored:
        return None
    cache = {}
    for rec in stored.values():
        cache.update(_cache_entries(rec))
    return cache or None


def reprocess_dump(path: str | Path, overrides: Overrides | None = None, *,
                   journal: str | Path | None = None, disk_cache=None) -> ReprocessResult:
    """Read a dump, rerun its analysis from the raw frames, and compare with the archived result.

    Parameters
    ----------
    path : str or Path
        The ``.h5`` data dump (any schema version up to this software's).
    overrides : Overrides, optional
        What to change; none reproduces the archived analysis.
    journal : str or Path, optional
        The station's journal (``journal.sqlite3``): where to find the archived record when the dump
        has lost its ``result`` group.
    disk_cache : DiskCache, optional
        The station's cache on disk (:func:`reprocess_content`).

    Returns
    -------
    ReprocessResult

    Raises
    ------
    DumpError
        The file is missing, empty, not HDF5, truncated, corrupt, foreign, of a newer schema, or lacks a
        dataset the analysis needs; the message names the file and the problem.
    ConfigError
        An override is invalid (a facet or calibration file that cannot be read, a bad value).
    """
    t0 = time.perf_counter()
    content = read_dump(path, load_frames=True, require_result=False)
    read_s = time.perf_counter() - t0
    archived, source = (content.record or None), "dump"
    if archived is None and journal is not None:
        archived = _archived_from_journal(journal, content.cycle_id)
        source = str(journal)
        if archived is None:
            log.warning("%s: cycle %s is not in the journal %s either", path, content.cycle_id, journal)
    return reprocess_content(content, overrides, archived=archived, archived_source=source, read_s=read_s,
                             disk_cache=disk_cache)
