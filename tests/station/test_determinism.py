"""docs/conventions.md#determinism: the analysis gives the same bits whatever the number of BLAS/OpenMP
threads and of its own worker threads (``[analysis] threads``)."""

import json
import os
import subprocess
import sys

import numpy as np

from sofast_station.config import load_config
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import capture

SCRIPT = """
import dataclasses, hashlib, json, sys
import numpy as np
from sofast_station.config import load_config
from sofast_station.measure.analysis import analyse
cfg = load_config(sys.argv[1])
d = np.load(sys.argv[2])
settings = dataclasses.replace(cfg.analysis, threads=int(sys.argv[3]))
a = analyse(d["frames"], cfg.fringes, cfg.geometry, cfg.design, float(d["distance"]), settings)
fig = {k: v for k, v in a.figures.items() if k != "timings_s"}
print(json.dumps(fig, sort_keys=True))
print(hashlib.sha256(a.slopes.tobytes()).hexdigest(), hashlib.sha256(a.points_facet_m.tobytes()).hexdigest())
"""


def test_same_bits_on_one_and_two_threads(small_station_toml, tmp_path):
    """BLAS on one thread with the analysis serial, both on two, and BLAS on one with the analysis on two."""
    station = open_station(load_config(small_station_toml), seed=5)
    try:
        frames, distance = capture(station)
    finally:
        station.close()
    npz = tmp_path / "capture.npz"
    np.savez(npz, frames=frames, distance=distance)
    outputs = []
    for blas, analysis in (("1", "1"), ("2", "2"), ("1", "2")):
        env = dict(os.environ, OPENBLAS_NUM_THREADS=blas, OMP_NUM_THREADS=blas, MKL_NUM_THREADS=blas)
        proc = subprocess.run([sys.executable, "-c", SCRIPT, str(small_station_toml), str(npz), analysis], env=env,
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr
        outputs.append(proc.stdout)
    assert outputs[0] == outputs[1] == outputs[2]
    assert json.loads(outputs[0].splitlines()[0])["n_points"] > 10_000
