"""Element-wise chains in blocks (measure/blocks.py) give the whole arrays' bits, on one thread or two."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from sofast_station.measure.blocks import blockwise
from sofast_station.measure.camera import to_frame
from sofast_station.geometry import Pose
from sofast_station.measure.surface import intersect_quadratic, normal_slopes


def reflect(rays, screen, pose, coeffs):
    rays, screen = to_frame(pose, rays, translate=False), to_frame(pose, screen)
    points = intersect_quadratic(coeffs, pose.translation, rays)
    s_x, s_y = normal_slopes(points, pose.translation, screen)
    return points, np.stack([s_x, s_y]), np.arctan(s_x)


@pytest.mark.parametrize("n, block", [(1, 4), (7, 4), (8, 4), (1000, 64), (5003, 128), (40_000, 16384)])
def test_blockwise_is_the_whole_computation_bit_for_bit(n, block):
    rng = np.random.default_rng(n)
    rays = rng.normal(0.0, 0.1, (3, n))
    rays[2] = 1.0
    rays /= np.linalg.norm(rays, axis=0)
    screen = rng.normal(0.0, 1.0, (3, n)) + np.array([[0.0], [0.0], [10.0]])
    angle = 0.01
    pose = Pose(np.array([[np.cos(angle), 0.0, np.sin(angle)], [0.0, 1.0, 0.0], [-np.sin(angle), 0.0, np.cos(angle)]]),
                np.array([0.01, -0.02, 10.0]))
    coeffs = np.array([0.046, 0.047, 1e-3, -2e-3, 1e-4, 0.0])
    whole = reflect(rays, screen, pose, coeffs)
    with ThreadPoolExecutor(max_workers=2) as pool:
        for p in (None, pool):
            got = blockwise(reflect, rays, screen, pool=p, block=block, pose=pose, coeffs=coeffs)
            assert len(got) == len(whole)
            for g, w in zip(got, whole):
                assert g.shape == w.shape and g.dtype == w.dtype
                assert np.array_equal(g, w, equal_nan=True)


def test_a_single_array_result_comes_back_as_a_tuple():
    x = np.arange(10.0)
    (y,) = blockwise(np.sqrt, x, block=3)
    assert np.array_equal(y, np.sqrt(x))
    with pytest.raises(ValueError, match="block"):
        blockwise(np.sqrt, x, block=0)
