"""The named fault-injection points the archive's crash tests use (:func:`fault_point`).

Atomic files and JSON live in :mod:`sofast_station.files`, times in :mod:`sofast_station.times`, memory in
:mod:`sofast_station.memory`.
"""

from __future__ import annotations

import logging
import os
import signal

log = logging.getLogger(__name__)

#: Environment variable naming the fault-injection point at which the process SIGKILLs itself.
FAULT_ENV = "SOFAST_FAULT"

#: The named fault-injection points (see :func:`fault_point`).
FAULT_POINTS = ("journal-append", "workbook-temp-written", "workbook-renamed", "dump-mid-write")


def fault_point(name: str) -> None:
    """Kill this process with SIGKILL when ``SOFAST_FAULT`` names this point (crash tests only).

    Parameters
    ----------
    name : str
        One of :data:`FAULT_POINTS`.
    """
    if os.environ.get(FAULT_ENV) == name:
        log.critical("fault injection: %s=%s, killing process %d", FAULT_ENV, name, os.getpid())
        sig = getattr(signal, "SIGKILL", None)
        if sig is None:      # Windows: no SIGKILL; an immediate exit is the nearest equivalent
            os._exit(137)
        os.kill(os.getpid(), sig)
