"""Issue 43, item 4: a calibration is refused while the line runs on the station's data folder (it would write
a record the page names while the line measures with the one it loaded), and the line does not start while a
calibration runs."""

from __future__ import annotations

import os

import pytest

from sofast_station.cli import main
from sofast_station.config import load_config
from sofast_station.station.service import DataDirLock, StationLocked


def test_calibrate_is_refused_while_the_line_holds_the_data_folder(small_station_toml, caplog):
    data_dir = load_config(small_station_toml).data_dir
    line = DataDirLock(data_dir)                       # what `run` takes before any device opens
    try:
        code = main(["calibrate", "radiometric", "--config", str(small_station_toml)])
        err = caplog.text                              # the command line's one error line goes to the log
        assert code == 2, err
        assert f"the line is running on {data_dir} (process {os.getpid()})" in err
        assert "Stop the line" in err and "takes the newest records at its start" in err
        assert not (data_dir / "calibration" / "radiometric").exists()      # nothing was written
        # a calibration that only reads (status) is not refused
        assert main(["calibrate", "status", "--config", str(small_station_toml)]) == 0
    finally:
        line.release()


def test_the_line_does_not_start_while_a_calibration_runs(small_station_toml):
    data_dir = load_config(small_station_toml).data_dir
    calibration = DataDirLock(data_dir, what="calibration")
    try:
        with pytest.raises(StationLocked, match=rf"another calibration \(process {os.getpid()}\) is running"):
            DataDirLock(data_dir)
    finally:
        calibration.release()
    DataDirLock(data_dir).release()                    # free again once the calibration is done
