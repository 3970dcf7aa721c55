"""The archiver: turns journaled cycles into workbook rows and spools into HDF5 dumps, in the background.

The station's part of a cycle is :meth:`Archiver.submit` (or the same two steps by hand): spool the
facet's cropped frames and metadata when a dump is wanted, then append the result to the journal, which
is durable when it returns; then the robot may go. Everything after that is the archiver's:

1. workbook: every pending journal row goes into its period's workbook (one atomic save per book), and
   is marked;
2. dumps: every pending dump is written from its spool (atomically), the journal is marked, and only
   then is the spool deleted;
3. housekeeping: spools whose dump is done are deleted, temporary files of crashed writers removed, the
   dump retention rule applied, free disk space watched.

Every step re-checks what is already done, so :meth:`Archiver.run_once` is idempotent and a crash (even
SIGKILL) at any point loses and duplicates nothing: rerunning finishes the work.

The background thread (:meth:`start`, :meth:`stop`) calls :meth:`run_once` every ``poll_interval_s``
(the workbook at most every ``workbook_interval_s``, because each save rewrites the whole part, and less
often when a save is long: the saves take at most ``workbook_cpu_share`` of one core on average, so a day's
part that has grown to hundreds of rows does not take a core from the measuring loop);
:meth:`wake` asks for a run now. It never raises: problems are logged and retried.
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ArchiveError, DumpError
from ..files import remove_stale_temp_files
from ..memory import release_memory
from ..times import parse_time
from .dumps import COMPRESSION_LEVEL, DumpContent, disk_ok, dump_path_for, prune_dumps, read_dump, write_dump
from .journal import Journal
from .spool import spool_get, spool_list, spool_path, spool_put
from .workbook import WorkbookSettings, write_pending

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ArchiverSettings:
    """How the archiver works.

    Attributes
    ----------
    workbook : WorkbookSettings
        Period (day or shift) and naming of the workbooks.
    poll_interval_s : float
        Background thread: time between runs, seconds.
    workbook_interval_s : float
        Background thread: least time between workbook saves, seconds (rows wait in the journal meanwhile).
    workbook_cpu_share : float
        Background thread: largest share of one core the workbook saves take on average, in (0, 1]. A save
        rewrites its part whole (about 14 ms of CPU a row of the full-resolution record), so after a save that
        took *c* seconds of CPU the next waits at least ``c * (1 / share - 1)`` seconds (rows wait in the
        journal, which is the record of truth, meanwhile).
    dump_keep_days : float or None
        Retention: largest age of a dump, days; None keeps them forever.
    dump_max_total_gb : float or None
        Retention: largest total size of the dumps, GB; None: no limit.
    min_free_gb : float
        Dumps wait in the spool while the dump disk has less free space than this, GB (after pruning).
    prune_interval_s : float
        Time between retention passes, seconds.
    missing_spool_grace_s : float
        A pending dump whose spool is still missing this long after its row was journaled is marked
        failed, seconds.
    orphan_spool_age_s : float
        A spool without a journal row (the station stopped between spooling and journaling) older than
        this is moved to ``spool/orphaned/``, seconds.
    compression_level : int
        gzip level of the dumped frames.
    late_spool_grace_s : float
        A spool whose row does not request a dump is kept this long (a late result spools first and
        then amends its row), seconds.
    """

    workbook: WorkbookSettings = field(default_factory=WorkbookSettings)
    poll_interval_s: float = 2.0
    workbook_interval_s: float = 60.0
    workbook_cpu_share: float = 0.1
    dump_keep_days: float | None = 90.0
    dump_max_total_gb: float | None = 100.0
    min_free_gb: float = 2.0
    prune_interval_s: float = 600.0
    missing_spool_grace_s: float = 300.0
    orphan_spool_age_s: float = 3600.0
    compression_level: int = COMPRESSION_LEVEL
    late_spool_grace_s: float = 120.0


@dataclass
class ArchiveReport:
    """What one :meth:`Archiver.run_once` did.

    Attributes
    ----------
    workbook_rows : int
        Rows added to workbooks.
    workbook_waiting : int
        Rows left pending (a book could not be saved).
    workbook_errors : dict
        Workbook -> error.
    dumps_written : list of Path
    dumps_failed : dict
        Cycle id -> reason (marked failed in the journal).
    dumps_waiting : int
        Pending dumps left for later (write error, low disk, stop requested).
    spools_removed : int
    pruned : list of Path
        Dumps removed by the retention rule.
    """

    workbook_rows: int = 0
    workbook_waiting: int = 0
    workbook_errors: dict = field(default_factory=dict)
    dumps_written: list = field(default_factory=list)
    dumps_failed: dict = field(default_factory=dict)
    dumps_waiting: int = 0
    spools_removed: int = 0
    pruned: list = field(default_factory=list)


class Archiver:
    """Drains the journal into workbooks and the spool into dumps.

    Parameters
    ----------
    journal : Journal
    data_dir : str or Path
        The station's data folder: workbooks go to ``archive/``, dumps to ``dumps/<date>/``, spools to
        ``spool/``.
    settings : ArchiverSettings, optional
    """

    def __init__(self, journal: Journal, data_dir: str | Path, settings: ArchiverSettings | None = None):
        self.journal = journal
        self.data_dir = Path(data_dir)
        self.settings = settings or ArchiverSettings()
        self.archive_dir = self.data_dir / "archive"
        self.dumps_dir = self.data_dir / "dumps"
        self.spool_dir = self.data_dir / "spool"
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._run_lock = threading.Lock()
        self._last_workbook = float("-inf")
        self._cpu_clock = time.thread_time      # the save runs in the calling thread (a test may set a clock)
        #: The least time between the last workbook save and the next, s (grows with a long save).
        self.workbook_gap_s = self.settings.workbook_interval_s
        self._last_prune = float("-inf")
        self._cleaned = False
        self._low_disk_logged = False
        self._dump_problem: str | None = None          # why dumps wait, as last logged
        self._pass_problem: tuple[str, float] | None = None   # a failing pass, as last logged (text, when)

    # -- the station's side -----------------------------------------------------------------------------
    def submit(self, cycle_id: str, record: dict, content: DumpContent | None = None, amend: bool = False) -> bool:
        """Spool the dump content (if any), then journal the record (durable on return), then wake the thread.

        Call before releasing the robot. Returns False when the cycle was already journaled. With *amend*
        (a late result, ``record["late"]`` true) the cycle's journaled record is replaced, and its workbook
        row rewritten by the next pass.
        """
        if amend:
            if content is not None:
                arrays, meta = content.to_spool()
                spool_put(self.spool_dir, cycle_id, arrays, meta)
            if self.journal.amend(cycle_id, record, dump_requested=content is not None):
                self.wake()
                return True
            log.warning("cycle %s was not journaled before its late result: journaling it now", cycle_id)
            added = self.journal.append(cycle_id, record, dump_requested=content is not None)
            self.wake()
            return added
        if content is not None:
            arrays, meta = content.to_spool()
            spool_put(self.spool_dir, cycle_id, arrays, meta)
        added = self.journal.append(cycle_id, record, dump_requested=content is not None)
        self.wake()
        return added

    # -- one pass ---------------------------------------------------------------------------------------
    def run_once(self, workbook: bool = True, dumps: bool = True) -> ArchiveReport:
        """Do all pending work once; idempotent, and safe to rerun after a crash at any point.

        Parameters
        ----------
        workbook, dumps : bool
            Which kinds of work to do.

        Returns
        -------
        ArchiveReport
        """
        with self._run_lock:
            report = ArchiveReport()
            if not self._cleaned:
                for folder, recursive in ((self.archive_dir, False), (self.dumps_dir, True), (self.spool_dir, False)):
                    remove_stale_temp_files(folder, recursive=recursive)
                self._cleaned = True
            if workbook and not self._stop_requested():
                self._workbook_step(report)
            if dumps:
                self._dump_step(report)
                self._spool_cleanup(report)
            if time.monotonic() - self._last_prune >= self.settings.prune_interval_s and not self._stop_requested():
                self._prune(report)
            return report

    def _stop_requested(self) -> bool:
        return self._stop.is_set() and threading.current_thread() is self._thread

    def _workbook_step(self, report: ArchiveReport) -> None:
        cpu = self._cpu_clock()
        wb = write_pending(self.journal, self.archive_dir, self.settings.workbook)
        if wb.rows_written or wb.already_present:
            release_memory()               # the loaded workbook part: back to the system, not kept at its peak
        self._last_workbook = time.monotonic()
        self._workbook_gap(self._cpu_clock() - cpu, wb.rows_written)
        report.workbook_rows += wb.rows_written
        report.workbook_waiting += wb.waiting
        report.workbook_errors.update(wb.errors)

    def _workbook_gap(self, cpu_s: float, rows: int) -> None:
        """The least time to the next save after one that took *cpu_s* seconds of CPU (the share cap)."""
        share = min(max(self.settings.workbook_cpu_share, 1e-3), 1.0)
        gap = max(self.settings.workbook_interval_s, cpu_s * (1.0 / share - 1.0))
        if gap > self.settings.workbook_interval_s and gap >= 1.5 * self.workbook_gap_s:
            log.info("workbook save took %.1f s of CPU (%d rows added): the next in %.0f s at the earliest, to "
                     "keep the saves under %.0f %% of a core (rows wait in the journal)", cpu_s, rows, gap,
                     100 * share)
        self.workbook_gap_s = gap

    def _prune(self, report: ArchiveReport) -> None:
        s = self.settings
        if s.dump_keep_days is not None or s.dump_max_total_gb is not None:
            report.pruned.extend(prune_dumps(self.dumps_dir, s.dump_keep_days, s.dump_max_total_gb))
        self._last_prune = time.monotonic()

    def _disk_ok(self, report: ArchiveReport) -> bool:
        ok, free = disk_ok(self.dumps_dir, self.settings.min_free_gb)
        if not ok:
            self._prune(report)
            ok, free = disk_ok(self.dumps_dir, self.settings.min_free_gb)
        if not ok:
            if not self._low_disk_logged:
                log.warning("only %.2f GB free for dumps under %s (need %.2f GB): dumps wait in the spool; free "
                            "disk space or lower the retention limits", free, self.dumps_dir,
                            self.settings.min_free_gb)
                self._low_disk_logged = True
        else:
            self._low_disk_logged = False
        return ok

    def _dump_step(self, report: ArchiveReport) -> None:
        pending = self.journal.pending_dump_rows()           # without the records: they come from the spool
        for i, row in enumerate(pending):
            if self._stop_requested():
                report.dumps_waiting += len(pending) - i
                return
            final = dump_path_for(self.dumps_dir, row.serial, row.time, row.cycle_id)
            spool = spool_path(self.spool_dir, row.cycle_id)
            # Done before a crash? (renamed into place, journal not yet marked)
            if final.exists():
                try:
                    done = read_dump(final, load_frames=False).cycle_id == row.cycle_id
                except ArchiveError as exc:
                    log.warning("replacing %s, which is unreadable (%s)", final, exc)
                    done = False
                if done:
                    self.journal.mark_dump(row.cycle_id, final)
                    self._remove_spool(spool, report)
                    report.dumps_written.append(final)
                    continue
            if not spool.exists():
                age = time.time() - parse_time(row.journaled_at).timestamp()
                if age > self.settings.missing_spool_grace_s:
                    reason = ("no spool: the station stopped before spooling the frames, or the spool was "
                              f"deleted ({spool})")
                    self.journal.mark_dump(row.cycle_id, None, error=reason)
                    report.dumps_failed[row.cycle_id] = reason
                    log.error("dump of cycle %s (serial %s) failed: %s", row.cycle_id, row.serial, reason)
                else:
                    report.dumps_waiting += 1
                continue
            if not self._disk_ok(report):
                report.dumps_waiting += len(pending) - i
                return
            try:
                content = DumpContent.from_spool(*spool_get(spool))
            except ArchiveError as exc:
                reason = f"unusable spool: {exc}"
                self.journal.mark_dump(row.cycle_id, None, error=reason)
                report.dumps_failed[row.cycle_id] = reason
                self._quarantine_spool(spool, "bad")
                log.error("dump of cycle %s (serial %s) failed: %s", row.cycle_id, row.serial, reason)
                continue
            try:
                write_dump(final, content, self.settings.compression_level)
            except DumpError as exc:
                # The content cannot make a dump (not the disk): writing it again will not help. Recorded as
                # failed, the spool kept aside with its frames (spool/bad/), never retried at every pass.
                reason = f"the spooled facet cannot be written as a dump: {exc}"
                self.journal.mark_dump(row.cycle_id, None, error=reason)
                report.dumps_failed[row.cycle_id] = reason
                self._quarantine_spool(spool, "bad")
                log.error("dump of cycle %s (serial %s) failed: %s; its spool is kept in %s", row.cycle_id,
                          row.serial, reason, self.spool_dir / "bad")
                continue
            except ArchiveError as exc:
                report.dumps_waiting += 1
                self._dump_waits(row.cycle_id, exc)
                continue
            self._dump_waits(None, None)
            self.journal.mark_dump(row.cycle_id, final)
            self._remove_spool(spool, report)
            report.dumps_written.append(final)

    def _dump_waits(self, cycle_id: str | None, exc: Exception | None) -> None:
        """Log a dump that cannot be written now once, not at every pass (every 2 s: a dumps folder made
        read-only mid-run filled the log); and once when dumps are written again."""
        if exc is None:
            if self._dump_problem is not None:
                log.info("dumps are written again (they waited in the spool since: %s)", self._dump_problem)
                self._dump_problem = None
            return
        cause = exc.__cause__ or exc                    # the same kind of failure, whichever cycle's dump
        problem = f"{type(cause).__name__} {getattr(cause, 'strerror', None) or ''}".strip()
        if problem != self._dump_problem:
            log.warning("dump of cycle %s waits in the spool: %s (said once; the archiver tries again at every "
                        "pass and says when dumps are written again)", cycle_id, exc)
            self._dump_problem = problem

    def _remove_spool(self, spool: Path, report: ArchiveReport) -> None:
        try:
            spool.unlink()
            report.spools_removed += 1
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("could not remove the spool %s: %s", spool, exc)

    def _quarantine_spool(self, spool: Path, why: str) -> None:
        target = self.spool_dir / why
        try:
            target.mkdir(parents=True, exist_ok=True)
            shutil.move(str(spool), str(target / spool.name))
        except OSError as exc:
            log.warning("could not move the spool %s to %s: %s", spool, target, exc)

    def _spool_cleanup(self, report: ArchiveReport) -> None:
        """Delete spools whose dump is done (a crash after the journal mark); set orphans aside."""
        for spool in spool_list(self.spool_dir):
            if self._stop_requested():
                return
            # the file name is the file-name-safe cycle id; find the row by the id stored inside when needed
            row = self.journal.get(spool.stem)
            if row is None:
                try:
                    age = time.time() - spool.stat().st_mtime
                except FileNotFoundError:
                    continue
                if age < self.settings.orphan_spool_age_s:
                    continue
                try:
                    cycle_id = spool_get(spool)[1].get("cycle_id", spool.stem)
                except ArchiveError:
                    cycle_id = None
                row = self.journal.get(cycle_id) if cycle_id else None
                if row is None:
                    log.warning("spool %s has no journal row (the station stopped between spooling and "
                                "journaling); moved to %s", spool, self.spool_dir / "orphaned")
                    self._quarantine_spool(spool, "orphaned")
                    continue
            if row.dump_status == "not requested":
                # A late result spools its frames before it amends its row to request the dump: give it time.
                try:
                    if time.time() - spool.stat().st_mtime < self.settings.late_spool_grace_s:
                        continue
                except FileNotFoundError:
                    continue
            if row.dump_status in ("written", "failed", "not requested"):
                self._remove_spool(spool, report)

    # -- background thread --------------------------------------------------------------------------------
    def start(self) -> None:
        """Run :meth:`run_once` in a background thread until :meth:`stop`."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name="sofast-archiver", daemon=True)
        self._thread.start()

    def wake(self) -> None:
        """Ask the background thread for a run now."""
        self._wake.set()

    def stop(self, timeout_s: float | None = None, drain: bool = False) -> bool:
        """Stop the background thread after its current step (one workbook save or one dump).

        Parameters
        ----------
        timeout_s : float, optional
            Longest wait for the thread, seconds; None waits until it ends.
        drain : bool
            After the thread has ended, do all remaining work once in the calling thread (shutdown).

        Returns
        -------
        bool
            True when the thread has ended (False: still busy after *timeout_s* seconds).
        """
        self._stop.set()
        self._wake.set()
        t = self._thread
        ended = True
        if t is not None:
            t.join(timeout_s)
            ended = not t.is_alive()
        if drain and ended:
            self.run_once()
        return ended

    #: Seconds between two log lines of the same failing pass.
    REPEAT_LOG_S = 600.0

    def _pass_failed(self, exc: Exception) -> None:
        """A pass that raised: the traceback once, then one line every :attr:`REPEAT_LOG_S` seconds while
        the same error repeats (it is retried every pass, every couple of seconds)."""
        text = f"{type(exc).__name__}: {exc}"
        now = time.monotonic()
        if self._pass_problem is None or self._pass_problem[0] != text:
            log.error("archiver pass failed; retrying every %.0f s (said once, then every %.0f min while it "
                      "repeats)", self.settings.poll_interval_s, self.REPEAT_LOG_S / 60, exc_info=exc)
            self._pass_problem = (text, now)
        elif now - self._pass_problem[1] >= self.REPEAT_LOG_S:
            log.error("archiver passes still fail: %s", text)
            self._pass_problem = (text, now)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _loop(self) -> None:
        log.debug("archiver thread started (%s)", self.data_dir)
        while not self._stop.is_set():
            due = time.monotonic() - self._last_workbook >= self.workbook_gap_s
            try:
                self.run_once(workbook=due)
                if self._pass_problem is not None:
                    log.info("archiver passes work again")
                    self._pass_problem = None
            except Exception as exc:       # never stop archiving: log and retry on the next pass
                self._pass_failed(exc)
            self._wake.wait(self.settings.poll_interval_s)
            self._wake.clear()
        log.debug("archiver thread stopped")
