"""Benchmark: the digital twin's render of one capture (18 frames), as the simulated camera takes it.

    .venv/bin/python benchmarks/twin_render.py            # default station (1600 x 1200), 9 captures
    .venv/bin/python benchmarks/twin_render.py --quick    # small station, 2 captures

Opens the simulated station (ray trace and fringe renderer: printed apart, once per station), takes one
capture to warm up (the display renders each pattern once), then times further captures: wall time
(median, min - max) and process CPU time (both threads; less disturbed by other load on the machine),
with the machine's load average (``uptime``) before and after. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))          # run from a checkout, installed or not


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "uptime unavailable"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "station.toml"))
    p.add_argument("--captures", type=int, default=9)
    p.add_argument("--quick", action="store_true", help="two captures (the test suite does this)")
    args = p.parse_args(argv)
    n = 2 if args.quick else args.captures

    from sofast_station.config import load_config
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture

    cfg = load_config(args.config)
    cam = cfg.geometry.camera
    print(f"before: {_uptime()}")
    print(f"camera {cam.width_px} x {cam.height_px}, {cfg.fringes.n_frames} frames per capture, {cfg.name}")
    t = time.perf_counter()
    station = open_station(cfg, seed=1)
    print(f"open (ray trace once per station, renderer): {time.perf_counter() - t:.2f} s")
    try:
        t = time.perf_counter()
        capture(station)
        print(f"first capture (renders every pattern once): {time.perf_counter() - t:.3f} s")
        wall, cpu = [], []
        for _ in range(n):
            t, c = time.perf_counter(), time.process_time()
            capture(station)
            wall.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
    finally:
        station.close()
    print(f"capture over {n} runs: wall {statistics.median(wall):.3f} s median ({min(wall):.3f} - {max(wall):.3f}), "
          f"cpu {statistics.median(cpu):.3f} s median ({min(cpu):.3f} - {max(cpu):.3f})")
    print(f"after: {_uptime()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
