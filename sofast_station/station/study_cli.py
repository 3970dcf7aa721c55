"""``sofast-station study repeatability``: the same facet taken out and put back N times on the twin.

Registered in :data:`sofast_station.commands.COMMAND_MODULES`.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from ..commands import add_command, add_config_option, json_safe, write_json_atomic

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
    write_json_atomic(table, json_safe({"rows": rows, "facets": args.facets, "seed": args.seed,
                                        "placement": {"mm": list(placement.mm), "mrad": list(placement.mrad)}}))
    if args.json:
        json.dump(json_safe(rows), sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(table_text(rows))
        worst = max((r for r in rows if r["std_over_U_random"] is not None), key=lambda r: r["std_over_U_random"])
        print(f"largest std(error) / U_random: {worst['std_over_U_random']:.2f} ({worst['figure']}); "
              "at most 1.5 is the study's mark")
        print(f"table {table}\nplot {png}")
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
