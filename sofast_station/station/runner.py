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
import threading
import time
import uuid
from dataclasses import dataclass, field

import numpy as np

from ..calibrate.settings import calibration_settings
from ..calibrate.store import check_cycle
from ..devices.protocols import FAULT_CODES, WARNING_BITS, FacetRequest
from ..errors import AnalysisTimeout, CameraError, StationError, TriggerError
from ..result.faults import fault_reason
from ..result.record import RecordHead, build_record
from ..result.verdict import judge
from ..serials import clean_serial
from . import console as _console
from .commands import take_commands, take_dump_next
from .drift import DriftMonitor
from .frames import capture_sequence, crop, crop_box, restore
from .heliostat import analysis_design, loop_record
from .heliostat import crop_box as heliostat_crop_box
from .opened import Station
from .recipes import Recipe, choose_recipe
from .status import StatusFile
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
        finish this much later; its figures are then journaled and its frames dumped, marked late.
    warmup : bool
        Analyse one capture before the station reports ready, so the first facet is not the slowest.
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


@dataclass
class CycleOutcome:
    """One facet's cycle, as answered to the robot and journaled."""

    cycle_id: str
    serial: str
    answer: str                       # pass | fail | invalid | fault
    record: dict
    fault_code: int = 0
    cycle_s: float = 0.0
    dumped: bool = False
    frames: np.ndarray | None = field(default=None, repr=False)
    #: The analysis's valid pixels (camera size) and its thinned per-pixel results, for the monitor.
    valid: np.ndarray | None = field(default=None, repr=False)
    preview: dict | None = field(default=None, repr=False)
    #: The uncertainty's sensitivities the analysis used (a record), written into the facet's dump.
    sensitivities: dict | None = field(default=None, repr=False)


def new_cycle_id() -> str:
    """Sortable and unique: UTC time to the millisecond plus 8 random hex digits."""
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")[:-4] + "-" + uuid.uuid4().hex[:8]


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
        self.archiver = archiver
        self.recipes = recipes
        self.settings = settings
        self.submit = submit
        self.console = console
        self.stop_event = threading.Event()
        self.cycles = 0
        self.fatal: StationError | None = None     # set when the station must stop (journal not writable)
        cam = station.config.geometry.camera
        self.worker = AnalysisWorker(station.config.geometry, station.config.fringes, cam.shape)
        # The designs' optical traces are the same for every facet of a type: made now, not in a cycle.
        self.worker.prepare_optics([(r.design, r.optics) for r in recipes.values()
                                    if r.optics is not None and r.ensemble is None])
        self._heartbeat_thread = threading.Thread(target=self._heartbeat, name="heartbeat", daemon=True)
        self._answer_lock = threading.Lock()
        self._calibration_policy = calibration_settings(station.config)[0]
        self._calibration_warned = False
        #: How many facets this run expects (the console's n/N), when known.
        self.expected_total: int | None = None
        #: Called with each answered CycleOutcome, after the robot's answer (the monitor's pictures).
        self.hooks: list = []
        self.status = StatusFile(station.config.data_dir)
        self.paused = False
        self._manual_serial: str | None = None
        self._last_request: FacetRequest | None = None
        #: Drift alarms: the control-chart rules on each recipe's recent facets (off without a baseline).
        self.drift = DriftMonitor(station.config, recipes, journal)

    def _check_drift(self, recipe: str, record: dict) -> None:
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

    def _check_calibration(self, dark_frame: np.ndarray) -> list[str]:
        """Judge the calibration again for this facet (age, and the dark level of its dark frame).

        Returns the warnings for the facet's record; raises StaleCalibrationError when the station refuses
        stale records. The log hears of it when the calibration goes stale and when it is fresh again,
        not on every facet.
        """
        status = self.station.calibration
        if status is None:
            return []
        dark_dn = float(np.mean(dark_frame, dtype=np.float64))
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
        while not self.stop_event.wait(self.settings.heartbeat_s):
            if getattr(self.trigger.trigger, "finished", False):
                continue                     # the simulated robot has placed its last facet
            try:
                self.trigger.heartbeat()
            except StationError as exc:
                log.warning("heartbeat failed: %s", exc)

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
                    log.error("robot/PLC handshake failed: %s; reconnecting", exc)
                    self.status.alarm("plc", f"robot/PLC handshake failed: {exc}")
                    self._reopen_trigger()
                    continue
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
        """Act on the operators' commands (station/commands.py); returns the re-measurements to run."""
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
            raw, _ = capture_sequence(self.station.display, self.station.camera, self.station.config.fringes,
                                      recipe.analysis.mask_threshold_dn, timeout_s=self.settings.camera_timeout_s)
            distance = float(self.station.range_finder.measure())
            self.worker.analyse(raw, analysis_design(recipe, self.station.config), recipe.analysis, distance,
                                timeout_s=max(60.0, 3 * self.settings.deadline_s), optics=recipe.optics,
                                uncertainty=self.station.config.uncertainty)
            log.info("warm-up: one capture analysed in %.1f s", time.perf_counter() - t)
        except StationError as exc:
            log.warning("warm-up capture not analysed (%s); the first facet may be slower", exc)
            self._reopen_camera()

    def _reopen_trigger(self) -> None:
        reopen = getattr(self.trigger.trigger, "reopen", None)
        if reopen:
            try:
                reopen()
            except StationError as exc:
                log.error("could not reconnect to the robot/PLC: %s", exc)
        time.sleep(min(1.0, self.settings.poll_s))

    # ------------------------------------------------------------------ one cycle
    def cycle(self, request: FacetRequest) -> CycleOutcome:
        t0 = time.perf_counter()
        cycle_id = new_cycle_id()
        self.cycles += 1
        serial, note = clean_serial(request.serial)
        if note:                             # one safe serial for the journal, workbook, dump and page
            log.warning("%s (cycle %s)", note, cycle_id)
            request = dataclasses.replace(request, serial=serial,
                                          extra={**request.extra, "serial_as_sent": ascii(request.serial[:200])})
        if self._manual_serial is not None and not request.extra.get("operator"):
            request = dataclasses.replace(request, serial=clean_serial(self._manual_serial)[0],
                                          extra={**request.extra, "serial_read": request.serial,
                                                 "serial_source": "operator"})
            self._manual_serial = None
            self.status.data["manual_serial"] = None
        self._last_request = request
        serial = request.serial
        state = {"answered": False, "stage": "start"}
        timings: dict[str, float] = {}
        self.status.update(state="measuring", serial=serial, cycle_id=cycle_id)
        try:
            if not request.extra.get("operator"):       # a re-measurement: the robot did not ask
                self.trigger.busy()
        except TriggerError as exc:
            log.error("%s: could not signal busy: %s", serial, exc)
        # The watchdog answers the robot at the deadline whatever this thread is doing.
        watchdog = threading.Timer(max(0.1, self.settings.deadline_s - 0.2), self._expire,
                                   args=(cycle_id, request, state, t0))
        watchdog.daemon = True
        watchdog.start()
        frames = raw_shape = box = distance = None
        outcome = None
        cal_warnings: list[str] = []
        try:
            recipe = choose_recipe(self.recipes, request)
            inject = getattr(self.station, "inject", None)
            hang_s = inject(serial) if inject else 0.0
            t = time.perf_counter()
            state["stage"] = "capture"
            raw, notes = capture_sequence(self.station.display, self.station.camera, self.station.config.fringes,
                                          recipe.analysis.mask_threshold_dn, timeout_s=self.settings.camera_timeout_s)
            distance = float(self.station.range_finder.measure())
            timings["capture"] = time.perf_counter() - t
            # (a heliostat: the box around every facet, not its largest region)
            box = (heliostat_crop_box if recipe.ensemble is not None else crop_box)(
                raw[0], raw[1], recipe.analysis.mask_threshold_dn)
            frames, raw_shape = crop(raw, box), raw.shape[1:]
            cal_warnings = self._check_calibration(raw[0])
            del raw
            # Past the deadline the watchdog answers "timeout"; the analysis may still finish within the
            # grace period, and its figures are then journaled and dumped as a late result.
            budget = self.settings.deadline_s - (time.perf_counter() - t0) - 0.3 + self.settings.late_grace_s
            if budget <= 0:
                raise AnalysisTimeout(f"the capture took {timings['capture']:.1f} s, past the "
                                      f"{self.settings.deadline_s:g} s deadline")
            t = time.perf_counter()
            state["stage"] = "analysis"
            res = self.worker.analyse(restore(frames, box, raw_shape), analysis_design(recipe, self.station.config),
                                      recipe.analysis, distance, timeout_s=budget, hang_s=hang_s,
                                      optics=recipe.optics, uncertainty=self.station.config.uncertainty)
            timings["analysis"] = time.perf_counter() - t
            # The ground truth (simulated station) is that of the station's own facet type.
            truth = self.station.truth(res.valid) if recipe.design.name == self.station.config.design.name else None
            head = self._head(cycle_id, request, recipe.name, cal_warnings, facet=recipe.design.name)
            if recipe.ensemble is not None:       # a heliostat: one entry per facet (docs/heliostats.md)
                record = loop_record(head, res.figures, recipe, truth, measured_distance_m=distance,
                                     capture_notes=notes, timings=timings)
            else:
                record = build_record(
                    head, figures=res.figures, verdict=judge(res.figures, recipe.design, recipe.limits,
                                                             recipe.quality),
                    truth=truth, measured_distance_m=distance, capture_notes=notes,
                    timings={**timings, **{f"analysis_{k}": v for k, v in res.figures.get("timings_s", {}).items()}})
                self._check_drift(recipe.name, record)
            outcome = CycleOutcome(cycle_id, serial, record["verdict"], record, valid=res.valid,
                                   preview=res.preview, sensitivities=getattr(res, "sensitivities", None))
        except Exception as exc:          # a bad facet must never stop the line
            code, reason = fault_reason(exc)
            if code == FAULT_CODES["internal"]:
                log.exception("%s: internal error", serial)
            record = self._fault_record(cycle_id, request, code, reason, timings, cal_warnings)
            outcome = CycleOutcome(cycle_id, serial, "fault", record, fault_code=code)
            if isinstance(exc, CameraError):
                self.status.alarm("camera", f"camera lost at facet {serial}: {exc}")
                self._reopen_camera()
        finally:
            watchdog.cancel()
        outcome.frames = frames
        if frames is not None:
            outcome.record["crop_box"] = list(box)
        with self._answer_lock:
            late = state["answered"]
            state["answered"] = True
        try:
            if late:
                self._finish_late(outcome, request, t0, state, raw_shape=raw_shape, box=box, distance=distance)
            else:
                self._finish(outcome, request, t0, raw_shape=raw_shape, box=box, distance=distance)
        finally:
            outcome.frames = None             # nothing of the frames outlives the cycle
        return outcome

    def _expire(self, cycle_id: str, request: FacetRequest, state: dict, t0: float) -> None:
        """Watchdog: the cycle reached its deadline with its thread still busy (a hung capture or a slow
        analysis): journal and answer "fault: timeout" now; the cycle's thread may still bring a late result."""
        with self._answer_lock:
            if state["answered"]:
                return
            state["answered"] = True
            stage = state["stage"]
        reason = (f"timeout: no result within the {self.settings.deadline_s:g} s cycle deadline "
                  f"({stage} did not return)")
        state["reason"] = reason
        log.error("%s: %s", request.serial, reason)
        record = self._fault_record(cycle_id, request, FAULT_CODES["timeout"], reason, {})
        record["timings_s"]["until_journal"] = time.perf_counter() - t0
        try:
            self.submit(cycle_id, record, None)
        except (OSError, StationError) as exc:
            self._journal_failed(exc)
        try:
            if not request.extra.get("operator"):
                self.trigger.fault(FAULT_CODES["timeout"], reason)
        except TriggerError as exc:
            log.error("could not answer the robot: %s", exc)
        self._report(record, "fault", time.perf_counter() - t0)
        if stage == "capture":
            # Closing the camera is how a blocked grab is aborted; the station's thread then comes back.
            self._reopen_camera()

    def _finish_late(self, outcome: CycleOutcome, request: FacetRequest, t0: float, state: dict, raw_shape, box,
                     distance) -> None:
        """The cycle's thread came back after the watchdog answered "timeout": keep what was measured.

        The robot's answer stays the timeout; the journaled row gets the figures (or the fault) and is
        marked late, and the frames are dumped (a timeout is a fault).
        """
        record = outcome.record
        late_by = time.perf_counter() - t0 - self.settings.deadline_s
        timeout_reason = state.get("reason", "timeout")
        reasons = list(record.get("reasons", []))
        if outcome.answer != "fault":
            record["late_verdict"] = outcome.answer
            note = (f"late result: the analysis finished {late_by:.1f} s after the deadline; its verdict would "
                    f"have been {outcome.answer}")
        else:
            note = f"late: {reasons.pop(0) if reasons else 'fault'}"
        record["reasons"] = [timeout_reason, note] + reasons
        record.update({"verdict": "fault", "fault_code": FAULT_CODES["timeout"], "late": True,
                       "late_by_s": round(late_by, 3)})
        outcome.answer, outcome.fault_code = "fault", FAULT_CODES["timeout"]
        dump = None
        if self._dump_due(outcome, request):
            dump = {"frames": outcome.frames, "crop_box": box, "full_shape": raw_shape,
                    "measured_distance_m": distance, "sensitivities": outcome.sensitivities}
        try:
            self.submit(outcome.cycle_id, record, dump, amend=True)
            outcome.dumped = dump is not None
        except (OSError, StationError) as exc:
            log.error("%s: the late result of cycle %s could not be journaled: %s", outcome.serial,
                      outcome.cycle_id, exc)
        outcome.cycle_s = time.perf_counter() - t0           # until the late result (the robot left earlier)
        # The console already has this facet's line (the timeout): the log says what became of it.
        log.warning("%s: %s (cycle %s; the robot was answered timeout)", outcome.serial, note, outcome.cycle_id)
        if self.archiver is not None:
            self.archiver.wake()
        outcome.valid = outcome.preview = None         # as after the hooks of an answered facet

    def _journal_failed(self, exc: BaseException) -> None:
        """The journal cannot be written: after this facet's fault answer the station stops."""
        log.critical("the journal cannot be written (%s): the station stops after answering this facet; free "
                     "disk space or fix the data folder's permissions, then start again", exc)
        if self.fatal is None:
            self.fatal = JournalFailed(f"the journal could not be written: {exc}; free disk space or fix the "
                                       f"permissions of {self.station.config.data_dir}, then start again")
        self.stop_event.set()

    def _dump_due(self, outcome: CycleOutcome, request: FacetRequest) -> bool:
        s = self.settings
        if outcome.frames is None:
            return False
        if take_dump_next(self.station.config.data_dir):
            return True
        return bool(request.dump or (s.dump_every_n and self.cycles % s.dump_every_n == 0)
                    or (s.dump_failed and outcome.answer in ("fail", "invalid", "indeterminate", "fault")))

    def _finish(self, outcome: CycleOutcome, request: FacetRequest, t0: float, raw_shape, box, distance) -> None:
        """Journal (and spool), then answer the robot: in that order."""
        record = outcome.record
        dump = None
        if self._dump_due(outcome, request):
            dump = {"frames": outcome.frames, "crop_box": box, "full_shape": raw_shape,
                    "measured_distance_m": distance, "sensitivities": outcome.sensitivities}
        record["timings_s"]["until_journal"] = time.perf_counter() - t0
        try:
            try:
                self.submit(outcome.cycle_id, record, dump)
                outcome.dumped = dump is not None
            except (OSError, StationError) as exc:
                if dump is None:
                    raise
                # The row matters more than the dump: keep the row, say why the dump is missing.
                log.error("%s: the frames for the dump could not be spooled (%s); journaling the row without",
                          outcome.serial, exc)
                record.setdefault("reasons", []).append(f"dump not written: {exc}")
                self.submit(outcome.cycle_id, record, None)
        except (OSError, StationError) as exc:
            # Not even the row could be written: the robot must still hear that this facet was not recorded.
            self._journal_failed(exc)
            reason = f"archive: the result could not be journaled ({exc})"
            record.update({"verdict": "fault", "fault_code": FAULT_CODES["archive"]})
            record["reasons"] = [reason] + list(record.get("reasons", []))
            outcome.answer, outcome.fault_code = "fault", FAULT_CODES["archive"]
        try:
            if request.extra.get("operator"):
                pass                                   # a re-measurement: the robot did not ask
            elif outcome.answer == "fault":
                self.trigger.fault(outcome.fault_code, record["reasons"][0] if record.get("reasons") else "fault")
            else:
                self.trigger.done(outcome.answer, warnings=WARNING_BITS["drift"] if record.get("drift_alarms") else 0)
        except TriggerError as exc:
            log.error("%s: could not answer the robot: %s", outcome.serial, exc)
            self._reopen_trigger()
        outcome.cycle_s = time.perf_counter() - t0
        self._report(record, outcome.answer, outcome.cycle_s)
        if self.archiver is not None:
            self.archiver.wake()
        for hook in self.hooks:
            try:
                hook(outcome)
            except Exception:                  # the monitor's extras must never stop the line
                log.exception("%s: a facet hook failed", outcome.serial)
        outcome.valid = outcome.preview = outcome.sensitivities = None   # the hooks and the dump had them

    def _reopen_camera(self) -> None:
        reopen = getattr(self.station, "reopen_camera", None)
        if reopen:
            try:
                reopen()
            except StationError as exc:
                log.error("could not reopen the camera: %s", exc)

    # ------------------------------------------------------------------ records
    def _head(self, cycle_id: str, request: FacetRequest, recipe_name: str, cal_warnings=(),
              facet: str | None = None) -> RecordHead:
        """The head of this cycle's record (:class:`~sofast_station.result.record.RecordHead`)."""
        return self.station.record_head(request.serial, list(cal_warnings), facet=facet, cycle_id=cycle_id,
                                        recipe=recipe_name,
                                        request={"recipe": request.recipe, "dump": request.dump, **request.extra})

    def _fault_record(self, cycle_id, request, code, reason, timings, cal_warnings=()) -> dict:
        return build_record(self._head(cycle_id, request, request.recipe or "", cal_warnings), fault=(code, reason),
                            timings=timings)

    def _report(self, record: dict, answer: str, cycle_s: float) -> None:
        """The facet's console line, its line in logs/station.log and the live status."""
        self.console(_console.facet_line(record, answer, cycle_s, self.cycles, self.expected_total))
        log.info("%s", _console.log_line(record, answer, cycle_s, self.cycles, self.expected_total))
        if answer != "fault" or not str((record.get("reasons") or [""])[0]).startswith(("camera", "timeout")):
            self.status.alarm("camera", None)
        self.status.update(state="paused" if self.paused else "fault" if answer == "fault" else "idle")

    def close(self) -> None:
        self.stop_event.set()
        self.worker.close()
        self.status.close()
