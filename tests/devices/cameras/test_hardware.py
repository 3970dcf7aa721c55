"""Opt-in checks against a real camera (skipped unless --camera-serial is given).

    pytest tests/devices/cameras -m hardware --camera-serial 40012345 --camera-shape 1200x1600
    pytest tests/devices/cameras -m hardware --camera-kind aravis --camera-serial 192.168.3.10 \\
        --camera-shape 1200x1600

A Basler camera is searched on every pylon transport layer and an Aravis camera given by device id is
found by a discovery broadcast: run these on the station's camera network only.
"""

import time

import numpy as np
import pytest

from sofast_station.devices.cameras import open_camera
from sofast_station.errors import CameraTimeoutError

pytestmark = pytest.mark.hardware


def _open(options, **extra):
    kind, ident, shape = options
    key = "serial" if kind == "basler" else "device_id"
    return open_camera(kind, **{key: ident}, expected_shape=shape, **extra)


def test_real_camera_grabs_frames_of_its_size(real_camera_options):
    with _open(real_camera_options) as cam:
        cam.set_exposure(0.01)
        cam.set_gain(cam.gain_range[0])
        assert cam.exposure_s == pytest.approx(0.01, rel=0.05)
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            frame = cam.grab(timeout_s=2.0)
            times.append(time.perf_counter() - t0)
            assert frame.dtype == np.uint8 and frame.shape == real_camera_options[2]
        assert max(times) < 1.0, times


def test_real_camera_exposure_changes_the_signal(real_camera_options):
    with _open(real_camera_options) as cam:
        cam.set_gain(cam.gain_range[0])
        cam.set_exposure(0.002)
        short = float(cam.grab().mean())
        cam.set_exposure(0.02)
        long = float(cam.grab().mean())
    assert long >= short                   # the scene must not change between the two grabs


def test_real_camera_hardware_trigger_times_out(real_camera_options):
    kind = real_camera_options[0]
    line = "Line1" if kind == "basler" else "Line0"
    with _open(real_camera_options, trigger=line) as cam:
        with pytest.raises(CameraTimeoutError):
            cam.grab(timeout_s=0.5)
