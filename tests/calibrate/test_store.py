"""Which radiometric record inspection uses, and what a stale record, a moved dark level, a missing or
corrupt record and a cold camera do (warn or refuse, as configured; errors name the file)."""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import time

import numpy as np
import pytest

from sofast_station.calibrate.errors import StaleCalibrationError, WarmupError
from sofast_station.calibrate.records import load_radiometric
from sofast_station.calibrate.store import (check_age, list_records, mark_camera_started, newest_record_path,
                                            select_radiometric, write_record)
from sofast_station.calibrate.settings import CalibrationPolicy, calibration_settings
from sofast_station.errors import ConfigError
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import inspect

from .conftest import install_record, small_config


def aged_copy(record_path, data_dir, hours: float, **changes):
    """Write the record again as a new file created *hours* ago (other fields changed as given)."""
    d = json.loads(record_path.read_text())
    d.update(changes)
    created = dt.datetime.now().astimezone() - dt.timedelta(hours=hours)
    path, _ = write_record(data_dir, "radiometric", lambda rid, iso: {**d, "record_id": rid, "created": iso}, created)
    return path


def test_newest_record_is_used_history_is_kept_and_nothing_is_overwritten(tmp_path, small_record, caplog):
    cfg = small_config(tmp_path)
    old = aged_copy(small_record.path, cfg.data_dir, hours=3)
    new = aged_copy(small_record.path, cfg.data_dir, hours=1)
    same_second = [write_record(cfg.data_dir, "radiometric", lambda rid, iso: {"record_id": rid}, when)[0]
                   for when in [dt.datetime(2030, 1, 2, 3, 4, 5, tzinfo=dt.timezone.utc)] * 2]
    assert same_second[0].name.endswith("-001.json") and same_second[1].name.endswith("-002.json")
    for p in same_second:
        p.unlink()
    assert list_records(cfg.data_dir, "radiometric") == [old, new]
    assert newest_record_path(cfg.data_dir, "radiometric") == new
    caplog.set_level(logging.INFO)
    station = open_station(cfg, noise=False)
    try:
        assert station.radiometric.record_id == new.stem and station.radiometric.path == new
        assert station.camera.exposure_s == small_record.exposure_s and station.camera.gain == small_record.gain
        assert station.display.settle_s == pytest.approx(small_record.settle_s)
        rec = inspect(station, "STORE-1")
    finally:
        station.close()
    assert rec["calibration"]["radiometric"] == new.stem
    assert rec["camera"] == {"exposure_s": small_record.exposure_s, "gain": small_record.gain}
    assert old.exists() and f"(data_dir, {new})" in caplog.text


def test_without_records_the_shipped_default_is_used_and_named_so(tmp_path, caplog):
    cfg = small_config(tmp_path)
    caplog.set_level(logging.INFO)
    status = select_radiometric(cfg)
    assert status.origin == "shipped default" and status.record.record_id == "simulated-default" and status.exempt
    station = open_station(cfg, noise=False)
    station.close()
    assert "simulated-default (shipped default" in caplog.text and "old" not in caplog.text
    # a hardware station's shipped default is not exempt: never calibrated on this station means stale
    hw = dataclasses.replace(cfg, backend="hardware")
    status = select_radiometric(hw)
    assert not status.exempt
    with pytest.raises(StaleCalibrationError, match="simulated_radiometric.json"):
        check_age(status, CalibrationPolicy(stale="refuse"))


@pytest.mark.parametrize("stale", ["warn", "refuse"])
def test_a_record_older_than_max_age_warns_or_refuses(tmp_path, small_record, caplog, stale):
    cfg = small_config(tmp_path, calibration={"stale": stale, "max_age_h": 24})
    path = aged_copy(small_record.path, cfg.data_dir, hours=30)
    if stale == "refuse":
        with pytest.raises(StaleCalibrationError, match=rf"{path.name}.*30\.0 h old.*max_age_h = 24 h"):
            open_station(cfg, noise=False)
    else:
        station = open_station(cfg, noise=False)
        station.close()
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
        assert any(str(path) in r.getMessage() and "30.0 h old" in r.getMessage() for r in warnings)
    # a longer allowed age: fine
    station = open_station(small_config(tmp_path, calibration={"stale": stale, "max_age_h": 48}), noise=False)
    station.close()


@pytest.mark.parametrize("stale", ["warn", "refuse"])
def test_a_moved_dark_level_warns_or_refuses(tmp_path, small_record, caplog, stale):
    """Room lights on: the background and the light the facet reflects rise; the open checks one dark frame."""
    policy = {"stale": stale, "max_dark_shift_dn": 4.0}
    install_record(small_record.path, tmp_path / "data")
    station = open_station(small_config(tmp_path, calibration=policy), noise=False)          # unchanged room: fine
    station.close()
    lit = small_config(tmp_path, calibration=policy, optics={"background": 0.06, "ambient": 0.05})
    if stale == "refuse":
        with pytest.raises(StaleCalibrationError, match=rf"dark level moved from {small_record.dark_level_dn:.2f} DN"):
            open_station(lit, noise=False)
    else:
        caplog.set_level(logging.WARNING)
        station = open_station(lit, noise=False)
        station.close()
        assert "dark level moved" in caplog.text and small_record.record_id in caplog.text
    # the check can be turned off
    station = open_station(small_config(tmp_path, calibration={**policy, "max_dark_shift_dn": 0},
                                        optics={"background": 0.06, "ambient": 0.05}), noise=False)
    station.close()


def test_a_missing_or_corrupt_record_is_a_clear_error_naming_the_file(tmp_path, small_record, caplog):
    cfg = small_config(tmp_path)
    missing = dataclasses.replace(cfg, radiometric_path=tmp_path / "nowhere.json")
    with pytest.raises(ConfigError, match=r"nowhere\.json does not exist.*calibrate radiometric"):
        open_station(missing, noise=False)
    good = install_record(small_record.path, cfg.data_dir)
    corrupt = aged_copy(small_record.path, cfg.data_dir, hours=0)
    corrupt.write_text(corrupt.read_text()[:200])
    with pytest.raises(ConfigError, match=rf"{corrupt.name} is corrupt"):
        open_station(cfg, noise=False)
    corrupt.write_text(json.dumps({**json.loads(good.read_text()), "lut": "a curve"}))
    with pytest.raises(ConfigError, match=rf"{corrupt.name} holds values that are not numbers"):
        open_station(cfg, noise=False)
    # the routine itself still opens the station (it replaces the record), with a warning
    caplog.set_level(logging.WARNING)
    station = open_station(cfg, noise=False, calibration_checks=False)
    station.close()
    assert station.radiometric.record_id == "none" and corrupt.name in caplog.text


def test_the_warm_up_interlock_says_how_long_to_wait(tmp_path, monkeypatch):
    import types

    from sofast_station.calibrate import store
    # the station's clock stands still, so the minutes in the message do not depend on the machine's speed
    now = time.time()
    monkeypatch.setattr(store, "time", types.SimpleNamespace(time=lambda: now, monotonic=time.monotonic))
    cfg = small_config(tmp_path, calibration={"warmup": True, "warmup_min": 30})
    with pytest.raises(WarmupError, match=r"wait 30\.0 min more"):
        open_station(cfg, noise=False)                       # the camera starts now
    mark_camera_started(cfg.data_dir, now - 10 * 60)
    with pytest.raises(WarmupError, match=r"warmed up for 10\.0 min of the 30 min required: wait 20\.0 min"):
        open_station(cfg, noise=False)
    mark_camera_started(cfg.data_dir, now - 31 * 60)
    station = open_station(cfg, noise=False)
    station.close()
    # off by default
    assert calibration_settings(small_config(tmp_path / "other"))[0].warmup is False


@pytest.mark.parametrize("table, match", [({"stale": "maybe"}, "stale"), ({"max_age_h": -1}, "max_age_h"),
                                          ({"warmup": "yes"}, "warmup"), ({"stael": "warn"}, "stael"),
                                          ({"routine": {"ramp_stp": 5}}, "ramp_stp"),
                                          ({"routine": {"target_dn": 300}}, "target_dn")])
def test_bad_calibration_settings_name_the_key_and_the_file(tmp_path, table, match):
    cfg = small_config(tmp_path, calibration=table)
    with pytest.raises(ConfigError, match=match) as err:
        open_station(cfg, noise=False)
    assert "station.toml" in str(err.value)


def test_record_fields_round_trip(small_record):
    again = load_radiometric(small_record.path)
    assert again.dark_level_dn == small_record.dark_level_dn and again.latency_frames == small_record.latency_frames
    assert np.array_equal(again.lut, small_record.lut) and again.curve["commands"][-1] == 255
    d = again.to_dict()
    # a data dump keeps the scalars; the record's own file also the measured curve
    assert {"dark_level_dn", "latency_frames", "settle_s", "refresh_hz"} <= set(d) and "curve" not in d
    assert again.to_dict(curve=True)["curve"] == json.loads(small_record.path.read_text())["curve"]
    created = dt.datetime.fromisoformat(again.created)
    assert created.tzinfo is not None


@pytest.mark.parametrize("stale", ["warn", "refuse"])
def test_room_light_change_mid_run_marks_the_rows_or_refuses_the_facets(tmp_path, small_record, stale):
    """The station opened in the room light of the calibration; the light goes off for facets 2 and 3,
    then on again (the noise-free station, whose record this is, so that only the light changes). Every
    facet's own dark frame is checked: the rows of facets 2 and 3 say they were measured on a stale
    calibration (warn), or those facets are refused with fault 7 (refuse); the line goes on either way."""
    from sofast_station.archive import Journal
    from sofast_station.devices.protocols import FAULT_CODES
    from sofast_station.station.service import Service

    install_record(small_record.path, tmp_path / "data")
    lit = {"SIM-0002": "lights-off", "SIM-0003": "lights-off"}
    cfg = small_config(tmp_path, calibration={"stale": stale, "max_dark_shift_dn": 4.0},
                       simulation={"faults": lit})
    lines: list[str] = []
    service = Service(cfg, simulated_facets=4, console=lines.append, archiver_process=False,
                      station=open_station(cfg, noise=False))
    robot = service.trigger
    try:
        service.runner.run()
    finally:
        service.close()
    finals = {a.serial: a for a in robot.answers if a.kind in ("done", "fault")}
    assert sorted(finals) == [f"SIM-{i:04d}" for i in range(1, 5)]
    journal = Journal(cfg.data_dir / "journal.sqlite3")
    try:
        rows = {r.serial: r.record for r in journal.rows()}
    finally:
        journal.close()
    for serial in ("SIM-0001", "SIM-0004"):
        assert finals[serial].kind == "done", finals[serial]
        assert rows[serial]["calibration"] == {"radiometric": small_record.record_id, "origin": "data_dir",
                                               "warnings": []}
    for serial, line in zip(lit, lines[1:3]):
        assert serial in line
        if stale == "warn":
            assert finals[serial].kind == "done"
            (warning,) = rows[serial]["calibration"]["warnings"]
            assert f"dark level moved from {small_record.dark_level_dn:.2f} DN" in warning
            assert "calibration stale: see the log" in line
        else:
            assert finals[serial].kind == "fault" and finals[serial].code == FAULT_CODES["calibration"]
            assert "dark level moved" in finals[serial].reason and "refuse" in finals[serial].reason
            assert rows[serial]["verdict"] == "fault" and rows[serial]["fault_code"] == FAULT_CODES["calibration"]
