"""Benchmark: the whole commands a user runs, each as a fresh process, as the user waits for them.

    .venv/bin/python benchmarks/commands.py                  # every command, 5 counted runs each
    .venv/bin/python benchmarks/commands.py --only reprocess --only import-opencsp
    .venv/bin/python benchmarks/commands.py --quick          # small station, 1 run, no 8x set (the test suite)

What a user waits for is the whole command: the interpreter's start, the imports, reading the input, the
analysis, the uncertainty, writing the output. ``benchmarks/analysis.py`` times the analysis inside a
running process; this times ``sofast-station ...`` from outside, one fresh process per run, with the
operating system's own accounting of each finished child (``os.wait4``: user and system CPU seconds, and
the peak resident memory of the process).

Commands: ``--help``; a usage error (an unknown option); a mistake found by the command (a missing station
file); ``inspect`` on the simulated station; ``reprocess DUMP`` of one full-resolution data dump, with the
station's cache on disk warm (the camera's rays and any sensitivities kept by an earlier run: what a
process engineer's second look costs) and cold (``data_dir/cache`` deleted before every run: the first
look), as dumped and with a design override (``--focal-length 5.4``: the dump's own sensitivities do not
apply, so they are computed cold and read from the cache warm); ``import-opencsp --robust`` of OpenCSP's
measured facet at its native 203 x 154 px and upsampled 8x (1624 x 1232 px, as ``benchmarks/analysis.py``
builds it), warm and cold; ``report DUMP`` (the slope-error maps of the dump); ``report spc`` (control
charts of a journal the setup fills with ``run`` on the small test station: the charts read records, not
images).

Setup (not timed): a temporary data_dir (``SOFAST_DATA_DIR``) holding the dump, the journal of
``run --facets N`` on the same station and the upsampled OpenCSP set. Every command runs once first,
uncounted (the disk cache and the operating system's file cache filled), then ``--runs`` times; the
printed table gives the median and the range of wall time, the median CPU time (user + system) and the
median peak memory (the benchmark's own process stays small, about 20 MB, because Linux keeps a
process's peak across ``exec``: that is the floor of the column), and the machine's load average
(``/proc/loadavg``) before and after, since the machine may be shared. The numbers are printed, never asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))              # run from a checkout, installed or not
sys.path.insert(0, str(ROOT / "benchmarks"))

OPENCSP = ROOT / "fixtures/opencsp/test_data"


@dataclass
class Command:
    """One row of the table: *argv* after ``sofast-station``; *cold*: delete data_dir/cache before each run."""

    name: str
    group: str
    argv: list
    cold: bool = False
    expect: int = 0
    runs: list = field(default_factory=list)


@dataclass(frozen=True)
class Run:
    wall_s: float
    cpu_s: float
    peak_mb: float
    code: int


def load() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def run_process(cmd: list, env: dict, cwd: Path, log: Path) -> Run:
    """The command *cmd* as a child process (its output appended to *log*); its wall time, and its CPU time
    and peak memory from the operating system's accounting of the finished child (``os.wait4``)."""
    with open(log, "ab") as out:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=out, env=env, cwd=cwd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
    return Run(wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024, os.waitstatus_to_exitcode(status))


def run_once(argv: list, env: dict, cwd: Path, log: Path) -> Run:
    """``sofast-station *argv*`` in a fresh interpreter; its wall time, CPU time and peak memory."""
    return run_process([sys.executable, "-m", "sofast_station", *argv], env, cwd, log)


def small_station(path: Path) -> str:
    """The small simulated dish station of the tests (400 x 300 px) written to *path*; its path."""
    path.write_text((ROOT / "fixtures/stations/small_dish.toml.in").read_text().format(
        name="Small simulated dish station (benchmark)", data_dir_line="", analysis="", twist="0.1",
        facet=ROOT / "fixtures/facets/dish_5m33.toml", radiometric=ROOT / "calibration/simulated_radiometric.json"))
    return str(path)


def setup(tmp: Path, config: str, facets: int, scale: int | None, env: dict) -> dict:
    """The dump, the journal (*facets* > 0) and the OpenCSP sets the commands read (printed as they are made)."""
    import analysis as bench_analysis

    t = time.perf_counter()
    spec = bench_analysis.prepare_dump(config, tmp, ["plain"], optics=True)     # as a dump from the line
    print(f"setup: {spec['what']} ({time.perf_counter() - t:.1f} s)", flush=True)
    if facets > 0:
        t = time.perf_counter()
        # The journal's records come from the small station (the same facet design; control charts read
        # records, not images, so the camera's size does not matter to them and 400 x 300 px is quick).
        small = small_station(tmp / "small.toml")
        proc = subprocess.run([sys.executable, "-m", "sofast_station", "run", "--config", small, "--facets",
                               str(facets)], capture_output=True, text=True, env=env, cwd=tmp)
        if proc.returncode != 0:
            raise SystemExit(f"setup: 'run --facets {facets}' failed:\n{proc.stderr[-2000:]}")
        print(f"setup: journal of {facets} simulated facets ({time.perf_counter() - t:.1f} s)", flush=True)
    sets = {"native": OPENCSP}
    if scale:
        t = time.perf_counter()
        sets[f"{scale}x"] = tmp / f"opencsp-{scale}x"
        bench_analysis.upsample_opencsp(OPENCSP, sets[f"{scale}x"], scale)
        print(f"setup: OpenCSP's facet upsampled {scale}x ({time.perf_counter() - t:.1f} s)", flush=True)
    return {"dump": spec["dump"], "opencsp": sets, "journal_station": str(tmp / "small.toml")}


def commands(config: str, inputs: dict) -> list[Command]:
    rows = [Command("sofast-station --help", "help", ["--help"]),
            Command("sofast-station inspect --bogus (usage error)", "usage error", ["inspect", "--bogus"], expect=2),
            Command("sofast-station inspect --config nowhere.toml", "usage error",
                    ["inspect", "--config", "nowhere.toml"], expect=2),
            Command("sofast-station inspect", "inspect", ["inspect", "--config", config]),
            Command("sofast-station reprocess DUMP (cache warm)", "reprocess", ["reprocess", inputs["dump"]]),
            Command("sofast-station reprocess DUMP (cache cold)", "reprocess", ["reprocess", inputs["dump"]],
                    cold=True),
            # An override the dump's sensitivities were not computed for: the uncertainty's sensitivities are
            # computed from the dump (cold), or read from the cache a previous run filled (warm).
            Command("sofast-station reprocess DUMP --focal-length 5.4 (cache warm)", "reprocess",
                    ["reprocess", inputs["dump"], "--focal-length", "5.4"]),
            Command("sofast-station reprocess DUMP --focal-length 5.4 (cache cold)", "reprocess",
                    ["reprocess", inputs["dump"], "--focal-length", "5.4"], cold=True)]
    for size, folder in inputs["opencsp"].items():
        argv = ["import-opencsp", "--robust", "--test-data", str(folder)]
        rows += [Command(f"sofast-station import-opencsp --robust, {size} (cache warm)", "import-opencsp", argv),
                 Command(f"sofast-station import-opencsp --robust, {size} (cache cold)", "import-opencsp", argv,
                         cold=True)]
    rows += [Command("sofast-station report DUMP (slope-error maps)", "report", ["report", inputs["dump"], "--out",
                                                                                  "maps"]),
             Command("sofast-station report spc", "report", ["report", "spc", "--baseline-n", "10", "--config",
                                                             inputs["journal_station"], "--out", "spc"])]
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=None,
                   help="the station (default: station.toml; with --quick the small test station)")
    p.add_argument("--runs", type=int, default=5, help="counted runs of each command (median quoted)")
    p.add_argument("--facets", type=int, default=12,
                   help="facets 'run' measures on the small station for the journal 'report spc' reads (control "
                        "limits need 10; measured only for 'report')")
    p.add_argument("--opencsp-scale", type=int, default=8, help="the upsampled OpenCSP set (0: native only)")
    p.add_argument("--only", action="append", default=None, metavar="GROUP",
                   help="only these groups (help, 'usage error', inspect, reprocess, import-opencsp, report); "
                        "repeatable")
    p.add_argument("--quick", action="store_true", help="small test station, 1 run, native OpenCSP only")
    p.add_argument("--setup-into", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.setup_into:                     # the child that builds the inputs: their paths as JSON, last line
        with redirect_stdout(sys.stderr):
            inputs = setup(Path(args.setup_into), args.config, args.facets, args.opencsp_scale or None,
                           dict(os.environ))
        print(json.dumps({**inputs, "opencsp": {k: str(v) for k, v in inputs["opencsp"].items()}}))
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="sofast-commands-"))
    keep = False
    try:
        config = args.config
        if args.quick:
            args.runs, args.opencsp_scale, args.facets = 1, 0, 10
            if config is None:
                config = small_station(tmp / "small.toml")
        config = str(Path(config or ROOT / "station.toml").resolve())
        data = tmp / "data"
        # The station's data (dumps, journal, cache) in the temporary folder; a cycle deadline no loaded
        # machine misses (the journal is for the charts, not a cycle-time test).
        env = {**os.environ, "SOFAST_DATA_DIR": str(data), "SOFAST_DEFAULT_DEADLINE_S": "120"}
        print(f"commands of sofast-station, each a fresh process; station {config}; {args.runs} counted run(s) "
              f"after 1 uncounted; python {sys.version.split()[0]}; {os.cpu_count()} CPU(s)", flush=True)
        print(f"load average before setup: {load()}", flush=True)
        # In a process of its own: Linux keeps a process's peak memory across exec, so a child started by a
        # parent that had loaded numpy and built the dump would report the parent's peak as its own.
        facets = args.facets if not args.only or "report" in args.only else 0
        proc = subprocess.run([sys.executable, __file__, "--setup-into", str(tmp), "--config", config, "--facets",
                               str(facets), "--opencsp-scale", str(args.opencsp_scale)], env=env,
                              stdout=subprocess.PIPE, text=True)
        if proc.returncode != 0:
            raise SystemExit("setup failed")
        inputs = json.loads(proc.stdout.strip().splitlines()[-1])
        rows = [c for c in commands(config, inputs) if not args.only or c.group in args.only]
        print(f"load average before the commands: {load()}", flush=True)
        log = tmp / "commands.log"
        for c in rows:
            for i in range(args.runs + 1):
                if c.cold:
                    shutil.rmtree(data / "cache", ignore_errors=True)
                r = run_once(c.argv, env, tmp, log)
                if i:
                    c.runs.append(r)
            codes = sorted({r.code for r in c.runs})
            print(f"  {c.name:<58} wall {statistics.median(r.wall_s for r in c.runs):6.2f} s "
                  f"({min(r.wall_s for r in c.runs):.2f}-{max(r.wall_s for r in c.runs):.2f})  "
                  f"cpu {statistics.median(r.cpu_s for r in c.runs):6.2f} s  "
                  f"peak {statistics.median(r.peak_mb for r in c.runs):6.0f} MB  exit {','.join(map(str, codes))}",
                  flush=True)
        print(f"load average after: {load()}")
        print()
        print("| command | wall s, median (min-max) | CPU s | peak MB |")
        print("| --- | --- | --- | --- |")
        for c in rows:
            w = [r.wall_s for r in c.runs]
            print(f"| `{c.name.removeprefix('sofast-station ')}` | {statistics.median(w):.2f} "
                  f"({min(w):.2f}-{max(w):.2f}) | {statistics.median(r.cpu_s for r in c.runs):.2f} | "
                  f"{statistics.median(r.peak_mb for r in c.runs):.0f} |")
        bad = [c.name for c in rows if any(r.code != c.expect for r in c.runs)]
        if bad:
            keep = True
            print(f"\nfailed (an exit status other than expected): {', '.join(bad)}; their output: {log}",
                  file=sys.stderr)
            return 1
        return 0
    finally:
        if not keep:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
