"""A simulated robot: hands out a fixed list of facet requests and records every answer.

It is the default trigger of the simulated station and the reference a test of the station loop checks
against: ``answers`` holds every busy/done/fault with its time, ``finished`` tells when every request has
been answered.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from ...errors import TriggerError
from ..protocols import FacetRequest
from ._handshake import ANSWERED, BUSY, CLOSED, IDLE, READY, REQUESTED, Handshake

log = logging.getLogger(__name__)

#: The newest answers and heartbeat times the simulated robot keeps (a fixed memory over a long soak).
ANSWERS_KEPT = 100_000
HEARTBEATS_KEPT = 10_000


@dataclass(frozen=True)
class Answer:
    """One answer of the station to the simulated robot.

    Attributes
    ----------
    serial : str
        Serial number of the facet answered.
    kind : str
        "busy", "done" or "fault".
    time_s : float
        When it was given, ``time.monotonic()`` seconds.
    verdict : str or None
        "pass", "fail" or "invalid" for "done".
    code : int or None
        Fault code for "fault" (see ``FAULT_CODES``).
    reason : str or None
        Fault reason for "fault".
    """

    serial: str
    kind: str
    time_s: float
    verdict: str | None = None
    code: int | None = None
    reason: str | None = None
    warnings: int = 0


class SimulatedRobot(Handshake):
    """Trigger backend that places the given facets one after the other.

    Parameters
    ----------
    requests : list of FacetRequest, or int
        The facets, in order; an int ``n`` means ``n`` facets with serials "SIM-0001" .. "SIM-000n"
        (four digits, more when n > 9999).
    period_s : float
        Line period, seconds: facet ``i`` (from 0) is not placed before ``i * period_s`` after the first
        ``ready()``, nor before the station is ready for it. 0 places each as soon as the station is ready.
    fail_ack : iterable of int, optional
        Indices (from 0) of requests whose ``done``/``fault`` raises TriggerError as if the robot had not
        acknowledged, after recording the answer: to test the station's recovery.
    place : callable, optional
        ``place(request)`` puts the facet in the fixture before the robot triggers (the simulated station's
        :meth:`~sofast_station.station.simulated.SimulatedStation.place`: a line whose facets differ).

    Attributes
    ----------
    answers : deque of Answer
        Every busy/done/fault, in order (the newest ``ANSWERS_KEPT``).
    heartbeats : deque of float
        The ``time.monotonic()`` seconds of every ``heartbeat()`` (the newest ``HEARTBEATS_KEPT``).
    """

    name = "simulated robot"

    def __init__(self, requests: list[FacetRequest] | int, period_s: float = 0.0, *,
                 fail_ack: Iterable[int] = (), place=None):
        super().__init__()
        self.place = place
        if isinstance(requests, int):
            if requests < 0:
                raise ValueError(f"number of requests must be >= 0, not {requests}")
            width = max(4, len(str(requests)))
            requests = [FacetRequest(serial=f"SIM-{i:0{width}d}") for i in range(1, requests + 1)]
        self.requests: list[FacetRequest] = list(requests)
        if period_s < 0:
            raise ValueError(f"period_s must be >= 0, not {period_s}")
        self.period_s = float(period_s)
        self.fail_ack = set(fail_ack)
        # Bounded: a soak runs the simulated robot for thousands of facets in the station's process.
        self.answers: deque[Answer] = deque(maxlen=ANSWERS_KEPT)
        self.heartbeats: deque[float] = deque(maxlen=HEARTBEATS_KEPT)
        self._next = 0            # index of the next request to place
        self._answered = 0        # requests answered with done or fault
        self._t0: float | None = None

    @property
    def finished(self) -> bool:
        """True once every request has been answered with done or fault."""
        return self._answered >= len(self.requests)

    @property
    def current(self) -> FacetRequest | None:
        """The request being handled (handed out, not yet answered), else None."""
        return self.requests[self._next - 1] if self._state in (REQUESTED, BUSY) else None

    def ready(self) -> None:
        """The station can take a facet."""
        self._enter("ready", (IDLE, READY, ANSWERED))
        if self._t0 is None:
            self._t0 = time.monotonic()
        self._state = READY

    def wait_for_facet(self, timeout_s: float) -> FacetRequest | None:
        """The next facet once it is due, else None after ``timeout_s`` seconds."""
        self._enter("wait_for_facet", (READY,))
        deadline = time.monotonic() + max(0.0, float(timeout_s))
        if self._next >= len(self.requests):
            time.sleep(max(0.0, float(timeout_s)))  # the line is empty: behave like an idle robot
            return None
        due = self._t0 + self._next * self.period_s
        now = time.monotonic()
        if due > deadline:
            time.sleep(max(0.0, deadline - now))
            return None
        if due > now:
            time.sleep(due - now)
        request = self.requests[self._next]
        if self.place is not None:
            self.place(request)                   # the robot puts the facet in the fixture, then triggers
        self._next += 1
        self._state = REQUESTED
        log.debug("simulated robot places facet %s", request.serial)
        return request

    def busy(self) -> None:
        """The station has taken the facet."""
        self._enter("busy", (REQUESTED,))
        self.answers.append(Answer(self.current.serial, "busy", time.monotonic()))
        self._state = BUSY

    def done(self, verdict: str, warnings: int = 0) -> None:
        """The facet is measured: ``verdict`` is "pass", "fail", "invalid" or "indeterminate"; ``warnings`` the
        WARNING_BITS."""
        self._enter("done", (BUSY,))
        self._check_verdict(verdict)
        self._answer(Answer(self.current.serial, "done", time.monotonic(), verdict=verdict, warnings=int(warnings)))

    def fault(self, code: int, reason: str, warnings: int = 0) -> None:
        """The facet could not be measured: fault ``code`` (FAULT_CODES) and a reason for the log; ``warnings``
        the WARNING_BITS (the line's health)."""
        self._enter("fault", (BUSY,))
        code = self._check_fault_code(code)
        self._answer(Answer(self.current.serial, "fault", time.monotonic(), code=code, reason=str(reason),
                            warnings=int(warnings)))

    def _answer(self, answer: Answer) -> None:
        index = self._next - 1
        self.answers.append(answer)
        self._answered += 1
        self._state = ANSWERED
        if index in self.fail_ack:
            raise TriggerError(f"{self.name}: PLC did not acknowledge the {answer.kind} of facet "
                               f"{answer.serial} (simulated); the station reports it and goes on")

    def heartbeat(self) -> None:
        """The station is alive."""
        self._enter("heartbeat", (IDLE, READY, REQUESTED, BUSY, ANSWERED))
        self.heartbeats.append(time.monotonic())

    def close(self) -> None:
        """Stop; a request handed out but not answered is placed again by :meth:`reopen`."""
        self._state = CLOSED

    def reopen(self) -> SimulatedRobot:
        """Open again after ``close`` (the station's recovery), keeping the answers and the position in
        the line; an unanswered request is placed again. Returns self."""
        if self._next > self._answered:  # the robot takes the unanswered facet back and places it again
            self._next = self._answered
        self._state = IDLE
        return self
