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
