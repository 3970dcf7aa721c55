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
