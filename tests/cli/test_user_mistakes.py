"""Issue 11: a user's mistake gives one line saying what to do and exit code 2, never a traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest



def _run(*args, timeout=300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "sofast_station", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.mark.parametrize("args, message", [
    (["run", "--facets", "-3"], "--facets: must be at least 1, got -3"),
    (["run", "--facets", "0"], "--facets: must be at least 1, got 0"),
    (["run", "--facets", "many"], "--facets: 'many' is not a whole number"),
    (["run", "--max-cycles", "0"], "--max-cycles: must be at least 1, got 0"),
    (["archive", "export", "--from", "someday"], "--from 'someday' is not a date"),
    (["archive", "export", "--from", "2026-12-02", "--to", "2026-12-01"], "is empty or reversed"),
])
def test_command_line_mistakes(small_station_toml, args, message):
    proc = _run(*args, "--config", str(small_station_toml))
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("line, message", [
    ('dump_every_n = "two"', "[run] dump_every_n must be a whole number of at least 0, got 'two'"),
    ("deadline_s = -1", "[run] deadline_s must be a number above 0, got -1"),
])
def test_station_file_mistakes_stop_run_at_the_door(small_station_toml, line, message):
    small_station_toml.write_text(small_station_toml.read_text() + f"\n[run]\n{line}\n")
    proc = _run("run", "--config", str(small_station_toml), "--facets", "2")
    assert proc.returncode == 2 and message in proc.stderr and str(small_station_toml) in proc.stderr
    assert "Traceback" not in proc.stderr and "serial" not in proc.stdout       # no facet was measured


def test_export_accepts_today_yesterday_and_iso_dates(small_station_toml, tmp_path):
    from sofast_station.archive import Journal

    Journal(tmp_path / "station-data" / "journal.sqlite3").close()
    proc = _run("archive", "export", "--config", str(small_station_toml), "--from", "yesterday", "--to", "today")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr


def test_output_piped_into_head_and_a_serial_that_is_a_path(small_station_toml, tmp_path):
    """`inspect --json | head -c 10`: the reader goes away, the command ends quietly; the serial
    ../../../escape writes its result inside data_dir."""
    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "inspect", "--config", str(small_station_toml),
                             "--json", "--serial", "../../../escape"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.read(10)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(300) == 0, err
    assert "Traceback" not in err and "BrokenPipeError" not in err
    saved = list((tmp_path / "station-data" / "inspections").glob("*.json"))
    assert len(saved) == 1 and "escape" in saved[0].name
    assert not [p for p in tmp_path.parent.rglob("escape*") if tmp_path not in p.parents]


def _radiometric(tmp_path, lut) -> str:
    import json

    path = tmp_path / "radiometric.json"
    path.write_text(json.dumps({"schema": 1, "kind": "radiometric", "record_id": "bad",
                                "created": "2026-12-01T00:00:00Z", "lut": lut, "floor_level": 0.01, "max_level": 1.0,
                                "exposure_s": 0.0167, "gain": 1.0}))
    return str(path)


@pytest.mark.parametrize("case", ["nan-record", "falling-record", "alignment-outside", "simulation-type",
                                  "archive-read-only"])
def test_records_recipes_and_folders_are_checked_before_the_first_facet(small_station_toml, tmp_path, case):
    """Issue 11: a bad radiometric record, a recipe's alignment point off the facet, a [simulation] typo or
    an archive folder the station cannot write stop `run` at the door: one line naming the file, the
    field and the value, and what to do; exit code 2 (README "Exit codes"); no traceback; no facet measured."""
    import os
    import re
    from pathlib import Path

    text = small_station_toml.read_text()
    if case in ("nan-record", "falling-record"):
        lut = [i / 99 for i in range(100)]
        lut[37] = float("nan") if case == "nan-record" else 0.2
        record = _radiometric(tmp_path, lut)
        text = re.sub(r'radiometric = ".*"', f'radiometric = "{record}"', text)
        expect = [record, "lut[37] = nan" if case == "nan-record"
                  else "not monotone: lut[36] = 0.363636 > lut[37] = 0.2", "calibrate radiometric"]
    elif case == "alignment-outside":
        text += "\n[recipes.edge]\nalignment_point_m = [0.9, 0.0]\n"
        expect = [str(small_station_toml), "[recipes.edge]", "alignment_point_m = [0.9, 0]",
                  "lies outside the facet's outline", "give a point on the facet"]
    elif case == "simulation-type":
        text = text.replace("twist_mrad_per_m = 0.1", 'twist_mrad_per_m = "0.1"')
        expect = [str(small_station_toml), "[simulation.facet] twist_mrad_per_m must be a number, got '0.1'"]
    else:
        archive = Path(os.environ["SOFAST_DATA_DIR"]) / "archive"       # the tests' data_dir (conftest)
        archive.mkdir(parents=True)
        archive.chmod(0o555)
        if os.access(archive, os.W_OK):         # root writes through permissions: a file in the folder's place
            archive.chmod(0o755)
            archive.rmdir()
            archive.write_text("not a folder")
        expect = [f"cannot write into its archive folder {archive}", "nothing was measured", "data_dir"]
    small_station_toml.write_text(text)
    try:
        proc = _run("run", "--config", str(small_station_toml), "--facets", "2")
    finally:
        if case == "archive-read-only" and archive.is_dir():
            archive.chmod(0o755)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and "SIM-0001" not in proc.stdout
    error = [line for line in proc.stderr.splitlines() if "ERROR" in line]
    assert len(error) == 1, proc.stderr
    for part in expect:
        assert part in error[0], (part, error[0])
