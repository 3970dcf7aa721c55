"""The production loop: trigger -> busy -> capture -> analyse -> verdict -> journal -> answer -> archive.

One facet at a time. Before the robot is released the facet's row is in the journal (and, when a dump is
due, its cropped frames are spooled), so nothing is lost if the station dies the next instant; workbook
rows and HDF5 dumps are written afterwards by the archiver, off the critical path.

A hard deadline guards every cycle. The analysis runs in a killable worker process and is abandoned when
the remaining time runs out; a capture that hangs past the deadline is abandoned by a watchdog thread,
which answers the robot "fault: timeout" and journals the fault while the station's thread is still stuck,
and the station reopens its camera when that thread comes back. Any StationError in a cycle becomes a
fault answer with its reason code; the loop then takes the next facet.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import logging
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

from ..calibrate.geometry import load_reference, station_reference
from ..calibrate.settings import calibration_settings
from ..calibrate.store import check_cycle
from ..devices.protocols import WARNING_BITS, FacetRequest
from ..errors import StationError, TriggerError
from ..live.operator_commands import take_commands
from ..live.status import StatusFile
from ..memory import trim_heap
from ..recipes import Recipe
from ..result.health import HealthSettings, LineHealth
from ..result.record import RecordHead
from ..result.shift import cycle_seconds
from ..serials import clean_serial, raw_for_record
from . import console as _console
from .clock import StationClock
from .cycle import Cycle, CycleOutcome
from .display import ALARM as DISPLAY_ALARM
from .display import DisplayCheck
from .drift import DriftMonitor
from .frames import capture_sequence
from .link import LinkWatch
from .marks import ALARM as GEOMETRY_ALARM
from .marks import MarkCheck
from .opened import Station
from .reference import AGE_ALARM, ReferenceCheck
from .reference import ALARM as REFERENCE_ALARM
from .temperature import TemperatureCheck
from .worker import AnalysisWorker

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunSettings:
    """``[run]`` in station.toml.

    Attributes
    ----------
    deadline_s : float
        Hard limit from trigger to answer; past it the robot gets "fault: timeout".
    dump_every_n : int
        Dump every n-th facet (0: never on a schedule).
    dump_failed : bool
        Dump every failed, invalid or faulted facet whose frames exist.
    heartbeat_s : float
        Heartbeat period toward the robot/PLC.
    poll_s : float
        How long one wait for a facet lasts before the loop looks at its stop flag.
    camera_timeout_s : float
        Longest wait for one frame.
    min_free_gb : float
        Below this much free space in data_dir no dump is written (the row still is), and the log warns.
    dump_keep_days, dump_max_gb : float
        Retention of dumps: older or beyond the total size, the oldest go first.
    late_grace_s : float
        An analysis still running at the deadline (the robot already answered "fault: timeout") may
        finish this much later, in its retired worker, while the standby measures the next facet; its
        figures are then journaled and its frames dumped, marked late.
    warmup : bool
        Analyse one capture before the station reports ready, so the first facet is not the slowest.
    standby_worker : bool
        Keep a second analysis worker started and warm, which takes over at once after a timeout or a
        crash, so the next facet is measured normally (a few hundred MB more memory at full resolution).
    alarm_faults_in_row, alarm_yield_window : int
        The line alarm's rules (:mod:`sofast_station.result.health`): faults in a row, and the newest facets of
        a recipe whose yield is compared with its recent yield.
    reference_every_h : float
        Warn (the alarm ``line-reference-age``) when no reference recipe's facet was measured for this long,
        hours; 0: never (:mod:`sofast_station.station.reference`).
    display_level_tolerance : float
        The display's self-test (:mod:`sofast_station.station.display`): the alarm ``line-display`` when the
        fringes' mean level departs from the radiometric table's by more; 0: no check.
    """

    deadline_s: float = 10.0
    dump_every_n: int = 0
    dump_failed: bool = True
    heartbeat_s: float = 1.0
    poll_s: float = 0.5
    camera_timeout_s: float = 2.0
    min_free_gb: float = 2.0
    dump_keep_days: float = 90.0
    dump_max_gb: float = 50.0
    late_grace_s: float = 10.0
    warmup: bool = True
    standby_worker: bool = True
    alarm_faults_in_row: int = 3
    alarm_yield_window: int = 20
    reference_every_h: float = 0.0
    display_level_tolerance: float = 0.015


def _recent_by_recipe(journal, n: int = 1000) -> dict:
    """Recipe name -> its newest journaled records (oldest first), for the line-health yield baseline; empty when
    the journal cannot be read (the rule then starts from this run's facets)."""
    out: dict = {}
    if journal is None:
        return out
    try:
        rows = journal.recent(n)
    except Exception as exc:           # the alarm is an aid: never stop the line for it
        log.warning("line health: cannot read the journal's recent facets: %s", exc)
        return out
    for row in rows:
        out.setdefault(str(row.record.get("recipe") or "default"), []).append(row.record)
    return out


def new_cycle_id() -> str:
    """Sortable and unique: UTC time to the millisecond plus 8 random hex digits (a cycle's id comes from
    the runner's :class:`~.clock.StationClock`, which also keeps ids increasing when the clock steps back)."""
    return StationClock().next_cycle()[0]


def _journal_newest(journal) -> tuple[str | None, _dt.datetime | None]:
    """The journal's newest cycle id and row time (None, None when it has none or cannot say)."""
    try:
        rows = journal.recent(1)
    except Exception:           # a journal that cannot be read here says so when the row is written
        return None, None
    if not rows:
        return None, None
    try:
        when = _dt.datetime.fromisoformat(rows[-1].time)
    except (TypeError, ValueError):
        when = None
    return rows[-1].cycle_id, when


class JournalFailed(StationError):
    """The journal could not be written (a full or read-only disk): the station stops after answering."""


class LockedTrigger:
    """The trigger shared by the loop, the heartbeat thread and the watchdog."""

    def __init__(self, trigger):
        self.trigger = trigger
        self.lock = threading.RLock()

    def __getattr__(self, name):
        method = getattr(self.trigger, name)

        def call(*args, **kwargs):
            with self.lock:
                return method(*args, **kwargs)
        return call


class StationRunner:
    """Runs cycles until stopped.

    Parameters
    ----------
    station : Station
        Devices, configuration and calibration (camera, display, range finder).
    trigger :
        The robot/PLC handshake (Trigger protocol).
    journal : Journal
        The append-only journal (thread-safe).
    archiver :
        The archiver (woken after each cycle), or None.
    recipes : dict[str, Recipe]
    settings : RunSettings
    submit : callable
        ``submit(cycle_id, record, dump)`` journals the record durably, first spooling *dump* (a dict
        with the cropped frames, crop box, full shape and measured distance) when it is not None.
    """

    def __init__(self, station: Station, trigger, journal, archiver, recipes: dict[str, Recipe],
                 settings: RunSettings, submit, console=print):
        self.station = station
        self.trigger = LockedTrigger(trigger)
        self.journal = journal
        #: The wall clock, watched for steps; cycle ids go on from the journal's newest (station/clock.py).
        last_id, last_time = _journal_newest(journal)
        self.clock = StationClock(last_cycle_id=last_id, last_time=last_time)
        self.archiver = archiver
        self.recipes = recipes
        self.settings = settings
        self.submit = submit
        self.console = console
        self.stop_event = threading.Event()
        #: Late results of abandoned analyses, queued by the retired workers' threads, kept by the loop.
        self.late_results: queue.SimpleQueue = queue.SimpleQueue()
        #: The robot/PLC link: outages logged once, then once a minute; reconnects after a growing pause.
        self.link = LinkWatch(settings.poll_s)
        self._pause = self.stop_event.wait          # the pause between reconnects (tests give their own)
        self.cycles = 0
        self.fatal: StationError | None = None     # set when the station must stop (journal not writable)
        cam = station.config.geometry.camera
        self.worker = AnalysisWorker(station.config.geometry, station.config.fringes, cam.shape,
                                     standby=settings.standby_worker)
        # The designs' optical traces are the same for every facet of a type: made now, not in a cycle.
        self.worker.prepare_optics([(r.design, r.optics) for r in recipes.values()
                                    if r.optics is not None and r.ensemble is None])
        self._heartbeat_thread = threading.Thread(target=self._heartbeat, name="heartbeat", daemon=True)
        self.answer_lock = threading.Lock()
        self._calibration_policy = calibration_settings(station.config)[0]
        self._calibration_warned = False
        #: How many facets this run expects (the console's n/N), when known.
        self.expected_total: int | None = None
        #: Called with each answered CycleOutcome, after the robot's answer (the monitor's pictures).
        self.hooks: list = []
        self.status = StatusFile(station.config.data_dir)
        # the records this line measures with, for the page: a record written meanwhile is not in force until
        # the next start (and calibrate refuses to write one while the line runs)
        in_force = {k: v for k, v in station.calibration_entry().items() if k != "warnings"}
        in_force["radiometric_created"] = station.radiometric.created
        self.status.update(in_force=in_force)
        self.paused = False
        self._manual_serial: str | None = None
        self._last_request: FacetRequest | None = None
        #: Drift alarms: the control-chart rules on each recipe's recent facets (off without a baseline).
        self.drift = DriftMonitor(station.config, recipes, journal)
        #: The line's own health (result/health.py): faults in a row, yield collapse, cycles at the deadline.
        self.health = LineHealth(settings.deadline_s, HealthSettings(faults_in_row=settings.alarm_faults_in_row,
                                                                     yield_window=settings.alarm_yield_window),
                                 _recent_by_recipe(journal))
        #: The fixture's marks in every white frame (station/marks.py): a moved camera stops the judging.
        self.marks = MarkCheck.open(station.config)
        self._geometry_alarm: str | None = None
        if self.marks is not None and self.marks.held:
            self._raise_geometry_alarm(self.marks.alarm_text())
        #: The screen's and the hall's temperature per facet (station/temperature.py), in every row and budget.
        self.temperature = TemperatureCheck.open(station.config, self.marks.record if self.marks else None)
        #: The reference every shift (station/reference.py): its last result, the hold it may put the line on.
        pose = (getattr(station.config, "commissioned", None) or {}).get("pose") or {}
        self.reference = ReferenceCheck(station.config.data_dir, settings.reference_every_h, pose.get("record_id"))
        self._reference_age: str | None = None
        #: The display's response on every facet (station/display.py): an alarm, no hold.
        self.display = None
        if settings.display_level_tolerance > 0 and getattr(station, "radiometric", None) is not None:
            self.display = DisplayCheck(station.radiometric, station.config.fringes, settings.display_level_tolerance,
                                        recipes["default"].analysis.mask_threshold_dn)
        if self.reference.hold:
            self._line_alarms({REFERENCE_ALARM: self.reference.hold})

    def check_drift(self, recipe: str, record: dict) -> None:
        """Drift alarm: the rules on the recipe's recent facets; alarms go to the record (journal row),
        the log, the status file (console and web page); the PLC's warning bit follows with the answer."""
        try:
            alarms = self.drift.check(recipe, record)
        except Exception:                   # an aid, never a reason to stop the line or fail the facet
            log.exception("%s: the drift check failed; the facet is answered without it", record.get("serial"))
            return
        if alarms:
            record["drift_alarms"] = alarms
            log.warning("%s: DRIFT ALARM, recipe %s: %s", record.get("serial"), recipe, " | ".join(alarms))
            self.status.alarm(f"drift-{recipe}", f"drift in recipe {recipe} at facet {record.get('serial')}: "
                                                 + " | ".join(alarms))

    def judge_line(self, record: dict, cycle_s: float | None) -> int:
        """The line's health after one answered facet (:class:`~sofast_station.result.health.LineHealth`): an alarm
        raised or cleared goes to the status file (the page, OPC UA), the log and the console; returns the
        warning bits the robot/PLC gets with this answer (``WARNING_BITS["line"]`` while any line alarm holds)."""
        try:
            changed = self.health.add(str(record.get("recipe") or "default"), record, cycle_s)
        except Exception:                   # an aid, never a reason to stop the line
            log.exception("the line-health check failed; the facet is answered without it")
            return 0
        self._line_alarms(changed)
        held = self._geometry_alarm or self.reference.hold or (self.display is not None and self.display.alarm)
        return WARNING_BITS["line"] if self.health.alarms or held else 0

    def judge_reference(self, record: dict, recipe) -> dict:
        """A reference recipe's facet judged against its certificate (:mod:`sofast_station.station.reference`):
        its verdict becomes the comparison's; beyond the limits the line holds (alarm ``line-reference``), within
        them a hold ends. Returns the record's ``station_checks.reference``."""
        twin = recipe.reference == "twin"
        certificate = station_reference(self.station) if twin else load_reference(recipe.reference)
        before = self.reference.hold
        entry = self.reference.judged(record, certificate, recipe.name)
        if self.reference.hold != before:
            self._line_alarms({REFERENCE_ALARM: self.reference.hold})
        return entry

    def station_checks(self, white: np.ndarray, cycle_id: str | None = None, serial: str | None = None,
                       frames: np.ndarray | None = None) -> dict:
        """The line's checks of itself on this cycle: the fixture's marks in its white frame
        (:class:`~sofast_station.station.marks.MarkCheck`), the temperature
        (:class:`~sofast_station.station.temperature.TemperatureCheck`) and, given the cycle's *frames*, the
        display's response (:class:`~sofast_station.station.display.DisplayCheck`). Returns the record's
        ``station_checks``
        (empty without either); its ``marks.withhold``, when set, is why the facet must not be judged. The
        geometry alarm follows the marks' hold."""
        checks: dict = {}
        if self.temperature is not None:
            checks["temperature"] = self.temperature.check()
        if self.display is not None and frames is not None:
            before = self.display.alarm
            try:
                checks["display"] = self.display.check(frames)
            except Exception:                    # a bug in the self-test must not stop the line
                log.exception("the display's self-test failed; the facet is measured without it")
            if self.display.alarm != before:
                self._line_alarms({DISPLAY_ALARM: self.display.alarm})
        age = self.reference.age_text()
        if age != self._reference_age:
            self._reference_age = age
            self._line_alarms({AGE_ALARM: age})
        if self.marks is None:
            self._show_health(checks, serial)
            return checks
        try:
            entry = self.marks.check(white, cycle_id, serial)
        except Exception as exc:              # a bug in the check must not judge facets on an unchecked camera
            log.exception("the fixture marks' check failed")
            entry = {"withhold": f"the fixture marks' check failed ({exc}): the facet is not judged; see the log"}
        if entry.get("withhold") and self.marks.held:
            self._raise_geometry_alarm(self.marks.alarm_text())
        elif entry.get("withhold"):
            log.warning("%s: %s", serial, entry["withhold"])
        checks["marks"] = entry
        self._show_health(checks, serial)
        return checks

    def _show_health(self, checks: dict, serial: str | None) -> None:
        """The page's lines on the station's own health (the status file's ``station_health``), from this cycle's
        checks: beside the facets' verdicts, so the operator sees the station judged too."""
        health = {}
        marks = checks.get("marks")
        if marks is not None:
            limit = self.marks.settings.max_turn_mrad if self.marks is not None else float("nan")
            turn = marks.get("turn_mrad")
            health["geometry (fixture marks)"] = (
                f"HOLD: {marks['withhold']}" if marks.get("withhold") else
                f"{marks.get('found')}/{marks.get('marks')} marks where commissioned: apparent camera turn "
                f"{(turn[0] ** 2 + turn[1] ** 2) ** 0.5:.3f} mrad (limit {limit:g}) at {serial}" if turn else "-")
        temp = checks.get("temperature")
        if temp is not None:
            health["temperature"] = (f"not read: {temp['error']}" if temp.get("error") else
                                     f"hall {temp['hall_c']:.1f} degC, screen {temp['screen_c']:.1f} degC: "
                                     f"{temp['delta_k']['hall']:+.1f} K and {temp['delta_k']['screen']:+.1f} K from "
                                     f"commissioning ({temp['commissioned']['from']}), in every facet's U")
        display = checks.get("display")
        if display is not None and "error" in display:
            health["display (response)"] = (
                f"{'ALARM: ' if self.display.alarm else ''}fringes' mean level {display['level']:.4f} of the white, "
                f"the radiometric table draws {display['expected_level']:.4f} ({display['error']:+.4f}, tolerance "
                f"{display['tolerance']:g})")
        last = self.reference.state.get("last")
        if self.reference.hold:
            health["reference"] = f"HOLD: {self.reference.hold}"
        elif last:
            health["reference"] = (f"{last.get('serial')} ({last.get('recipe')}) at {last.get('time')}: "
                                   f"{last.get('errors') or 'judged'}, within its certificate's limits; "
                                   f"f x / y errors of the last references: {self.reference.trend_text()}")
        if health and health != self.status.data.get("station_health"):
            self.status.update(station_health=health)

    def _raise_geometry_alarm(self, text: str | None) -> None:
        if text is None or text == self._geometry_alarm:
            return
        self._geometry_alarm = text
        self._line_alarms({GEOMETRY_ALARM: text})

    def _line_alarms(self, changed: dict) -> None:
        for name, text in changed.items():
            self.status.alarm(name, text)
            if text is not None:
                log.error("LINE ALARM: %s", text)
                self.console(f"LINE ALARM: {text}")
            else:
                log.warning("line alarm %s cleared", name)
                self.console(f"line alarm cleared ({name})")

    def check_calibration(self, dark_frame: np.ndarray | None) -> list[str]:
        """Judge the calibration again for this facet (age, and the dark level of its dark frame).

        Returns the warnings for the facet's record; raises StaleCalibrationError when the station refuses
        stale records. The log hears of it when the calibration goes stale and when it is fresh again,
        not on every facet.
        """
        status = self.station.calibration
        if status is None:
            return []
        # (a capture without a dark frame, a fixed pattern's one frame: its age only)
        dark_dn = None if dark_frame is None else float(np.mean(dark_frame, dtype=np.float64))
        try:
            warnings = check_cycle(status, self._calibration_policy, dark_dn).warnings
        except StationError:
            if not self._calibration_warned:
                log.error("the calibration went stale: facets are refused until it is renewed")
            self._calibration_warned = True
            raise
        if warnings and not self._calibration_warned:
            log.warning("calibration stale from this facet on (recorded in every row): %s", "; ".join(warnings))
        elif not warnings and self._calibration_warned:
            log.info("calibration checks pass again")
        self._calibration_warned = bool(warnings)
        return warnings

    # ------------------------------------------------------------------ loop
    def _heartbeat(self) -> None:
        warned = False
        while not self.stop_event.wait(self.settings.heartbeat_s):
            if getattr(self.trigger.trigger, "finished", False) or self.link.down:
                continue                     # the last facet placed, or the link down: the loop reconnects
            try:
                self.trigger.heartbeat()
                warned = False
            except StationError as exc:
                if not warned:               # once per failure streak, not every second
                    log.warning("heartbeat failed: %s", exc)
                warned = True

    def stop(self) -> None:
        """Finish the current facet, then stop."""
        self.stop_event.set()

    def run(self, max_cycles: int | None = None, on_outcome=None) -> list[CycleOutcome]:
        """Take facets until stopped, *max_cycles* are done, or the (simulated) robot has no more.

        Each finished cycle goes to *on_outcome* when given, and is then dropped (a station that runs
        for months keeps nothing per facet); without it the outcomes are returned (tests, benchmarks).
        Frames are never kept past their cycle.
        """
        outcomes = []
        if not self._heartbeat_thread.is_alive():
            self._heartbeat_thread.start()
        try:
            while not self.stop_event.is_set():
                if max_cycles is not None and self.cycles >= max_cycles:
                    break
                self.supervise()
                self._keep_late_results()
                for operator_request in self._take_commands():
                    done = self.cycle(operator_request)
                    if on_outcome is not None:
                        on_outcome(done)
                    else:
                        outcomes.append(done)
                if self.paused:
                    self.stop_event.wait(min(self.settings.poll_s, 0.25))
                    continue
                try:
                    self.trigger.ready()
                    request = self.trigger.wait_for_facet(self.settings.poll_s)
                except TriggerError as exc:
                    self._link_failed(exc)
                    continue
                self.link.ok()
                self.status.alarm("plc", None)
                if request is None:
                    if getattr(self.trigger.trigger, "finished", False):
                        break
                    continue
                outcome = self.cycle(request)
                if on_outcome is not None:
                    on_outcome(outcome)
                else:
                    outcomes.append(outcome)
                if self.fatal is not None:
                    raise self.fatal
        finally:
            self.stop_event.set()
        return outcomes

    def _take_commands(self) -> list[FacetRequest]:
        """Act on the operators' commands (live/operator_commands.py); returns the re-measurements to run."""
        remeasure = []
        for cmd in take_commands(self.station.config.data_dir):
            log.info("operator command %s%s (%s)", cmd.name, f" {cmd.serial!r}" if cmd.serial else "",
                     cmd.source or "no source")
            if cmd.name in ("pause", "resume"):
                self.paused = cmd.name == "pause"
            elif cmd.name == "serial":
                self._manual_serial = cmd.serial
                self.status.update(manual_serial=cmd.serial)
            elif cmd.name == "remeasure":
                last = self._last_request
                if last is None:
                    log.warning("re-measure asked for, but no facet has been measured since the start")
                    continue
                remeasure.append(FacetRequest(serial=last.serial, recipe=last.recipe,
                                              extra={"operator": "remeasure"}))
                if self.expected_total:
                    self.expected_total += 1              # one cycle more than the robot's
        if not remeasure:
            # with re-measurements queued the state says "measuring" until they are done; each cycle's end
            # then says "paused" if a pause was asked for, so "paused" always means no facet is being taken
            self.status.update(state="paused" if self.paused else "idle")
        return remeasure

    def supervise(self) -> None:
        """Between facets: restart a dead analysis worker or archiver (logged), so the line goes on."""
        self.worker.supervise()
        check = getattr(self.archiver, "supervise", None)
        if check is not None:
            check()

    def warm_up(self) -> None:
        """Capture once and analyse it in the worker before the station reports ready.

        The first analysis in a fresh process pays for imports, caches and page faults (seconds); paid
        here, the first facet is not the slowest. It is analysed as a facet is, with the recipe's optical
        figures and the uncertainty, so the worker also keeps the design's trace and the uncertainty's
        sensitivities (seconds on their own) before the first facet. A warm-up that fails (no facet in
        the fixture) is logged and does not stop the station.
        """
        t = time.perf_counter()
        try:
            recipe = self.recipes["default"]
            job = self.station.job_for(recipe)
            raw, _ = capture_sequence(self.station.display, self.station.camera, job.shows(self.station.config.fringes),
                                      recipe.analysis.mask_threshold_dn, timeout_s=self.settings.camera_timeout_s)
            distance = float(self.station.range_finder.measure())
            capture_s = time.perf_counter() - t
            for first in (True, False):
                t_an = time.perf_counter()
                self.worker.warm_up(raw, job, distance, timeout_s=max(60.0, 3 * self.settings.deadline_s),
                                    uncertainty=self.station.config.uncertainty)
                if first:
                    log.info("warm-up: one capture analysed in %.1f s", time.perf_counter() - t)
            # the second analysis is what every facet pays: with the capture, it must fit the deadline
            analysis_s = time.perf_counter() - t_an
            log.info("warm-up: a capture takes %.1f s and an analysis %.1f s (deadline %g s)", capture_s, analysis_s,
                     self.settings.deadline_s)
            text = self.health.startup(capture_s, analysis_s)
            if text is not None:
                self._line_alarms({"line-startup": text})
            # a camera moved while the station was off is caught before the first facet
            found = self.station_checks(raw[1], None, "warm-up").get("marks", {})
            if found.get("withhold"):
                log.error("warm-up: %s", found["withhold"])
        except StationError as exc:
            log.warning("warm-up capture not analysed (%s); the first facet may be slower", exc)
            self.reopen_camera()

    def _link_failed(self, exc: BaseException) -> None:
        """The handshake failed while waiting for a facet: alarm, reconnect, pause; logged by the link watch
        once, then once a minute while the outage lasts (it was five lines a second)."""
        pause = self.link.failed(exc)
        self.status.alarm("plc", f"robot/PLC handshake failed: {exc}")
        reopen = getattr(self.trigger.trigger, "reopen", None)
        if reopen:
            try:
                reopen()
            except StationError as again:
                pause = self.link.failed(again)
        self._pause(pause)

    def reopen_trigger(self) -> None:
        reopen = getattr(self.trigger.trigger, "reopen", None)
        if reopen:
            try:
                reopen()
            except StationError as exc:
                log.error("could not reconnect to the robot/PLC: %s", exc)
        time.sleep(min(1.0, self.settings.poll_s))

    # ------------------------------------------------------------------ one cycle
    def cycle(self, request: FacetRequest) -> CycleOutcome:
        """One facet, from the robot's request to its answer: a :class:`~sofast_station.station.cycle.Cycle`
        of its own (docs/architecture.md, steps 3-9), with the next cycle id from the line's clock and the
        request accepted (:meth:`accept`). Never raises for a bad facet."""
        t0 = time.perf_counter()
        cycle_id, clock_warning = self.clock.next_cycle()
        self.cycles += 1
        request = self.accept(request, cycle_id)
        return Cycle(self, request, cycle_id, clock_warning, t0=t0).run()

    def accept(self, request: FacetRequest, cycle_id: str) -> FacetRequest:
        """The request as the cycle uses it: one safe serial for the journal, workbook, dump and page (what
        was sent goes to the record's ``serial_raw``), or the serial an operator typed for this facet."""
        serial, note = clean_serial(request.serial)
        if note:
            log.warning("%s (cycle %s)", note, cycle_id)
            request = dataclasses.replace(request, serial=serial,
                                          extra={**request.extra, "serial_raw": raw_for_record(request.serial)})
        if self._manual_serial is not None and not request.extra.get("operator"):
            manual, note = clean_serial(self._manual_serial)
            extra = {k: v for k, v in request.extra.items() if k != "serial_raw"}   # the robot's: serial_read now
            extra.update(serial_read=request.serial, serial_source="operator")
            if note:
                log.warning("%s (cycle %s, typed by an operator)", note, cycle_id)
                extra["serial_raw"] = raw_for_record(self._manual_serial)
            request = dataclasses.replace(request, serial=manual, extra=extra)
            self._manual_serial = None
            self.status.data["manual_serial"] = None
        self._last_request = request
        return request

    def journal_failed(self, exc: BaseException) -> None:
        """The journal cannot be written: after this facet's fault answer the station stops."""
        log.critical("the journal cannot be written (%s): the station stops after answering this facet; free "
                     "disk space or fix the data folder's permissions, then start again", exc)
        if self.fatal is None:
            self.fatal = JournalFailed(f"the journal could not be written: {exc}; free disk space or fix the "
                                       f"permissions of {self.station.config.data_dir}, then start again")
        self.stop_event.set()

    def reopen_camera(self) -> None:
        reopen = getattr(self.station, "reopen_camera", None)
        if reopen:
            try:
                reopen()
            except StationError as exc:
                log.error("could not reopen the camera: %s", exc)

    # ------------------------------------------------------------------ records
    def head(self, cycle_id: str, request: FacetRequest, recipe_name: str, cal_warnings=(),
              facet: str | None = None, checks: dict | None = None) -> RecordHead:
        """The head of this cycle's record (:class:`~sofast_station.result.record.RecordHead`), dated by the
        runner's clock (station/clock.py); the serial as received goes to ``serial_raw`` when making it safe
        changed it."""
        extra = dict(request.extra)
        raw = extra.pop("serial_raw", None)
        head = self.station.record_head(request.serial, list(cal_warnings), facet=facet, cycle_id=cycle_id,
                                        recipe=recipe_name, serial_raw=raw,
                                        request={"recipe": request.recipe, "dump": request.dump, **extra},
                                        station_checks=checks or None)
        return dataclasses.replace(head, time=self.clock.now_iso())

    def report(self, record: dict, answer: str) -> None:
        """The facet's console line, its line in logs/station.log and the live status; the cycle time shown is
        the record's own (:func:`~sofast_station.result.shift.cycle_seconds`), as on the page and OPC UA."""
        cycle_s = cycle_seconds(record)
        self.console(_console.facet_line(record, answer, cycle_s, self.cycles, self.expected_total))
        log.info("%s", _console.log_line(record, answer, cycle_s, self.cycles, self.expected_total))
        if answer != "fault" or not str((record.get("reasons") or [""])[0]).startswith(("camera", "timeout")):
            self.status.alarm("camera", None)
        self.status.update(state="paused" if self.paused else "fault" if answer == "fault" else "idle")

    def _keep_late_results(self) -> None:
        """Between facets, in the loop's thread: journal and dump the late results that came in (they are
        queued by the retired workers' threads, so that the records, the spools of tens of MB and the
        journal are written where every other facet's are, not in a thread per late result)."""
        while True:
            try:
                keep = self.late_results.get_nowait()
            except queue.Empty:
                return
            keep()
            keep = None
            trim_heap()                 # the late facet's frames and result: back to the system

    def close(self) -> None:
        self.stop_event.set()
        if self.temperature is not None:
            self.temperature.close()
        self.worker.close()             # waits for an abandoned analysis within its grace: it queues its result
        self._keep_late_results()
        self.status.close()
