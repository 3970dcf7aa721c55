"""The population study (issue 26): validity checks and uncertainty on stations drawn at random.

    .venv/bin/python benchmarks/population.py --captures 500                 # 50 stations of 10 captures
    .venv/bin/python benchmarks/population.py --captures 200 --seed 1 --out /tmp/pop
    .venv/bin/python benchmarks/population.py --merge /tmp/pop/population-0-500.json /tmp/pop/population-1-200.json

What it draws and what it reports: sofast_station/station/population.py (``sofast-station study population``
runs the same). Each run writes population-SEED-N.json (every case, the tallies), .txt (the table) and .png
under --out (default: a temporary folder, printed). ``--merge`` makes the tallies of several runs' cases
(seeds run in parallel processes, each its own stations) without analysing anything. Nothing is asserted
here; tests/station/test_population.py runs a small population in CI.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    from sofast_station.station.population import EDGE_MODELS, FAULTS, KINDS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--captures", type=int, default=500, help="good captures in all")
    p.add_argument("--per-station", type=int, default=10, help="good captures per drawn station")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--kinds", default=",".join(KINDS))
    p.add_argument("--edges", default=",".join(EDGE_MODELS))
    p.add_argument("--no-faults", action="store_true")
    p.add_argument("--out", default=None, help="folder for the JSON, table and PNG")
    p.add_argument("--merge", nargs="+", default=None, metavar="JSON", help="tallies over these runs' cases")
    args = p.parse_args(argv)
    import math

    from sofast_station.station.population import ProgressLog, population_png, study, summarise, summary_text

    if args.merge:
        runs = [json.loads(Path(f).read_text()) for f in args.merge]
        keys = [(r["seed"], c["index"]) for r in runs for c in r["cases"]]
        cases = []
        for r in runs:
            for c in r["cases"]:
                cases.append({**c, "index": f"{r['seed']}:{c['index']}"})    # stations of different seeds apart
        summary = summarise(cases)
        print(f"{len(runs)} runs (seeds {', '.join(str(r['seed']) for r in runs)}; {len(set(keys))} stations)")
        print(summary_text(summary))
        if args.out:
            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            population_png(cases, summary, out / "population-merged.png")
            (out / "population-merged.txt").write_text(summary_text(summary) + "\n")
            print(f"png {out / 'population-merged.png'}")
        return 0
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="population-"))
    faults = () if args.no_faults else FAULTS
    command = (f".venv/bin/python benchmarks/population.py --captures {args.captures} --per-station "
               f"{args.per_station} --seed {args.seed}" + (" --no-faults" if args.no_faults else ""))
    stations = math.ceil(args.captures / args.per_station)
    result = study(args.captures, seed=args.seed, per_station=args.per_station, kinds=tuple(args.kinds.split(",")),
                   edges=tuple(args.edges.split(",")), faults=faults, out_dir=out, command=command,
                   progress=ProgressLog(stations))
    print(result["text"])
    print("\n".join(f"{k} {v}" for k, v in result["paths"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
