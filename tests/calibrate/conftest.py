"""Fixtures for the calibration tests: small simulated stations and a record calibrated on one.

``[calibration]`` settings beyond ``radiometric`` are put into the loaded configuration's raw table (as
``load_config`` would once it accepts them), so the tests do not depend on how station.toml is parsed.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import pytest

from sofast_station.calibrate.radiometric import calibrate_radiometric, save_radiometric
from sofast_station.calibrate.settings import RadiometricSettings
from sofast_station.config import load_config
from tests.conftest import ROOT, SMALL_STATION


def small_config(folder: Path, calibration: dict | None = None, simulation: dict | None = None,
                 optics: dict | None = None, **replace):
    """The quarter-resolution simulated dish station, its data under ``folder/data``."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=folder / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    cfg = load_config(path)
    raw = dict(cfg.raw)
    raw["calibration"] = {**raw.get("calibration", {}), **(calibration or {})}
    sim = dict(cfg.simulation)
    if simulation:
        sim.update(simulation)
    if optics:
        sim["optics"] = {**sim.get("optics", {}), **optics}
    return dataclasses.replace(cfg, raw=raw, simulation=sim, data_dir=folder / "data", **replace)


@pytest.fixture(scope="session")
def small_record(tmp_path_factory):
    """A radiometric record made by the routine on the small noise-free station (copy it before use)."""
    from sofast_station.station.factory import open_station

    folder = tmp_path_factory.mktemp("small-calibrated")
    cfg = small_config(folder)
    station = open_station(cfg, noise=False, calibration_checks=False)
    try:
        result = calibrate_radiometric(station.display, station.camera, RadiometricSettings(ramp_step=15))
    finally:
        station.close()
    return save_radiometric(cfg.data_dir, result, "tests: small station", plot=False)


def install_record(record_path: Path, data_dir: Path) -> Path:
    """Copy a record file into a station's data folder (as the routine would have written it)."""
    target = data_dir / "calibration" / "radiometric" / record_path.name
    target.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(record_path, target)
    return target
