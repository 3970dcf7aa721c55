"""Benchmark: the robust fit's CPU time over the plain fit's, the two analysed alternately in one process.

    .venv/bin/python benchmarks/robust_ratio.py                     # every path, 7 rounds
    .venv/bin/python benchmarks/robust_ratio.py --source twin --rounds 11
    .venv/bin/python benchmarks/robust_ratio.py --quick             # small station, twin, 1 round (the tests)

Issue 14 limits the robust fit to 30 % more than the plain one. ``analysis.py`` measures each fit in its own
process, one after the other; on a machine shared with other jobs the load changes between those
processes, and their ratio moved by +-0.15 from run to run (twin 1.40 and dump 1.09 in one run, on the
same kind of capture). Here one fresh process per path (the inputs prepared as ``analysis.py`` prepares
them: the station's worker for ``twin``, ``reprocess`` of a dump per fit for ``dump``, ``import-opencsp``
of OpenCSP's facet upsampled ``--opencsp-scale`` times for ``opencsp``) analyses the same capture with the
plain and the robust fit in turn, after two analyses of each (the first is cold, and the first plain
analysis after the robust fit's cold one is slow too): both see the same load. Printed per
path: the median process CPU time (both threads) of each fit, the ratio of the medians and the median of
each round's ratio, with the load average before and after. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))          # run from a checkout, installed or not
sys.path.insert(0, str(ROOT / "benchmarks"))


def _child(spec: dict) -> dict:
    """Alternate the plain and the robust analysis of one capture; CPU seconds of each."""
    import dataclasses

    source, rounds = spec["source"], spec["rounds"]
    if source == "twin":
        import numpy as np

        from sofast_station.config import load_config
        from sofast_station.measure.analysis import analyse
        from sofast_station.precompute import ray_table, warm_up

        cfg = load_config(spec["config"])
        d = np.load(spec["capture"])
        frames, distance = d["frames"], float(d["distance"])
        warm_up(cfg.geometry.camera)
        rays = ray_table(cfg.geometry.camera)
        caches: dict = {False: {}, True: {}}    # the sensitivities: computed in each fit's cold run

        def once(robust):
            settings = dataclasses.replace(cfg.analysis, robust_fit=robust)
            return analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, settings, rays_cam=rays,
                           uncertainty=cfg.uncertainty, sensitivity_cache=caches[robust]).figures
    elif source == "dump":
        from sofast_station.archive.dumps import read_dump
        from sofast_station.reanalysis.reprocess import reprocess_content

        contents = {False: read_dump(spec["dump"], load_frames=True),
                    True: read_dump(spec["dump_robust"], load_frames=True)}

        def once(robust):
            res = reprocess_content(contents[robust])
            if res.analysis is None:
                raise SystemExit("the dump's analysis was refused: " + "; ".join(res.record.get("reasons", [])))
            return res.analysis.figures
    else:
        from sofast_station.interop.opencsp import opencsp_test_data_paths, read_opencsp

        m = read_opencsp(**opencsp_test_data_paths(spec["opencsp"]))

        def once(robust):
            return m.analyse(robust=robust).figures

    for _ in range(2):      # cold, then once more: the first analysis after the other fit's cold one is slow
        once(False)
        once(True)
    cpu: dict = {False: [], True: []}
    for _ in range(rounds):
        for robust in (False, True):
            c = time.process_time()
            once(robust)
            cpu[robust].append(time.process_time() - c)
    return {"plain": cpu[False], "robust": cpu[True]}


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "load average " + " ".join(Path("/proc/loadavg").read_text().split()[:3])


def main(argv=None) -> int:
    import analysis as bench

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", choices=("twin", "dump", "opencsp", "all"), default="all")
    p.add_argument("--config", default=str(ROOT / "station.toml"), help="station for the twin and dump sources")
    p.add_argument("--opencsp-scale", type=int, default=8, help="upsampling of OpenCSP's measurement (1: native)")
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--quick", action="store_true", help="one round (use with a small station's --config)")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(_child(json.loads(args.child))))
        return 0
    if args.rounds < 1 or args.opencsp_scale < 1:
        p.error("--rounds and --opencsp-scale must be at least 1")
    rounds = 1 if args.quick else args.rounds
    sources = ("twin", "dump", "opencsp") if args.source == "all" else (args.source,)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for source in sources:
            if source == "twin":
                spec = bench.prepare_twin(args.config, tmp)
            elif source == "dump":
                spec = bench.prepare_dump(args.config, tmp, ("plain", "robust"))
            else:
                spec = bench.prepare_opencsp(args.opencsp_scale, tmp)
            what = spec.pop("what")
            before = _uptime()
            env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
                       PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
            out = subprocess.run([sys.executable, __file__, "--child",
                                  json.dumps({**spec, "source": source, "rounds": rounds})],
                                 capture_output=True, text=True, env=env)
            if out.returncode != 0:
                raise SystemExit(f"the analysis process failed:\n{out.stderr}")
            cpu = json.loads(out.stdout.strip().splitlines()[-1])
            plain, robust = statistics.median(cpu["plain"]), statistics.median(cpu["robust"])
            per_round = statistics.median(r / q for q, r in zip(cpu["plain"], cpu["robust"]))
            print(f"\n== source {source}: {what}\n{before}")
            print(f"CPU s per analysis, median of {rounds} (min - max): plain {plain:.3f} "
                  f"({min(cpu['plain']):.3f} - {max(cpu['plain']):.3f}), robust {robust:.3f} "
                  f"({min(cpu['robust']):.3f} - {max(cpu['robust']):.3f})")
            print(f"robust/plain: {robust / plain:.2f} (medians), {per_round:.2f} (median of the rounds' ratios)")
            print(_uptime())
            rows.append((source, plain, robust, per_round))
    print("\nsummary: source, plain CPU s, robust CPU s, robust/plain (medians; rounds)")
    for source, plain, robust, per_round in rows:
        print(f"  {source:<8} {plain:6.3f} {robust:6.3f}  {robust / plain:.2f}; {per_round:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
