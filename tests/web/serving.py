"""What the browser tests of the page share: a free port, ``sofast-station serve`` in its own process
(as on the line) and Debian's chromium (``setup-env test`` installs it; Playwright never downloads one)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from tests.conftest import ROOT

CHROMIUM = "/usr/bin/chromium"


def shift_started_hours_ago(hours: float = 2.0) -> str:
    """A shift start ("HH:MM", local time) *hours* before now: the facets a test journals now are in the
    current shift whatever the time of day (a fixed "00:00" left out the facets a test made in the last
    minute before midnight, when it ran just after)."""
    import datetime

    return (datetime.datetime.now() - datetime.timedelta(hours=hours)).strftime("%H:%M")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(config: Path, data: Path) -> subprocess.Popen:
    """``sofast-station serve --config CONFIG`` on *data*, once it has written where it listens."""
    (data / "live" / "monitor.json").unlink(missing_ok=True)
    env = dict(os.environ, PYTHONPATH=str(ROOT), SOFAST_DATA_DIR=str(data))
    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "serve", "--config", str(config)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    end = time.monotonic() + 120
    while not (data / "live" / "monitor.json").exists():
        if proc.poll() is not None or time.monotonic() > end:
            proc.kill()
            raise AssertionError(f"the server did not start: {proc.communicate()}")
        time.sleep(0.1)
    return proc


def stop_server(proc: subprocess.Popen) -> None:
    """SIGTERM, as ``run --serve`` ends its monitor (killed after 30 s)."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def launch_chromium(pw):
    """Debian's chromium, headless, through Playwright; an assertion error when it is not installed."""
    assert os.access(CHROMIUM, os.X_OK), f"Debian's chromium is missing at {CHROMIUM}: ./setup-env test installs it"
    return pw.chromium.launch(executable_path=CHROMIUM, args=[
        "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"])
