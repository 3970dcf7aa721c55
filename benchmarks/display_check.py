"""Benchmark: the display's self-test (docs/reliability.md#the-screen-checks-itself) -- its cost per cycle.

    .venv/bin/python benchmarks/display_check.py              # 1600 x 1200 and 400 x 300, 200 checks each
    .venv/bin/python benchmarks/display_check.py --quick      # the tests: 20 checks each

The check reads a cycle's frames (dark, white, the phase-step sets) on a regular grid of at most
``MAX_PIXELS`` pixels, so its cost does not grow with the resolution. The frames here are random counts with
the white above the dark (the cost does not depend on what they show; what the check reads is held to the
twin's truth in tests/station/test_display_check.py). Prints the CPU and wall time per check (median, 95th
percentile) and the machine's load. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from sofast_station.fringes import FringeSet
from sofast_station.measure.display_response import MAX_PIXELS, fringe_mean_levels


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checks", type=int, default=200)
    parser.add_argument("--quick", action="store_true", help="20 checks per resolution (the tests)")
    args = parser.parse_args(argv)
    n = 20 if args.quick else args.checks
    fringes = FringeSet()
    rng = np.random.default_rng(0)
    print(f"== the display's self-test: {fringes.n_frames} frames, at most {MAX_PIXELS} pixels; load "
          f"{os.getloadavg()[0]:.1f}")
    for rows, cols in ((1200, 1600), (300, 400)):
        frames = rng.integers(0, 190, (fringes.n_frames, rows, cols)).astype(np.uint8)
        frames[1] = np.minimum(frames[0].astype(np.int32) + 60, 253).astype(np.uint8)
        cpu, wall = [], []
        for _ in range(n):
            c, w = time.process_time(), time.perf_counter()
            fringe_mean_levels(frames, fringes.slices(), 20.0)
            cpu.append(1e3 * (time.process_time() - c))
            wall.append(1e3 * (time.perf_counter() - w))
        print(f"camera {cols} x {rows}: {n} checks, CPU ms per check median {np.median(cpu):.2f} (95th percentile "
              f"{np.percentile(cpu, 95):.2f}), wall ms median {np.median(wall):.2f} "
              f"(95th {np.percentile(wall, 95):.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
