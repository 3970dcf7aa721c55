"""Issue 44 item 3: a reference every shift that judges the station, not a facet. A reference recipe's facet is
judged against its certificate; beyond its limits the line judges no facet until a reference passes again."""

from __future__ import annotations

import datetime as _dt

import pytest

from sofast_station.calibrate.geometry import GeometryReference
from sofast_station.devices.protocols import FAULT_CODES, WARNING_BITS
from sofast_station.result.shift import summarize
from sofast_station.station.reference import ReferenceCheck, judge_reference
from tests.station.line_run import small_line, run_line



def test_a_reference_of_unknown_outline_is_judged_by_its_focal_lengths(tmp_path):
    """A calibration mirror of unknown outline has no measured placement: its focal lengths alone are judged
    (0.1 % off against a 0.5 % tolerance: within; 0.8 %: beyond, naming f_x), the placement said not judged."""
    ref = GeometryReference("flat sphere", 5.4, 5.4, focal_length_tolerance=0.005)
    record = {"serial": "REF-1", "focal_length_x_m": 5.4 * 1.001, "focal_length_y_m": 5.4,
              "curvature_x_per_m": 1 / (5.4 * 1.001), "curvature_y_per_m": 1 / 5.4}
    check = judge_reference(record, ref)
    assert check["within_tolerance"] and check["placement_error_mm"] is None and "not judged" in check["placement_note"]
    assert check["focal_length_relative_errors"]["x"] == pytest.approx(0.001, rel=1e-9)
    record.update(focal_length_x_m=5.4 * 1.008, curvature_x_per_m=1 / (5.4 * 1.008))
    check = judge_reference(record, ref)
    assert not check["within_tolerance"] and check["reasons"][0].startswith("f_x")


def test_no_reference_for_longer_than_a_shift_is_said(tmp_path):
    """With [run] reference_every_h = 12: no reference yet, or the last 13 h ago, is said (an alarm, no hold);
    one 2 h ago is not."""
    check = ReferenceCheck(tmp_path, every_h=12.0)
    assert "no reference has been measured" in check.age_text()
    now = _dt.datetime.now().astimezone()
    check.state["last"] = {"serial": "REF-7", "time": (now - _dt.timedelta(hours=13)).isoformat()}
    assert "REF-7" in check.age_text(now) and "13.0 h ago" in check.age_text(now)
    check.state["last"]["time"] = (now - _dt.timedelta(hours=2)).isoformat()
    assert check.age_text(now) is None
    assert ReferenceCheck(tmp_path, every_h=0.0).age_text() is None


def test_a_reference_beyond_its_limits_holds_the_line_until_one_passes(tmp_path):
    """The small station with a reference recipe (serial REF-..., the twin's truth as its certificate, the 0.5 %
    default tolerance). Its range finder reads 80 mm long (docs/calibration.md: f moves by about 0.8 %): REF-1 is
    judged beyond its limits (its verdict "fail", f_x named), the line holds: SIM-1 is withheld (fault 7, the line's
    warning bit), the page's alarm line-reference and its health line say so, and the hold is kept on disk (a
    restart holds too). The range finder set right, REF-2 passes and ends the hold: SIM-2 is judged again, and the
    page's health line trends both references' errors; the shift's summary counts the references apart."""
    from sofast_station.live.status import read_status

    serials = ["REF-1", "SIM-1", "REF-2", "SIM-2"]
    recipe = '\n[recipes.reference]\nserial_pattern = "^REF-"\nreference = "twin"\n'
    config, service = small_line(tmp_path, serials, recipe)
    service.station.range_finder.error_m = 0.08
    seen = {}

    def between(outcome):
        if outcome.serial == "SIM-1":
            seen["status"] = read_status(config.data_dir)
            seen["held_on_disk"] = ReferenceCheck(config.data_dir).hold
            service.station.range_finder.error_m = 0.0

    answers, final_status, rows = run_line(config, service, between)
    assert answers["REF-1"].kind == "done" and answers["REF-1"].verdict == "fail"
    assert answers["SIM-1"].kind == "fault" and answers["SIM-1"].code == FAULT_CODES["calibration"]
    assert answers["SIM-1"].warnings & WARNING_BITS["line"]
    reason = answers["SIM-1"].reason
    assert "the reference REF-1" in reason and "beyond its certificate's limits" in reason
    assert "line-reference" in seen["status"]["alarms"]
    assert seen["status"]["station_health"]["reference"].startswith("HOLD: the reference REF-1")
    assert seen["held_on_disk"] and "REF-1" in seen["held_on_disk"]
    assert answers["REF-2"].kind == "done" and answers["REF-2"].verdict == "pass"
    assert answers["SIM-2"].kind == "done" and not answers["SIM-2"].warnings & WARNING_BITS["line"]
    assert "line-reference" not in final_status["alarms"]
    # the page's health line trends the references: REF-1 failed (f about +0.7 %), REF-2 within 0.1 %
    trend = final_status["station_health"]["reference"].split("last references: ")[1]
    assert trend.startswith("REF-1 +0.") and "FAIL; REF-2 " in trend and not trend.endswith("FAIL")
    ref1 = rows["REF-1"]["station_checks"]["reference"]
    assert not ref1["within"] and ref1["focal_lengths"]["x"]["relative_error"] > 0.005
    # its own verdict against the recipe's facet limits is kept beside (80 mm out of place: invalid)
    assert rows["REF-1"]["recipe"] == "reference" and rows["REF-1"]["facet_verdict"] == "invalid"
    ref2 = rows["REF-2"]["station_checks"]["reference"]
    assert ref2["within"] and abs(ref2["focal_lengths"]["x"]["relative_error"]) < 0.001
    # the shift's summary (page, console, OPC UA) leaves the references out of the facets and the yield
    summary = summarize(list(rows.values()))
    assert summary.references == 2 and summary.total == 2 and summary.station_faults == 1
