"""Benchmark: a whole heliostat's analysis against one facet's, and the canting on a population at full size.

    .venv/bin/python benchmarks/heliostat.py                    # full resolution: 1 facet, 2x2, 5x5; 7 runs each
    .venv/bin/python benchmarks/heliostat.py --runs 11
    .venv/bin/python benchmarks/heliostat.py --population 10    # also 10 drawn 2x2 heliostats at full resolution
    .venv/bin/python benchmarks/heliostat.py --quick            # a quarter of the resolution, 1 run, the 5x5
                                                                #   without U (the test suite)

What is timed is the analysis as the station's worker runs it, facet after facet, in one process: the
single facet is the default station's (``station.toml``: the 0.6 m dish facet, 1600 x 1200 camera,
:func:`~sofast_station.measure.analysis.analyse` with its uncertainty); the heliostats are the 2x2 and 5x5 of
``fixtures/facets/`` on their stations (1600 x 1200 cameras; :func:`~sofast_station.measure.heliostat.
analyse_heliostat` with every facet's uncertainty and the canting's). Each gets a noisy twin capture; its
first analysis (cold: the sensitivities computed, the kernels and caches filled) is reported on its own,
then the median (min - max) of the timed runs, wall and process CPU (both threads), and the machine's load
average before and after (the machine is shared: a busy machine makes every number longer, the ratios
less so). The 2x2's ratio to the single facet is also taken in turn: the two analysed one after the other,
run by run, the median of the pairs' ratios (a pair sees nearly one load; timed apart they may not). The
heliostats' optics (three traces and the canting's Monte Carlo) are timed apart.

``--population N`` draws N 2x2 heliostats (canting 1 mrad RMS per facet and axis, facet heights to 0.2 mm,
placements +-3 mm / +-2 mrad, the twin's default noise) at full resolution and prints the canting errors
against the twin's truth: the station known exactly, then with its inputs drawn from ``[uncertainty]``
(coverage of U). ``--inputs`` moves each group of the station's inputs by twice its standard uncertainty
in the twin alone, and raises one facet 1 mm on its frame, and prints the canting's change beside what U's
sensitivities predict. Nothing is asserted.

    .venv/bin/python benchmarks/heliostat.py --runs 1 --inputs
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: The heliostat stations (camera, screen and layout) the benchmark runs, as the station files ship them.
STATIONS = {"2x2": ROOT / "fixtures/stations/heliostat-ensemble.toml",
            "5x5": ROOT / "fixtures/stations/heliostat-ensemble-5x5.toml"}


def load() -> str:
    a, b, c = os.getloadavg()
    return f"{a:.2f} {b:.2f} {c:.2f} (1, 5, 15 min) on {os.cpu_count()} CPUs"


def timed(fn, runs: int) -> tuple[float, list[float], list[float]]:
    t, c = time.perf_counter(), time.process_time()
    fn()
    cold = time.perf_counter() - t
    walls, cpus = [], []
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return cold, walls, cpus


def in_turn(one, other, runs: int) -> tuple[float, float]:
    """*other*'s time over *one*'s, the two run one after the other *runs* times: the median of the pairs'
    ratios, wall and process CPU. Timed apart, minutes from each other on a shared machine, the two see
    different loads; a pair sees nearly the same."""
    walls, cpus = [], []
    for _ in range(runs):
        times = []
        for fn in (one, other):
            t, c = time.perf_counter(), time.process_time()
            fn()
            times.append((time.perf_counter() - t, time.process_time() - c))
        walls.append(times[1][0] / times[0][0])
        cpus.append(times[1][1] / max(times[0][1], 1e-9))
    return statistics.median(walls), statistics.median(cpus)


def summary(name: str, cold: float, walls: list, cpus: list) -> str:
    return (f"{name:34s} cold {cold:6.2f} s   median {statistics.median(walls):6.3f} s "
            f"({min(walls):.3f} - {max(walls):.3f}), CPU {statistics.median(cpus):6.3f} s")


def scaled(config, scale: int):
    """The station with its camera's resolution divided by *scale* (the same field of view)."""
    import dataclasses

    from sofast_station.station.heliostat_study import scaled_camera
    if scale == 1:
        return config
    return dataclasses.replace(config, geometry=dataclasses.replace(
        config.geometry, camera=scaled_camera(config.geometry.camera, scale)))


def single_facet(scale: int, runs: int, rng):
    import dataclasses

    from sofast_station.config import load_config
    from sofast_station.measure.analysis import analyse
    from sofast_station.precompute import ray_table, warm_up
    from sofast_station.station.study import TwinRig

    cfg = scaled(load_config(ROOT / "station.toml"), scale)
    if scale > 1:
        cfg = dataclasses.replace(cfg, analysis=dataclasses.replace(cfg.analysis, edge_window_px=3))
    rig = TwinRig(cfg)
    twin = rig.twin((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    frames = rig.capture(twin, rng)
    distance = twin.measured_distance_m()
    warm_up(cfg.geometry.camera)
    rays = ray_table(cfg.geometry.camera)
    cache: dict = {}
    box = {}

    def once():
        box["a"] = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis, rays_cam=rays,
                           uncertainty=cfg.uncertainty, sensitivity_cache=cache)
    cold, walls, cpus = timed(once, runs)
    a = box["a"].figures
    cam = cfg.geometry.camera
    print(f"single facet: {cfg.design.name}, camera {cam.width_px} x {cam.height_px}, {a['n_points']:,} points")
    print(summary("  analysis (with U)", cold, walls, cpus))
    return statistics.median(walls), statistics.median(cpus), once


def heliostat(kind: str, scale: int, runs: int, rng, optics_runs: int, with_u: bool = True):
    import dataclasses

    from sofast_station.calibrate.store import open_calibration
    from sofast_station.config import load_config
    from sofast_station.measure.heliostat import analyse_heliostat
    from sofast_station.precompute import warm_up
    from sofast_station.job.heliostat import analysis_optics
    from sofast_station.station.heliostat_study import HeliostatRig
    from sofast_station.twin.parameters import TwinOptics
    from sofast_station.twin.heliostat import draw_heliostat

    cfg = scaled(load_config(STATIONS[kind]), scale)
    analysis = cfg.analysis if scale == 1 else dataclasses.replace(cfg.analysis, edge_window_px=3)
    ens = cfg.ensemble
    radiometric = open_calibration(cfg, checks=False).record
    rig = HeliostatRig(cfg.geometry, ens, cfg.fringes, radiometric, analysis, cfg.heliostat, cfg.uncertainty)
    true = draw_heliostat(ens, rng, canting_mrad=1.0)
    t = time.perf_counter()
    twin = rig.twin(true, TwinOptics())
    frames = rig.capture(twin, rng)
    setup = time.perf_counter() - t
    distance = twin.measured_distance_m()
    warm_up(cfg.geometry.camera)
    box = {}

    def once():
        box["r"] = analyse_heliostat(frames, cfg.fringes, cfg.geometry, ens, distance, analysis, cfg.heliostat,
                                     rays_cam=rig.rays, uncertainty=cfg.uncertainty if with_u else None,
                                     sensitivity_cache=rig.cache)
    cold, walls, cpus = timed(once, runs)
    r = box["r"]
    cam = cfg.geometry.camera
    points = sum(f.get("n_points", 0) for f in r.figures["facets"])
    print(f"heliostat {ens.name}: {ens.n_facets} facets ({r.figures['heliostat']['n_measured']} measured), camera "
          f"{cam.width_px} x {cam.height_px}, {points:,} points (setup, not timed: twin and capture {setup:.1f} s)")
    print(summary("  analysis (with every U)" if with_u else "  analysis (no U)", cold, walls, cpus))
    steps = {}
    for k, v in r.timings_s.items():
        group = k.split("_")[0] if k.startswith(("reduce_", "facet_")) else k
        steps[group] = steps.get(group, 0.0) + v
    # (reduce and facet: every facet's own seconds summed; the facets run side by side, so they overlap)
    print("  last run's steps (facets' seconds summed): " + ", ".join(f"{k} {v:.3f} s" for k, v in steps.items()))
    if optics_runs and cfg.optics is not None:
        o_cold, o_walls, o_cpus = timed(lambda: analysis_optics(r, ens, cfg.optics), optics_runs)
        print(summary("  optics (3 traces + Monte Carlo)", o_cold, o_walls, o_cpus))
    return statistics.median(walls), statistics.median(cpus), once


def population(n: int, scale: int, rng) -> None:
    import numpy as np

    from sofast_station.calibrate.store import open_calibration
    from sofast_station.config import load_config
    from sofast_station.station.heliostat_study import HeliostatRig
    from sofast_station.twin.parameters import TwinOptics
    from sofast_station.twin.heliostat import draw_heliostat

    cfg = scaled(load_config(STATIONS["2x2"]), scale)
    radiometric = open_calibration(cfg, checks=False).record
    rig = HeliostatRig(cfg.geometry, cfg.ensemble, cfg.fringes, radiometric, cfg.analysis, cfg.heliostat,
                       cfg.uncertainty)
    for perturb in (False, True):
        errors, us, predicted, within = [], [], [], []
        t = time.perf_counter()
        for k in range(n):
            drawn: dict = {}
            r = rig.case(draw_heliostat(cfg.ensemble, rng, canting_mrad=1.0, position_mm=0.2 if not perturb else 0.5),
                         TwinOptics(), rng, perturb=perturb, keep=perturb, drawn=drawn)
            pred = drawn_prediction(r.analysis, drawn) if perturb else {}
            inside = []
            for label in r.canting:
                errors.append(np.subtract(r.canting[label], r.truth[label]))
                us.append(r.u[label])
                inside.extend(np.abs(errors[-1]) <= us[-1])
                if perturb:
                    predicted.append(pred[label])
            within.append(np.mean(inside))
            print(f"  {'drawn station' if perturb else 'exact station'} {k + 1}/{n}: largest error so far "
                  f"{np.abs(errors).max():.4f} mrad", flush=True)
        e, u = np.array(errors), np.array(us)
        what = ("station inputs drawn from [uncertainty], facet heights 0.5 mm" if perturb
                else "the station known exactly, facet heights 0.2 mm")
        print(f"population, {what}: "
              f"{n} heliostats, {e.size} canting errors: largest {np.abs(e).max():.4f} mrad, RMS "
              f"{np.sqrt(np.mean(e ** 2)):.4f} mrad, {100 * np.mean(np.abs(e) <= u):.1f} % within U, median U "
              f"{np.median(u):.4f} mrad, RMS of error / (U / 2) {np.sqrt(np.mean((2 * e / u) ** 2)):.2f} "
              f"({time.perf_counter() - t:.0f} s)")
        print(f"  per heliostat, % within U: {' '.join(f'{100 * w:.0f}' for w in within)}"
              + (" (a heliostat's errors share its one drawn station)" if perturb else ""))
        if perturb:
            q = np.array(predicted)
            print(f"  the errors against U's own prediction from the drawn inputs (its sensitivities times the draws): "
                  f"slope {float(np.sum(e * q) / np.sum(q * q)):.3f}, "
                  f"correlation {np.corrcoef(e.ravel(), q.ravel())[0, 1]:.3f}, "
                  f"the rest RMS {np.sqrt(np.mean((e - q) ** 2)):.4f} mrad (the facets' heights, noise, corners)")


def drawn_prediction(res, drawn: dict) -> dict:
    """Facet label -> the canting error (x, y, mrad) U's model predicts for the station inputs *drawn* (from
    :func:`~sofast_station.station.study.perturbed_geometry`): each facet's sensitivities of its optical tilt,
    per unit of each input, times the draw (opposite in sign: the twin moved, the analysis believes the nominal
    station; alike for the distance, which the analysis is given wrong), less the facets' mean. The twin's one
    pitch moves both of U's pitch rows."""
    import numpy as np

    from sofast_station.measure.sensitivity_record import from_record

    keys = sorted(res.analyses)
    sens = [from_record(res.analyses[i].sensitivities)[1] for i in keys]
    tilts = np.zeros((len(keys), 2))
    for r, s in enumerate(sens):
        for col, ax in enumerate("xy"):
            j = s.paths.index(("optical_tilt_mrad", ax))
            for k, inp in enumerate(s.inputs):
                d = drawn.get("screen pitch" if inp.name.startswith("screen pitch") else inp.name)
                if d is not None and inp.kind == "systematic":
                    tilts[r, col] += (1.0 if inp.name == "distance" else -1.0) * s.linear[k, j] / inp.u * d
    tilts -= tilts.mean(axis=0)
    labels = {f["index"]: f["label"] for f in res.figures["facets"]}
    return {labels[i]: tuple(tilts[r]) for r, i in enumerate(keys)}


class _TwoSigma:
    """A stand-in for the generator :func:`~sofast_station.station.study.perturbed_geometry` draws from: the
    draws numbered in *on* (in its order, ``DRAWN_INPUTS``) are +2 standard uncertainties, the rest 0."""

    def __init__(self, on):
        self.on, self.i = set(on), 0

    def normal(self, loc, scale, size=None):
        import numpy as np

        out = []
        for _ in range(1 if size is None else size):
            out.append(2.0 * float(scale) if self.i in self.on else 0.0)
            self.i += 1
        return out[0] if size is None else np.array(out)


#: The station's inputs moved one group at a time: draws of ``perturbed_geometry`` and U's rows.
INPUT_GROUPS = {"camera focal lengths": ((0, 1), ("camera fx", "camera fy")),
                "camera principal point": ((2, 3), ("camera cx", "camera cy")),
                "camera distortion": ((4, 5, 6, 7, 8), ("camera k1", "camera k2", "camera p1", "camera p2",
                                                        "camera k3")),
                "screen rotation x": ((9,), ("screen rx",)), "screen rotation y": ((10,), ("screen ry",)),
                "screen rotation z": ((11,), ("screen rz",)),
                "screen translation": ((12, 13, 14), ("screen tx", "screen ty", "screen tz")),
                "fixture": ((15, 16, 17, 18, 19, 20), ("fixture rx", "fixture ry", "fixture rz", "fixture tx",
                                                       "fixture ty", "fixture tz")),
                "screen pitch": ((21,), ("screen pitch x", "screen pitch y")), "distance": ((22,), ("distance",))}


def inputs_check(scale: int) -> None:
    """Each group of the station's inputs moved by +2 standard uncertainties in the twin alone (the analysis
    believes the nominal station), and a facet raised 1 mm on its frame: the canting's change, facet by
    facet, against what U's sensitivities predict (the same size; the opposite sign, since the analysis's
    belief is what is off). One noise-free 2x2 heliostat."""
    import dataclasses

    import numpy as np

    from sofast_station.calibrate.store import open_calibration
    from sofast_station.config import load_config
    from sofast_station.measure.heliostat import analyse_heliostat
    from sofast_station.measure.sensitivity_record import from_record
    from sofast_station.station.heliostat_study import HeliostatRig
    from sofast_station.station.study import perturbed_geometry
    from sofast_station.twin.parameters import TwinOptics
    from sofast_station.twin.heliostat import draw_heliostat, heliostat_truth

    cfg = scaled(load_config(STATIONS["2x2"]), scale)
    analysis = cfg.analysis if scale == 1 else dataclasses.replace(cfg.analysis, edge_window_px=3)
    radiometric = open_calibration(cfg, checks=False).record
    rig = HeliostatRig(cfg.geometry, cfg.ensemble, cfg.fringes, radiometric, analysis, cfg.heliostat,
                       cfg.uncertainty)
    true = draw_heliostat(cfg.ensemble, np.random.default_rng(3), canting_mrad=1.0, position_mm=0.0)

    def errors(heliostat, geometry, distance_error):
        twin = rig.twin(heliostat, TwinOptics.noise_free(), geometry)
        res = analyse_heliostat(rig.capture(twin, None), rig.fringes, rig.geometry, rig.ensemble,
                                twin.measured_distance_m() + distance_error, rig.analysis, rig.heliostat,
                                rays_cam=rig.rays, uncertainty=rig.uncertainty, sensitivity_cache=rig.cache)
        truth = heliostat_truth(twin, res.valid)["facets"]
        return np.array([[f["canting_mrad"][a] - truth[f["label"]]["canting_mrad"][a] for a in "xy"]
                         for f in res.figures["facets"]]), res

    base, res = errors(true, cfg.geometry, 0.0)
    sens = [from_record(res.analyses[i].sensitivities)[1] for i in sorted(res.analyses)]
    n = len(sens)
    weights = np.eye(n) - 1.0 / n

    def predicted(names):
        out = np.zeros((n, 2))
        for col, ax in enumerate("xy"):
            lin = np.array([[s.linear[k, s.paths.index(("optical_tilt_mrad", ax))] if s.inputs[k].name in names
                             else 0.0 for k in range(len(s.inputs))] for s in sens])
            out[:, col] = 2.0 * (weights @ lin).sum(axis=1)
        return out

    print(f"inputs: each moved by +2 u in the twin alone; the canting's change (x, y per facet, mrad) against "
          f"U's prediction, on {n} facets (signs opposite where the twin moved, alike for the distance, which the "
          f"analysis is given wrong)")
    for name, (draws, rows) in INPUT_GROUPS.items():
        geometry, distance_error = perturbed_geometry(cfg.geometry, cfg.uncertainty, _TwoSigma(draws))
        e, _ = errors(true, geometry, distance_error)
        change, pred = e - base, predicted(rows)
        print(f"  {name:24s} change {np.abs(change).min():.3f} to {np.abs(change).max():.3f}, predicted "
              f"{np.abs(pred).min():.3f} to {np.abs(pred).max():.3f}; facet by facet "
              f"{' '.join(f'{c:+.3f}/{q:+.3f}' for c, q in zip(change.ravel(), pred.ravel()))}", flush=True)
    facets = list(true.facets)
    m = (cfg.ensemble.measure_facet + 1) % n        # not the measure facet, whose height the range finder sees
    facets[m] = dataclasses.replace(facets[m], placement_mm=tuple(np.add(facets[m].placement_mm, (0.0, 0.0, 1.0))))
    e, _ = errors(dataclasses.replace(true, facets=tuple(facets)), cfg.geometry, 0.0)
    own = (e - base)[m] - np.delete(e - base, m, axis=0).mean(axis=0)
    dist = [k for k, inp in enumerate(sens[m].inputs) if inp.name == "distance"][0]
    model = [float(sens[m].linear[dist, sens[m].paths.index(("optical_tilt_mrad", a))]) / sens[m].inputs[dist].u
             for a in "xy"]
    print(f"  facet {cfg.ensemble.facets[m].label} raised 1 mm on its frame: its canting against the others' moves "
          f"x {own[0]:+.4f}, y {own[1]:+.4f} mrad; U's height term takes {abs(model[0]):.4f}, {abs(model[1]):.4f} "
          f"mrad per mm")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=7, help="timed runs after the cold one (default 7)")
    p.add_argument("--quick", action="store_true", help="a quarter of the resolution, 1 run")
    p.add_argument("--population", type=int, default=0, help="also this many drawn 2x2 heliostats (canting errors)")
    p.add_argument("--inputs", action="store_true",
                   help="also check U's model input by input on one 2x2 heliostat (about 12 captures)")
    p.add_argument("--seed", type=int, default=30)
    args = p.parse_args(argv)
    import numpy as np

    from sofast_station.precompute import prepare_analysis_process

    scale, runs = (4, 1) if args.quick else (1, args.runs)
    prepare_analysis_process()
    print(f"load average before: {load()}")
    rng = np.random.default_rng(args.seed)
    one_wall, one_cpu, one_once = single_facet(scale, runs, rng)
    two_wall, two_cpu, two_once = heliostat("2x2", scale, runs, rng, optics_runs=max(1, runs // 2))
    # (quick: the 5x5 without its U, whose 25 facets' sensitivities take most of a minute to compute cold)
    five_wall, five_cpu, _ = heliostat("5x5", scale, runs, rng, optics_runs=max(1, runs // 2), with_u=not args.quick)
    print(f"2x2 against one facet: {two_wall / one_wall:.2f} x the wall time, {two_cpu / one_cpu:.2f} x the CPU "
          f"(target: within 2 x)")
    walls, cpus = in_turn(one_once, two_once, runs)
    print(f"2x2 against one facet, taken in turn ({runs} pairs, each on the same load): median {walls:.2f} x the "
          f"wall time, {cpus:.2f} x the CPU")
    print(f"5x5: {five_wall:.2f} s wall, {five_cpu:.2f} s CPU (target: at most 10 s)")
    if args.population:
        population(args.population, scale, rng)
    if args.inputs:
        inputs_check(scale)
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
