"""The facet's result record: the one builder that inspect, the loop and reprocess share, and the fault codes."""

from __future__ import annotations

import pytest

from sofast_station.devices.protocols import FAULT_CODES
from sofast_station.errors import (AnalysisTimeout, CameraTimeoutError, ConfigError, FacetNotFoundError,
                                   UnknownRecipeError, WorkerDied)
from sofast_station.result.faults import fault_code_for, fault_kind, fault_reason
from sofast_station.result.record import FIGURE_KEYS, RecordHead, build_record, figure_uncertainty, figure_value

HEAD = RecordHead(serial="F-1", time="2026-01-02T03:04:05.000+01:00", station="line 1", config_hash="abc",
                  calibration={"radiometric": "r1"}, camera={"exposure_s": 0.01, "gain": 1.0}, facet="dish")


def _figures() -> dict:
    fig = {k: float(i) for i, k in enumerate(FIGURE_KEYS)}
    fig["slope_rms_mrad"] = {"design": {"x": 1.0, "y": 2.0, "magnitude": 2.2}}
    fig["slope_rms_mrad_U"] = {"design": {"x": 0.1, "y": 0.2, "magnitude": 0.25}}
    fig["timings_s"] = {"phase": 0.1}
    fig["valid_fraction"] = 0.9
    return fig


def test_a_measured_record_has_the_head_then_the_figures_then_the_verdict():
    rec = build_record(HEAD, figures=_figures(), verdict={"verdict": "pass", "reasons": []},
                       timings={"capture": 1.5}, measured_distance_m=10.6)
    keys = list(rec)
    assert keys[:3] == ["serial", "time", "station"] and "cycle_id" not in rec and "request" not in rec
    first_figure = keys.index(FIGURE_KEYS[0])
    assert keys[first_figure:first_figure + len(FIGURE_KEYS)] == list(FIGURE_KEYS)
    assert rec["valid_fraction"] == 0.9 and rec["measured_distance_m"] == 10.6
    assert rec["timings_s"] == {"capture": 1.5}, "the analysis's own timings are not a figure"
    assert rec["verdict"] == "pass" and keys[-1] == "timings_s"
    assert figure_value(rec, "slope_rms_mrad.design.magnitude") == 2.2
    assert figure_uncertainty(rec, "slope_rms_mrad.design.magnitude") == 0.25
    assert figure_value(rec, "slope_rms_mrad.parabola.magnitude") is None


def test_a_fault_record_names_its_code_and_reason_first():
    rec = build_record(HEAD, fault=(FAULT_CODES["camera"], "camera: no frame within 2 s"), timings={})
    assert rec["verdict"] == "fault" and rec["fault_code"] == 2 and rec["reasons"] == ["camera: no frame within 2 s"]
    assert fault_kind(rec) == "camera"
    assert not any(k in rec for k in FIGURE_KEYS)


def test_a_record_has_figures_or_a_fault_never_both_nor_neither():
    with pytest.raises(ValueError):
        build_record(HEAD, timings={})
    with pytest.raises(ValueError):
        build_record(HEAD, figures=_figures(), fault=(5, "analysis: x"))


def test_the_truth_keeps_only_the_compared_figures_and_the_optics():
    truth = {"focal_length_x_m": 5.4, "exact_normals": [1, 2, 3], "optics": {"intercept": 0.9}}
    rec = build_record(HEAD, figures=_figures(), verdict={"verdict": "pass"}, truth=truth)
    assert rec["truth"] == {"focal_length_x_m": 5.4, "optics": {"intercept": 0.9}}


@pytest.mark.parametrize("exc, kind", [(AnalysisTimeout("late"), "timeout"), (CameraTimeoutError("no frame"), "camera"),
                                       (FacetNotFoundError("none"), "capture"), (UnknownRecipeError("r"), "recipe"),
                                       (WorkerDied("oom"), "worker"), (ConfigError("bad"), "analysis"),
                                       (RuntimeError("bug"), "internal")])
def test_each_error_that_ends_a_cycle_has_its_fault_code(exc, kind):
    assert fault_code_for(exc) == (FAULT_CODES[kind], kind)
    code, reason = fault_reason(exc)
    assert code == FAULT_CODES[kind] and reason == f"{kind}: {exc}"
