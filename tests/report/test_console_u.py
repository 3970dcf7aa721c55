"""Every figure the console shows carries its U (standards: once the metrology issue landed, every reported figure
is a measurement result): the slope RMS values, and the noise-corrected ones, which were printed bare until
2026-12-06."""

from __future__ import annotations

import json
import re

from sofast_station.report.summary import record_text
from tests.conftest import ROOT


def test_noise_corrected_slope_rms_is_printed_with_its_u():
    rec = json.loads((ROOT / "tests/archive/full_record.json").read_text())
    text = record_text(rec)
    block = text[text.index("with that noise removed"):].splitlines()[1:4]
    assert [line.split()[0] for line in block] == ["design", "parabola", "higher_order"]
    for line, model in zip(block, ("design", "parabola", "higher_order")):
        values = re.findall(r"([0-9.]+) ± ([0-9.]+)", line)
        assert len(values) == 3, line
        want = [rec["slope_rms_corrected_mrad_U"][model][a] for a in ("x", "y", "magnitude")]
        assert [float(u) for _, u in values] == [float(f"{w:.2g}") for w in want], line


def test_the_noise_floor_is_printed_with_its_u_where_the_record_has_one():
    rec = json.loads((ROOT / "tests/archive/full_record.json").read_text())
    model = next(iter(rec["slope_rms_noise_mrad"]))
    line = next(s for s in record_text(rec).splitlines() if "noise explained" in s)
    assert "±" not in line, line                 # an archived record from before the floor had its U
    rec["slope_rms_noise_mrad_U"] = {m: {a: 0.0021 for a in ("x", "y", "magnitude")}
                                     for m in rec["slope_rms_noise_mrad"]}
    line = next(s for s in record_text(rec).splitlines() if "noise explained" in s)
    values = re.findall(r"([0-9.]+) ± ([0-9.]+)", line)
    assert [float(u) for _, u in values] == [0.0021] * 3, line
    assert [float(v) for v, _ in values] == [round(rec["slope_rms_noise_mrad"][model][a], 4)
                                             for a in ("x", "y", "magnitude")], line
