"""The re-analysis commands of ``sofast-station``: ``reprocess``, ``batch`` and ``report``.

``register(subparsers)`` adds them to the ``sofast-station`` parser (listed in
:data:`sofast_station.commands.COMMAND_MODULES`). Importing
this module imports nothing heavy: each command first puts BLAS on one thread (unless the user set a
thread count), then loads numpy and the analysis, so that reprocessing is bit-exact
(docs/conventions.md#determinism).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import textwrap
import time
from pathlib import Path

from ..commands import add_command
from ..commands import build_parser as _build_parser
from ..commands import default_config, lower_priority, run
from ..result.formatting import aperture_text, with_u
from ._env import single_thread_blas

log = logging.getLogger(__name__)

#: Exit codes: some dump could not be reprocessed; with --check, some figure (or its U) differs from the archive.
EXIT_FAILED = 2
EXIT_DIFFERS = 3


# -- options shared by the three commands ---------------------------------------------------------------
def _add_overrides(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("overrides (what the engineer changes; default: the dump's own)")
    g.add_argument("--facet", metavar="FILE", help="facet model: a facet TOML file ([facet] table) replacing the "
                   "dumped design (its shape, outline, measure and alignment points)")
    g.add_argument("--focal-length", metavar="M", type=float, help="design focal length, metres")
    g.add_argument("--alignment-point", metavar=("X", "Y"), type=float, nargs=2,
                   help="boresight alignment point (x, y) in the facet frame, metres")
    g.add_argument("--distance", metavar="M", type=float,
                   help="measured distance from the screen centre to the design's measure point, metres")
    g.add_argument("--mask-threshold", metavar="DN", type=float,
                   help="facet mask threshold (white - dark), DN")
    g.add_argument("--calibration", metavar="FILE", help="radiometric calibration record (JSON); the frames "
                   "were captured with the dumped record, so only the result's calibration reference changes")


def overrides_from_args(args):
    """The :class:`~sofast_station.reanalysis.reprocess.Overrides` of parsed command-line options."""
    from .reprocess import Overrides

    return Overrides(facet_path=args.facet, focal_length_m=args.focal_length,
                     alignment_point_m=tuple(args.alignment_point) if args.alignment_point else None,
                     measured_distance_m=args.distance, mask_threshold_dn=args.mask_threshold,
                     radiometric_path=args.calibration)


def register(subparsers) -> None:
    """Add ``reprocess``, ``batch``, ``report`` and ``export`` to a ``sofast-station`` subparsers object.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        From ``parser.add_subparsers()``.
    """
    rep = add_command(
        subparsers, "reprocess",
        help="rerun the analysis of data dumps from their raw frames and compare with the archive",
        description="Recompute every figure of each dump from its raw frames (never a stored result) and print "
                    "archived versus new. With no overrides, the same software on the same platform reproduces "
                    "the archived figures exactly, and says so.")
    rep.add_argument("dumps", nargs="+", metavar="DUMP", help="HDF5 data dump(s)")
    rep.add_argument("--json", action="store_true",
                     help="print one JSON object per dump and line (the keys of 'inspect --json', plus 'archived', "
                          "'differences' and 'reprocess') and nothing else on stdout")
    rep.add_argument("--all", action="store_true", help="list every figure, not only the main and the changed ones")
    rep.add_argument("--journal", metavar="PATH",
                     help="the station's journal.sqlite3: the archived record of a dump that has lost its own")
    rep.add_argument("--check", action="store_true",
                     help=f"exit with {EXIT_DIFFERS} when a figure or its U differs from the archive")
    _add_overrides(rep)
    rep.set_defaults(func=cmd_reprocess)

    bat = add_command(
        subparsers, "batch", help="reprocess a folder or glob of dumps, locally or on a Dask cluster, resumably",
        description="Reprocess many dumps: one JSON result per dump in OUT/results/ (written atomically; a "
                    "killed batch resumes without redoing finished dumps), then OUT/summary.xlsx and "
                    "OUT/summary.csv. A dump that fails is reported in the summary; the batch goes on.")
    bat.add_argument("sources", nargs="+", metavar="FOLDER_OR_GLOB", help="folders (searched for *.h5), dumps, or "
                     "glob patterns (quote them; ** matches sub-folders)")
    bat.add_argument("--out", required=True, metavar="DIR", help="output folder (reuse it to resume)")
    bat.add_argument("--workers", type=int, default=None, metavar="N",
                     help="local worker processes (default: the number of CPUs)")
    bat.add_argument("--scheduler", metavar="ADDRESS",
                     help="run on the Dask cluster of this scheduler (tcp://host:8786); the dumps must be "
                          "readable by its workers under the same paths")
    bat.add_argument("--journal", metavar="PATH", help="journal for dumps that have lost their archived record")
    bat.add_argument("--retry-failed", action="store_true", help="redo the dumps that failed in an earlier run")
    bat.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    _add_overrides(bat)
    bat.set_defaults(func=cmd_batch)

    rpt = add_command(
        subparsers, "report", help="slope-error maps of dumps (the paper's Figs. 8-10), 'report trend' over a period, "
                                   "'report flux' (flux maps), or the quality reports",
        description="'report DUMP...' writes one PNG per dump: the slope-error magnitude with arrows of the error "
                    "direction, for the design, the fitted parabola and the higher-order model, the RMS figures in "
                    "the titles, and a detail page against one model (--detail). 'report trend [--from] [--to]' plots "
                    "focal lengths, residuals and twist over the period from the station's journal (in the data_dir "
                    "of --config), or from --journal PATH, or from the --results DIR of a batch. 'report spc', "
                    "'report acceptance', 'report certificate SERIAL' and 'report diff A B' are the quality "
                    "engineer's reports: control charts of the journal, contract acceptance of a lot, one facet's "
                    "certificate, two facets compared (their options say which report they belong to). 'report flux "
                    "DUMP...' (or opencsp:DIR, or --opencsp DIR) writes the facet's flux map on the target plane in "
                    "W/m² beside its design's, the receiver aperture drawn, with the dump's [optics] settings unless "
                    "the flux options change them; it prints the intercept factor, 90 % spot radius, centroid offset "
                    "and power ratio.")
    rpt.add_argument("targets", nargs="+", metavar="DUMP_OR_REPORT",
                     help="dump(s) or opencsp:DIR; or 'trend', 'spc', 'acceptance', 'certificate SERIAL', 'diff A B', "
                          "'flux DUMP...'")
    rpt.add_argument("--out", metavar="DIR_OR_FILE", default=None,
                     help="folder for the pictures (default: the current folder); for a trend, a .png file or a "
                          "folder")
    rpt.add_argument("--vmax", type=float, default=None, metavar="MRAD",
                     help="top of the colour scale, mrad (default: the 99th percentile of the data, rounded up; "
                          "the paper used 5)")
    rpt.add_argument("--arrow-step", type=int, default=None, metavar="N",
                     help="an arrow at every Nth camera row and column (default: 10, more on large images)")
    rpt.add_argument("--cmap", default="viridis", help="Matplotlib colour map of the magnitude (default viridis)")
    rpt.add_argument("--detail", default="parabola", choices=("design", "parabola", "higher_order", "none"),
                     help="also write <dump>-detail-MODEL.png: e_x, e_y, magnitude, height error (µm) and local "
                          "focal power against this model (default parabola; none: skip)")
    rpt.add_argument("--separate", action="store_true", help="three files per dump instead of three panels")
    rpt.add_argument("--journal", metavar="PATH",
                     help="trend: a station's journal.sqlite3 (default: the journal in the data_dir of --config)")
    rpt.add_argument("--config", metavar="FILE", default=None,
                     help="trend: the station file whose data_dir holds the journal, when neither --journal nor "
                          "--results is given (default: ./station.toml if present, else the one beside the package)")
    rpt.add_argument("--results", metavar="DIR", help="trend: a batch output folder")
    rpt.add_argument("--from", dest="since", default=None, metavar="ISO", help="trend: start (inclusive)")
    rpt.add_argument("--to", dest="until", default=None, metavar="ISO", help="trend: end (exclusive)")
    from .quality_reports import add_options as add_quality_options
    add_quality_options(rpt)
    flux = rpt.add_argument_group("flux maps ('report flux')")
    flux.add_argument("--opencsp", metavar="DIR", default=None,
                      help="flux: an OpenCSP measurement in the layout of its test data (e.g. fixtures/opencsp/"
                           "test_data) instead of dumps")
    flux.add_argument("--opencsp-focal-length", type=float, default=100.0, metavar="M",
                      help="flux: the OpenCSP facet's design focal length, metres")
    flux.add_argument("--sun", choices=("pillbox", "gaussian", "buie"), default=None,
                      help="flux: sun shape (default: the dump's [optics], else pillbox)")
    flux.add_argument("--sigma-mrad", type=float, default=None, help="flux: Gaussian sun's sigma, mrad")
    flux.add_argument("--csr", type=float, default=None, help="flux: Buie sun's circumsolar ratio")
    flux.add_argument("--dni", type=float, default=None, metavar="W_M2", help="flux: DNI, W/m² (default 1000)")
    flux.add_argument("--reflectivity", type=float, default=None, help="flux: mirror reflectivity (default 0.94)")
    flux.add_argument("--incidence", type=float, default=None, metavar="DEG", help="flux: incidence angle, degrees")
    flux.add_argument("--slant-range", type=float, default=None, metavar="M",
                      help="flux: distance to the target plane, metres (default: the design's focal distance)")
    flux.add_argument("--aperture", type=float, nargs="+", default=None, metavar="M",
                      help="flux: receiver aperture, metres: one value is a circle's radius, two a rectangle's "
                           "width and height")
    flux.add_argument("--rays-per-pixel", type=float, default=None, help="flux: rays per measured point")
    flux.add_argument("--grid-cells", type=int, default=None, help="flux: cells per side of the map")
    _add_overrides(rpt)
    rpt.set_defaults(func=cmd_report)

    e = add_command(
        subparsers, "export", help="write a measured surface for other tools (CSV, PLY, OpenCSP, SolTrace)",
        description="""
            export surface DUMP.h5 --format csv|ply|opencsp|soltrace: reprocess the dump and write its measured
            points, normals, slope errors and height error in the facet frame, named and headed by the facet's
            serial, with the units in the header (sofast_station/interop/export.py says what each format
            holds). The OpenCSP file is in the layout of OpenCSP's SOFAST processing output; the SolTrace file
            is a finite-element surface (.fed) of the design's height plus the measured height error.""")
    e.add_argument("what", choices=("surface",), help="what to export: surface")
    e.add_argument("dumps", nargs="+", metavar="DUMP", help="data dumps (HDF5) of the facets")
    e.add_argument("--format", required=True, choices=("csv", "ply", "opencsp", "soltrace"),
                   help="csv (one row per point), ply (binary point cloud with normals), opencsp (its processed-"
                        "result HDF5), soltrace (finite-element surface .fed)")
    e.add_argument("--out", default=".", metavar="DIR_OR_FILE",
                   help="folder for the files (default: here), or the file when one dump is given")
    e.set_defaults(func=cmd_export)


def build_parser() -> argparse.ArgumentParser:
    """A parser with only the re-analysis commands (for tests and ``python -m``)."""
    return _build_parser(description="The re-analysis commands of sofast-station (docs/reanalysis.md).",
                         modules=(__name__,))


# -- reprocess ----------------------------------------------------------------------------------------------
def _fmt(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        return f"{v:.10g}"
    if isinstance(v, (list, dict)):
        text = json.dumps(v, ensure_ascii=False)
    else:
        text = str(v)
    return text if len(text) <= 24 else text[:21] + "..."


def comparison_table(result, show_all: bool = False) -> str:
    """Archived versus new, one figure a line (``value ± U`` where the record has its U, by the one rule:
    :func:`~sofast_station.result.formatting.with_u`), the value's difference and its U's: the main
    figures and every one whose value or U changed (or all)."""
    from .reprocess import HEADLINE, figure_of_uncertainty, flatten_figures, flatten_uncertainties

    def u_by_figure(record) -> dict:
        """Figure name -> (its U's flat name, U) of a record."""
        if not record:
            return {}
        return {figure_of_uncertainty(k): (k, v) for k, v in flatten_uncertainties(record).items()
                if not k.endswith("_U_random") and "_U_random." not in k and "_U_random[" not in k
                and "_interval[" not in k}

    new = flatten_figures(result.record)
    old = flatten_figures(result.archived) if result.archived else {}
    new_u, old_u = u_by_figure(result.record), u_by_figure(result.archived)

    def value_u(value, u) -> str:
        if u is None or not isinstance(value, (int, float)) or isinstance(value, bool):
            return _fmt(value)
        return with_u(value, u)

    def u_change(name) -> str:
        """How the figure's U moved: "0", "+0.00019 (+20 %)", "(absent)"..."""
        key = (new_u.get(name) or old_u.get(name) or (None,))[0]
        d = result.differences.get(key) if key else None
        if key is None or not old:
            return ""
        if d is None:
            return "0"
        if d["difference"] is None:
            return "changed"
        a = d["archived"]
        return f"{d['difference']:+.2g}" + (f" ({100 * d['difference'] / a:+.0f} %)" if a else "")

    moved_u = {d.get("uncertainty_of") for d in result.differences.values()}
    names = list(new) + [k for k in old if k not in new]
    shown = names if show_all else [k for k in names if k in HEADLINE or k in result.differences or k in moved_u]
    lines = [f"  {'figure':<40} {'archived':>24} {'new':>24} {'new - archived':>16} {'U: new - archived':>18}"]
    for name in shown:
        a, b = old.get(name, "(absent)" if old else "-"), new.get(name, "(absent)")
        d = result.differences.get(name)
        if not old:
            diff = ""
        elif d is None:
            diff = "0"
        elif d["difference"] is not None:
            diff = f"{d['difference']:+.3e}"
        else:
            diff = "changed"
        lines.append(f"  {name:<40} {value_u(a, (old_u.get(name) or (0, None))[1]):>24} "
                     f"{value_u(b, (new_u.get(name) or (0, None))[1]):>24} {diff:>16} {u_change(name):>18}".rstrip())
    hidden = len(names) - len(shown)
    if hidden:
        lines.append(f"  ({hidden} more figure(s), each and its U identical to the archive; --all lists them)"
                     if old else f"  ({hidden} more figure(s); --all lists them)")
    return "\n".join(lines)


def result_text(result, show_all: bool = False) -> str:
    """The human-readable report of one reprocessed dump."""
    rec = result.record
    wrap = textwrap.TextWrapper(width=110, initial_indent="  ", subsequent_indent="    ")
    from ..report.summary import head_line

    out = [str(result.path),
           f"  {head_line(rec)}; cycle {rec.get('cycle_id')}; dump schema {result.schema_version}, measured by "
           f"sofast-station {result.dump_software_version}"]
    for note in result.notes:
        out.append(wrap.fill(f"note: {note}"))
    if rec.get("verdict") == "fault":
        out.append(wrap.fill(f"the analysis refused the capture: {'; '.join(rec.get('reasons', []))}"))
    out.append(comparison_table(result, show_all))
    out.append(f"  => {result.summary()}")
    return "\n".join(out)


def cmd_reprocess(args) -> int:
    single_thread_blas()
    from ..errors import StationError

    missing = [d for d in args.dumps if not Path(d).is_file()]
    if len(missing) == len(args.dumps):          # nothing to do: say so at once, before numpy is loaded
        from ..errors import DumpError
        word = "" if Path(missing[0]).suffix or "/" in missing[0] else \
            f" (and is not a report: {', '.join(REPORT_WORDS)})"
        raise DumpError(f"{missing[0]} does not exist{word}" if len(missing) == 1 else
                        f"none of the {len(missing)} dumps exists ({missing[0]}, ...)")
    overrides = overrides_from_args(args)
    overrides.check()
    from ..cache import open_cache
    from ..files import station_data_dir
    from ..precompute import keep_rays, prepare_analysis_process, use_disk_cache

    prepare_analysis_process()      # as the station's worker: memory reused, kernels loaded before the first dump
    from .batch import error_result
    from .reprocess import reprocess_dump

    # The station's cache (data_dir/cache of the station file): sensitivities a dump does not carry and the
    # camera's rays, kept across runs; the figures are the same bits without it (sofast_station/cache.py).
    cache = open_cache(station_data_dir(default_config()))
    use_disk_cache(cache)
    failed = differs = 0
    for i, dump in enumerate(args.dumps):
        try:
            res = reprocess_dump(dump, overrides, journal=args.journal, disk_cache=cache)
        except StationError as exc:
            failed += 1
            if args.json:
                print(json.dumps(error_result(dump, exc), ensure_ascii=False), flush=True)
            log.error("%s", exc if str(dump) in str(exc) else f"{dump}: {exc}")
            continue
        except Exception as exc:              # a bug: say so, with its traceback, and go on with the others
            failed += 1
            if args.json:
                print(json.dumps(error_result(dump, exc, internal=True), ensure_ascii=False), flush=True)
            log.exception("%s: internal error while reprocessing", dump)
            continue
        differs += bool(res.differences)
        if args.json:
            print(json.dumps(res.to_json(), ensure_ascii=False, allow_nan=False), flush=True)
        else:
            if i:
                print()
            print(result_text(res, args.all), flush=True)
    keep_rays()
    if failed:
        log.error("%d of %d dump(s) could not be reprocessed", failed, len(args.dumps))
        return EXIT_FAILED
    return EXIT_DIFFERS if args.check and differs else 0


# -- batch ----------------------------------------------------------------------------------------------
class ProgressBar:
    """A small progress bar on a stream (stderr): redrawn in place on a terminal, a line every 10 % or
    30 s otherwise (log files).

    Called as ``bar(done, total, failed, name)``.
    """

    def __init__(self, stream=None, width: int = 30, label: str = "dumps"):
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.width = width
        self.label = label
        self.t0 = time.monotonic()
        self.start_done = None
        self.last_draw = 0.0
        self.last_decile = -1
        self.drawn = False

    def __call__(self, done: int, total: int, failed: int, name: str = "") -> None:
        now = time.monotonic()
        if self.start_done is None:
            self.start_done = done
            self.t0 = now
        finished = done >= total
        if self.tty and not finished and now - self.last_draw < 0.1 and done > self.start_done:
            return
        decile = int(10 * done / max(total, 1))
        if not self.tty and not finished and decile == self.last_decile and now - self.last_draw < 30:
            return
        self.last_draw, self.last_decile = now, decile
        frac = done / max(total, 1)
        fill = int(round(self.width * frac))
        rate = (done - self.start_done) / max(now - self.t0, 1e-9)
        eta = (total - done) / rate if rate > 0 else float("nan")
        eta_text = "--:--" if eta != eta else time.strftime("%H:%M:%S", time.gmtime(eta))
        line = (f"[{'#' * fill}{'.' * (self.width - fill)}] {done}/{total} {self.label} {100 * frac:3.0f}% "
                f"{rate:5.1f}/s eta {eta_text}" + (f", {failed} failed" if failed else ""))
        if self.tty:
            self.stream.write("\r" + line + "\x1b[K")
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.drawn = True

    def close(self) -> None:
        if self.tty and self.drawn:
            self.stream.write("\n")
            self.stream.flush()


def cmd_batch(args) -> int:
    single_thread_blas()
    lower_priority()                    # beside a running station the measuring loop keeps its cores
    from .batch import run_batch

    overrides = overrides_from_args(args)
    bar = None if args.no_progress else ProgressBar()
    try:
        summary = run_batch(args.sources, args.out, overrides, workers=args.workers, scheduler=args.scheduler,
                            journal=args.journal, retry_failed=args.retry_failed, progress=bar)
    except KeyboardInterrupt:
        if bar:
            bar.close()
        log.error("interrupted: the finished results are kept; run the same command again to resume")
        return 130
    if bar:
        bar.close()
    print(summary.text(), flush=True)
    return 1 if summary.failed or summary.unfinished else 0


# -- report ---------------------------------------------------------------------------------------------
#: The reports 'report' makes besides a dump's maps (its first word; quality_reports.REPORTS are the quality
#: engineer's): 'sofast-station --help' lists each (sofast_station/cli.py USERS).
REPORT_WORDS = ("trend", "flux", "spc", "acceptance", "certificate", "diff")


def cmd_report(args) -> int:
    single_thread_blas()
    from ..errors import StationError

    # The priority is lowered (batch work beside the line) once the inputs are checked, on each path below:
    # a refusal (a faulted facet, a serial never measured, a dump that is not there) then answers at once,
    # where at niceness 10 on a busy machine its checks alone waited seconds for a core.
    if args.targets[0] == "trend":
        lower_priority()
        return _cmd_trend(args)
    if args.targets[0] == "flux":
        lower_priority()
        return _cmd_flux(args)
    from .quality_reports import REPORTS, run as run_quality_report
    if args.targets[0] in REPORTS:
        return run_quality_report(args)
    if args.journal or args.results or args.since or args.until or args.config:
        from ..errors import ConfigError
        raise ConfigError("--journal, --results, --config, --from and --to belong to 'report trend'")
    missing = [t for t in args.targets if not Path(t.removeprefix("opencsp:")).exists()]
    if len(missing) == len(args.targets):        # nothing to draw: say so before numpy and h5py are loaded
        from ..errors import DumpError
        word = "" if Path(missing[0]).suffix or "/" in missing[0] else \
            f" (and is not a report: {', '.join(REPORT_WORDS)})"
        raise DumpError(f"{missing[0]} does not exist{word}" if len(missing) == 1 else
                        f"none of the {len(missing)} dumps exists ({missing[0]}, ...)")
    lower_priority()
    from ..report.maps import write_detail_maps, write_slope_error_maps
    from .sources import load_measured

    overrides = overrides_from_args(args)
    overrides.check()
    out = Path(args.out or ".")
    failed = 0
    for dump in args.targets:
        try:
            res = load_measured(dump, overrides)
            for path in write_slope_error_maps(res, out, vmax_mrad=args.vmax, arrow_step_px=args.arrow_step,
                                               cmap=args.cmap, separate=args.separate):
                print(path, flush=True)
            if args.detail != "none":
                print(write_detail_maps(res, out / f"{Path(dump).stem}-detail-{args.detail}.png", args.detail),
                      flush=True)
        except StationError as exc:
            failed += 1
            log.error("%s", exc if str(dump) in str(exc) else f"{dump}: {exc}")
    return EXIT_FAILED if failed else 0


def _flux_table(args) -> dict:
    """The command line's optics options as an [optics] table (only those given)."""
    table = {}
    for opt, key in (("sun", "sun"), ("sigma_mrad", "sigma_mrad"), ("csr", "csr"), ("dni", "dni_w_m2"),
                     ("reflectivity", "reflectivity"), ("incidence", "incidence_angle_deg"),
                     ("slant_range", "slant_range_m"), ("rays_per_pixel", "rays_per_pixel"),
                     ("grid_cells", "grid_cells")):
        if getattr(args, opt) is not None:
            table[key] = getattr(args, opt)
    if args.aperture is not None:
        from ..errors import ConfigError
        if len(args.aperture) == 1:
            table["aperture"] = {"shape": "circle", "radius_m": args.aperture[0]}
        elif len(args.aperture) == 2:
            table["aperture"] = {"shape": "rectangle", "width_m": args.aperture[0], "height_m": args.aperture[1]}
        else:
            raise ConfigError("--aperture takes one value (a circle's radius) or two (a rectangle's width and "
                              f"height), metres; got {len(args.aperture)}")
    return table


#: The sun shape each shape option belongs to.
_SUN_OPTIONS = {"csr": ("--csr", "buie"), "sigma_mrad": ("--sigma-mrad", "gaussian")}


def _check_sun_options(args, table: dict, target) -> None:
    """Refuse a sun-shape option that does not apply to the sun the map is drawn with (``--csr`` without the
    Buie sun was silently ignored)."""
    from ..errors import ConfigError

    sun = table.get("sun", "pillbox")
    for opt, (flag, shape) in _SUN_OPTIONS.items():
        if getattr(args, opt) is not None and sun != shape:
            where = "--sun" if args.sun is not None else f"{target}'s [optics] (or the default)"
            raise ConfigError(f"{flag} applies to the {shape} sun, but the sun here is {sun} (from {where}): add "
                              f"--sun {shape}, or leave {flag} out")


def sun_text(sun: dict) -> str:
    """The sun shape as the console and the map name it, e.g. ``Buie, circumsolar ratio 0.1``."""
    shape = str(sun.get("shape", "?"))
    if shape == "pillbox":
        return f"pillbox, half-angle {sun.get('half_angle_mrad', 4.65):.2f} mrad"
    if shape == "gaussian":
        return f"Gaussian, sigma {sun.get('sigma_mrad'):g} mrad"
    if shape == "buie":
        return f"Buie, circumsolar ratio {sun.get('csr'):g}"
    return shape


def flux_text(name: str, figures: dict, path) -> str:
    """One facet's optical figures, as the console shows them."""
    f = figures
    d = f["design"]
    c = f["conditions"]
    off = f["centroid_offset_mrad"]

    def pm(key, scale=1.0, digits=4, d_=None, sign=""):     # value ± U (k = 2) when the record has U
        src = f if d_ is None else d_
        v = src[key] if d_ is None else src.get(key)
        u = f.get(f"{key}_U") if d_ is None else (f.get("centroid_offset_mrad_U") or {}).get(key)
        return with_u(v, u, decimals=digits, scale=scale, sign=sign == "+")

    r90 = "-" if f["spot_radius_m"] is None else (f"{pm('spot_radius_m', 1000.0, 2)} mm "
                                                  f"({pm('spot_radius_mrad', 1.0, 3)} mrad)")
    d90 = "-" if d["spot_radius_m"] is None else f"{1000 * d['spot_radius_m']:.2f} mm"
    return (f"{name}: sun {sun_text(c.get('sun') or {})}, DNI {c.get('dni_w_m2', 0):g} W/m², target at "
            f"{c['slant_range_m']:.3f} m, aperture {aperture_text(c['aperture'])}\n"
            f"  intercept {pm('intercept')} (design {d['intercept']:.4f}), power / design's "
            f"{pm('power_ratio_vs_design')}\n"
            f"  90 % spot radius {r90}, design {d90}; analytic (patent model) {1000 * f['analytic_spot_radius_m']:.2f} "
            f"mm, design {1000 * d['analytic_spot_radius_m']:.2f} mm\n"
            f"  centroid offset x {pm('x', 1.0, 3, off, '+')} y {pm('y', 1.0, 3, off, '+')} mrad "
            f"(magnitude {pm('magnitude', 1.0, 3, off)})\n"
            f"  {path}")


def _cmd_flux(args) -> int:
    import tomllib

    from ..errors import ConfigError, StationError
    from ..report.flux import write_flux_map
    from .sources import load_measured
    from ..result.optical_figures import analysis_optics, optics_for

    targets = args.targets[1:] + ([f"opencsp:{args.opencsp}"] if args.opencsp else [])
    if not targets:
        raise ConfigError("'report flux' needs dump(s) or opencsp:DIR (or --opencsp DIR)")
    cli_table = _flux_table(args)
    out = Path(args.out or ".")
    overrides = overrides_from_args(args)
    overrides.check()
    failed = 0
    for target in targets:
        try:
            res = load_measured(target, overrides, focal_length_m=args.opencsp_focal_length)
            table = dict(cli_table)
            if res.kind == "dump":        # the dump's own [optics] (and its recipe's), under the options given
                from ..archive.dumps import read_dump
                text = read_dump(target, load_frames=False, require_result=False).station_toml
                raw = tomllib.loads(text) if text.strip() else {}
                recipe = res.record.get("recipe", "default")
                over = raw.get("recipes", {}).get(recipe, {}) if recipe != "default" else {}
                table = {**raw.get("optics", {}), **(over.get("optics", {}) if isinstance(over, dict) else {}),
                         **cli_table, "enabled": True}
            _check_sun_options(args, table, target)
            settings = optics_for({"optics": table}, f"{target} ([optics] and the command line)")
            opt = analysis_optics(res.analysis, res.design, settings)
            name = str(res.record.get("serial", "")) or Path(target).stem
            stem = f"opencsp-{name}" if res.kind == "opencsp" else Path(target).name.removesuffix(".h5")
            stem = stem.replace(" ", "_")
            path = out if out.suffix.lower() == ".png" and len(targets) == 1 else out / f"flux-{stem}.png"
            title = (f"OpenCSP measurement {name} ({res.record.get('time', '')}), design f "
                     f"{res.design.focal_length_m:g} m" if res.kind == "opencsp"
                     else f"{name} ({res.design.name}), {res.record.get('time', '')}")
            path = write_flux_map(opt, path, title=title)
            print(flux_text(name, opt.figures, path), flush=True)
        except StationError as exc:
            failed += 1
            log.error("%s", exc if str(target) in str(exc) else f"{target}: {exc}")
    return EXIT_FAILED if failed else 0


def _cmd_trend(args) -> int:
    from ..errors import ConfigError
    from ..report.trend import default_trend_name, trend_records_from_journal, trend_records_from_results, write_trend

    if len(args.targets) > 1:
        raise ConfigError("'report trend' takes no dumps: use --journal PATH or --results DIR")
    from ..times import check_period, parse_bound
    args.since, args.until = parse_bound(args.since, "--from"), parse_bound(args.until, "--to")
    check_period(args.since, args.until)
    if args.journal and args.results:
        raise ConfigError("'report trend' takes one of --journal PATH and --results DIR, not both")
    if not args.journal and not args.results:
        from ..config import load_config

        config = load_config(args.config or default_config(), use_camera_record=False)  # no camera needed
        args.journal = config.data_dir / "journal.sqlite3"
        if not args.journal.exists():
            raise ConfigError(f"no journal at {args.journal} (the data_dir of {config.path}): this station has "
                              "not measured anything yet; give --journal PATH, --results DIR or --config FILE")
    if args.journal:
        records = trend_records_from_journal(args.journal, args.since, args.until)
        source = f"journal {args.journal}"
    else:
        records = trend_records_from_results(args.results, args.since, args.until)
        source = f"batch results {args.results}"
    out = Path(args.out) if args.out else Path(".")
    if out.suffix.lower() != ".png":
        out = out / default_trend_name(args.since, args.until)
    period = f"from {args.since or 'the start'} to {args.until or 'now'}"
    print(write_trend(records, out, title=f"{source}, {period}"), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run one re-analysis command (as ``sofast-station`` would), for tests and ``python -m``."""
    return run(build_parser().parse_args(argv))


def cmd_export(args) -> int:
    """``export surface DUMP... --format F``: one file per dump, named after its serial."""
    from ..files import safe_name
    from ..errors import ReportError, StationError
    from ..interop.export import SUFFIX, export_surface, surface_points
    from .reprocess import reprocess_dump

    out = Path(args.out)
    single = len(args.dumps) == 1 and out.suffix.lower() == SUFFIX[args.format]
    failed = 0
    for dump in args.dumps:
        try:
            m = reprocess_dump(dump, None)
            if m.analysis is None:
                raise ReportError(f"cannot export {dump}: the analysis refused the capture "
                                  f"({'; '.join(m.record.get('reasons', []))})")
            points = surface_points(m.analysis, m.record, m.design)
            path = out if single else out / f"surface-{safe_name(points.serial, 64)}{SUFFIX[args.format]}"
            print(export_surface(points, args.format, path), flush=True)
        except StationError as exc:
            failed += 1
            log.error("%s", exc if str(dump) in str(exc) else f"{dump}: {exc}")
    return 2 if failed else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
