"""AravisCamera against Aravis's fake GigE Vision camera (arv-fake-gv-camera-0.8) on 127.0.0.1.

The fake camera (Aravis 0.8.26) cannot serve image files; it sends a 512 x 512 Mono8 diagonal ramp,
``pixel = clamp(((column + row + frame_id) % 255) * scale, 0, 255)`` with
``scale = 1 + gain + log10(exposure_us / 10000)``, so every frame's content, its order (frame_id counts
up by one per frame) and the effect of exposure and gain can be checked exactly.

It is always opened by its address: opening by device id would broadcast a GigE Vision discovery on
every network interface.
"""

import time

import numpy as np
import pytest

from sofast_station.devices.cameras import (CameraFrameSizeError, CameraNotFoundError, CameraSettingError,
                                            open_camera)
from sofast_station.devices.cameras.aravis import AravisCamera
from sofast_station.errors import CameraDisconnectedError, CameraError, CameraTimeoutError


def ramp(shape, frame_id, scale=1.0):
    rows, cols = np.indices(shape)
    return np.clip(((rows + cols + frame_id) % 255) * scale, 0, 255).astype(np.uint8)


def frame_number(frame):
    """frame_id % 255 of an unscaled ramp frame, checking that the whole frame is that ramp."""
    fid = int(frame[0, 0])
    np.testing.assert_array_equal(frame, ramp(frame.shape, fid))
    return fid


def test_grabs_consecutive_frames_of_the_expected_size(fake_gv_camera):
    with AravisCamera(fake_gv_camera.address, (512, 512), exposure_s=0.01, gain=0) as cam:
        assert cam.shape == (512, 512)
        assert cam.serial == fake_gv_camera.serial and cam.device_id == fake_gv_camera.device_id
        ids = []
        for _ in range(4):
            frame = cam.grab(timeout_s=2.0)
            assert frame.dtype == np.uint8 and frame.shape == (512, 512)
            ids.append(frame_number(frame))
        # one software trigger, one new frame: no frame repeated, none skipped
        assert [(b - a) % 255 for a, b in zip(ids, ids[1:])] == [1, 1, 1]
        assert cam.frames_grabbed == 4


def test_exposure_and_gain_change_the_frames(fake_gv_camera):
    with open_camera("aravis", device_id=fake_gv_camera.address, expected_shape=(512, 512)) as cam:
        cam.set_exposure(0.01)
        cam.set_gain(0)
        assert cam.exposure_s == pytest.approx(0.01) and cam.gain == 0
        fid = frame_number(cam.grab())
        cam.set_gain(1)                                   # scale 1 + 1 + log10(1) = 2
        assert cam.gain == 1
        np.testing.assert_array_equal(cam.grab(), ramp((512, 512), fid + 1, 2.0))
        cam.set_gain(0)
        cam.set_exposure(0.1)                             # 100 ms: scale 1 + 0 + log10(10) = 2
        assert cam.exposure_s == pytest.approx(0.1)
        np.testing.assert_array_equal(cam.grab(), ramp((512, 512), fid + 2, 2.0))
        low, high = cam.gain_range
        with pytest.raises(CameraSettingError, match="gain 11 .*outside the camera's range"):
            cam.set_gain(high + 1)
        with pytest.raises(CameraSettingError, match="exposure 100 s is outside"):
            cam.set_exposure(100)


def test_features_set_the_region(fake_gv_camera):
    with AravisCamera(fake_gv_camera.address, (128, 256), features={"Width": 256, "Height": 128}) as cam:
        frame = cam.grab()
        assert frame.shape == (128, 256)
        frame_number(frame)


def test_free_run(fake_gv_camera):
    with AravisCamera(fake_gv_camera.address, (512, 512), trigger="freerun") as cam:
        a, b = frame_number(cam.grab()), frame_number(cam.grab())
        assert a != b                                      # a newer frame each time


def test_timeout_while_the_camera_still_answers(fake_gv_camera):
    # Hardware trigger on Line0, where nothing is connected.
    with AravisCamera(fake_gv_camera.address, (512, 512), trigger="Line0") as cam:
        t0 = time.perf_counter()
        with pytest.raises(CameraTimeoutError, match="no frame from trigger line Line0 within 0.3 s"):
            cam.grab(timeout_s=0.3)
        assert 0.25 < time.perf_counter() - t0 < 1.5      # the liveness probe answers at once


def test_camera_killed_mid_sequence_then_reopened(fake_gv_camera):
    cam = AravisCamera(fake_gv_camera.address, (512, 512))
    try:
        frame_number(cam.grab())
        frame_number(cam.grab())
        fake_gv_camera.kill()                              # power cut: the camera just stops answering
        t0 = time.perf_counter()
        with pytest.raises(CameraDisconnectedError, match="does not answer"):
            cam.grab(timeout_s=1.0)
        assert time.perf_counter() - t0 < 8.0              # Aravis retries a command for about 2.5 s
        with pytest.raises(CameraDisconnectedError):
            cam.grab()
    finally:
        t0 = time.perf_counter()
        cam.close()
    assert time.perf_counter() - t0 < 1.0                 # the dead device is released in the background
    with pytest.raises(CameraNotFoundError):               # nobody there while the camera is off
        AravisCamera(fake_gv_camera.address, (512, 512))
    fake_gv_camera.start()                                 # power back
    with AravisCamera(fake_gv_camera.address, (512, 512)) as again:
        frame_number(again.grab())
        frame_number(again.grab())


def test_wrong_expected_size(fake_gv_camera):
    with pytest.raises(CameraFrameSizeError, match=r"512 x 512 pixels .* expects 480 x 640"):
        AravisCamera(fake_gv_camera.address, (480, 640))
    with AravisCamera(fake_gv_camera.address, (512, 512)) as again:     # the failed open released it
        frame_number(again.grab())


def test_unknown_feature_and_trigger_source(fake_gv_camera):
    with pytest.raises(CameraSettingError, match="no feature 'NoSuchFeature'"):
        AravisCamera(fake_gv_camera.address, (512, 512), features={"NoSuchFeature": 3})
    with pytest.raises(CameraSettingError, match="TriggerSource"):
        AravisCamera(fake_gv_camera.address, (512, 512), trigger="Line7")
    with AravisCamera(fake_gv_camera.address, (512, 512)) as again:
        frame_number(again.grab())


def test_grab_after_close(fake_gv_camera):
    cam = AravisCamera(fake_gv_camera.address, (512, 512))
    cam.close()
    cam.close()
    with pytest.raises(CameraError, match="closed"):
        cam.grab()
