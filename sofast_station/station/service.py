"""Assemble a running station from station.toml: devices, trigger, journal, archiver, analysis worker.

Process layout: the station process owns the display, the camera and the robot handshake and runs the
cycles; the analysis runs in a worker process (killable on a deadline); the archiver runs in a process
of its own, so that openpyxl rewriting a large workbook (seconds, holding its interpreter's lock) never
slows a cycle. They share only files: the journal (SQLite WAL) and the spool.
"""

from __future__ import annotations

import dataclasses
import logging
import logging.handlers
import multiprocessing
import signal
from pathlib import Path

from ..archive import Archiver, ArchiverSettings, DumpContent, Journal, WorkbookSettings
from ..config import StationConfig
from ..devices.protocols import FacetRequest
from ..errors import ConfigError
from ..web.settings import web_settings
from .inspect import open_station
from .pictures import FacetPictures
from .recipes import recipes_from_config
from .runner import RunSettings, StationRunner

log = logging.getLogger(__name__)

_DEVICE_KEYS = {"trigger", "trigger_options", "display_options", "camera", "camera_options",
                "range_finder_options"}
_ARCHIVE_KEYS = {"workbook_period", "workbook_interval_s", "dump_keep_days", "dump_max_gb", "min_free_gb"}


def run_settings(config: StationConfig) -> RunSettings:
    table = config.raw.get("run", {})
    known = {f.name for f in dataclasses.fields(RunSettings)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{config.path} [run] has unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(known))}")
    return RunSettings(**table)


def archiver_settings(config: StationConfig, run: RunSettings) -> ArchiverSettings:
    table = config.raw.get("archive", {})
    unknown = sorted(set(table) - _ARCHIVE_KEYS)
    if unknown:
        raise ConfigError(f"{config.path} [archive] has unknown key(s) {', '.join(unknown)}")
    return ArchiverSettings(workbook=WorkbookSettings(period=table.get("workbook_period", "day")),
                            workbook_interval_s=float(table.get("workbook_interval_s", 30.0)),
                            dump_keep_days=table.get("dump_keep_days", run.dump_keep_days),
                            dump_max_total_gb=table.get("dump_max_gb", run.dump_max_gb),
                            min_free_gb=float(table.get("min_free_gb", run.min_free_gb)))


def open_trigger_from_config(config: StationConfig, simulated_facets: list[FacetRequest] | int | None):
    """The robot/PLC of ``[devices]`` (``trigger = "simulated" | "modbus" | "usb"``, ``trigger_options``)."""
    from ..devices.triggers import open_trigger

    dev = config.raw.get("devices", {})
    unknown = sorted(set(dev) - _DEVICE_KEYS)
    if unknown:
        raise ConfigError(f"{config.path} [devices] has unknown key(s) {', '.join(unknown)}")
    kind = dev.get("trigger", "simulated")
    options = dict(dev.get("trigger_options", {}))
    if kind == "simulated":
        options.setdefault("requests", simulated_facets if simulated_facets is not None else 20)
    return open_trigger(kind, **options)


def _archiver_main(journal_path: str, data_dir: str, settings: ArchiverSettings, stop) -> None:
    """The archiver process: drain journal and spool until *stop* is set, then once more."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the station decides when the archiver stops
    logging.basicConfig(level=logging.INFO, format="%(asctime)s archiver %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")
    setup_logging(Path(data_dir), name="archiver.log")
    journal = Journal(journal_path)
    archiver = Archiver(journal, data_dir, settings)
    archiver.start()
    stop.wait()
    archiver.stop(timeout_s=120, drain=True)
    journal.close()


class ArchiverProcess:
    """The archiver in its own process."""

    def __init__(self, journal_path: Path, data_dir: Path, settings: ArchiverSettings):
        ctx = multiprocessing.get_context("spawn")
        self._stop = ctx.Event()
        self._proc = ctx.Process(target=_archiver_main, name="sofast-archiver",
                                 args=(str(journal_path), str(data_dir), settings, self._stop), daemon=True)
        self._proc.start()

    def wake(self) -> None:
        """The archiver polls every couple of seconds; nothing to do."""

    def stop(self, timeout_s: float = 180.0) -> None:
        self._stop.set()
        self._proc.join(timeout_s)
        if self._proc.is_alive():
            log.error("the archiver did not finish within %.0f s; stopping it (pending rows stay in the "
                      "journal and are written at the next start)", timeout_s)
            self._proc.terminate()
            self._proc.join(10)


def setup_logging(data_dir: Path, verbose: bool = False, name: str = "station.log") -> Path:
    """Console (stderr) plus a rotating log file under data_dir/logs."""
    log_dir = data_dir / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    path = log_dir / name
    handler = logging.handlers.RotatingFileHandler(path, maxBytes=10_000_000, backupCount=10)
    handler.setFormatter(logging.Formatter("%(asctime)s %(process)d %(name)s %(levelname)s %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    return path


class Service:
    """Everything `sofast-station run` holds open."""

    def __init__(self, config: StationConfig, simulated_facets=None, seed: int | None = None, console=print,
                 archiver_process: bool = True, station=None):
        self.config = config
        data_dir = config.data_dir
        data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = run_settings(config)
        self.recipes = recipes_from_config(config)
        self.journal = Journal(data_dir / "journal.sqlite3")
        arch_settings = archiver_settings(config, self.settings)
        self.archiver = Archiver(self.journal, data_dir, arch_settings)   # submit() only, in this process
        self.archiver_process = self.station = self.trigger = self.runner = None
        try:
            self.archiver_process = ArchiverProcess(data_dir / "journal.sqlite3", data_dir, arch_settings) \
                if archiver_process else None
            self.station = open_station(config, seed=seed) if station is None else station
            self.trigger = open_trigger_from_config(config, simulated_facets)
            self.runner = StationRunner(self.station, self.trigger, self.journal, self.archiver_process,
                                        self.recipes, self.settings, self.submit, console=console)
            requests = getattr(self.trigger, "requests", None)
            self.runner.expected_total = len(requests) if isinstance(requests, list) else None
            self.runner.hooks.append(FacetPictures(data_dir, keep=web_settings(config).keep_pictures))
        except BaseException:
            self.close()
            raise

    def submit(self, cycle_id: str, record: dict, dump: dict | None) -> None:
        """Journal the record (and spool its dump content first): durable when it returns."""
        content = None
        if dump is not None:
            recipe = self.recipes.get(record.get("recipe") or "default", self.recipes["default"])
            facet_path = self.config.raw.get("recipes", {}).get(recipe.name, {}).get("facet")
            content = DumpContent.from_station(
                self.station, cycle_id=cycle_id, record=record, frames_cropped=dump["frames"],
                crop_box=dump["crop_box"], full_shape=dump["full_shape"],
                measured_distance_m=dump["measured_distance_m"], design=recipe.design, analysis=recipe.analysis,
                facet_path=(self.config.path.parent / facet_path) if facet_path else None)
        self.archiver.submit(cycle_id, record, content)

    def close(self) -> None:
        for part in (self.runner, self.trigger, self.station):
            try:
                if part is not None:
                    part.close()
            except Exception:
                log.exception("error while shutting down")
        if self.archiver_process is not None:
            self.archiver_process.stop()
        self.journal.close()
