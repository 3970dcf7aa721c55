"""The production line's commands: ``inspect``, ``run``, ``dump-next`` and ``archive export``.

Registered in :data:`sofast_station.commands.COMMAND_MODULES`; each command imports the station, the
devices and the archive only when it runs.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from ..commands import add_command, add_config_option, positive_int
from ..files import json_ready, write_json_atomic
from ..errors import StationError
from ..result.formatting import budget_text, shown_decimals, value_and_u, with_u

log = logging.getLogger("sofast_station")


def _fmt(v, unit="", digits=4):
    if v is None:
        return "inf" if unit == " m" else "-"
    return f"{v:.{digits}f}{unit}"


def optics_lines(opt: dict | None, truth: dict | None = None) -> list[str]:
    """The optical figures of a record (``optics``), with their ``_U`` uncertainty and truth when present."""
    if not opt:
        return []

    def show(d, key, fmt, scale=1.0, u=None):
        """The value, `` ± U`` when ``key_U`` is in *d* (or *key* in *u*, for a nested figure's U); *fmt* gives
        the decimals (and sign) of a value without U."""
        big_u = d.get(f"{key}_U") if u is None else u.get(key)
        decimals = int(fmt.split(".")[1].rstrip("f}"))
        return with_u(d.get(key), big_u, decimals=decimals, scale=scale, sign="+" in fmt)

    def extra(key, fmt, scale=1.0, sub=None):
        if not truth:
            return ""
        v = truth.get(key) if sub is None else (truth.get(key) or {}).get(sub)
        return f"   (truth {'-' if v is None else fmt.format(v * scale)})"

    c = opt["conditions"]
    ap = c["aperture"]
    ap_text = (f"circle r {1000 * ap['radius_m']:.1f} mm" if ap["shape"] == "circle"
               else f"rectangle {1000 * ap['width_m']:.1f} x {1000 * ap['height_m']:.1f} mm")
    off = opt["centroid_offset_mrad"]
    off_u = opt.get("centroid_offset_mrad_U") or {}
    return [f"  optics: {c['sun']['shape']} sun, DNI {c['dni_w_m2']:g} W/m^2, reflectivity {c['reflectivity']:g}, "
            f"target at {c['slant_range_m']:.3f} m, aperture {ap_text}",
            f"    intercept factor        {show(opt, 'intercept', '{:.4f}'):>12}   (design "
            f"{opt['design']['intercept']:.4f}){extra('intercept', '{:.4f}')}",
            f"    90 % spot radius        {show(opt, 'spot_radius_m', '{:.2f}', 1000.0):>12} mm   (design "
            f"{_fmt(opt['design']['spot_radius_m'] and 1000 * opt['design']['spot_radius_m'], '', 2)} mm; analytic "
            f"{1000 * opt['analytic_spot_radius_m']:.2f} mm){extra('spot_radius_m', '{:.2f}', 1000.0)}",
            f"    centroid offset         {show(off, 'magnitude', '{:.3f}', u=off_u):>12} mrad "
            f"(x {show(off, 'x', '{:+.3f}', u=off_u)}, y {show(off, 'y', '{:+.3f}', u=off_u)})"
            f"{extra('centroid_offset_mrad', '{:.3f}', sub='magnitude')}",
            f"    power / design's        {show(opt, 'power_ratio_vs_design', '{:.4f}'):>12}"
            f"{extra('power_ratio_vs_design', '{:.4f}')}"]


def _pm(v, u, unit="", digits=4):
    """``5.4183 ± 0.0021 m`` (:func:`~sofast_station.result.formatting.with_u`), or the value to *digits*
    decimals without an uncertainty."""
    return _fmt(v, unit, digits) if v is None else with_u(v, u, unit, digits)


def summary_text(rec: dict) -> str:
    """A readable summary of one result record (``value ± U`` where the record has ``name_U``, k = 2)."""
    lines = [f"Facet {rec['serial']} ({rec['facet']}) on {rec['station']}, {rec['time']}",
             f"  verdict: {rec['verdict'].upper()}" + "".join(f"\n    - {r}" for r in rec.get("reasons", []))
             + "".join(f"\n    warning: {w}" for w in rec.get("warnings", []))]
    truth = rec.get("truth")
    k = rec.get("coverage_factor")
    if k is not None:
        lines.append(f"  figures are value ± U, the expanded uncertainty (k={k:g})")

    def row(label, key, unit="", digits=4, scale=1.0):
        v = rec.get(key)
        v = None if v is None else v * scale
        u = rec.get(f"{key}_U")
        u = None if u is None else u * scale
        digits = shown_decimals(v, u, digits)         # the truth to the value's decimals
        t = None if not truth or truth.get(key) is None else truth[key] * scale
        extra = f"   (truth {_fmt(t, unit, digits)})" if truth is not None else ""
        lines.append(f"  {label:<26}{_pm(v, u, unit, digits):>24}{extra}")

    row("focal length x", "focal_length_x_m", " m")
    row("focal length y", "focal_length_y_m", " m")
    row("twist", "twist_mrad_per_m", " mrad/m")
    row("twist E1 / E2", "twist_e1_mrad_per_m", " mrad/m")
    row("", "twist_e2_mrad_per_m", " mrad/m")
    rms_u = rec.get("slope_rms_mrad_U") or {}
    lines.append("  slope error RMS (mrad)        x        y   magnitude" + ("      ± U" if rms_u else ""))
    for model, rms in rec["slope_rms_mrad"].items():
        t = truth["slope_rms_mrad"].get(model) if truth else None
        u = (rms_u.get(model) or {}).get("magnitude")
        magnitude, big_u = ("-", None) if rms["magnitude"] is None else value_and_u(rms["magnitude"], u, 3)
        text = f"    {model:<22}{_fmt(rms['x'], '', 3):>9}{_fmt(rms['y'], '', 3):>9}{magnitude:>12}"
        if big_u is not None:
            text += f" ± {big_u}"
        if t:
            text += f"   (truth {t['x']:.3f} {t['y']:.3f} {t['magnitude']:.3f})"
        lines.append(text)
    noise = rec.get("slope_rms_noise_mrad")
    corrected = rec.get("slope_rms_corrected_mrad")
    if noise and corrected:
        n = next(iter(noise.values()))
        lines.append(f"    {'noise explained':<22}{n['x']:9.3f}{n['y']:9.3f}{n['magnitude']:12.3f}"
                     "   (slope noise the capture's own noise explains)")
        lines.append("    with that noise removed in quadrature:")
        for model, c in corrected.items():
            lines.append(f"    {model:<22}{_fmt(c['x'], '', 3):>9}{_fmt(c['y'], '', 3):>9}"
                         f"{_fmt(c['magnitude'], '', 3):>12}")

    def pair(label, key, unit, note=""):
        v = rec.get(key)
        if not v:
            return
        u = rec.get(f"{key}_U") or {}
        tt = truth.get(key) if truth else None
        extra = f"   (truth {tt['x']:.3f}, {tt['y']:.3f})" if tt else ""
        lines.append(f"  {label:<28}{_pm(v['x'], u.get('x'), '', 3)}, {_pm(v['y'], u.get('y'), '', 3)} {unit}"
                     f"{note}{extra}")

    pair("boresight rotation (x, y)", "boresight_mrad", "mrad", "   (from the corner pose)")
    for key, why in (rec.get("not_measured") or {}).items():        # an unknown outline's, the plano model's
        lines.append(f"  {key.replace('_', ' '):<26} not measured: {why}")
    pair("optical tilt in fixture", "optical_tilt_mrad", "mrad")
    pl = rec.get("placement")
    if pl:
        pu = rec.get("placement_U") or {"mm": [None] * 3, "mrad": [None] * 3}
        lines.append("  placement in fixture       " + ", ".join(_pm(v, u, "", 2) for v, u in zip(pl["mm"], pu["mm"]))
                     + " mm, " + ", ".join(_pm(v, u, "", 2) for v, u in zip(pl["mrad"], pu["mrad"])) + " mrad")
    lines.extend(optics_lines(rec.get("optics"), (truth or {}).get("optics")))
    lines.append(f"  points                    {rec['n_points']:>14,}   "
                 f"({100 * rec['valid_fraction']:.1f} % of the facet's pixels)")
    lines.append(f"  median modulation         {rec['median_modulation_dn']:>11.1f} DN")
    it = rec["iterations"]
    lines.append(f"  iterations                {it['shape']:>9} shape, {it['boresight']} boresight "
                 f"({'converged' if it['converged'] else 'NOT converged'})")
    t = rec["timings_s"]
    lines.append(f"  time: capture {t['capture']:.2f} s, analysis {t['analysis']:.2f} s, total {t['total']:.2f} s")
    return "\n".join(lines)


def cmd_inspect(args) -> int:
    from ..files import safe_name
    from ..config import load_config
    from ..serials import clean_serial, raw_for_record
    from .factory import open_station
    from .inspection import inspect

    config = load_config(args.config)
    log.info("station %s (%s), facet %s", config.name, config.backend, config.design.name)
    log.info("preparing the station (simulated stations trace the twin once)...")
    station = open_station(config, seed=args.seed, noise=not args.noise_free)
    try:
        def progress(i, n):
            if i == n or i % 6 == 0:
                log.info("captured %d/%d frames", i, n)
        serial, note = clean_serial(args.serial)
        if note:
            log.warning("%s", note)
        recipe = None
        if args.recipe is not None:
            from ..recipes import recipes_from_config

            recipes = recipes_from_config(config)
            if args.recipe not in recipes:
                from ..errors import ConfigError
                raise ConfigError(f"--recipe {args.recipe!r} is not one of {config.path}'s recipes: "
                                  f"{', '.join(sorted(recipes))} ([recipes.NAME] tables)")
            recipe = recipes[args.recipe]
        rec = inspect(station, serial, progress=progress, pictures_dir=config.data_dir / "inspections", recipe=recipe)
        if note:                             # the serial as typed, when making it safe changed it
            rec["serial_raw"] = raw_for_record(args.serial)
    finally:
        station.close()
    rec = json_ready(rec)
    # the serial never makes a path: no '/', no '..' (the result stays inside data_dir/inspections)
    out = config.data_dir / "inspections" / f"{safe_name(rec['serial'], 64)}-{rec['time'][:19].replace(':', '')}.json"
    write_json_atomic(out, rec)
    log.info("result written to %s", out)
    if args.json:
        json.dump(rec, sys.stdout, indent=1)
        sys.stdout.write("\n")
    elif "facets" in rec:                     # a heliostat: one line per facet, its optics, what to turn
        from .heliostat import summary_text as heliostat_summary
        print(heliostat_summary(rec))
    else:
        print(summary_text(rec))
        if args.budget:
            print(budget_text(rec))
    return 0


def cmd_run(args) -> int:
    import signal

    from ..config import load_config
    from ..web.settings import opcua_settings, web_settings
    from . import console
    from ..live.logs import setup_logging
    from .service import Service
    from ..result.shift import ShiftTally

    config = load_config(args.config)
    log_path = setup_logging(config.data_dir, args.verbose)
    log.info("station %s (%s); data in %s; log %s", config.name, config.backend, config.data_dir, log_path)
    web, opcua = web_settings(config), opcua_settings(config)
    monitor = None
    if args.serve or opcua.enabled:
        from ..web.monitor import MonitorProcess
        monitor = MonitorProcess(config, web if args.serve else None, opcua)
    try:
        service = Service(config, simulated_facets=args.facets, seed=args.seed)
    except BaseException:
        if monitor is not None:
            monitor.stop()
        raise
    stop_signals = {"count": 0}

    def on_signal(signum, frame):
        stop_signals["count"] += 1
        if stop_signals["count"] == 1:
            log.warning("stop requested (%s): finishing the current facet", signal.Signals(signum).name)
            service.runner.stop()
        else:
            raise KeyboardInterrupt

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    # The run's summary as running statistics (a fixed size): a station runs for months, and an outcome
    # holds the analysis's pixel mask and preview (megabytes at full resolution).
    tally = ShiftTally()

    def keep(outcome):
        tally.add(outcome.record)              # its cycle time as the page shows it (cycle_seconds)
    runner = service.runner
    if args.max_cycles is not None:
        runner.expected_total = min(args.max_cycles, runner.expected_total or args.max_cycles)
    try:
        print(console.header(runner.expected_total), flush=True)
        runner.run(max_cycles=args.max_cycles, on_outcome=keep)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        log.info("stopping: waiting for the archiver to write pending rows and dumps")
        service.close()
        if monitor is not None:
            monitor.stop()
    summary = tally.summary()
    text = console.summary_text(summary)
    log.info("run summary: %s", text.replace("\n", " | "))
    print(text, flush=True)
    return 0


def cmd_serve(args) -> int:
    from ..config import load_config
    from ..web.monitor import serve
    from ..web.settings import opcua_settings, web_settings
    from ..live.logs import setup_logging

    config = load_config(args.config, use_camera_record=False)      # the page opens no device
    setup_logging(config.data_dir, args.verbose, name="monitor.log")
    web = web_settings(config)
    if args.host is not None or args.port is not None:
        import dataclasses
        web = dataclasses.replace(web, host=args.host or web.host, port=web.port if args.port is None else args.port)
        web.exposure(f"{config.path} [web] (with --host/--port)")     # beyond loopback: HTTPS or a decision
    opcua = opcua_settings(config)

    def ready(info):
        print(f"the line's page: {info['url']}" + ("" if web.token else "  (read-only: no [web] token)"), flush=True)
        if info.get("opcua"):
            print(f"OPC UA server: {info['opcua']}", flush=True)
    serve(config, web, opcua, nice=web.nice, on_ready=ready)
    return 0


def cmd_archive_export(args) -> int:
    from ..archive import Journal, export_workbook
    from ..times import check_period, parse_bound
    from ..config import load_config

    args.since = parse_bound(args.since, "--from")
    args.until = parse_bound(args.until, "--to")
    check_period(args.since, args.until)
    config = load_config(args.config, use_camera_record=False)  # no camera needed
    path = config.data_dir / "journal.sqlite3"
    if not path.exists():
        raise StationError(f"no journal at {path}: this station has not measured anything yet")
    journal = Journal(path)
    try:
        out = Path(args.out) if args.out else config.data_dir / "exports" / \
            f"sofast-{args.since or 'start'}-{args.until or 'now'}.xlsx".replace(":", "")
        files = export_workbook(journal, args.since, args.until, out)
    finally:
        journal.close()
    for f in files:
        print(f)
    return 0


def cmd_dump_next(args) -> int:
    from ..config import load_config

    from ..live.operator_commands import request_dump_next

    config = load_config(args.config, use_camera_record=False)  # no camera needed
    flag = request_dump_next(config.data_dir)
    print(f"the next facet will be dumped ({flag})")
    return 0


def register(subparsers) -> None:
    """Add ``inspect``, ``run``, ``dump-next`` and ``archive`` to the ``sofast-station`` *subparsers*."""
    ins = add_command(
        subparsers, "inspect", help="measure the facet in the fixture once and print its figures",
        description="""
            Measure the facet in the fixture once: show the 18 fringe images, capture them, analyse them and
            print the facet's figures (focal lengths, twist, slope-error RMS per model, boresight, placement)
            with the verdict. On the simulated station the twin's ground truth is printed beside each figure.
            The result is also written as JSON under the station's data_dir/inspections/.

            Progress goes to stderr; with --json stdout holds one JSON object and nothing else.""")
    add_config_option(ins)
    ins.add_argument("--serial", default="SIM-0001", help="the facet's serial number")
    ins.add_argument("--recipe", default=None, metavar="NAME",
                     help="measure with station.toml's [recipes.NAME] (its facet design, settings and limits; a facet "
                          "file with outline_known = false measures a mirror of unknown outline) instead of the "
                          "station's own")
    ins.add_argument("--json", action="store_true", help="print one JSON object and nothing else on stdout")
    ins.add_argument("--seed", type=int, default=None,
                     help="simulated station: noise seed (default: the [simulation] seed of the station file)")
    ins.add_argument("--noise-free", action="store_true", help="simulated station: no sensor noise")
    ins.add_argument("--budget", action="store_true",
                     help="also print the uncertainty budget: input against figure (docs/uncertainty.md)")
    ins.set_defaults(func=cmd_inspect)

    run = add_command(
        subparsers, "run", help="run the production loop: robot-triggered inspections until stopped",
        description="""
            Run the production loop: wait for the robot or PLC to signal "facet in place", answer busy,
            capture, analyse, judge, journal the facet's row, and answer done (pass, fail, invalid) or fault
            with a reason code. An archiver process writes the daily workbooks and the data dumps. One line
            per facet goes to stdout, a rotating log to data_dir/logs/.

            Ctrl-C or SIGTERM finishes the facet in progress, waits for the archiver, then stops; a second
            Ctrl-C stops at once.""")
    add_config_option(run)
    run.add_argument("--facets", type=positive_int, default=None, metavar="N",
                     help="simulated robot: how many facets to place (default 20)")
    run.add_argument("--max-cycles", type=positive_int, default=None, metavar="N",
                     help="stop after this many facets (default: run until stopped)")
    run.add_argument("--seed", type=int, default=None,
                     help="simulated station: noise seed (default: the [simulation] seed of the station file)")
    run.add_argument("--serve", action="store_true",
                     help="also serve the line's web page ([web] in the station file; see 'serve --help')")
    run.set_defaults(func=cmd_run)

    srv = add_command(
        subparsers, "serve", help="serve the line's web page (and OPC UA when [opcua] enabled)",
        description="""
            Serve the operator's web page for the line: the last facet (serial, recipe, verdict, reasons,
            figures with their limits, the white frame with the found outline, the slope-error map), the
            shift (facets, yield, faults by kind, cycle times, charts of the last 50 facets) and the station
            (state, calibration, free disk, archive backlog, alarms). The page updates itself when a facet
            is journaled. It reads the journal and the files in data_dir only, so it can run beside
            'sofast-station run' (or use 'run --serve'), at a lower priority.

            Actions (dump the next facet, pause and resume, re-measure, a serial by hand) need the token
            of [web] token in the station file; without one the page is read-only. The page is served on
            127.0.0.1 unless [web] host says otherwise. With [opcua] enabled = true the OPC UA server
            (docs/opcua.md) runs in the same process.""")
    add_config_option(srv)
    srv.add_argument("--host", default=None, help="address to listen on (default: [web] host, else 127.0.0.1)")
    srv.add_argument("--port", type=int, default=None, help="port (default: [web] port, else 8080; 0: any free)")
    srv.set_defaults(func=cmd_serve)

    dn = add_command(
        subparsers, "dump-next", help="write a data dump of the next facet measured",
        description="""
            Ask the running station to write an HDF5 data dump of the next facet it measures (it leaves a
            flag file in data_dir that the loop picks up). Dumps go to data_dir/dumps/; their layout is
            docs/dump-schema.md.""")
    add_config_option(dn)
    dn.set_defaults(func=cmd_dump_next)

    arch = add_command(
        subparsers, "archive", help="the archive: export a period of the journal to a workbook",
        description="""
            The station's archive. 'archive export' writes the journal's rows of a period into an Excel
            workbook (the daily workbooks in data_dir/archive/ are written by the running station).""")
    arch_sub = arch.add_subparsers(dest="archive_command", required=True, metavar="SUBCOMMAND", title="subcommands")
    exp = add_command(
        arch_sub, "export", help="write a workbook of the journal's rows in a period",
        description="""
            Write the journal's rows of a period to an Excel workbook (several when the rows exceed Excel's
            row limit) and print the file names. Nothing is measured: the camera is not opened.""")
    add_config_option(exp)
    exp.add_argument("--from", dest="since", default=None, metavar="DATE",
                     help="ISO date or date/time, 'today' or 'yesterday' (local midnight), inclusive (default: the "
                          "start of the journal)")
    exp.add_argument("--to", dest="until", default=None, metavar="DATE",
                     help="ISO date or date/time, 'today' or 'yesterday', exclusive: --from yesterday --to today is "
                          "yesterday's rows (default: now)")
    exp.add_argument("--out", default=None, metavar="FILE",
                     help="the .xlsx to write (default: data_dir/exports/sofast-FROM-TO.xlsx)")
    exp.set_defaults(func=cmd_archive_export)
