"""The analysis in a separate, killable process, with a warm standby beside it.

A hung analysis must not hang the line: the station runs its recipe's job (:mod:`sofast_station.job`)
in a long-lived worker process (spawned, so it shares no OpenGL or thread state with the station), hands
it the frames through shared memory (no 35 MB pickle per facet) and waits with a deadline. The worker
computes the camera's pixel rays once.

A second worker waits beside it, started, its optics traced and warmed on the warm-up capture: the
*standby*. When an analysis passes the deadline, or the worker dies, the standby takes over at once and a
new standby starts in the background, so the next facet is measured normally (it used to wait out the
late grace and a restart, 8-9 s, and time out too). The abandoned worker is not killed at once: it may
still finish within ``late_grace_s`` (its result is then journaled, marked late, through the
:class:`concurrent.futures.Future` the timeout carries), at a lower priority (:data:`RETIRED_NICE`) so
that it slows the facet the standby is measuring little, yet finishes on a busy machine; then it is killed.

A worker that dies *before* it begins a facet's analysis (killed or out of memory between facets, its
death not yet seen when the next facet arrives) costs that facet nothing: the worker marks each analysis
it begins in the shared memory, so the station knows the facet was never started and analyses it on the
standby within the facet's time budget. A worker that dies *during* an analysis answers that facet with
the worker fault (the facet itself may be what kills it), and the next facet is measured on the standby.
A worker killed while it starts is started again (:data:`START_ATTEMPTS` times).

An analysis that has not answered after :data:`RERUN_FACTOR` times its usual time is run again on the
standby only when its worker has *stalled* (:class:`_Progress`: neither runnable nor using the processor
over the last stretch: a deadlock, a stalled page-in, a stopped process). An analysis that is merely slow,
because the machine is busy, keeps computing: the analysis is deterministic, so a rerun would compute the
same thing on the same busy cores, halve the processor each of the two gets and let both miss the deadline
(on a loaded machine 0 of 4 late results were kept that way). When a rerun and its first analysis are both
abandoned at the deadline, whichever answers first within the grace is the late result.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import statistics
import threading
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures import wait as wait_futures
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory

import numpy as np

from ..errors import AnalysisTimeout, CaptureError, StationError, WorkerDied
from ..facet import FacetDesign
from ..fringes import FringeSet
from ..geometry import StationGeometry
from ..job import Capture
from ..measure.uncertainty import InputUncertainties
from ..memory import trim_heap
from ..optics import design_samples, facet_optics
from ..precompute import ray_table, warm_up
from ..result.optical_figures import DesignTraces
from .frames import crop, restore
from .memtrace import start_from_env

log = logging.getLogger(__name__)


def watch_parent(parent_pid: int | None = None, poll_s: float = 0.5) -> None:
    """In a child process: exit as soon as the process that started it (*parent_pid*; by default the
    present parent) is gone. Given the PID, a child whose parent died while it was still starting exits at
    once instead of taking its new parent (PID 1) for the one to watch.

    A station killed with SIGKILL cannot stop its children; without this they would live on under
    PID 1 (an orphaned archiver writing the data folder beside the restarted station). The check is a
    daemon thread comparing ``os.getppid()`` with its value at start, which, unlike
    ``PR_SET_PDEATHSIG``, does not fire when merely the parent's *thread* that spawned the child ends.
    """
    parent = os.getppid() if parent_pid is None else parent_pid
    if os.getppid() != parent:
        os._exit(0)

    def watch():
        while True:
            time.sleep(poll_s)
            if os.getppid() != parent:
                os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


@dataclass
class WorkerResult:
    """What comes back from the worker: the figures and the pixels the analysis kept."""

    figures: dict
    valid: np.ndarray
    seconds: float
    preview: dict | None = None
    #: The uncertainty's sensitivities the worker keeps for this recipe (a record, a few kB), for the dump.
    sensitivities: dict | None = None
    #: When the first worker did not answer within :data:`RERUN_FACTOR` times the recipe's usual analysis
    #: time and the facet was analysed again on the standby: the seconds waited before that; else None.
    rerun_after_s: float | None = None
    #: Whose answer this is when rerun: "standby" (the rerun's) or "first" (the slow worker's, first after all).
    rerun_answer: str | None = None


# --- worker process side -------------------------------------------------------------------------
_STATE: dict = {}


#: Bytes at the end of the shared memory past the frames: the number of the analysis the worker began last.
_BEGUN_BYTES = 8


def _frame_bytes(shape: tuple[int, int, int]) -> int:
    """The frames' bytes in the shared memory, rounded up so that the number after them is aligned."""
    n = int(np.prod(shape))
    return n + (-n) % _BEGUN_BYTES


def _begun_slot(shm: SharedMemory, shape: tuple[int, int, int]) -> np.ndarray:
    """The shared number (int64, past the frames) of the analysis the worker began last."""
    return np.ndarray((1,), dtype=np.int64, buffer=shm.buf, offset=_frame_bytes(shape))


def _fill(buffer: np.ndarray, frames: np.ndarray) -> None:
    """*frames* into the shared *buffer*, the rest of it black: a capture of fewer frames than the fringes'
    (a fixed pattern's: its job reads its own first frames) fits the buffer the fringes sized."""
    n = frames.shape[0]
    np.copyto(buffer[:n], frames)
    buffer[n:] = 0


def _init(shm_name: str, shape: tuple[int, int, int], geometry: dict, fringes: dict) -> None:
    watch_parent()
    shm = SharedMemory(name=shm_name)
    _STATE["shm"] = shm
    _STATE["frames"] = np.ndarray(shape, dtype=np.uint8, buffer=shm.buf)
    _STATE["begun"] = _begun_slot(shm, shape)
    _STATE["geometry"] = StationGeometry.from_dict(geometry)
    _STATE["fringes"] = FringeSet.from_dict(fringes)
    warm_up(_STATE["geometry"].camera)          # every pixel's ray before the first facet
    _STATE["rays"] = ray_table(_STATE["geometry"].camera)
    # What the analysis imports on first use, imported here rather than in a facet's cycle: the
    # uncertainty's pooled frame brightness needs scipy.special's F quantile from the second capture on
    # (the warm-up capture being the first).
    # lazy: scipy.special costs ~0.5 s; the station's process imports this module and never needs it
    import scipy.special  # noqa: F401
    start_from_env("worker")                    # off unless SOFAST_TRACEMALLOC_S is set (leak hunts)


def _run(ticket: int, job, distance_m: float, uncertainty: dict | None = None, attempt: int = 0):
    """Analyse the frames in the shared memory as *job* says (a :class:`~sofast_station.job.Job`, sent pickled with
    its ``kind``): the figures, the kept pixels (packed), the seconds, the operator's preview and the
    sensitivities. *attempt*: 0 for a facet's analysis, 1 for its rerun on the standby."""
    _STATE["begun"][0] = ticket          # begun: from here a death is this facet's (see the module's text)
    t = time.perf_counter()
    frames = np.array(_STATE["frames"])  # a private copy: the station may refill the buffer after a timeout
    inputs = None if uncertainty is None else InputUncertainties.from_dict(uncertainty)
    # Sensitivities are computed on the first facet of each recipe, the design's optical trace for each design,
    # and kept for the worker's life.
    out = job.analyse(Capture(frames, float(distance_m), _STATE["fringes"], _STATE["geometry"], _STATE["rays"]),
                      uncertainty=inputs, sensitivity_cache=_STATE.setdefault("sensitivities", {}),
                      design_traces=_STATE.setdefault("design_traces", DesignTraces()), attempt=attempt)
    result = (out.figures, np.packbits(out.valid), out.valid.shape, time.perf_counter() - t, job.preview(out),
              out.sensitivities)
    del out, frames
    trim_heap()                          # the per-pixel arrays' pages go back: the worker's memory stays flat
    return result


def _prepare_optics(designs: list) -> int:
    cache = _STATE.setdefault("design_traces", DesignTraces(max(4, len(designs))))
    for design, optics in designs:
        facet = FacetDesign.from_dict(design)
        scene, traced = cache.get(facet, optics)
        # One small trace through the measured facet's path, so the first facet runs warm code.
        points, slopes, _ = design_samples(facet, 2000)
        facet_optics(points, slopes, np.array([0.0, 0.0, 2.0 * facet.focal_length_m]), facet, optics,
                     scene=scene, design_result=traced)
    return len(designs)


def _ping() -> bool:
    return "rays" in _STATE


# --- station side -------------------------------------------------------------------------------------

#: How often a worker that dies while it starts (killed, out of memory) is started again before the
#: station gives up (it then says so, exit code 2): a kill -9 in the first seconds of `run` ended the run.
START_ATTEMPTS = 3
#: Longest wait for a worker to start (spawn, imports, pixel rays, optics traces), seconds.
START_TIMEOUT_S = 120.0
#: An analysis still running after this many times its recipe's usual time (the median of the last
#: :data:`USUAL_OF` analyses), in a worker that has stalled (:class:`_Progress`), is run again on the warm
#: standby; the first answer is the facet's. A worker that hangs (a deadlock, a stalled page-in, a stopped
#: process) then costs the facet a few seconds, not a timeout; an analysis that keeps computing (a facet
#: slow in itself, or a busy machine) is left to finish, or to time out and come late.
RERUN_FACTOR = 3.0
#: Never rerun before this many seconds (a quick recipe's scheduler hiccup is not a hang), seconds; also the
#: shortest stretch without progress that makes a worker stalled.
RERUN_MIN_S = 1.0
#: How many of a recipe's last analysis times make its usual time; none is rerun before :data:`RERUN_AFTER_N`.
USUAL_OF = 15
RERUN_AFTER_N = 3
#: How often the station looks at a slow analysis's worker (its state and processor time), seconds.
PROGRESS_POLL_S = 0.1
#: A worker that used less than this share of a core over a stretch, and was never seen runnable in it, has
#: stalled. An analysis computing on a busy machine is runnable whenever it is looked at and gets a few per
#: cent of a core even at a load of 50 on two cores; a blocked one (asleep, in a page-in, stopped) gets none
#: (its parent-watch thread wakes twice a second for microseconds).
STALLED_CPU_SHARE = 0.02
#: The niceness of an abandoned analysis within its late grace, above the station's (0-19). Not the lowest:
#: at 19 it gets 1.5 % of what a process of the station's priority gets, and on a machine busy with other
#: work it did not finish within the grace (0 of 5 late results kept beside two spinning processes; 1 of 4
#: at 5, a third of the share); at 2 it gets two thirds (4 of 4 kept), while the worker measuring the next
#: facet still wins a contested core 61 to 39 (docs/reliability.md, "Under load").
RETIRED_NICE = 2


_CLOCK_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 0.01


def process_state(pid: int) -> tuple[str, float] | None:
    """Process *pid*'s scheduler state (``R`` runnable, ``S`` asleep, ``D`` waiting on the disk, ``T``
    stopped...) and its processor time so far (user + system, every thread), seconds, from ``/proc``; None
    where that cannot be read (not Linux, or the process is gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[1].split()
        return fields[0].decode("ascii", "replace"), (int(fields[11]) + int(fields[12])) * _CLOCK_TICK_S
    except (OSError, IndexError, ValueError):
        return None


class _Progress:
    """Whether a worker's analysis is progressing: its state and processor time, sampled as the station waits.

    A worker that was never runnable and used (almost) no processor over a stretch has *stalled*: waiting on a
    lock, a page-in or a signal, not on the processor. One that computes slowly on a busy machine is runnable
    (waiting for a core counts) and does use some: it is *progressing*, and a rerun beside it would only
    share the same cores.
    """

    def __init__(self, pids: list[int]):
        self.pids = list(pids)
        self.samples: deque = deque()            # (time.perf_counter(), runnable, processor seconds)

    def sample(self, now: float | None = None) -> None:
        now = time.perf_counter() if now is None else now
        states = [process_state(pid) for pid in self.pids]
        if not states or any(s is None for s in states):
            self.samples.append((now, None, None))   # unknown: treated as stalled (a rerun, as before)
            return
        self.samples.append((now, any(s[0] == "R" for s in states), sum(s[1] for s in states)))

    def stalled(self, window_s: float, now: float | None = None) -> bool:
        """True when the samples cover the last *window_s* seconds and show no progress in them (or cannot
        be read); False while they do not cover it yet."""
        now = time.perf_counter() if now is None else now
        while len(self.samples) > 1 and self.samples[1][0] <= now - window_s:
            self.samples.popleft()               # keep one sample at or before the stretch's start
        if not self.samples or self.samples[0][0] > now - window_s + PROGRESS_POLL_S:
            return False
        if any(runnable is None for _, runnable, _ in self.samples):
            return True
        used = self.samples[-1][2] - self.samples[0][2]
        return not any(runnable for _, runnable, _ in self.samples) and \
            used < max(2 * _CLOCK_TICK_S, STALLED_CPU_SHARE * window_s)


class _Process:
    """One analysis process (a one-process pool) with its own shared frame buffer.

    Each worker has its own buffer: a retired worker may still read its frames while the standby that took
    over is given the next facet's.
    """

    def __init__(self, shape: tuple[int, int, int]):
        self.shape = shape
        # close() may run on two threads at once (a retired worker's waiter, and the station stopping)
        self._closing = threading.Lock()
        self.shm = SharedMemory(create=True, size=_frame_bytes(shape) + _BEGUN_BYTES)
        self.frames = np.ndarray(shape, dtype=np.uint8, buffer=self.shm.buf)
        self.begun = _begun_slot(self.shm, shape)
        self.begun[0] = 0
        self.pool: ProcessPoolExecutor | None = None
        self.warm = False

    def start(self, geometry: dict, fringes: dict, optics_designs: list, timeout_s: float = START_TIMEOUT_S) -> None:
        """Spawn the process and wait until it has its pixel rays (and the designs' optical traces).

        Raises BrokenProcessPool (it died), TimeoutError or OSError; the caller closes it then."""
        ctx = multiprocessing.get_context("spawn")
        self.pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_init,
                                        initargs=(self.shm.name, self.shape, geometry, fringes))
        self.pool.submit(_ping).result(timeout=timeout_s)
        self.prepare(optics_designs, timeout_s)

    def prepare(self, optics_designs: list, timeout_s: float = START_TIMEOUT_S) -> None:
        if optics_designs:
            self.pool.submit(_prepare_optics, optics_designs).result(timeout=timeout_s)

    def pids(self) -> list[int]:
        pool = self.pool
        return [p.pid for p in list((getattr(pool, "_processes", None) or {}).values())] if pool else []

    def alive(self) -> bool:
        pool = self.pool
        if pool is None or getattr(pool, "_broken", False):
            return False
        procs = list((getattr(pool, "_processes", None) or {}).values())
        return bool(procs) and all(p.is_alive() for p in procs)

    def lower_priority(self) -> None:
        """Run :data:`RETIRED_NICE` below the station from now on (a retired worker must not slow the one
        measuring much, yet still finish within its grace on a busy machine)."""
        if not hasattr(os, "setpriority"):
            return
        target = min(19, os.getpriority(os.PRIO_PROCESS, 0) + RETIRED_NICE)
        for pid in self.pids():
            try:
                os.setpriority(os.PRIO_PROCESS, pid, max(target, os.getpriority(os.PRIO_PROCESS, pid)))
            except OSError:
                pass

    def kill(self) -> None:
        pool, self.pool = self.pool, None
        if pool is not None:
            procs = list((getattr(pool, "_processes", None) or {}).values())
            for proc in procs:
                proc.kill()
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.join(5)                 # reap it: a zombie's PID would keep its temporary files "alive"

    def close(self) -> None:
        """Kill the process and free its shared frame buffer; a second call, from any thread, does nothing."""
        self.kill()
        with self._closing:
            shm, self.shm = self.shm, None
            if shm is None:
                return
            self.frames = self.begun = None
        shm.close()
        try:
            shm.unlink()
        except FileNotFoundError:
            pass


def _first_late(lates: list[tuple[Future, _Process, str]], rerun_after_s: float) -> Future:
    """One late result for an analysis and its rerun, both abandoned at the deadline: the first of *lates*
    (each ``(future, worker, "first" | "standby")``) to bring figures (or the analysis's own error); None
    when neither does within its grace. The other worker is then killed at once: its result would be
    dropped, and it takes a core from the line until its grace ends."""
    out: Future = Future()
    lock = threading.Lock()
    left = [len(lates)]

    def done(fut: Future, answer: str) -> None:
        with lock:
            left[0] -= 1
            if out.done():
                return
            error = fut.exception()
            res = None if error is not None else fut.result()
            if error is None and res is None and left[0] > 0:
                return                           # this one gave nothing; the other may still
            if error is not None:
                out.set_exception(error)
            else:
                if res is not None:
                    res.rerun_after_s, res.rerun_answer = rerun_after_s, answer
                out.set_result(res)
        for other, proc, _ in lates:
            if not other.done():
                proc.kill()                      # its waiter then sees the pool broken and closes it

    for fut, _, answer in lates:
        fut.add_done_callback(lambda f, a=answer: done(f, a))
    return out


def _result(out) -> WorkerResult:
    figures, packed, shape, seconds, preview, sensitivities = out
    valid = np.unpackbits(packed, count=int(np.prod(shape))).astype(bool).reshape(shape)
    return WorkerResult(figures, valid, seconds, preview, sensitivities)


class AnalysisWorker:
    """The analysis process the station measures with, and its warm standby.

    Parameters
    ----------
    geometry, fringes :
        The station's geometry and fringe definition (fixed for the workers' lives).
    shape : (int, int)
        The camera frame's (rows, columns).
    standby : bool
        Keep a second worker started and warm, which takes over at once after a timeout or a crash
        (``[run] standby_worker``); without it a replacement starts only then (seconds).
    """

    def __init__(self, geometry, fringes, shape: tuple[int, int], standby: bool = True):
        self._geometry = geometry.to_dict()
        self._fringes = fringes.to_dict()
        self._shape = (fringes.n_frames, *shape)
        self._use_standby = bool(standby)
        self._lock = threading.Lock()
        self._optics_designs: list = []          # (design dict, OpticsSettings) traced at every start
        self._warm_job: tuple | None = None      # the warm-up capture (cropped) and its analysis's inputs
        self._tickets = 0                        # analyses asked for so far
        self._active: _Process | None = None
        self._standby: _Process | None = None
        self._standby_thread: threading.Thread | None = None
        self._starting: list[_Process] = []      # being started (killed by close())
        self._retired: list[tuple[_Process, threading.Thread]] = []
        self._dismissed: list[threading.Thread] = []     # closing a worker a rerun replaced (_dismiss)
        self._closed = False
        self.starts = 0                          # worker processes started (the standbys included)
        self.takeovers = 0                       # times the standby took over
        self.reruns = 0                          # analyses run again on the standby (RERUN_FACTOR)
        self._usual: dict[str, deque] = {}       # recipe key -> its last analyses' wall times, s
        self._active = self._new_process()
        if self._use_standby:
            self._launch_standby()

    # -- starting ------------------------------------------------------------------------------------
    def _new_process(self) -> _Process:
        """A started worker; one killed while it starts is started again (START_ATTEMPTS in all)."""
        for attempt in range(1, START_ATTEMPTS + 1):
            t = time.perf_counter()
            proc = _Process(self._shape)
            with self._lock:
                if self._closed:
                    proc.close()
                    raise WorkerDied("the station is closing: no analysis worker is started")
                self._starting.append(proc)
            try:
                proc.start(self._geometry, self._fringes, self._optics_designs)
            except (BrokenProcessPool, FutureTimeout, OSError) as exc:
                proc.close()
                if self._closed:
                    raise WorkerDied("the station is closing: no analysis worker is started") from None
                if attempt == START_ATTEMPTS:
                    raise WorkerDied(f"the analysis worker could not start ({type(exc).__name__}: {exc}; "
                                     f"{START_ATTEMPTS} attempts); see the log, and check memory and the Python "
                                     "environment") from None
                log.warning("the analysis worker died while starting (%s: %s): starting it again (attempt %d of "
                            "%d)", type(exc).__name__, exc, attempt + 1, START_ATTEMPTS)
                continue
            finally:
                with self._lock:
                    if proc in self._starting:
                        self._starting.remove(proc)
            self.starts += 1
            log.info("analysis worker ready in %.1f s (process %s)", time.perf_counter() - t, proc.pids())
            return proc
        raise AssertionError("unreachable")

    def _launch_standby(self) -> None:
        """Start a standby in the background (when none is there or starting)."""
        with self._lock:
            if self._closed or self._standby is not None or self._standby_thread is not None:
                return
            self._standby_thread = threading.Thread(target=self._standby_main, name="analysis-standby", daemon=True)
            self._standby_thread.start()

    def _standby_main(self) -> None:
        try:
            proc = self._new_process()
            if self._warm_job is not None:
                self._warm(proc)
            with self._lock:
                if self._closed:
                    proc.close()
                else:
                    self._standby = proc
        except StationError as exc:
            if not self._closed:
                log.error("no standby analysis worker: %s; the next timeout or crash waits for a new start", exc)
        finally:
            with self._lock:
                self._standby_thread = None

    def _wait_standby(self, until: float) -> None:
        """Wait (until *until*, time.perf_counter seconds) for a standby being started or warmed."""
        thread = self._standby_thread
        if thread is not None:
            thread.join(max(0.0, until - time.perf_counter()))

    def _warm(self, proc: _Process) -> None:
        """Analyse the warm-up capture on *proc* (its first analysis pays for imports, caches, page faults
        and the uncertainty's sensitivities: seconds, paid here and not by a facet)."""
        cropped, box, full, args = self._warm_job
        _fill(proc.frames, restore(cropped, box, full))
        try:
            proc.pool.submit(_run, 0, *args).result(timeout=START_TIMEOUT_S)
            proc.warm = True
        except (BrokenProcessPool, FutureTimeout, RuntimeError, OSError) as exc:
            log.warning("the standby worker's warm-up analysis failed (%s); it takes over cold", exc)
        except StationError as exc:
            log.warning("the standby worker's warm-up analysis failed (%s); it takes over cold", exc)

    def prepare_optics(self, designs: list, timeout_s: float = START_TIMEOUT_S) -> None:
        """Trace each (design, OpticsSettings)'s design surface in the workers now, so that no facet's cycle
        pays for it; every worker started later traces them while it starts."""
        self._optics_designs = [(d.to_dict(), o) for d, o in designs]
        if not designs:
            return
        t = time.perf_counter()
        for attempt in (1, 2):
            try:
                self._ensure_active(time.perf_counter() + timeout_s)
                self._active.prepare(self._optics_designs, timeout_s)
                break
            except (BrokenProcessPool, RuntimeError) as exc:
                if attempt == 2:
                    raise WorkerDied(f"the analysis worker died twice while tracing the designs' optics ({exc})") \
                        from None
                log.warning("the analysis worker died while tracing the designs' optics (%s): replacing it", exc)
                self._replace(self._active)
        self._wait_standby(time.perf_counter() + timeout_s)
        with self._lock:
            standby = self._standby
        if standby is not None:
            try:
                standby.prepare(self._optics_designs, timeout_s)
            except (BrokenProcessPool, RuntimeError, FutureTimeout):
                self._drop_standby(standby)
        log.info("optics: %d design trace(s) ready in %.2f s", len(designs), time.perf_counter() - t)

    def warm_up(self, frames: np.ndarray, job, distance_m: float, timeout_s: float, uncertainty=None) -> WorkerResult:
        """Analyse one capture as *job* says before the first facet, in the worker and in the standby; the capture
        (cropped as the job crops) is kept to warm every later standby the same way."""
        res = self.analyse(frames, job, distance_m, timeout_s=timeout_s, uncertainty=uncertainty)
        box = job.crop_box(*frames[:2])
        self._warm_job = (crop(frames, box), box, frames.shape[1:],
                          (job, float(distance_m), None if uncertainty is None else uncertainty.to_dict()))
        self._active.warm = True
        self._wait_standby(time.perf_counter() + timeout_s)
        with self._lock:
            standby = self._standby
        if standby is not None and not standby.warm:
            self._warm(standby)
        return res

    # -- taking over ---------------------------------------------------------------------------------
    def _drop_standby(self, proc: _Process) -> None:
        with self._lock:
            if self._standby is proc:
                self._standby = None
        proc.close()
        self._launch_standby()

    def _promote(self) -> bool:
        """The standby becomes the worker at once (True), and a new standby starts in the background."""
        with self._lock:
            proc, self._standby = self._standby, None
        if proc is None:
            return False
        if not proc.alive():
            log.warning("the standby analysis worker had died: starting another")
            proc.close()
            return False
        self._active = proc
        self.takeovers += 1
        log.warning("the standby analysis worker (process %s) took over", proc.pids())
        self._launch_standby()
        return True

    def _replace(self, proc: _Process | None) -> None:
        """Close a dead or abandoned worker; the standby takes over, or a replacement starts."""
        if proc is not None:
            proc.close()
        if proc is self._active or proc is None:
            self._active = None
            if not self._promote():
                self._launch_standby()

    def _ensure_active(self, until: float) -> None:
        """A live worker to analyse with: the present one, else the standby at once, else the one being
        started (waited for until *until*, time.perf_counter seconds), else one started now."""
        if self._active is not None and self._active.alive():
            return
        if self._active is not None:
            log.error("the analysis worker (process %s) is gone", self._active.pids() or "?")
            self._replace(self._active)
            if self._active is not None:
                return
        if self._promote():
            return
        self._launch_standby()
        self._wait_standby(until)
        if self._promote():
            return
        if time.perf_counter() >= until:
            raise AnalysisTimeout("the analysis worker was being started for the facet's whole time budget; the "
                                  "facet was not analysed")
        self._active = self._new_process()

    def supervise(self) -> bool:
        """Between facets: a worker that died is replaced (the standby takes over), a dead standby restarted,
        a missing standby started; True when the worker was replaced."""
        replaced = False
        if self._active is not None and not self._active.alive():
            log.error("the analysis worker (process %s) is gone: replacing it", self._active.pids() or "?")
            self._replace(self._active)
            replaced = True
        elif self._active is None and not self._promote():
            self._launch_standby()               # none ready (a takeover's standby still starting): on its way
        with self._lock:
            standby = self._standby
        if standby is not None and not standby.alive():
            log.warning("the standby analysis worker (process %s) died: starting another", standby.pids() or "?")
            self._drop_standby(standby)
        elif self._use_standby:
            self._launch_standby()
        return replaced

    def _retire(self, proc: _Process, fut, grace_s: float) -> Future:
        """Abandon *proc*'s analysis at the deadline: the standby takes over now; *proc* keeps running it at
        a lower priority (:data:`RETIRED_NICE`) for up to *grace_s* seconds, then is killed. Returns the late
        result's future."""
        self._active = None
        if not self._promote():
            self._launch_standby()
        proc.lower_priority()
        return self._retire_only(proc, fut, grace_s)

    # -- analysing -------------------------------------------------------------------------------------
    def pids(self) -> list[int]:
        """Process ids of the worker measuring (empty while none is ready)."""
        proc = self._active
        return proc.pids() if proc is not None else []

    def standby_pids(self) -> list[int]:
        """Process ids of the standby (empty while none is ready)."""
        proc = self._standby
        return proc.pids() if proc is not None else []

    def alive(self) -> bool:
        """Whether the worker measuring runs (False after it died, or while none is ready)."""
        proc = self._active
        return proc is not None and proc.alive()

    def analyse(self, frames: np.ndarray, job, distance_m: float, timeout_s: float, uncertainty=None,
                late_s: float = 0.0) -> WorkerResult:
        """Analyse *frames* as *job* says (a :class:`~sofast_station.job.Job`); :class:`AnalysisTimeout` after
        *timeout_s* seconds.

        An analysis still running after :data:`RERUN_FACTOR` times the recipe's usual time in a worker that
        has stalled (:class:`_Progress`) is run again on the warm standby (which becomes the worker; the
        stalled one runs on at a lower priority) and the first of the two answers is the facet's
        (``WorkerResult.rerun_after_s`` says so); one that is still computing (a busy machine) is left to
        finish. At the timeout the standby takes over at once; the abandoned analysis (or the first of it and
        its rerun) may still finish within *late_s* seconds, through the timeout's ``late`` future. Errors
        raised by the analysis (StationError subclasses) come back as themselves.
        """
        if (frames.ndim != 3 or not 1 <= frames.shape[0] <= self._shape[0] or frames.shape[1:] != self._shape[1:]
                or frames.dtype != np.uint8):
            raise CaptureError(f"the capture is {frames.dtype} {frames.shape}, the station expects uint8 "
                               f"{self._shape}; check the camera's pixel format and size")
        t_end = time.perf_counter() + timeout_s
        key = str(job.name)
        args = (job, float(distance_m), None if uncertainty is None else uncertainty.to_dict())
        for attempt in (1, 2):
            self._ensure_active(t_end)
            proc = self._active
            left_s = t_end - time.perf_counter()
            if left_s <= 0:
                raise AnalysisTimeout(f"the analysis worker was being replaced for the facet's whole "
                                      f"{timeout_s:.1f} s; the facet was not analysed")
            _fill(proc.frames, frames)
            self._tickets += 1
            fut = None
            try:
                t_submit = time.perf_counter()
                fut = proc.pool.submit(_run, self._tickets, *args, 0)
                rerun_at, usual = self._rerun_after(key)
                if rerun_at is not None and rerun_at < left_s:
                    out = self._wait_or_rerun(proc, fut, frames, args, t_submit, t_end, timeout_s, late_s,
                                              rerun_at, usual)
                    if isinstance(out, WorkerResult):
                        return out
                else:
                    out = fut.result(timeout=max(left_s, 0.01))
                self._note_time(key, time.perf_counter() - t_submit)
                break
            except FutureTimeout:
                log.error("the analysis exceeded its %.1f s budget: the standby worker takes over%s", timeout_s,
                          f"; the analysis may still finish within {late_s:.0f} s" if late_s > 0 else "")
                late = self._retire(proc, fut, late_s)
                raise AnalysisTimeout(f"the analysis did not finish within {timeout_s:.1f} s; the standby worker "
                                      "took over", late=late) from None
            except (BrokenProcessPool, RuntimeError) as exc:
                begun = int(proc.begun[0]) == self._tickets
                self._replace(proc)
                if begun or attempt == 2:
                    log.error("the analysis worker died during the analysis (%s): replaced", exc)
                    raise WorkerDied("the analysis worker process died during this facet's analysis (killed or "
                                     "out of memory); the standby worker took over, the next facet is measured") \
                        from None
                log.warning("the analysis worker had died before this facet's analysis began (%s): analysing the "
                            "facet on the standby", exc)
            finally:
                # An analysis error is raised from the future, which keeps it: the error's traceback holds
                # this frame, and this frame the future, a reference cycle that would keep the cycle's
                # frames (tens of MB at full resolution) until the garbage collector's rare full pass.
                # Broken here.
                fut = None
        return _result(out)

    # -- a slow analysis run again -------------------------------------------------------------------
    def _note_time(self, key: str, seconds: float) -> None:
        self._usual.setdefault(key, deque(maxlen=USUAL_OF)).append(seconds)

    def _rerun_after(self, key: str) -> tuple[float | None, float]:
        """(seconds after which this recipe's analysis is run again on the standby, None: not now; its usual
        time, seconds)."""
        times = self._usual.get(key)
        if not self._use_standby or times is None or len(times) < RERUN_AFTER_N:
            return None, 0.0
        usual = statistics.median(times)
        return max(RERUN_FACTOR * usual, RERUN_MIN_S), usual

    def _wait_or_rerun(self, proc: _Process, fut, frames, args: tuple, t_submit: float, t_end: float,
                       timeout_s: float, late_s: float, rerun_at: float, usual: float):
        """Wait for *proc*'s analysis until *t_end*, watching its progress: past *rerun_at* seconds, once its
        worker has stalled for ``max(usual, RERUN_MIN_S)`` seconds, run it again on the standby (the
        rerun's :class:`WorkerResult`); while no warm standby is ready, one is started and the wait goes on.
        Returns the analysis's raw output, or a WorkerResult from :meth:`_rerun`; raises FutureTimeout at
        *t_end* (as ``fut.result`` would)."""
        window = max(usual, RERUN_MIN_S)
        # Samples from here on cover the stretch before rerun_at; until then the wait is a plain one.
        watch_from = t_submit + rerun_at - window - PROGRESS_POLL_S
        progress: _Progress | None = None
        while True:
            now = time.perf_counter()
            left = t_end - now
            if left <= 0:
                raise FutureTimeout()
            step = PROGRESS_POLL_S if progress is not None else max(watch_from - now, PROGRESS_POLL_S)
            try:
                return fut.result(timeout=min(step, left))
            except FutureTimeout:
                pass
            now = time.perf_counter()
            if progress is None:
                progress = _Progress(proc.pids())
            progress.sample(now)
            waited = now - t_submit
            if waited < rerun_at or t_end - now <= 1.5 * usual or not progress.stalled(window, now):
                continue
            res = self._rerun(proc, fut, frames, args, t_end, timeout_s, late_s, waited, usual)
            if res is not None:
                return res
            self._launch_standby()               # none ready (one still starting after a take-over): wait on

    def _rerun(self, proc: _Process, fut, frames, args: tuple, t_end: float, timeout_s: float, late_s: float,
               waited_s: float, usual: float) -> WorkerResult | None:
        """*proc*'s analysis has run *waited_s* seconds, at least RERUN_FACTOR times its *usual* (and RERUN_MIN_S):
        run it again on the standby, which becomes the worker, and answer with the first result. None when no
        warm standby is ready or too little time is left (the caller waits on and asks again, while time
        is left for a rerun)."""
        with self._lock:
            standby = self._standby
            ready = (standby is not None and standby.warm and standby.alive()
                     and t_end - time.perf_counter() > 1.5 * usual)
            if ready:
                self._standby = None
        if not ready:
            return None
        log.warning("the analysis has run %.1f s (its usual: %.2f s) and its worker has stalled (neither "
                    "computing nor waiting for a core): it is run again on the standby worker (process %s); the "
                    "first answer is the facet's", waited_s, usual, standby.pids())
        self._active = standby
        self.takeovers += 1
        self.reruns += 1
        self._launch_standby()
        proc.lower_priority()
        _fill(standby.frames, frames)
        self._tickets += 1
        again = standby.pool.submit(_run, self._tickets, *args, 1)
        pending = {fut: proc, again: standby}
        while pending:
            left = t_end - time.perf_counter()
            done, _ = wait_futures(list(pending), timeout=max(left, 0.0), return_when=FIRST_COMPLETED)
            if not done:
                break
            for f in done:
                who = pending.pop(f)
                try:
                    out = f.result()
                except (BrokenProcessPool, RuntimeError, CancelledError) as exc:
                    log.warning("the %s analysis's worker died (%s)", "rerun" if who is standby else "first", exc)
                    if who is standby:
                        self._replace(standby)
                    else:
                        self._dismiss(proc)                 # its shared frame buffer goes with it
                    continue
                except BaseException:
                    self._dismiss(proc)
                    raise                                   # the analysis's own error: the facet's answer
                self._dismiss(proc)
                res = _result(out)
                res.rerun_after_s = waited_s
                res.rerun_answer = "standby" if who is standby else "first"
                return res
        if not pending:                                     # both workers died
            raise WorkerDied("the analysis worker process died during this facet's analysis, and so did its "
                             "rerun on the standby; the next facet is measured on a new worker")
        log.error("the analysis and its rerun exceeded the %.1f s budget: both workers are retired; the first "
                  "of them to finish within %.0f s gives the late result", timeout_s, late_s)
        lates = []
        for f, who in pending.items():
            late = self._retire(who, f, late_s) if who is standby else self._retire_only(who, f, late_s)
            lates.append((late, who, "standby" if who is standby else "first"))
        raise AnalysisTimeout(f"the analysis did not finish within {timeout_s:.1f} s, nor its rerun on the "
                              "standby worker; a new standby takes over", late=_first_late(lates, waited_s))

    def _dismiss(self, proc: _Process) -> None:
        """The rerun facet is answered: the slow first worker, replaced by the standby, is closed (in the
        background: killing and reaping it takes a moment; :meth:`close` waits for it, so that no hung
        analysis outlives the station). A rerun still going when the first worker answered finishes on its
        own as the new worker's first job; its result is dropped."""
        def close():
            try:
                proc.close()
            finally:
                with self._lock:
                    self._dismissed = [t for t in self._dismissed if t is not threading.current_thread()]
        thread = threading.Thread(target=close, name="analysis-dismissed", daemon=True)
        with self._lock:
            self._dismissed.append(thread)
        thread.start()

    def _retire_only(self, proc: _Process, fut, grace_s: float) -> Future:
        """*proc* is out of service (another worker took over): its analysis may still finish within
        *grace_s* seconds (the returned future's result), then *proc* is killed."""
        late: Future = Future()

        def wait():
            try:
                late.set_result(_result(fut.result(timeout=max(grace_s, 0.0))))
            except FutureTimeout:
                log.warning("the abandoned analysis did not finish within the late grace (%.0f s): its worker "
                            "(process %s) is killed", grace_s, proc.pids())
                late.set_result(None)
            except (BrokenProcessPool, RuntimeError, CancelledError):
                late.set_result(None)
            except BaseException as exc:
                late.set_exception(exc)
            finally:
                proc.close()
                with self._lock:
                    self._retired = [(p, t) for p, t in self._retired if p is not proc]
        thread = threading.Thread(target=wait, name="analysis-retired", daemon=True)
        with self._lock:
            self._retired.append((proc, thread))
        thread.start()
        return late

    def close(self, late_wait_s: float | None = None) -> None:
        """Stop every worker. An abandoned analysis still within its grace is waited for (up to
        *late_wait_s* seconds, default its grace) so that its result is kept; then everything is killed."""
        with self._lock:
            self._closed = True
            starting = list(self._starting)
            retired = list(self._retired)
            dismissed = list(self._dismissed)
        for proc in starting:                     # a start under way ends now (its thread then gives up)
            proc.kill()
        for thread in dismissed:                  # a replaced worker being killed and reaped
            thread.join(30)
        for proc, thread in retired:
            thread.join(late_wait_s)
            proc.close()
            thread.join(10)
        thread = self._standby_thread
        if thread is not None:
            thread.join(30)
        for proc in (self._active, self._standby):
            if proc is not None:
                proc.close()
        self._active = self._standby = None
