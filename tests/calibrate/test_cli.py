"""The ``calibrate`` subcommands through their own parser (``register``), on the small simulated station."""

from __future__ import annotations

import argparse
import json
import logging

import pytest

from sofast_station.station.calibrate_cli import register
from sofast_station.calibrate.store import list_records
from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.station.factory import open_station


def run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="sofast-station")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_calibrate_radiometric_writes_a_dated_record_and_inspection_uses_it(small_station_toml, capsys, caplog):
    """The twin's default room light varies by 20 % from frame to frame: the routine averages the most frames
    it may (8) per ramp level and says the levels are still known to only ~0.2 DN."""
    caplog.set_level(logging.INFO)
    assert run(["calibrate", "radiometric", "--config", str(small_station_toml), "--seed", "4"]) == 0
    out = capsys.readouterr().out
    cfg = load_config(small_station_toml)
    records = list_records(cfg.data_dir, "radiometric")
    assert len(records) == 1 and records[0].with_suffix(".png").exists()
    assert out.startswith(f"Radiometric calibration {records[0].stem}") and "display latency: 0 frame(s)" in out
    assert "exposure: 16.667 ms (1 refresh period(s) at 60 Hz)" in out and "fit polynomial" in out
    assert "ramp: 52 levels, 8 frame(s) each" in caplog.text and "will be known to" in caplog.text
    for step in ("active pixels:", "display latency:", "exposure:", "gain:", "ramp: 52/52 levels", "response: floor"):
        assert step in caplog.text, step
    # a second run keeps the first record
    assert run(["calibrate", "radiometric", "--config", str(small_station_toml), "--noise-free", "--ramp-step", "15",
                "--no-plot", "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    records = list_records(cfg.data_dir, "radiometric")
    assert len(records) == 2 and data["path"] == str(records[1]) and data["curve"]["commands"][1] == 15
    station = open_station(cfg, noise=False)
    try:
        assert station.radiometric.record_id == records[1].stem
    finally:
        station.close()
    assert run(["calibrate", "status", "--config", str(small_station_toml)]) == 0
    status = capsys.readouterr().out
    assert f"radiometric record {records[1].stem} (data_dir" in status and "radiometric: 2 record(s)" in status


def test_bad_routine_options_are_refused(small_station_toml):
    from sofast_station.errors import ConfigError
    with pytest.raises(ConfigError, match="command line: .*ramp_step"):
        run(["calibrate", "radiometric", "--config", str(small_station_toml), "--ramp-step", "0"])


# -- arguments checked before anything is measured (issue 43) -------------------------------------------------

def _nothing_may_open(monkeypatch):
    """Fail the test if a station opens or a commissioning step starts: the refusals below come first."""
    from sofast_station.station import commissioning, factory

    def opened(*args, **kwargs):
        raise AssertionError("a station was opened before the arguments were checked")
    monkeypatch.setattr(factory, "open_station", opened)
    monkeypatch.setattr(commissioning, "run_radiometric", opened)


def test_calibrate_screen_refuses_views_it_cannot_use(small_station_toml, capsys, monkeypatch):
    """`calibrate screen --views 0` ran the station file's views without a word (`views or default`). Zero is
    a usage error (exit 2, naming --views); fewer than the calibration needs to keep a record (min_views 4) is
    refused before the station opens, naming the least it takes; likewise --placements for calibrate pose."""
    from sofast_station.cli import main

    _nothing_may_open(monkeypatch)
    with pytest.raises(SystemExit) as exit_:
        main(["calibrate", "screen", "--config", str(small_station_toml), "--views", "0"])
    assert exit_.value.code == 2 and "argument --views: must be at least 1, got 0" in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"--views 2: calibrate screen needs at least 4 usable views"):
        run(["calibrate", "screen", "--config", str(small_station_toml), "--views", "2"])
    with pytest.raises(ConfigError, match=r"--placements 1: calibrate pose needs at least 3 usable placements"):
        run(["calibrate", "pose", "--config", str(small_station_toml), "--placements", "1"])


def test_calibrate_commission_checks_every_argument_before_its_first_step(small_station_toml, tmp_path, caplog,
                                                                          monkeypatch):
    """`calibrate commission --target missing.toml` ran the radiometric step (minutes on a real station) before
    the pose step found the target missing. Now a missing or broken --target or --reference stops it at once,
    in one line (exit 2), and no step runs, no record is written."""
    from sofast_station.cli import main

    _nothing_may_open(monkeypatch)
    caplog.set_level(logging.ERROR)
    config = str(small_station_toml)
    assert main(["calibrate", "commission", "--config", config, "--target", str(tmp_path / "missing.toml")]) == 2
    (line,) = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert line.startswith("--target: reference mirror file") and "missing.toml does not exist" in line
    (tmp_path / "reference.toml").write_text("[reference]\nfocal_length_x_m = 5.4\n")
    caplog.clear()
    assert main(["calibrate", "commission", "--config", config, "--reference", str(tmp_path / "reference.toml")]) == 2
    (line,) = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert line.startswith("--reference:") and "is missing focal_length_y_m" in line
    assert not (load_config(small_station_toml).data_dir / "calibration").exists()
