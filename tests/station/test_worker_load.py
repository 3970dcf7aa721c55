"""Issue 43, item 7: on a busy machine a slow analysis is not rerun, and a late result is kept.

On a loaded machine every analysis is slow; the rerun meant for a hung worker fired on them too, halved the
processor each of the two copies got, and both were abandoned at the deadline with no late result kept (0 of
4). The worker now reruns only an analysis whose worker has stalled (neither runnable nor computing), and
when a rerun and its first analysis are both abandoned, the first of them to finish is the late result.

The slowness is controlled, never the machine's: the simulated station's faults (station/simulated_faults.py)
either work slowly (``slow-analysis``: runnable, computing a tenth of the time, as an analysis on a busy
machine) or hang (asleep, as a deadlock). The job is a stand-in that reads the capture's white frame (a few
milliseconds; tests/station/worker_faults.py), so each answer says which capture it belongs to: the truth is
the grey level this test wrote into that frame. No time is asserted: the waits (3 to 10 s) are far from the
deadlines they are compared with (1.5 to 8 s) only in the direction that makes the expected path certain on a
loaded machine, and a hung attempt never ends (an hour).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.errors import AnalysisTimeout
from sofast_station.station import worker as worker_module
from sofast_station.station.simulated_faults import FaultyJob, faulty_job
from sofast_station.station.worker import AnalysisWorker, _Progress

from .worker_faults import QuickJob, alive


def _frames(shape, grey: int) -> np.ndarray:
    frames = np.zeros(shape, dtype=np.uint8)
    frames[1] = grey                       # the white frame: the stand-in job's one figure
    return frames


def test_a_stalled_worker_is_told_from_a_busy_one():
    """The rule alone, on samples: stalled only when the samples cover the stretch, none saw the worker
    runnable and it used under 2 % of a core (at least two clock ticks) in it."""
    tick = worker_module._CLOCK_TICK_S
    p = _Progress([])

    def samples(*rows):
        p.samples.clear()
        p.samples.extend(rows)

    samples((0.0, False, 5.0), (0.5, False, 5.0), (1.0, False, 5.0 + tick))
    assert p.stalled(1.0, now=1.0)                          # asleep throughout: one tick of the parent watch
    samples((0.0, False, 5.0), (0.5, True, 5.0), (1.0, False, 5.0))
    assert not p.stalled(1.0, now=1.0)                      # seen waiting for a core: a busy machine
    samples((0.0, False, 5.0), (0.5, False, 5.05), (1.0, False, 5.1))
    assert not p.stalled(1.0, now=1.0)                      # 10 % of a core in bursts, never caught running
    samples((0.6, False, 5.0), (1.0, False, 5.0))
    assert not p.stalled(1.0, now=1.0)                      # the stretch is not covered yet
    samples((0.0, None, None), (1.0, None, None))
    assert p.stalled(1.0, now=1.0)                          # nothing readable: as before, a rerun
    samples((0.0, True, 1.0), (0.2, False, 1.01), (1.1, False, 1.01), (1.3, False, 1.01))
    assert p.stalled(1.0, now=1.3)                          # the last second: asleep (the busy start is older)


@pytest.fixture
def workers(small_station_toml):
    """A worker and its warm standby on the small station's camera (400 x 300), warmed on the stand-in job and
    with its usual time known (four quick analyses: a rerun is then possible after RERUN_MIN_S)."""
    cfg = load_config(small_station_toml)
    shape = (cfg.fringes.n_frames, *cfg.geometry.camera.shape)
    w = AnalysisWorker(cfg.geometry, cfg.fringes, cfg.geometry.camera.shape, standby=True)
    try:
        w.warm_up(_frames(shape, 1), QuickJob(), 1.0, timeout_s=120.0)
        for grey in (2, 3, 4, 5):
            assert w.analyse(_frames(shape, grey), QuickJob(), 1.0, timeout_s=120.0).figures["white_mean_dn"] == grey
        yield w, shape
    finally:
        w.close(late_wait_s=0)


def _standby_ready(w: AnalysisWorker) -> None:
    end = time.monotonic() + 300
    while not w.standby_pids():
        assert time.monotonic() < end, "no standby worker started"
        time.sleep(0.1)


def test_a_slow_machine_keeps_its_late_results_and_a_hung_rerun_gives_the_first_answer(workers):
    """Three facets on one worker and its standby.

    * 10: slow work (3 s, as on a busy machine), deadline 60 s: not rerun (the code before reran it after
      1 s beside itself), answered by the first worker.
    * 11: both the analysis and its rerun hang past the 8 s deadline; the first attempt would hang for an hour,
      the rerun ends 10 s after it began. The late result is the rerun's (the code before kept only the first
      analysis's, which never came: no late result), and the hung worker is killed once it is in.
    * 12: slow work (4 s) past a 1.5 s deadline: not rerun; its late result is kept.
    """
    w, shape = workers
    slow = faulty_job(QuickJob(), "slow-analysis", hang_s=3600.0, slow_s=3.0)
    assert isinstance(slow, FaultyJob) and slow.busy
    res = w.analyse(_frames(shape, 10), slow, 1.0, timeout_s=60.0, late_s=60.0)
    assert res.figures["white_mean_dn"] == 10 and res.rerun_after_s is None and w.reruns == 0

    _standby_ready(w)
    first_pids = w.pids()
    both_hang = FaultyJob(QuickJob(), "hung-facet", (3600.0, 10.0))         # asleep: stalled, rerun
    with pytest.raises(AnalysisTimeout) as timeout:
        w.analyse(_frames(shape, 11), both_hang, 1.0, timeout_s=8.0, late_s=60.0)
    assert w.reruns == 1
    late = timeout.value.late.result(timeout=120)
    assert late is not None, "no late result: the rerun's answer was not kept"
    assert late.figures["white_mean_dn"] == 11 and late.figures["attempt"] == 1 and late.rerun_answer == "standby"
    end = time.monotonic() + 60
    while any(alive(pid) for pid in first_pids):
        assert time.monotonic() < end, "the hung first worker was left running after the late result came"
        time.sleep(0.1)

    slower = faulty_job(QuickJob(), "slow-analysis", hang_s=3600.0, slow_s=4.0)
    with pytest.raises(AnalysisTimeout) as timeout:
        w.analyse(_frames(shape, 12), slower, 1.0, timeout_s=1.5, late_s=60.0)
    late = timeout.value.late.result(timeout=120)
    assert late is not None and late.figures["white_mean_dn"] == 12 and late.rerun_after_s is None
    assert w.reruns == 1                                    # facet 12 was not rerun
