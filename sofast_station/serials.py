"""Facet serial numbers from outside (PLC, robot, command line) made safe once, for every use.

A serial travels into file names (dumps, inspection results), workbook cells, HDF5 attributes, the
journal, log lines and the web page. :func:`clean_serial` is applied where a serial enters the station
(the production loop's request, ``inspect --serial``), so every later use sees the same safe text:

* control characters (NUL, line breaks, escapes) are dropped: HDF5 strings cannot hold NUL, and a line
  break would forge log lines;
* surrounding blanks are stripped, inner runs of blanks become one space;
* at most :data:`MAX_SERIAL_CHARS` characters are kept (a file name holds 255 bytes);
* an empty result becomes ``"NOSERIAL"``.

What it does not do, because it belongs to the writer: file names use
:func:`sofast_station.archive._common.safe_name` (no ``/`` or ``..`` reaches a path), the workbook
stores text that starts with ``=`` as text, never as a formula, and a web page escapes HTML.
"""

from __future__ import annotations

import re
import unicodedata

#: Longest serial kept, characters.
MAX_SERIAL_CHARS = 64

_BLANKS = re.compile(r"\s+")


def clean_serial(serial) -> tuple[str, str | None]:
    """The serial as the station uses it, and a note saying what was changed (None when nothing was).

    Parameters
    ----------
    serial : str
        As received.

    Returns
    -------
    (str, str or None)
    """
    raw = "" if serial is None else str(serial)
    text = "".join(" " if ch in "\t\n\r\v\f" else ch for ch in raw
                   if ch in "\t\n\r\v\f" or unicodedata.category(ch) not in ("Cc", "Cf", "Cs", "Co", "Cn"))
    text = _BLANKS.sub(" ", text).strip()
    if len(text) > MAX_SERIAL_CHARS:
        text = text[:MAX_SERIAL_CHARS]
    text = text or "NOSERIAL"
    if text == raw:
        return text, None
    shown = raw if len(raw) <= 80 else raw[:80] + "..."
    return text, f"serial {shown!r} ({len(raw)} characters) was made safe: {text!r}"
