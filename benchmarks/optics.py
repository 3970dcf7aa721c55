"""Benchmark: the optical figures of one facet (trace, flux map, intercept, spot radius, centroid, power ratio).

    .venv/bin/python benchmarks/optics.py               # 500,000 points of the default station's facet, 9 runs
    .venv/bin/python benchmarks/optics.py --points 800000 --rays-per-pixel 0.5 --grid-cells 201
    .venv/bin/python benchmarks/optics.py --quick       # 20,000 points, 1 run (the test suite does this)

The points and slopes are the twin's true facet of the station file ([simulation.facet]: focal-length
errors, twist, slope errors) sampled on a regular grid inside the outline, as many as a camera's valid
pixels; the camera sits at twice the focal length on the axis. What is timed is what the station does
per facet after the analysis: :func:`sofast_station.optics.facet_optics` with the design's trace already
made (it is the same for every facet of a type; its one-off time is printed separately). Printed: points,
rays, grid, the median (min, max) over the runs, the machine's load average, and the figures. Nothing is
asserted: the line's target is 0.3 s for 500,000 points.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))          # run from a checkout, installed or not


def facet_samples(config, n_points: int):
    """(points (3, N), slopes (2, N)) of the twin's true facet on a grid inside the design outline."""
    import numpy as np

    from sofast_station.optics.facet import inside_polygon, outline_area_m2
    from sofast_station.twin.parameters import TrueFacet
    from sofast_station.twin.surface import TrueSurface

    design = config.design
    facet = TrueFacet.from_dict(dict(config.simulation.get("facet", {})))
    lo, hi = design.outline_m.min(axis=0), design.outline_m.max(axis=0)
    fill = outline_area_m2(design.outline_m) / float(np.prod(hi - lo))
    n = int(math.ceil(math.sqrt(n_points / fill)))
    gx = lo[0] + (np.arange(n) + 0.5) * (hi[0] - lo[0]) / n
    gy = lo[1] + (np.arange(n) + 0.5) * (hi[1] - lo[1]) / n
    x, y = (a.ravel() for a in np.meshgrid(gx, gy))
    keep = inside_polygon(x, y, design.outline_m)
    x, y = x[keep][:n_points], y[keep][:n_points]
    z, s_x, s_y = TrueSurface(facet, design).height_and_slopes(x, y)
    return np.stack([x, y, z]), np.stack([s_x, s_y])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default=str(ROOT / "station.toml"), help="station file (default: station.toml)")
    p.add_argument("--points", type=int, default=500_000, help="measured points (valid pixels)")
    p.add_argument("--runs", type=int, default=9, help="timed runs")
    p.add_argument("--rays-per-pixel", type=float, default=None, help="override [optics] rays_per_pixel")
    p.add_argument("--grid-cells", type=int, default=None, help="override [optics] grid_cells")
    p.add_argument("--quick", action="store_true", help="20,000 points, 1 run")
    args = p.parse_args(argv)
    if args.quick:
        args.points, args.runs = 20_000, 1

    import dataclasses

    import numpy as np

    from sofast_station.config import load_config
    from sofast_station.optics import OpticsSettings, design_trace, facet_optics, make_scene

    config = load_config(args.config)
    settings = config.optics or OpticsSettings()
    changes = {k: v for k, v in (("rays_per_pixel", args.rays_per_pixel), ("grid_cells", args.grid_cells))
               if v is not None}
    if args.quick:
        changes["design_points"] = 20_000
    settings = dataclasses.replace(settings, **changes)
    design = config.design
    points, slopes = facet_samples(config, args.points)
    camera_m = np.array([design.centroid_m[0], design.centroid_m[1], 2.0 * design.focal_length_m])

    t = time.perf_counter()
    scene = make_scene(design, settings)
    design_result = design_trace(design, settings, scene)
    t_design = time.perf_counter() - t

    times, cpu = [], []
    for _ in range(args.runs + 1):          # the first run warms numpy's code paths; it is shown apart
        t, c = time.perf_counter(), time.process_time()
        res = facet_optics(points, slopes, camera_m, design, settings, slope_error_mrad=0.5,
                           focal_power_per_m=design.curvature_per_m, scene=scene, design_result=design_result)
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    first, runs, cpu_runs = times[0], times[1:] or times, cpu[1:] or cpu
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    f = res.figures
    print(f"facet {design.name} ({config.path.name}): {points.shape[1]:,} points, {f['conditions']['rays']:,} rays, "
          f"{settings.grid_cells} x {settings.grid_cells} grid, {settings.sun.kind} sun")
    print(f"design trace (once per facet type, {settings.design_points:,} samples): {t_design:.3f} s")
    print(f"per-facet optical figures: median {statistics.median(runs):.3f} s (min {min(runs):.3f}, max "
          f"{max(runs):.3f}) over {len(runs)} runs; first run {first:.3f} s; CPU {statistics.median(cpu_runs):.3f} s")
    print(f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} on {os.cpu_count()} CPUs")
    print(f"figures: intercept {f['intercept']:.4f} (design {f['design']['intercept']:.4f}), 90 % spot radius "
          f"{1000 * f['spot_radius_m']:.2f} mm (design {1000 * f['design']['spot_radius_m']:.2f} mm), centroid "
          f"offset {f['centroid_offset_mrad']['magnitude']:.3f} mrad, power ratio {f['power_ratio_vs_design']:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
