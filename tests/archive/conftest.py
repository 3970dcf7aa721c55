"""Shared pieces of the archive tests: a real result record, records at chosen times, child processes."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT, SMALL_STATION

HERE = Path(__file__).resolve().parent

#: A real record of the small simulated station (``sofast-station inspect --json``), with truth.
SAMPLE_RECORD = json.loads((HERE / "sample_record.json").read_text())


def make_record(serial: str = "SIM-0001", time: str = "2026-03-02T10:15:00.000+01:00", **changes) -> dict:
    """A copy of the sample record with another serial and time (and any other top-level changes)."""
    rec = copy.deepcopy(SAMPLE_RECORD)
    rec.update(serial=serial, time=time, **changes)
    return rec


def run_child(script: str, *args, fault: str | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run *script* in a fresh interpreter (the project on its path), with SOFAST_FAULT set to *fault*."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("SOFAST_FAULT", None)
    if fault:
        env["SOFAST_FAULT"] = fault
    return subprocess.run([sys.executable, "-c", script, *map(str, args)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture
def small_config(tmp_path):
    """The small simulated station's configuration (loaded; nothing traced)."""
    from sofast_station.config import load_config

    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    return load_config(path)


def synthetic_content(config, cycle_id: str = "cycle-1", record: dict | None = None, seed: int = 0):
    """Dump content with random frames (18 x 120 x 160 cropped from 300 x 400) and the real configuration."""
    from sofast_station.archive.dumps import DumpContent
    from sofast_station.calibrate.records import load_radiometric

    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, size=(18, 120, 160), dtype=np.uint8)
    return DumpContent.build(config, load_radiometric(config.radiometric_path), cycle_id=cycle_id,
                             record=record or make_record(), frames_cropped=frames, crop_box=(90, 120),
                             full_shape=(300, 400), measured_distance_m=10.661360242493231)
