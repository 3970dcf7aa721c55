"""The monitor: the line's web page and the OPC UA server, in a process of their own.

``sofast-station serve`` runs it in the foreground; ``sofast-station run --serve`` (or ``[opcua] enabled``)
starts it beside the loop with :class:`MonitorProcess`. Either way it runs at a lower priority than the
station (``[web] nice``) and shares nothing with the loop but files: it reads the journal through a
read-only SQLite connection, the live status and the pictures, and posts commands as files
(live/operator_commands.py). A slow browser, a hung OPC UA client or a crash here cannot delay a facet.

Where it listens is written to ``data_dir/live/monitor.json`` (``{"url": ..., "opcua": ...}``), so a
port chosen by the system (``port = 0``) can be found.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import multiprocessing
import os
import signal
import socket
from pathlib import Path

from ..errors import StationError
from ..files import write_file_atomic
from ..live.logs import setup_logging
from .settings import OpcUaSettings, WebSettings

log = logging.getLogger(__name__)


#: The longest the monitor takes to stop its servers once asked (the page's event streams, uvicorn, OPC UA,
#: their tasks), seconds: well within :meth:`MonitorProcess.stop`'s wait, so a stop is clean unless the
#: machine gives the monitor no processor at all.
STOP_BUDGET_S = 6.0


def monitor_info_path(data_dir) -> Path:
    return Path(data_dir) / "live" / "monitor.json"


def _lower_priority(nice: int) -> None:
    try:
        if nice:
            os.nice(nice)
    except OSError as exc:
        log.warning("could not lower the monitor's priority: %s", exc)


def _bind(host: str, port: int) -> socket.socket:
    """A listening socket on *host*:*port*; StationError saying what to do when that is impossible."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(family, kind, proto)
    except (OSError, IndexError) as exc:
        raise StationError(f"cannot serve the page on {host}:{port}: {exc}; set [web] host to an address of "
                           "this computer (127.0.0.1 by default)") from None
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(64)
    except OSError as exc:
        sock.close()
        raise StationError(f"cannot serve the page on {host}:{port}: {exc.strerror or exc}; is another "
                           "'sofast-station serve' running? Set [web] port (or --port) to a free port") from None
    return sock


def _server_class():
    # lazy: uvicorn, starlette cost ~490 ms CPU; the station's process imports this module only to start the monitor
    import uvicorn

    class Server(uvicorn.Server):
        """uvicorn's server without its own signal handling: the monitor's handlers stop both servers."""

        @contextlib.contextmanager
        def capture_signals(self):
            yield
    return Server


async def _serve(config, web: WebSettings | None, opcua: OpcUaSettings | None, on_ready=None) -> None:
    # lazy: uvicorn, starlette cost ~490 ms CPU; the station's process imports this module only to start the monitor
    import uvicorn

    _Server = _server_class()

    # lazy: uvicorn, starlette cost ~490 ms CPU; the station's process imports this module only to start the monitor
    from .app import create_app
    from .data import LineData

    info: dict = {"pid": os.getpid()}
    server = None
    tasks = []
    if web is not None:
        exposure = web.exposure()                    # ConfigError beyond loopback without a decision
        app = create_app(config, web)
        tls = {"ssl_certfile": web.certificate, "ssl_keyfile": web.key} if web.tls else {}
        server = _Server(uvicorn.Config(app, host=web.host, port=web.port, log_level="warning",
                                        timeout_graceful_shutdown=5, lifespan="on", access_log=False, **tls))
        sock = _bind(web.host, web.port)             # here, so a taken port is a clear error, not an exit
        tasks.append(asyncio.create_task(server.serve(sockets=[sock])))
        while not server.started:
            if tasks[0].done():
                await tasks[0]
                raise StationError(f"the page's server on {web.host}:{web.port} stopped as it started; see the log")
            await asyncio.sleep(0.05)
        host, port = server.servers[0].sockets[0].getsockname()[:2]
        shown = f"[{host}]" if ":" in host else host
        info["url"] = f"{'https' if web.tls else 'http'}://{shown}:{port}/"
        log.info("the line's page: %s%s", info["url"], "" if web.token else " (read-only: no [web] token)")
        if exposure:
            log.warning("%s", exposure)
        for warning in web.warnings:                 # the certificate expired, or about to
            log.warning("%s", warning)
    publisher = None
    if opcua is not None and opcua.enabled:
        # lazy: ~95 ms CPU, only with [opcua] enabled (asyncua, optional, loads when it starts)
        from .opcua import OpcUaPublisher
        publisher = OpcUaPublisher(LineData(config, web or WebSettings()), opcua)
        try:
            await publisher.start()
        except OSError as exc:
            if server is not None:
                server.should_exit = True
                await tasks[0]
            raise StationError(f"cannot start the OPC UA server at {opcua.endpoint}: {exc}; set [opcua] endpoint "
                               "in the station file") from None
        info["opcua"] = publisher.endpoint
        for warning in opcua.warnings:
            log.warning("%s", warning)
        tasks.append(asyncio.create_task(publisher.run()))
    # The stop handlers before monitor.json: whoever sees the file may stop the monitor at once (a SIGTERM
    # before them ends it abruptly, and a stopped, starved one could not be told from a dead one).
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    path = monitor_info_path(config.data_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(info)
    write_file_atomic(path, lambda fh: fh.write(text), mode="w")
    if on_ready is not None:
        on_ready(info)
    try:
        waiter = asyncio.create_task(stop.wait())
        await asyncio.wait([waiter, *tasks], return_when=asyncio.FIRST_COMPLETED)
    finally:
        await shut_down(app.hub if server is not None else None, server, publisher, tasks)


async def shut_down(hub, server, publisher, tasks: list, budget_s: float = STOP_BUDGET_S) -> None:
    """Stop the page's server and the OPC UA server within *budget_s* seconds in all: what has not ended by
    then is cancelled (it was: the stream's grace, then the OPC UA server, then 5 s per task, one after the
    other, which a starved monitor did not finish within the station's 10 s wait)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + budget_s
    if server is not None:
        # End the pages' event streams first (each says "the monitor stopped" and closes), then stop the
        # server: an open stream left to the server's shutdown is cancelled with a traceback.
        hub.stopping = True
        await asyncio.sleep(0.3)
        server.should_exit = True
    if publisher is not None:
        try:
            await asyncio.wait_for(publisher.stop(), timeout=max(0.1, end - loop.time()))
        except Exception as exc:                    # a timeout, or asyncua's own error: the process ends anyway
            log.warning("the OPC UA server did not stop cleanly (%s); the monitor ends all the same",
                        type(exc).__name__)
    pending = [t for t in tasks if not t.done()]
    if pending:
        _, pending = await asyncio.wait(pending, timeout=max(0.1, end - loop.time()))
    for t in pending:
        t.cancel()
    if pending:
        await asyncio.wait(pending, timeout=1.0)


def serve(config, web: WebSettings | None, opcua: OpcUaSettings | None, nice: int = 0, on_ready=None) -> None:
    """Run the monitor in this process until SIGINT or SIGTERM."""
    _lower_priority(nice)
    asyncio.run(_serve(config, web, opcua, on_ready))


def _monitor_main(config, web, opcua, nice) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s monitor %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")
    setup_logging(Path(config.data_dir), name="monitor.log")
    try:
        serve(config, web, opcua, nice)
    except StationError as exc:
        log.error("the monitor stopped: %s", exc)
    except OSError as exc:
        log.error("the monitor could not serve: %s (is the port taken? set [web] port)", exc)


class MonitorProcess:
    """The monitor beside the station's loop, in a spawned process at lower priority."""

    def __init__(self, config, web: WebSettings | None, opcua: OpcUaSettings | None):
        self._info = monitor_info_path(config.data_dir)
        self._info.unlink(missing_ok=True)
        ctx = multiprocessing.get_context("spawn")
        nice = (web or WebSettings()).nice
        self._proc = ctx.Process(target=_monitor_main, name="sofast-monitor", args=(config, web, opcua, nice),
                                 daemon=True)
        self._proc.start()

    @property
    def pid(self) -> int | None:
        return self._proc.pid

    def stop(self, timeout_s: float = 10.0) -> None:
        """Ask the monitor to stop (SIGTERM: both servers stop cleanly, within :data:`STOP_BUDGET_S`) and wait
        up to *timeout_s* seconds; a monitor still stopping then is ended (SIGKILL). Nothing is lost either
        way: the monitor only reads the station's files (and posts the operator's commands whole)."""
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(timeout_s)
        if not self._proc.is_alive():
            return
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
        log.warning("the monitor (page and OPC UA) was still stopping %.0f s after it was asked to (load average "
                    "%.1f on %d cores: a busy machine gives it little processor time); it was ended. Nothing of "
                    "the line's is lost: the monitor only reads the station's files", timeout_s, load,
                    os.cpu_count() or 1)
        self._proc.kill()
        self._proc.join(5)
        self._info.unlink(missing_ok=True)           # where it listened: it no longer does
