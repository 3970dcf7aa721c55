"""The station's cache on disk (sofast_station/cache.py): the uncertainty's sensitivities and the camera's pixel
rays kept across processes, so a fresh ``reprocess`` does not compute them again.

What must hold: a value read from the cache is the value computing it gives (a cold and a warm run print the
same bits of every figure and U); anything that changes what a value is computed from misses (another
capture, another measured distance, another sensitivity key, another camera); several processes writing at
once never leave a half-written value; a cache that cannot be used is skipped, not fatal. The dumps are the
small simulated station's (400 x 300 px; tests/reanalysis/conftest.py).
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from sofast_station.archive import read_dump
from sofast_station.archive.dumps import write_dump
from sofast_station.cache import DiskCache, SensitivityStore, capture_basis, load_rays, open_cache, save_rays
from sofast_station.geometry import CameraIntrinsics
from sofast_station.measure.camera import RayTable
from sofast_station.reanalysis.reprocess import Overrides, flatten_figures, reprocess_content

COMPUTED = "analysis_uncertainty_sensitivities"      # in a record's timings when the sensitivities were computed


def bare(path):
    """A dump's content without the station's sensitivities (as an older dump): reprocess must find or compute
    them."""
    content = read_dump(path)
    content.sensitivities = None
    return content


def figures(res) -> dict:
    return {**flatten_figures(res.record), **flatten_figures(res.record, uncertainties=True)}


def test_reprocess_with_a_cold_and_a_warm_cache_gives_the_same_figures(station_dumps, tmp_path):
    without = reprocess_content(bare(station_dumps.good[0]))
    cold = reprocess_content(bare(station_dumps.good[0]), disk_cache=DiskCache(tmp_path / "cache"))
    # another DiskCache on the folder: what another process sees
    warm = reprocess_content(bare(station_dumps.good[0]), disk_cache=DiskCache(tmp_path / "cache"))
    assert without.record["timings_s"][COMPUTED] > 0 and cold.record["timings_s"][COMPUTED] > 0
    assert COMPUTED not in warm.record["timings_s"], "the warm run computed the sensitivities again"
    assert figures(warm) == figures(cold) == figures(without)
    assert any(k.endswith("_U") or "_U" in k for k in figures(warm)), "no uncertainty among the figures compared"


def test_a_changed_capture_or_distance_misses_the_cache(station_dumps, tmp_path):
    """The key names the capture the sensitivities are finite differences of: another dump of the same
    station and recipe, or the same dump at another measured distance, computes its own."""
    cache = DiskCache(tmp_path / "cache")
    reprocess_content(bare(station_dumps.good[0]), disk_cache=cache)
    other = reprocess_content(bare(station_dumps.good[1]), disk_cache=cache)
    assert other.record["timings_s"][COMPUTED] > 0
    content = bare(station_dumps.good[0])
    moved = reprocess_content(content, Overrides(measured_distance_m=content.measured_distance_m + 0.01),
                              disk_cache=cache)
    assert moved.record["timings_s"][COMPUTED] > 0
    again = reprocess_content(bare(station_dumps.good[1]), disk_cache=cache)
    assert COMPUTED not in again.record["timings_s"]
    assert figures(again) == figures(other)


def test_a_changed_sensitivity_key_misses(station_dumps, tmp_path):
    """The sensitivity key hashes the geometry, recipe and input uncertainties
    (measure.uncertainty.sensitivity_key): a value stored under one key is never read under another."""
    content = read_dump(station_dumps.good[0])
    from sofast_station.measure.sensitivity_record import from_record

    key, sens = from_record(content.sensitivities)
    basis = capture_basis(content.frames_cropped, content.measured_distance_m)
    store = SensitivityStore(DiskCache(tmp_path / "cache"), basis)
    store[key] = sens
    fresh = SensitivityStore(DiskCache(tmp_path / "cache"), basis)
    assert fresh.get(key + "0") is None and fresh.hits == 0
    got = fresh.get(key)
    assert fresh.hits == 1
    np.testing.assert_array_equal(got.linear, sens.linear)
    np.testing.assert_array_equal(got.curvature, sens.curvature)
    other_basis = capture_basis(content.frames_cropped, content.measured_distance_m + 1e-9)
    assert SensitivityStore(DiskCache(tmp_path / "cache"), other_basis).get(key) is None


def test_a_value_stored_under_another_key_with_the_same_name_is_a_miss(tmp_path):
    """A hash collision (or a file edited by hand) cannot hand back another key's value: the key is stored
    with the value and compared on every read."""
    cache = DiskCache(tmp_path / "cache")
    assert cache.put("k", {"a": 1}, b"payload")
    assert cache.get("k", {"a": 1}) == b"payload"
    assert cache.get("k", {"a": 2}) is None
    name, _ = cache._name("k", {"a": 1})
    cache._store.set(name, json.dumps({"kind": "k", "layout": 1, "a": 2}).encode() + b"\0forged")
    assert cache.get("k", {"a": 1}) is None


WRITER = textwrap.dedent("""
    import sys
    from pathlib import Path
    from sofast_station.cache import DiskCache
    cache = DiskCache(Path(sys.argv[1]))
    me = int(sys.argv[2])
    bad = 0
    for i in range(40):
        cache.put("blob", {"n": i % 4}, bytes([me]) * 200_000)       # on a file of its own (> 32 kB)
        got = cache.get("blob", {"n": (i + 1) % 4})
        if got is not None and (len(got) != 200_000 or len(set(got)) != 1):
            bad += 1
    print(bad)
""")


def test_concurrent_writers_never_leave_a_half_written_value(tmp_path):
    """Three processes write and read the same four keys at once (large values, each written to a file of
    its own): every read is absent or one writer's whole value."""
    procs = [subprocess.Popen([sys.executable, "-c", WRITER, str(tmp_path / "cache"), str(k)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for k in (1, 2, 3)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-800:] for o in outs]
    assert [o[0].strip() for o in outs] == ["0", "0", "0"]
    cache = DiskCache(tmp_path / "cache")
    for n in range(4):
        got = cache.get("blob", {"n": n})
        assert got is not None and len(got) == 200_000 and len(set(got)) == 1 and got[0] in (1, 2, 3)


def test_a_cache_that_cannot_be_opened_is_skipped_with_a_warning(tmp_path, caplog):
    (tmp_path / "cache").write_text("a file where the cache folder should be")
    with caplog.at_level(logging.WARNING):
        assert open_cache(tmp_path) is None
    assert "cache" in caplog.text and "computed afresh" in caplog.text
    assert open_cache(None) is None


def test_pixel_rays_kept_on_disk_are_the_same_bits_and_another_camera_misses(tmp_path):
    camera = CameraIntrinsics(64, 48, [[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]], [-0.2, 0.05, 0.001, -0.002, 0])
    table = RayTable(camera)
    idx = np.arange(5, 64 * 48, 7)
    expected = table.take(idx)
    cache = DiskCache(tmp_path / "cache")
    assert save_rays(cache, table)
    again = RayTable(camera)
    assert load_rays(DiskCache(tmp_path / "cache"), again) == idx.size == again.n_known
    np.testing.assert_array_equal(again.take(idx), expected)
    assert again.n_known == idx.size, "pixels kept on disk were computed again"
    other = CameraIntrinsics(64, 48, [[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]], [-0.2, 0.05, 0.001, -0.002, 1e-6])
    assert load_rays(cache, RayTable(other)) == 0


@pytest.fixture
def bare_dump_file(station_dumps, tmp_path):
    path = tmp_path / "bare.h5"
    write_dump(path, bare(station_dumps.good[0]))
    return path


def test_a_fresh_reprocess_process_reads_what_the_previous_one_computed(bare_dump_file, tmp_path):
    """Across processes, through the command: the second ``reprocess`` of a dump without sensitivities
    reads them from data_dir/cache, and prints the same figures."""
    env_dir = tmp_path / "station-data"

    def run():
        import os

        proc = subprocess.run([sys.executable, "-m", "sofast_station", "reprocess", "--json", str(bare_dump_file)],
                              capture_output=True, text=True, timeout=300,
                              env={**os.environ, "SOFAST_DATA_DIR": str(env_dir)})
        assert proc.returncode == 0, proc.stderr[-1500:]
        return json.loads(proc.stdout)

    first, second = run(), run()
    assert first["timings_s"][COMPUTED] > 0
    assert COMPUTED not in second["timings_s"]
    assert (env_dir / "cache").is_dir()
    strip = ("timings_s", "reprocess")
    assert {k: v for k, v in first.items() if k not in strip} == {k: v for k, v in second.items() if k not in strip}
