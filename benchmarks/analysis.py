"""Benchmark: the analysis of one full-resolution capture of the default station, stage by stage.

    .venv/bin/python benchmarks/analysis.py            # default station, 7 timed runs
    .venv/bin/python benchmarks/analysis.py --quick    # small station, 1 run (the test suite does this)

One noisy capture is taken from the simulated station and saved; a fresh process then analyses it
repeatedly, as the station's long-running process does facet after facet, with the camera's pixel rays
precomputed (they depend only on the camera calibration and are computed once when the station starts;
their cost is printed separately). The first analysis in the process (cold: first calls into numpy and
OpenCV) is reported on its own; the stage table is over the runs after it. Printed: camera size, valid
pixels, the median (min, max) time of every stage and of the whole analysis, and the peak memory the
analysis adds to the process (resident set, read from /proc). Nothing is asserted.
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
runs = []
for i in range(int(sys.argv[3]) + 1):
    t = time.perf_counter()
    a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis, rays_cam=rays)
    runs.append({"total": time.perf_counter() - t, "stages": a.timings_s})
    if i == 0:
        peak = rss_kb("VmHWM:")
print(json.dumps({"runs": runs, "n_points": a.figures["n_points"], "base_mb": base / 1024,
                  "peak_mb": peak / 1024, "peak_reset": reset}))
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

    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "capture.npz"
        import numpy as np
        np.savez(npz, frames=frames, distance=distance, rays=rays)
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
                   PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
        out = subprocess.run([sys.executable, "-c", _CHILD, args.config, str(npz), str(runs)], capture_output=True,
                             text=True, env=env, check=True)
        result = json.loads(out.stdout.strip().splitlines()[-1])
    print(f"valid pixels: {result['n_points']:,}")
    cold, warm = result["runs"][0], result["runs"][1:]
    print(f"first analysis in a new process (cold): {cold['total']:.3f} s")
    print(f"analysis over {len(warm)} further run(s), seconds: median (min - max)")
    for s in cold["stages"]:
        v = [r["stages"][s] for r in warm]
        print(f"  {s:<10} {statistics.median(v):7.3f}  ({min(v):.3f} - {max(v):.3f})")
    tot = [r["total"] for r in warm]
    print(f"  {'total':<10} {statistics.median(tot):7.3f}  ({min(tot):.3f} - {max(tot):.3f})")
    peak, base = result["peak_mb"], result["base_mb"]
    note = "" if result["peak_reset"] else " (peak could not be reset: includes loading)"
    print(f"memory: peak resident {peak:.0f} MB, of which the analysis added {peak - base:.0f} MB over the "
          f"{base:.0f} MB holding the capture and rays{note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
