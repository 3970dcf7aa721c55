"""Issue 15: the line's web page in a real browser (Debian's chromium, headless, driven by Playwright).

One small simulated run with the page served by ``sofast-station serve`` in its own process, as on the
line. After each facet (a runner hook, so the loop waits while the browser looks) the open page must
show that facet without being reloaded. The serials include ``../../etc/passwd``, markup with unicode and
a 300-character one: the page shows them as text, and no request path reaches a file outside the
pictures of data_dir. A guarded action without the token is refused; with it, it reaches the loop's
command interface. Finally the server is restarted and the page reconnects by itself.

Screenshots after a pass, a fail and a fault go to $SOFAST_SCREENSHOTS (default: a temporary folder).
"""

from __future__ import annotations

import http.client
import json
import os
from pathlib import Path

import pytest

from playwright.sync_api import sync_playwright   # a test dependency: missing, the suite fails (setup-env test)

from sofast_station.config import load_config
from sofast_station.devices.protocols import FacetRequest
from sofast_station.serials import clean_serial
from sofast_station.live.operator_commands import commands_dir
from sofast_station.station.service import Service
from tests.conftest import ROOT, SMALL_STATION
from tests.web.serving import free_port, launch_chromium, shift_started_hours_ago, start_server, stop_server

TOKEN = "line-token-for-tests"
LONG = "L" * 280 + "-END-OF-LONG-SERIAL"           # 300 characters
UNICODE = "<script>alert('x')</script>Ærø-序列-🙂"
SERIALS = ["SIM-0001", "F-0002", "../../etc/passwd", UNICODE, LONG, "X-0006"]
VERDICTS = ["pass", "fail", "pass", "pass", "pass", "fault"]
EXTRA = """
[run]
deadline_s = 300          # a busy machine must not turn a facet into a timeout fault

[recipes.strict]
serial_pattern = "^F-"
limits = {{ focal_length_tolerance = 0.005 }}

[simulation.faults]
"X-0006" = "dark"

[web]
token = "{token}"
port = {port}
nice = 0
shift_starts = ["{shift_start}"]
"""


def _raw_get(port: int, path: str) -> tuple[int, bytes]:
    """GET with the path sent exactly as given (no client-side normalisation of ../)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.putrequest("GET", path, skip_accept_encoding=True)
        conn.endheaders()
        r = conn.getresponse()
        return r.status, r.read()
    finally:
        conn.close()


@pytest.fixture(scope="module")
def line(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("web")
    data = tmp / "data"
    port = free_port()
    config = tmp / "station.toml"
    config.write_text(SMALL_STATION.format(data_dir=data, facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                           radiometric=ROOT / "calibration/simulated_radiometric.json")
                      + EXTRA.format(port=port, token=TOKEN, shift_start=shift_started_hours_ago()))
    shots = Path(os.environ.get("SOFAST_SCREENSHOTS") or tmp / "screenshots")
    shots.mkdir(parents=True, exist_ok=True)
    return config, data, port, shots


def test_the_page_follows_the_line(line, monkeypatch):
    config_path, data, port, shots = line
    monkeypatch.setenv("SOFAST_DATA_DIR", str(data))
    cfg = load_config(config_path)
    server = start_server(config_path, data)
    url = f"http://127.0.0.1:{port}/"
    seen: list[dict] = []
    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        try:
            page = browser.new_page(viewport={"width": 1500, "height": 1100})
            dialogs: list[str] = []
            page.on("dialog", lambda d: (dialogs.append(d.message), d.dismiss()))
            page.goto(url)
            assert "No facet measured yet" in page.inner_text("#last")
            page.evaluate("window.__loadedOnce = true")       # gone if the page were reloaded

            def look(outcome):
                """After each facet: the open page shows it, without a reload."""
                page.wait_for_function("c => document.body.dataset.cycle === c", arg=outcome.cycle_id,
                                       timeout=60_000)
                assert page.evaluate("window.__loadedOnce") is True
                verdict = page.get_attribute("#last .verdict", "data-verdict")
                serial = page.inner_text("#last .serial")
                title = page.get_attribute("#last .serial", "title")
                reasons = page.locator("#last .reasons li").all_inner_texts()
                if outcome.answer != "fault":
                    page.wait_for_function("() => { const i = document.getElementById('map'); "
                                           "return i && i.complete && i.naturalWidth > 0; }", timeout=60_000)
                page.wait_for_function("() => { const i = document.getElementById('white'); "
                                       "return i && i.complete && i.naturalWidth > 0; }", timeout=60_000)
                seen.append({"serial": serial, "title": title, "verdict": verdict, "reasons": reasons,
                             "scripts": page.locator("script").count(),
                             "facets": page.inner_text("#shift .kpis div:first-child b")})
                if outcome.serial in ("SIM-0001", "F-0002", "X-0006"):
                    page.screenshot(path=str(shots / f"page-after-{outcome.answer}.png"), full_page=True)
                elif outcome.serial in (clean_serial(UNICODE)[0], clean_serial(LONG)[0]):
                    name = "unicode" if outcome.serial == clean_serial(UNICODE)[0] else "long"
                    page.screenshot(path=str(shots / f"page-serial-{name}.png"))

            requests = [FacetRequest(serial=s) for s in SERIALS]
            service = Service(cfg, simulated_facets=requests, console=lambda line: None, archiver_process=False)
            service.runner.hooks.append(look)
            try:
                outcomes = service.runner.run()
            finally:
                service.close()
            assert [o.answer for o in outcomes] == VERDICTS

            # what the page showed after each facet: that facet, its serial as text, every reason
            # the station keeps a serial's first MAX_SERIAL_CHARS characters (sofast_station/serials.py); the
            # page shows the start and end of what it kept when that is too long to show whole
            kept = clean_serial(LONG)[0]
            shown_long = kept[:29] + "…" + kept[-29:]
            # every serial as the station keeps it: "../../etc/passwd" and "</script>" are never a path
            kept_all = [clean_serial(s)[0] for s in SERIALS]
            assert kept_all[2] == "____etc_passwd" and "<script>" in kept_all[3]       # markup stays, escaped
            assert [s["serial"] for s in seen] == kept_all[:4] + [shown_long] + kept_all[5:], seen
            assert seen[4]["title"] == kept
            assert [s["verdict"] for s in seen] == VERDICTS, seen
            assert [s["facets"] for s in seen] == [str(i) for i in range(1, 7)], seen
            assert any("focal length x" in r for r in seen[1]["reasons"]), seen
            assert "dark everywhere" in seen[5]["reasons"][0], seen
            assert all(s["scripts"] == 1 for s in seen) and not dialogs, (seen, dialogs)   # markup stayed text

            # a guarded action without the token (or with a wrong one) is refused and posts nothing
            page.click("button[data-action='pause']")
            page.wait_for_function("() => document.getElementById('action-result').textContent.length > 0")
            assert page.inner_text("#action-result").startswith("refused: wrong or missing token"), \
                page.inner_text("#action-result")
            page.fill("#token", "not-the-token")
            page.evaluate("document.getElementById('action-result').textContent = ''")
            page.click("button[data-action='remeasure']")
            page.wait_for_function("() => document.getElementById('action-result').textContent.length > 0")
            assert page.inner_text("#action-result").startswith("refused"), page.inner_text("#action-result")
            assert not commands_dir(data).exists() or not list(commands_dir(data).glob("*.json"))
            # with the token it reaches the loop's command interface
            page.fill("#token", TOKEN)
            page.fill("#serial-input", "HAND-7")
            page.evaluate("document.getElementById('action-result').textContent = ''")
            page.click("button[data-action='serial']")
            page.wait_for_function("() => document.getElementById('action-result').textContent.length > 0")
            assert page.inner_text("#action-result") == "the next facet gets the serial HAND-7", \
                page.inner_text("#action-result")
            posted = [json.loads(p.read_text()) for p in commands_dir(data).glob("*.json")]
            assert [(c["command"], c["serial"]) for c in posted] == [("serial", "HAND-7")]

            # the server restarts: the page reconnects by itself and shows the same last facet
            stop_server(server)
            page.wait_for_function("() => document.body.dataset.live === '0'", timeout=60_000)
            server = start_server(config_path, data)
            page.wait_for_function("() => document.body.dataset.live === '1'", timeout=60_000)
            assert page.evaluate("window.__loadedOnce") is True
            assert page.get_attribute("#last .verdict", "data-verdict") == "fault"
        finally:
            browser.close()
            stop_server(server)
    for name in ("pass", "fail", "fault"):
        assert (shots / f"page-after-{name}.png").stat().st_size > 10_000


def test_no_file_outside_the_pictures_is_served(line, monkeypatch):
    """Whatever the request path holds (the serials' own text, ../, encoded slashes), only the page, its
    script and style, the JSON state and the pictures of data_dir/live/facets come back."""
    config_path, data, port, _ = line
    server = start_server(config_path, data)
    try:
        secret = b"root:"
        outside = data.parent / "outside.png"
        outside.write_bytes(b"\x89PNG not for the page")
        paths = ["/../../etc/passwd", "/facet/../../etc/passwd/white.png", "/facet/..%2F..%2Fetc%2Fpasswd/white.png",
                 "/%2e%2e/%2e%2e/etc/passwd", "/page.css/../../../etc/passwd", "/facet/%2e%2e/outside.png",
                 "/facet/..%2f..%2foutside/white.png", "//etc/passwd", "/static/../../etc/passwd",
                 "/facet/" + "L" * 300 + "/white.png", "/facet/%E5%BA%8F%E5%88%97/map.png",
                 "/facet/20261201T000000000-0a1b2c3d/white.png"]
        for path in paths:
            status, body = _raw_get(port, path)
            assert secret not in body and b"not for the page" not in body, path
            assert status in (400, 404), (path, status)
        status, body = _raw_get(port, "/api/state")
        assert status == 200 and json.loads(body)["station"]
    finally:
        stop_server(server)
