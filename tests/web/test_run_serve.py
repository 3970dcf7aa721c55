"""Issue 15: `sofast-station run --serve` starts the page beside the loop (its own process, lower
priority), which stops with the run; the log has one line per facet and the console a summary."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import urllib.request

from sofast_station.live.operator_commands import post_command
from sofast_station.live.status import read_status
from tests.conftest import ROOT


def test_run_serve_starts_and_stops_the_page(small_station_toml, tmp_path):
    small_station_toml.write_text(small_station_toml.read_text() + "\n[web]\nport = 0\n\n[run]\ndeadline_s = 300\n")
    data = tmp_path / "station-data"
    post_command(data, "pause", source="test")       # the line waits, paused, until the page is checked
    env = dict(os.environ, PYTHONPATH=str(ROOT), SOFAST_DATA_DIR=str(data))
    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "run", "--serve", "--config",
                             str(small_station_toml), "--facets", "2"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    try:
        end = time.monotonic() + 180
        while not (data / "live" / "monitor.json").exists() or read_status(data)["state"] != "paused":
            assert time.monotonic() < end and proc.poll() is None, "the station or its page did not start"
            time.sleep(0.1)
        info = json.loads((data / "live" / "monitor.json").read_text())
        pid = info["pid"]
        assert pid != proc.pid
        # [web] nice (2 unless set) below the station: close to its share, so it serves on a busy machine
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(19, os.getpriority(os.PRIO_PROCESS, proc.pid) + 2)
        with urllib.request.urlopen(info["url"] + "api/state", timeout=30) as r:
            state = json.loads(r.read())
        assert state["station"].startswith("Small simulated") and state["state"] == "paused"
        assert not state["actions_enabled"]
        post_command(data, "resume", source="test")
    except BaseException:
        proc.kill()
        raise
    header = proc.stdout.readline()
    first = proc.stdout.readline()
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert header.split()[:2] == ["n", "serial"] and first.split()[:2] == ["1/2", "SIM-0001"]
    assert "2 facet(s): 2 pass" in out and "yield 100.0 % (2/2)" in out and "95th percentile" in out
    try:
        os.kill(pid, 0)
        alive = True
    except ProcessLookupError:
        alive = False
    assert not alive, "the page's process ended with the run"
    log = (data / "logs" / "station.log").read_text()
    facet_lines = [ln for ln in log.splitlines() if " facet " in ln and "verdict=" in ln]
    assert [ln.split("serial=")[1].split()[0] for ln in facet_lines] == ["'SIM-0001'", "'SIM-0002'"]
    assert all("focal_length_x_m=" in ln and "cycle_s=" in ln for ln in facet_lines)
