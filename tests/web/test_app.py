"""Issue 15: the page's server without a browser: a read-only page refuses every action, the settings are
validated with messages that say what to do, and the renderer escapes whatever a serial holds."""

from __future__ import annotations

import asyncio
import dataclasses
import json

import pytest

from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.live.operator_commands import commands_dir
from sofast_station.web.app import create_app
from sofast_station.web.render import last_html
from sofast_station.web.settings import WebSettings, opcua_settings, web_settings
from tests.web.serving import shift_started_hours_ago


def _call(app, method: str, path: str, headers: dict | None = None, body: bytes = b"") -> tuple[int, dict, bytes]:
    """One HTTP request straight into the ASGI application."""
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method, "path": path,
             "raw_path": path.encode(), "query_string": b"", "root_path": "", "scheme": "http",
             "headers": [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()],
             "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 8080)}
    messages, state = [], {"sent": False}

    async def receive():
        if not state["sent"]:
            state["sent"] = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.sleep(3600)

    async def send(message):
        messages.append(message)

    asyncio.run(app(scope, receive, send))
    start = messages[0]
    return (start["status"], {k.decode(): v.decode() for k, v in start["headers"]},
            b"".join(m.get("body", b"") for m in messages[1:]))


def test_a_page_without_token_is_read_only(small_station_toml):
    config = load_config(small_station_toml)
    app = create_app(config, WebSettings(token=""))
    status, headers, body = _call(app, "GET", "/")
    assert status == 200 and b"Read-only" in body and b"disabled" in body
    assert "script-src 'self'" in headers["content-security-policy"]
    for name in ("pause", "resume", "dump-next", "remeasure", "serial"):
        status, _, body = _call(app, "POST", f"/action/{name}", {"x-station-token": "anything-at-all"}, b"{}")
        assert status == 403 and "read-only" in json.loads(body)["error"]
    assert not commands_dir(config.data_dir).exists()
    assert not (config.data_dir / "dump-next").exists()


def test_actions_need_the_right_token(small_station_toml):
    config = load_config(small_station_toml)
    app = create_app(config, WebSettings(token="a-long-token"))
    assert _call(app, "POST", "/action/pause", {}, b"{}")[0] == 403
    assert _call(app, "POST", "/action/pause", {"x-station-token": "a-long-tokem"}, b"{}")[0] == 403
    status, _, body = _call(app, "POST", "/action/serial", {"x-station-token": "a-long-token"},
                            json.dumps({"serial": "X" * 65}).encode())
    assert status == 400 and "at most 64" in json.loads(body)["error"]
    assert _call(app, "POST", "/action/reboot", {"x-station-token": "a-long-token"}, b"{}")[0] == 404
    status, _, body = _call(app, "POST", "/action/pause", {"x-station-token": "a-long-token"}, b"{}")
    assert status == 200 and json.loads(body)["ok"]
    assert [json.loads(p.read_text())["command"] for p in commands_dir(config.data_dir).glob("*.json")] == ["pause"]


def test_settings_are_validated(small_station_toml):
    config = load_config(small_station_toml)
    assert web_settings(config) == WebSettings() and not opcua_settings(config).enabled

    def with_tables(**tables):
        return dataclasses.replace(config, raw={**config.raw, **tables})
    for table, match in [({"token": "short"}, r"\[web\] token = 'short': must be a string of at least 8"),
                         ({"port": 70000}, r"\[web\] port = 70000"),
                         ({"shift_starts": ["25:00"]}, r"shift_starts = \['25:00'\]"),
                         ({"colour": "red"}, r"\[web\] has unknown key\(s\) colour")]:
        with pytest.raises(ConfigError, match=match) as info:
            web_settings(with_tables(web=table))
        assert str(config.path) in str(info.value)
    with pytest.raises(ConfigError, match="anonymous = false but no users"):
        opcua_settings(with_tables(opcua={"enabled": True, "anonymous": False}))
    with pytest.raises(ConfigError, match=r"endpoint = 'http://x'"):
        opcua_settings(with_tables(opcua={"endpoint": "http://x"}))


def test_serials_are_rendered_as_text():
    for serial in ("<script>alert(1)</script>", "../../etc/passwd", "x' onerror='alert(1)", "序列🙂" * 100):
        html = last_html({"last": {"serial": serial, "verdict": "pass", "cycle_id": "20261201T000000000-0a1b2c3d",
                                   "reasons": [serial]}, "figures": [], "last_has_picture": True})
        assert "<script>" not in html and "onerror='" not in html
        assert html.count("&lt;script&gt;") in (0, 3) and "/facet/20261201T000000000-0a1b2c3d/white.png" in html


# --- issue 28: the page on the network -------------------------------------------------------------------

TOKEN = {"x-station-token": "a-long-token"}


def _make_tls_pair(folder, host="127.0.0.1", expired: bool = False):
    """A throwaway self-signed certificate and key for *host* (PEM files in *folder*; nothing committed); with
    *expired*, one that was valid for a year until yesterday."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, host)])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(days=366 if expired else 0, minutes=5))
            .not_valid_after(now + datetime.timedelta(days=-1 if expired else 30))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address(host))]), critical=False)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = folder / "page-cert.pem", folder / "page-key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path


def _with_web(config, **web):
    return dataclasses.replace(config, raw={**config.raw, "web": web})


def test_serving_beyond_this_computer_is_a_decision(small_station_toml, tmp_path):
    """Issue 28: host = "0.0.0.0" served actions over plain HTTP with no warning. Beyond loopback the
    station file must give HTTPS (certificate and key) or say allow_plain_http = true; either way the start
    says it is on the network."""
    config = load_config(small_station_toml)
    for host in ("0.0.0.0", "192.168.0.10", "station.plant.local", "::"):
        with pytest.raises(ConfigError, match=r"serves the page beyond this computer over plain HTTP.*certificate "
                                              r"and key .* allow_plain_http = true"):
            web_settings(_with_web(config, host=host, token="a-long-token"))
    for host in ("127.0.0.1", "127.0.1.1", "localhost", "::1"):
        assert web_settings(_with_web(config, host=host)).exposure() is None
    plain = web_settings(_with_web(config, host="0.0.0.0", token="a-long-token", allow_plain_http=True))
    assert "plain HTTP" in plain.exposure() and "clear text" in plain.exposure()
    assert "read-only" in web_settings(_with_web(config, host="0.0.0.0", allow_plain_http=True)).exposure()
    cert, key = _make_tls_pair(tmp_path)
    tls = web_settings(_with_web(config, host="0.0.0.0", token="a-long-token", certificate=str(cert), key=str(key)))
    assert tls.tls and "over HTTPS" in tls.exposure()
    with pytest.raises(ConfigError, match="give both certificate and key"):
        web_settings(_with_web(config, certificate=str(cert)))
    with pytest.raises(ConfigError, match="no such file"):
        web_settings(_with_web(config, certificate="nope.pem", key=str(key)))
    with pytest.raises(ConfigError, match="do not make a TLS server"):
        web_settings(_with_web(config, certificate=str(key), key=str(cert)))
    # `serve --host` is held to the same rule before anything listens (exit code 2, one line)
    from sofast_station.cli import main
    assert main(["serve", "--config", str(small_station_toml), "--host", "0.0.0.0"]) == 2


def test_a_body_beyond_the_limit_is_refused_before_it_is_read(small_station_toml):
    """Issue 28: a 200 MB body with the token took the monitor from 179 to 751 MB. A declared or streamed
    body beyond MAX_BODY_BYTES is answered 413 and nothing is queued."""
    from sofast_station.web.settings import MAX_BODY_BYTES

    config = load_config(small_station_toml)
    app = create_app(config, WebSettings(token="a-long-token"))
    big = json.dumps({"serial": "F-1", "pad": "x" * MAX_BODY_BYTES}).encode()
    status, _, body = _call(app, "POST", "/action/serial", {**TOKEN, "content-length": str(len(big))}, big)
    assert status == 413 and "larger than" in json.loads(body)["error"]
    status, _, _ = _call(app, "POST", "/action/serial", TOKEN, big)        # no length declared: read, then cut
    assert status == 413
    assert not commands_dir(config.data_dir).exists()
    small = json.dumps({"serial": "F-1"}).encode()
    assert _call(app, "POST", "/action/serial", {**TOKEN, "content-length": str(len(small))}, small)[0] == 200


def test_an_action_from_another_sites_page_is_refused(small_station_toml):
    """Issue 28: the Origin header was never checked. A page elsewhere that got hold of the token cannot
    make the operator's browser act; the page itself and tools without an Origin can."""
    config = load_config(small_station_toml)
    app = create_app(config, WebSettings(token="a-long-token"))
    host = {"host": "127.0.0.1:8080"}
    for other in ({"origin": "http://evil.example"}, {"origin": "null"}, {"origin": "https://127.0.0.1:8080"},
                  {"origin": "http://127.0.0.1:8080", "sec-fetch-site": "cross-site"}):
        status, _, body = _call(app, "POST", "/action/pause", {**TOKEN, **host, **other}, b"{}")
        assert status == 403 and "another site" in json.loads(body)["error"], other
    assert not commands_dir(config.data_dir).exists()
    assert _call(app, "POST", "/action/pause", {**TOKEN, **host, "origin": "http://127.0.0.1:8080",
                                                "sec-fetch-site": "same-origin"}, b"{}")[0] == 200
    assert _call(app, "POST", "/action/resume", {**TOKEN, **host}, b"{}")[0] == 200       # curl: no Origin


@pytest.mark.parametrize("body, kind, status, expected", [
    (json.dumps({"serial": ["A-1", "B-2"]}), "application/json", 400, "must be text"),
    (json.dumps({"serial": 12345}), "application/json", 400, "must be text"),
    (json.dumps(["F-123"]), "application/json", 400, "JSON object"),
    ("{not json", "application/json", 400, "not JSON"),
    (json.dumps({"serial": "F\x00123"}), "application/json", 400, "control characters"),
    ("serial=F-123", "application/x-www-form-urlencoded", 200, "F-123"),
    ("serial=MF%2F2024+001", "application/x-www-form-urlencoded", 200, "MF/2024 001"),
    ("<serial>F-1</serial>", "application/xml", 400, "not understood"),
])
def test_hostile_serials_through_the_page(small_station_toml, body, kind, status, expected):
    """Issue 28: the page answered {"serial": [..]} or a number with HTTP 500 and a traceback *and* queued
    the command; a form-encoded serial=F-123 said "the serial is empty". Now: 400 saying why and nothing
    queued, or the serial queued as typed (the loop makes it safe and keeps the original)."""
    config = load_config(small_station_toml)
    app = create_app(config, WebSettings(token="a-long-token"))
    got, _, reply = _call(app, "POST", "/action/serial", {**TOKEN, "content-type": kind}, body.encode())
    answer = json.loads(reply)
    assert got == status, answer
    queued = [json.loads(p.read_text()) for p in commands_dir(config.data_dir).glob("*.json")] \
        if commands_dir(config.data_dir).exists() else []
    if status == 200:
        assert answer["message"].endswith(expected) and [q["serial"] for q in queued] == [expected]
    else:
        assert expected in answer["error"] and queued == []


def test_the_page_is_served_over_https_with_its_certificate(small_station_toml, tmp_path):
    """`serve` with [web] certificate and key: uvicorn serves HTTPS (the URL says so), a client that trusts
    the certificate reads the page's state, and plain HTTP on that port gets no page."""
    import os
    import ssl
    import subprocess
    import sys
    import urllib.error
    import urllib.request

    from tests.conftest import ROOT

    cert, key = _make_tls_pair(tmp_path)
    small_station_toml.write_text(small_station_toml.read_text()
                                  + f'\n[web]\nport = 0\nnice = 0\ncertificate = "{cert}"\nkey = "{key}"\n')
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "serve", "--config", str(small_station_toml)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()
        assert line.startswith("the line's page: https://127.0.0.1:"), (line, proc.poll())
        url = line.split()[3]
        trusted = ssl.create_default_context(cafile=str(cert))
        with urllib.request.urlopen(url + "api/state", timeout=60, context=trusted) as r:
            assert json.loads(r.read())["station"].startswith("Small simulated")
        with pytest.raises((urllib.error.URLError, ConnectionError, OSError)):
            urllib.request.urlopen(url.replace("https://", "http://") + "api/state", timeout=30).read()
        with pytest.raises(urllib.error.URLError, match="CERTIFICATE_VERIFY_FAILED"):
            urllib.request.urlopen(url + "api/state", timeout=30, context=ssl.create_default_context())
    finally:
        proc.terminate()
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


def test_an_expired_certificate_is_served_with_a_warning(small_station_toml, tmp_path):
    """Issue 43: a certificate that expired yesterday was served without a word (the ssl module loads it; the
    operator's browser then refuses the page). `serve` still serves it, and says at the start that it expired,
    when and what to do; a certificate valid for 30 more days is not warned about, one of 10 days is."""
    import datetime
    import os
    import subprocess
    import sys

    from sofast_station.web.settings import certificate_dates
    from tests.conftest import ROOT

    cert, key = _make_tls_pair(tmp_path, expired=True)
    (warning,) = web_settings(_with_web(load_config(small_station_toml), certificate=str(cert), key=str(key))).warnings
    assert "expired on" in warning and "1 day ago" in warning and "make a new certificate" in warning
    (tmp_path / "good").mkdir()
    good, _ = _make_tls_pair(tmp_path / "good")
    now = datetime.datetime.now(datetime.timezone.utc)
    assert certificate_dates(str(good), "[web]", now) is None
    assert "in 10 days" in certificate_dates(str(good), "[web]", now + datetime.timedelta(days=19))
    small_station_toml.write_text(small_station_toml.read_text()
                                  + f'\n[web]\nport = 0\nnice = 0\ncertificate = "{cert}"\nkey = "{key}"\n')
    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "serve", "--config", str(small_station_toml)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
    try:
        line = proc.stdout.readline()                 # printed once the page is served, after the warnings
        assert line.startswith("the line's page: https://127.0.0.1:"), (line, proc.poll())
    finally:
        proc.terminate()
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate()
    (logged,) = [e for e in err.splitlines() if "expired on" in e]
    assert "WARNING" in logged and str(cert) in logged


# --- issue 29: what the page shows -------------------------------------------------------------------------

def _journal_records(data, records) -> None:
    from sofast_station.archive import Journal

    data.mkdir(parents=True, exist_ok=True)
    with Journal(data / "journal.sqlite3") as journal:
        for i, rec in enumerate(records):
            journal.append(f"20261203T0000{i:05d}0-{i:08x}", rec)


def _facet(i: int, verdict: str, recipe: str = "default", **figures) -> dict:
    import datetime

    from tests.report.test_quality_reports import SAMPLE

    rec = json.loads(json.dumps(SAMPLE))
    rec.update(serial=f"F-{i:04d}", verdict=verdict, recipe=recipe, cycle_id=f"c{i}",
               time=(datetime.datetime.now().astimezone() - datetime.timedelta(seconds=60 - i)).isoformat(),
               **{k: v for k, v in figures.items() if k != "rms"})
    if "rms" in figures:
        rec["slope_rms_mrad"]["design"]["magnitude"] = figures["rms"]
    rec.setdefault("timings_s", {})["until_journal"] = 1.0 + 0.01 * i
    return rec


def test_indeterminate_facets_are_counted_on_the_page(small_station_toml):
    """Two indeterminate facets showed "2 facets" and 0 in every class, yield 0 %."""
    from sofast_station.web.data import LineData
    from sofast_station.web.opcua import values
    from sofast_station.web.render import shift_html

    config = load_config(small_station_toml)
    _journal_records(config.data_dir, [_facet(1, "indeterminate"), _facet(2, "indeterminate"), _facet(3, "pass")])
    snap = LineData(config, WebSettings(shift_starts=(shift_started_hours_ago(),))).snapshot()
    html = shift_html(snap)
    assert "<b class='indeterminate-t'>2</b><span>indeterminate</span>" in html, html
    assert "<b class='pass-t'>1</b><span>pass</span>" in html and "33.3 %" in html
    assert values(snap)["Counters/Indeterminate"] == 2


def test_the_charts_draw_the_limits_of_the_last_facets_recipe(small_station_toml):
    """A facet failing a 0.7 mrad recipe limit was drawn far below the default recipe's 3 mrad line."""
    from sofast_station.web.data import LineData
    from sofast_station.web.render import shift_html

    small_station_toml.write_text(small_station_toml.read_text() + '\n[recipes.strict]\nserial_pattern = "^S-"\n'
                                  'limits = { max_slope_rms_mrad = { design = 0.7, parabola = 0.6 } }\n')
    config = load_config(small_station_toml)
    facets = [_facet(i, "pass", rms=0.5 + 0.01 * i) for i in range(5)]
    facets += [_facet(10 + i, "fail" if i == 3 else "pass", "strict", rms=0.6 + 0.04 * i) for i in range(4)]
    _journal_records(config.data_dir, facets)
    snap = LineData(config, WebSettings(shift_starts=(shift_started_hours_ago(),))).snapshot()
    chart = snap["chart"]
    assert chart["recipe"] == "strict" and len(chart["serials"]) == 4       # the last facet's recipe only
    rms = chart["panels"][1]
    assert [lim for lim in rms["limits"] if lim[2] == "limit vs design"][0][0] == 0.7
    html = shift_html(snap)
    assert "Recipe strict" in html and "limit vs design 0.700" in html      # drawn: 0.72 failed it
    assert "3.000" not in html
    # readable axes: round ticks between the data and the limits, not only at the limits
    svg = html[html.index("slope error RMS"):]
    ticks = [t for t in ("0.60", "0.65", "0.70", "0.75") if f">{t}</text>" in svg]
    assert len(ticks) >= 3, svg


def test_a_limit_far_from_the_data_is_named_not_drawn():
    from sofast_station.web.render import svg_chart

    svg = svg_chart("slope error RMS (mrad)", [("vs design", [0.50, 0.52, 0.51], "#fff")],
                    [(3.0, "#f00", "limit vs design")], decimals=3, unit="mrad")
    assert "limit vs design 3.000" not in svg and "beyond the view: limit vs design 3 mrad ↑" in svg
    assert ">0.50<" in svg or ">0.500<" in svg


def test_the_page_has_an_icon(small_station_toml):
    config = load_config(small_station_toml)
    app = create_app(config, WebSettings())
    for path in ("/favicon.ico", "/favicon.svg"):
        status, headers, body = _call(app, "GET", path)
        assert status == 200 and headers["content-type"].startswith("image/svg+xml") and b"<svg" in body


def test_the_page_names_the_records_the_running_line_uses_and_a_newer_one_as_waiting(small_station_toml):
    """Issue 43, item 4: while the line runs, the page shows the records it loaded (its live status), not the
    newest on disk; a radiometric record written since is named as waiting for the next start."""
    import datetime
    import os
    import shutil

    from sofast_station.calibrate.store import record_dir
    from sofast_station.live.status import StatusFile
    from sofast_station.web.data import LineData
    from sofast_station.web.render import station_html
    from tests.conftest import ROOT

    config = load_config(small_station_toml)
    made = (datetime.datetime.now().astimezone() - datetime.timedelta(hours=2)).isoformat(timespec="seconds")
    status = StatusFile(config.data_dir)
    status.update(state="idle", pid=os.getpid(), in_force={"radiometric": "radiometric-20261206T040000Z-001",
                                                            "radiometric_created": made, "origin": "data_dir",
                                                            "screen": "screen-20261205T120000Z-001"})
    folder = record_dir(config.data_dir, "radiometric")
    folder.mkdir(parents=True)
    newer = json.loads((ROOT / "calibration/simulated_radiometric.json").read_text())
    newer["record_id"] = "radiometric-20261206T070000Z-001"
    (folder / "radiometric-20261206T070000Z-001.json").write_text(json.dumps(newer))
    try:
        snap = LineData(config, WebSettings(shift_starts=(shift_started_hours_ago(),))).snapshot()
    finally:
        status.close()
        shutil.rmtree(folder)
    cal = snap["calibration"]
    assert cal["record"] == "radiometric-20261206T040000Z-001" and cal["newer"] == "radiometric-20261206T070000Z-001"
    assert cal["others"] == {"screen": "screen-20261205T120000Z-001"} and 1.9 < cal["age_h"] < 2.1
    html = station_html(snap)
    assert "radiometric record radiometric-20261206T040000Z-001" in html and "screen record screen-2026" in html
    assert "a newer radiometric record radiometric-20261206T070000Z-001 waits" in html
