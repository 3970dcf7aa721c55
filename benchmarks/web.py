"""Benchmark: does the line's web page slow the loop? Cycle time over 20 facets without and with the page.

    .venv/bin/python benchmarks/web.py              # default full-resolution station, 20 facets per run
    .venv/bin/python benchmarks/web.py --quick      # 3 facets per run (a smoke run)

Both runs use the same station as benchmarks/cycle.py (the twin's capture replayed with a modelled
display settle, the real loop, worker and archiver processes). The run "with the page" also starts the
monitor exactly as ``sofast-station run --serve`` does (its own process, at [web] nice), and opens the
page in Debian's chromium, headless, driven by Playwright from a separate process (as an operator's
browser would be): it follows the live updates and, to make it harder, reloads the whole page every
``--reload-s`` seconds. The browser records when each facet appeared on the page; with the journal's
``journaled_at`` that gives the page's latency. Runs alternate (without, with, with, without for
``--rounds 2``) so a machine that gets busier or quieter does not favour one side. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import multiprocessing
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

CHROMIUM = "/usr/bin/chromium"


def _browser(url: str, out: str, stop, reload_s: float, nice: int) -> None:
    """The operator's browser: the page open, live; reloaded every *reload_s*; appearance times saved."""
    if nice:
        os.nice(nice)                                # chromium, started from here, inherits it
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    seen: dict = {}
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=[
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run"])
        page = browser.new_page(viewport={"width": 1500, "height": 1100})
        # a facet first seen as the page (re)loads is not a live update: its time is not a latency
        watch = """() => { window.__seen = window.__seen || {};
            const note = (live) => { const c = document.body.dataset.cycle; if (c && !(c in window.__seen))
                window.__seen[c] = live ? Date.now() : null; };
            new MutationObserver(() => note(true)).observe(document.body, {attributes: true}); note(false); }"""
        page.set_default_timeout(120_000)             # a busy machine starves the monitor (it runs niced)
        page.goto(url, wait_until="domcontentloaded")
        page.evaluate(watch)
        last = time.monotonic()
        while not stop.is_set():
            page.wait_for_timeout(1000)              # the page notes each facet's time itself; this only idles
            if time.monotonic() - last > reload_s:
                for k, v in page.evaluate("window.__seen || {}").items():
                    seen.setdefault(k, v)
                try:
                    page.reload(wait_until="domcontentloaded")
                    page.evaluate(watch)
                except PlaywrightError as exc:
                    print(f"browser: reload failed ({exc}); going on", flush=True)
                last = time.monotonic()
        for k, v in page.evaluate("window.__seen || {}").items():
            seen.setdefault(k, v)
        browser.close()
    Path(out).write_text(json.dumps(seen))


def _cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return float("nan")


def _tree_cpu_seconds(pid: int, name_prefix: str = "") -> float:
    """CPU seconds of *pid* and every living descendant whose name starts with *name_prefix* (e.g. the
    browser's renderer and GPU processes, not Playwright's driver)."""
    children: dict = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                ppid = int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            name = Path(f"/proc/{p}/comm").read_text().strip()
        except OSError:
            name = ""
        if name.startswith(name_prefix):
            c = _cpu_seconds(p)
            total += 0.0 if c != c else c
        todo.extend(children.get(p, []))
    return total


def one_run(cfg, frames, distance, frame_delay, n: int, with_page: bool, reload_s: float,
            browser_nice: int = 0) -> dict:
    from cycle import FixedRangeFinder, NullDisplay

    from sofast_station.archive import Journal
    from sofast_station.calibrate.records import load_radiometric
    from sofast_station.devices.cameras.replay import ReplayCamera
    from sofast_station.station.opened import Station
    from sofast_station.station.service import Service
    from sofast_station.web.monitor import MonitorProcess, monitor_info_path
    from sofast_station.web.settings import web_settings

    with tempfile.TemporaryDirectory() as tmp:
        raw = dict(cfg.raw, run={"dump_every_n": 5}, archive={"workbook_interval_s": 5.0},
                   web={"port": 0, "token": "benchmark-token"})
        bench_cfg = dataclasses.replace(cfg, data_dir=Path(tmp), raw=raw, simulation={})
        monitor = browser = stop = None
        result: dict = {"with_page": with_page}
        if with_page:
            web = dataclasses.replace(web_settings(bench_cfg), port=0)
            monitor = MonitorProcess(bench_cfg, web, None)
            info = monitor_info_path(bench_cfg.data_dir)
            end = time.monotonic() + 120
            while not info.exists():
                if time.monotonic() > end:
                    raise SystemExit("the monitor did not start")
                time.sleep(0.1)
            url = json.loads(info.read_text())["url"]
            ctx = multiprocessing.get_context("spawn")
            stop = ctx.Event()
            seen_path = Path(tmp) / "seen.json"
            browser = ctx.Process(target=_browser, args=(url, str(seen_path), stop, reload_s, browser_nice),
                                  daemon=True)
            browser.start()
            time.sleep(5.0)                          # the page is open before the first facet
            cpu_before = (_cpu_seconds(monitor.pid), _tree_cpu_seconds(browser.pid, "chrom"))
        service = Service.__new__(Service)
        station = Station(config=bench_cfg, display=NullDisplay(),
                          camera=ReplayCamera(frames, frame_delay_s=frame_delay, loop=True),
                          range_finder=FixedRangeFinder(distance),
                          radiometric=load_radiometric(cfg.radiometric_path), twin=None)
        Service.__init__(service, bench_cfg, simulated_facets=n, console=lambda line: None, station=station)
        try:
            outcomes = service.runner.run()
        finally:
            service.close()
        result["cycle_s"] = [o.cycle_s for o in outcomes]
        result["answers"] = [o.answer for o in outcomes]
        if with_page:
            time.sleep(2.0)                          # the last facet reaches the page
            result["monitor_cpu_s"] = _cpu_seconds(monitor.pid) - cpu_before[0]
            result["browser_cpu_s"] = _tree_cpu_seconds(browser.pid, "chrom") - cpu_before[1]
            stop.set()
            browser.join(120)
            monitor.stop()
            seen = json.loads(seen_path.read_text()) if seen_path.exists() else {}
            with Journal(Path(tmp) / "journal.sqlite3") as journal:
                lat = []
                for row in journal.rows():
                    if seen.get(row.cycle_id) is not None:
                        t_row = _dt.datetime.fromisoformat(row.journaled_at).timestamp()
                        lat.append(seen[row.cycle_id] / 1000.0 - t_row)
            result["latency_s"] = lat
            result["facets_seen"] = len(seen)
    return result


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "station.toml"))
    p.add_argument("--facets", type=int, default=20)
    p.add_argument("--rounds", type=int, default=1, help="pairs of runs (without/with, then with/without, ...)")
    p.add_argument("--reload-s", type=float, default=10.0, help="the browser reloads the whole page this often")
    p.add_argument("--browser-nice", type=int, default=0,
                   help="run the browser this much below normal priority (a kiosk browser on the station PC)")
    p.add_argument("--quick", action="store_true", help="3 facets per run")
    args = p.parse_args(argv)
    n = 3 if args.quick else args.facets
    if not os.path.exists(CHROMIUM):
        print("Debian's chromium is not installed: './setup-env test' installs it")
        return 1

    import logging
    logging.basicConfig(level=logging.WARNING)
    from sofast_station.config import load_config
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture

    cfg = load_config(args.config)
    twin = open_station(cfg, seed=1)
    try:
        frames, distance = capture(twin)
    finally:
        twin.close()
    frame_delay = 3.0 / 60.0
    cam = cfg.geometry.camera
    print(f"station: {cfg.name}; camera {cam.width_px} x {cam.height_px}; {n} facets per run; "
          f"{os.cpu_count()} CPUs; load average {os.getloadavg()[0]:.1f} at the start; browser nice "
          f"{args.browser_nice}")
    order = []
    for r in range(args.rounds):
        order += [False, True] if r % 2 == 0 else [True, False]
    runs = []
    for with_page in order:
        res = one_run(cfg, frames, distance, frame_delay, n, with_page, args.reload_s, args.browser_nice)
        runs.append(res)
        c = res["cycle_s"]
        extra = ""
        if with_page:
            lat = res["latency_s"]
            extra = (f"; on the page {res['facets_seen']}/{n} facets, journal row -> page (live, {len(lat)}) median "
                     f"{statistics.median(lat):.2f} s, worst {max(lat):.2f} s" if lat else "; no facet seen")
            extra += (f"; CPU during the facets: monitor {res['monitor_cpu_s'] / n:.2f} s per facet, chromium "
                      f"{res['browser_cpu_s'] / n:.2f} s per facet")
        label = "with the page   " if with_page else "without the page"
        print(f"  {label}: cycle median {statistics.median(c):.3f} s, "
              f"mean {statistics.mean(c):.3f} s, worst {max(c):.3f} s ({', '.join(sorted(set(res['answers'])))})"
              + extra, flush=True)
    without = [t for r in runs if not r["with_page"] for t in r["cycle_s"]]
    with_ = [t for r in runs if r["with_page"] for t in r["cycle_s"]]
    m0, m1 = statistics.median(without), statistics.median(with_)
    pairs = [statistics.median(b["cycle_s"]) / statistics.median(a["cycle_s"]) - 1
             for a, b in zip(runs[0::2], runs[1::2]) for a, b in [(a, b) if not a["with_page"] else (b, a)]]
    print("each round, with against without (median cycle): " + ", ".join(f"{100 * d:+.1f} %" for d in pairs))
    print(f"median cycle: without {m0:.3f} s, with the page {m1:.3f} s: {100 * (m1 / m0 - 1):+.1f} % "
          f"(mean {100 * (statistics.mean(with_) / statistics.mean(without) - 1):+.1f} %); "
          f"load average {os.getloadavg()[0]:.1f} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
