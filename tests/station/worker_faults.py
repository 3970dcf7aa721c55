"""Faults injected into the analysis worker's own process by the station tests (imported there by name)."""

from __future__ import annotations

import os
from pathlib import Path

from sofast_station.station import worker

#: Environment variable naming a flag file: the first worker process to find it removes it and dies.
DIE_ONCE_ENV = "SOFAST_TEST_WORKER_DIES_ONCE"


def ping_dies_once() -> bool:
    """The worker's readiness check, but the first process to run it dies (SIGKILL-like exit) before it
    is ready, as a worker killed in the first seconds of `run` does."""
    try:
        Path(os.environ[DIE_ONCE_ENV]).unlink()
    except (KeyError, FileNotFoundError):
        return worker._ping()
    os._exit(9)


class QuickJob:
    """A job whose "analysis" reads the capture's white frame and nothing more (a few milliseconds): the worker's
    mechanics (timeouts, reruns, late results) without the analysis's cost. Its one figure, the white frame's
    mean count, says which capture an answer belongs to."""

    kind = "facet"
    name = "quick"

    def crop_box(self, dark, white):
        return (0, 0, white.shape[0], white.shape[1])

    def analyse(self, capture, *, attempt: int = 0, **kwargs):
        from sofast_station.job.base import Outcome

        white = capture.frames[1]
        return Outcome({"white_mean_dn": float(white.mean()), "attempt": attempt}, white > 0)

    def preview(self, outcome):
        return None


def alive(pid: int) -> bool:
    """Whether process *pid* exists and is not a zombie (from /proc)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False
