"""Shared fixtures: nothing here writes into the source tree (runtime data goes to tmp_path)."""

from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


@pytest.fixture(autouse=True)
def _data_dir(tmp_path, monkeypatch):
    """Every test's station data (journal, results, records) goes to its own temporary folder."""
    monkeypatch.setenv("SOFAST_DATA_DIR", str(tmp_path / "station-data"))
    # A cycle deadline far beyond any facet's time on a loaded machine, where a test does not set one on
    # purpose: the tests do not depend on the machine's speed (issue 11).
    monkeypatch.setenv("SOFAST_DEFAULT_DEADLINE_S", "120")
    # `batch` and `report` lower their own process's priority (issue 11). Called in-process from a test,
    # that would renice the whole pytest run for every later test; tests/test_priority.py checks it apart.
    monkeypatch.setenv("SOFAST_NICE", "0")


SMALL_STATION = """
[station]
name = "Small simulated dish station (tests)"
backend = "simulated"
data_dir = "{data_dir}"
facet = "{facet}"

[camera]
width_px = 400
height_px = 300
focal_length_px = 3409.0
distortion = [-0.05, 0.1, 0.0002, -0.0001, 0.0]

[screen]
width_px = 1920
height_px = 1080
pitch_m = 0.000275

[layout]
separation_m = 0.34

[calibration]
radiometric = "{radiometric}"

[simulation]
seed = 3

[simulation.facet]
focal_length_x_m = 5.42
focal_length_y_m = 5.35
twist_mrad_per_m = 0.1
slope_error_rms_mrad = 0.5
"""


@pytest.fixture
def small_station_toml(tmp_path) -> Path:
    """A quarter-resolution simulated dish station for mechanics tests (CLI, configuration)."""
    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    return path


# The camera tests' --camera-serial / --camera-kind / --camera-shape options (real hardware, opt-in)
# must be known wherever pytest starts.
from tests.devices.cameras.conftest import pytest_addoption  # noqa: E402,F401
