"""Assemble a running station from station.toml: devices, trigger, journal, archiver, analysis worker.

Process layout: the station process owns the display, the camera and the robot handshake and runs the
cycles; the analysis runs in a worker process (killable on a deadline); the archiver runs in a process
of its own, so that openpyxl rewriting a large workbook (seconds, holding its interpreter's lock) never
slows a cycle. They share only files: the journal (SQLite WAL) and the spool.
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import logging
import multiprocessing
import os
import signal
import time
from pathlib import Path

from ..archive import Archiver, ArchiverSettings, DumpContent, Journal, WorkbookSettings
from ..archive.spool import spool_get, spool_list
from ..config import StationConfig
from ..devices.protocols import FacetRequest
from ..devices.triggers import open_trigger
from ..errors import ArchiveError, ConfigError, StationError, TriggerError
from ..files import remove_stale_temp_files, temp_path_for
from ..job import job_for
from ..live.logs import setup_logging
from ..live.pictures import FacetPictures
from ..memory import map_large_blocks
from ..recipes import recipes_from_config
from ..web.settings import web_settings
from .factory import open_station
from .memtrace import start_from_env
from .runner import RunSettings, StationRunner
from .worker import watch_parent

log = logging.getLogger(__name__)

_DEVICE_KEYS = {"trigger", "trigger_options", "display_options", "camera", "camera_options",
                "range_finder_options"}
_ARCHIVE_KEYS = {"workbook_period", "workbook_interval_s", "workbook_cpu_share", "workbook_max_rows", "dump_keep_days",
                 "dump_max_gb", "min_free_gb"}

#: Data rows per workbook part unless ``[archive] workbook_max_rows`` says otherwise: the archiver writes a
#: part whole on every save (streamed, its memory does not grow with the part), so a day of a busy line is
#: split into parts to keep that work bounded (about 14 s of CPU per save of a full 1000-row part; the
#: archiver spaces its saves so that they take at most ``[archive] workbook_cpu_share`` of a core).
WORKBOOK_MAX_ROWS = 1000


#: Environment variable: the cycle deadline, seconds, when station.toml's [run] does not set deadline_s.
#: The test suite sets it long, so that no test depends on the machine's load (only tests that set a
#: deadline on purpose meet one).
DEFAULT_DEADLINE_ENV = "SOFAST_DEFAULT_DEADLINE_S"


def run_settings(config: StationConfig) -> RunSettings:
    """``[run]`` of station.toml (checked at load by the config schema)."""
    table = config.raw.get("run", {})
    known = {f.name for f in dataclasses.fields(RunSettings)}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{config.path} [run] has unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(known))}")
    table = dict(table)
    default_deadline = os.environ.get(DEFAULT_DEADLINE_ENV)
    if default_deadline and "deadline_s" not in table:
        try:
            table["deadline_s"] = float(default_deadline)
        except ValueError:
            raise ConfigError(f"{DEFAULT_DEADLINE_ENV}={default_deadline!r} is not a number of seconds") from None
    return RunSettings(**table)


def archiver_settings(config: StationConfig, run: RunSettings) -> ArchiverSettings:
    table = config.raw.get("archive", {})
    unknown = sorted(set(table) - _ARCHIVE_KEYS)
    if unknown:
        raise ConfigError(f"{config.path} [archive] has unknown key(s) {', '.join(unknown)}")
    return ArchiverSettings(workbook=WorkbookSettings(period=table.get("workbook_period", "day"),
                                                      max_rows=table.get("workbook_max_rows", WORKBOOK_MAX_ROWS)),
                            workbook_interval_s=float(table.get("workbook_interval_s", 30.0)),
                            workbook_cpu_share=float(table.get("workbook_cpu_share", 0.1)),
                            dump_keep_days=table.get("dump_keep_days", run.dump_keep_days),
                            dump_max_total_gb=table.get("dump_max_gb", run.dump_max_gb),
                            min_free_gb=float(table.get("min_free_gb", run.min_free_gb)))


def open_trigger_from_config(config: StationConfig, simulated_facets: list[FacetRequest] | int | None,
                             retry_s: float | None = 2.0):
    """The robot/PLC of ``[devices]`` (``trigger = "simulated" | "modbus" | "usb"``, ``trigger_options``).

    A PLC that cannot be reached is tried again every *retry_s* seconds until it answers (None: raise).
    """
    dev = config.raw.get("devices", {})
    unknown = sorted(set(dev) - _DEVICE_KEYS)
    if unknown:
        raise ConfigError(f"{config.path} [devices] has unknown key(s) {', '.join(unknown)}")
    kind = dev.get("trigger", "simulated")
    options = dict(dev.get("trigger_options", {}))
    if kind == "simulated":
        options.setdefault("requests", simulated_facets if simulated_facets is not None else 20)
    attempt = 0
    while True:
        try:
            return open_trigger(kind, **options)
        except TriggerError as exc:
            # The PLC may simply not be up yet (the line powers on together): retry, as the message says.
            if retry_s is None:
                raise
            attempt += 1
            if attempt == 1 or attempt % 30 == 0:
                log.error("%s (attempt %d; retrying every %g s until it answers, Ctrl-C or SIGTERM to give up)",
                          exc, attempt, retry_s)
            time.sleep(retry_s)


class StationLocked(StationError):
    """Another station (or a calibration, or an archiver) runs on this data folder: ``holder`` its process id,
    ``holder_what`` what it is ("station", "calibration"), when its lock file says."""

    def __init__(self, message: str, holder: int | None = None, holder_what: str | None = None):
        super().__init__(message)
        self.holder, self.holder_what = holder, holder_what


class DataDirLock:
    """One station per data folder: an exclusive ``flock`` on ``data_dir/station.lock`` holding the PID.

    The lock is the kernel's: it goes with the process, so a station killed with SIGKILL leaves a lock
    file that the next station simply takes again (and says so). Taken before any device opens.
    """

    def __init__(self, data_dir: Path, name: str = "station.lock", wait_s: float = 0.0, what: str = "station"):
        self.path = Path(data_dir) / name
        self._fd = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise StationError(f"cannot open the {what}'s lock {self.path} ({exc.strerror or exc}): make the data "
                               f"folder {data_dir} writable (permissions, a read-only mount, a full disk) or give "
                               f"the station another data_dir (station.toml [station] data_dir, or "
                               f"SOFAST_DATA_DIR), then start again") from None
        deadline = time.monotonic() + wait_s
        while True:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                    os.close(self._fd)
                    raise StationError(f"cannot lock {self.path}: {exc}") from None
                if time.monotonic() >= deadline:
                    holder, holder_what = self._holder(), self._holder_what()
                    os.close(self._fd)
                    raise StationLocked(
                        f"another {holder_what or what} (process {holder or '?'}) is running on the data folder "
                        f"{data_dir}: stop it first, or give this one its own data_dir (station.toml [station] "
                        f"data_dir, or SOFAST_DATA_DIR)", holder, holder_what) from None
                time.sleep(0.1)
        previous = self._holder()
        try:
            os.ftruncate(self._fd, 0)
            os.pwrite(self._fd, f"{os.getpid()} {what}\n".encode(), 0)
        except OSError as exc:
            # A full disk (or a read-only one) refuses even the PID's few bytes: say so, not with a traceback.
            os.close(self._fd)                       # and the flock with it: nothing is held
            self._fd = None
            raise StationError(
                f"cannot write the {what}'s process id into {self.path} ({exc.strerror or exc}): the data "
                f"folder {data_dir} is full or read-only; nothing was started. Free disk space or make it "
                f"writable, or give the station another data_dir (station.toml [station] data_dir, or "
                f"SOFAST_DATA_DIR), then start again") from None
        if previous and previous != os.getpid():
            log.warning("the %s lock %s was left by process %d, which is gone (killed?): taken over",
                        what, self.path, previous)
        self.recovered_from = previous if previous and previous != os.getpid() else None

    def _read(self) -> list[str]:
        try:
            return os.pread(self._fd, 64, 0).decode(errors="replace").split()
        except OSError:
            return []

    def _holder(self) -> int | None:
        """The process id the lock file names (its first word), or None."""
        words = self._read()
        return int(words[0]) if words and words[0].isdigit() else None

    def _holder_what(self) -> str | None:
        """What holds the lock ("station", "calibration"...; its second word), or None (an older file)."""
        words = self._read()
        return words[1] if len(words) > 1 and words[1].isalpha() else None

    def release(self) -> None:
        if self._fd is not None:
            try:
                os.ftruncate(self._fd, 0)
            except OSError:
                pass
            os.close(self._fd)          # closing the descriptor releases the flock
            self._fd = None


def recover_leftovers(data_dir: Path, journal: Journal) -> dict:
    """At start, under the station lock: remove what a killed station left, and say so in the log.

    Every temporary file under ``archive/``, ``dumps/`` and ``spool/`` is a dead writer's (the lock
    guarantees no other writer, and this station's own have not started); a spool without a journal row
    (the station died between spooling and journaling, before it answered) is journaled as a fault with
    its figures and queued for its dump, so the measurement is not lost.
    """
    removed = []
    for folder, recursive in (("archive", False), ("dumps", True), ("spool", False)):
        removed += remove_stale_temp_files(data_dir / folder, max_age_s=0.0, recursive=recursive)
    # live/ and commands/ are written by the monitor too (a `serve` beside the station may be running):
    # there only the temporary files of processes that are gone.
    for folder, recursive in (("live", True), ("commands", False)):
        removed += remove_stale_temp_files(data_dir / folder, recursive=recursive)
    # Names of the live status's and the pictures' temporary files before they were made like the others
    # (a full disk left them for good); only the station writes either, and this one has not started yet.
    for leftover in [*(data_dir / "live").glob(".status.*.tmp"), *(data_dir / "live" / "facets").glob(".*.tmp")]:
        try:
            leftover.unlink()
            removed.append(leftover)
        except OSError as exc:
            log.warning("could not remove the leftover temporary file %s: %s", leftover, exc)
    requeued = []
    for spool in spool_list(data_dir / "spool"):
        if journal.get(spool.stem) is not None:
            continue
        try:
            meta = spool_get(spool)[1]
        except ArchiveError as exc:
            log.warning("leftover spool %s is unreadable (%s); left for the archiver to set aside", spool, exc)
            continue
        cycle_id = meta.get("cycle_id", spool.stem)
        if journal.get(cycle_id) is not None:
            continue
        record = dict(meta.get("record") or {})
        record.setdefault("serial", meta.get("serial", "?"))
        record.setdefault("time", meta.get("time"))
        record.update({"cycle_id": cycle_id, "recovered": True, "verdict": "fault",
                       "fault_code": record.get("fault_code", 99)})
        record["reasons"] = ["internal: the station stopped after spooling this facet and before journaling it "
                             "(no answer reached the robot); recovered at the next start"] + \
            list(record.get("reasons", []))
        try:
            journal.append(cycle_id, record, dump_requested=True)
            requeued.append(cycle_id)
            log.warning("re-queued the orphan spool %s (serial %s) left by a stopped station: journaled as a "
                        "fault, its dump will be written", spool.name, record["serial"])
        except ArchiveError as exc:
            log.error("could not journal the orphan spool %s: %s", spool, exc)
    if removed:
        log.warning("removed %d temporary file(s) left by a stopped writer", len(removed))
    return {"temp_files": removed, "requeued": requeued}


#: The folders under data_dir the station and its archiver write, checked at start (see check_writable).
WRITTEN_FOLDERS = ("archive", "dumps", "spool")


def check_writable(data_dir: Path) -> None:
    """At start, before any device opens: each folder the archive writes takes a small file.

    A folder the station cannot write (permissions, a read-only mount, a full disk) would otherwise show
    up facets later, in the archiver's log; here it stops the start with one message. The probe is a
    temporary file (``.write-test.PID.HEX.tmp``), removed at once, or at the next start if killed.

    Raises
    ------
    StationError
        Naming the folder, the system's reason and what to do.
    """
    for name in WRITTEN_FOLDERS:
        folder = Path(data_dir) / name
        probe = temp_path_for(folder / "write-test")
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            try:
                os.write(fd, b"0")
            finally:
                os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise StationError(
                f"the station cannot write into its {name} folder {folder} ({exc.strerror or exc}); nothing was "
                f"measured. Make the folder writable (permissions, a read-only mount, a full disk), or give the "
                f"station another data_dir (station.toml [station] data_dir, or SOFAST_DATA_DIR), then start "
                f"again") from None


#: The archiver starts afresh (the station starts a new one between facets) once its memory has grown
#: this many MB past what it held after its first minute: a hard bound on the long-lived process, whatever
#: holds on to memory (freed memory fragments; a leak in a library). A safety net: the workbook writer
#: streams its parts and the archiver's memory is flat without it.
ARCHIVER_RECYCLE_MB = 192.0
#: Seconds after its start at which the archiver takes its memory as the reference for that bound.
ARCHIVER_BASELINE_S = 60.0

#: The archiver's exit code when it ends to start afresh (EX_TEMPFAIL), not because it failed.
RECYCLED_EXIT = 75


def _rss_mb() -> float:
    """This process's resident memory, MB (0 where /proc is not there)."""
    try:
        with open("/proc/self/status") as fh:
            return next(int(line.split()[1]) for line in fh if line.startswith("VmRSS:")) / 1024.0
    except (OSError, StopIteration, ValueError):
        return 0.0


def _archiver_main(journal_path: str, data_dir: str, settings: ArchiverSettings, conn,
                   recycle_mb: float = ARCHIVER_RECYCLE_MB, baseline_s: float = ARCHIVER_BASELINE_S) -> None:
    """The archiver process: drain journal and spool until the station says stop (or goes away), then once
    more; past *recycle_mb* of growth it drains and exits with :data:`RECYCLED_EXIT` to start afresh."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the station decides when the archiver stops
    watch_parent()                                    # a killed station takes its archiver with it
    map_large_blocks()                                # frames read and written per dump: never kept
    logging.basicConfig(level=logging.INFO, format="%(asctime)s archiver %(levelname)s %(message)s",
                        datefmt="%H:%M:%S")
    setup_logging(Path(data_dir), name="archiver.log")
    start_from_env("archiver")                        # off unless SOFAST_TRACEMALLOC_S is set (leak hunts)
    # One archiver per data folder, even for the instant a killed station's archiver takes to notice.
    lock = DataDirLock(Path(data_dir), name="archiver.lock", wait_s=30.0, what="archiver")
    journal = Journal(journal_path)
    archiver = Archiver(journal, data_dir, settings)
    archiver.start()
    t_start, base_mb, recycle = time.monotonic(), None, False
    try:
        while True:
            try:
                if conn.poll(1.0):
                    conn.recv()
                    break
            except (EOFError, OSError):                   # the station is gone
                break
            rss = _rss_mb()
            if base_mb is None and time.monotonic() - t_start >= baseline_s:
                base_mb = rss
            elif base_mb is not None and rss > base_mb + recycle_mb:
                log.info("the archiver holds %.0f MB, %.0f MB more than %.0f s after its start: it writes what is "
                         "pending and starts afresh", rss, rss - base_mb, baseline_s)
                recycle = True
                break
        archiver.stop(timeout_s=120, drain=True)
    finally:
        journal.close()
        lock.release()
    if recycle:
        os._exit(RECYCLED_EXIT)


class ArchiverProcess:
    """The archiver in its own process, supervised by the station.

    The station tells it to stop through a pipe (not a shared lock: a process killed while holding a
    multiprocessing lock would block the station's shutdown forever); end of file on the pipe also
    stops it. :meth:`supervise` restarts a dead archiver between facets.
    """

    def __init__(self, journal_path: Path, data_dir: Path, settings: ArchiverSettings,
                 recycle_mb: float | None = None):
        self._args = (str(journal_path), str(data_dir), settings)
        self._recycle = (ARCHIVER_RECYCLE_MB if recycle_mb is None else recycle_mb, ARCHIVER_BASELINE_S)
        self._proc = self._conn = None
        self.restarts = 0            # after the archiver died
        self.recycles = 0            # after it started afresh to give back memory (RECYCLED_EXIT)
        self._start()

    def _start(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_archiver_main, name="sofast-archiver",
                                 args=(*self._args, child, *self._recycle), daemon=True)
        self._proc.start()
        child.close()

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def supervise(self) -> bool:
        """Restart the archiver when it died (logged); True when restarted."""
        if self.alive():
            return False
        code = self._proc.exitcode if self._proc is not None else None
        if code == RECYCLED_EXIT:
            log.info("the archiver process %s started afresh to give back its memory: a new one takes over",
                     self.pid)
            self.recycles += 1
        else:
            log.error("the archiver process %s ended (exit code %s): restarting it; rows and dumps it had not "
                      "written wait in the journal and the spool", self.pid, code)
            self.restarts += 1
        self._close_conn()
        self._start()
        return True

    def wake(self) -> None:
        """The archiver polls every couple of seconds; nothing to do."""

    def _close_conn(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None

    def stop(self, timeout_s: float = 180.0) -> None:
        if not self.alive() and self._proc is not None and self._proc.exitcode == RECYCLED_EXIT:
            self.supervise()            # it had just ended to start afresh: a new one writes what is pending
        if not self.alive():
            log.warning("the archiver was not running at shutdown; pending rows and dumps are written at the "
                        "next start")
            self._close_conn()
            return
        try:
            self._conn.send("stop")
        except OSError:
            pass
        self._proc.join(timeout_s)
        if self._proc.exitcode == RECYCLED_EXIT:    # it ended to start afresh just before "stop" came
            self.supervise()
            return self.stop(timeout_s)
        if self._proc.is_alive():
            log.error("the archiver did not finish within %.0f s; stopping it (pending rows stay in the "
                      "journal and are written at the next start)", timeout_s)
            self._proc.kill()
            self._proc.join(10)
        self._close_conn()


class Service:
    """Everything `sofast-station run` holds open."""

    def __init__(self, config: StationConfig, simulated_facets=None, seed: int | None = None, console=print,
                 archiver_process: bool = True, station=None):
        self.config = config
        data_dir = config.data_dir                 # made by the lock, which says so when it cannot
        self.settings = run_settings(config)
        self.recipes = recipes_from_config(config)
        self.lock = DataDirLock(data_dir)          # before any device opens or anything is written
        self.journal = self.archiver_process = self.station = self.trigger = self.runner = None
        try:
            self.journal = Journal(data_dir / "journal.sqlite3")
            self.recovered = recover_leftovers(data_dir, self.journal)
            check_writable(data_dir)           # before the archiver starts and any device opens
            arch_settings = archiver_settings(config, self.settings)
            self.archiver = Archiver(self.journal, data_dir, arch_settings)   # submit() only, in this process
            self.archiver_process = ArchiverProcess(data_dir / "journal.sqlite3", data_dir, arch_settings) \
                if archiver_process else None
            self.station = open_station(config, seed=seed) if station is None else station
            self.trigger = open_trigger_from_config(config, simulated_facets)
            if hasattr(self.trigger, "place") and hasattr(self.station, "place"):
                self.trigger.place = self.station.place     # the simulated robot places the line's facets
            self.runner = StationRunner(self.station, self.trigger, self.journal, self.archiver_process,
                                        self.recipes, self.settings, self.submit, console=console)
            requests = getattr(self.trigger, "requests", None)
            self.runner.expected_total = len(requests) if isinstance(requests, list) else None
            self.runner.hooks.append(FacetPictures(data_dir, keep=web_settings(config).keep_pictures))
            if self.settings.warmup:
                self.runner.warm_up()
        except BaseException:
            self.close()
            raise

    def submit(self, cycle_id: str, record: dict, dump: dict | None, amend: bool = False) -> None:
        """Journal the record (and spool its dump content first): durable when it returns."""
        content = None
        if dump is not None:
            recipe = self.recipes.get(record.get("recipe") or "default", self.recipes["default"])
            facet_path = self.config.raw.get("recipes", {}).get(recipe.name, {}).get("facet")
            # the job the cycle measured with: a heliostat's canting prescription is its serial's (no simulated fault)
            job = job_for(recipe, self.config, record.get("serial"))
            content = DumpContent.from_station(
                self.station, cycle_id=cycle_id, record=record, frames_cropped=dump["frames"],
                crop_box=dump["crop_box"], full_shape=dump["full_shape"],
                measured_distance_m=dump["measured_distance_m"], design=recipe.design, analysis=recipe.analysis,
                facet_path=(self.config.path.parent / facet_path) if facet_path else None,
                sensitivities=dump.get("sensitivities"),
                heliostat=job.dumped())
        self.archiver.submit(cycle_id, record, content, amend=amend)

    def close(self) -> None:
        for part in (self.runner, self.trigger, self.station):
            try:
                if part is not None:
                    part.close()
            except Exception:
                log.exception("error while shutting down")
        if self.archiver_process is not None:
            self.archiver_process.stop()
        if self.journal is not None:
            self.journal.close()
        self.lock.release()
