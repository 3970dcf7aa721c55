"""``sofast-station study repeatability``: the same facet taken out and put back N times on the twin;
``sofast-station study population``: the validity checks and the uncertainty on stations drawn at random.

Registered in :data:`sofast_station.commands.COMMAND_MODULES`.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from ..commands import add_command, add_config_option
from ..files import json_ready, write_json_atomic

log = logging.getLogger("sofast_station")


def cmd_study_repeatability(args) -> int:
    from ..config import load_config
    from ..errors import StationError
    from .study import Placement, repeatability_png, repeatability_table, run_repeats, table_text

    config = load_config(args.config)
    if args.facets < 2:
        raise StationError(f"--facets must be at least 2 to give a standard deviation, got {args.facets}")
    placement = Placement(mm=(args.placement_mm, args.placement_mm, args.placement_mm / 2),
                          mrad=(args.placement_mrad,) * 3)
    log.info("repeatability study: %d placements of %s on the twin of %s", args.facets, config.design.name,
             config.name)

    def progress(i, n, rec):
        log.info("placement %d/%d done (%.1f s)", i, n, rec["seconds"])

    repeats = run_repeats(config, args.facets, seed=args.seed, placement=placement, progress=progress)
    rows = repeatability_table(repeats, config)
    out_dir = Path(args.out) if args.out else config.data_dir / "studies"
    out_dir.mkdir(parents=True, exist_ok=True)
    png = out_dir / f"repeatability-{config.design.name}-{args.facets}.png"
    repeatability_png(rows, png, f"repeatability of {config.design.name}: {args.facets} placements within "
                                 f"±{args.placement_mm:g} mm, ±{args.placement_mrad:g} mrad, new noise each")
    table = out_dir / f"repeatability-{config.design.name}-{args.facets}.json"
    write_json_atomic(table, json_ready({"rows": rows, "facets": args.facets, "seed": args.seed,
                                        "placement": {"mm": list(placement.mm), "mrad": list(placement.mrad)}}))
    if args.json:
        json.dump(json_ready(rows), sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(table_text(rows))
        worst = max((r for r in rows if r["std_over_U_random"] is not None), key=lambda r: r["std_over_U_random"])
        print(f"largest std(error) / U_random: {worst['std_over_U_random']:.2f} ({worst['figure']}); "
              "at most 1.5 is the study's mark")
        print(f"table {table}\nplot {png}")
    return 0


def cmd_study_population(args) -> int:
    import math

    from ..errors import StationError
    from .population import EDGE_MODELS, FAULTS, KINDS, ProgressLog, study

    if args.captures < 1:
        raise StationError(f"--captures must be at least 1, got {args.captures}")
    if args.per_station < 1:
        raise StationError(f"--per-station must be at least 1, got {args.per_station}")
    kinds = tuple(args.kinds.split(",")) if args.kinds else tuple(KINDS)
    edges = tuple(args.edges.split(",")) if args.edges else tuple(EDGE_MODELS)
    for given, known, what in ((kinds, KINDS, "--kinds"), (edges, EDGE_MODELS, "--edges")):
        bad = [k for k in given if k not in known]
        if bad:
            raise StationError(f"{what}: unknown {', '.join(bad)}; use some of {', '.join(known)}")
    faults = () if args.no_faults else FAULTS
    if args.out:
        out_dir = Path(args.out)
    else:
        from ..config import load_config
        out_dir = load_config(args.config).data_dir / "studies"
    stations = math.ceil(args.captures / args.per_station)
    log.info("population study: %d good captures on %d stations (seed %d), and %d planted faults on each",
             args.captures, stations, args.seed, len(faults))
    command = (f"sofast-station study population --captures {args.captures} --per-station {args.per_station} "
               f"--seed {args.seed}" + (f" --kinds {args.kinds}" if args.kinds else "")
               + (f" --edges {args.edges}" if args.edges else "") + (" --no-faults" if args.no_faults else ""))
    result = study(args.captures, seed=args.seed, per_station=args.per_station, kinds=kinds, edges=edges,
                   faults=faults, out_dir=out_dir, command=command, progress=ProgressLog(stations))
    summary = result["summary"]
    if args.json:
        json.dump(json_ready(summary), sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(result["text"])
        print("\n".join(f"{k} {v}" for k, v in result["paths"].items()))
    missed = sum(r["n"] - r["k"] for r in summary["faults"].values())
    return 0 if summary["good"]["false_alarms"]["k"] == 0 and missed == 0 else 1


def cmd_study_methods(args) -> int:
    from ..errors import StationError
    from .methods_study import FIXED_KINDS, study_methods
    from .population import EDGE_MODELS

    if args.captures < 1 or args.per_station < 1:
        raise StationError(f"--captures and --per-station must be at least 1, got {args.captures} and "
                           f"{args.per_station}")
    kinds = tuple(args.kinds.split(",")) if args.kinds else FIXED_KINDS
    bad = [k for k in kinds if k not in FIXED_KINDS]
    if bad:
        raise StationError(f"--kinds: {', '.join(bad)} cannot be measured by the fixed method (its layout puts the "
                           f"centre of curvature between camera and screen); use some of {', '.join(FIXED_KINDS)}")
    if args.out:
        out_dir = Path(args.out)
    else:
        from ..config import load_config
        out_dir = load_config(args.config).data_dir / "studies"
    result = study_methods(args.captures, seed=args.seed, per_station=args.per_station, kinds=kinds,
                           edges=tuple(EDGE_MODELS), out_dir=out_dir)
    if args.json:
        json.dump(json_ready(result["summary"]), sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(result["text"])
        print("\n".join(f"{k} {v}" for k, v in result["paths"].items()))
    return 0


def register(subparsers) -> None:
    """Add ``study repeatability`` to the ``sofast-station`` *subparsers*."""
    study = add_command(subparsers, "study", help="measurement studies on the simulated station",
                        description="Measurement studies on the simulated station (the digital twin).")
    sub = study.add_subparsers(dest="study", metavar="STUDY", required=True)
    rep = add_command(
        sub, "repeatability", help="the same facet taken out and put back N times: spread against U and tolerance",
        description="""
            The same facet taken out of the fixture and put back N times on the twin: a new placement
            within the fixture tolerance and new sensor noise each time. For each figure: mean, standard
            deviation, the stated random uncertainty U_random (k=2) and the ratio std / U_random, and %GRR
            = 6 std / tolerance width against [limits] (10 % or less: acceptable; 10-30 %: marginal). Prints
            a table and writes it as JSON with a PNG under data_dir/studies/ (or --out).""")
    add_config_option(rep)
    rep.add_argument("--facets", type=int, default=30, metavar="N", help="placements of the facet")
    rep.add_argument("--seed", type=int, default=0, help="seed of placements and noise")
    rep.add_argument("--placement-mm", type=float, default=1.0,
                     help="fixture tolerance: x and y uniform in ±this (z in ± half of it), mm")
    rep.add_argument("--placement-mrad", type=float, default=1.0,
                     help="fixture tolerance: rotations uniform in ±this, mrad")
    rep.add_argument("--out", default=None, help="folder for the table and the PNG (default data_dir/studies)")
    rep.add_argument("--json", action="store_true", help="print the table as JSON on stdout")
    rep.set_defaults(func=cmd_study_repeatability)
    pop = add_command(
        sub, "population", help="the validity checks and U on stations and captures drawn at random",
        description="""
            Trust outside the one default station: draws stations at random (the dish, the gore, the
            heliostat facet of f 100 m and a nearly flat facet of f 600 m, each with a 400 x 300 camera;
            lens distortion up to |k1| 0.3; an image-formation model of the facet's edge: exact area,
            point or coarse grid sampling, a Gaussian blur, a defocus disk, a bevelled glass rim, strong
            vignetting; read noise 0.3-5 DN, shot noise, room light, display
            flicker, the display's residual nonlinearity) and on each --per-station good captures (new
            placement, the station's geometry drawn within [uncertainty] in the twin only, new noise),
            plus one capture of each planted fault (x and y sets swapped, display gamma not linearised, an
            obstruction, the facet misplaced). Reports the false INVALID / refusal rate on good captures
            (and which check), each fault's detection rate, each check's statistic against its threshold,
            and per figure the coverage of |error against truth| <= U. Seeded and reproducible. Writes
            population-SEED-N.json / .txt / .png under data_dir/studies/ (or --out); progress on stderr.
            Exit status 1 when a good capture was refused or invalid or a fault was missed.""")
    add_config_option(pop)
    pop.add_argument("--captures", type=int, default=100, metavar="N", help="good captures in all")
    pop.add_argument("--per-station", type=int, default=10, metavar="M", help="good captures per drawn station")
    pop.add_argument("--seed", type=int, default=0, help="seed of the population (stations, captures, faults)")
    pop.add_argument("--kinds", default=None, help="comma-separated facet kinds (default: all)")
    pop.add_argument("--edges", default=None, help="comma-separated edge models (default: all)")
    pop.add_argument("--no-faults", action="store_true", help="no planted faults (good captures only)")
    pop.add_argument("--out", default=None, help="folder for the JSON, table and PNG (default data_dir/studies)")
    pop.add_argument("--json", action="store_true", help="print the tallies as JSON on stdout")
    pop.set_defaults(func=cmd_study_population)
    met = add_command(
        sub, "methods", help="the fringes and the fixed pattern on the same facets: error, U coverage, points, time",
        description="""
            Both methods on the same captures of the population study's stations (the heliostat facet's and
            the nearly flat facet's: the layouts that index a dot grid): each capture photographed with the
            18 fringe frames and with one frame of a dot grid (spacing 12 camera px), each analysed with its
            U against the twin's truth. Per method: per figure the coverage of |error| <= U and the RMS of
            error / (U / 2), the points per facet, the capture time (frames x (settle + exposure)) and the
            analysis's CPU time (docs/method.md, "Choosing the method"). Writes methods-SEED-N.json / .txt
            under data_dir/studies/ (or --out).""")
    add_config_option(met)
    met.add_argument("--captures", type=int, default=40, metavar="N", help="captures in all (each both ways)")
    met.add_argument("--per-station", type=int, default=5, metavar="M", help="captures per drawn station")
    met.add_argument("--seed", type=int, default=0, help="seed of the population")
    met.add_argument("--kinds", default=None, help="comma-separated kinds (default: heliostat,flat)")
    met.add_argument("--out", default=None, help="folder for the JSON and table (default data_dir/studies)")
    met.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    met.set_defaults(func=cmd_study_methods)
