"""GenICamCamera: one camera protocol over two transports, held to the same contract.

The first half runs the same checks against both transports, each against its library's own emulated camera
(pylon's camera emulation, Aravis's fake GigE Vision camera on 127.0.0.1): the truths are what those
emulators are (their exposure and gain ranges, their frame size, a trigger line with nothing wired to it),
written down here, not read through the code under test. The second half drives GenICamCamera through a
scripted transport, to check the rules the emulators cannot provoke on demand (a late frame from before
the software trigger, a damaged buffer, the library failing mid-grab).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from sofast_station.devices.cameras import (CameraFrameSizeError, CameraIncompleteFrameError, CameraSettingError,
                                            open_camera)
from sofast_station.devices.cameras.genicam import Delivery, GenICamCamera, GenICamTransport
from sofast_station.errors import CameraDisconnectedError, CameraError, CameraTimeoutError

from .conftest import EMULATOR_CLASS, EMULATOR_SERIAL

# pypylon's SWIG wrappers warn once on import under Python 3.11+.
pytestmark = pytest.mark.filterwarnings("ignore:builtin type .* has no __module__ attribute:DeprecationWarning")


@dataclass(frozen=True)
class Emulated:
    """An emulated camera and what it is."""

    kind: str
    identity: dict
    shape: tuple[int, int]
    exposure_range_s: tuple[float, float]
    gain_range: tuple[float, float]
    unwired_line: str

    def open(self, **options):
        options.setdefault("expected_shape", self.shape)
        return open_camera(self.kind, **self.identity, **options)


@pytest.fixture(params=["basler", "aravis"])
def emulated(request) -> Emulated:
    """Each transport's emulated camera. Its ranges are the emulator's own (pylon's camera emulation:
    ExposureTime 1 us to 10 s, Gain 0 to 48 dB; Aravis 0.8.26's fake camera: ExposureTimeAbs 10 us to 10 s,
    GainRaw 0 to 10), as their feature lists state."""
    if request.param == "basler":
        request.getfixturevalue("pylon_emulation")
        return Emulated("basler", {"serial": EMULATOR_SERIAL, "device_class": EMULATOR_CLASS}, (1040, 1024),
                        (1e-6, 10.0), (0.0, 48.0), "Line1")
    fake = request.getfixturevalue("fake_gv_camera")
    return Emulated("aravis", {"device_id": fake.address}, fake.shape, (1e-5, 10.0), (0.0, 10.0), "Line0")


def test_exposure_and_gain_land_on_what_was_asked(emulated):
    """Over 6 exposures drawn log-uniformly in [0.1 ms, 0.1 s] and 3 whole-number gains, the camera reports
    what was asked to within its step. Both emulators keep the exposure in whole microseconds (pylon's
    rounds, Aravis's fake truncates: 7337.56 us reads back 7337 us), so the tolerance is one step, 1 us.
    pylon's emulated Gain goes through a raw register (under 5e-5 dB off, measured at 1, 6 and 7.3 dB) and
    Aravis's GainRaw is an integer, so whole-number gains come back within 1e-3 gain units."""
    rng = np.random.default_rng(46)
    with emulated.open() as cam:
        assert cam.exposure_range_s == pytest.approx(emulated.exposure_range_s, rel=1e-6)
        assert cam.gain_range == pytest.approx(emulated.gain_range, rel=1e-6)
        for seconds in 10.0 ** rng.uniform(-4, -1, size=6):
            cam.set_exposure(seconds)
            assert abs(cam.exposure_s - seconds) <= 1e-6 + 1e-12, (seconds, cam.exposure_s)
        for gain in rng.choice(np.arange(1, 10), size=3, replace=False):
            cam.set_gain(float(gain))
            assert cam.gain == pytest.approx(gain, abs=1e-3)
        assert cam.grab().shape == emulated.shape


def test_refusals_name_the_range_and_leave_the_camera_grabbing(emulated):
    low_s, high_s = emulated.exposure_range_s
    low_gain, high_gain = emulated.gain_range
    with emulated.open() as cam:
        with pytest.raises(CameraSettingError, match=rf"exposure 20 s is outside the camera's range "
                                                     rf"\[{low_s:g}, {high_s:g}\] s: choose a value inside it"):
            cam.set_exposure(20.0)
        with pytest.raises(CameraSettingError, match=rf"gain {high_gain + 1:g} \(camera units\) is outside the "
                                                     rf"camera's range \[{low_gain:g}, {high_gain:g}"):
            cam.set_gain(high_gain + 1)
        with pytest.raises(CameraSettingError, match="gain must be a finite number"):
            cam.set_gain(float("nan"))
        assert cam.grab().shape == emulated.shape
        assert "open" in repr(cam)


def test_opening_refusals_say_the_same_on_both(emulated):
    with pytest.raises(CameraSettingError, match=r"has no feature 'NoSuchFeature': check the .* or the camera model"):
        emulated.open(features={"NoSuchFeature": 1})
    with pytest.raises(CameraSettingError, match="TriggerSoftware is a command: give it the value true"):
        emulated.open(features={"TriggerSoftware": 3})
    rows, cols = emulated.shape
    with pytest.raises(CameraFrameSizeError, match=rf"is set to frames of {rows} x {cols} pixels \(rows x columns\) "
                                                   r"but the station expects 10 x 20"):
        emulated.open(expected_shape=(10, 20))
    with emulated.open() as again:          # every refused open released the camera
        assert again.grab().shape == emulated.shape


def test_unwired_trigger_line_times_out_then_close_is_final(emulated):
    cam = emulated.open(trigger=emulated.unwired_line)
    try:
        with pytest.raises(CameraTimeoutError, match=f"no frame from trigger line {emulated.unwired_line} "
                                                     "within 0.2 s"):
            cam.grab(timeout_s=0.2)
        assert "open" in repr(cam)          # a timeout is not a disconnect
    finally:
        cam.close()
    cam.close()
    assert repr(cam).endswith("closed>") and type(cam).__name__ in repr(cam)
    for step in (cam.grab, lambda: cam.set_exposure(0.01), lambda: cam.exposure_range_s):
        with pytest.raises(CameraError, match="is closed; open a new camera"):
            step()


# -- the shared rules, through a scripted transport ---------------------------------------------------------


class LinkDown(Exception):
    """The scripted library's exception."""


class ScriptedTransport(GenICamTransport):
    """A transport whose camera answers from a script: ``deliveries`` are what ``next_frame`` returns in
    turn (a Delivery, None for no frame in time, or an exception to raise)."""

    def __init__(self, deliveries):
        super().__init__("S1")
        self.deliveries = list(deliveries)
        self.nodes = {"PixelFormat": "Mono8", "Width": 4, "Height": 3, "TriggerMode": "Off",
                      "TriggerSource": "Line0", "exposure": 1000.0, "gain": 0.0}
        self.releases = 0

    def load(self):
        self.error_types = (LinkDown,)

    def unopened_description(self):
        return "scripted camera"

    def open(self):
        self.handle, self.vendor, self.model, self.serial = object(), "Script", "S", "1"

    def feature_kind(self, name):
        return "value" if name in self.nodes else None

    def read(self, name):
        return self.nodes.get(name)

    def write(self, name, value, required):
        self.nodes[name] = value

    def execute(self, name):
        raise AssertionError("no command in this script")

    def quantity(self, name):
        return self.nodes[name]

    def set_quantity(self, name, value):
        self.nodes[name] = value

    def quantity_range(self, name):
        return (10.0, 1e6) if name == "exposure" else (0.0, 12.0)

    def prepare_acquisition(self):
        pass

    def start(self):
        pass

    def drop_waiting(self):
        return 0

    def software_trigger(self, timeout_s):
        return True

    def next_frame(self, timeout_s, bits):
        item = self.deliveries.pop(0)
        if isinstance(item, Exception):
            raise item
        return item

    def check_alive(self):
        pass

    def release(self):
        self.handle = None
        self.releases += 1

    def _verdict(self, exc, setting):
        return "gone" if isinstance(exc, LinkDown) else None


def scripted(deliveries, trigger="software") -> tuple[GenICamCamera, ScriptedTransport]:
    transport = ScriptedTransport(deliveries)
    return GenICamCamera(transport, (3, 4), trigger=trigger), transport


FRAME_A = np.arange(12, dtype=np.uint8).reshape(3, 4)
FRAME_B = FRAME_A + 100
BEFORE_ANY_TRIGGER = 1                  # 1 ns after 1970: earlier than any trigger this test sends
AFTER_EVERY_TRIGGER = 2 ** 62           # the year 2116


def test_a_frame_that_arrived_before_the_software_trigger_is_dropped():
    cam, _ = scripted([Delivery(FRAME_A, "", BEFORE_ANY_TRIGGER), Delivery(FRAME_B, "", AFTER_EVERY_TRIGGER)])
    np.testing.assert_array_equal(cam.grab(), FRAME_B)
    assert (cam.frames_dropped, cam.frames_grabbed) == (1, 1)
    # In free run the trigger time means nothing: the first frame to come is the one returned.
    free, _ = scripted([Delivery(FRAME_A, "", BEFORE_ANY_TRIGGER)], trigger="freerun")
    np.testing.assert_array_equal(free.grab(), FRAME_A)
    assert free.frames_dropped == 0


def test_damaged_frame_and_timeout_keep_the_camera_usable():
    cam, _ = scripted([Delivery(None, "missing packets", AFTER_EVERY_TRIGGER), None,
                       Delivery(FRAME_A, "", AFTER_EVERY_TRIGGER), Delivery(np.zeros((3, 5), np.uint8))])
    with pytest.raises(CameraIncompleteFrameError, match=r"Script S \(serial 1\) delivered a damaged frame "
                                                          r"\(missing packets\)"):
        cam.grab()
    with pytest.raises(CameraTimeoutError, match="no frame after a software trigger within 0.5 s"):
        cam.grab(timeout_s=0.5)
    np.testing.assert_array_equal(cam.grab(), FRAME_A)
    with pytest.raises(CameraFrameSizeError, match=r"frame of 3 x 5 pixels .* expects 3 x 4"):
        cam.grab()


def test_library_failure_mid_grab_means_gone_until_reopened():
    cam, transport = scripted([LinkDown("link down")])
    with pytest.raises(CameraDisconnectedError, match=r"does not answer while grabbing a frame \(link down\)"):
        cam.grab()
    with pytest.raises(CameraDisconnectedError, match="was disconnected; check the cable"):
        cam.set_gain(1.0)
    assert "disconnected" in repr(cam)
    cam.close()
    cam.close()
    assert transport.releases == 1


def test_exposure_goes_to_the_transport_in_microseconds():
    cam, transport = scripted([])
    cam.set_exposure(0.0125)
    assert transport.nodes["exposure"] == pytest.approx(12500.0, rel=1e-12)
    assert cam.exposure_s == pytest.approx(0.0125, rel=1e-12)
    with pytest.raises(CameraSettingError, match=r"exposure 2 s is outside the camera's range \[1e-05, 1\] s"):
        cam.set_exposure(2.0)
