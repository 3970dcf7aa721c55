"""The archiver's memory and save time as a day's workbook part fills: the workbook writer alone.

    .venv/bin/python benchmarks/archiver_memory.py                    # 3000 rows, 25 per save, 1000 per part
    .venv/bin/python benchmarks/archiver_memory.py --rows 600 --per-save 10

One process does what the archiver process does with workbook rows: the station's part (journal appends,
here through a second connection) and the archiver's (:meth:`Archiver.run_once`, workbook only: write the
pending rows into the day's part, give the memory back). Rows are full-width records of the
full-resolution simulated station (``tests/archive/full_record.json``: 236 workbook columns, the
uncertainties included), ``--per-save`` of them per pass, as the archiver gathers the facets of its
``workbook_interval_s``. Every ``--sample-every`` rows it records the process's resident memory (VmRSS)
and prints the growth per 100 rows (least squares) after ``--warmup`` rows and over the whole run, and
the time a pass took, wall clock and this process's CPU (median, largest, and onto a nearly full part):
on a busy machine the CPU time is the figure to compare.
Nothing is asserted; the figures are printed (and written as JSON with ``--json``).
"""

from __future__ import annotations

import argparse
import copy
import datetime as dt
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.soak import proc_sample, slope_per_100  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", type=int, default=3000, help="rows to write (default 3000)")
    p.add_argument("--per-save", type=int, default=25, help="rows per archiver pass (default 25)")
    p.add_argument("--part-rows", type=int, default=1000, help="[archive] workbook_max_rows (default 1000)")
    p.add_argument("--sample-every", type=int, default=100, help="memory sample every n rows (default 100)")
    p.add_argument("--warmup", type=int, default=200, help="rows not counted in the growth after warm-up")
    p.add_argument("--record", default=str(ROOT / "tests/archive/full_record.json"), help="the record to write")
    p.add_argument("--json", default=None, help="write the figures to this JSON file")
    args = p.parse_args(argv)

    from sofast_station.archive import Journal
    from sofast_station.archive.archiver import Archiver, ArchiverSettings
    from sofast_station.archive.workbook import WorkbookSettings, flatten_record

    record = json.loads(Path(args.record).read_text())
    t0 = dt.datetime(2026, 12, 2, 0, 0, tzinfo=dt.timezone.utc)
    samples: list[tuple[int, float]] = []
    passes: list[tuple[int, float, float]] = []               # (rows in the part before, wall s, CPU s)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "data"
        station = Journal(data / "journal.sqlite3")           # the station's connection: appends
        journal = Journal(data / "journal.sqlite3")           # the archiver's connection
        settings = ArchiverSettings(workbook=WorkbookSettings(max_rows=args.part_rows), min_free_gb=0.0)
        archiver = Archiver(journal, data, settings)
        print(f"archiver memory: {args.rows} rows of {len(flatten_record('x', record))} columns, {args.per_save} "
              f"per pass, {args.part_rows} per part; pid {os.getpid()}", flush=True)
        written = 0
        t_start = time.perf_counter()
        while written < args.rows:
            n = min(args.per_save, args.rows - written)
            for i in range(written, written + n):
                rec = copy.deepcopy(record)
                rec.update(serial=f"SIM-{i:05d}", time=(t0 + dt.timedelta(seconds=5 * i)).isoformat(
                    timespec="milliseconds"))
                station.append(f"c{i:06d}", rec)
            t, c = time.perf_counter(), time.process_time()
            report = archiver.run_once(workbook=True, dumps=False)
            passes.append((written % args.part_rows, time.perf_counter() - t, time.process_time() - c))
            if report.workbook_rows != n:
                print(f"pass at row {written}: {report.workbook_rows} rows written, {n} expected; "
                      f"{report.workbook_errors}", flush=True)
            before, written = written, written + n
            if written // args.sample_every > before // args.sample_every:
                rss = proc_sample(os.getpid())[0]
                samples.append((written, rss))
                print(f"  {written:5d} rows, {time.perf_counter() - t_start:6.0f} s: RSS {rss:6.1f} MB, last pass "
                      f"{passes[-1][1]:.2f} s ({passes[-1][2]:.2f} s CPU)", flush=True)
        station.close()
        journal.close()
    later = [s for s in samples if s[0] >= args.warmup]
    growth = slope_per_100([s[0] for s in later], [s[1] for s in later])
    overall = slope_per_100([s[0] for s in samples], [s[1] for s in samples])
    times = [s for _, s, _ in passes]
    cpu = [c for _, _, c in passes]
    full = [c for k, _, c in passes if k >= args.part_rows - 2 * args.per_save]  # passes onto a nearly full part
    figures = {"rows": args.rows, "per_save": args.per_save, "part_rows": args.part_rows,
               "columns": len(flatten_record("x", record)), "warmup": args.warmup,
               "rss_first_mb": samples[0][1], "rss_last_mb": samples[-1][1], "rss_max_mb": max(s for _, s in samples),
               "growth_mb_per_100_rows_after_warmup": growth, "growth_mb_per_100_rows_overall": overall,
               "pass_s_median": statistics.median(times), "pass_s_max": max(times),
               "pass_cpu_s_median": statistics.median(cpu), "pass_cpu_s_max": max(cpu),
               "pass_cpu_s_full_part_median": statistics.median(full) if full else None,
               "run_s": time.perf_counter() - t_start, "load_average": os.getloadavg(), "samples": samples}
    print(f"RSS {samples[0][1]:.1f} MB at row {samples[0][0]}, {samples[-1][1]:.1f} MB at the end, "
          f"{figures['rss_max_mb']:.1f} MB at most; growth per 100 rows {growth:+.2f} MB after the warm-up of "
          f"{args.warmup} rows, {overall:+.2f} MB overall")
    print(f"a pass ({args.per_save} rows): wall median {figures['pass_s_median']:.2f} s, largest {max(times):.2f} s;"
          f" CPU median {figures['pass_cpu_s_median']:.2f} s, largest {max(cpu):.2f} s"
          + (f", onto a nearly full part (>= {args.part_rows - 2 * args.per_save} rows) median "
             f"{figures['pass_cpu_s_full_part_median']:.2f} s" if full else "")
          + f"; {figures['run_s']:.0f} s in all; load average {os.getloadavg()[0]:.1f}")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
