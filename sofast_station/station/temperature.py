"""The line's temperature reading per facet, against the commissioning's (docs/reliability.md#temperature).

:class:`TemperatureCheck` reads the thermometer of ``[temperature]`` (:mod:`sofast_station.devices.thermometer`)
once per cycle; the record's ``station_checks.temperature`` keeps the reading, the temperature of
commissioning it is compared with (the newest marks record's reading, which ``calibrate marks`` takes, else
``[temperature] commissioned_c``) and the standard uncertainties the expansion since then leaves
(:func:`~sofast_station.measure.thermal.thermal_u`), which the facet's budget then gets
(:func:`~sofast_station.measure.thermal.widen_for_temperature`). A reading that fails is said in the row and the
log (once, and when it reads again); the facet is measured all the same, its U without the thermal row.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..devices.thermometer import TemperatureSettings, open_thermometer, temperature_settings
from ..measure.thermal import thermal_u

log = logging.getLogger(__name__)


def read_temperature(config) -> dict | None:
    """One reading of the station's thermometer (for a record made at commissioning), or None without
    ``[temperature]`` or when it cannot be read (logged)."""
    settings = temperature_settings(config)
    if settings is None:
        return None
    thermometer = open_thermometer(settings, config.simulation)
    try:
        return {"source": settings.source, **thermometer.read()}
    except Exception as exc:              # the record is made without it, and says so in the log
        log.warning("the temperature could not be read for the record: %s", exc)
        return None
    finally:
        thermometer.close()


class TemperatureCheck:
    """One reading per cycle and what it leaves unknown of the geometry (module docstring)."""

    def __init__(self, settings: TemperatureSettings, thermometer, commissioned: dict, geometry,
                 pitch_u_relative: float):
        self.settings = settings
        self.thermometer = thermometer
        self.commissioned = commissioned
        self.distance_m = float(np.linalg.norm(geometry.fixture_to_camera.translation))
        self.rotation = geometry.fixture_to_camera.rotation
        self.pitch_u = float(pitch_u_relative)
        self._failing = False

    @classmethod
    def open(cls, config, marks_record: dict | None = None) -> "TemperatureCheck | None":
        """The check of a station (*config*), or None without ``[temperature]``. The temperature of commissioning
        is *marks_record*'s reading when it has one, else ``[temperature] commissioned_c``."""
        settings = temperature_settings(config)
        if settings is None:
            return None
        taken = (marks_record or {}).get("temperature_c")
        if isinstance(taken, dict) and all(isinstance(taken.get(k), (int, float)) for k in ("screen_c", "hall_c")):
            commissioned = {"screen_c": float(taken["screen_c"]), "hall_c": float(taken["hall_c"]),
                            "from": f"marks record {marks_record.get('record_id')}"}
        else:
            commissioned = {"screen_c": settings.commissioned_c, "hall_c": settings.commissioned_c,
                            "from": "[temperature] commissioned_c"}
        return cls(settings, open_thermometer(settings, config.simulation), commissioned, config.geometry,
                   config.uncertainty.screen_pitch_relative)

    def check(self) -> dict:
        """This cycle's reading and the uncertainties it implies (the record's ``station_checks.temperature``)."""
        s = self.settings
        entry: dict = {"source": s.source, "commissioned": dict(self.commissioned)}
        try:
            reading = self.thermometer.read()
        except Exception as exc:              # a thermometer never stops the line: the row says what is missing
            if not self._failing:
                log.warning("the temperature could not be read (%s): facets are measured without the thermal "
                            "expansion in their U until it reads again", exc)
            self._failing = True
            entry["error"] = f"not read: {exc}"
            return entry
        if self._failing:
            log.info("the temperature reads again")
        self._failing = False
        screen, hall = float(reading["screen_c"]), float(reading["hall_c"])
        if not (math.isfinite(screen) and math.isfinite(hall)):
            entry["error"] = f"not a temperature: {reading}"
            return entry
        d_screen, d_hall = screen - self.commissioned["screen_c"], hall - self.commissioned["hall_c"]
        entry.update({"screen_c": round(screen, 3), "hall_c": round(hall, 3),
                      "delta_k": {"screen": round(d_screen, 3), "hall": round(d_hall, 3)},
                      "u": thermal_u(d_screen, d_hall, s.u_reading_k, s.screen_expansion_per_k,
                                     s.fixture_expansion_per_k, self.distance_m, self.rotation),
                      "coefficients_per_k": {"screen": s.screen_expansion_per_k, "fixture": s.fixture_expansion_per_k}})
        return entry

    def close(self) -> None:
        self.thermometer.close()
