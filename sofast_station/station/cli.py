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
from ..result.formatting import budget_text

log = logging.getLogger("sofast_station")


def summary_text(rec: dict) -> str:
    """A readable summary of one result record, a facet's or a heliostat's (``value ± U`` where the record has
    ``name_U``, k = 2): :func:`sofast_station.report.summary.record_text`, the one summary of a record."""
    from ..report.summary import record_text

    return record_text(rec)


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
    else:                                     # a heliostat's: one line per facet, its optics, what to turn
        print(summary_text(rec))
        if args.budget and "facets" not in rec:
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
