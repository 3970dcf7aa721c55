"""Each station its own calibration (issue 43, items 2 and 5).

The six shipped stations shared ~/sofast-station-data, so the heliostat station measured with the dish
station's radiometric record; a screen record from another station (a screen 10 % larger, the same pixel
count) was used without a word. Now each shipped station has a data folder and an identity of its own, every
record a command makes carries its station's identity, and a record made by another station, or one for a
screen of another size, is refused in one line that says what to do.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from sofast_station.calibrate.store import record_dir, select_radiometric, write_record
from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.geometry import ScreenSpec
from sofast_station.measure.screen_shape import ScreenShape
from tests.conftest import ROOT

SHIPPED = [ROOT / "station.toml", *sorted((ROOT / "fixtures/stations").glob("*.toml"))]
DEFAULT_RECORD = ROOT / "calibration/simulated_radiometric.json"


def _radiometric_record(data_dir: Path, station: dict | None) -> Path:
    """The shipped radiometric record written into *data_dir* as a record made on *station*."""
    content = json.loads(DEFAULT_RECORD.read_text())

    def build(record_id, created):
        return {**content, "record_id": record_id, "created": created,
                **({} if station is None else {"station": station})}
    return write_record(data_dir, "radiometric", build)[0]


def _screen_record(data_dir: Path, stated: ScreenSpec, scale: float, station: dict | None = None) -> Path:
    """A flat screen record of a display *scale* times as large as *stated* (the same pixels), as that
    display's own station would have made it (its station.toml stating that display's pitch)."""
    pitch = (stated.pitch_x_m * scale, stated.pitch_y_m * scale)
    made_for = ScreenSpec(stated.width_px, stated.height_px, *pitch)
    shape = ScreenShape("flat", made_for.width_m, made_for.height_m)
    uv, points = shape.grid(5, 4)

    def build(record_id, created):
        return {"schema": 1, "kind": "screen", "record_id": record_id, "created": created, "source": "tests",
                "stated_screen": made_for.to_dict(), "model": "flat", "shape": shape.to_dict(),
                "pitch_m": {"x": {"value": pitch[0], "std": 1e-7}, "y": {"value": pitch[1], "std": 1e-7}},
                "grid": {"nodes_uv_m": uv.tolist(), "nodes_screen_m": points.tolist(), "modes_m": []},
                **({} if station is None else {"station": station})}
    return write_record(data_dir, "screen", build)[0]


def test_each_shipped_station_has_a_data_folder_and_an_identity_of_its_own(monkeypatch, tmp_path):
    """Loaded as a user would (no SOFAST_DATA_DIR; the home folder a temporary one here), the seven shipped
    stations resolve seven different data folders under ~/sofast-station-data and seven different identities."""
    monkeypatch.delenv("SOFAST_DATA_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert len(SHIPPED) == 7                 # station.toml and six in fixtures/stations
    configs = [load_config(path) for path in SHIPPED]
    folders = {c.data_dir for c in configs}
    assert len(folders) == 7, sorted(map(str, folders))
    assert all(f.parent == tmp_path / "sofast-station-data" for f in folders)
    assert len({c.identity["id"] for c in configs}) == 7


def test_the_heliostat_station_does_not_take_the_dish_stations_radiometric_record(monkeypatch, tmp_path):
    """The issue's case: a radiometric record made on the dish station; the heliostat station keeps its own
    (here none yet: the shipped default), where before it measured with the dish's."""
    monkeypatch.delenv("SOFAST_DATA_DIR")
    monkeypatch.setenv("HOME", str(tmp_path))
    dish = load_config(ROOT / "station.toml")
    made = _radiometric_record(dish.data_dir, {"id": "sim-dish", "name": dish.name, "file": str(dish.path)})
    assert select_radiometric(load_config(ROOT / "station.toml")).path == made
    heliostat = load_config(ROOT / "fixtures/stations/heliostat.toml")
    status = select_radiometric(heliostat)
    assert status.origin == "shipped default" and status.path != made


def test_a_record_made_by_another_station_is_refused_in_one_line(small_station_toml, caplog):
    """Two stations sharing one SOFAST_DATA_DIR (or a record copied between their folders): the record of the
    dish station is refused by the small station, in one line naming both and what to do, exit 2."""
    from sofast_station.cli import main

    dish = {"id": "sim-dish", "name": "Simulated dish station", "file": str(ROOT / "station.toml")}
    cfg = load_config(small_station_toml)
    made = _radiometric_record(cfg.data_dir, dish)
    with pytest.raises(ConfigError, match="was made by station 'sim-dish'") as err:
        load_config(small_station_toml)
    text = str(err.value)
    assert str(made) in text and "'Small simulated dish station (tests)'" in text
    assert "data_dir of its own" in text and "calibrate radiometric" in text
    caplog.set_level(logging.ERROR)
    assert main(["calibrate", "status", "--config", str(small_station_toml)]) == 2
    (line,) = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert "was made by station 'sim-dish'" in line and "\n" not in line
    # the station's own record (and one that names no station: made before records carried it) is used
    made.unlink()
    own = _radiometric_record(cfg.data_dir, cfg.identity)
    assert select_radiometric(load_config(small_station_toml)).path == own
    shutil.copy(own, record_dir(cfg.data_dir, "radiometric") / "radiometric-29991231T235959Z-001.json")
    anonymous = record_dir(cfg.data_dir, "radiometric") / "radiometric-29991231T235959Z-001.json"
    anonymous.write_text(json.dumps({k: v for k, v in json.loads(own.read_text()).items() if k != "station"}))
    assert select_radiometric(load_config(small_station_toml)).path == anonymous


def test_a_screen_record_of_a_display_ten_percent_larger_is_refused(small_station_toml):
    """Another station's screen record, 10 % larger with the same pixel count, was used without a word (f off
    by 9 mm); even without an identity (a record made before records carried one) it is now refused, naming
    the pitch and how far off it is. A screen 1 % off station.toml's pitch (a data sheet's error, which
    calibrate screen exists to find) is still taken."""
    cfg = load_config(small_station_toml)
    stated = cfg.stated_geometry.screen
    big = _screen_record(cfg.data_dir, stated, 1.10)
    with pytest.raises(ConfigError, match=r"\+10\.0 % off") as err:
        load_config(small_station_toml)
    assert str(big) in str(err.value) and "calibrate screen" in str(err.value)
    big.unlink()
    near = _screen_record(cfg.data_dir, stated, 1.01, cfg.identity)
    taken = load_config(small_station_toml)
    assert taken.commissioned["screen"]["path"] == str(near)
    x = taken.geometry.measured_screen.nodes_screen_m[:, 0]
    assert np.isclose(x.max() - x.min(), 1.01 * stated.width_m)        # the record's screen, not [screen]'s
