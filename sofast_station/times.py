"""Times as the station writes and reads them: ISO 8601 with the UTC offset, keys that sort like instants, and
the command line's period bounds."""

from __future__ import annotations

import datetime as _dt

from .errors import ConfigError


def parse_time(value) -> _dt.datetime:
    """A time-zone-aware datetime from an ISO 8601 string or a datetime.

    A value without a UTC offset is taken as the machine's local time.

    Raises
    ------
    ValueError
        When *value* is not an ISO 8601 date or date and time.
    """
    if isinstance(value, _dt.datetime):
        dt = value
    elif isinstance(value, _dt.date):
        dt = _dt.datetime(value.year, value.month, value.day)
    else:
        dt = _dt.datetime.fromisoformat(str(value))
    if dt.tzinfo is None:
        dt = dt.astimezone()
    return dt


def utc_key(value) -> str:
    """A string that sorts like the instant *value* denotes: UTC, ``YYYY-MM-DDTHH:MM:SS.ffffffZ``."""
    return parse_time(value).astimezone(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def parse_bound(text, what: str = "--from/--to") -> str | None:
    """A period bound from the command line: an ISO date (local midnight at its start), an ISO date and
    time, or ``today`` / ``yesterday`` / ``tomorrow`` (local midnight); None stays None.

    Raises
    ------
    ConfigError
        Naming *what* and the accepted forms, when *text* is none of them.
    """
    if text is None:
        return None
    t = str(text).strip()
    words = {"today": 0, "yesterday": -1, "tomorrow": 1}
    if t.lower() in words:
        return (_dt.date.today() + _dt.timedelta(days=words[t.lower()])).isoformat()
    try:
        if len(t) == 10:
            return _dt.date.fromisoformat(t).isoformat()
        _dt.datetime.fromisoformat(t)
        return t
    except ValueError:
        raise ConfigError(f"{what} {text!r} is not a date: give an ISO date (2026-11-25), a date and time "
                          f"(2026-11-25T06:00), 'today' or 'yesterday'") from None


def check_period(since, until, what: str = "--from/--to") -> None:
    """Refuse an empty or reversed period ``[since, until)`` with a message that says so."""
    if since is not None and until is not None and utc_key(since) >= utc_key(until):
        raise ConfigError(f"{what}: the period from {since} to {until} is empty or reversed (the end is "
                          f"exclusive): the start must come before the end")


def now_iso() -> str:
    """Local date and time with its UTC offset, ISO 8601, to the millisecond."""
    return _dt.datetime.now().astimezone().isoformat(timespec="milliseconds")
