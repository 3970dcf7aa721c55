"""Issue 11: serials from outside, made safe once (sofast_station.serials)."""

import pytest

from sofast_station.serials import MAX_SERIAL_CHARS, clean_serial


@pytest.mark.parametrize("raw, clean", [
    ("F-123", "F-123"),
    ("  F-123 ", "F-123"),
    ("AB\x00CD", "ABCD"),
    ("line\nbreak", "line break"),
    ("esc\x1b[31mred", "esc[31mred"),
    ("", "NOSERIAL"),
    ("\x00\x00", "NOSERIAL"),
    ("=1+2", "=1+2"),                     # kept: the workbook stores it as text, never as a formula
    ("../../x", "____x"),                 # never a path (issue 28): no separator, no '..', no leading dot
    ("MF/2024\\001", "MF_2024_001"),
    ("..", "_"),
    (".hidden", "hidden"),
    ("A.B-1.2", "A.B-1.2"),               # single dots inside are file-name safe
])
def test_clean_serial(raw, clean):
    got, note = clean_serial(raw)
    assert got == clean
    assert (note is None) == (raw == clean)


def test_a_long_serial_is_cut_and_the_note_says_so():
    got, note = clean_serial("S" * 300)
    assert got == "S" * MAX_SERIAL_CHARS and "300 characters" in note
