"""BaslerCamera against pylon's camera emulation (PYLON_CAMEMU), replaying digital-twin frames from files.

The emulated camera serves the image files of a folder in name order (``ImageFilename`` = the folder,
``ImageFileMode`` = On) when they have its Width x Height, and starts again after the last one.
"""

import time

import cv2
import numpy as np
import pytest

from sofast_station.devices.cameras import (CameraFrameSizeError, CameraIncompleteFrameError, CameraNotFoundError,
                                            CameraSettingError, open_camera)
from sofast_station.devices.cameras.basler import BaslerCamera
from sofast_station.errors import CameraDisconnectedError, CameraError, CameraTimeoutError

from .conftest import EMULATOR_CLASS, EMULATOR_SERIAL

N_FRAMES = 6

# pypylon's SWIG wrappers warn once on import under Python 3.11+.
pytestmark = pytest.mark.filterwarnings("ignore:builtin type .* has no __module__ attribute:DeprecationWarning")


@pytest.fixture(scope="module")
def twin_frames(tmp_path_factory):
    """The first frames of a small simulated station's capture (dark, white, fringes), as PNG files."""
    from sofast_station.config import load_config
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture
    from tests.conftest import ROOT, SMALL_STATION

    folder = tmp_path_factory.mktemp("twin")
    toml = folder / "station.toml"
    toml.write_text(SMALL_STATION.format(data_dir=folder / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    station = open_station(load_config(toml), seed=5)
    try:
        frames, _ = capture(station)
    finally:
        station.close()
    frames = frames[:N_FRAMES]
    images = folder / "frames"
    images.mkdir()
    for i, frame in enumerate(frames):
        assert cv2.imwrite(str(images / f"frame_{i:03d}.png"), frame)
    assert frames.dtype == np.uint8 and frames.shape[1:] == (300, 400)
    assert len({f.tobytes() for f in frames}) == N_FRAMES          # all different: order is testable
    return frames, images


def replaying(folder, rows, cols, **extra):
    """BaslerCamera options that make the emulated camera replay ``folder``."""
    features = {"Width": cols, "Height": rows, "TestImageSelector": "Off",
                "ImageFilename": str(folder), "ImageFileMode": "On"}
    return dict(serial=EMULATOR_SERIAL, expected_shape=(rows, cols), device_class=EMULATOR_CLASS,
                features=features, **extra)


def test_replays_image_files_in_order(pylon_emulation, twin_frames):
    frames, folder = twin_frames
    cam = BaslerCamera(**replaying(folder, 300, 400))
    try:
        assert cam.shape == (300, 400) and cam.serial == EMULATOR_SERIAL
        for i in range(N_FRAMES + 2):                 # and round again after the last file
            got = cam.grab(timeout_s=2.0)
            assert got.dtype == np.uint8 and got.flags.c_contiguous
            np.testing.assert_array_equal(got, frames[i % N_FRAMES], err_msg=f"grab {i}")
        assert cam.frames_grabbed == N_FRAMES + 2
    finally:
        cam.close()


def test_factory_and_context_manager(pylon_emulation, twin_frames):
    frames, folder = twin_frames
    with open_camera("basler", **replaying(folder, 300, 400)) as cam:
        np.testing.assert_array_equal(cam.grab(), frames[0])
    assert "closed" in repr(cam)


def test_exposure_in_seconds_and_gain(pylon_emulation):
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS, exposure_s=0.004) as cam:
        assert cam.exposure_s == pytest.approx(0.004)
        cam.set_exposure(0.0125)
        assert cam.exposure_s == pytest.approx(0.0125)
        node = cam._camera.GetNodeMap().GetNode("ExposureTime")       # pylon works in microseconds
        assert node.Value == pytest.approx(12500.0)
        low, high = cam.gain_range
        cam.set_gain(6.0)
        assert cam.gain == pytest.approx(6.0, abs=0.05)               # the emulator quantises gain
        with pytest.raises(CameraSettingError, match=r"outside the camera's range"):
            cam.set_gain(high + 10)
        with pytest.raises(CameraSettingError, match=r"exposure 100 s is outside the camera's range"):
            cam.set_exposure(100.0)
        with pytest.raises(CameraSettingError, match="positive"):
            cam.set_exposure(0)
        assert cam.grab().shape == (1040, 1024)                       # still grabbing after refusals


def test_free_run(pylon_emulation):
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), trigger="freerun", device_class=EMULATOR_CLASS) as cam:
        first, second = cam.grab(), cam.grab()
        assert first.shape == second.shape == (1040, 1024)
        assert not np.array_equal(first, second)                      # the test pattern moves per frame


def test_timeout_when_the_trigger_never_comes(pylon_emulation):
    # Hardware trigger on Line1, where nothing is connected: the camera waits for ever.
    cam = BaslerCamera(EMULATOR_SERIAL, (1040, 1024), trigger="Line1", device_class=EMULATOR_CLASS)
    try:
        t0 = time.perf_counter()
        with pytest.raises(CameraTimeoutError, match="no frame from trigger line Line1 within 0.3 s"):
            cam.grab(timeout_s=0.3)
        assert 0.25 < time.perf_counter() - t0 < 2.0
    finally:
        cam.close()
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS) as again:
        assert again.grab().shape == (1040, 1024)


def test_removal_mid_sequence_then_reopen(pylon_emulation, twin_frames):
    frames, folder = twin_frames
    cam = BaslerCamera(**replaying(folder, 300, 400))
    try:
        np.testing.assert_array_equal(cam.grab(), frames[0])
        np.testing.assert_array_equal(cam.grab(), frames[1])
        # The emulator's "FirePnPCallback" fires pylon's device-removal callback, as an unplugged camera.
        cam._camera.GetNodeMap().GetNode("FirePnPCallback").Execute()
        with pytest.raises(CameraDisconnectedError, match="was removed"):
            cam.grab()
        with pytest.raises(CameraDisconnectedError):
            cam.set_exposure(0.01)
    finally:
        cam.close()
    cam.close()                                                     # idempotent
    with BaslerCamera(**replaying(folder, 300, 400)) as again:
        np.testing.assert_array_equal(again.grab(), frames[0])


def test_device_destroyed_underneath(pylon_emulation):
    cam = BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS)
    try:
        cam.grab()
        cam._camera.DestroyDevice()                                 # the pylon device vanishes
        with pytest.raises(CameraDisconnectedError, match="closed underneath"):
            cam.grab()
    finally:
        cam.close()
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS) as again:
        assert again.grab().shape == (1040, 1024)


def test_wrong_frame_size_when_opening(pylon_emulation, twin_frames):
    _, folder = twin_frames
    options = replaying(folder, 300, 400)
    options["expected_shape"] = (1200, 1600)
    with pytest.raises(CameraFrameSizeError, match=r"300 x 400 pixels .* expects 1200 x 1600"):
        BaslerCamera(**options)
    with BaslerCamera(**replaying(folder, 300, 400)) as again:     # the failed open released the camera
        assert again.grab().shape == (300, 400)


def test_wrong_frame_size_while_grabbing(pylon_emulation):
    cam = BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS)
    try:
        assert cam.grab().shape == (1040, 1024)
        # Someone changes the region of interest behind the station's back.
        pylon = pylon_emulation
        cam._camera.StopGrabbing()
        cam._camera.Width.Value = 512
        cam._camera.StartGrabbing(pylon.GrabStrategy_OneByOne)
        with pytest.raises(CameraFrameSizeError, match=r"frame of 1040 x 512 pixels .* expects 1040 x 1024"):
            cam.grab()
    finally:
        cam.close()


def test_damaged_frame_then_recovers(pylon_emulation):
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS) as cam:
        nodes = cam._camera.GetNodeMap()
        nodes.GetNode("ForceFailedBufferCount").Value = 1
        nodes.GetNode("ForceFailedBuffer").Execute()
        with pytest.raises(CameraIncompleteFrameError, match="damaged frame"):
            cam.grab()
        assert cam.grab().shape == (1040, 1024)


def test_mono12_is_scaled_to_8_bits(pylon_emulation):
    # The emulator's Mono12 test image is its Mono8 ramp (+1 per column) shifted left by 4 bits.
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), "Mono12", device_class=EMULATOR_CLASS) as cam:
        assert cam._camera.PixelFormat.Value == "Mono12"
        frame = cam.grab()
    assert frame.dtype == np.uint8 and frame.shape == (1040, 1024)
    steps = np.diff(frame[0].astype(int)) % 256
    assert np.all(steps == 1), steps[:10]


def test_unknown_serial(pylon_emulation):
    with pytest.raises(CameraNotFoundError, match=f"serial 12345.*{EMULATOR_SERIAL}"):
        BaslerCamera("12345", (1040, 1024), device_class=EMULATOR_CLASS)


def test_unknown_feature_and_pixel_format(pylon_emulation):
    with pytest.raises(CameraSettingError, match="no feature 'NoSuchFeature'"):
        BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS, features={"NoSuchFeature": 1})
    with pytest.raises(CameraSettingError, match="pixel format 'RGB8'"):
        BaslerCamera(EMULATOR_SERIAL, (1040, 1024), "RGB8", device_class=EMULATOR_CLASS)
    with BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS) as again:
        assert again.grab().shape == (1040, 1024)


def test_grab_after_close(pylon_emulation):
    cam = BaslerCamera(EMULATOR_SERIAL, (1040, 1024), device_class=EMULATOR_CLASS)
    cam.close()
    with pytest.raises(CameraError, match="closed"):
        cam.grab()
