"""``--help`` and a mistake answer at once: before a command needs them, none of the heavy libraries is loaded.

Each case runs ``python -X importtime -m sofast_station ...`` in a fresh interpreter, as a user's
``sofast-station ...`` does, and reads from the interpreter's own import log every module it loaded. A test
of what is imported, not of time (the machine's speed is no test's business; benchmarks/commands.py times
the commands): numpy with its friends is 0.3 to 1 s of start-up, and a user who mistyped an option should
not wait for it.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

#: Libraries that take a tenth of a second or more to load, and that no --help or mistake needs.
HEAVY = ("numpy", "scipy", "cv2", "numba", "matplotlib", "h5py", "openpyxl", "starlette", "uvicorn", "diskcache",
         "asyncua", "moderngl", "pymodbus", "usb", "PIL")


def loaded_packages(argv: list[str], cwd) -> tuple[subprocess.CompletedProcess, set[str]]:
    """Run ``sofast-station *argv*`` in a fresh interpreter; its result and the top-level names of every module
    it imported (from ``-X importtime``'s log on stderr)."""
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "sofast_station", *argv], capture_output=True,
                          text=True, timeout=120, cwd=cwd)
    names = set()
    for line in proc.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            name = line.rsplit("|", 1)[1].strip()
            if name and name != "package":
                names.add(name.split(".")[0])
    assert "sofast_station" in names, "the import log was not read: " + proc.stderr[-500:]
    return proc, names


CASES = {
    "top-level help": (["--help"], 0, "commands"),
    "a command's help": (["inspect", "--help"], 0, "--config"),
    "help of the re-analysis": (["reprocess", "--help"], 0, "DUMP"),
    "help of the import": (["import-opencsp", "--help"], 0, "--robust"),
    "a mistyped command": (["inspekt"], 2, "invalid choice"),
    "an unknown option": (["inspect", "--bogus"], 2, "unrecognized arguments"),
    "a missing argument": (["reprocess"], 2, "required"),
    "a missing station file": (["inspect", "--config", "nowhere.toml"], 2, "nowhere.toml does not exist"),
    "a missing station file for report spc": (["report", "spc", "--config", "nowhere.toml"], 2, "does not exist"),
    "a missing station file for calibrate": (["calibrate", "status", "--config", "nowhere.toml"], 2,
                                             "does not exist"),
    "a missing dump to reprocess": (["reprocess", "nowhere.h5"], 2, "nowhere.h5 does not exist"),
    "a missing dump to report": (["report", "nowhere.h5"], 2, "nowhere.h5 does not exist"),
    "a missing OpenCSP folder": (["import-opencsp", "--test-data", "nowhere"], 2, "nowhere"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_help_and_mistakes_load_no_heavy_library(case, tmp_path):
    argv, code, said = CASES[case]
    proc, names = loaded_packages(argv, tmp_path)
    assert proc.returncode == code, proc.stdout[-400:] + proc.stderr[-800:]
    assert said in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr
    assert not names & set(HEAVY), f"{case} loaded {sorted(names & set(HEAVY))}"


def test_the_import_log_sees_a_heavy_library_when_one_is_loaded(tmp_path):
    """The check above can fail: a command that does its work (a station file that exists and a facet it
    measures is too slow here; a report of the journal of an empty station loads the station's config)
    shows numpy in the same log."""
    station = tmp_path / "station.toml"
    station.write_text('[station]\nfacet = "nowhere.toml"\n')
    proc, names = loaded_packages(["inspect", "--config", str(station)], tmp_path)
    assert proc.returncode == 2 and "nowhere.toml" in proc.stderr
    assert "numpy" in names


def test_a_second_import_of_the_same_opencsp_files_builds_no_triangulation(repo_root, tmp_path, monkeypatch):
    """The display grid's triangulation (scipy.interpolate, 0.2-0.5 s to load and build) is kept in the
    station's cache by the first import of OpenCSP's files; the second reads which way each grid cell is
    split and loads neither scipy's interpolation nor its rotations (OpenCV's Rodrigues serves)."""
    monkeypatch.setenv("SOFAST_DATA_DIR", str(tmp_path / "data"))
    argv = ["import-opencsp", "--test-data", str(repo_root / "fixtures" / "opencsp" / "test_data")]

    def modules():
        proc = subprocess.run([sys.executable, "-X", "importtime", "-m", "sofast_station", *argv],
                              capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-800:]
        return proc.stdout, {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines()
                             if line.startswith("import time:") and "|" in line}

    first_out, first = modules()
    second_out, second = modules()
    assert "scipy.interpolate" in first               # the check can fail: the first run builds it
    assert not {"scipy.interpolate", "scipy.spatial", "scipy.spatial.transform"} & second
    assert second_out == first_out                    # the same figures, every printed digit
