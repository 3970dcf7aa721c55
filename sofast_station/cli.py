"""The ``sofast-station`` command."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import tempfile
from pathlib import Path

from . import __version__
from .errors import StationError

log = logging.getLogger("sofast_station")


def _default_config() -> str:
    """station.toml in the current folder, else the one beside the package (a source checkout)."""
    here = Path("station.toml")
    if here.exists():
        return str(here)
    return str(Path(__file__).resolve().parents[1] / "station.toml")


def _json_safe(obj):
    """Replace NaN and infinities by None: JSON has no Infinity (an infinite f is null:
    docs/conventions.md#focal-power)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if hasattr(obj, "item"):          # numpy scalar
        return _json_safe(obj.item())
    return obj


def write_json_atomic(path: Path, data: dict) -> None:
    """Write JSON to a temporary file in the same folder, flush it to disk, then rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(data, fh, indent=1)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _fmt(v, unit="", digits=4):
    if v is None:
        return "inf" if unit == " m" else "-"
    return f"{v:.{digits}f}{unit}"


def summary_text(rec: dict) -> str:
    """A readable summary of one result record."""
    lines = [f"Facet {rec['serial']} ({rec['facet']}) on {rec['station']}, {rec['time']}",
             f"  verdict: {rec['verdict'].upper()}" + "".join(f"\n    - {r}" for r in rec.get("reasons", []))]
    truth = rec.get("truth")

    def row(label, key, unit="", digits=4, scale=1.0):
        v = rec.get(key)
        v = None if v is None else v * scale
        t = None if not truth or truth.get(key) is None else truth[key] * scale
        extra = f"   (truth {_fmt(t, unit, digits)})" if truth is not None else ""
        lines.append(f"  {label:<26}{_fmt(v, unit, digits):>14}{extra}")

    row("focal length x", "focal_length_x_m", " m")
    row("focal length y", "focal_length_y_m", " m")
    row("twist", "twist_mrad_per_m", " mrad/m")
    row("twist E1 / E2", "twist_e1_mrad_per_m", " mrad/m")
    row("", "twist_e2_mrad_per_m", " mrad/m")
    lines.append("  slope error RMS (mrad)        x        y   magnitude")
    for model, rms in rec["slope_rms_mrad"].items():
        t = truth["slope_rms_mrad"].get(model) if truth else None
        text = f"    {model:<22}{_fmt(rms['x'], '', 3):>9}{_fmt(rms['y'], '', 3):>9}{_fmt(rms['magnitude'], '', 3):>12}"
        if t:
            text += f"   (truth {t['x']:.3f} {t['y']:.3f} {t['magnitude']:.3f})"
        lines.append(text)
    b = rec.get("boresight_mrad")
    if b:
        lines.append(f"  boresight rotation (x, y)   {b['x']:7.3f}, {b['y']:.3f} mrad   (from the corner pose)")
    tilt = rec.get("optical_tilt_mrad")
    if tilt:
        tt = truth.get("optical_tilt_mrad") if truth else None
        extra = f"   (truth {tt['x']:.3f}, {tt['y']:.3f})" if tt else ""
        lines.append(f"  optical tilt in fixture     {tilt['x']:7.3f}, {tilt['y']:.3f} mrad{extra}")
    pl = rec.get("placement")
    if pl:
        lines.append("  placement in fixture       " + ", ".join(f"{v:.2f}" for v in pl["mm"]) + " mm, "
                     + ", ".join(f"{v:.2f}" for v in pl["mrad"]) + " mrad")
    lines.append(f"  points                    {rec['n_points']:>14,}   ({100 * rec['valid_fraction']:.1f} % of the facet's pixels)")
    lines.append(f"  median modulation         {rec['median_modulation_dn']:>11.1f} DN")
    it = rec["iterations"]
    lines.append(f"  iterations                {it['shape']:>9} shape, {it['boresight']} boresight "
                 f"({'converged' if it['converged'] else 'NOT converged'})")
    t = rec["timings_s"]
    lines.append(f"  time: capture {t['capture']:.2f} s, analysis {t['analysis']:.2f} s, total {t['total']:.2f} s")
    return "\n".join(lines)


def cmd_inspect(args) -> int:
    from .config import load_config
    from .station.inspect import inspect, open_station

    config = load_config(args.config)
    log.info("station %s (%s), facet %s", config.name, config.backend, config.design.name)
    log.info("preparing the station (simulated stations trace the twin once)...")
    station = open_station(config, seed=args.seed, noise=not args.noise_free)
    try:
        def progress(i, n):
            if i == n or i % 6 == 0:
                log.info("captured %d/%d frames", i, n)
        rec = inspect(station, args.serial, progress=progress)
    finally:
        station.close()
    rec = _json_safe(rec)
    out = config.data_dir / "inspections" / f"{rec['serial']}-{rec['time'][:19].replace(':', '')}.json"
    write_json_atomic(out, rec)
    log.info("result written to %s", out)
    if args.json:
        json.dump(rec, sys.stdout, indent=1)
        sys.stdout.write("\n")
    else:
        print(summary_text(rec))
    return 0


def cmd_run(args) -> int:
    import signal

    from .config import load_config
    from .station.service import Service, setup_logging

    config = load_config(args.config)
    log_path = setup_logging(config.data_dir, args.verbose)
    log.info("station %s (%s); data in %s; log %s", config.name, config.backend, config.data_dir, log_path)
    service = Service(config, simulated_facets=args.facets, seed=args.seed)
    stop_signals = {"count": 0}

    def on_signal(signum, frame):
        stop_signals["count"] += 1
        if stop_signals["count"] == 1:
            log.warning("stop requested (%s): finishing the current facet", signal.Signals(signum).name)
            service.runner.stop()
        else:
            raise KeyboardInterrupt

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    counts: dict[str, int] = {}
    try:
        print(f"{'serial':<14} {'focal lengths':^30} {'slope error RMS':^30} verdict  cycle", flush=True)
        for outcome in service.runner.run(max_cycles=args.max_cycles):
            counts[outcome.answer] = counts.get(outcome.answer, 0) + 1
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        log.info("stopping: waiting for the archiver to write pending rows and dumps")
        service.close()
    total = sum(counts.values())
    print(f"{total} facet(s): " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items())), flush=True)
    return 0


def cmd_archive_export(args) -> int:
    from .archive import Journal, export_workbook
    from .config import load_config

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
    from .config import load_config

    config = load_config(args.config, use_camera_record=False)  # no camera needed
    flag = config.data_dir / "dump-next"
    flag.parent.mkdir(parents=True, exist_ok=True)
    flag.touch()
    print(f"the next facet will be dumped ({flag})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sofast-station", description=__doc__)
    p.add_argument("--version", action="version", version=f"sofast-station {__version__}")
    p.add_argument("-v", "--verbose", action="store_true", help="log debugging detail")
    sub = p.add_subparsers(dest="command", required=True)
    ins = sub.add_parser("inspect", help="measure the facet in the fixture once and print its figures")
    ins.add_argument("--config", default=_default_config(), help="station file (default: ./station.toml)")
    ins.add_argument("--serial", default="SIM-0001", help="facet serial number")
    ins.add_argument("--json", action="store_true", help="print one JSON object and nothing else on stdout")
    ins.add_argument("--seed", type=int, default=None, help="simulated station: noise seed")
    ins.add_argument("--noise-free", action="store_true", help="simulated station: no sensor noise")
    ins.set_defaults(func=cmd_inspect)
    run = sub.add_parser("run", help="run the production loop: robot-triggered inspections until stopped")
    run.add_argument("--config", default=_default_config(), help="station file (default: ./station.toml)")
    run.add_argument("--facets", type=int, default=None,
                     help="simulated robot: how many facets to place (default 20)")
    run.add_argument("--max-cycles", type=int, default=None, help="stop after this many facets")
    run.add_argument("--seed", type=int, default=None, help="simulated station: noise seed")
    run.set_defaults(func=cmd_run)
    arch = sub.add_parser("archive", help="the archive: export a period to a workbook")
    arch_sub = arch.add_subparsers(dest="archive_command", required=True)
    exp = arch_sub.add_parser("export", help="write a workbook of the journal's rows in a period")
    exp.add_argument("--config", default=_default_config())
    exp.add_argument("--from", dest="since", default=None, help="ISO date/time, inclusive (default: the start)")
    exp.add_argument("--to", dest="until", default=None, help="ISO date/time, exclusive (default: now)")
    exp.add_argument("--out", default=None, help="the .xlsx to write (default: data_dir/exports/...)")
    exp.set_defaults(func=cmd_archive_export)
    dn = sub.add_parser("dump-next", help="write a data dump of the next facet measured")
    dn.add_argument("--config", default=_default_config())
    dn.set_defaults(func=cmd_dump_next)
    from .calibrate.cli import register as register_calibrate
    from .interop.cli import register as register_interop
    from .reanalysis.cli import register as register_reanalysis
    register_calibrate(sub, _default_config())
    register_interop(sub)
    register_reanalysis(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """Run a parsed command: logging to stderr, a StationError is one line and exit code 2."""
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    try:
        return args.func(args)
    except StationError as exc:
        log.error("%s", exc)
        return 2
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
