"""Soak: the production loop for many cycles with injected faults; memory and open files of every process.

    .venv/bin/python benchmarks/soak.py                      # 500 cycles, default full-resolution station
    .venv/bin/python benchmarks/soak.py --cycles 3000 --small  # a long run at 400 x 300
    .venv/bin/python benchmarks/soak.py --quick              # the test suite's smoke run

Runs the real station (simulated devices, analysis worker and its standby, archiver process) on a fresh
data folder. Every ``--fault-every``-th facet gets an injected fault, in turn: a dark capture, a misplaced
facet, a camera timeout, and an analysis that finishes after the deadline (a late result).
``--hung-percent P`` also makes P % of the other facets (drawn with a fixed seed) hang their analysis for
good: each must cost the line that one facet (the deadline), the standby measuring the next; compare the
cycles per minute with a run without (``--no-standby`` shows the line without a standby). ``--burners N``
runs N processes spinning at the normal priority beside the line (a machine busy with other work); the
journal then says how many facets past the deadline kept their late result. Every
``--sample-every`` cycles it records the resident memory (VmRSS) and open file descriptors of the
station, the analysis worker, its standby and the archiver, and reports for each the growth per 100 cycles
(least squares) twice: after a warm-up (``--warmup`` cycles, default 20 % of the run, at least 50, so that
start-up allocations, first-use caches and the allocator settling do not count) and over the whole run;
the growth of its high-water mark after the warm-up (robust to a process that swings between two levels
within a cycle, as the station does by a capture's frames);
and, since a worker that times out is replaced, the growth of each process over its own life.
``--trace N`` also follows the station process's Python allocations with tracemalloc: a snapshot at the
end of the warm-up, then every N cycles the sites that grew most since it; the archiver and the analysis
worker log theirs every ``--trace-s`` seconds (``SOFAST_TRACEMALLOC_S``, sofast_station/station/memtrace.py).
Slower; for finding a leak, not for the RSS figures.

After the run it checks the archive: one journal row per cycle (no id twice), every row in exactly one
workbook row, every requested dump written and readable with its frames, no temporary file left.
Nothing is asserted; the figures are printed (and written as JSON with ``--json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FAULT_CYCLE = ("dark", "misplaced", "camera-timeout", "slow-analysis")

#: --small: the tests' 400 x 300 station (fixtures/stations/small_dish.toml.in), its paths under {root}.
SMALL = (ROOT / "fixtures/stations/small_dish.toml.in").read_text().format(
    name="Soak station (400 x 300)", data_dir_line="", facet="{root}/fixtures/facets/dish_5m33.toml", analysis="",
    radiometric="{root}/calibration/simulated_radiometric.json", twist="0.1")


def proc_sample(pid: int | None) -> tuple[float, int] | None:
    """(VmRSS in MB, open file descriptors) of a process, None when it is gone."""
    if not pid:
        return None
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        rss_kb = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:"))
        return rss_kb / 1024.0, len(os.listdir(f"/proc/{pid}/fd"))
    except (OSError, StopIteration):
        return None


def slope_per_100(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of ys over xs, times 100 (MB per 100 cycles)."""
    n = len(xs)
    if n < 2:
        return float("nan")
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    return 100.0 * sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sxx if sxx else float("nan")


def high_water_per_100(xs: list[float], ys: list[float]) -> float:
    """Growth of the high-water mark, MB per 100 cycles: the largest sample of the second half of the
    series less that of the first half, over the cycles between the halves' middles.

    A process whose resident memory swings between two levels as it samples a cycle at different stages
    (the station holds a capture's frames, 40 MB at full resolution, for part of each cycle) gives a
    least-squares slope that is only where the swings happened to fall; a leak raises the high-water mark
    as well as the mean."""
    n = len(xs)
    if n < 4:
        return float("nan")
    h = n // 2
    span = (xs[h + (n - h) // 2] - xs[h // 2]) or float("nan")
    return 100.0 * (max(ys[h:]) - max(ys[:h])) / span


def archive_checks(data: Path) -> dict:
    """What a soak or kill campaign left in *data*: journal and workbook rows (counts, ids unique, the same
    ids in both), requested dumps that do not read back with their frames ("cycle: why"), temporary files
    and orphan spools left behind."""
    from sofast_station.archive import Journal, read_dump, read_workbook

    journal = Journal(data / "journal.sqlite3")
    try:
        rows = journal.rows()
    finally:
        journal.close()
    ids = [r.cycle_id for r in rows]
    book_ids = [r["cycle_id"] for b in sorted((data / "archive").glob("*.xlsx")) for r in read_workbook(b)]
    bad_dumps = []
    for r in rows:
        if r.dump_requested:
            try:
                if read_dump(r.dump_path, load_frames=True).cycle_id != r.cycle_id:
                    bad_dumps.append(f"{r.cycle_id}: wrong cycle")
            except Exception as exc:  # every failure is reported
                bad_dumps.append(f"{r.cycle_id}: {type(exc).__name__}: {exc}")
    return {"journal_rows": len(rows), "journal_unique": len(set(ids)) == len(ids),
            "workbook_rows": len(book_ids), "workbook_unique": len(set(book_ids)) == len(book_ids),
            "workbook_equals_journal": sorted(book_ids) == sorted(ids),
            "dumps_requested": sum(r.dump_requested for r in rows), "dumps_bad": bad_dumps,
            "temp_files": [str(p) for p in data.rglob("*.tmp")],
            "orphan_spools": [str(p) for p in (data / "spool").glob("*.npz")] if (data / "spool").exists() else []}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "station.toml"), help="station file (default: full resolution)")
    p.add_argument("--small", action="store_true", help="a 400 x 300 station instead of --config")
    p.add_argument("--cycles", type=int, default=500, help="facets to measure (default 500)")
    p.add_argument("--fault-every", type=int, default=10, help="every n-th facet gets a fault (default 10)")
    p.add_argument("--sample-every", type=int, default=10, help="memory sample every n cycles (default 10)")
    p.add_argument("--deadline", type=float, default=10.0, help="[run] deadline_s (default 10)")
    p.add_argument("--data", default=None, help="data folder (default: a temporary one, removed)")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")
    p.add_argument("--minutes", type=float, default=None,
                   help="stop after this long (the facet in progress is finished) and report what was done")
    p.add_argument("--warmup", type=int, default=None,
                   help="cycles not counted in the growth after warm-up (default: 20 %% of the run, at least 50)")
    p.add_argument("--trace", type=int, default=0, metavar="N",
                   help="tracemalloc in the station process: the top growth sites every N cycles after warm-up")
    p.add_argument("--trace-s", type=float, default=300.0,
                   help="with --trace: the archiver's and the worker's growth sites every this many seconds")
    p.add_argument("--no-truth", action="store_true",
                   help="skip the twin's ground truth per facet (a simulation extra a real station does not "
                        "compute; seconds per facet at full resolution)")
    p.add_argument("--hung-percent", type=float, default=0.0, metavar="P",
                   help="this percentage of the facets without another fault hang their analysis for good")
    p.add_argument("--no-standby", action="store_true", help="[run] standby_worker = false")
    p.add_argument("--seed", type=int, default=28, help="the draw of the hung facets (default 28)")
    p.add_argument("--burners", type=int, default=0,
                   help="processes spinning at the normal priority beside the run (a machine busy with other "
                        "work, as 'yes > /dev/null' makes it)")
    p.add_argument("--quick", action="store_true", help="12 cycles at 400 x 300 (the test suite's smoke run)")
    args = p.parse_args(argv)
    if args.quick:
        args.small, args.cycles, args.fault_every, args.sample_every, args.deadline = True, 12, 4, 2, 10.0
    warmup = args.warmup if args.warmup is not None else min(max(50, args.cycles // 5), args.cycles // 2)

    import logging
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(message)s", datefmt="%H:%M:%S")
    from sofast_station.config import load_config
    from sofast_station.station.service import Service
    from sofast_station.result.shift import ShiftTally

    with tempfile.TemporaryDirectory() as tmp:
        config_path = Path(args.config)
        if args.small:
            config_path = Path(tmp) / "station.toml"
            config_path.write_text(SMALL.format(root=ROOT))
        data = Path(args.data) if args.data else Path(tmp) / "data"
        cfg = load_config(config_path)
        faults = {f"SIM-{i:04d}": FAULT_CYCLE[(i // args.fault_every - 1) % len(FAULT_CYCLE)]
                  for i in range(args.fault_every, args.cycles + 1, args.fault_every)} if args.fault_every else {}
        if args.hung_percent > 0:
            import random
            free = [f"SIM-{i:04d}" for i in range(2, args.cycles + 1) if f"SIM-{i:04d}" not in faults]
            hung = random.Random(args.seed).sample(free, round(args.cycles * args.hung_percent / 100.0))
            faults.update({serial: "hung-analysis" for serial in hung})
        raw = dict(cfg.raw, run={"deadline_s": args.deadline, "late_grace_s": 10.0, "dump_every_n": 25,
                                 "standby_worker": not args.no_standby},
                   archive={"workbook_interval_s": 10.0})
        cfg = dataclasses.replace(cfg, data_dir=data, raw=raw,
                                  simulation={**cfg.simulation, "faults": faults, "slow_s": args.deadline + 2.0})
        cam = cfg.geometry.camera
        kinds = Counter(faults.values())
        print(f"soak: {cfg.name}, camera {cam.width_px} x {cam.height_px}, {args.cycles} cycles, "
              f"{len(faults)} injected faults ({', '.join(f'{n} {k}' for k, n in sorted(kinds.items()))}), "
              f"deadline {args.deadline:g} s, standby worker {'off' if args.no_standby else 'on'}, data in {data}; "
              f"load average {os.getloadavg()[0]:.1f} at the start", flush=True)
        if args.trace:
            from sofast_station.station.memtrace import ENV
            os.environ[ENV] = str(args.trace_s)           # the archiver and the worker inherit it
        t0 = time.perf_counter()
        service = Service(cfg, simulated_facets=args.cycles, console=lambda line: None)
        print(f"station started in {time.perf_counter() - t0:.1f} s", flush=True)
        if args.no_truth:
            service.runner.station.truth = lambda *a, **k: None   # what a real station knows: no truth
        samples: dict[str, list[tuple[int, float, int]]] = {"station": [], "worker": [], "standby": [],
                                                             "archiver": []}
        by_pid: dict[tuple[str, int], list[tuple[int, float]]] = {}
        answers: Counter = Counter()
        late = [0]
        pids: dict[str, set] = {"worker": set(), "standby": set(), "archiver": set()}

        def sample(n: int) -> None:
            worker = (service.runner.worker.pids() or [None])[0]
            standby = (service.runner.worker.standby_pids() or [None])[0]
            archiver = service.archiver_process.pid
            for name, pid in (("worker", worker), ("standby", standby), ("archiver", archiver)):
                pids[name].add(pid)
            for name, pid in (("station", os.getpid()), ("worker", worker), ("standby", standby),
                              ("archiver", archiver)):
                s = proc_sample(pid)
                if s is not None:
                    samples[name].append((n, *s))
                    by_pid.setdefault((name, pid), []).append((n, s[0]))

        traced: dict = {}

        def trace(n: int) -> None:
            import tracemalloc
            if n == warmup:
                tracemalloc.start(8)
                traced["base"] = tracemalloc.take_snapshot()
                print(f"  tracemalloc: baseline at cycle {n}", flush=True)
            elif "base" in traced and (n - warmup) % args.trace == 0:
                from sofast_station.station.memtrace import growth_lines
                lines = growth_lines(tracemalloc.take_snapshot(), traced["base"], strip=str(ROOT) + "/")
                print(f"  station memory trace at cycle {n} (baseline: cycle {warmup}): {lines[0]}", flush=True)
                for line in lines[1:]:
                    print(f"    {line}", flush=True)

        tally = ShiftTally()                   # what `sofast-station run` keeps for its summary

        fault_reasons: list = []

        def on_outcome(outcome) -> None:
            tally.add(outcome.record)
            answers[outcome.answer] += 1
            if outcome.answer == "fault":
                fault_reasons.append(outcome.record.get("reasons"))
            late[0] += bool(outcome.record.get("late"))
            n = sum(answers.values())
            if n % args.sample_every == 0:
                sample(n)
            if args.trace and n >= warmup:
                trace(n)
            if n % max(args.cycles // 10, 1) == 0:
                rss = ", ".join(f"{k} {v[-1][1]:.0f} MB" for k, v in samples.items() if v)
                print(f"  {n:5d} cycles, {time.perf_counter() - t0:7.0f} s: {rss}", flush=True)

        import signal
        import threading
        for sig in (signal.SIGINT, signal.SIGTERM):     # stop after the facet in progress, then report
            signal.signal(sig, lambda *_: service.runner.stop())
        if args.minutes:
            timer = threading.Timer(60.0 * args.minutes, service.runner.stop)
            timer.daemon = True
            timer.start()
        import subprocess
        burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.burners)]
        t_run = time.perf_counter()
        try:
            service.runner.run(on_outcome=on_outcome)
        finally:
            t_close = time.perf_counter()
            service.close()
            for b in burners:
                b.kill()
                b.wait()
        run_s, close_s = t_close - t_run, time.perf_counter() - t_close
        n = sum(answers.values())
        per_minute = 60.0 * n / run_s if run_s > 0 else float("nan")
        by_kind = Counter(str((o or [""])[0]).split(":")[0] for o in fault_reasons)
        print(f"{n} cycles in {run_s:.0f} s ({run_s / max(n, 1):.2f} s each, {per_minute:.2f} cycles per minute), "
              f"shutdown {close_s:.1f} s; answers: " + ", ".join(f"{v} {k}" for k, v in sorted(answers.items()))
              + f" (faults: {', '.join(f'{v} {k}' for k, v in sorted(by_kind.items()))}); {late[0]} late results "
              f"kept; the standby took over {service.runner.worker.takeovers} times ({service.runner.worker.reruns} of "
              f"them to rerun a hung analysis); load average "
              f"{os.getloadavg()[0]:.1f} at the end")

        figures: dict = {"cycles": n, "camera": [cam.width_px, cam.height_px], "answers": dict(answers),
                         "deadline_s": args.deadline, "truth": not args.no_truth, "hung_percent": args.hung_percent,
                         "standby": not args.no_standby, "cycles_per_minute": per_minute,
                         "faults_by_kind": dict(by_kind), "takeovers": service.runner.worker.takeovers,
                         "reruns": service.runner.worker.reruns,
                         "late": late[0], "run_s": run_s, "warmup_cycles": warmup, "processes": {},
                         "load_average": os.getloadavg()}
        print(f"growth per 100 cycles (least squares): after the warm-up of {warmup} cycles, and over the whole "
              "run; and of the high-water mark after the warm-up (high-water)")
        print("           RSS (MB):                          growth/100 cycles (MB):")
        print("process       first  at warm-up   last    max  after warm-up  overall  high-water"
              "   open files first  last  (pids)")
        for name, rows in samples.items():
            if not rows:
                continue
            later = [r for r in rows if r[0] >= warmup]
            growth = slope_per_100([r[0] for r in later], [r[1] for r in later])
            overall = slope_per_100([r[0] for r in rows], [r[1] for r in rows])
            fd_growth = slope_per_100([r[0] for r in later], [r[2] for r in later])
            high = high_water_per_100([r[0] for r in later], [r[1] for r in later])
            at_warmup = later[0][1] if later else float("nan")
            figures["processes"][name] = {"rss_first_mb": rows[0][1], "rss_at_warmup_mb": at_warmup,
                                          "rss_last_mb": rows[-1][1], "rss_max_mb": max(r[1] for r in rows),
                                          "rss_growth_mb_per_100_after_warmup": growth,
                                          "rss_growth_mb_per_100_overall": overall,
                                          "rss_high_water_growth_mb_per_100_after_warmup": high,
                                          "rss_samples": [[r[0], r[1]] for r in rows], "fds_first": rows[0][2],
                                          "fds_last": rows[-1][2], "fds_max": max(r[2] for r in rows),
                                          "fds_growth_per_100_after_warmup": fd_growth, "samples": len(rows)}
            who = pids.get(name, {os.getpid()}) - {None}
            print(f"{name:<10} {rows[0][1]:8.1f} {at_warmup:10.1f} {rows[-1][1]:7.1f} {max(r[1] for r in rows):6.1f}"
                  f" {growth:+14.2f} {overall:+8.2f} {high:+11.2f} {rows[0][2]:19d} {rows[-1][2]:5d}  "
                  f"({len(who)} process{'es' if len(who) > 1 else ''})")
        # each process over its own life after the warm-up (a worker that timed out was replaced, so the
        # worker's row above mixes processes), for those sampled at least 10 times
        own = []
        for (name, pid), rows in sorted(by_pid.items(), key=lambda kv: kv[1][0][0]):
            later = [r for r in rows if r[0] >= warmup]
            if len(later) >= 10:
                g = slope_per_100([r[0] for r in later], [r[1] for r in later])
                own.append({"process": name, "pid": pid, "cycles": [later[0][0], later[-1][0]], "samples": len(later),
                            "rss_first_mb": later[0][1], "rss_last_mb": later[-1][1], "growth_mb_per_100": g})
        figures["each_process"] = own
        if own:
            print("each process after the warm-up, over its own life (>= 10 samples): "
                  + "; ".join(f"{o['process']} {o['pid']} cycles {o['cycles'][0]}-{o['cycles'][1]} "
                              f"{o['rss_first_mb']:.0f}->{o['rss_last_mb']:.0f} MB {o['growth_mb_per_100']:+.2f}/100"
                              for o in own))

        from sofast_station.archive import Journal
        with Journal(data / "journal.sqlite3") as journal:
            past = [r.record for r in journal.rows() if r.record.get("late")]
        kept = sum("late_verdict" in rec for rec in past)
        figures["past_deadline"], figures["late_kept"] = len(past), kept
        print(f"past the deadline: {len(past)} facets, {kept} of them with their late result kept (figures "
              f"journaled), {len(past) - kept} without (no result within the late grace); {args.burners} spinning "
              "process(es) beside the run")
        c = archive_checks(data)
        rows, book_ids, requested = c["journal_rows"], c["workbook_rows"], c["dumps_requested"]
        temps, spools = c["temp_files"], c["orphan_spools"]
        checks = {"journal_rows": rows, "journal_ids_unique": c["journal_unique"],
                  "workbook_rows": book_ids, "workbook_ids_unique": c["workbook_unique"],
                  "workbook_equals_journal": c["workbook_equals_journal"], "dumps_requested": requested,
                  "dumps_valid": requested - len(c["dumps_bad"]), "dump_errors": c["dumps_bad"][:10],
                  "temp_files_left": temps, "spools_left": spools}
        figures["checks"] = checks
        print(f"journal: {rows} rows for {n} cycles, ids unique: {checks['journal_ids_unique']}; workbooks: "
              f"{book_ids} rows, unique: {checks['workbook_ids_unique']}, same ids as the journal: "
              f"{checks['workbook_equals_journal']}")
        print(f"dumps: {requested} requested, {checks['dumps_valid']} valid (read back with frames); "
              f"temporary files left: {len(temps)}; spools left: {len(spools)}")
        if args.json:
            Path(args.json).write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
