"""One facet's cycle, from the robot's request to its answer: :class:`Cycle`, which the line
(:class:`~sofast_station.station.runner.StationRunner`) makes for each facet and drives.

A cycle holds what is its own: the request, its id and start, what it captured (:class:`CycleCapture`), the
watchdog that answers the robot at the deadline whatever the cycle's thread is doing, and whether the robot
has been answered. What lasts between cycles (the devices, the worker, the journal, the status, the operators'
commands, the clock) is the line's, reached through ``self.line``.

The order of one cycle (docs/architecture.md, steps 3-9): busy; capture, crop, the calibration check on the
dark frame; the analysis in the worker process within what is left of the deadline (the facet's job:
``station.job_for``); verdict and record; the record journaled, with its frames spooled when a dump is due;
and only then the robot's answer. An analysis abandoned at the deadline is answered "timeout" at once and its
late result kept between facets; a result that comes after the watchdog answered is kept as late.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..devices.protocols import FAULT_CODES, WARNING_BITS, FacetRequest
from ..errors import AnalysisTimeout, CameraError, StationError, TriggerError
from ..live.operator_commands import take_dump_next
from ..recipes import choose_recipe
from ..measure.fixture_marks import widen_for_pose
from ..measure.thermal import widen_for_temperature
from ..result.faults import fault_reason
from ..result.record import build_record
from ..result.shift import cycle_seconds
from .frames import capture_sequence, crop, restore
from .marks import CameraMoved
from .reference import ReferenceFailed
from .worker import RERUN_FACTOR

log = logging.getLogger("sofast_station.station.runner")    # the line's log, as station/link.py's


@dataclass
class CycleOutcome:
    """One facet's cycle, as answered to the robot and journaled."""

    cycle_id: str
    serial: str
    answer: str                       # pass | fail | invalid | fault
    record: dict
    fault_code: int = 0
    #: The facet's cycle time (result/shift.py ``cycle_seconds``: trigger to journal row), what the console,
    #: the page and OPC UA show; ``release_s``: trigger to the robot's release (its answer sent), what the
    #: cycle benchmark times.
    cycle_s: float = 0.0
    release_s: float = 0.0
    dumped: bool = False
    frames: np.ndarray | None = field(default=None, repr=False)
    #: The analysis's valid pixels (camera size) and its thinned per-pixel results, for the monitor.
    valid: np.ndarray | None = field(default=None, repr=False)
    preview: dict | None = field(default=None, repr=False)
    #: The uncertainty's sensitivities the analysis used (a record), written into the facet's dump.
    sensitivities: dict | None = field(default=None, repr=False)


@dataclass
class CycleCapture:
    """What a cycle captured and keeps until its answer: the frames cropped to the facet (what a dump keeps),
    the crop box in the camera image, the camera image's size and the measured distance (metres). Empty
    when the capture failed."""

    frames: np.ndarray | None = field(default=None, repr=False)
    box: tuple | None = None
    full_shape: tuple | None = None
    distance_m: float | None = None

    def restored(self) -> np.ndarray:
        """The frames at the camera's full size (outside the crop: 0), as the analysis takes them."""
        return restore(self.frames, self.box, self.full_shape)

    def dump(self, sensitivities: dict | None) -> dict:
        """What :meth:`Service.submit <sofast_station.station.service.Service.submit>` spools for a dump."""
        return {"frames": self.frames, "crop_box": self.box, "full_shape": self.full_shape,
                "measured_distance_m": self.distance_m, "sensitivities": sensitivities}


@dataclass
class _Late:
    """An analysis abandoned at the deadline that may still finish: its future and what its record needs."""

    future: object
    recipe: object
    job: object
    notes: list
    timings: dict
    cal_warnings: list
    t_analysis: float


class Cycle:
    """One facet's cycle (see the module docstring); :meth:`run` once.

    Parameters
    ----------
    line : StationRunner
        The line the cycle runs on: its station, trigger, worker, settings, journal (``submit``), status and
        hooks.
    request : FacetRequest
        The robot's (or an operator's re-measurement) request.
    cycle_id : str
        From the line's clock.
    clock_warning : str or None
        Set when the wall clock stepped back before this cycle: every record of the cycle carries it.
    t0 : float, optional
        When the request came (``time.perf_counter()``); default: now.
    """

    def __init__(self, line, request: FacetRequest, cycle_id: str, clock_warning: str | None = None,
                 t0: float | None = None):
        self.line = line
        self.request = request
        self.cycle_id = cycle_id
        self.clock_warning = clock_warning
        self.t0 = time.perf_counter() if t0 is None else t0
        self.captured = CycleCapture()
        self.late: _Late | None = None
        #: What the watchdog needs: whether the robot was answered, the stage that did not return, the
        #: timeout's reason and when its row was journaled.
        self.answered = False
        self.stage = "start"
        self.reason: str | None = None
        self.until_journal: float | None = None
        #: What the line's checks of itself found on this cycle's frames (the record's ``station_checks``).
        self.checks: dict = {}

    # ------------------------------------------------------------------ the cycle
    def run(self) -> CycleOutcome:
        """The cycle: busy, the watchdog, the measurement (:meth:`measure`); then journal and answer
        (:meth:`finish`), or keep a late result (:meth:`follow_late`, :meth:`finish_late`).

        Never raises for a bad facet: any error in the measurement becomes a fault answer with its reason
        code (:mod:`sofast_station.result.faults`)."""
        line, request = self.line, self.request
        line.status.update(state="measuring", serial=request.serial, cycle_id=self.cycle_id)
        try:
            if not request.extra.get("operator"):       # a re-measurement: the robot did not ask
                line.trigger.busy()
        except TriggerError as exc:
            log.error("%s: could not signal busy: %s", request.serial, exc)
        # The watchdog answers the robot at the deadline whatever this thread is doing.
        watchdog = threading.Timer(max(0.1, line.settings.deadline_s - 0.2), self.expire)
        watchdog.daemon = True
        watchdog.start()
        try:
            outcome = self.measure()
        finally:
            watchdog.cancel()
            # A watchdog that has fired may still be answering the robot (journal, then the trigger): the
            # loop's next ready() must come after that answer, not in the middle of it.
            watchdog.join()
        outcome.frames = self.captured.frames
        if self.captured.frames is not None:
            outcome.record["crop_box"] = list(self.captured.box)
        with line.answer_lock:
            answered = self.answered
            self.answered = True
        try:
            if self.late is not None:
                # The analysis was abandoned at the deadline and may still finish: the row is the timeout now
                # (answered here, or by the watchdog), its figures and dump follow when the late result comes.
                self.follow_late(outcome, answered)
            elif answered:
                self.finish_late(outcome)
            else:
                self.finish(outcome)
        finally:
            outcome.frames = None             # nothing of the frames outlives the cycle
        return outcome

    def measure(self) -> CycleOutcome:
        """Measure the facet: the recipe, the capture (cropped into ``self.captured``, which the answer and the
        dump use), the calibration check on its dark frame, the analysis in the worker within what is left of
        the deadline, the verdict and the record. Any error becomes a fault outcome; an analysis abandoned at
        the deadline leaves its future in ``self.late``. ``self.stage`` tells the watchdog what did not
        return."""
        line, request, captured = self.line, self.request, self.captured
        timings: dict[str, float] = {}
        cal_warnings: list[str] = []
        try:
            recipe = choose_recipe(line.recipes, request)
            # the recipe's job (the simulated station may give one that injects the faults its tests ask for)
            job = line.station.job_for(recipe, request.serial)
            t = time.perf_counter()
            self.stage = "capture"
            shown = job.shows(line.station.config.fringes)
            raw, notes = capture_sequence(line.station.display, line.station.camera, shown,
                                          recipe.analysis.mask_threshold_dn, timeout_s=line.settings.camera_timeout_s)
            captured.distance_m = float(line.station.range_finder.measure())
            timings["capture"] = time.perf_counter() - t
            # (a heliostat's job: the box around every facet, not its largest region)
            captured.box = job.crop_box(*raw[:2])
            captured.frames, captured.full_shape = crop(raw, captured.box), raw.shape[1:]
            # which frame is dark and which white is what the capture showed (a fixed pattern's one frame has
            # neither: no dark level to check, the marks, lit by the hall, in its dot frame, no fringes to check
            # the display's response on)
            labels = [p.label for p in shown.patterns()]
            cal_warnings = line.check_calibration(raw[labels.index("dark")] if "dark" in labels else None)
            # the fixture's marks in the white frame: a camera that moved since commissioning judges no facet
            self.checks = line.station_checks(raw[labels.index("white")] if "white" in labels else raw[0],
                                              self.cycle_id, request.serial,
                                              frames=captured.frames if any(shown.slices().values()) else None)
            withhold = self.checks.get("marks", {}).get("withhold")
            if withhold:
                raise CameraMoved(withhold)
            if line.reference.hold and getattr(recipe, "reference", None) is None:
                raise ReferenceFailed(line.reference.hold)       # a reference judges the station: it is measured
            del raw
            # At the deadline this thread answers "timeout" itself (just before the watchdog would) and the
            # standby worker takes over for the next facet; the abandoned analysis may still finish within
            # the late grace in its retired worker, and its figures are then journaled and dumped as a late
            # result (follow_late).
            budget = line.settings.deadline_s - (time.perf_counter() - self.t0) - 0.3
            if budget <= 0:
                raise AnalysisTimeout(f"the capture took {timings['capture']:.1f} s, past the "
                                      f"{line.settings.deadline_s:g} s deadline")
            t = time.perf_counter()
            self.stage = "analysis"
            try:
                res = line.worker.analyse(captured.restored(), job, captured.distance_m, timeout_s=budget,
                                          uncertainty=line.station.config.uncertainty,
                                          late_s=line.settings.late_grace_s)
            except AnalysisTimeout as exc:
                if exc.late is not None:
                    self.late = _Late(exc.late, recipe, job, notes, dict(timings), list(cal_warnings), t)
                raise
            timings["analysis"] = time.perf_counter() - t
            if res.rerun_after_s is not None:
                notes = [*notes, f"the analysis had not answered after {res.rerun_after_s:.1f} s (over "
                                 f"{RERUN_FACTOR:g} times its usual time): it was run again on the standby worker; "
                                 f"this is the {'rerun' if res.rerun_answer == 'standby' else 'first'} analysis's "
                                 "result"]
            record = self.measured_record(recipe, job, res, notes, timings, cal_warnings)
            if job.kind == "facet":               # (a heliostat's facets are not one facet's trend)
                line.check_drift(recipe.name, record)
            return CycleOutcome(self.cycle_id, request.serial, record["verdict"], record, valid=res.valid,
                                preview=res.preview, sensitivities=getattr(res, "sensitivities", None))
        except Exception as exc:          # a bad facet must never stop the line
            code, reason = fault_reason(exc)
            if code == FAULT_CODES["internal"]:
                log.exception("%s: internal error", request.serial)
            record = self.fault_record(code, reason, timings, cal_warnings)
            if isinstance(exc, CameraError):
                line.status.alarm("camera", f"camera lost at facet {request.serial}: {exc}")
                line.reopen_camera()
            return CycleOutcome(self.cycle_id, request.serial, "fault", record, fault_code=code)

    # ------------------------------------------------------------------ records
    def clock_note(self) -> dict:
        """``{"clock_warning": ...}`` when the wall clock stepped back before this cycle (else empty)."""
        return {"clock_warning": self.clock_warning} if self.clock_warning else {}

    def measured_record(self, recipe, job, res, notes, timings, cal_warnings) -> dict:
        """The record of an analysed facet (in time or late): the job's record of its figures, with, on the
        simulated station, the truth of the station's own facet type."""
        station = self.line.station
        truth = station.truth(res.valid, job) if job.name == station.config.design.name else None
        pose_u = self.checks.get("marks", {}).get("pose_u")
        if pose_u:
            # what the marks' small shift leaves unknown of the fixture's pose, in the U's it reaches
            self.checks["marks"]["widened_U"] = widen_for_pose(res.figures, pose_u)
        thermal = self.checks.get("temperature", {}).get("u")
        if thermal and self.line.temperature is not None:
            # the screen's and the fixture's expansion since commissioning, in the U's they reach
            self.checks["temperature"]["widened_U"] = widen_for_temperature(res.figures, thermal,
                                                                            self.line.temperature.pitch_u)
        head = self.line.head(self.cycle_id, self.request, recipe.name, cal_warnings, facet=job.name,
                              checks=self.checks)
        record = job.record(head, res.figures, truth, timings, measured_distance_m=self.captured.distance_m,
                            capture_notes=notes, **self.clock_note())
        if getattr(recipe, "reference", None) is not None:
            # a reference judges the station: its verdict is its certificate's comparison (station/reference.py)
            record.setdefault("station_checks", {})["reference"] = self.line.judge_reference(record, recipe)
        return record

    def fault_record(self, code: int, reason: str, timings: dict, cal_warnings=()) -> dict:
        head = self.line.head(self.cycle_id, self.request, self.request.recipe or "", cal_warnings,
                              checks=self.checks)
        return build_record(head, fault=(code, reason), timings=timings, **self.clock_note())

    # ------------------------------------------------------------------ answers
    def expire(self) -> None:
        """Watchdog: the cycle reached its deadline with its thread still busy (a hung capture or a slow
        analysis): journal and answer "fault: timeout" now; the cycle's thread may still bring a late result."""
        line, request = self.line, self.request
        with line.answer_lock:
            if self.answered:
                return
            self.answered = True
            stage = self.stage
        reason = (f"timeout: no result within the {line.settings.deadline_s:g} s cycle deadline "
                  f"({stage} did not return)")
        self.reason = reason
        log.error("%s: %s", request.serial, reason)
        record = self.fault_record(FAULT_CODES["timeout"], reason, {})
        record["timings_s"]["until_journal"] = self.until_journal = time.perf_counter() - self.t0
        try:
            line.submit(self.cycle_id, record, None)
        except (OSError, StationError) as exc:
            line.journal_failed(exc)
        warnings = line.judge_line(record, self.until_journal)
        try:
            if not request.extra.get("operator"):
                line.trigger.fault(FAULT_CODES["timeout"], reason, warnings=warnings)
        except TriggerError as exc:
            log.error("could not answer the robot: %s", exc)
        line.report(record, "fault")
        if stage == "capture":
            # Closing the camera is how a blocked grab is aborted; the station's thread then comes back.
            line.reopen_camera()

    def dump_due(self, outcome: CycleOutcome) -> bool:
        """Whether this facet's frames are dumped: the operators' flag file, the request, every n-th facet, or
        a facet that did not pass."""
        s = self.line.settings
        if outcome.frames is None:
            return False
        if take_dump_next(self.line.station.config.data_dir):
            return True
        return bool(self.request.dump or (s.dump_every_n and self.line.cycles % s.dump_every_n == 0)
                    or (s.dump_failed and outcome.answer in ("fail", "invalid", "indeterminate", "fault")))

    def finish(self, outcome: CycleOutcome, dump: bool = True) -> None:
        """Journal (and spool), then answer the robot: in that order. *dump* False: no dump now (a late
        result may follow, which brings it)."""
        line, record = self.line, outcome.record
        wanted = dump and self.dump_due(outcome)
        spooled = self.captured.dump(outcome.sensitivities) if wanted else None
        record["timings_s"]["until_journal"] = time.perf_counter() - self.t0
        try:
            try:
                line.submit(outcome.cycle_id, record, spooled)
                outcome.dumped = spooled is not None
            except (OSError, StationError) as exc:
                if spooled is None:
                    raise
                # The row matters more than the dump: keep the row, say why the dump is missing.
                log.error("%s: the frames for the dump could not be spooled (%s); journaling the row without",
                          outcome.serial, exc)
                record.setdefault("reasons", []).append(f"dump not written: {exc}")
                line.submit(outcome.cycle_id, record, None)
        except (OSError, StationError) as exc:
            # Not even the row could be written: the robot must still hear that this facet was not recorded.
            line.journal_failed(exc)
            reason = f"archive: the result could not be journaled ({exc})"
            record.update({"verdict": "fault", "fault_code": FAULT_CODES["archive"]})
            record["reasons"] = [reason] + list(record.get("reasons", []))
            outcome.answer, outcome.fault_code = "fault", FAULT_CODES["archive"]
        warnings = line.judge_line(record, cycle_seconds(record))
        try:
            if self.request.extra.get("operator"):
                pass                                   # a re-measurement: the robot did not ask
            elif outcome.answer == "fault":
                line.trigger.fault(outcome.fault_code, record["reasons"][0] if record.get("reasons") else "fault",
                                   warnings=warnings)
            else:
                line.trigger.done(outcome.answer,
                                  warnings=warnings | (WARNING_BITS["drift"] if record.get("drift_alarms") else 0))
        except TriggerError as exc:
            log.error("%s: could not answer the robot: %s", outcome.serial, exc)
            line.reopen_trigger()
        outcome.release_s = time.perf_counter() - self.t0
        outcome.cycle_s = cycle_seconds(record)
        line.report(record, outcome.answer)
        if line.archiver is not None:
            line.archiver.wake()
        for hook in line.hooks:
            try:
                hook(outcome)
            except Exception:                  # the monitor's extras must never stop the line
                log.exception("%s: a facet hook failed", outcome.serial)
        outcome.valid = outcome.preview = outcome.sensitivities = None   # the hooks and the dump had them

    def follow_late(self, outcome: CycleOutcome, answered: bool) -> None:
        """An analysis abandoned at the deadline: journal and answer the timeout now (unless the watchdog did),
        without the dump; when the retired worker's result comes (or its grace ends), the line amends the row
        with the figures, marked late, and dumps the frames, between facets (:meth:`finish_late`)."""
        line, late = self.line, self.late
        self.late = None
        wanted = self.dump_due(outcome)                      # decided now: the flag file is for this facet
        if not answered:
            self.finish(outcome, dump=False)
            # the timeout's answer ends the facet's cycle, as when the watchdog answers (expire)
            self.until_journal = outcome.record["timings_s"]["until_journal"]
        if self.reason is None:
            self.reason = (outcome.record.get("reasons") or ["timeout"])[0]
        frames = outcome.frames
        timeout_record = outcome.record

        def done(fut) -> None:                     # in the retired worker's thread: hand it to the line
            line.late_results.put(lambda: keep(fut))

        def keep(fut) -> None:                     # in the line's thread, between facets
            try:
                res, error = fut.result(), None
            except BaseException as exc:          # the analysis's own error, late: kept in the row
                res, error = None, exc
            try:
                if res is not None:
                    late.timings["analysis"] = time.perf_counter() - late.t_analysis
                    record = self.measured_record(late.recipe, late.job, res, late.notes, late.timings,
                                                  late.cal_warnings)
                    result = CycleOutcome(self.cycle_id, outcome.serial, record["verdict"], record,
                                          sensitivities=res.sensitivities)
                else:
                    record = dict(timeout_record)
                    record["reasons"] = [fault_reason(error)[1] if error is not None else
                                         f"no result within the late grace of {line.settings.late_grace_s:g} s "
                                         "(the abandoned worker was killed)"]
                    result = CycleOutcome(self.cycle_id, outcome.serial, "fault", record,
                                          fault_code=outcome.fault_code)
                result.frames = frames
                self.finish_late(result, dump=wanted)
            except Exception:                      # a late result must never stop the line
                log.exception("%s: the late result of cycle %s could not be kept", outcome.serial, self.cycle_id)
            finally:
                result = None
        late.future.add_done_callback(done)

    def finish_late(self, outcome: CycleOutcome, dump: bool | None = None) -> None:
        """A result that came after the robot was answered "timeout" (the watchdog's, or this thread's at the
        deadline): keep what was measured.

        The robot's answer stays the timeout; the journaled row gets the figures (or the fault) and is
        marked late, and the frames are dumped (a timeout is a fault). *dump* says whether (decided at the
        deadline); None: decide now.
        """
        line, record = self.line, outcome.record
        late_by = time.perf_counter() - self.t0 - line.settings.deadline_s
        timeout_reason = self.reason or "timeout"
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
        # The robot was answered at the deadline: that ends the facet's cycle (result/shift.py cycle_seconds);
        # when the late result came is kept beside it.
        timings = record.setdefault("timings_s", {})
        timings["until_journal"] = self.until_journal
        timings["until_late_result"] = time.perf_counter() - self.t0
        outcome.answer, outcome.fault_code = "fault", FAULT_CODES["timeout"]
        wanted = self.dump_due(outcome) if dump is None else (dump and outcome.frames is not None)
        spooled = self.captured.dump(outcome.sensitivities) if wanted else None
        try:
            line.submit(outcome.cycle_id, record, spooled, amend=True)
            outcome.dumped = spooled is not None
        except (OSError, StationError) as exc:
            log.error("%s: the late result of cycle %s could not be journaled: %s", outcome.serial,
                      outcome.cycle_id, exc)
        outcome.cycle_s = outcome.release_s = timings["until_journal"]   # the robot left at the timeout
        # The console already has this facet's line (the timeout): the log says what became of it.
        log.warning("%s: %s (cycle %s; the robot was answered timeout)", outcome.serial, note, outcome.cycle_id)
        if line.archiver is not None:
            line.archiver.wake()
        outcome.valid = outcome.preview = None         # as after the hooks of an answered facet
