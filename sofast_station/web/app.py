"""The line's web page: a Starlette application (ASGI, served by uvicorn).

Routes
------
``GET /``                           the page (server-rendered; works without script, updates with it)
``GET /events``                     server-sent events: the page's sections again whenever the journal,
                                    the live status or the last facet's pictures change (polled every 0.25 s)
``GET /api/state``                  the same facts as JSON, for tools
``GET /facet/{cycle_id}/white.png`` the white frame with the found outline
``GET /facet/{cycle_id}/map.png``   the slope-error map
``GET /facet/{cycle_id}/facets.png`` a heliostat's facets and their canting errors
``POST /action/{name}``             a guarded action (``dump-next``, ``pause``, ``resume``, ``remeasure``,
                                    ``serial`` with ``{"serial": ...}`` as JSON or ``serial=...`` as a form);
                                    needs the ``X-Station-Token`` header equal to ``[web] token``; refused
                                    (403) when none is configured, or when the request comes from another
                                    site's page (its ``Origin`` is not the page's own)

No file is served by path: pictures are found by cycle id (a fixed pattern) under
``data_dir/live/facets``, and the page's style and script are constants of this module. No request body
larger than :data:`~.settings.MAX_BODY_BYTES` is read (413). Serving beyond this computer (HTTPS, or plain
HTTP by decision) is ``[web]``'s business: docs/network.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import logging
import time
import urllib.parse

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Route

from ..errors import CommandError
from ..live.operator_commands import COMMANDS, check_manual_serial, post_command
from .data import LineData
from .images import FacetImages
from .render import esc, sections
from .settings import MAX_BODY_BYTES

log = logging.getLogger(__name__)

POLL_S = 0.25
_SECURITY_HEADERS = [
    (b"content-security-policy", b"default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; "
                                 b"connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
]


class _SecurityHeaders:
    """Adds the security headers to every response (pure ASGI: streams pass through untouched)."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                message = dict(message)
                message["headers"] = list(message.get("headers", [])) + _SECURITY_HEADERS
            await send(message)
        return await self.app(scope, receive, send_with_headers)


class _BodyLimit:
    """Refuses a request body larger than *limit* bytes with 413 before the application reads it (pure ASGI).

    A declared ``content-length`` beyond the limit is refused at once; a body sent without one (chunked) is
    read here up to the limit and handed on only when it stayed within it. A 200 MB body took the monitor
    from 179 to 751 MB before.
    """

    def __init__(self, app, limit: int):
        self.app = app
        self.limit = int(limit)

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        try:
            too_big = declared is not None and int(declared) > self.limit
        except ValueError:
            too_big = True
        if too_big:
            return await self._refuse(send)
        if scope.get("method") in ("GET", "HEAD"):
            return await self.app(scope, receive, send)
        body, more = bytearray(), True
        while more:
            message = await receive()
            if message["type"] != "http.request":
                return                                  # the client went away
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > self.limit:
                return await self._refuse(send)
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()
        return await self.app(scope, replay, send)

    async def _refuse(self, send) -> None:
        text = json.dumps({"ok": False, "error": f"the request body is larger than {self.limit} bytes: an action "
                                                 "carries a few dozen"}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(text)).encode()),
                                (b"connection", b"close"), *_SECURITY_HEADERS]})
        await send({"type": "http.response.body", "body": text})


def _with_now(payload: str) -> str:
    """The sections' JSON *payload* with the monitor's clock now (``_now``, seconds since 1970) added."""
    now = f'"_now": {time.time():.3f}'
    return "{" + now + ("}" if payload.strip() == "{}" else ", " + payload.lstrip()[1:])


def _same_origin(request: Request) -> bool:
    """Whether an action comes from the page itself (or from a tool that sends no ``Origin``): a browser
    names the page that sends a request in ``Origin`` (and, today, ``Sec-Fetch-Site``); an action from
    another site's page is refused even when it carries the token."""
    if request.headers.get("sec-fetch-site", "same-origin") not in ("same-origin", "none"):
        return False
    origin = request.headers.get("origin")
    if origin is None:
        return True
    host = request.headers.get("host", "")
    return bool(host) and origin.lower() == f"{request.url.scheme}://{host}".lower()


async def _serial_of(request: Request):
    """The ``serial`` of an action's body: JSON ``{"serial": ...}`` or a form ``serial=...``; None when the
    body holds none. CommandError when the body is neither."""
    body = await request.body()
    kind = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if kind == "application/x-www-form-urlencoded":
        try:
            values = urllib.parse.parse_qs(body.decode("utf-8"), strict_parsing=bool(body), max_num_fields=10)
        except (UnicodeDecodeError, ValueError):
            raise CommandError("the form could not be read: send serial=THE-SERIAL (URL-encoded UTF-8)") from None
        return values.get("serial", [None])[0]
    if kind not in ("", "application/json", "text/plain"):
        raise CommandError(f"a {kind} body is not understood: send JSON {{\"serial\": \"F-123\"}} or the form "
                           "serial=F-123")
    if not body.strip():
        return None
    try:
        data = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        raise CommandError("the body is not JSON: send {\"serial\": \"F-123\"} (or the form serial=F-123)") from None
    if not isinstance(data, dict):
        raise CommandError(f"the body must be a JSON object such as {{\"serial\": \"F-123\"}}, not "
                           f"{type(data).__name__}")
    return data.get("serial")


class Hub:
    """Polls the station's files and keeps the page's sections of the newest state for every client."""

    def __init__(self, data: LineData):
        self.data = data
        self.version = None
        self.counter = 0
        self.payload = "{}"
        self.snapshot: dict | None = None
        self.stopping = False
        self._lock = asyncio.Lock()

    def _compute(self) -> tuple:
        version = self.data.version()
        if version == self.version and self.snapshot is not None:
            return version, None, None
        snap = self.data.snapshot()
        payload = sections(snap)
        payload["_seq"] = version[0] or 0
        payload["_cycle"] = (snap.get("last") or {}).get("cycle_id", "")
        return version, snap, json.dumps(payload)

    async def refresh(self) -> None:
        async with self._lock:
            version, snap, payload = await asyncio.to_thread(self._compute)
            if snap is not None:
                self.version, self.snapshot, self.payload = version, snap, payload
                self.counter += 1

    async def run(self) -> None:
        while not self.stopping:
            try:
                await self.refresh()
            except Exception:
                log.exception("reading the station's state failed; trying again")
            await asyncio.sleep(POLL_S)


def create_app(config, settings) -> Starlette:
    """The page's application for the station of *config* (a StationConfig) with ``[web]`` *settings*."""
    data = LineData(config, settings)
    hub = Hub(data)
    images = FacetImages(config.data_dir, config=config)
    tasks: list = []

    async def page(request: Request) -> Response:
        await hub.refresh()
        snap = hub.snapshot
        parts = sections(snap)
        return HTMLResponse(_PAGE.format(name=esc(config.name), seq=esc(hub.version[0] or 0), now=f"{time.time():.3f}",
                                         cycle=esc((snap.get("last") or {}).get("cycle_id", "")),
                                         actions=_actions_html(settings), **parts),
                            headers={"cache-control": "no-store"})

    async def events(request: Request) -> Response:
        async def stream():
            yield "retry: 1000\n\n"
            seen = -1
            idle = 0.0
            while not hub.stopping:
                if hub.counter != seen:
                    seen = hub.counter
                    # the monitor's clock now, for the verdict's age (the payload was made when it changed)
                    yield f"event: sections\ndata: {_with_now(hub.payload)}\n\n"
                    idle = 0.0
                elif idle > 15:
                    yield f"event: clock\ndata: {time.time():.3f}\n\n"
                    idle = 0.0
                if await request.is_disconnected():
                    break
                await asyncio.sleep(POLL_S / 2)
                idle += POLL_S / 2
            if hub.stopping:
                # a normal end: the page says the monitor stopped instead of "reconnecting…", and this
                # response ends now, so the server's shutdown has nothing to cancel
                yield "event: end\ndata: the monitor stopped\n\n"
        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"cache-control": "no-store", "x-accel-buffering": "no"})

    async def state(request: Request) -> Response:
        await hub.refresh()
        snap = hub.snapshot
        last = snap.get("last") or {}
        s = snap["summary"]
        return JSONResponse({"station": config.name, "state": snap["status"].get("state"), "seq": hub.version[0],
                             "last": {k: last.get(k) for k in ("cycle_id", "serial", "recipe", "verdict", "reasons",
                                                               "time")},
                             "shift": {"start": snap["shift_start"], "counts": s.counts, "total": s.total,
                                       "yield": s.yield_fraction, "cycle_median_s": s.cycle_median_s,
                                       "cycle_worst_s": s.cycle_worst_s, "faults_by_kind": s.faults_by_kind},
                             "alarms": [{"kind": k, "text": t} for k, t in snap["alarms"]],
                             "calibration": snap["calibration"], "disk": snap["disk"],
                             "actions_enabled": bool(settings.token)}, headers={"cache-control": "no-store"})

    async def picture(request: Request) -> Response:
        cycle_id, kind = request.path_params["cycle_id"], request.path_params["kind"]
        png = await asyncio.to_thread(images.get, cycle_id, kind)
        if png is None:
            return Response("no such picture", status_code=404, media_type="text/plain",
                            headers={"cache-control": "no-store"})
        return Response(png, media_type="image/png", headers={"cache-control": "max-age=3600"})

    async def action(request: Request) -> Response:
        name = request.path_params["name"]
        if not settings.token:
            return JSONResponse({"ok": False, "error": "this page is read-only: set [web] token in station.toml to "
                                 "allow actions"}, status_code=403)
        given = request.headers.get("x-station-token", "")
        if not hmac.compare_digest(given.encode("utf-8"), settings.token.encode("utf-8")):
            log.warning("refused action %r from %s: %s token", name[:40], request.client.host if request.client
                        else "?", "wrong" if given else "no")
            return JSONResponse({"ok": False, "error": "wrong or missing token"}, status_code=403)
        if not _same_origin(request):
            log.warning("refused action %r from %s: sent by another site's page (Origin %r)", name[:40],
                        request.client.host if request.client else "?", request.headers.get("origin", "")[:100])
            return JSONResponse({"ok": False, "error": "refused: the action was sent by another site's page"},
                                status_code=403)
        if name not in COMMANDS:
            return JSONResponse({"ok": False, "error": f"unknown action; known: {', '.join(COMMANDS)}"},
                                status_code=404)
        serial = None
        try:
            if name == "serial":
                serial = check_manual_serial(await _serial_of(request))
            post_command(config.data_dir, name, serial,
                         source=f"web page from {request.client.host if request.client else '?'}")
        except CommandError as exc:
            return JSONResponse({"ok": False, "error": str(exc)}, status_code=400)
        return JSONResponse({"ok": True, "message": _DONE[name] + (f" {serial}" if serial else "")})

    async def static(request: Request) -> Response:
        name = request.url.path.rsplit("/", 1)[-1]
        body, kind = _STATIC[name]
        return Response(body, media_type=kind, headers={"cache-control": "max-age=60"})

    @contextlib.asynccontextmanager
    async def lifespan(app):
        tasks.append(asyncio.create_task(hub.run()))
        # the pictures' imports (OpenCV, the colour table) now, not inside the first facet's picture request
        tasks.append(asyncio.create_task(asyncio.to_thread(images.warm)))
        try:
            yield
        finally:
            hub.stopping = True
            for t in tasks:
                t.cancel()
            data.close()

    routes = [Route("/", page), Route("/events", events), Route("/api/state", state),
              Route("/facet/{cycle_id}/{kind}.png", picture), Route("/action/{name}", action, methods=["POST"]),
              Route("/page.css", static), Route("/page.js", static), Route("/favicon.svg", static),
              Route("/favicon.ico", static)]
    app = Starlette(routes=routes, lifespan=lifespan)
    app.state.hub = hub
    wrapped = _SecurityHeaders(_BodyLimit(app, MAX_BODY_BYTES))
    wrapped.hub = hub                  # the monitor ends the event streams before it stops the server
    return wrapped


_DONE = {"dump-next": "the next facet will be dumped", "pause": "the line pauses after the facet in progress",
         "resume": "the line takes facets again", "remeasure": "the facet in the fixture will be measured again",
         "serial": "the next facet gets the serial"}


def _actions_html(settings) -> str:
    if not settings.token:
        note = ("<p class='muted'>Read-only: actions need a token (<code>[web] token</code> in station.toml).</p>")
        disabled = " disabled"
    else:
        note = "<p class='muted'>Actions need the station's token.</p>"
        disabled = ""
    return (f"<h2>Actions</h2>{note}<div class='actions'>"
            f"<input id='token' type='password' placeholder='token' autocomplete='off'{disabled}>"
            f"<button data-action='dump-next'{disabled}>Dump next facet</button>"
            f"<button data-action='pause'{disabled}>Pause line</button>"
            f"<button data-action='resume'{disabled}>Resume line</button>"
            f"<button data-action='remeasure'{disabled}>Re-measure facet in fixture</button>"
            f"<input id='serial-input' maxlength='64' placeholder='serial by hand'{disabled}>"
            f"<button data-action='serial'{disabled}>Use serial</button></div>"
            f"<p id='action-result' role='status'></p>")


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>{name}: the line</title><link rel="icon" href="/favicon.svg" type="image/svg+xml">
<link rel="stylesheet" href="/page.css"><script src="/page.js" defer></script>
</head><body data-seq="{seq}" data-cycle="{cycle}" data-now="{now}">
<header><h1>{name}</h1><div id="state">{state}</div><div id="link" class="link">live</div></header>
<main><section id="last">{last}</section>
<div class="side"><section id="shift">{shift}</section><section id="station">{station}</section>
<section id="actions">{actions}</section></div></main></body></html>
"""

_CSS = """
:root { color-scheme: dark; }
body { margin: 0; font: 16px/1.35 system-ui, sans-serif; background: #111827; color: #e5e7eb; }
header { display: flex; gap: 1.5rem; align-items: center; padding: .5rem 1rem; background: #030712; }
header h1 { font-size: 1.3rem; margin: 0; flex: 1; min-width: 0; overflow-wrap: anywhere; }
main { display: grid; grid-template-columns: minmax(0, 1.1fr) minmax(0, 1fr); gap: 1rem; padding: 1rem; }
section { background: #1f2937; border-radius: 8px; padding: .6rem 1rem; margin-bottom: 1rem; }
h2 { margin: .2rem 0 .6rem; font-size: 1.2rem; } h3 { margin: .6rem 0 .3rem; font-size: 1rem; }
.muted { color: #9ca3af; font-weight: normal; font-size: .9rem; }
.serial { font-size: 2.6rem; font-weight: 700; overflow-wrap: anywhere; max-height: 7.5rem; overflow: hidden; }
.meta { color: #9ca3af; overflow-wrap: anywhere; }
/* The verdict: one box of a fixed height whatever the word; the word's size follows the box's width
   (container units; the page's script then shrinks it further if a font runs wider), never cut. */
.verdict-box { container-type: inline-size; margin: .6rem 0 .2rem; }
.verdict { display: flex; align-items: center; justify-content: center; height: clamp(4.5rem, 24cqi, 11rem);
  font-weight: 900; line-height: 1; border-radius: 10px; letter-spacing: .04em; white-space: nowrap;
  overflow: hidden; font-size: min(9rem, 24cqi); }
.verdict .word { display: inline-block; }
.verdict[data-verdict="fault"] { font-size: min(9rem, 19cqi); }
.verdict[data-verdict="invalid"] { font-size: min(9rem, 14cqi); }
.verdict[data-verdict="indeterminate"] { font-size: min(9rem, 8cqi); }
.verdict.pass { background: #15803d; color: #fff; } .verdict.fail { background: #b91c1c; color: #fff; }
.verdict.invalid { background: #d97706; color: #111; } .verdict.fault { background: #7e22ce; color: #fff; }
.verdict.indeterminate { background: #0e7490; color: #fff; }
/* Not live (the station offline, the verdict old, the page cut off): no verdict colour. */
.verdict.stale { background: #374151; color: #9ca3af; outline: 3px dashed #6b7280; outline-offset: -6px; }
.verdict-age { margin: 0 0 .6rem; font-size: 1.1rem; color: #9ca3af; }
.verdict-age.stale { color: #fbbf24; font-weight: 700; }
.pass-t { color: #4ade80; } .fail-t { color: #f87171; } .invalid-t { color: #fbbf24; } .fault-t { color: #c084fc; }
.indeterminate-t { color: #22d3ee; }
.reasons li { font-size: 1.25rem; margin: .2rem 0; overflow-wrap: anywhere; }
table { border-collapse: collapse; width: 100%; } th, td { text-align: left; padding: .2rem .4rem; }
.figures td, .figures th { font-size: 1.15rem; border-bottom: 1px solid #374151; }
td.num { text-align: right; font-variant-numeric: tabular-nums; } td.lim { color: #9ca3af; }
tr.out td, tr.out th { color: #f87171; } .ok { color: #4ade80; } .bad { color: #f87171; font-weight: 700; }
.pictures { display: flex; gap: 1rem; } figure { margin: .5rem 0; flex: 1 1 0; min-width: 0; }
figure img { width: 100%; max-height: 420px; object-fit: contain; background: #000; border-radius: 4px; }
figcaption { color: #9ca3af; font-size: .85rem; }
.kpis { display: flex; gap: 1.2rem; flex-wrap: wrap; } .kpis div { display: flex; flex-direction: column; }
.kpis b { font-size: 2.2rem; } .kpis span { color: #9ca3af; font-size: .85rem; }
.charts svg { width: 100%; height: auto; background: #111827; border-radius: 6px; margin-top: .4rem; }
.chart .ct { fill: #e5e7eb; font-size: 13px; } .chart .cl { fill: #9ca3af; font-size: 11px; }
.chart .lg { font-size: 12px; }
.chart .frame { fill: none; stroke: #374151; } .chart .grid { stroke: #2b3544; stroke-width: 1; }
.badge { padding: .15rem .7rem; border-radius: 999px; font-weight: 700; text-transform: uppercase; }
.state-idle { background: #374151; } .state-measuring { background: #1d4ed8; } .state-fault { background: #7e22ce; }
.state-paused { background: #d97706; color: #111; } .state-offline { background: #000; color: #f87171; }
.alarms li { color: #fbbf24; overflow-wrap: anywhere; }
.link { font-size: .85rem; color: #4ade80; } .link.down { color: #f87171; }
.actions { display: flex; flex-wrap: wrap; gap: .4rem; }
.actions button, .actions input { font-size: 1rem; padding: .4rem .6rem; }
#action-result.error { color: #f87171; }
@media (max-width: 1000px) { main { grid-template-columns: 1fr; } }
"""

_JS = """
"use strict";
const shown = {};
// The monitor's clock (seconds since 1970) when its last message came, and this page's clock then: the
// verdict's age is reckoned on the station computer's clock, whatever the panel's own clock says.
let clock = {server: NaN, at: 0};
let connection = "up";       // up | down (reconnecting) | ended (the monitor stopped)
function serverNow() { return clock.server + (performance.now() - clock.at) / 1000; }
function setClock(seconds) { if (Number.isFinite(seconds)) clock = {server: seconds, at: performance.now()}; }
function put(sections) {
  setClock(sections._now);
  for (const [id, html] of Object.entries(sections)) {
    if (id.startsWith("_") || shown[id] === html) continue;   // unchanged: no re-layout, no image reload
    const el = document.getElementById(id);
    if (el) { el.innerHTML = html; shown[id] = html; }
  }
  document.body.dataset.seq = sections._seq;
  document.body.dataset.cycle = sections._cycle;
  freshness();
}
function ageText(s) {
  if (!Number.isFinite(s)) return "age unknown";
  if (s < 90) return Math.round(s) + " s ago";
  if (s < 5400) return Math.round(s / 60) + " min ago";
  if (s < 172800) return (s / 3600).toFixed(1) + " h ago";
  return (s / 86400).toFixed(1) + " days ago";
}
// The verdict word as large as its box allows, never cut (fonts differ from panel to panel).
function fit(box) {
  const word = box.querySelector(".word");
  if (!word) return;
  box.style.fontSize = "";
  const room = box.clientWidth * 0.94, wide = word.getBoundingClientRect().width;
  if (wide > room && wide > 0) {
    box.style.fontSize = (parseFloat(getComputedStyle(box).fontSize) * room / wide) + "px";
  }
}
// Grey the verdict (no verdict colour) and say why when it is not live; show its age.
function freshness() {
  const badge = document.querySelector("#state [data-state]");
  const offline = badge !== null && badge.dataset.state === "offline";
  if (connection === "up") {                  // "live" only while the station itself runs
    const el = document.getElementById("link");
    el.textContent = offline ? "connected · station offline" : "live";
    el.classList.toggle("down", offline);
  }
  const box = document.getElementById("verdict"), line = document.getElementById("verdict-age");
  if (!box || !line) return;
  const age = serverNow() - parseFloat(box.dataset.timeS);
  const limit = parseFloat(box.dataset.staleAfterS);
  let why = "";
  if (connection !== "up") why = connection === "ended" ? "the monitor has stopped" : "the page has lost the monitor";
  else if (offline) why = "the station is offline";
  else if (age > limit) why = "no facet for more than " + limit + " s";
  box.classList.toggle("stale", why !== "");
  line.classList.toggle("stale", why !== "");
  line.textContent = "measured " + ageText(age) + (why ? " · not live: " + why : "");
  document.body.dataset.stale = why ? "1" : "0";
  if (box.dataset.fitted !== String(box.clientWidth)) { fit(box); box.dataset.fitted = String(box.clientWidth); }
}
function link(state) {
  connection = state;
  const el = document.getElementById("link");
  el.textContent = {up: "live", down: "reconnecting…",
                    ended: "monitor stopped; the page reconnects when it is back"}[state];
  el.classList.toggle("down", state !== "up");
  document.body.dataset.live = state === "up" ? "1" : "0";
  freshness();
}
function connect() {
  const es = new EventSource("/events");
  es.addEventListener("sections", ev => { put(JSON.parse(ev.data)); link("up"); });
  es.addEventListener("clock", ev => setClock(parseFloat(ev.data)));
  // a normal end of the monitor (the station's run ended): no alarm, a quiet retry every 5 s
  es.addEventListener("end", () => { es.close(); link("ended"); setTimeout(connect, 5000); });
  es.onopen = () => link("up");
  es.onerror = () => {
    if (connection !== "ended") link("down");
    if (es.readyState === EventSource.CLOSED) { es.close(); setTimeout(connect, connection === "ended" ? 5000 : 1000); }
  };
}
async function act(name) {
  const out = document.getElementById("action-result");
  const token = document.getElementById("token").value;
  const body = name === "serial" ? JSON.stringify({serial: document.getElementById("serial-input").value}) : "{}";
  try {
    const r = await fetch("/action/" + name, {method: "POST", body,
      headers: {"content-type": "application/json", "x-station-token": token}});
    const j = await r.json();
    out.textContent = j.ok ? j.message : ("refused: " + j.error);
    out.className = j.ok ? "" : "error";
  } catch (e) { out.textContent = "the station did not answer: " + e; out.className = "error"; }
}
document.addEventListener("DOMContentLoaded", () => {
  setClock(parseFloat(document.body.dataset.now));
  for (const b of document.querySelectorAll("button[data-action]")) {
    b.addEventListener("click", () => act(b.dataset.action));
  }
  window.addEventListener("resize", () => {
    const v = document.getElementById("verdict");
    if (v) v.dataset.fitted = "";
    freshness();
  });
  setInterval(freshness, 1000);
  freshness();
  connect();
});
"""

#: The page's icon (a mirror facet and a reflected ray), so the browser's request for one finds it.
_ICON = """<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 32 32"><rect width="32" height="32" rx="6"
fill="#111827"/><path d="M5 24 Q16 16 27 24" fill="none" stroke="#93c5fd" stroke-width="3"/><path d="M16 4 L16 19
L25 7" fill="none" stroke="#fbbf24" stroke-width="2"/></svg>"""

_STATIC = {"page.css": (_CSS, "text/css"), "page.js": (_JS, "text/javascript"),
           "favicon.svg": (_ICON, "image/svg+xml"), "favicon.ico": (_ICON, "image/svg+xml")}
