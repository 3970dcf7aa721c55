"""Issue 15: operator commands reach the running loop between facets (live/operator_commands.py).

One small simulated run: a serial typed by hand and a dump asked for before the first facet, a
re-measurement and a pause after the second; the line waits while paused and goes on when resumed.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from sofast_station.archive import Journal
from sofast_station.config import load_config
from sofast_station.errors import CommandError
from sofast_station.live.operator_commands import post_command, take_commands
from sofast_station.live.pictures import picture_path
from sofast_station.station.service import Service
from sofast_station.live.status import read_status


def _wait_for(predicate, timeout_s=120.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def test_commands_reach_the_loop(small_station_toml):
    small_station_toml.write_text(small_station_toml.read_text() + "\n[run]\ndeadline_s = 300\n")  # busy machines
    cfg = load_config(small_station_toml)
    data = cfg.data_dir
    post_command(data, "serial", "HAND-0001", source="test")
    post_command(data, "dump-next", source="test")
    lines: list[str] = []
    service = Service(cfg, simulated_facets=3, console=lines.append, archiver_process=False)
    runner, robot = service.runner, service.trigger

    def after(outcome):
        if outcome.serial == "SIM-0002" and not outcome.record["request"].get("operator"):
            post_command(data, "remeasure", source="test")
            post_command(data, "pause", source="test")
    runner.hooks.append(after)
    seen: dict = {}

    def operator():                           # the station's devices belong to the main thread
        seen["paused"] = _wait_for(lambda: read_status(data)["state"] == "paused")
        seen["cycles"] = runner.cycles
        time.sleep(1.0)                       # paused: no facet is taken, however long it waits
        seen["cycles_later"] = runner.cycles
        seen["answers"] = [a.serial for a in robot.answers if a.kind != "busy"]
        post_command(data, "resume", source="test")
    thread = threading.Thread(target=operator, daemon=True)
    try:
        thread.start()
        outcomes = runner.run()
        thread.join(timeout=120)
    finally:
        service.close()
    assert seen["paused"] and seen["cycles"] == seen["cycles_later"] == 3, seen
    assert seen["answers"] == ["SIM-0001", "SIM-0002"]
    assert [o.serial for o in outcomes] == ["HAND-0001", "SIM-0002", "SIM-0002", "SIM-0003"]
    first, _, again, _ = (o.record for o in outcomes)
    assert first["request"]["serial_read"] == "SIM-0001" and first["request"]["serial_source"] == "operator"
    assert outcomes[0].dumped and not outcomes[1].dumped
    assert again["request"]["operator"] == "remeasure"
    # the robot was answered for its three facets only, under the serials it placed
    assert [(a.serial, a.kind) for a in robot.answers if a.kind != "busy"] == [
        ("SIM-0001", "done"), ("SIM-0002", "done"), ("SIM-0003", "done")]
    with Journal(data / "journal.sqlite3") as journal:
        assert [r.serial for r in journal.rows()] == ["HAND-0001", "SIM-0002", "SIM-0002", "SIM-0003"]
    assert read_status(data)["state"] == "offline"
    assert take_commands(data) == []
    # every facet left its small picture file: the white frame, the outline mask, the thinned map
    for o in outcomes:
        with np.load(picture_path(data, o.cycle_id)) as pic:
            assert pic["white"].max() > 100 and pic["mask"].shape == pic["white"].shape
            assert pic["mask"].mean() > 0.3
            assert pic["map_points_xy_m"].shape[0] == 2 and pic["map_residuals_design"].shape[0] == 2
    assert len(lines) == 4 and lines[2].lstrip().startswith("3/4")


def test_bad_commands_are_refused(tmp_path):
    with pytest.raises(CommandError, match="unknown command"):
        post_command(tmp_path, "format-disk")
    with pytest.raises(CommandError, match="at most"):
        post_command(tmp_path, "serial", "X" * 300)
    with pytest.raises(CommandError, match="control characters"):
        post_command(tmp_path, "serial", "A\x1b[2JB")
    (tmp_path / "commands").mkdir(exist_ok=True)
    (tmp_path / "commands" / "0001.json").write_text("{not json")
    assert take_commands(tmp_path) == [] and not list((tmp_path / "commands").glob("*.json"))
