"""Benchmark: the analysis of one full-resolution capture of the default station, stage by stage.

    .venv/bin/python benchmarks/analysis.py            # default station, 7 timed runs
    .venv/bin/python benchmarks/analysis.py --quick    # small station, 1 run (the test suite does this)

One noisy capture is taken from the simulated station and saved; each run then analyses it in a fresh
process, as a station would, with the camera's pixel rays precomputed (they depend only on the camera
calibration and are computed once when the station starts; their cost is printed separately). Printed:
camera size, valid pixels, the median (min, max) time of every stage and of the whole analysis, and the
peak memory the analysis adds to the process (resident set, read from /proc). Nothing is asserted.
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

_CHILD = r"""
import json, os, sys, time
import numpy as np

def rss_kb(field):
    for line in open("/proc/self/status"):
        if line.startswith(field):
            return int(line.split()[1])
    return 0

from sofast_station.config import load_config
from sofast_station.measure.pipeline import analyse
cfg = load_config(sys.argv[1])
d = np.load(sys.argv[2])
frames, distance, rays = d["frames"], float(d["distance"]), d["rays"]
base = rss_kb("VmRSS:")
try:
    with open("/proc/self/clear_refs", "w") as fh:   # reset the peak (VmHWM) to the current RSS
        fh.write("5")
    reset = True
except OSError:
    reset = False
t = time.perf_counter()
a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis, rays_cam=rays)
total = time.perf_counter() - t
peak = rss_kb("VmHWM:")
print(json.dumps({"total": total, "stages": a.timings_s, "n_points": a.figures["n_points"],
                  "base_mb": base / 1024, "peak_mb": peak / 1024, "peak_reset": reset,
                  "f_x": a.figures["focal_length_x_m"]}))
"""


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "station.toml"))
    p.add_argument("--runs", type=int, default=7)
    p.add_argument("--quick", action="store_true", help="one run on the given (or small test) station")
    args = p.parse_args(argv)
    runs = 1 if args.quick else args.runs

    from sofast_station.config import load_config
    from sofast_station.measure.camera import ray_grid
    from sofast_station.station.inspect import capture, open_station

    cfg = load_config(args.config)
    cam = cfg.geometry.camera
    print(f"station: {cfg.name} ({args.config})")
    print(f"camera: {cam.width_px} x {cam.height_px} pixels, facet {cfg.design.name}")
    t = time.perf_counter()
    station = open_station(cfg, seed=1)
    t_open = time.perf_counter() - t
    try:
        t = time.perf_counter()
        frames, distance = capture(station)
        t_capture = time.perf_counter() - t
        t = time.perf_counter()
        rays = ray_grid(cam)
        t_rays = time.perf_counter() - t
    finally:
        station.close()
    print(f"setup (not part of the analysis): twin trace and renderer {t_open:.2f} s, simulated capture "
          f"{t_capture:.2f} s, pixel rays for this camera {t_rays:.2f} s (once per calibration)")

    results = []
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "capture.npz"
        import numpy as np
        np.savez(npz, frames=frames, distance=distance, rays=rays)
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        for i in range(runs):
            out = subprocess.run([sys.executable, "-c", _CHILD, args.config, str(npz)], capture_output=True,
                                 text=True, env=env, check=True)
            results.append(json.loads(out.stdout.strip().splitlines()[-1]))
    n = results[0]["n_points"]
    print(f"valid pixels: {n:,}")
    stages = results[0]["stages"].keys()
    print(f"analysis over {runs} run(s), seconds: median (min - max)")
    for s in stages:
        v = [r["stages"][s] for r in results]
        print(f"  {s:<10} {statistics.median(v):7.3f}  ({min(v):.3f} - {max(v):.3f})")
    tot = [r["total"] for r in results]
    print(f"  {'total':<10} {statistics.median(tot):7.3f}  ({min(tot):.3f} - {max(tot):.3f})")
    peak = max(r["peak_mb"] for r in results)
    base = statistics.median(r["base_mb"] for r in results)
    note = "" if results[0]["peak_reset"] else " (peak could not be reset: includes loading)"
    print(f"memory: peak resident {peak:.0f} MB, of which the analysis added {peak - base:.0f} MB over the "
          f"{base:.0f} MB holding the capture and rays{note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
