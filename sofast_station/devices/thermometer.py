"""Temperature as an input of the measurement: the screen's and the hall's temperature, read once per facet
(``[temperature]`` in station.toml; docs/reliability.md#temperature).

Sources:

* ``fixed``: typed into the station file (a station with no sensor fitted: the operator updates it, or the
  hall is air-conditioned); the default, at 20 degC;
* ``modbus``: two holding registers of a PLC or a sensor gateway over Modbus TCP (pymodbus), each a signed
  16-bit count times ``scale`` plus ``offset`` degC (the common 0.1 degC per count of PT100 transmitters);
* ``simulated``: the simulated station's hall, ``[simulation.temperature]`` (a start and a drift per hundred
  facets: an afternoon warming the hall), the screen as warm as the hall plus ``screen_above_hall_k``.

Each reading is ``{"screen_c": ..., "hall_c": ...}``. The settings also hold what the budget needs:
the expansion coefficients of the screen's pixel pitch and of the structure from the camera to the fixture (with
their sources), the temperature of commissioning and the reading's standard uncertainty.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..errors import ConfigError, StationError, check_table

SOURCES = ("fixed", "modbus", "simulated")

#: Linear thermal expansion of an LCD's pixel pitch: the panel's TFT glass substrate sets it (alkaline-earth
#: boro-aluminosilicate glass, Corning EAGLE XG: 3.17e-6 /K from 0 to 300 degC, its data sheet).
SCREEN_EXPANSION_PER_K = 3.2e-6
#: Linear thermal expansion of the steel structure from the camera to the fixture (EN 1993-1-1, 3.2.6:
#: 12e-6 /K for structural steel; an aluminium frame is 23e-6 /K, EN 1999-1-1, 3.2.5).
FIXTURE_EXPANSION_PER_K = 12e-6

_KEYS = {"source", "screen_c", "hall_c", "commissioned_c", "u_reading_k", "screen_expansion_per_k",
         "screen_expansion_source", "fixture_expansion_per_k", "fixture_expansion_source", "modbus"}
_MODBUS_KEYS = {"host", "port", "unit_id", "screen_register", "hall_register", "scale", "offset", "timeout_s"}


@dataclass(frozen=True)
class TemperatureSettings:
    """``[temperature]``: where the readings come from and what the budget makes of them.

    Attributes
    ----------
    source : str
        ``fixed``, ``modbus`` or ``simulated``.
    screen_c, hall_c : float
        The fixed readings, degC (``source = "fixed"``).
    commissioned_c : float
        The hall's and the screen's temperature when the geometry was commissioned, degC, unless a marks record
        states the reading ``calibrate marks`` took then.
    u_reading_k : float
        The reading's standard uncertainty, K.
    screen_expansion_per_k, fixture_expansion_per_k : float
        Linear expansion coefficients, 1/K: the screen's pixel pitch, and the structure from the camera to the
        fixture (its length is the camera's distance to the fixture).
    screen_expansion_source, fixture_expansion_source : str
        Where each coefficient comes from.
    modbus : dict
        ``host``, ``port`` (502), ``unit_id`` (1), ``screen_register``, ``hall_register``, ``scale`` (0.1),
        ``offset`` (0.0), ``timeout_s`` (1.0).
    """

    source: str = "fixed"
    screen_c: float = 20.0
    hall_c: float = 20.0
    commissioned_c: float = 20.0
    u_reading_k: float = 0.5
    screen_expansion_per_k: float = SCREEN_EXPANSION_PER_K
    screen_expansion_source: str = "TFT glass substrate, Corning EAGLE XG data sheet: 3.17e-6 /K"
    fixture_expansion_per_k: float = FIXTURE_EXPANSION_PER_K
    fixture_expansion_source: str = "structural steel, EN 1993-1-1 3.2.6: 12e-6 /K"
    modbus: dict = field(default_factory=dict)


def temperature_settings(config) -> TemperatureSettings | None:
    """``[temperature]`` of a station file (*config*: ``path`` and ``raw``), checked; None when it has none.

    Raises
    ------
    ConfigError
        Naming the file, the key, the value and what is allowed.
    """
    table = config.raw.get("temperature")
    if table is None:
        return None
    where = f"{config.path} [temperature]"
    check_table(table, _KEYS, where)
    source = table.get("source", "fixed")
    if source not in SOURCES:
        raise ConfigError(f"{where} source must be one of {', '.join(map(repr, SOURCES))}, got {source!r}")
    values = {}
    for key, low, high in (("screen_c", -40.0, 80.0), ("hall_c", -40.0, 80.0), ("commissioned_c", -40.0, 80.0),
                           ("u_reading_k", 0.0, 20.0), ("screen_expansion_per_k", 0.0, 1e-4),
                           ("fixture_expansion_per_k", 0.0, 1e-4)):
        if key in table:
            v = table[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not low <= v <= high:
                raise ConfigError(f"{where} {key} must be a number from {low:g} to {high:g}, got {v!r}")
            values[key] = float(v)
    for key in ("screen_expansion_source", "fixture_expansion_source"):
        if key in table:
            if not isinstance(table[key], str) or not table[key].strip():
                raise ConfigError(f"{where} {key} must say where the coefficient comes from, got {table[key]!r}")
            values[key] = table[key]
    for key, src in (("screen_expansion_per_k", "screen_expansion_source"),
                     ("fixture_expansion_per_k", "fixture_expansion_source")):
        if key in values and src not in values:
            raise ConfigError(f"{where} {key} is given without {src}: name where the coefficient comes from "
                              "(a data sheet, a standard)")
    modbus = table.get("modbus", {})
    if source == "modbus":
        if not isinstance(modbus, dict) or set(modbus) - _MODBUS_KEYS:
            bad = sorted(set(modbus) - _MODBUS_KEYS) if isinstance(modbus, dict) else modbus
            raise ConfigError(f"{where} modbus must be a table of {', '.join(sorted(_MODBUS_KEYS))}; got {bad!r}")
        for key in ("host", "screen_register", "hall_register"):
            if key not in modbus:
                raise ConfigError(f"{where} modbus needs {key} (source = \"modbus\")")
        for key in ("port", "unit_id", "screen_register", "hall_register"):
            if key in modbus and (isinstance(modbus[key], bool) or not isinstance(modbus[key], int)
                                  or not 0 <= modbus[key] <= 65535):
                raise ConfigError(f"{where} modbus.{key} must be a whole number from 0 to 65535, got {modbus[key]!r}")
    return TemperatureSettings(source=source, modbus=dict(modbus), **values)


class FixedThermometer:
    """Readings typed into the station file."""

    def __init__(self, screen_c: float, hall_c: float):
        self.screen_c, self.hall_c = float(screen_c), float(hall_c)

    def read(self) -> dict:
        return {"screen_c": self.screen_c, "hall_c": self.hall_c}

    def close(self) -> None:
        pass


class ModbusThermometer:
    """Two holding registers over Modbus TCP, each a signed 16-bit count x ``scale`` + ``offset`` degC."""

    def __init__(self, host: str, screen_register: int, hall_register: int, port: int = 502, unit_id: int = 1,
                 scale: float = 0.1, offset: float = 0.0, timeout_s: float = 1.0):
        self.host, self.port, self.unit_id = str(host), int(port), int(unit_id)
        self.registers = {"screen_c": int(screen_register), "hall_c": int(hall_register)}
        self.scale, self.offset, self.timeout_s = float(scale), float(offset), float(timeout_s)
        self._client = None

    def _connect(self):
        # optional: the sensor's driver (pymodbus, ~75 ms CPU), loaded only when [temperature] names a Modbus sensor
        from pymodbus.client import ModbusTcpClient

        client = ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        if not client.connect():
            client.close()
            raise StationError(f"the temperature sensor at {self.host}:{self.port} does not answer (Modbus TCP): "
                               "check it is on and [temperature] modbus host and port")
        return client

    def read(self) -> dict:
        if self._client is None:
            self._client = self._connect()
        out = {}
        for name, address in self.registers.items():
            try:
                rr = self._client.read_holding_registers(address, count=1, device_id=self.unit_id)
            except Exception as exc:            # pymodbus's and the socket's errors alike
                self.close()
                raise StationError(f"reading the {name[:-2]} temperature (register {address} of "
                                   f"{self.host}:{self.port}) failed: {type(exc).__name__}: {exc}") from exc
            if rr.isError():
                raise StationError(f"the temperature sensor refused register {address} ({rr}): check [temperature] "
                                   f"modbus {name[:-2]}_register")
            count = int(rr.registers[0])
            count = count - 65536 if count >= 32768 else count       # signed 16-bit
            out[name] = count * self.scale + self.offset
        return out

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None


class DriftingThermometer:
    """The simulated hall: *start_c* warming by *k_per_100* every hundred readings (one per facet), the screen
    *screen_above_k* warmer than the hall."""

    def __init__(self, start_c: float, k_per_100: float = 0.0, screen_above_k: float = 0.0):
        self.start_c, self.k_per_100, self.screen_above_k = float(start_c), float(k_per_100), float(screen_above_k)
        self.readings = 0

    def read(self) -> dict:
        hall = self.start_c + self.k_per_100 * self.readings / 100.0
        self.readings += 1
        return {"screen_c": hall + self.screen_above_k, "hall_c": hall}

    def close(self) -> None:
        pass


def open_thermometer(settings: TemperatureSettings, simulation: dict | None = None):
    """The thermometer *settings* name (the simulated hall reads ``[simulation.temperature]``: ``start_c`` (the
    settings' hall_c), ``k_per_100`` (0), ``screen_above_k`` (0))."""
    if settings.source == "fixed":
        return FixedThermometer(settings.screen_c, settings.hall_c)
    if settings.source == "modbus":
        return ModbusThermometer(**settings.modbus)
    sim = dict((simulation or {}).get("temperature", {}))
    unknown = sorted(set(sim) - {"start_c", "k_per_100", "screen_above_k"})
    if unknown:
        raise ConfigError(f"[simulation.temperature] has unknown key(s) {', '.join(unknown)}; allowed: start_c, "
                          "k_per_100, screen_above_k")
    return DriftingThermometer(sim.get("start_c", settings.hall_c), sim.get("k_per_100", 0.0),
                               sim.get("screen_above_k", 0.0))
