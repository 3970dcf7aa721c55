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
