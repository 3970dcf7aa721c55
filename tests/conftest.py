"""Shared fixtures: nothing here writes into the source tree (runtime data goes to tmp_path)."""

from __future__ import annotations

import importlib
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Debian's chromium, which the page's browser tests drive through Playwright (setup-env test installs it).
CHROMIUM = "/usr/bin/chromium"


def require(module: str):
    """Import a test dependency: when it is missing the suite FAILS (a collection error naming it and how
    to install it), never skips (CI has what setup-env installs; a skipped test proves nothing)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        pytest.fail(f"the test dependency {module} is missing ({exc}): run ./setup-env test", pytrace=False)


def require_chromium() -> str:
    """Debian's chromium for the browser tests, or a failure saying how to install it."""
    if not (os.path.exists(CHROMIUM) and os.access(CHROMIUM, os.X_OK)):
        pytest.fail(f"the test dependency chromium is missing ({CHROMIUM}): run ./setup-env test "
                    "(it installs Debian's chromium)", pytrace=False)
    return CHROMIUM


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


#: The small simulated dish station (400 x 300 camera) as a str.format template of {data_dir}, {facet} and
#: {radiometric}; the benchmarks fill in the same shared template (fixtures/stations/small_dish.toml.in).
SMALL_STATION = (ROOT / "fixtures/stations/small_dish.toml.in").read_text().format(
    name="Small simulated dish station (tests)", data_dir_line='data_dir = "{data_dir}"\n', facet="{facet}",
    analysis="", radiometric="{radiometric}", twist="0.1")


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
