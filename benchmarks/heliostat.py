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
less so). The heliostats' optics (three traces and the canting's Monte Carlo) are timed apart.

``--population N`` draws N 2x2 heliostats (canting 1 mrad RMS per facet and axis, facet heights to 0.2 mm,
placements +-3 mm / +-2 mrad, the twin's default noise) at full resolution and prints the canting errors
against the twin's truth: the station known exactly, then with its inputs drawn from ``[uncertainty]``
(coverage of U). Nothing is asserted.
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
    return statistics.median(walls), statistics.median(cpus)


def heliostat(kind: str, scale: int, runs: int, rng, optics_runs: int, with_u: bool = True):
    import dataclasses

    from sofast_station.calibrate.store import open_calibration
    from sofast_station.config import load_config
    from sofast_station.measure.heliostat import analyse_heliostat
    from sofast_station.precompute import warm_up
    from sofast_station.station.heliostat import analysis_optics
    from sofast_station.station.heliostat_study import HeliostatRig
    from sofast_station.twin.config import TwinOptics
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
    print("  last run's steps: " + ", ".join(f"{k} {v:.3f} s" for k, v in steps.items()))
    if optics_runs and cfg.optics is not None:
        o_cold, o_walls, o_cpus = timed(lambda: analysis_optics(r, ens, cfg.optics), optics_runs)
        print(summary("  optics (3 traces + Monte Carlo)", o_cold, o_walls, o_cpus))
    return statistics.median(walls), statistics.median(cpus)


def population(n: int, scale: int, rng) -> None:
    import numpy as np

    from sofast_station.calibrate.store import open_calibration
    from sofast_station.config import load_config
    from sofast_station.station.heliostat_study import HeliostatRig
    from sofast_station.twin.config import TwinOptics
    from sofast_station.twin.heliostat import draw_heliostat

    cfg = scaled(load_config(STATIONS["2x2"]), scale)
    radiometric = open_calibration(cfg, checks=False).record
    rig = HeliostatRig(cfg.geometry, cfg.ensemble, cfg.fringes, radiometric, cfg.analysis, cfg.heliostat,
                       cfg.uncertainty)
    for perturb in (False, True):
        errors, us = [], []
        t = time.perf_counter()
        for k in range(n):
            r = rig.case(draw_heliostat(cfg.ensemble, rng, canting_mrad=1.0, position_mm=0.2 if not perturb else 0.5),
                         TwinOptics(), rng, perturb=perturb)
            for label in r.canting:
                errors.append(np.subtract(r.canting[label], r.truth[label]))
                us.append(r.u[label])
            print(f"  {'drawn station' if perturb else 'exact station'} {k + 1}/{n}: largest error so far "
                  f"{np.abs(errors).max():.4f} mrad", flush=True)
        e, u = np.array(errors), np.array(us)
        print(f"population, {'station inputs drawn from [uncertainty], facet heights 0.5 mm' if perturb else 'the station known exactly, facet heights 0.2 mm'}: "
              f"{n} heliostats, {e.size} canting errors: largest {np.abs(e).max():.4f} mrad, RMS "
              f"{np.sqrt(np.mean(e ** 2)):.4f} mrad, {100 * np.mean(np.abs(e) <= u):.1f} % within U, median U "
              f"{np.median(u):.4f} mrad ({time.perf_counter() - t:.0f} s)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=7, help="timed runs after the cold one (default 7)")
    p.add_argument("--quick", action="store_true", help="a quarter of the resolution, 1 run")
    p.add_argument("--population", type=int, default=0, help="also this many drawn 2x2 heliostats (canting errors)")
    p.add_argument("--seed", type=int, default=30)
    args = p.parse_args(argv)
    import numpy as np

    from sofast_station.precompute import prepare_analysis_process

    scale, runs = (4, 1) if args.quick else (1, args.runs)
    prepare_analysis_process()
    print(f"load average before: {load()}")
    rng = np.random.default_rng(args.seed)
    one_wall, one_cpu = single_facet(scale, runs, rng)
    two_wall, two_cpu = heliostat("2x2", scale, runs, rng, optics_runs=max(1, runs // 2))
    # (quick: the 5x5 without its U, whose 25 facets' sensitivities take most of a minute to compute cold)
    five_wall, five_cpu = heliostat("5x5", scale, runs, rng, optics_runs=max(1, runs // 2), with_u=not args.quick)
    print(f"2x2 against one facet: {two_wall / one_wall:.2f} x the wall time, {two_cpu / one_cpu:.2f} x the CPU "
          f"(target: within 2 x)")
    print(f"5x5: {five_wall:.2f} s wall, {five_cpu:.2f} s CPU (target: at most 10 s)")
    if args.population:
        population(args.population, scale, rng)
    print(f"load average after: {load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
