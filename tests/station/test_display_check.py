"""The display checks itself on every facet (issue 44, item 2): the fringes' mean level against the radiometric
table's, on the twin (its own display model, gamma and floor; its sensor's noise, room light and flicker)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.devices.protocols import WARNING_BITS
from sofast_station.devices.renderer import FringeRenderer
from sofast_station.measure.display_response import expected_mean_level, fringe_mean_levels
from sofast_station.station.marks_study import MarkStation
from tests.station.line_run import run_line, small_line

TABLE_GAMMA = 2.2          # the shipped simulated radiometric record was made on the twin's display at 2.2


def _model_level(gamma: float, floor: float, top: float) -> float:
    """The twin's display at *gamma* behind a table made at 2.2: a level y is drawn at y**(gamma / 2.2) of the
    white (its display floor cancels between dark and white); the mean over a period, by quadrature."""
    phi = np.linspace(0.0, 2 * np.pi, 100000, endpoint=False)
    return float(np.mean((floor + (top - floor) * (0.5 + 0.5 * np.cos(phi))) ** (gamma / TABLE_GAMMA)))


def test_the_level_follows_the_twins_display_over_drawn_stations(tmp_path):
    """2 stations drawn from the population (their display's gamma 2.1-2.3 against the table's 2.2, read noise,
    room light, flicker), 3 good captures each with the facet placed anew, and the display changed to gamma
    1.9 and 2.5. Every level is the model's (above) within 2e-3 (the table's own fit and the 8-bit commands:
    the model and the twin agreed within 1e-3 over 3 stations when the tolerance was set); the good captures
    read within the default tolerance 0.015 (the population's worst gamma, 2.1 or 2.3, is 0.0093 from the table's
    level by the model, and flicker moves a cycle by up to 0.003), the changed displays beyond it (0.029 and
    0.025 by the model)."""
    tolerance = 0.015
    for index in range(2):
        st = MarkStation(index, 44, tmp_path)
        rad, cfg = st.radiometric, st.config
        scr = cfg.geometry.screen
        with FringeRenderer(scr.width_px, scr.height_px, lut=rad.lut, floor_level=rad.floor_level,
                            max_level=rad.max_level) as renderer:
            images = renderer.render_all(cfg.fringes.patterns())
        rng = np.random.default_rng([44, index])
        expected = expected_mean_level(rad.floor_level, rad.max_level)

        def level(twin):
            frames = np.stack([st.frame(twin, rng, image) for image in images])
            return fringe_mean_levels(frames, cfg.fringes.slices(), 20.0)["level"]

        gamma = st.optics.display_gamma
        for _ in range(3):
            twin = st.twin((tuple(rng.uniform(-3, 3, 3)), tuple(rng.uniform(-2, 2, 3))))
            got = level(twin)
            assert got == pytest.approx(_model_level(gamma, rad.floor_level, rad.max_level), abs=2e-3)
            assert abs(got - expected) < tolerance
        for changed in (1.9, 2.5):
            got = level(st.twin0.with_optics(dataclasses.replace(st.optics, display_gamma=changed)))
            assert got == pytest.approx(_model_level(changed, rad.floor_level, rad.max_level), abs=2e-3)
            assert abs(got - expected) > tolerance


def test_a_display_changed_on_the_line_raises_its_alarm_and_clears(tmp_path):
    """The small station's line: SIM-1 good; then its display set to gamma 2.6 (a picture mode changed behind
    the table's back): SIM-2 is beyond the tolerance, SIM-3 too and raises line-display (the PLC's line bit,
    the page's alarm and health line); the facets are still judged. The display set back: the alarm clears
    after three facets within it (SIM-4..6)."""
    from sofast_station.live.status import read_status

    serials = [f"SIM-{i}" for i in range(1, 7)]
    config, service = small_line(tmp_path, serials)
    seen = {}

    def between(outcome):
        if outcome.serial == "SIM-1":
            seen["gamma"] = service.station.nominal_twin.optics.display_gamma
            service.station.change_display(display_gamma=2.6)
        if outcome.serial == "SIM-3":
            seen["status"] = read_status(config.data_dir)
            service.station.change_display(display_gamma=seen["gamma"])

    answers, final_status, records = run_line(config, service, between)
    assert all(answers[s].kind == "done" for s in serials)
    line = {s: bool(answers[s].warnings & WARNING_BITS["line"]) for s in serials}
    assert line == {"SIM-1": False, "SIM-2": False, "SIM-3": True, "SIM-4": True, "SIM-5": True, "SIM-6": False}
    assert "line-display" in seen["status"]["alarms"] and "calibrate radiometric" in seen["status"]["alarms"][
        "line-display"]
    assert seen["status"]["station_health"]["display (response)"].startswith("ALARM: ")
    assert "line-display" not in final_status["alarms"]
    rows = {serial: record["station_checks"]["display"] for serial, record in records.items()}
    # gamma 2.6 behind the 2.2 table: the model of the test above gives 0.0327 below the table's level; this
    # station's flicker (each frame's own refresh phase) moved its good cycles' levels by up to 0.003 about the
    # model when measured (4 cycles), hence 5e-3
    assert seen["gamma"] == pytest.approx(TABLE_GAMMA)
    for serial in ("SIM-2", "SIM-3"):
        assert rows[serial]["beyond"] and rows[serial]["error"] == pytest.approx(-0.0327, abs=5e-3)
    assert not rows["SIM-1"]["beyond"] and abs(rows["SIM-1"]["error"]) < 0.005
