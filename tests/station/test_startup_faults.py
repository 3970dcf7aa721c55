"""Issue 28: what a year of running finds at start and around the loop's files.

A full disk when the lock writes its PID, a commands folder in the wrong shape, temporary files a full
disk left behind, and hostile serials in command files: each is one clear line (or a log line once), never
a traceback, and the station starts and runs.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import logging
import os

import numpy as np
import pytest

from sofast_station.archive import Journal
from sofast_station.config import load_config
from sofast_station.errors import StationError
from sofast_station.live import operator_commands as commands_module
from sofast_station.live.operator_commands import (CommandError, commands_dir, post_command, take_commands,
                                                   take_dump_next)
from sofast_station.live.pictures import FacetPictures
from sofast_station.station.service import DataDirLock, Service, recover_leftovers
from sofast_station.live.status import StatusFile


@pytest.fixture(autouse=True)
def _fresh_reports(monkeypatch):
    """Each test sees the once-per-process log lines of the commands folder afresh."""
    monkeypatch.setattr(commands_module, "_reported", set(), raising=False)


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def test_a_full_disk_when_the_lock_writes_its_pid_is_one_line(tmp_path, monkeypatch, small_station_toml, caplog):
    """The lock's PID (a few bytes) could not be written: an OSError traceback on every start. Now a
    StationError naming the disk (exit code 2 from `run`), and the lock is not left held."""
    monkeypatch.setattr(os, "pwrite", _enospc)
    with pytest.raises(StationError, match=r"station.lock \(No space left on device\): the data folder .* is full"):
        DataDirLock(tmp_path)
    from sofast_station.cli import main
    with caplog.at_level(logging.ERROR):
        assert main(["run", "--config", str(small_station_toml), "--facets", "1"]) == 2
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "is full or read-only" in errors[0].getMessage() and errors[0].exc_info is None
    monkeypatch.undo()
    DataDirLock(tmp_path).release()                    # nothing was held: the next start takes the lock


@pytest.mark.parametrize("shape", ["folder-named-json", "commands-is-a-file", "dump-next-is-a-folder"])
def test_the_commands_folder_in_any_shape_never_stops_the_loop(tmp_path, shape, caplog):
    """A folder commands/evil.json, a file where the commands folder belongs, a folder named dump-next:
    IsADirectoryError / NotADirectoryError on every start. Now each is logged once and set aside or ignored;
    the loop's looks between facets take what they can and never raise."""
    data = tmp_path
    if shape == "folder-named-json":
        (commands_dir(data) / "evil.json").mkdir(parents=True)
        post_command(data, "pause", source="test")                  # a good command beside it still works
    elif shape == "commands-is-a-file":
        commands_dir(data).write_text("not a folder")
        with pytest.raises(CommandError, match="must be a writable folder"):
            post_command(data, "pause", source="test")
    else:
        (data / "dump-next").mkdir()
    with caplog.at_level(logging.ERROR, logger="sofast_station.live.operator_commands"):
        for _ in range(5):                                          # the loop looks between every two facets
            taken = take_commands(data)
            assert not take_dump_next(data)
            if shape == "folder-named-json":
                assert [c.name for c in taken] == (["pause"] if _ == 0 else [])
            else:
                assert taken == []
    assert len([r for r in caplog.records if r.levelno >= logging.ERROR]) == 1, caplog.text   # once, not at every look
    if shape == "folder-named-json":
        assert not (commands_dir(data) / "evil.json").exists()
        assert [p.name.startswith("evil.json.") for p in (commands_dir(data) / "rejected").iterdir()] == [True]


@pytest.mark.parametrize("serial, why", [
    (["A-1", "B-2"], "must be text"),
    (12345, "must be text"),
    ("S" * 300, "at most 64"),
    ("AB\x00CD", "control characters"),
    ("line\nbreak", "control characters"),
    ("", "empty"),
])
def test_a_hostile_serial_in_a_command_file_is_dropped_with_its_reason(tmp_path, serial, why, caplog):
    """A serial command written by hand: a list became the serial "['A-1', 'B-2']", 300 characters were cut to
    64 and NUL or a line break dropped, without a word. Now the file is dropped, saying why."""
    folder = commands_dir(tmp_path)
    folder.mkdir()
    (folder / "00000000000000000001-abcdef01.json").write_text(json.dumps({"command": "serial", "serial": serial}))
    with caplog.at_level(logging.ERROR, logger="sofast_station.live.operator_commands"):
        assert take_commands(tmp_path) == []
    assert why in caplog.text and "dropping the command file" in caplog.text
    assert not list(folder.glob("*.json"))


def test_a_full_disk_leaves_no_temporary_status_or_picture(tmp_path, monkeypatch):
    """The live status and the pictures left `.status.<pid>.tmp` and `.<cycle>.tmp` on a full disk, for good."""
    status = StatusFile(tmp_path)
    pictures = FacetPictures(tmp_path)

    class Outcome:
        cycle_id = "20261202T101010000Z-0123abcd"
        frames = np.zeros((18, 40, 50), np.uint8)
        record = {"crop_box": [0, 0, 40, 50]}
        valid = preview = None
    monkeypatch.setattr(os, "replace", _enospc)
    status.update(state="measuring")                        # logged, never raised: the line goes on
    with pytest.raises(OSError):
        pictures(Outcome())                                  # the runner logs a hook's failure
    monkeypatch.undo()
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".tmp")]


def test_leftover_temporary_files_of_a_dead_station_are_removed_at_start(tmp_path):
    """Those a killed station left in live/ and commands/ (new and old names), beside the archive's."""
    dead = 999999
    live, facets, cmds = tmp_path / "live", tmp_path / "live" / "facets", commands_dir(tmp_path)
    for folder in (facets, cmds):
        folder.mkdir(parents=True, exist_ok=True)
    leftovers = [live / f".status.{dead}.tmp", facets / ".20261202T101010000Z-0123abcd.tmp",
                 live / f".status.json.{dead}.0123abcd.tmp", facets / f".x.npz.{dead}.0123abcd.tmp",
                 cmds / f".0001.json.{dead}.0123abcd.tmp", live / f".monitor.json.{dead}.0123abcd.tmp"]
    for p in leftovers:
        p.write_bytes(b"half")
    alive = live / f".monitor.json.{os.getpid()}.0123abcd.tmp"     # a running monitor's, being written
    alive.write_bytes(b"half")
    with Journal(tmp_path / "journal.sqlite3") as journal:
        removed = recover_leftovers(tmp_path, journal)["temp_files"]
    assert sorted(map(str, removed)) == sorted(map(str, leftovers))
    assert alive.exists()


def test_a_station_starts_and_measures_with_a_commands_file_and_a_dump_next_folder(small_station_toml, tmp_path):
    """The run itself: before, `run` ended at its first look for commands, on every start."""
    cfg = load_config(small_station_toml)
    cfg = dataclasses.replace(cfg, data_dir=tmp_path / "d", raw=dict(cfg.raw, run={"warmup": False}))
    cfg.data_dir.mkdir()
    commands_dir(cfg.data_dir).write_text("a file where the folder belongs")
    (cfg.data_dir / "dump-next").mkdir()
    service = Service(cfg, simulated_facets=2, console=lambda line: None, archiver_process=False)
    try:
        outcomes = service.runner.run()
    finally:
        service.close()
    assert [o.answer for o in outcomes] == ["pass", "pass"]
