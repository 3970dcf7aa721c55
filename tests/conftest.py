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
