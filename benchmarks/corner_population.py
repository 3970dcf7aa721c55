"""Corners and the figures they decide over a drawn population of stations, captures and edge models.

    .venv/bin/python benchmarks/corner_population.py                       # 400 cases, seed 26
    .venv/bin/python benchmarks/corner_population.py --cases 40 --out /tmp/pop.json
    .venv/bin/python benchmarks/corner_population.py --merge a.json b.json  # the table over saved runs

Each case draws:

* a facet kind: the dish, the gore (both f 5.33 m), the heliostat (f 100 m) or a nearly flat facet (the
  heliostat's outline with a design focal length of 800 m, truly 760-840 m), each with its fixture's station
  (``station.toml``, ``fixtures/stations/*.toml``) at a quarter of its camera's resolution (400 x 300 px,
  the same field of view);
* the lens's radial distortion k1 from {-0.3, -0.15, 0, 0.15, 0.3} (the analysis knows it; the sensitivities
  are computed once per kind and k1);
* a placement within the fixture's tolerance (+-1 mm, +-0.5 mm in z, +-1 mrad; ``study.Placement``) and the
  station's geometry drawn within its stated uncertainties (``[uncertainty]``) for the twin only, as
  ``benchmarks/uncertainty_coverage.py`` does;
* read noise uniform in 0.3-5 DN (with the twin's shot noise, ambient jitter and flicker-free exposure);
* one edge model of ``twin/edges.py``: exact area, centre-ray point sampling, a 2 x 2 sub-ray grid, a
  Gaussian (0.3-1.5 px) or disk (0.5-2.5 px) blur, strong vignetting (0.3-0.8 at the corner, exponent 2, 4
  or 6), or a bevelled rim of 1, 2 or 3 mm (tilted 1-10 mrad: lit, other fringes; or 100-500 mrad: dark;
  reflectance 0.3-1) that the design declares (``edge_rim_m``).

Printed: the corners' RMS error against the twin's true corner pixels per edge model (median, 90th
percentile, the fraction within 0.1 px) and per kind; then per figure the coverage of U (|error| <= U,
target 95 +- 3 %: over 400 cases the binomial standard deviation is 1.1 %), the median U and the errors'
spread; the gore's twist error. Nothing is asserted (``tests/test_benchmarks.py`` runs a small version).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: Station file and true facet of each kind (the station tests' facets; the near-flat one is drawn).
KINDS = {
    "dish": ("station.toml", {"focal_length_x_m": 5.42, "focal_length_y_m": 5.35, "twist_mrad_per_m": 0.1,
                              "slope_error_rms_mrad": 0.5, "slope_error_correlation_m": 0.02, "surface_seed": 11}),
    "gore": ("fixtures/stations/gore.toml", {"focal_length_x_m": 5.42, "focal_length_y_m": 5.35,
                                             "twist_mrad_per_m": 0.12, "slope_error_rms_mrad": 0.5,
                                             "slope_error_correlation_m": 0.03, "surface_seed": 5}),
    "heliostat": ("fixtures/stations/heliostat.toml", {"focal_length_x_m": 95.0, "focal_length_y_m": 104.0,
                                                       "twist_mrad_per_m": 0.05, "slope_error_rms_mrad": 0.3,
                                                       "slope_error_correlation_m": 0.04, "surface_seed": 9}),
    "near-flat": ("fixtures/stations/heliostat.toml", {"twist_mrad_per_m": 0.02, "slope_error_rms_mrad": 0.3,
                                                       "slope_error_correlation_m": 0.04, "surface_seed": 9}),
}
NEAR_FLAT_F_M = 800.0
K1 = (-0.3, -0.15, 0.0, 0.15, 0.3)
EDGE_MODELS = ("area", "point", "grid 2x2", "gaussian blur", "disk blur", "vignetting", "bevel")

#: The figures the corners decide (and the twist and axis angle, through the boresight frame's turn).
FIGURES = ("twist_mrad_per_m", "axis_angle_rad", "optical_tilt_mrad.x", "optical_tilt_mrad.y", "boresight_mrad.x",
           "boresight_mrad.y", "placement.mm.0", "placement.mm.1", "placement.mm.2", "placement.mrad.0",
           "placement.mrad.1", "placement.mrad.2")


def draw_edge_model(name: str, rng: np.random.Generator) -> tuple[dict, float]:
    """TwinOptics keys of an edge model drawn from its range, and the design's rim width (m)."""
    if name == "area":
        return {}, 0.0
    if name == "point":
        return {"edge_sampling": "point"}, 0.0
    if name == "grid 2x2":
        return {"edge_sampling": "grid", "edge_grid": 2}, 0.0
    if name == "gaussian blur":
        return {"blur_px": float(rng.uniform(0.3, 1.5))}, 0.0
    if name == "disk blur":
        return {"defocus_px": float(rng.uniform(0.5, 2.5))}, 0.0
    if name == "vignetting":
        return {"vignetting": float(rng.uniform(0.3, 0.8)), "vignetting_exponent": float(rng.choice([2, 4, 6]))}, 0.0
    width_mm = float(rng.choice([1.0, 2.0, 3.0]))
    tilt = float(rng.uniform(1, 10) if rng.random() < 0.5 else rng.uniform(100, 500))
    return {"bevel_width_mm": width_mm, "bevel_tilt_mrad": tilt,
            "bevel_reflectance": float(rng.uniform(0.3, 1.0))}, 1e-3 * width_mm


def station(kind: str, k1: float):
    """(config, true facet) of a kind at 400 x 300 px with radial distortion k1."""
    from sofast_station.config import load_config

    path, facet = KINDS[kind]
    cfg = load_config(ROOT / path)
    cam = cfg.geometry.camera
    k = cam.matrix.copy()
    scale = cam.width_px / 400
    k[:2] /= scale
    k[0, 2], k[1, 2] = 199.5, 149.5
    distortion = np.array(cam.distortion, dtype=float)
    distortion[0] = k1
    cam = dataclasses.replace(cam, width_px=400, height_px=300, matrix=k, distortion=distortion)
    design = cfg.design
    if kind == "near-flat":
        design = dataclasses.replace(design, name="near-flat-800", focal_length_m=NEAR_FLAT_F_M)
    return dataclasses.replace(cfg, geometry=dataclasses.replace(cfg.geometry, camera=cam), design=design), facet


class Rigs:
    """A study rig (fringe images rendered once) and a sensitivity cache per (kind, k1, rim)."""

    def __init__(self):
        self._rigs: dict = {}

    def get(self, kind: str, k1: float, rim_m: float):
        from sofast_station.station.study import TwinRig

        key = (kind, k1, rim_m)
        if key not in self._rigs:
            cfg, facet = station(kind, k1)
            cfg = dataclasses.replace(cfg, design=dataclasses.replace(cfg.design, edge_rim_m=rim_m))
            self._rigs[key] = (cfg, facet, TwinRig(cfg), {})
        return self._rigs[key]


def run_case(i: int, rng: np.random.Generator, rigs: Rigs) -> dict:
    """One drawn case: figures, U, truth (flat dicts) and the corners' error."""
    from sofast_station.measure.pipeline import analyse
    from sofast_station.measure.uncertainty import SCALAR_PATHS, get_path, path_name
    from sofast_station.station.study import Placement, _flat, perturbed_geometry
    from sofast_station.twin.config import TrueFacet, TwinOptics
    from sofast_station.twin.station import TwinStation
    from sofast_station.twin.truth import ground_truth

    t0 = time.perf_counter()
    kind = str(rng.choice(list(KINDS)))
    k1 = float(rng.choice(K1))
    model = str(rng.choice(EDGE_MODELS))
    edge, rim_m = draw_edge_model(model, rng)
    noise = float(rng.uniform(0.3, 5.0))
    cfg, facet, rig, cache = rigs.get(kind, k1, rim_m)
    if kind == "near-flat":
        facet = {**facet, "focal_length_x_m": NEAR_FLAT_F_M * float(rng.uniform(0.95, 1.05)),
                 "focal_length_y_m": NEAR_FLAT_F_M * float(rng.uniform(0.95, 1.05))}
    place = Placement(mm=(1.0, 1.0, 0.5), mrad=(1.0, 1.0, 1.0)).draw(rng)
    geometry, distance_error = perturbed_geometry(cfg.geometry, cfg.uncertainty, rng)
    optics = TwinOptics(**{**rig.optics.to_dict(), **edge, "read_noise_dn": noise})
    true_facet = TrueFacet.from_dict({**facet, "placement_mm": list(place[0]), "placement_mrad": list(place[1])})
    twin = TwinStation(geometry, cfg.design, true_facet, optics)
    frames = rig.capture(twin, np.random.default_rng(rng.integers(2**63)))
    case = {"i": i, "kind": kind, "k1": k1, "model": model, "edge": edge, "noise_dn": noise,
            "placement": place}
    try:
        a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m() + distance_error,
                    cfg.analysis, uncertainty=cfg.uncertainty, sensitivity_cache=cache)
    except Exception as exc:                 # a refused capture is a result too (and must be rare)
        case.update(refused=f"{type(exc).__name__}: {exc}", seconds=time.perf_counter() - t0)
        return case
    truth_px = twin.corner_pixels()
    order = [int(np.argmin(np.linalg.norm(a.corners_px - t, axis=1))) for t in truth_px]
    err_px = a.corners_px[order] - truth_px
    truth = dict(ground_truth(twin, a.valid))
    truth["placement"] = {"mm": list(place[0]), "mrad": list(place[1])}
    fig = a.figures
    u_all = {k[:-2]: v for k, v in fig.items() if k.endswith("_U")}
    rec_truth = {}
    for p in SCALAR_PATHS:
        try:
            rec_truth[path_name(p)] = get_path(truth, p)
        except (KeyError, IndexError, TypeError):
            rec_truth[path_name(p)] = None
    case.update(figures=_flat(fig, SCALAR_PATHS), U=_flat(u_all, SCALAR_PATHS), truth=rec_truth,
                corner_rms_px=float(np.sqrt(np.mean(np.sum(err_px ** 2, axis=1)))),
                verdict=fig.get("verdict"), seconds=time.perf_counter() - t0)
    return case


def report(cases: list[dict]) -> dict:
    """Print the tables; return them."""
    from sofast_station.station.study import coverage_table

    done = [c for c in cases if "figures" in c]
    refused = [c for c in cases if "refused" in c]
    print(f"{len(cases)} cases, {len(refused)} refused")
    for c in refused[:10]:
        print(f"  refused: {c['kind']} {c['model']} k1 {c['k1']:+.2f} noise {c['noise_dn']:.1f} DN: {c['refused']}")
    out: dict = {"n": len(cases), "refused": len(refused), "corners": {}, "coverage": []}
    print(f"\ncorners against the twin's true corner pixels (RMS per case, px):")
    print(f"{'group':<22}{'n':>5}{'median':>9}{'p90':>8}{'max':>8}{'<= 0.1 px':>11}")
    groups = [("model", m) for m in EDGE_MODELS] + [("kind", k) for k in KINDS] + [("all", None)]
    for key, value in groups:
        rms = np.array([c["corner_rms_px"] for c in done if key == "all" or c[key] == value])
        if rms.size == 0:
            continue
        row = {"n": int(rms.size), "median": float(np.median(rms)), "p90": float(np.percentile(rms, 90)),
               "max": float(rms.max()), "within_0.1": float(np.mean(rms <= 0.1))}
        out["corners"][f"{key} {value or ''}".strip()] = row
        print(f"{(value or 'all'):<22}{row['n']:5d}{row['median']:9.3f}{row['p90']:8.3f}{row['max']:8.3f}"
              f"{100 * row['within_0.1']:10.1f}%")
    from sofast_station.measure.uncertainty import SCALAR_PATHS, path_name

    paths = [p for p in SCALAR_PATHS if path_name(p) in FIGURES]
    rows = coverage_table(done, paths)
    print(f"\n{'figure':<26}{'n':>5}{'coverage':>10}{'median U':>11}{'mean err':>11}{'std err':>10}{'U/std':>7}")
    for r in rows:
        flag = "" if abs(r["coverage"] - 0.95) <= 0.03 else "  <- outside 95 +- 3 %"
        print(f"{r['figure']:<26}{r['n']:5d}{100 * r['coverage']:9.1f}%{r['median_U']:11.3g}{r['mean_error']:11.2g}"
              f"{r['std_error']:10.3g}{(r['U_over_std'] or 0):7.2f}{flag}")
    out["coverage"] = rows
    by_model = {}
    for m in EDGE_MODELS:
        sub = coverage_table([c for c in done if c["model"] == m], paths)
        by_model[m] = {r["figure"]: r["coverage"] for r in sub}
    print("\ncoverage per edge model (%):")
    print(f"{'figure':<26}" + "".join(f"{m[:9]:>10}" for m in EDGE_MODELS))
    for r in rows:
        print(f"{r['figure']:<26}" + "".join(f"{100 * by_model[m].get(r['figure'], float('nan')):10.0f}"
                                             for m in EDGE_MODELS))
    out["coverage_by_model"] = by_model
    gore = [c["figures"]["twist_mrad_per_m"] - c["truth"]["twist_mrad_per_m"] for c in done if c["kind"] == "gore"]
    if gore:
        gore = np.abs(gore)
        out["gore_twist_error"] = {"n": int(gore.size), "max": float(gore.max()), "p95": float(np.percentile(gore, 95)),
                                   "within_0.002": float(np.mean(gore <= 0.002))}
        print(f"\ngore twist |error| over {gore.size} cases: max {gore.max():.4f}, 95th percentile "
              f"{np.percentile(gore, 95):.4f} mrad/m, {100 * np.mean(gore <= 0.002):.0f} % within 0.002 mrad/m")
    secs = [c["seconds"] for c in cases]
    print(f"\nper case: median {np.median(secs):.1f} s")
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", type=int, default=400)
    p.add_argument("--seed", type=int, default=26)
    p.add_argument("--out", default=None, help="write the cases and the tables as JSON here")
    p.add_argument("--merge", nargs="+", default=None, metavar="JSON", help="the tables over saved --out files")
    args = p.parse_args(argv)
    if args.merge:
        cases = [c for f in args.merge for c in json.loads(Path(f).read_text())["cases"]]
        report(cases)
        return 0
    rng = np.random.default_rng(args.seed)
    rigs = Rigs()
    cases = []
    t0 = time.perf_counter()
    for i in range(args.cases):
        cases.append(run_case(i, np.random.default_rng(rng.integers(2**63)), rigs))
        if (i + 1) % 10 == 0 or i + 1 == args.cases:
            print(f"  {i + 1}/{args.cases} cases ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
            if args.out:
                Path(args.out).write_text(json.dumps({"cases": cases}, default=str))
    tables = report(cases)
    if args.out:
        Path(args.out).write_text(json.dumps({"cases": cases, "tables": tables}, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
