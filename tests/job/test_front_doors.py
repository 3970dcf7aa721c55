"""Issue 46 item 1: one job per kind of measurement, and the same record through every front door.

The same frames (one capture of the simulated station's twin, replayed) go through ``inspect``, through the
production line (its runner, its analysis worker process, its journal and dump) and through ``reprocess`` of
the line's dump: the three records must be the same, bit for bit, every figure, U, verdict, reason and the
twin's truth; only what describes the cycle (its id, time, request, timings, the re-analysis's notes) differs.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from sofast_station.files import to_json
from sofast_station.config import load_config
from sofast_station.devices.cameras.replay import ReplayCamera
from sofast_station.devices.protocols import FacetRequest
from sofast_station.reanalysis.reprocess import reprocess_dump
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import capture, inspect
from sofast_station.station.service import Service
from tests.conftest import ROOT, SMALL_STATION

#: What a record says of its cycle rather than of the facet.
CYCLE_KEYS = ("cycle_id", "time", "recipe", "request", "timings_s", "reprocess", "crop_box", "serial_raw",
              "calibration", "station_checks")


def measured(record: dict) -> dict:
    """The record without its cycle's own keys, as a JSON archive holds it."""
    out = json.loads(to_json(record))
    for k in CYCLE_KEYS:
        out.pop(k, None)
    return out


def _station_toml(tmp_path):
    """The small simulated station; its line dumps every facet, measures with no warm-up (so the worker's pool
    of frame brightness starts empty, as inspect's does) and one worker, and waits as long as it takes."""
    path = tmp_path / "station.toml"
    text = SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                radiometric=ROOT / "calibration/simulated_radiometric.json")
    path.write_text(text + "\n[run]\ndeadline_s = 600.0\nwarmup = false\ndump_every_n = 1\nstandby_worker = false\n")
    return path


@pytest.fixture(scope="module")
def doors(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("doors")
    cfg = load_config(_station_toml(tmp))
    # one capture of the twin, replayed to every door
    station = open_station(cfg, seed=11)
    try:
        frames, _ = capture(station)
        station.camera = ReplayCamera(frames, loop=True)
        by_inspect = inspect(station, "DOOR-1")
    finally:
        station.close()
    # the line: one facet, dumped
    service = Service(dataclasses.replace(cfg, data_dir=tmp / "line-data"), simulated_facets=[FacetRequest("DOOR-1")],
                      seed=11)
    try:
        service.station.camera = ReplayCamera(frames, loop=True)
        outcomes = service.runner.run()
    finally:
        service.close()
    by_line = outcomes[0].record
    dumps = sorted((tmp / "line-data" / "dumps").rglob("*.h5"))
    assert len(dumps) == 1, dumps
    by_reprocess = reprocess_dump(dumps[0]).record
    return by_inspect, by_line, by_reprocess


def test_the_same_frames_make_the_same_record_through_inspect_the_line_and_reprocess(doors):
    by_inspect, by_line, by_reprocess = doors
    a, b, c = (measured(r) for r in doors)
    assert a["verdict"] in ("pass", "fail") and "focal_length_x_m_U" in a and "truth" in a
    for name, other in (("the line", b), ("reprocess", c)):
        differ = sorted(k for k in set(a) | set(other) if a.get(k) != other.get(k))
        assert not differ, f"inspect and {name} differ in {differ}: " + "; ".join(
            f"{k}: {a.get(k)!r} / {other.get(k)!r}" for k in differ[:3])
    assert by_reprocess["reprocess"]["exact"] is True


def test_the_job_goes_to_the_worker_with_its_kind(small_station_toml):
    """The worker is sent the job itself (pickled), which says its kind; a heliostat's job is a heliostat's."""
    import pickle

    from sofast_station.job import FacetJob, HeliostatJob, job_for
    from sofast_station.recipes import default_recipe

    cfg = load_config(small_station_toml)
    job = job_for(default_recipe(cfg), cfg)
    assert isinstance(job, FacetJob) and job.kind == "facet" and job.name == cfg.design.name
    back = pickle.loads(pickle.dumps(job))
    assert back.kind == "facet" and back.design.to_dict() == job.design.to_dict() and back.analysis == job.analysis
    heli = load_config(ROOT / "fixtures/stations/heliostat-ensemble.toml")
    hjob = job_for(default_recipe(heli), heli)
    assert isinstance(hjob, HeliostatJob) and hjob.kind == "heliostat" and hjob.dumped()["ensemble"]["name"]
    frames = np.zeros((heli.fringes.n_frames, *heli.geometry.camera.shape), np.uint8)
    assert hjob.crop_box(frames[0], frames[1]) == (0, 0, *heli.geometry.camera.shape)

