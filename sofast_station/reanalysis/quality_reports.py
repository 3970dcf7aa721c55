"""``sofast-station report spc | acceptance | certificate SERIAL | diff A B``: the quality engineer's reports.

The ``report`` command itself is registered by :mod:`sofast_station.reanalysis.cli` (its first word
chooses the report); :func:`add_options` adds these reports' options to it and :func:`run` runs them. The
pictures and documents are drawn by :mod:`sofast_station.report`; this module finds the records, the
recipes and the measurements they need.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)

#: The first words of ``report`` handled here.
REPORTS = ("spc", "acceptance", "certificate", "diff")


def ewma_lambda(text: str) -> float:
    """argparse type of ``--ewma``: the EWMA's weight of the newest point, in (0, 1] (a usage error, exit 2,
    otherwise; ``--ewma 5`` was a ValueError traceback)."""
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number: give the EWMA weight, e.g. 0.2") from None
    if not (math.isfinite(value) and 0.0 < value <= 1.0):
        raise argparse.ArgumentTypeError(f"{text} is not a weight between 0 (excluded) and 1: the EWMA's lambda is "
                                         "the weight of the newest facet, e.g. 0.2 (0.05 to 0.3 are usual)")
    return value


def add_options(rpt) -> None:
    """Options of the quality reports on the ``report`` parser."""
    # --config (the station file) is the report command's own option, shared with 'report trend'
    rpt.add_argument("--recipe", default=None, help="spc, acceptance: only facets of this recipe (default: all for "
                     "spc; 'default' for acceptance)")
    rpt.add_argument("--facet-type", dest="facet_type", default=None,
                     help="spc: only this facet type (the record's 'facet', e.g. dish-5.33)")
    rpt.add_argument("--serial", default=None, metavar="REGEX", help="spc: only serials matching this pattern")
    rpt.add_argument("--ewma", type=ewma_lambda, default=None, metavar="LAMBDA",
                     help="spc: also draw an EWMA chart with this weight of the newest facet, 0 < LAMBDA <= 1 "
                          "(e.g. 0.2)")
    rpt.add_argument("--rules", default="western_electric", choices=("western_electric", "nelson", "beyond_limits"),
                     help="spc: the run rules")
    rpt.add_argument("--baseline-n", type=int, default=25, metavar="N",
                     help="spc: control limits from the first N measured facets of the selection")
    rpt.add_argument("--baseline-from", default=None, metavar="DATE",
                     help="spc: control limits from this period instead (with --baseline-to)")
    rpt.add_argument("--baseline-to", default=None, metavar="DATE", help="spc: end of the baseline period")
    rpt.add_argument("--any-design", action="store_true",
                     help="diff: draw the difference of two facet types too (refused by default: it shows their "
                          "designs' difference, not a change of shape)")
    rpt.add_argument("--save-baseline", action="store_true",
                     help="spc: save the control limits as the recipe's baseline for the line's drift alarms "
                          "(data_dir/quality/baseline-RECIPE.json; needs --recipe)")


def parse_date(text, what: str):
    from ..times import parse_bound
    return parse_bound(text, what)


def check_range(since, until, what: str = "--from/--to") -> None:
    from ..times import check_period
    check_period(since, until, what)


def _config(args):
    from ..commands import default_config
    from ..config import load_config

    return load_config(args.config or default_config(), use_camera_record=False)


def _records(args, config) -> tuple[list[dict], str]:
    from ..report.trend import trend_records_from_journal, trend_records_from_results

    if args.results:
        return trend_records_from_results(args.results), f"batch results {args.results}"
    journal = Path(args.journal) if args.journal else config.data_dir / "journal.sqlite3"
    return trend_records_from_journal(journal), f"journal {journal}"


def _recipe(config, name: str | None):
    from ..errors import ConfigError
    from ..recipes import recipes_from_config

    recipes = recipes_from_config(config)
    name = name or "default"
    if name not in recipes:
        raise ConfigError(f"no recipe {name!r} in {config.path} (known: {', '.join(sorted(recipes))})")
    return recipes[name]


def run(args) -> int:
    """Run ``report spc | acceptance | certificate | diff``."""
    kind = args.targets[0]
    return {"spc": cmd_spc, "acceptance": cmd_acceptance, "certificate": cmd_certificate, "diff": cmd_diff}[kind](args)


def _period(args):
    since = parse_date(args.since, "--from")
    until = parse_date(args.until, "--to")
    check_range(since, until)
    return since, until


def cmd_spc(args) -> int:
    from ..commands import lower_priority
    from ..errors import ConfigError
    from ..qc import spc as qspc
    from ..result.specs import figure_specs
    from ..report.control_charts import (build_charts, draw_charts, draw_yield, select_records, write_summary_workbook,
                      yield_table)

    if len(args.targets) > 1:
        raise ConfigError("'report spc' takes no dumps: choose facets with --recipe, --facet, --serial, --from/--to")
    lower_priority()
    config = _config(args)
    since, until = _period(args)
    records, source = _records(args, config)
    chosen = select_records(records, recipe=args.recipe, facet=args.facet_type, serial=args.serial, since=since,
                            until=until)
    recipe = _recipe(config, args.recipe)
    facets = {r.get("facet") for r in chosen if r.get("facet")}
    if args.recipe is None and len(facets) > 1:
        raise ConfigError(f"the period holds {len(facets)} facet types ({', '.join(sorted(facets))}): choose one with "
                          "--recipe or --facet-type, so one chart does not mix them")
    specs = figure_specs(recipe.design.focal_length_m, recipe.limits)
    baselines = None
    if args.baseline_from or args.baseline_to:
        b0 = parse_date(args.baseline_from, "--baseline-from")
        b1 = parse_date(args.baseline_to, "--baseline-to")
        check_range(b0, b1, "--baseline-from/--baseline-to")
        base_records = [r for r in select_records(records, recipe=args.recipe, facet=args.facet_type,
                                                  serial=args.serial, since=b0, until=b1)
                        if r.get("verdict") in ("pass", "fail")]
        baselines = {}
        for s in specs:
            from ..result.record import figure_value
            values = [v for v in (figure_value(r, s.key) for r in base_records) if v is not None]
            try:
                baselines[s.key] = qspc.baseline(values)
            except ValueError as exc:
                raise ConfigError(f"the baseline period {b0} to {b1} gives no limits for {s.label}: {exc}") from None
    charts = build_charts(chosen, specs, baseline_n=args.baseline_n, baselines=baselines, rule_set=args.rules,
                          ewma_lambda=args.ewma)
    name = f"spc-{recipe.name}-{since or 'start'}-{until or 'now'}".replace(":", "")
    out = Path(args.out or ".")
    n = len(charts[0].values) if charts else 0
    first, last = (charts[0].times[0], charts[0].times[-1]) if n else (None, None)
    span = f"{first:%Y-%m-%d %H:%M} to {last:%Y-%m-%d %H:%M}" if n else f"{since or 'start'} to {until or 'now'}"
    title = (f"Control charts, recipe {recipe.name} ({recipe.design.name}): {n} facets, {span}; control limits from "
             + (f"the baseline {args.baseline_from} to {args.baseline_to}" if baselines
                else f"the first {min(args.baseline_n, n)} facets")
             + f"; rules {args.rules.replace('_', ' ')}")
    log.info("report spc: %s (%s)", title, source)
    for p in (draw_charts(charts, out / f"{name}.png", title, ewma_lambda=args.ewma),
              draw_yield(yield_table(chosen), out / f"{name}-yield.png", title),
              write_summary_workbook(charts, yield_table(chosen), out / f"{name}.xlsx", title, args.rules)):
        print(p, flush=True)
    if args.save_baseline:
        from ..station.drift import save_baseline
        if args.recipe is None:
            raise ConfigError("--save-baseline needs --recipe: a baseline belongs to one recipe")
        saved = {c.spec.key: c.baseline for c in charts if c.baseline is not None}
        period = ({"from": args.baseline_from, "to": args.baseline_to} if baselines else
                  {"first_facets": args.baseline_n, "from": since, "to": until})
        log.info("drift baseline of recipe %s saved to %s", recipe.name,
                 save_baseline(config.data_dir, recipe.name, saved, period))
    for c in charts:
        n_bad = len({int(k) for v in c.violations.values() for k in v})
        cap = c.capability
        log.info("%s: %d facets, %d violating a rule, Cp %s, Cpk %s", c.spec.label, c.values.size, n_bad,
                 "-" if cap.get("cp") is None else f"{cap['cp']:.2f}",
                 "-" if cap.get("cpk") is None else f"{cap['cpk']:.2f}")
    return 0


def cmd_acceptance(args) -> int:
    from ..commands import lower_priority
    from ..errors import ConfigError
    from ..qc.acceptance import contract_from_config
    from ..report.acceptance import draw, evaluate, text
    from ..report.control_charts import select_records

    if len(args.targets) > 1:
        raise ConfigError("'report acceptance' takes no dumps: choose facets with --recipe and --from/--to")
    lower_priority()
    config = _config(args)
    since, until = _period(args)
    recipe = args.recipe or "default"
    contract = contract_from_config(config, recipe)
    records, source = _records(args, config)
    chosen = select_records(records, recipe=recipe, since=since, until=until)
    results = evaluate(contract, chosen)
    period = f"{since or 'start'} to {until or 'now'}"
    print(text(contract, results, period), flush=True)
    out = Path(args.out or ".")
    log.info("report acceptance: recipe %s, %s, from the %s", recipe, period, source)
    print(draw(contract, results, out / f"acceptance-{recipe}-{since or 'start'}-{until or 'now'}.png".replace(":", ""),
               f"Contract acceptance, recipe {recipe}: {len(chosen)} facets, {period}; population "
               f"{contract.population}, confidence {100 * contract.confidence:g} %"), flush=True)
    return 0 if all(r["verdict"] == "pass" for r in results) else 1


def cmd_certificate(args) -> int:
    from ..commands import default_config, lower_priority
    from ..files import safe_name, station_data_dir
    from ..report.certificate import refuse_faulted
    from ..archive.journal import Journal
    from ..serials import clean_serial
    from ..errors import ConfigError, StationError
    from ..report.certificate import write_certificate
    from .sources import load_measured
    from ..result.specs import figure_specs

    if len(args.targets) != 2:
        raise ConfigError("'report certificate' needs one serial: report certificate SERIAL")
    serial = args.targets[1]
    # The refusals first, from the journal alone: a serial never measured, a facet whose cycle ended in a
    # fault. The station file (its records; a simulated station's twin: a second of processor) and the
    # dump's reprocessing for the maps (minutes at full resolution on a busy machine: the faulted facet was
    # once refused after 7 min 26 s) come after, at the lower priority.
    data_dir = None if args.journal else station_data_dir(args.config or default_config())
    config = _config(args) if data_dir is None and not args.journal else None
    path = Path(args.journal) if args.journal else (data_dir or config.data_dir) / "journal.sqlite3"
    if not path.is_file():
        raise ConfigError(f"no journal at {path}: this station has not measured anything yet")
    with Journal(path) as j:
        rows = j.rows(serial=serial)
        safe = clean_serial(serial)[0]
        if not rows and safe != serial:          # typed as printed; journaled as the station made it safe
            rows = j.rows(serial=safe)
    if not rows:
        raise ConfigError(f"serial {serial!r} is not in the journal {path}")
    row = rows[-1]                         # the latest test of the serial
    rec = row.record
    refuse_faulted(rec)
    lower_priority()
    config = config or _config(args)
    recipe = _recipe(config, rec.get("recipe") or "default")
    measured = None
    dump = Path(row.dump_path) if row.dump_path else None
    if isinstance(rec.get("facets"), list):         # a heliostat: the map of its facets and their table
        from ..report.certificate import write_heliostat_certificate
        if recipe.ensemble is None:
            raise ConfigError(f"serial {serial!r} is a heliostat's, but recipe {recipe.name!r} of this station file "
                              "names no heliostat: pass the heliostat station's --config")
        out = Path(args.out) if args.out and args.out.lower().endswith(".pdf") else \
            Path(args.out or ".") / f"certificate-{serial}.pdf"
        print(write_heliostat_certificate(rec, out, ensemble=recipe.ensemble,
                                          limit_mrad=recipe.limits.max_canting_mrad,
                                          dump_path=dump if dump is not None and dump.exists() else None,
                                          issuer=config.raw.get("certificate") or {}), flush=True)
        return 0
    if dump is not None and dump.exists():
        try:
            measured = load_measured(str(dump))
        except StationError as exc:
            log.warning("the dump %s could not be reprocessed for the maps: %s", dump, exc)
    elif dump is not None:
        log.warning("the dump %s named in the journal is missing: certificate without maps", dump)
        dump = None
    # The serial names the file, never a path: a journaled serial (or one typed here) such as "../../x"
    # stays inside the --out folder.
    out = Path(args.out) if args.out and args.out.lower().endswith(".pdf") else \
        Path(args.out or ".") / f"certificate-{safe_name(serial, 64)}.pdf"
    issuer = config.raw.get("certificate") or {}
    if not issuer.get("issuer"):
        log.warning("no [certificate] issuer in %s: the certificate says so in its heading", config.path)
    print(write_certificate(rec, out, specs=figure_specs(recipe.design.focal_length_m, recipe.limits),
                            measured=measured, dump_path=dump, issuer=issuer), flush=True)
    if len(rows) > 1:
        log.info("serial %s was tested %d times: the certificate shows the latest (%s)", serial, len(rows), row.time)
    return 0


def cmd_diff(args) -> int:
    from ..errors import ConfigError
    from ..commands import lower_priority
    from ..report.diff import check_same_design, common_grid_difference, diff_figures, diff_text, write_diff
    from .sources import check_measured, load_measured

    if len(args.targets) != 3:
        raise ConfigError("'report diff' needs two measurements: report diff A B (dumps, or opencsp:DIR)")
    for target in args.targets[1:]:          # both readable before either is reprocessed (minutes each)
        check_measured(target)
    lower_priority()
    a, b = (load_measured(t) for t in args.targets[1:])
    if not args.any_design:
        check_same_design(a, b)
    out = Path(args.out) if args.out and args.out.lower().endswith(".png") else \
        Path(args.out or ".") / f"diff-{Path(a.path).stem}-{Path(b.path).stem}.png"
    d = common_grid_difference(a, b)
    print(diff_text(a, b, diff_figures(a, b, d)), flush=True)
    print(write_diff(a, b, out, d=d), flush=True)
    return 0
