"""Issue 44 item 4: temperature as an input. A reading per facet in every row (and so every dump); the budget
gets the screen's and the fixture's thermal expansion since commissioning."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from sofast_station.devices.thermometer import ModbusThermometer, temperature_settings
from sofast_station.errors import ConfigError, StationError
from sofast_station.measure.thermal import thermal_u, widen_for_temperature


def test_the_expansion_since_commissioning_is_the_budgets_thermal_row():
    """10 K warmer than at commissioning, read to 0.5 K: the camera-to-fixture structure (steel, 12e-6 /K, 10.66 m)
    grows by 12e-6 x 10.66 m x sqrt(10^2 + 0.5^2) = 1.2812 mm along the line of sight, which is the fixture's z
    when it faces the camera (its axes the camera's turned by a half-turn about x); the screen's pitch by
    3.2e-6 x sqrt(10^2 + 0.5^2) = 3.204e-5. The budget's screen pitch row, computed at u_p = 1e-4, reaches each
    figure by sqrt(2) x 3.204e-5 / 1e-4 of its contribution (both axes expand together); the placement along z
    by the 1.2812 mm. Every reached U grows in quadrature by twice that, the combined standard by it."""
    u = thermal_u(10.0, 10.0, 0.5, 3.2e-6, 12e-6, 10.66, np.diag([1.0, -1.0, -1.0]))
    along = 12e-6 * 10.66e3 * math.hypot(10.0, 0.5)
    assert u["screen_pitch_relative"] == pytest.approx(3.2e-6 * math.hypot(10.0, 0.5))
    assert u["fixture_translation_mm"] == pytest.approx([0.0, 0.0, along])
    names = ["focal_length_x_m", "placement.mm.2", "slope_rms_mrad.design.x"]
    figures = {"focal_length_x_m_U": 0.0012, "placement_U": {"mm": [1.0, 1.0, 1.0]},
               "slope_rms_mrad_U": {"design": {"x": 0.02}},
               "uncertainty_budget": {"figures": names, "combined_standard": [0.0006, 0.5, 0.01],
                                      "rows": [{"group": "screen pitch", "contributions": [0.0002, 0.0, 0.001]}]}}
    added = widen_for_temperature(figures, u, 1e-4)
    ratio = math.sqrt(2.0) * u["screen_pitch_relative"] / 1e-4
    assert added["focal_length_x_m"] == pytest.approx(2 * 0.0002 * ratio)
    assert figures["focal_length_x_m_U"] == pytest.approx(math.hypot(0.0012, 2 * 0.0002 * ratio))
    assert figures["slope_rms_mrad_U"]["design"]["x"] == pytest.approx(math.hypot(0.02, 2 * 0.001 * ratio))
    assert figures["placement_U"]["mm"][2] == pytest.approx(math.hypot(1.0, 2 * along))
    assert figures["placement_U"]["mm"][:2] == [1.0, 1.0]
    row = figures["uncertainty_budget"]["rows"][-1]
    assert row["group"] == "thermal expansion"
    # (the budget's table keeps three significant digits, as the analysis writes it)
    assert figures["uncertainty_budget"]["combined_standard"][1] == pytest.approx(math.hypot(0.5, along), rel=5e-3)


def test_a_coefficient_without_its_source_is_refused():
    """Every coefficient names where it comes from; a source the station does not know is named."""
    cfg = SimpleNamespace(path="station.toml", raw={"temperature": {"fixture_expansion_per_k": 23e-6}})
    with pytest.raises(ConfigError, match="fixture_expansion_per_k is given without fixture_expansion_source"):
        temperature_settings(cfg)
    cfg.raw = {"temperature": {"source": "usb"}}
    with pytest.raises(ConfigError, match=r"\[temperature\] source must be one of 'fixed', 'modbus', 'simulated'"):
        temperature_settings(cfg)
    cfg.raw = {"temperature": {"source": "modbus", "modbus": {"host": "10.0.0.5", "screen_register": 3}}}
    with pytest.raises(ConfigError, match="modbus needs hall_register"):
        temperature_settings(cfg)


def test_a_modbus_sensor_is_read_as_signed_tenths_of_a_degree(tmp_path):
    """A gateway's holding registers (a pymodbus server in its own process, as the PLC tests use): 235 counts
    read 23.5 degC and 65511 (-25 as a signed 16-bit count) -2.5 degC; a sensor that stops answering is a
    StationError naming the register and the host."""
    from pymodbus.client import ModbusTcpClient

    from tests.devices.triggers.test_modbus import Plc

    plc = Plc({"facets": []})
    try:
        writer = ModbusTcpClient("127.0.0.1", port=plc.port, timeout=2)
        assert writer.connect()
        assert not writer.write_registers(150, [235, 65536 - 25], device_id=1).isError()
        writer.close()
        sensor = ModbusThermometer("127.0.0.1", 150, 151, port=plc.port, timeout_s=1.0)
        assert sensor.read() == pytest.approx({"screen_c": 23.5, "hall_c": -2.5})
        plc.kill()
        with pytest.raises(StationError, match=r"(register 150 of 127\.0\.0\.1|does not answer)"):
            sensor.read()
        sensor.close()
    finally:
        plc.kill()
