"""The simulated station's faults of the analysis, injected by the job it gives the worker.

``[simulation.faults]`` names a serial and a fault. Those of the analysis are the job's to play: the
simulated station wraps the recipe's job in a :class:`FaultyJob` (:meth:`~sofast_station.station.simulated.
SimulatedStation.job_for`), which the analysis worker receives and runs like any job, so the production
worker and loop carry no test hooks:

* "hung-analysis": the worker hangs (``hang_s``) on its first attempt; the rerun on the standby answers;
* "hung-facet": every attempt hangs (the facet itself hangs any worker);
* "slow-analysis": every attempt works slowly for ``slow_s`` and then answers (a late result);
* "worker-dies": the worker process exits in the middle of the analysis.

A hang sleeps: the worker is neither runnable nor using the processor, as in a deadlock or a stalled page-in,
and the worker's watch sees it stalled. Slow work keeps the worker runnable, in short bursts of computing
(:data:`BUSY_SHARE` of a core), as an analysis on a machine busy with other work: progressing, only slowly.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

#: The analysis's faults and, per attempt (the analysis, its rerun), how long it waits first: seconds, or
#: None for the worker's death. ``hang`` and ``slow`` stand for ``hang_s`` and ``slow_s``.
DELAYS = {"hung-analysis": ("hang", 0.0), "hung-facet": ("hang", "hang"), "slow-analysis": ("slow", "slow"),
          "worker-dies": (None, None)}
#: The faults whose waits are slow work, not a hang.
BUSY = frozenset({"slow-analysis"})
#: The share of a core slow work computes, in bursts every :data:`BUSY_PERIOD_S` seconds: enough to be seen
#: progressing, little enough that a test's slow facet costs a tenth of its wait in processor time.
BUSY_SHARE = 0.1
BUSY_PERIOD_S = 0.02


def work_slowly(seconds: float, share: float = BUSY_SHARE, period_s: float = BUSY_PERIOD_S) -> None:
    """Compute in bursts for *seconds* (wall clock): *share* of every *period_s* seconds spinning, the rest
    asleep, so the process is runnable and uses about *share* of a core, as slow work does."""
    end = time.perf_counter() + seconds
    while (now := time.perf_counter()) < end:
        burst_end = min(now + share * period_s, end)
        while time.perf_counter() < burst_end:
            pass
        time.sleep(max(0.0, min((1.0 - share) * period_s, end - time.perf_counter())))


@dataclass(frozen=True)
class FaultyJob:
    """*job* with a fault of the analysis: before each attempt it waits (``delays_s[attempt]``, seconds), or,
    for None, the worker process dies. Everything else is *job*'s."""

    job: object
    fault: str
    delays_s: tuple
    #: Whether the waits are slow work (runnable, computing a little) rather than a hang (asleep).
    busy: bool = False

    @property
    def kind(self) -> str:
        return self.job.kind

    @property
    def name(self) -> str:
        return self.job.name

    def __getattr__(self, name):              # design, analysis, optics, limits...: the job's own
        if name in ("job", "fault", "delays_s", "busy"):
            raise AttributeError(name)
        return getattr(self.job, name)

    def crop_box(self, *frames):
        return self.job.crop_box(*frames)

    def analyse(self, capture, *, attempt: int = 0, **kwargs):
        delay = self.delays_s[min(attempt, len(self.delays_s) - 1)]
        if delay is None:
            os._exit(9)                       # the worker dies mid-analysis (what the fault is for)
        if delay > 0 and self.busy:
            work_slowly(delay)
        elif delay > 0:
            time.sleep(delay)
        return self.job.analyse(capture, attempt=attempt, **kwargs)

    def preview(self, outcome):
        return self.job.preview(outcome)

    def record(self, head, figures, truth=None, timings=None, **extra):
        return self.job.record(head, figures, truth, timings, **extra)

    def pictures(self, record, outcome, folder):
        return self.job.pictures(record, outcome, folder)


def faulty_job(job, fault: str | None, hang_s: float, slow_s: float):
    """*job*, wrapped in a :class:`FaultyJob` when *fault* is one of the analysis's (:data:`DELAYS`)."""
    if fault not in DELAYS:
        return job
    seconds = {"hang": float(hang_s), "slow": float(slow_s)}
    return FaultyJob(job, fault, tuple(seconds.get(d, d) for d in DELAYS[fault]), busy=fault in BUSY)
