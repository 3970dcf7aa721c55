"""The robot/PLC link as the loop sees it: an outage is said once, then once a minute, and retried with a
growing pause.

A PLC switched off, a cable pulled or a network down makes every handshake call fail at once. The loop
used to log each failure and each failed reconnect, every half second, about five lines a second (and
pymodbus its own): an outage of a night filled the log. :class:`LinkWatch` keeps the loop's side of it:
the first failure is logged with what happened, then one line per :data:`REPEAT_S` while it lasts, and
one when the link is back; reconnects are tried after a pause that doubles from the loop's poll interval
up to :data:`MAX_PAUSE_S`, so a PLC that comes back is taken again within a few seconds.
"""

from __future__ import annotations

import logging
import time

log = logging.getLogger("sofast_station.station.runner")

#: Seconds between two log lines of the same outage.
REPEAT_S = 60.0
#: Longest pause between two reconnects, seconds.
MAX_PAUSE_S = 5.0


class LinkWatch:
    """The state of the robot/PLC link: up, or down since when, after how many attempts.

    Parameters
    ----------
    first_pause_s : float
        Pause after the first failure, seconds (the loop's poll interval); it doubles up to
        :data:`MAX_PAUSE_S`.
    clock : callable
        Monotonic seconds (``time.monotonic``; tests give their own).
    """

    def __init__(self, first_pause_s: float, clock=time.monotonic):
        self.first_pause_s = min(max(float(first_pause_s), 0.05), MAX_PAUSE_S)
        self.clock = clock
        self.since: float | None = None
        self.attempts = 0
        self._said = 0.0

    @property
    def down(self) -> bool:
        return self.since is not None

    def failed(self, exc: BaseException) -> float:
        """A handshake call or a reconnect failed: log it when due; returns the pause before the next try."""
        now = self.clock()
        if self.since is None:
            self.since, self.attempts, self._said = now, 0, now
            log.error("robot/PLC handshake failed: %s; reconnecting (said once, then every %.0f s while it lasts)",
                      exc, REPEAT_S)
        elif now - self._said >= REPEAT_S:
            self._said = now
            log.error("the robot/PLC is still unreachable after %.0f s (%d reconnects tried): %s", now - self.since,
                      self.attempts, exc)
        self.attempts += 1
        return min(MAX_PAUSE_S, self.first_pause_s * 2.0 ** min(self.attempts - 1, 8))

    def ok(self) -> None:
        """A handshake call worked: the link is up (logged when it was down)."""
        if self.since is not None:
            log.warning("the robot/PLC link is back after %.0f s (%d reconnects tried)", self.clock() - self.since,
                        self.attempts)
            self.since, self.attempts = None, 0
