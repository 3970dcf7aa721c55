"""A heliostat's result: one record for the whole heliostat with one entry per facet, and its verdict.

The record (``inspect --json``, the journal, the dump, the workbook's rows) is the single facet's record
(:func:`~sofast_station.result.record.build_record`) for the heliostat, plus:

* ``heliostat``: the heliostat's own figures (pose, common tilt, canting RMS and largest, counts), from
  :func:`~sofast_station.measure.heliostat.analyse_heliostat`;
* ``facets``: one entry per facet of the design, in its order: ``index``, ``label``, ``serial`` (the
  heliostat's serial and the facet's label), ``status`` (measured, missing, hidden, cut off, invalid) and
  ``reason``; for a measured facet every single-facet figure with its U (built by ``build_record`` itself, so
  a facet's entry has a facet record's keys), ``canting_mrad`` {x, y} with ``canting_mrad_U``, its own
  ``verdict``, ``reasons`` and ``warnings``, and on the twin its ``truth`` (the facet's figures and canting);
* ``optics``: the heliostat's design, measured and re-canted traces
  (:func:`~sofast_station.optics.heliostat.heliostat_optics`), when ``[optics]`` is on;
* ``canting_instructions``: per facet which way and how far to turn it (:mod:`sofast_station.report.canting`);
* ``canting_reference`` (when the recipe names canting prescriptions, docs/field.md): what the canting errors
  are against: ``{"source": "prescription", "file", "serial"}`` (the heliostat's own place in the field) or
  ``{"source": "design", "design", "note"}`` (its serial has no prescription).

The verdict (:func:`judge_heliostat`): each measured facet as a single facet (:func:`~.verdict.judge`, its
optical limits left to the heliostat) and its canting against ``[limits] max_canting_mrad``; the heliostat
``invalid`` when a facet could not be measured for a reason of the measurement (hidden, cut off, refused),
else ``fail`` when a facet fails or is missing, ``indeterminate`` when one is, else ``pass``; the optical
limits on the heliostat's measured trace. Each reason names its facet.
"""

from __future__ import annotations

import dataclasses
import math

from .record import RecordHead, build_record
from .verdict import OPTICAL_LIMITS, Limits, Quality, judge, judge_optics

#: The head's keys, said once for the heliostat, not again in each facet's entry.
_HEAD_KEYS = ("cycle_id", "time", "recipe", "station", "facet", "software_version", "config_hash", "calibration",
              "camera", "request")
#: A facet's entry's keys that are the heliostat's business, not its own.
_FACET_DROP = ("uncertainty_budget", "timings_s", "window", "area_px", "expected_area_px")
#: Verdicts, the worst first.
_ORDER = ("invalid", "fail", "indeterminate", "pass")


def facet_serial(serial: str, label: str) -> str:
    """A facet's serial within a heliostat: the heliostat's serial and the facet's label (``H-0012-R1C2``)."""
    return f"{serial}-{label}"


def judge_canting(entry: dict, limits: Limits) -> tuple[list[str], list[str]]:
    """(fail reasons, indeterminate reasons) of a facet's canting against ``max_canting_mrad`` (its size,
    sqrt(x^2 + y^2); the guarded rule with its U along the error's direction)."""
    limit = limits.max_canting_mrad
    c = entry.get("canting_mrad")
    if limit is None or c is None:
        return [], []
    size = math.hypot(c["x"], c["y"])
    text = f"canting error {size:.3f} mrad (x {c['x']:+.3f}, y {c['y']:+.3f}; limit {limit:g})"
    if limits.decision_rule != "guarded":
        return ([text] if size > limit else []), []
    u = entry.get("canting_mrad_U") or {}
    ux, uy = u.get("x") or 0.0, u.get("y") or 0.0
    big_u = (math.hypot(c["x"] * ux, c["y"] * uy) / size) if size > 0 else max(ux, uy)
    excess = size - limit
    if excess > big_u:
        return [f"{text}, beyond the limit by more than its U {big_u:.3g}"], []
    if excess > -big_u:
        return [], [f"canting error {size:.3f} mrad is within its U {big_u:.3g} of the limit {limit:g}"]
    return [], []


#: The test uncertainty ratio wanted: the canting limit at least this many times the canting's U (a measurement
#: whose U is more than a third of the limit barely tells a facet within it from one beyond).
WANTED_RATIO = 3.0


def canting_resolution(facets: list[dict], limit_mrad: float | None) -> dict | None:
    """How well the facets' canting is known against its limit: the test uncertainty ratio, the limit over the
    largest U (a facet's U the larger of its two axes', k = 2: the error's direction is not known before it is
    measured), and a warning in plain words when U is more than a third of the limit (ratio below
    :data:`WANTED_RATIO`). None without a limit or without a measured facet's U.

    Returns
    -------
    dict or None
        ``limit_mrad``, ``U_mrad`` (the largest), ``facet`` (whose), ``ratio``, ``wanted_ratio``,
        ``coarse_facets`` (every facet with U over a third of the limit) and ``warning`` (None when there is
        none).
    """
    if limit_mrad is None:
        return None
    us = []
    for f in facets:
        u = f.get("canting_mrad_U") or {}
        if "canting_mrad" in f and u.get("x") is not None and u.get("y") is not None:
            us.append((max(float(u["x"]), float(u["y"])), f["label"]))
    if not us:
        return None
    worst_u, worst = max(us)
    ratio = limit_mrad / worst_u if worst_u > 0 else math.inf
    coarse = [label for u, label in us if u > limit_mrad / WANTED_RATIO]
    warning = None
    if coarse:
        which = (f"facet {coarse[0]}'s canting is" if len(coarse) == 1
                 else f"the canting of all {len(us)} facets measured is" if len(coarse) == len(us)
                 else f"the canting of {len(coarse)} of the {len(us)} facets measured is")
        warning = (f"the measurement barely tells the canting limit apart: {which} known only to "
                   f"{worst_u:.2f} mrad (U, k = 2; at worst, {worst}), more than a third of the {limit_mrad:g} mrad "
                   f"limit (test uncertainty ratio {ratio:.1f}; {WANTED_RATIO:g} or more is wanted). A facet near "
                   "the limit may be passed or failed wrongly: measure with more camera pixels on each facet (a longer "
                   "lens or a closer camera), or agree a wider limit")
    return {"limit_mrad": limit_mrad, "U_mrad": worst_u, "facet": worst, "ratio": ratio,
            "wanted_ratio": WANTED_RATIO, "coarse_facets": coarse, "warning": warning}


def _worst(verdicts) -> str:
    return min(verdicts, key=_ORDER.index) if verdicts else "invalid"


def judge_heliostat(facets: list[dict], designs: dict, limits: Limits, quality: Quality,
                    optics: dict | None = None) -> dict:
    """The heliostat's verdict, and each facet's (set in its entry): see the module docstring.

    Parameters
    ----------
    facets : list of dict
        The record's facet entries (``label``, ``status``, ``reason``, the figures of a measured one); each
        gets its ``verdict``, ``reasons`` and ``warnings``.
    designs : dict
        Facet label -> its FacetDesign.
    limits, quality : Limits, Quality
    optics : dict, optional
        The heliostat's optical figures (``measured``: the trace the optical limits apply to).

    Returns
    -------
    dict
        ``verdict``, ``reasons`` and ``warnings`` of the heliostat.
    """
    per_facet = dataclasses.replace(limits, **{k: None for k in OPTICAL_LIMITS})
    reasons: dict[str, list] = {v: [] for v in _ORDER}
    warnings = []
    for e in facets:
        label = e["label"]
        if e["status"] in ("missing", "hidden", "cut off", "invalid") and "canting_mrad" not in e:
            verdict = "fail" if e["status"] == "missing" else "invalid"
            e.update(verdict=verdict, reasons=[e.get("reason", f"facet {label} was not measured")], warnings=[])
            reasons[verdict].append(f"{label}: {e['reasons'][0]}")
            continue
        v = judge(e, designs[label], per_facet, quality)
        fail, unsure = judge_canting(e, limits)
        if v["verdict"] != "invalid" and fail:
            v = {"verdict": "fail", "reasons": [r for r in v["reasons"]] + fail, "warnings": v["warnings"]}
        elif v["verdict"] in ("pass", "indeterminate") and unsure:
            v = {"verdict": "indeterminate", "reasons": v["reasons"] + unsure, "warnings": v["warnings"]}
        e.update(v)
        reasons[v["verdict"]].extend(f"{label}: {r}" for r in v["reasons"])
        warnings.extend(f"{label}: {w}" for w in v["warnings"])
    heliostat_fail = judge_optics(None if optics is None else optics.get("measured"), limits)
    reasons["fail"].extend(f"heliostat: {r}" for r in heliostat_fail)
    for verdict in _ORDER[:-1]:
        if reasons[verdict]:
            shown = reasons[verdict] + (reasons["fail"] if verdict == "invalid" else [])
            return {"verdict": verdict, "reasons": shown, "warnings": warnings}
    return {"verdict": "pass", "reasons": [], "warnings": warnings}


def heliostat_record(head: RecordHead, figures: dict, ensemble, limits: Limits, quality: Quality, *,
                     truth: dict | None = None, optics: dict | None = None, instructions: dict | None = None,
                     timings: dict | None = None, canting_reference: dict | None = None, **extra) -> dict:
    """A heliostat's result record (see the module docstring).

    Parameters
    ----------
    head : RecordHead
        The heliostat's (its serial; ``facet`` its design's name).
    figures : dict
        :attr:`~sofast_station.measure.heliostat.HeliostatAnalysis.figures`: ``heliostat`` and ``facets``.
    ensemble : EnsembleDesign
    limits, quality : Limits, Quality
    truth : dict, optional
        The twin's :func:`~sofast_station.twin.heliostat.heliostat_truth`.
    optics : dict, optional
        The heliostat's optical figures.
    instructions : dict, optional
        :func:`~sofast_station.report.canting.canting_instructions`.
    timings : dict, optional
    canting_reference : dict, optional
        What the canting is against (:func:`~sofast_station.job.heliostat.canting_design`); None: the design,
        unsaid.
    **extra
        More keys after the heliostat's figures (``measured_distance_m``, ``capture_notes``...).
    """
    designs = {f.label: f.design for f in ensemble.facets}
    facets = []
    for f in figures["facets"]:
        if "focal_length_x_m" in f:          # measured: a facet record's keys, from the one builder
            facet_truth = None if truth is None else truth.get("facets", {}).get(f["label"])
            entry = build_record(dataclasses.replace(head, serial=facet_serial(head.serial, f["label"])),
                                 figures=f, truth=facet_truth)
            for k in _HEAD_KEYS + _FACET_DROP:
                entry.pop(k, None)
            if facet_truth is not None:
                entry["truth"].update({k: facet_truth[k] for k in ("canting_mrad", "canting_rz_mrad")
                                       if k in facet_truth})
        else:
            entry = {k: v for k, v in f.items() if k not in _FACET_DROP}
            entry["serial"] = facet_serial(head.serial, f["label"])
        facets.append(entry)
    verdict = judge_heliostat(facets, designs, limits, quality, optics)
    out = head.to_dict()
    out["heliostat"] = dict(figures["heliostat"])
    if canting_reference is not None:
        out["canting_reference"] = dict(canting_reference)
    out.update(extra)
    out["facets"] = facets
    if optics is not None:
        out["optics"] = optics
    if instructions is not None:
        # made by the job before the record had a serial: the instructions name the heliostat they are for
        out["canting_instructions"] = {**instructions, "serial": head.serial}
    out.update(verdict)
    if truth is not None:
        out["truth"] = {"heliostat": truth.get("heliostat")}
    out["timings_s"] = dict(timings or {})
    return out


def is_heliostat_record(record: dict) -> bool:
    """Whether *record* is a heliostat's (it has a ``facets`` list)."""
    return isinstance(record.get("facets"), list)
