"""Benchmark: does the monitor (the line's page and OPC UA) keep serving when the machine's cores are busy?

    .venv/bin/python benchmarks/monitor_under_load.py                  # nice 10, 2 and 0; a burner per core
    .venv/bin/python benchmarks/monitor_under_load.py --nice 2 --burners 4
    .venv/bin/python benchmarks/monitor_under_load.py --quick          # the default nice, one burner (the suite)

Issue 43: on a busy machine the monitor, at nice 10, got about 1 s of processor in 2 minutes and its OPC UA
server never came up in 600 s. For each niceness asked, this starts ``sofast-station serve`` (the monitor's
code, as ``run --serve`` starts it) on the small simulated station with the page and OPC UA, beside
``--burners`` processes that spin at the normal priority (as ``yes > /dev/null`` does: a backup, a virus
scan, a second program), and measures from outside: when the page first answers (``GET /api/state``), when
the OPC UA server first answers a read (``Station/State``), the page's and OPC UA's answer times over
``--requests`` requests once up, how long the monitor takes to stop after SIGTERM, and the processor time
it used (``os.wait4``). The burners start first and stop after the monitor. The machine's load average is
printed before and after each run, since it may be shared. The numbers are printed, never asserted.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SPIN = "while True: pass"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def load() -> str:
    return " ".join(f"{v:.1f}" for v in os.getloadavg())


def station_file(folder: Path, nice: int, page_port: int, opcua_port: int) -> Path:
    """The tests' small simulated dish station, its page on *page_port* and OPC UA on *opcua_port*, the
    monitor at *nice*."""
    text = (ROOT / "fixtures/stations/small_dish.toml.in").read_text().format(
        name="Small simulated dish station (benchmark)", data_dir_line="", analysis="", twist="0.1",
        facet=ROOT / "fixtures/facets/dish_5m33.toml", radiometric=ROOT / "calibration/simulated_radiometric.json")
    text += (f"\n[web]\nport = {page_port}\nnice = {nice}\n\n[opcua]\nenabled = true\n"
             f'endpoint = "opc.tcp://127.0.0.1:{opcua_port}/sofast-station/"\nanonymous = true\n')
    path = folder / f"station-nice{nice}.toml"
    path.write_text(text)
    return path


def page_answers(url: str) -> float | None:
    """Seconds for one ``GET`` of *url*; None when it does not answer (not up yet, or refused)."""
    t = time.perf_counter()
    try:
        with urllib.request.urlopen(url, timeout=60) as r:
            r.read()
    except OSError:
        return None
    return time.perf_counter() - t


async def opcua_reads(endpoint: str, deadline: float, requests: int) -> tuple[float | None, list[float]]:
    """When (time.monotonic) the OPC UA server first answered a read of Station/State, and *requests* more
    reads' times (s). Generous timeouts: what is measured is when it answers, not whether a client gives up."""
    from asyncua import Client

    up = None
    while up is None and time.monotonic() < deadline:
        client = Client(endpoint, timeout=120, watchdog_intervall=120)
        try:
            await client.connect()
        except (OSError, asyncio.TimeoutError, ConnectionError):
            await asyncio.sleep(0.2)
            continue
        try:
            ns = await client.get_namespace_index("urn:sofast-station")
            node = await client.nodes.objects.get_child([f"{ns}:SofastStation", f"{ns}:Station", f"{ns}:State"])
            await node.read_value()
            up = time.monotonic()
            times = []
            for _ in range(requests):
                t = time.perf_counter()
                await node.read_value()
                times.append(time.perf_counter() - t)
                await asyncio.sleep(0.1)
            return up, times
        finally:
            await client.disconnect()
    return None, []


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_run(folder: Path, nice: int, burners: int, requests: int, limit_s: float) -> dict:
    """The monitor at *nice* beside *burners* spinning processes: its times (s) and processor seconds."""
    page_port, opcua_port = free_port(), free_port()
    config = station_file(folder, nice, page_port, opcua_port)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "SOFAST_DATA_DIR": str(folder / f"data-nice{nice}")}
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN]) for _ in range(burners)]
    out: dict = {"nice": nice, "load_before": load()}
    try:
        time.sleep(1.0)                                   # the burners have the cores before the monitor starts
        t0 = time.monotonic()
        monitor = subprocess.Popen([sys.executable, "-m", "sofast_station", "serve", "--config", str(config)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
        try:
            url = f"http://127.0.0.1:{page_port}/api/state"
            while (first := page_answers(url)) is None:
                if monitor.poll() is not None or time.monotonic() - t0 > limit_s:
                    break
                time.sleep(0.1)
            out["page_up_s"] = time.monotonic() - t0 if first is not None else None
            out["cpu_at_page_s"] = cpu_s(monitor.pid) if monitor.poll() is None else None
            up, reads = asyncio.run(opcua_reads(f"opc.tcp://127.0.0.1:{opcua_port}/sofast-station/",
                                                t0 + limit_s, requests))
            out["opcua_up_s"] = None if up is None else up - t0
            out["opcua_reads_s"] = reads
            out["cpu_at_opcua_s"] = cpu_s(monitor.pid) if monitor.poll() is None else None
            pages = [page_answers(url) for _ in range(requests)]
            out["page_reads_s"] = [p for p in pages if p is not None]
            t = time.monotonic()
            monitor.send_signal(signal.SIGTERM)
            try:
                _, status, usage = os.wait4(monitor.pid, 0)
                out["stop_s"] = time.monotonic() - t
                out["exit"] = os.waitstatus_to_exitcode(status)
                out["cpu_s"] = usage.ru_utime + usage.ru_stime
                monitor.returncode = out["exit"]
            except ChildProcessError:
                out["stop_s"] = out["exit"] = out["cpu_s"] = None
        finally:
            if monitor.poll() is None:
                monitor.kill()
                monitor.wait()
            out["stderr_tail"] = (monitor.stderr.read() if monitor.stderr else "")[-600:]
    finally:
        for s in spinners:
            s.kill()
        for s in spinners:
            s.wait()
    out["load_after"] = load()
    return out


def _fmt(v, digits: int = 2) -> str:
    return "never" if v is None else f"{v:.{digits}f}"


def _spread(values: list) -> str:
    return "-" if not values else f"{statistics.median(values):.3f} / {max(values):.3f}"


def main(argv=None) -> int:
    import logging

    from sofast_station.web.settings import WebSettings

    logging.getLogger("asyncua").setLevel(logging.ERROR)      # its notes on session timeouts are not ours

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nice", type=int, action="append", default=None,
                   help="the monitor's niceness ([web] nice); repeatable (default: 10, the default's, 0)")
    p.add_argument("--burners", type=int, default=None, help="spinning processes (default: one per core)")
    p.add_argument("--requests", type=int, default=20, help="page and OPC UA requests timed once each is up")
    p.add_argument("--limit-s", type=float, default=300.0, help="give up waiting for a server after this long")
    p.add_argument("--quick", action="store_true", help="the default nice only, one burner, 3 requests")
    args = p.parse_args(argv)
    default = WebSettings().nice
    if args.quick:
        nices, burners, requests = [default], 1, 3
    else:
        nices = args.nice or sorted({10, default, 0}, reverse=True)
        burners = os.cpu_count() or 1 if args.burners is None else args.burners
        requests = args.requests
    print(f"the monitor (page and OPC UA) under load: {burners} spinning process(es) on {os.cpu_count()} core(s), "
          f"the monitor at nice {', '.join(map(str, nices))} (default {default}); python {sys.version.split()[0]}",
          flush=True)
    rows = []
    with tempfile.TemporaryDirectory(prefix="sofast-monitor-load-") as tmp:
        for nice in nices:
            r = one_run(Path(tmp), nice, burners, requests, args.limit_s)
            rows.append(r)
            print(json.dumps({k: v for k, v in r.items() if k != "stderr_tail"}), flush=True)
            if r.get("page_up_s") is None or r.get("opcua_up_s") is None:
                print(f"  the monitor's last words: {r['stderr_tail']!r}", flush=True)
    print()
    print("nice  page up, s  OPC UA up, s  page answer median / max, s  OPC UA read median / max, s  stop, s  "
          "monitor CPU, s  load average before -> after")
    for r in rows:
        print(f"{r['nice']:>4}  {_fmt(r['page_up_s']):>10}  {_fmt(r['opcua_up_s']):>12}  "
              f"{_spread(r['page_reads_s']):>28}  {_spread(r['opcua_reads_s']):>30}  {_fmt(r['stop_s']):>7}  "
              f"{_fmt(r['cpu_s']):>14}  {r['load_before']} -> {r['load_after']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
