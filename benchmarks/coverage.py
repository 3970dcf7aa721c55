"""Proof of the stated uncertainty on the twin: coverage of |error against truth| <= U (k = 2).

    .venv/bin/python benchmarks/coverage.py                 # 200 captures on a 400 x 300 dish station
    .venv/bin/python benchmarks/coverage.py --captures 30 --out /tmp/cov.json

Each capture: a new placement of the facet within the fixture tolerance, new sensor noise, and the station's
geometry (camera intrinsics and distortion, camera-to-screen pose, screen pitch, fixture pose, measured
distance) drawn from normal distributions with the standard uncertainties of ``[uncertainty]``; the twin
photographs with that perturbed geometry, the analysis uses the nominal one. Ground truth comes from the
twin (:mod:`sofast_station.twin.truth`). Printed per figure: the fraction of captures with
|error| <= U (target 95 % +- 3 %), the median U, the errors' standard deviation and the ratio median U / std
(target <= 2: U is not overstated), plus the noise-corrected slope RMS values against truth. Nothing is
asserted (the test suite runs a reduced version).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SMALL_STATION = """
[station]
name = "Small simulated dish station (coverage study)"
backend = "simulated"
data_dir = "{data_dir}"
facet = "{facet}"

[camera]
width_px = 400
height_px = 300
focal_length_px = 3409.0
distortion = [-0.05, 0.1, 0.0002, -0.0001, 0.0]

[screen]
width_px = 1920
height_px = 1080
pitch_m = 0.000275

[layout]
separation_m = 0.34

[analysis]
edge_window_px = 3

[calibration]
radiometric = "{radiometric}"

[simulation]
seed = 3

[simulation.facet]
focal_length_x_m = 5.42
focal_length_y_m = 5.35
twist_mrad_per_m = 0.12
slope_error_rms_mrad = 0.5
"""


def small_station(folder: Path) -> Path:
    path = folder / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=folder / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    return path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=None, help="station file (default: a 400 x 300 dish station)")
    p.add_argument("--captures", type=int, default=200)
    p.add_argument("--seed", type=int, default=12)
    p.add_argument("--out", default=None, help="write the per-capture results and the table as JSON here")
    p.add_argument("--merge", nargs="+", default=None, metavar="JSON",
                   help="no new captures: the table over the captures of these --out files (runs in parallel)")
    args = p.parse_args(argv)
    if args.merge:
        reps = [c for f in args.merge for c in json.loads(Path(f).read_text())["captures"]]
        print(f"{len(reps)} captures from {len(args.merge)} file(s)")
        report(reps)
        return 0

    from sofast_station.config import load_config
    from sofast_station.station.study import run_repeats

    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_config(args.config or small_station(Path(tmp)))
        cam = cfg.geometry.camera
        print(f"station: {cfg.name}, camera {cam.width_px} x {cam.height_px}, facet {cfg.design.name}; "
              f"{args.captures} captures")
        t0 = time.perf_counter()

        def progress(i, n, rec):
            if i % 10 == 0 or i == n:
                print(f"  {i}/{n} captures ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)

        reps = run_repeats(cfg, args.captures, seed=args.seed, perturb_geometry=True, progress=progress)
    rows, crow = report(reps)
    if args.out:
        Path(args.out).write_text(json.dumps({"rows": rows, "corrected": crow, "captures": reps}, default=str))
    return 0


def report(reps):
    """Print the coverage table of *reps*; returns (rows, noise-corrected rows)."""
    from sofast_station.station.study import coverage_table

    rows = coverage_table(reps)
    # The noise-corrected slope RMS values against truth, with their own U.
    corrected = [{"figures": r["corrected"], "U": r["U_corrected"], "truth": r["truth"]} for r in reps]
    from sofast_station.measure.uncertainty import SCALAR_PATHS
    crow = coverage_table(corrected, [q for q in SCALAR_PATHS if q[0] == "slope_rms_mrad"])
    print(f"{'figure':<38}{'coverage':>9}{'median U':>11}{'mean err':>11}{'std err':>11}{'U/std':>7}{'U/rms':>7}")
    for label, table in (("", rows), ("noise-corrected ", crow)):
        for r in table:
            flag = "" if abs(r["coverage"] - 0.95) <= 0.03 else "  <- outside 95 +- 3 %"
            flag += "" if r["U_over_std"] is None or r["U_over_std"] <= 2.0 else "  <- U > 2 std"
            print(f"{label + r['figure']:<38}{100 * r['coverage']:8.1f}%{r['median_U']:11.3g}{r['mean_error']:11.2g}"
                  f"{r['std_error']:11.3g}{(r['U_over_std'] or 0):7.2f}"
                  f"{r['median_U'] / r['rms_error'] if r['rms_error'] else 0:7.2f}{flag}")
    t_an = [r["analysis_seconds"].get("uncertainty", 0.0) for r in reps[1:]]
    print(f"per capture: {sum(r['seconds'] for r in reps) / len(reps):.2f} s (twin trace, capture, analysis); "
          f"uncertainty per facet (cached sensitivities) median {sorted(t_an)[len(t_an) // 2]:.3f} s")
    return rows, crow


if __name__ == "__main__":
    sys.exit(main())
