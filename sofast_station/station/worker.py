"""The analysis in a separate, killable process.

A hung analysis must not hang the line: the station runs :func:`~sofast_station.measure.analysis.analyse`
in one long-lived worker process (spawned, so it shares no OpenGL or thread state with the station),
hands it the frames through shared memory (no 35 MB pickle per facet), waits with a deadline, and kills
and restarts the worker when the deadline passes. The worker computes the camera's pixel rays once.

A worker that dies *before* it begins a facet's analysis (killed or out of memory between facets, its
death not yet seen when the next facet arrives) costs that facet nothing: the worker marks each analysis
it begins in the shared memory, so the station knows the facet was never started, restarts the worker and
analyses it again within the facet's time budget. A worker that dies *during* an analysis answers that
facet with the worker fault (the facet itself may be what kills it), and the next facet is measured.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from multiprocessing.shared_memory import SharedMemory

import numpy as np

from ..errors import AnalysisTimeout, StationError, WorkerDied

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


def _init(shm_name: str, shape: tuple[int, int, int], geometry: dict, fringes: dict) -> None:
    from ..fringes import FringeSet
    from ..geometry import StationGeometry
    from ..precompute import ray_table, warm_up

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
    import scipy.special  # noqa: F401
    from .memtrace import start_from_env
    start_from_env("worker")                    # off unless SOFAST_TRACEMALLOC_S is set (leak hunts)


def _run(ticket: int, design: dict, settings: dict, distance_m: float, hang_s: float, optics=None,
         uncertainty: dict | None = None):
    from ..archive._common import trim_heap
    from ..facet import FacetDesign
    from ..measure.analysis import analyse
    from ..measure.pipeline import AnalysisSettings
    from ..measure.uncertainty import InputUncertainties
    from ..result.optical_figures import DesignTraces, add_optics

    _STATE["begun"][0] = ticket          # begun: from here a death is this facet's (see the module's text)
    if hang_s < 0:                       # fault injection for tests: the worker dies mid-analysis
        os._exit(9)
    if hang_s > 0:                       # fault injection for tests: an analysis that hangs
        time.sleep(hang_s)
    t = time.perf_counter()
    frames = np.array(_STATE["frames"])  # a private copy: the station may refill the buffer after a timeout
    if "ensemble" in design:             # a heliostat recipe (station/heliostat.py HeliostatJob)
        from .heliostat import analyse_job
        inputs = None if uncertainty is None else InputUncertainties.from_dict(uncertainty)
        figures, valid, sensitivities = analyse_job(
            frames, _STATE["fringes"], _STATE["geometry"], design, AnalysisSettings(**settings), distance_m,
            rays_cam=_STATE["rays"], optics=optics, uncertainty=inputs,
            sensitivity_cache=_STATE.setdefault("sensitivities", {}))
        out = (figures, np.packbits(valid), valid.shape, time.perf_counter() - t, None, sensitivities)
        del frames, valid
        trim_heap()
        return out
    facet = FacetDesign.from_dict(design)
    # Sensitivities are computed on the first facet of each recipe and kept for the worker's life.
    inputs = None if uncertainty is None else InputUncertainties.from_dict(uncertainty)
    a = analyse(frames, _STATE["fringes"], _STATE["geometry"], facet, distance_m,
                AnalysisSettings(**settings), rays_cam=_STATE["rays"], uncertainty=inputs,
                sensitivity_cache=_STATE.setdefault("sensitivities", {}))
    # The optical figures (intercept, spot size, aim), with the design's trace kept for the next facet.
    add_optics(a, facet, optics, _STATE.setdefault("design_traces", DesignTraces()))
    out = (a.figures, np.packbits(a.valid), a.valid.shape, time.perf_counter() - t, _preview(a), a.sensitivities)
    del a, frames
    trim_heap()                          # the per-pixel arrays' pages go back: the worker's memory stays flat
    return out


def _preview(a, most: int = 6000) -> dict:
    """A thinned copy of the per-pixel results for the operator's slope-error map: every k-th camera row
    and column (at most about *most* points), as float32; a few hundred kB, a few ms."""
    rows, cols = np.nonzero(a.valid)
    k = max(1, int(np.ceil(np.sqrt(rows.size / most))))
    pick = (rows % k == 0) & (cols % k == 0)
    return {"step_px": k, "rows": rows[pick].astype(np.int32), "cols": cols[pick].astype(np.int32),
            "points_xy_m": np.asarray(a.points_facet_m[:2, pick], dtype=np.float32),
            "residuals_mrad": {m: np.asarray([e[0][pick], e[1][pick]], dtype=np.float32)
                               for m, e in a.residuals_mrad.items()},
            "corners_px": np.asarray(a.corners_px, dtype=np.float32)}


def _prepare_optics(designs: list) -> int:
    from ..facet import FacetDesign
    from ..result.optical_figures import DesignTraces

    import numpy as np

    from ..optics import design_samples, facet_optics

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
class AnalysisWorker:
    """One analysis process with a shared frame buffer.

    Parameters
    ----------
    geometry, fringes :
        The station's geometry and fringe definition (fixed for the worker's life).
    n_frames, shape :
        Size of the frame stack it analyses.
    """

    def __init__(self, geometry, fringes, shape: tuple[int, int]):
        self._geometry = geometry.to_dict()
        self._fringes = fringes.to_dict()
        self._shape = (fringes.n_frames, *shape)
        self._shm = SharedMemory(create=True, size=_frame_bytes(self._shape) + _BEGUN_BYTES)
        self._frames = np.ndarray(self._shape, dtype=np.uint8, buffer=self._shm.buf)
        self._begun = _begun_slot(self._shm, self._shape)
        self._tickets = 0                        # analyses asked for so far
        self._begun[0] = 0
        self._pool = None
        self._restarting: threading.Thread | None = None
        self._optics_designs: list = []          # (design dict, OpticsSettings) traced at every (re)start
        self.starts = 0
        try:
            self._start()
        except BaseException:
            self._shm.close()
            self._shm.unlink()
            raise

    def _start(self) -> None:
        t = time.perf_counter()
        ctx = multiprocessing.get_context("spawn")
        self._pool = ProcessPoolExecutor(max_workers=1, mp_context=ctx, initializer=_init,
                                         initargs=(self._shm.name, self._shape, self._geometry, self._fringes))
        try:
            self._pool.submit(_ping).result(timeout=120)
        except (BrokenProcessPool, FutureTimeout, OSError) as exc:
            self._kill()
            raise WorkerDied(f"the analysis worker could not start ({type(exc).__name__}: {exc}); see the log, "
                             "and check memory and the Python environment") from None
        if self._optics_designs:
            self._pool.submit(_prepare_optics, self._optics_designs).result(timeout=120)
        self.starts += 1
        log.info("analysis worker ready in %.1f s (process %s)", time.perf_counter() - t, self.pids())

    def pids(self) -> list[int]:
        """Process ids of the worker (empty while it is being restarted)."""
        pool = self._pool
        return [p.pid for p in list((getattr(pool, "_processes", None) or {}).values())] if pool else []

    def alive(self) -> bool:
        """Whether the worker process runs (False while a restart is under way, or after it died)."""
        pool = self._pool
        if pool is None or getattr(pool, "_broken", False):
            return False
        procs = list((getattr(pool, "_processes", None) or {}).values())
        return bool(procs) and all(p.is_alive() for p in procs)

    def supervise(self) -> bool:
        """Between facets: restart a worker that died; True when a restart was started."""
        if self._restarting is not None or self.alive():
            return False
        log.error("the analysis worker (process %s) is gone: restarting it", self.pids() or "?")
        self._restart()
        return True

    def _restart(self) -> None:
        self._kill()
        # The new worker starts in the background: the robot gets its answer now, not after the start.
        self._restarting = threading.Thread(target=self._restart_main, name="analysis-worker-restart", daemon=True)
        self._restarting.start()

    def _restart_main(self) -> None:
        try:
            self._start()
        except StationError as exc:
            log.error("%s", exc)

    def _ready(self) -> None:
        """Wait for a restart under way; start again when it failed."""
        if self._restarting is not None:
            self._restarting.join()
            self._restarting = None
        if self._pool is None:
            self._start()

    def analyse(self, frames: np.ndarray, design, settings, distance_m: float, timeout_s: float,
                hang_s: float = 0.0, optics=None, uncertainty=None) -> WorkerResult:
        """Analyse *frames* in the worker; :class:`AnalysisTimeout` after *timeout_s* (worker restarted).

        With *optics* (OpticsSettings) the figures carry the facet's optical figures (``optics``).

        Errors raised by the analysis (StationError subclasses) come back as themselves.
        """
        if frames.shape != self._shape or frames.dtype != np.uint8:
            from ..errors import CaptureError
            raise CaptureError(f"the capture is {frames.dtype} {frames.shape}, the station expects uint8 "
                               f"{self._shape}; check the camera's pixel format and size")
        t_end = time.perf_counter() + timeout_s
        for attempt in (1, 2):
            self._ready()                          # a restart under way: wait for the new worker
            if not self.alive():
                self.supervise()
                self._ready()
            left_s = t_end - time.perf_counter()
            if left_s <= 0:
                raise AnalysisTimeout(f"the analysis worker was being restarted for the facet's whole "
                                      f"{timeout_s:.1f} s; the facet was not analysed")
            np.copyto(self._frames, frames)
            self._tickets += 1
            fut = None
            try:
                fut = self._pool.submit(_run, self._tickets, design.to_dict(), settings.to_dict(),
                                        float(distance_m), float(hang_s), optics,
                                        None if uncertainty is None else uncertainty.to_dict())
                figures, packed, shape, seconds, preview, sensitivities = fut.result(timeout=max(left_s, 0.01))
                break
            except FutureTimeout:
                log.error("analysis exceeded its %.1f s budget: restarting the analysis worker", timeout_s)
                self._restart()
                raise AnalysisTimeout(f"the analysis did not finish within {timeout_s:.1f} s; the worker was "
                                      "restarted") from None
            except (BrokenProcessPool, RuntimeError) as exc:
                begun = int(self._begun[0]) == self._tickets
                self._restart()
                if begun or attempt == 2:
                    log.error("the analysis worker died during the analysis (%s): restarting it", exc)
                    raise WorkerDied("the analysis worker process died during this facet's analysis (killed or "
                                     "out of memory); it is restarted, the next facet is measured") from None
                log.warning("the analysis worker had died before this facet's analysis began (%s): restarting "
                            "it and analysing the facet again", exc)
            finally:
                # An analysis error is raised from the future, which keeps it: the error's traceback holds
                # this frame, and this frame the future, a reference cycle that would keep the cycle's
                # frames (tens of MB at full resolution) until the garbage collector's rare full pass.
                # Broken here.
                fut = None
        valid = np.unpackbits(packed, count=int(np.prod(shape))).astype(bool).reshape(shape)
        return WorkerResult(figures, valid, seconds, preview, sensitivities)

    def prepare_optics(self, designs: list, timeout_s: float = 120.0) -> None:
        """Trace each (design, OpticsSettings)'s design surface in the worker now, so that no facet's cycle
        pays for it; a restarted worker traces them again while it starts."""
        self._optics_designs = [(d.to_dict(), o) for d, o in designs]
        if designs:
            t = time.perf_counter()
            self._pool.submit(_prepare_optics, self._optics_designs).result(timeout=timeout_s)
            log.info("optics: %d design trace(s) ready in %.2f s", len(designs), time.perf_counter() - t)

    def _kill(self) -> None:
        pool, self._pool = self._pool, None
        if pool is not None:
            procs = list((getattr(pool, "_processes", None) or {}).values())
            for proc in procs:
                proc.kill()
            pool.shutdown(wait=False, cancel_futures=True)
            for proc in procs:
                proc.join(5)                 # reap it: a zombie's PID would keep its temporary files "alive"

    def close(self) -> None:
        if self._restarting is not None:
            self._restarting.join()
            self._restarting = None
        self._kill()
        self._frames = self._begun = None
        self._shm.close()
        self._shm.unlink()
