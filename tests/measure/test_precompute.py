"""Per-camera rays kept between analyses: the same bits as computing them afresh, computed once."""

import numpy as np

from sofast_station.geometry import CameraIntrinsics
from sofast_station.measure.camera import RayTable, pixel_rays, ray_grid
from sofast_station.precompute import MAX_CAMERAS, ray_table, warm_up


def camera(f=900.0):
    return CameraIntrinsics(160, 120, [[f, 0, 80.3], [0, f * 1.001, 59.6], [0, 0, 1]], [-0.2, 0.15, 1e-3, -5e-4, 0.02])


def test_ray_table_gives_the_rays_of_pixel_rays_and_of_the_grid_bit_for_bit():
    cam = camera()
    rng = np.random.default_rng(3)
    first = np.sort(rng.choice(cam.width_px * cam.height_px, 5000, replace=False))
    second = np.sort(rng.choice(cam.width_px * cam.height_px, 5000, replace=False))
    table = RayTable(cam)
    a = table.take(first)
    assert int(table._known.sum()) == first.size
    b = table.take(second)                       # only the pixels not asked for before are computed
    assert int(table._known.sum()) == np.union1d(first, second).size
    for idx, got in ((first, a), (second, b), (first, table.take(first))):
        rows, cols = np.divmod(idx, cam.width_px)
        assert np.array_equal(got, pixel_rays(cam, cols, rows))
    grid = ray_grid(cam)
    assert np.array_equal(RayTable.from_grid(cam, grid).take(second), b)
    assert np.array_equal(grid.reshape(3, -1)[:, second], b)


def test_one_table_per_camera_filled_by_the_warm_up():
    cam = camera(901.0)
    assert ray_table(cam) is ray_table(camera(901.0))        # equal calibrations share a table
    assert ray_table(camera(902.0)) is not ray_table(cam)
    warm_up(cam)
    assert ray_table(cam)._known.all()
    for k in range(MAX_CAMERAS + 1):                          # least recently used tables are dropped
        ray_table(camera(950.0 + k))
    assert not ray_table(cam)._known.any()


FREED_MEMORY_SCRIPT = """
import resource, sys
from concurrent.futures import ThreadPoolExecutor
import numpy as np
from sofast_station.precompute import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "keep" else None
faults = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def analysis():                   # arrays of a few MB made and dropped, some kept to the end
    kept = []
    for k in range(6):
        a = np.ones(300_000 + 10_000 * k)
        kept.append(a * 2.0)
        del a
    return sum(float(x[0]) for x in kept)
pool = ThreadPoolExecutor(1)
for _ in range(3):
    pool.submit(analysis).result(); analysis()
f0 = faults()
for _ in range(5):                 # two analyses side by side, as the pipeline's two threads
    f = pool.submit(analysis); analysis(); f.result()
print(applied, (faults() - f0) / 5)
"""


def test_the_warmed_up_process_keeps_freed_memory_for_the_next_analysis(repo_root):
    """After keep_freed_memory (the worker's warm-up calls it) the arrays of an analysis reuse the memory
    the previous one freed: no new page faults per analysis, where glibc's default maps and unmaps them."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=str(repo_root))
    runs = {}
    for mode in ("keep", "default"):
        out = subprocess.run([sys.executable, "-c", FREED_MEMORY_SCRIPT, mode], capture_output=True, text=True,
                             env=env, timeout=120, check=True).stdout.split()
        runs[mode] = (out[0], float(out[1]))
    if runs["keep"][0] != "True":
        import pytest
        pytest.skip("not glibc's allocator")
    pages_per_round = 12 * 2.5e6 / 4096                # 12 arrays of about 2.5 MB
    assert runs["keep"][1] < 0.1 * pages_per_round
    if runs["default"][1] > 0.5 * pages_per_round:    # (where the default maps afresh: here, 15,000 faults)
        assert runs["keep"][1] < 0.1 * runs["default"][1]
