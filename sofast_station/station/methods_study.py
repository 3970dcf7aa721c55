"""Choosing between the methods, measured (issue 42 item 5): the fringes and the fixed pattern on the same
facets of the population study's stations (``sofast-station study methods``).

Each station is drawn as :mod:`~sofast_station.station.population` draws it (its kind, true facet, lens, edge model
and the twin's optics, from the same seed), on the kinds whose layout lets the fixed method index its dot grid (the
heliostat facet's and the nearly flat facet's stations: a dish's is refused,
:func:`~sofast_station.measure.fixed.check_fixed_layout`). Each of its captures is one placement of the facet and
one draw of the station's geometry within its stated uncertainties (in the twin only), photographed both ways: the
station's fringe frames (26 on the heliostat station, 18 on the flat one), and one frame of the dot grid a
fixed-pattern recipe of ``spacing_px = 12`` shows (:func:`~sofast_station.recipes.fixed_capture`), each with its
own noise. Both are analysed with their U (each method's sensitivities kept per station, as a station's worker
keeps them) and compared with the twin's truth at the points each kept.

Per method: per figure the coverage of |error| <= U and the RMS of error / (U / 2) (both ends of the coverage
band: :func:`~sofast_station.station.population.coverage_band`), the points per facet, the capture time
(frames x (settle + exposure): :func:`frame_time_s`, the settle time the station's display waits)
and the analysis's CPU time.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from ..calibrate.records import load_radiometric
from ..devices.renderer import FringeRenderer
from ..errors import ConfigError, StationError
from ..files import json_ready, write_json_atomic
from ..fringes import Pattern
from ..job.fixed import dot_locations, grid_image
from ..measure.analysis import analyse
from ..measure.fixed import analyse_fixed
from ..recipes import fixed_capture
from ..twin.truth import ground_truth
from .population import (EDGE_MODELS, PopulationStation, coverage_band, coverage_rows, draw_station,
                         judged_count)
from .study import Placement, capture_record, perturbed_geometry

#: The population's kinds whose stations the fixed method can measure (their layout indexes the dot grid).
FIXED_KINDS = ("heliostat", "flat")
#: The fixed-pattern recipe the study measures with: dots about 12 camera pixels apart on the nominal facet.
RECIPE_TABLE = {"spacing_px": 12.0}


def frame_time_s(config, radiometric) -> float:
    """Seconds one frame takes to capture on the station of *config*: the display's settle time (its latency
    calibration's, in the radiometric record, or station.toml's ``[devices] display_options.settle_s`` until
    one exists, 0.05 s by default: as the station's display waits) plus the exposure."""
    if radiometric.settle_s is not None:
        settle = float(radiometric.settle_s)
    else:
        settle = float(dict(config.raw.get("devices", {}).get("display_options", {})).get("settle_s", 0.05))
    return settle + float(radiometric.exposure_s)


def _dot_image(st: PopulationStation, grid):
    """The display's picture of *grid* (the station's renderer, as the line's simulated display draws it)."""
    record = load_radiometric(st.config.radiometric_path)
    scr = st.config.geometry.screen
    with FringeRenderer(scr.width_px, scr.height_px, lut=record.lut, floor_level=record.floor_level,
                        max_level=record.max_level) as renderer:
        return renderer.render_all([Pattern("image", image=grid_image(grid))])[0]


def _case(method: str, analysed, twin, place, cpu_s: float, capture_s: float, n_frames: int) -> dict:
    fig = analysed.figures
    return {"method": method, "n_points": int(fig["n_points"]), "analysis_cpu_s": cpu_s, "capture_s": capture_s,
            "n_frames": n_frames, **capture_record(fig, ground_truth(twin, analysed.valid), place)}


def run_methods(captures: int, seed: int = 0, per_station: int = 5, kinds=FIXED_KINDS, edges=tuple(EDGE_MODELS),
                progress=None) -> list[dict]:
    """Both methods on every capture of the drawn stations until *captures* captures (*per_station* on each):
    one case per method and capture (``method``, ``index``, ``kind``, ``capture``, the figures, U and truth,
    ``n_points``, ``analysis_cpu_s``, ``capture_s``), or ``outcome`` "refused" with its ``error``."""
    cases: list[dict] = []
    images: dict = {}
    placement = Placement()
    with tempfile.TemporaryDirectory() as tmp:
        index = 0
        while sum(c["method"] == "fringe" for c in cases) < captures:
            spec = draw_station(index, seed, kinds, edges)
            index += 1
            st = PopulationStation(spec, Path(tmp), images)
            cfg = st.config
            try:
                fixed = fixed_capture(RECIPE_TABLE, cfg, cfg.design, f"station {spec['index']} ({spec['kind']})")
            except ConfigError as exc:
                cases.append({"method": "fixed", "index": spec["index"], "kind": spec["kind"], "outcome": "layout",
                              "error": str(exc)})
                continue
            dots = dot_locations(fixed.grid, cfg.geometry)
            dot_img = _dot_image(st, fixed.grid)
            cal = st.calibration
            frame_s = frame_time_s(cfg, cal)
            fixed_cache: dict = {}
            rng = np.random.default_rng([seed, spec["index"], 0x3E7D])
            n = min(per_station, captures - sum(c["method"] == "fringe" for c in cases))
            for j in range(n):
                place = placement.draw(rng)
                geometry, d_error = perturbed_geometry(cfg.geometry, cfg.uncertainty, rng)
                twin = st.twin(geometry, *place)
                distance = twin.measured_distance_m() + d_error
                frames = st.capture(twin, np.random.default_rng(rng.integers(2**63)))
                frame_rng = np.random.default_rng(rng.integers(2**63))
                dot_frame = twin.capture(dot_img, frame_rng, exposure_s=cal.exposure_s, gain=cal.gain,
                                         flicker_phase=float(frame_rng.random()))
                base = {"index": spec["index"], "kind": spec["kind"], "edge": spec["edge"], "capture": j,
                        "read_noise_dn": spec["optics"]["read_noise_dn"]}
                for method in ("fringe", "fixed"):
                    c0 = time.process_time()
                    try:
                        if method == "fringe":
                            a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis,
                                        uncertainty=cfg.uncertainty, sensitivity_cache=st.cache)
                        else:
                            a = analyse_fixed(dot_frame, dots, cfg.geometry, cfg.design, distance, cfg.analysis,
                                              fixed.settings, uncertainty=cfg.uncertainty,
                                              sensitivity_cache=fixed_cache)
                    except StationError as exc:
                        cases.append({**base, "method": method, "outcome": "refused",
                                      "error": f"{type(exc).__name__}: {exc}"})
                        continue
                    n_frames = cfg.fringes.n_frames if method == "fringe" else fixed.n_frames
                    case = {**base, "outcome": "measured",
                            **_case(method, a, twin, place, time.process_time() - c0, n_frames * frame_s, n_frames)}
                    cases.append(case)
                    if progress:
                        progress(case)
    return cases


def summarise_methods(cases: list[dict]) -> dict:
    """Per method: captures measured and refused, per figure the coverage and RMS of error / (U / 2) with
    the coverage band of its count, the points per facet, capture and analysis time (medians); and the
    stations whose layout refused the fixed method."""
    out: dict = {"layout_refused": sorted({c["index"] for c in cases if c.get("outcome") == "layout"})}
    for method in ("fringe", "fixed"):
        mine = [c for c in cases if c["method"] == method and c.get("outcome") != "layout"]
        done = [c for c in mine if c["outcome"] == "measured"]
        # a station's first analysis computes its sensitivities (seconds, once per geometry): the steady ones
        steady = [c for c in done if c["capture"] > 0] or done
        rows = coverage_rows(done)
        for r in rows:
            r["band"] = list(coverage_band(judged_count(r)))
        out[method] = {
            "n": len(mine), "refused": [c.get("error") for c in mine if c["outcome"] == "refused"],
            "coverage": rows,
            "points": float(np.median([c["n_points"] for c in done])) if done else None,
            "frames": done[0]["n_frames"] if done else None,
            "capture_s": float(np.median([c["capture_s"] for c in done])) if done else None,
            "analysis_cpu_s": float(np.median([c["analysis_cpu_s"] for c in steady])) if done else None,
            "by_kind_points": {k: float(np.median([c["n_points"] for c in done if c["kind"] == k]))
                               for k in sorted({c["kind"] for c in done})}}
    return out


def methods_text(summary: dict) -> str:
    """The comparison as a table: per method its cost, then per figure both methods' coverage side by side."""
    lines = []
    for m in ("fringe", "fixed"):
        s = summary[m]
        if s["points"] is None:
            lines.append(f"{m}: nothing measured ({len(s['refused'])} refused)")
            continue
        lines.append(f"{m:<7} {s['n']} captures ({len(s['refused'])} refused), {s['frames']} frame(s): median "
                     f"{s['points']:,.0f} points per facet (" + ", ".join(f"{k} {v:,.0f}" for k, v in
                                                                         s["by_kind_points"].items())
                     + f"), capture {1e3 * s['capture_s']:.0f} ms, analysis {s['analysis_cpu_s']:.2f} s CPU (median, "
                     "a station's first analysis, which computes its sensitivities, left out)")
    if summary["layout_refused"]:
        lines.append(f"stations whose layout refused the fixed method: {summary['layout_refused']}")
    rows = {m: {r["figure"]: r for r in summary[m]["coverage"]} for m in ("fringe", "fixed")}
    lines.append(f"{'figure':<42}{'fringe: cov':>12}{'z rms':>7}{'n':>5}{'fixed: cov':>12}{'z rms':>7}{'n':>5}"
                 f"{'band (n of fixed)':>20}")
    for name in [*rows["fringe"], *(k for k in rows["fixed"] if k not in rows["fringe"])]:
        a, b = rows["fringe"].get(name), rows["fixed"].get(name)

        def cells(r):
            return f"{100 * r['coverage']:>11.1f}%{r['z_rms']:>7.2f}{r['n']:>5}" if r else f"{'-':>12}{'':>7}{'':>5}"
        band = f"{100 * b['band'][0]:.0f}-{100 * b['band'][1]:.0f} %" if b else ""
        lines.append(f"{name:<42}{cells(a)}{cells(b)}{band:>20}")
    return "\n".join(lines)


def study_methods(captures: int, seed: int = 0, per_station: int = 5, kinds=FIXED_KINDS, edges=tuple(EDGE_MODELS),
                  out_dir: Path | None = None, progress=None) -> dict:
    """:func:`run_methods`, :func:`summarise_methods` and :func:`methods_text`; the cases and the summary as
    ``methods-SEED-N.json`` (and the table as .txt) under *out_dir* when given."""
    t0 = time.perf_counter()
    cases = run_methods(captures, seed, per_station, kinds, edges, progress)
    summary = summarise_methods(cases)
    summary["seconds"] = time.perf_counter() - t0
    text = methods_text(summary)
    paths = {}
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        stem = out_dir / f"methods-{seed}-{captures}"
        write_json_atomic(stem.with_suffix(".json"), json_ready({"summary": summary, "cases": cases}))
        stem.with_suffix(".txt").write_text(text + "\n")
        paths = {"json": str(stem.with_suffix(".json")), "text": str(stem.with_suffix(".txt"))}
    return {"summary": summary, "text": text, "paths": paths, "cases": cases}


__all__ = ["FIXED_KINDS", "methods_text", "run_methods", "study_methods", "summarise_methods"]
