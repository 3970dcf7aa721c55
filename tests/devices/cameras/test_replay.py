"""ReplayCamera: frames in order, delay, exhaustion, loop, recorded settings."""

import time

import numpy as np
import pytest

from sofast_station.devices.cameras import CameraSettingError, ReplayCamera
from sofast_station.errors import CameraError, CameraTimeoutError, ConfigError


def stack(n=3, rows=4, cols=5):
    return np.arange(n * rows * cols, dtype=np.uint8).reshape(n, rows, cols)


def test_serves_frames_in_order_then_times_out():
    frames = stack()
    cam = ReplayCamera(frames)
    assert cam.shape == (4, 5)
    for i in range(3):
        got = cam.grab()
        assert got.dtype == np.uint8
        np.testing.assert_array_equal(got, frames[i])
    with pytest.raises(CameraTimeoutError, match="all 3 recorded frames"):
        cam.grab()
    cam.rewind()
    np.testing.assert_array_equal(cam.grab(), frames[0])


def test_loop_starts_again():
    frames = stack(2)
    cam = ReplayCamera(frames, loop=True)
    got = [cam.grab()[0, 0] for _ in range(5)]
    assert got == [frames[i % 2][0, 0] for i in range(5)]


def test_frames_are_copies_both_ways():
    frames = stack()
    cam = ReplayCamera(frames)
    frames[0] = 99                       # changing the caller's array does not change the recording
    first = cam.grab()
    assert first[0, 0] == 0
    first[:] = 7                         # nor does changing a grabbed frame
    cam.rewind()
    assert cam.grab()[0, 0] == 0


def test_delay_models_latency_and_timeout():
    cam = ReplayCamera(stack(), frame_delay_s=0.05)
    t0 = time.perf_counter()
    cam.grab()
    assert time.perf_counter() - t0 >= 0.05
    t0 = time.perf_counter()
    with pytest.raises(CameraTimeoutError, match="longer than the grab timeout"):
        cam.grab(timeout_s=0.01)
    assert time.perf_counter() - t0 < 0.05
    assert cam.index == 1                # the late frame was not used up


def test_exposure_and_gain_are_recorded_only():
    frames = stack()
    cam = ReplayCamera(frames)
    cam.set_exposure(0.02)
    cam.set_gain(3.5)
    assert (cam.exposure_s, cam.gain) == (0.02, 3.5)
    np.testing.assert_array_equal(cam.grab(), frames[0])
    with pytest.raises(CameraSettingError):
        cam.set_exposure(-1)
    with pytest.raises(CameraSettingError):
        cam.set_gain(float("nan"))


def test_from_frames_accepts_a_list_and_rejects_mixed_sizes():
    frames = [np.full((3, 4), i, np.uint8) for i in range(3)]
    cam = ReplayCamera.from_frames(frames, loop=True)
    assert cam.n_frames == 3 and cam.shape == (3, 4)
    with pytest.raises(ConfigError, match="differ in size"):
        ReplayCamera.from_frames([np.zeros((3, 4), np.uint8), np.zeros((4, 4), np.uint8)])
    with pytest.raises(ConfigError, match="no frames"):
        ReplayCamera.from_frames([])


@pytest.mark.parametrize("bad, match", [
    (np.zeros((4, 5), np.uint8), "n, rows, columns"),
    (np.zeros((0, 4, 5), np.uint8), "n >= 1"),
    (np.zeros((2, 4, 5), np.uint16), "uint8"),
])
def test_rejects_bad_frames(bad, match):
    with pytest.raises(ConfigError, match=match):
        ReplayCamera(bad)


def test_grab_after_close_is_a_camera_error():
    cam = ReplayCamera(stack())
    cam.close()
    cam.close()
    with pytest.raises(CameraError, match="after close"):
        cam.grab()
