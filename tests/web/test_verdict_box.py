"""Issue 29: the operator's page never lies about its verdict, at every screen it meets.

The page is served by ``sofast-station serve`` on a journal written here (no station runs: the records are
the archive's sample record with the verdict, serial and time each test needs), and looked at in Debian's
chromium through Playwright at 1920 x 1080, at a 1024 x 768 panel PC and at 800 x 600:

- every verdict word is shown whole inside its box (once cut to "INVAL", "INDETERM", FAULT spilling out),
  at a readable size, in a box whose height does not depend on the word;
- the verdict shows its age and is greyed (no verdict colour) once older than ``[web] stale_after_s`` or
  when the station is offline (once a 17-minute-old PASS stayed green); the page's clock is Playwright's
  fake clock, so the age is set, not waited for;
- an alarm says the station is offline; the header says "live" only while it runs;
- a normal end of the monitor says so (not "reconnecting…") and prints no traceback; no request of the
  page fails (the browser's favicon request once got a 404).

Screenshots go to $SOFAST_SCREENSHOTS (default: a temporary folder).
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
from pathlib import Path

import pytest
from playwright.sync_api import sync_playwright   # a test dependency: missing, the suite fails (setup-env test)

from sofast_station.archive import Journal
from sofast_station.live.status import status_path
from tests.conftest import ROOT, SMALL_STATION
from tests.web.serving import free_port, launch_chromium, shift_started_hours_ago, start_server, stop_server

SAMPLE = json.loads((ROOT / "tests/archive/full_record.json").read_text())
VIEWPORTS = ((1920, 1080), (1024, 768), (800, 600))
WORDS = ("pass", "fail", "fault", "invalid", "indeterminate")
#: The verdict's background colours (page.css): the live ones, and the grey of a verdict that is not live.
LIVE_COLOUR = {"pass": "rgb(21, 128, 61)", "fail": "rgb(185, 28, 28)"}
GREY = "rgb(55, 65, 81)"


def _station(tmp: Path, port: int, stale_after_s: float) -> tuple[Path, Path]:
    data = tmp / "data"
    config = tmp / "station.toml"
    config.write_text(SMALL_STATION.format(data_dir=data, facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                           radiometric=ROOT / "calibration/simulated_radiometric.json")
                      + f'\n[web]\nport = {port}\nnice = 0\nshift_starts = ["{shift_started_hours_ago()}"]\n'
                      + f'stale_after_s = {stale_after_s}\n')
    (data / "live").mkdir(parents=True)
    return config, data


def _journal(data: Path, n: int, verdict: str, age_s: float = 0.0) -> str:
    """Journal facet *n* with *verdict*, measured *age_s* seconds ago; returns its cycle id."""
    rec = json.loads(json.dumps(SAMPLE))
    rec.update(serial=f"SIM-{n:04d}", verdict=verdict, reasons=[] if verdict == "pass" else [f"a {verdict} reason"],
               time=(_dt.datetime.now().astimezone() - _dt.timedelta(seconds=age_s)).isoformat(timespec="milliseconds"))
    cycle_id = rec["cycle_id"] = f"20261203T000000000-{n:08x}"
    with Journal(data / "journal.sqlite3") as journal:
        journal.append(cycle_id, rec)
    return cycle_id


def _status(data: Path, state: str, pid: int | None) -> None:
    """The live status as the station writes it (a state with an alive process, or offline)."""
    now = _dt.datetime.now().astimezone().isoformat(timespec="milliseconds")
    status_path(data).write_text(json.dumps({"state": state, "pid": pid, "alarms": {}, "since": now,
                                             "updated": now}))


_MEASURE = """() => {
  const box = document.getElementById('verdict'), word = box.querySelector('.word');
  const b = box.getBoundingClientRect(), w = word.getBoundingClientRect();
  return {text: box.innerText.trim(), box: [b.left, b.right, b.top, b.bottom], word: [w.left, w.right, w.top, w.bottom],
          scroll: box.scrollWidth, client: box.clientWidth, font: parseFloat(getComputedStyle(box).fontSize),
          viewport: document.documentElement.clientWidth};
}"""


@pytest.fixture
def shots(tmp_path) -> Path:
    path = Path(os.environ.get("SOFAST_SCREENSHOTS") or tmp_path / "screenshots")
    path.mkdir(parents=True, exist_ok=True)
    return path


def test_every_verdict_word_fits_its_box_at_1920_1024_and_800_pixels(tmp_path, shots):
    port = free_port()
    config, data = _station(tmp_path, port, stale_after_s=86400)
    _status(data, "idle", os.getpid())
    server = start_server(config, data)
    seen: dict = {}
    try:
        with sync_playwright() as pw:
            browser = launch_chromium(pw)
            try:
                pages = {}
                for width, height in VIEWPORTS:
                    pages[width] = browser.new_page(viewport={"width": width, "height": height})
                    pages[width].goto(f"http://127.0.0.1:{port}/")
                for n, word in enumerate(WORDS, 1):
                    cycle = _journal(data, n, word)
                    for width, page in pages.items():
                        page.wait_for_function("c => document.body.dataset.cycle === c", arg=cycle, timeout=60_000)
                        seen[word, width] = page.evaluate(_MEASURE)
                        if word in ("indeterminate", "fault", "invalid"):
                            page.screenshot(path=str(shots / f"verdict-{word}-{width}.png"))
            finally:
                browser.close()
    finally:
        stop_server(server)
    for (word, width), m in seen.items():
        left, right, top, bottom = m["box"]
        w_left, w_right, w_top, w_bottom = m["word"]
        where = f"{word.upper()} at {width} px: {m}"
        assert m["text"] == word.upper(), where                                  # the whole word, never cut
        assert left <= w_left and w_right <= right and top <= w_top and w_bottom <= bottom, where
        assert m["scroll"] <= m["client"], where                                 # nothing spills out
        assert 0 <= left and right <= m["viewport"], where                       # the box is on the screen
        assert m["font"] >= 36, where          # readable across the cell: INDETERMINATE at 800 px is ~45 px
    for width, _ in VIEWPORTS:
        heights = {word: seen[word, width]["box"][3] - seen[word, width]["box"][2] for word in WORDS}
        assert max(heights.values()) - min(heights.values()) < 1.0, (width, heights)   # the box does not jump
        # the short words use the large size; the long ones are scaled to the box, not left tiny
        assert seen["pass", width]["font"] > 1.5 * seen["indeterminate", width]["font"], width
        ind = seen["indeterminate", width]
        assert ind["word"][1] - ind["word"][0] > 0.6 * (ind["box"][1] - ind["box"][0]), (width, ind)
    assert seen["pass", 1920]["font"] >= 100


def test_a_stale_verdict_is_greyed_with_its_age_and_an_offline_station_is_an_alarm(tmp_path, shots):
    port = free_port()
    config, data = _station(tmp_path, port, stale_after_s=60)
    _status(data, "idle", os.getpid())          # this process stands for the running station
    _journal(data, 1, "pass", age_s=5.0)
    server = start_server(config, data)
    failed: list[str] = []
    try:
        with sync_playwright() as pw:
            browser = launch_chromium(pw)
            try:
                page = browser.new_page(viewport={"width": 1024, "height": 768})
                page.on("response", lambda r: failed.append(f"{r.status} {r.url}") if r.status >= 400 else None)
                # the page's clock is Playwright's: the verdict's age moves when the test says so
                page.clock.install()
                page.goto(f"http://127.0.0.1:{port}/")
                page.wait_for_function("() => document.body.dataset.live === '1'", timeout=60_000)

                def look():
                    page.clock.run_for(1000)                     # the page's once-a-second refresh
                    return page.evaluate("""() => {
                      const v = document.getElementById('verdict');
                      return {stale: v.classList.contains('stale'), colour: getComputedStyle(v).backgroundColor,
                              age: document.getElementById('verdict-age').innerText,
                              link: document.getElementById('link').innerText,
                              alarms: document.querySelector('#station').innerText};
                    }""")
                fresh = look()
                assert not fresh["stale"] and fresh["colour"] == LIVE_COLOUR["pass"], fresh
                # 5 s old when journaled, plus however long the server took to start on this machine
                age = re.fullmatch(r"measured (\d+) s ago", fresh["age"])
                assert age and 5 <= int(age.group(1)) < 60, fresh
                assert fresh["link"] == "live" and "offline" not in fresh["alarms"], fresh
                page.clock.fast_forward("17:00")                 # the line stopped 17 minutes ago
                old = look()
                assert old["stale"] and old["colour"] == GREY, old
                assert old["age"] == "measured 17 min ago · not live: no facet for more than 60 s", old
                page.screenshot(path=str(shots / "verdict-stale-1024.png"))

                # a new facet is live again
                cycle = _journal(data, 2, "fail", age_s=0.0)
                page.wait_for_function("c => document.body.dataset.cycle === c", arg=cycle, timeout=60_000)
                new = look()
                assert not new["stale"] and new["colour"] == LIVE_COLOUR["fail"], new

                # the station goes offline: grey at once, whatever the verdict's age, and an alarm says so
                _status(data, "offline", None)
                page.wait_for_function("() => document.querySelector('#state [data-state]').dataset.state === "
                                       "'offline'", timeout=60_000)
                off = look()
                assert off["stale"] and off["colour"] == GREY, off
                assert off["age"].endswith("not live: the station is offline"), off
                assert "offline: the station is not running" in off["alarms"], off
                assert off["link"] == "connected · station offline", off
                page.screenshot(path=str(shots / "verdict-offline-1024.png"), full_page=True)
            finally:
                browser.close()
    finally:
        stop_server(server)
    assert not failed, failed                              # the favicon too is found


def test_a_normal_end_of_the_monitor_is_no_reconnecting_and_no_traceback(tmp_path):
    port = free_port()
    config, data = _station(tmp_path, port, stale_after_s=60)
    _status(data, "idle", os.getpid())
    _journal(data, 1, "pass")
    server = start_server(config, data)
    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        try:
            page = browser.new_page(viewport={"width": 1024, "height": 768})
            page.goto(f"http://127.0.0.1:{port}/")
            page.wait_for_function("() => document.body.dataset.live === '1'", timeout=60_000)
            stop_server(server)                      # SIGTERM, as `run --serve` ends its monitor
            page.wait_for_function("() => document.body.dataset.live === '0'", timeout=60_000)
            link = page.inner_text("#link")
            stale = page.evaluate("() => document.getElementById('verdict').classList.contains('stale')")
        finally:
            browser.close()
    err = server.stderr.read()
    assert link.startswith("monitor stopped"), link
    assert stale                                      # nothing live is shown once the monitor has gone
    assert "Traceback" not in err and "CancelledError" not in err, err
