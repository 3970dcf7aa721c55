"""The suite's guard over the user's data folder (issue 43): a station file loaded outside a test's own
SOFAST_DATA_DIR fails the test that loaded it, instead of reading the records ~/sofast-station-data holds."""

from __future__ import annotations

import pytest

from sofast_station.config import load_config
from tests.conftest import USER_DATA, load_station


def test_a_station_loaded_with_the_default_data_dir_fails_the_test(repo_root, monkeypatch):
    monkeypatch.delenv("SOFAST_DATA_DIR")          # as in a module fixture, before the per-test one is set
    with pytest.raises(pytest.fail.Exception, match="user's data folder"):
        load_config(repo_root / "station.toml")


def test_a_module_fixture_loads_a_station_with_its_own_data(repo_root, monkeypatch, tmp_path):
    monkeypatch.delenv("SOFAST_DATA_DIR")
    cfg = load_station(repo_root / "station.toml", tmp_path / "data")
    assert cfg.data_dir == tmp_path / "data"
    assert USER_DATA not in cfg.data_dir.parents
