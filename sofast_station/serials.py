"""Facet serial numbers from outside (PLC, robot, operator, command file, command line) made safe once.

A serial travels into file names (dumps, inspection results, certificates), workbook cells, HDF5
attributes, the journal, log lines and the web page. :func:`clean_serial` is applied where a serial enters
the station (the production loop, for every request whatever its source: PLC, simulated robot, a serial
typed on the page or written in a command file; ``inspect --serial``), so every later use sees the same
safe text:

* control characters (NUL, line breaks, escapes) are dropped: HDF5 strings cannot hold NUL, and a line
  break would forge log lines;
* surrounding blanks are stripped, inner runs of blanks become one space;
* it is never a path: ``/`` and ``\\`` become ``_``, a run of dots (``..``) becomes ``_`` and leading dots
  are dropped, so no use of the serial as a file name can climb out of its folder or hide a file;
* at most :data:`MAX_SERIAL_CHARS` characters are kept (a file name holds 255 bytes);
* an empty result becomes ``"NOSERIAL"``.

When anything was changed, the record keeps the serial as received in ``serial_raw``
(:func:`raw_for_record`) and the log says what was changed. What stays with the writers: file names still
go through :func:`sofast_station.archive._common.safe_name`, the workbook stores text that starts with
``=`` as text, never as a formula, and the web page escapes HTML.
"""

from __future__ import annotations

import re
import unicodedata

#: Longest serial kept, characters.
MAX_SERIAL_CHARS = 64
#: Longest original kept in a record's ``serial_raw``, characters (the PLC sends at most 120; a command
#: file or a page could send megabytes).
MAX_RAW_CHARS = 256

_BLANKS = re.compile(r"\s+")
_PATH = re.compile(r"[/\\]|\.{2,}")


def clean_serial(serial) -> tuple[str, str | None]:
    """The serial as the station uses it, and a note saying what was changed (None when nothing was).

    Parameters
    ----------
    serial : str
        As received (anything else is taken as its text).

    Returns
    -------
    (str, str or None)
    """
    raw = "" if serial is None else str(serial)
    text = "".join(" " if ch in "\t\n\r\v\f" else ch for ch in raw
                   if ch in "\t\n\r\v\f" or unicodedata.category(ch) not in ("Cc", "Cf", "Cs", "Co", "Cn"))
    text = _BLANKS.sub(" ", text).strip()
    text = _PATH.sub("_", text).lstrip(".").strip()
    if len(text) > MAX_SERIAL_CHARS:
        text = text[:MAX_SERIAL_CHARS]
    text = text or "NOSERIAL"
    if text == raw:
        return text, None
    shown = raw if len(raw) <= 80 else raw[:80] + "..."
    return text, f"serial {shown!r} ({len(raw)} characters) was made safe: {text!r}"


def raw_for_record(serial) -> str:
    """The serial as received, for the record's ``serial_raw``: exact up to :data:`MAX_RAW_CHARS` characters
    (control characters included: JSON escapes them, the workbook shows them as a replacement mark), then cut
    with a note of its length."""
    raw = "" if serial is None else str(serial)
    if len(raw) <= MAX_RAW_CHARS:
        return raw
    return f"{raw[:MAX_RAW_CHARS]}... ({len(raw)} characters)"
