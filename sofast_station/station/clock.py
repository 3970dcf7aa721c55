"""The station's wall clock, watched for steps: every cycle's id and record time come from it.

The wall clock dates each row (the day's workbook it is filed in follows that date) and orders cycle ids.
A clock that steps backwards (a wrong time set by hand, a battery-backed clock read at boot, an NTP
correction of a clock that ran ahead) would silently file rows under an earlier day and give cycle ids that
sort before earlier ones. The monotonic clock cannot step: between two cycles the wall clock must advance
by what the monotonic clock did, within a tolerance; when it went back instead, the step is logged as a
warning and stated in the cycle's record (``clock_warning``). Which of the two readings was right, the
station cannot know: the row keeps the clock's present date, and says so. Cycle ids stay unique and
increasing whatever the clock does: an id never sorts before the last one (the journal's newest at start).
"""

from __future__ import annotations

import datetime as _dt
import logging
import re
import time
import uuid

log = logging.getLogger(__name__)

#: A cycle id's time stamp: UTC to the millisecond, ``YYYYmmddTHHMMSSmmm``.
_STAMP = "%Y%m%dT%H%M%S%f"
_STAMP_RE = re.compile(r"^([0-9]{8}T[0-9]{9})")


def _local_now() -> _dt.datetime:
    return _dt.datetime.now().astimezone()


def format_cycle_id(utc_ms: int, suffix: str | None = None) -> str:
    """A cycle id: UTC time to the millisecond (*utc_ms*, milliseconds since the epoch) and 8 hex digits."""
    stamp = _dt.datetime.fromtimestamp(utc_ms / 1000.0, _dt.timezone.utc).strftime(_STAMP)[:-3]
    return f"{stamp}-{suffix or uuid.uuid4().hex[:8]}"


def cycle_id_ms(cycle_id: str | None) -> int | None:
    """The milliseconds since the epoch a cycle id's stamp holds (None when it holds none)."""
    m = _STAMP_RE.match(cycle_id or "")
    if not m:
        return None
    stamp = _dt.datetime.strptime(m.group(1) + "000", _STAMP).replace(tzinfo=_dt.timezone.utc)
    return int(round(stamp.timestamp() * 1000))


def _hours(seconds: float) -> str:
    return f"{seconds / 3600.0:.1f} h" if abs(seconds) >= 3600 else f"{seconds:.1f} s"


class StationClock:
    """The wall clock of the production loop, checked against the monotonic clock at every cycle.

    Parameters
    ----------
    wall : callable, optional
        ``wall() -> datetime`` (time-zone aware, local): the wall clock (a test's controlled clock).
    monotonic : callable, optional
        ``monotonic() -> float`` seconds: a clock that never steps.
    tolerance_s : float
        A wall clock behind the monotonic clock's advance by more than this is a step backwards.
    last_cycle_id : str, optional
        The newest cycle id already journaled: ids go on from it.
    last_time : datetime, optional
        The newest journaled row's time: a clock that now reads earlier stepped back while the station was off.
    """

    def __init__(self, wall=None, monotonic=None, tolerance_s: float = 2.0, last_cycle_id: str | None = None,
                 last_time: _dt.datetime | None = None):
        self._wall = wall or _local_now
        self._monotonic = monotonic or time.monotonic
        self.tolerance_s = float(tolerance_s)
        self._last_ms = cycle_id_ms(last_cycle_id)
        self._last_reading: tuple[_dt.datetime, float] | None = None
        self._last_time = last_time

    def now(self) -> _dt.datetime:
        """The wall clock's local time (time-zone aware)."""
        return self._wall()

    def now_iso(self) -> str:
        """:meth:`now` in ISO 8601 with its UTC offset, to the millisecond (a record's ``time``)."""
        return self.now().isoformat(timespec="milliseconds")

    def next_cycle(self) -> tuple[str, str | None]:
        """A new cycle's id and, when the wall clock stepped back since the last cycle (or reads earlier
        than the journal's newest row), the warning for its record (None otherwise; logged here)."""
        now, mono = self.now(), self._monotonic()
        warning = None
        if self._last_reading is not None:
            before, before_mono = self._last_reading
            step = (now - before).total_seconds() - (mono - before_mono)
            if step < -self.tolerance_s:
                warning = (f"the wall clock stepped back by {_hours(-step)} since the previous cycle (it read "
                           f"{before.isoformat(timespec='seconds')}, {_hours(mono - before_mono)} ago, and reads "
                           f"{now.isoformat(timespec='seconds')}): this row is dated, and filed, by the clock as it "
                           "reads now; check the station's time (NTP)")
        elif self._last_time is not None and (self._last_time - now).total_seconds() > self.tolerance_s:
            back = _hours((self._last_time - now).total_seconds())
            warning = (f"the wall clock reads {now.isoformat(timespec='seconds')}, {back} "
                       f"before the journal's newest row ({self._last_time.isoformat(timespec='seconds')}): it stepped "
                       "back while the station was off; this row is dated, and filed, by the clock as it reads now; "
                       "check the station's time (NTP)")
        if warning:
            log.warning("%s", warning)
        self._last_reading = (now, mono)
        ms = int(round(now.timestamp() * 1000))
        if self._last_ms is not None and ms <= self._last_ms:
            ms = self._last_ms + 1                 # ids never go back, whatever the clock does
        self._last_ms = ms
        return format_cycle_id(ms), warning
