"""The small interfaces the station talks to. Real and simulated backends implement the same ones;
the station loop cannot tell them apart.

Errors: a camera raises :class:`~sofast_station.errors.CameraTimeoutError`,
:class:`~sofast_station.errors.CameraDisconnectedError` or :class:`~sofast_station.errors.CameraError`
(wrong frame size); a trigger raises :class:`~sofast_station.errors.TriggerError`. After any of them
the station closes and reopens the device and carries on with the next facet.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..fringes import Pattern


class Display(Protocol):
    """Shows one display image at a time.

    ``show`` returns once the image is on the screen and has had its settle time: drawn, swapped,
    finished (glFinish), and the configured settle (the display-latency calibration's, else ``settle_s``)
    waited.
    """

    def show(self, pattern: Pattern) -> None: ...

    def close(self) -> None: ...


class Camera(Protocol):
    """Grabs monochrome frames (rows, columns) of integer counts (uint8)."""

    shape: tuple[int, int]

    def set_exposure(self, seconds: float) -> None: ...

    def set_gain(self, gain: float) -> None: ...

    def grab(self, timeout_s: float = 2.0) -> np.ndarray: ...

    def close(self) -> None: ...


class RangeFinder(Protocol):
    """Distance from the screen centre to the facet's measure point, metres."""

    def measure(self) -> float: ...


@dataclass(frozen=True)
class FacetRequest:
    """What the robot/PLC says when a facet is in place.

    Attributes
    ----------
    serial : str
        The facet's serial number.
    recipe : str
        Facet type / recipe name ("" = choose by serial pattern or the station default).
    dump : bool
        The PLC asks for a data dump of this facet.
    extra : dict
        Backend-specific details (register values, sequence numbers), recorded with the cycle.
    """

    serial: str
    recipe: str = ""
    dump: bool = False
    extra: dict = field(default_factory=dict)


#: Fault reason codes sent to the robot/PLC with a "fault" answer.
FAULT_CODES = {
    "timeout": 1,          # the cycle missed its hard deadline (hung capture or analysis)
    "camera": 2,           # camera timeout, disconnect or wrong frame size
    "capture": 3,          # the capture was unusable (dark, saturated, out of order, no facet...)
    "geometry": 4,         # the facet pose / measured distance does not fit
    "analysis": 5,         # the analysis could not produce figures
    "display": 6,          # the display failed
    "calibration": 7,      # the calibration went stale mid-run and the station refuses ([calibration] stale)
    "recipe": 8,           # the PLC asked for a recipe station.toml does not define
    "worker": 9,           # the analysis worker process died (killed, out of memory); the standby took over
    "archive": 10,         # the result could not be journaled (disk full, read-only): the station stops
    "internal": 99,        # a bug: see the log
}


#: Warning bits sent to the robot/PLC with a "done" answer (the line goes on; docs/plc.md).
WARNING_BITS = {
    "drift": 1,            # a control-chart rule flagged the recipe's recent facets (a drift alarm)
    "line": 2,             # the line is failing as a line (faults in a row, yield collapse, cycles at the deadline,
                           # a machine too slow for the deadline): result/health.py; sent with done and fault
}


class Trigger(Protocol):
    """The robot/PLC handshake, seen from the station.

    The station calls ``ready()`` when it can take a facet, then ``wait_for_facet`` repeatedly (each
    call returns None after ``timeout_s`` so the station can beat its heartbeat and notice a stop
    request); on a request it answers ``busy()``, then exactly one of ``done(verdict)`` ("pass", "fail",
    "invalid", "indeterminate") or ``fault(code, reason)``; ``heartbeat()`` at least once a second while running.
    """

    def ready(self) -> None: ...

    def wait_for_facet(self, timeout_s: float) -> FacetRequest | None: ...

    def busy(self) -> None: ...

    def done(self, verdict: str, warnings: int = 0) -> None: ...

    def fault(self, code: int, reason: str, warnings: int = 0) -> None: ...

    def heartbeat(self) -> None: ...

    def close(self) -> None: ...
