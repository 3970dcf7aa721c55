"""The population study (issue 26): validity checks and uncertainty on stations drawn at random.

    .venv/bin/python benchmarks/population.py --captures 500                 # 50 stations of 10 captures
    .venv/bin/python benchmarks/population.py --captures 200 --seed 1 --out /tmp/pop
    .venv/bin/python benchmarks/population.py --merge /tmp/pop/population-0-500.json /tmp/pop/population-1-200.json
    .venv/bin/python benchmarks/population.py --held-out --out /tmp/held   # once per release, never while developing

What it draws and what it reports: sofast_station/station/population.py (``sofast-station study population``
runs the same). Each run writes population-SEED-N.json (every case, the tallies), .txt (the table) and .png
under --out (default: a temporary folder, printed). ``--merge`` makes the tallies of several runs' cases
(seeds run in parallel processes, each its own stations) without analysing anything. ``--held-out`` runs the
frozen held-out seeds (``population.HELD_OUT_SEEDS``, --captures split between them) and prints their merged
tallies: the check of the population claims on seeds the method was never tuned on, once per release
(docs/uncertainty.md#held-out-seeds); never run it while developing. Nothing is asserted here;
tests/station/test_population.py runs a small population in CI.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def merged_text(runs: list[dict], out: Path | None) -> str:
    """The tallies over several runs' cases (each run's JSON as loaded), their stations kept apart by seed."""
    from sofast_station.station.population import population_png, summarise, summary_text

    cases = [{**c, "index": f"{r['seed']}:{c['index']}"} for r in runs for c in r["cases"]]
    summary = summarise(cases)
    keys = {(r["seed"], c["index"]) for r in runs for c in r["cases"]}
    text = (f"{len(runs)} runs (seeds {', '.join(str(r['seed']) for r in runs)}; {len(keys)} stations)\n"
            + summary_text(summary))
    if out:
        out.mkdir(parents=True, exist_ok=True)
        population_png(cases, summary, out / "population-merged.png")
        (out / "population-merged.txt").write_text(text + "\n")
        text += f"\npng {out / 'population-merged.png'}"
    return text


def main(argv=None) -> int:
    from sofast_station.station.population import EDGE_MODELS, FAULTS, HELD_OUT_SEEDS, KINDS

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--captures", type=int, default=500, help="good captures in all")
    p.add_argument("--per-station", type=int, default=10, help="good captures per drawn station")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--kinds", default=",".join(KINDS))
    p.add_argument("--edges", default=",".join(EDGE_MODELS))
    p.add_argument("--no-faults", action="store_true")
    p.add_argument("--out", default=None, help="folder for the JSON, table and PNG")
    p.add_argument("--merge", nargs="+", default=None, metavar="JSON", help="tallies over these runs' cases")
    p.add_argument("--held-out", action="store_true",
                   help=f"the frozen held-out seeds {', '.join(map(str, HELD_OUT_SEEDS))} (--captures split between "
                        "them), merged: once per release, never while developing")
    args = p.parse_args(argv)
    import math

    from sofast_station.station.population import ProgressLog, study

    if args.merge:
        print(merged_text([json.loads(Path(f).read_text()) for f in args.merge], Path(args.out) if args.out else None))
        return 0
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="population-"))
    faults = () if args.no_faults else FAULTS
    seeds = HELD_OUT_SEEDS if args.held_out else (args.seed,)
    runs = []
    for seed in seeds:
        captures = math.ceil(args.captures / len(seeds))
        command = (f".venv/bin/python benchmarks/population.py --captures {captures} --per-station "
                   f"{args.per_station} --seed {seed}" + (" --no-faults" if args.no_faults else ""))
        stations = math.ceil(captures / args.per_station)
        result = study(captures, seed=seed, per_station=args.per_station, kinds=tuple(args.kinds.split(",")),
                       edges=tuple(args.edges.split(",")), faults=faults, out_dir=out, command=command,
                       progress=ProgressLog(stations))
        print(result["text"])
        print("\n".join(f"{k} {v}" for k, v in result["paths"].items()))
        runs.append(json.loads(result["paths"]["json"].read_text()))
    if len(runs) > 1:
        print("\nheld-out seeds, merged:\n" + merged_text(runs, out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
