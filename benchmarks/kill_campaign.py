"""Kill campaign: kill -9 the station, its analysis worker or its archiver at random moments; check the archive.

    .venv/bin/python benchmarks/kill_campaign.py --kills 30          # 30 kills on a 400 x 300 station
    .venv/bin/python benchmarks/kill_campaign.py --two-runs 100      # two runs on one data folder
    .venv/bin/python benchmarks/kill_campaign.py --quick             # the test suite's smoke run

``--kills N``: runs ``sofast-station run`` (the real command, a fresh process) on one data folder and,
N times, waits for a facet and a random 0.5 to 6 s more, then sends SIGKILL to the station, the worker or
the archiver: a third of the kills each (at least ``--archiver`` of the archiver), in a random order. After a station
kill it checks that no process of the killed station
remains (within 10 s) and starts the station again; after a worker or archiver kill it checks that the
line goes on with passes. At the end the station is stopped with SIGTERM and must exit by itself.

Then the archive is checked: every facet line printed (answered) has its journal row, every journal row
is in exactly one workbook row, every requested dump is readable, no temporary file and no process is
left. (A station killed between journaling and printing leaves a row without a printed line: those are
counted, at most one per station kill.)

``--quick``: three kills, one each of the station, the worker and the archiver, 0.1 to 1 s after a facet, the
line going on for 2 facets after a worker or archiver kill (the test suite's run; the archive checks are the
same).

``--two-runs N``: a run of N facets; while it runs a second ``run`` on the same data folder must refuse
(naming the first one's PID); then a second run of N facets; 2 N rows, none lost or duplicated.
"""

from __future__ import annotations

import argparse
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.soak import SMALL, archive_checks  # noqa: E402


def children(pid: int) -> set[int]:
    out: set[int] = set()
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return out
    for task in tasks:
        try:
            out |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            pass
    return out


def gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
    except OSError:
        return True


def cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


class Station:
    """One ``sofast-station run`` process, its console lines collected by a thread."""

    def __init__(self, config: Path, facets: int, env: dict):
        self.proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "run", "--config", str(config),
                                      "--facets", str(facets)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=env, cwd=str(ROOT), start_new_session=True)
        self.lines: list[str] = []
        self.err: list[str] = []
        self._t = threading.Thread(target=self._read, args=(self.proc.stdout, self.lines), daemon=True)
        self._e = threading.Thread(target=self._read, args=(self.proc.stderr, self.err), daemon=True)
        self._t.start()
        self._e.start()

    @staticmethod
    def _read(stream, into):
        for line in stream:
            into.append(line.rstrip("\n"))

    def facets(self) -> list[str]:
        return [ln for ln in self.lines if " SIM-" in f" {ln}"]

    def wait_facets(self, n: int, timeout_s: float = 300.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.proc.poll() is None:
            if len(self.facets()) >= n:
                return True
            time.sleep(0.05)
        return len(self.facets()) >= n

    def worker_and_archiver(self) -> tuple[int | None, int | None]:
        worker = archiver = None
        for c in children(self.proc.pid):
            text = cmdline(c)
            if "resource_tracker" in text:
                continue
            if "spawn_main" in text:
                # the archiver holds data_dir/archiver.lock open; the analysis worker does not
                try:
                    files = {os.readlink(f"/proc/{c}/fd/{fd}") for fd in os.listdir(f"/proc/{c}/fd")}
                except OSError:
                    continue
                if any(f.endswith("archiver.lock") for f in files):
                    archiver = c
                else:
                    worker = worker or c
        return worker, archiver

    def finish(self, timeout_s: float) -> int | None:
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None
        self._t.join(5)
        self._e.join(5)
        return self.proc.returncode


def write_config(folder: Path) -> Path:
    path = folder / "station.toml"
    path.write_text(SMALL.format(root=ROOT) + "\n[run]\ndump_every_n = 3\nlate_grace_s = 5.0\n"
                    "[archive]\nworkbook_interval_s = 2.0\n")
    return path


def check_archive(data: Path, answered: int, station_kills: int) -> dict:
    result = archive_checks(data)
    return {"answered_lines": answered, "rows_without_line": result["journal_rows"] - answered,
            "station_kills": station_kills, **result}


def campaign(kills: int, seed: int, folder: Path, archiver_kills: int = 10, wait_s: tuple[float, float] = (0.5, 6.0),
             go_on: int = 3) -> int:
    """*kills* kills, each *wait_s* (a uniform range, s) after a facet; after a worker or archiver kill the line
    must go on with *go_on* facets, some of them passes."""
    rng = random.Random(seed)
    config = write_config(folder)
    data = folder / "data"
    env = dict(os.environ, SOFAST_DATA_DIR=str(data), PYTHONPATH=str(ROOT))
    answered = 0
    station_kills = 0
    problems: list[str] = []
    all_pids: set[int] = set()
    station = Station(config, 100000, env)
    counts = {"station": 0, "worker": 0, "archiver": 0}
    n_archiver = max(archiver_kills, kills // 3)
    n_worker = (kills - n_archiver) // 2
    plan = ["archiver"] * n_archiver + ["worker"] * n_worker + ["station"] * (kills - n_archiver - n_worker)
    rng.shuffle(plan)
    t_start = time.monotonic()
    for k in range(1, kills + 1):
        if not station.wait_facets(len(station.facets()) + 1, 300):
            problems.append(f"kill {k}: the station measured nothing (exit {station.proc.poll()}): "
                            + " | ".join(station.err[-5:]))
            break
        time.sleep(rng.uniform(*wait_s))
        worker, archiver = station.worker_and_archiver()
        all_pids |= {p for p in (worker, archiver) if p} | children(station.proc.pid)
        target = plan[k - 1]
        pid = {"station": station.proc.pid, "worker": worker, "archiver": archiver}[target]
        for _ in range(100):                 # a worker or archiver being restarted: wait for the new one
            if pid is not None:
                break
            time.sleep(0.1)
            worker, archiver = station.worker_and_archiver()
            pid = {"station": station.proc.pid, "worker": worker, "archiver": archiver}[target]
        if pid is None:
            problems.append(f"kill {k}: no {target} process to kill")
            continue
        before = len(station.facets())
        kids = children(station.proc.pid)
        os.kill(pid, signal.SIGKILL)
        counts[target] += 1
        if target == "station":
            station_kills += 1
            station.finish(10)
            answered += len(station.facets())
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and not all(gone(c) for c in kids):
                time.sleep(0.1)
            left = [c for c in kids if not gone(c)]
            if left:
                problems.append(f"kill {k}: processes {left} of the killed station remain")
            station = Station(config, 100000, env)
            note = "restarted"
        else:
            ok = station.wait_facets(before + go_on, 300)
            recent = station.facets()[before:]
            passes = sum(" PASS " in ln for ln in recent)
            if not ok or not passes:
                problems.append(f"kill {k}: after killing the {target} the line did not go on with passes "
                                f"({recent})")
            note = f"line went on: {len(recent)} facets, {passes} pass"
        print(f"kill {k:2d} at {time.monotonic() - t_start:6.0f} s: {target:<8} (pid {pid}) after {before} facets "
              f"of this run; {note}", flush=True)
    station.wait_facets(len(station.facets()) + 2, 300)
    station.proc.send_signal(signal.SIGTERM)
    code = station.finish(180)
    if code != 0:
        problems.append(f"the last run did not exit by itself on SIGTERM (exit {code}): {station.err[-5:]}")
    answered += len(station.facets())
    time.sleep(2)
    left = [p for p in all_pids if not gone(p)]
    if left:
        problems.append(f"processes left: {left}")
    result = check_archive(data, answered, station_kills)
    print(f"kills: {counts}; {answered} facets answered in {time.monotonic() - t_start:.0f} s; load average "
          f"{os.getloadavg()[0]:.1f}")
    for k, v in result.items():
        print(f"  {k}: {v}")
    if not (result["journal_unique"] and result["workbook_unique"] and result["workbook_equals_journal"]
            and 0 <= result["rows_without_line"] <= station_kills and not result["dumps_bad"]
            and not result["temp_files"] and not result["orphan_spools"]):
        problems.append("archive check failed (see above)")
    print("problems: " + ("; ".join(problems) if problems else "none"))
    return 1 if problems else 0


def two_runs(n: int, folder: Path) -> int:
    config = write_config(folder)
    data = folder / "data"
    env = dict(os.environ, SOFAST_DATA_DIR=str(data), PYTHONPATH=str(ROOT))
    first = Station(config, n, env)
    first.wait_facets(1, 300)
    second = subprocess.run([sys.executable, "-m", "sofast_station", "run", "--config", str(config), "--facets",
                             str(n)], capture_output=True, text=True, env=env, cwd=str(ROOT), timeout=300)
    refused = second.returncode == 2 and f"(process {first.proc.pid})" in second.stderr
    print(f"second run while the first runs: exit {second.returncode}; "
          f"{second.stderr.strip().splitlines()[-1] if second.stderr.strip() else ''}")
    code1 = first.finish(3600)
    then = Station(config, n, env)
    code2 = then.finish(3600)
    answered = len(first.facets()) + len(then.facets())
    result = check_archive(data, answered, 0)
    print(f"first run exit {code1}, {len(first.facets())} facets; second run exit {code2}, "
          f"{len(then.facets())} facets")
    for k, v in result.items():
        print(f"  {k}: {v}")
    ok = (refused and code1 == 0 and code2 == 0 and result["journal_rows"] == 2 * n == answered
          and result["workbook_equals_journal"] and result["workbook_unique"] and not result["dumps_bad"])
    print("two runs: " + ("ok" if ok else "FAILED"))
    return 0 if ok else 1


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kills", type=int, default=30)
    p.add_argument("--two-runs", type=int, default=0, metavar="N", help="instead: two runs of N facets")
    p.add_argument("--archiver", type=int, default=10, help="at least this many of the kills hit the archiver")
    p.add_argument("--seed", type=int, default=11)
    p.add_argument("--keep", default=None, help="keep the data folder here")
    p.add_argument("--quick", action="store_true", help="3 kills, one of each, short waits (the test suite's run)")
    args = p.parse_args(argv)
    wait_s, go_on = (0.5, 6.0), 3
    if args.quick:
        args.kills, args.archiver, wait_s, go_on = 3, 1, (0.1, 1.0), 2
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        if args.two_runs:
            return two_runs(args.two_runs, folder)
        return campaign(args.kills, args.seed, folder, args.archiver, wait_s, go_on)


if __name__ == "__main__":
    sys.exit(main())
