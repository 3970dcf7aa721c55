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
