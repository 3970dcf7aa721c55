"""Issue 29: `study repeatability`'s table: its columns ran together (a 36-character name column with
37-character names, numbers pressed against each other); now every column starts where its heading does,
with the figures' human names and units."""

from __future__ import annotations

import re

from sofast_station.station.study import table_text

ROWS = [
    {"figure": "focal_length_x_m", "mean": 5.418312, "std": 0.00021, "std_error": 0.00019, "U_random": 0.00041,
     "U": 0.00086, "std_over_U_random": 0.46, "grr_percent": 0.59, "grr_class": "acceptable"},
    {"figure": "slope_rms_mrad.higher_order.magnitude", "mean": 0.70441, "std": 0.0021, "std_error": None,
     "U_random": 0.0031, "U": 0.0031, "std_over_U_random": None, "grr_percent": None, "grr_class": None},
    {"figure": "placement.mrad.2", "mean": -0.0123456, "std": 123.4567, "std_error": 0.5, "U_random": 1.0,
     "U": 2.0, "std_over_U_random": 0.5, "grr_percent": None, "grr_class": None},
]


def test_the_study_table_is_aligned_with_human_names_and_units():
    lines = table_text(ROWS).splitlines()
    head = lines[0]
    assert [ln.split("  ")[0].strip() for ln in lines[1:]] == [
        "focal length f_x", "slope error RMS vs higher-order fit", "placement rotation z"]
    # each numeric column ends where its heading ends; names and units start where theirs start
    for column in ("mean", "std error", "U (k=2)", "%GRR"):
        end = head.index(column) + len(column)
        for ln in lines[1:]:
            assert ln[end - 1] != " " and (end == len(ln) or ln[end] == " "), (column, ln)
    unit_at = head.index("unit")
    assert [ln[unit_at:unit_at + 4].strip() for ln in lines[1:]] == ["m", "mrad", "mrad"]
    # two spaces at least between neighbouring columns, even for the widest values: every cell stays apart
    assert [len(re.split(r"\s{2,}", ln.strip())) for ln in lines] == [10, 10, 9, 9]
