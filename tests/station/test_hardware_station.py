"""The hardware station path with real backends standing in for the hardware: the LCD window on a
virtual X server (Xvfb), a replay camera serving a data dump's frames, the production loop around them.

The dump comes from the simulated station; replayed through the hardware station it must give exactly
the figures archived with it (the same frames, the same analysis).
"""

from __future__ import annotations

import dataclasses
import json

import pytest

from sofast_station.archive import Journal, read_dump
from sofast_station.config import load_config
from sofast_station.result.record import FIGURE_KEYS
from sofast_station.station.service import Service
from tests.devices.test_lcd import running_xvfb


@pytest.fixture(scope="module")
def dump_path(tmp_path_factory):
    """One facet of the small simulated station, dumped."""
    from tests.conftest import ROOT, SMALL_STATION
    d = tmp_path_factory.mktemp("sim")
    path = d / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=d / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json")
                    + "\n[run]\ndump_every_n = 1\n")
    cfg = dataclasses.replace(load_config(path), data_dir=d / "data")
    service = Service(cfg, simulated_facets=1, console=lambda line: None)
    try:
        service.runner.run()
    finally:
        service.close()
    journal = Journal(d / "data" / "journal.sqlite3")
    try:
        (row,) = journal.rows()
        return row.dump_path
    finally:
        journal.close()


def test_lcd_window_and_replay_camera_reproduce_the_dump(dump_path, tmp_path, tmp_path_factory, monkeypatch):
    dump = read_dump(dump_path, load_frames=False)
    station_toml = tmp_path / "station.toml"
    text = dump.station_toml
    # the same station, now with real device backends
    text = text.replace('backend = "simulated"', 'backend = "hardware"')
    text = text.split("[simulation]")[0] + f"""
[devices]
display_options = {{ monitor = "screen", settle_s = 0.0 }}
camera = "replay"
camera_options = {{ dump = "{dump_path}" }}
range_finder_options = {{ distance_m = {dump.measured_distance_m!r} }}
trigger = "simulated"
"""
    station_toml.write_text(text)
    with running_xvfb(tmp_path_factory.mktemp("xvfb")) as display:
        monkeypatch.setenv("DISPLAY", display)
        cfg = load_config(station_toml)
        assert cfg.backend == "hardware"
        service = Service(cfg, simulated_facets=2, console=lambda line: None)
        try:
            outcomes = service.runner.run()
        finally:
            service.close()
    assert [o.answer for o in outcomes] == [dump.record["verdict"]] * 2
    for o in outcomes:
        for k in FIGURE_KEYS:
            assert json.loads(json.dumps(o.record[k])) == dump.record[k], k
