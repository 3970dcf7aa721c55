"""Fixtures for the camera backends: pylon's camera emulation, Aravis's fake GigE Vision camera, and the
opt-in real-camera options.

The emulators must be installed (CI installs them): a missing library or binary makes the tests that need
it FAIL with the package to install, never skip.

Network: everything here talks to 127.0.0.1 only. The pylon tests search only the emulator's transport
layer (``device_class="BaslerCamEmu"``) and the Aravis tests open the fake camera by its address, so no
GigE Vision discovery broadcast leaves the machine.

Real hardware (opt-in): ``pytest tests/devices/cameras --camera-serial SERIAL --camera-shape 1200x1600
[--camera-kind basler|aravis]``. The options are registered here and so are known when this folder is
given on the command line; to use them from a plain ``pytest``, ``tests/conftest.py`` must register them
too (``from tests.devices.cameras.conftest import pytest_addoption``).
"""

from __future__ import annotations

import contextlib
import fcntl
import shutil
import socket
import struct
import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from sofast_station.devices.cameras._common import CameraBackendMissingError

FAKE_GV_CAMERA = "arv-fake-gv-camera-0.8"
FAKE_ADDRESS = "127.0.0.1"
GVCP_PORT = 3956
EMULATOR_CLASS = "BaslerCamEmu"
EMULATOR_SERIAL = "0815-0000"     # the first emulated camera's serial number


def pytest_addoption(parser):
    group = parser.getgroup("cameras", "tests against a real camera (skipped unless --camera-serial)")
    try:
        group.addoption("--camera-serial", default=None,
                        help="serial number (Basler) or device id / IP address (Aravis) of a real camera")
        group.addoption("--camera-kind", default="basler", choices=("basler", "aravis"),
                        help="backend for --camera-serial (default basler)")
        group.addoption("--camera-shape", default=None,
                        help="the real camera's frame size ROWSxCOLUMNS, e.g. 1200x1600")
    except ValueError:      # already registered by a parent conftest
        pass


def pytest_configure(config):
    config.addinivalue_line("markers", "hardware: needs a real camera (--camera-serial); skipped otherwise")


def pytest_collection_modifyitems(config, items):
    if config.getoption("camera_serial", default=None):
        return
    skip = pytest.mark.skip(reason="real-camera test: give --camera-serial (and --camera-shape) to run it")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


# -- pylon camera emulation -------------------------------------------------------------------------


@pytest.fixture
def pylon_emulation(monkeypatch):
    """Turn on one emulated Basler camera (serial 0815-0000) and return the ``pypylon.pylon`` module.

    pypylon reads PYLON_CAMEMU when it enumerates devices, so setting it here, after pypylon may have
    been imported, is enough; the emulated camera starts from its defaults on every open.
    """
    monkeypatch.setenv("PYLON_CAMEMU", "1")
    from sofast_station.devices.cameras.basler import _import_pylon
    try:
        pylon, _ = _import_pylon()
    except CameraBackendMissingError as exc:
        pytest.fail(f"{exc} (CI installs it)", pytrace=False)
    return pylon


# -- Aravis and its fake GigE Vision camera ---------------------------------------------------------


@pytest.fixture(scope="session")
def aravis_module():
    """``gi.repository.Aravis`` (0.8), or FAIL naming the packages to install."""
    from sofast_station.devices.cameras.aravis import _import_aravis
    try:
        aravis, _ = _import_aravis()
    except CameraBackendMissingError as exc:
        pytest.fail(f"{exc} (CI installs it)", pytrace=False)
    return aravis


def _gvcp_discovery_answered(address: str, timeout_s: float) -> bool:
    """Send one GVCP discovery command to ``address`` (unicast) and wait for its acknowledge."""
    packet = struct.pack(">BBHHH", 0x42, 0x01, 0x0002, 0, 1)    # key, flags (ack), DISCOVERY_CMD, len, id
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(timeout_s)
        sock.sendto(packet, (address, GVCP_PORT))
        try:
            data, _ = sock.recvfrom(1024)
        except (socket.timeout, ConnectionRefusedError):
            return False
    return len(data) >= 8 and struct.unpack(">H", data[2:4])[0] == 0x0003      # DISCOVERY_ACK


class FakeGvCamera:
    """Aravis's fake GigE Vision camera (512 x 512 Mono8 diagonal ramp) as a subprocess on 127.0.0.1."""

    address = FAKE_ADDRESS
    shape = (512, 512)

    def __init__(self, serial: str, log_path: Path):
        self.serial = serial
        self.device_id = f"Aravis-Fake-{serial}"
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None

    def start(self) -> "FakeGvCamera":
        exe = shutil.which(FAKE_GV_CAMERA)
        if exe is None:
            pytest.fail(f"{FAKE_GV_CAMERA} is not installed: apt-get install aravis-tools (CI installs it)",
                        pytrace=False)
        if _gvcp_discovery_answered(self.address, 0.05):
            pytest.fail(f"something already answers GigE Vision on {self.address}:{GVCP_PORT} (a leftover "
                        f"{FAKE_GV_CAMERA}?): stop it first", pytrace=False)
        with open(self.log_path, "ab") as log:
            self.proc = subprocess.Popen([exe, "-i", self.address, "-s", self.serial], stdin=subprocess.DEVNULL,
                                         stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                pytest.fail(f"{FAKE_GV_CAMERA} exited with {self.proc.returncode}: "
                            f"{self.log_path.read_text(errors='replace')[-2000:]}", pytrace=False)
            if _gvcp_discovery_answered(self.address, 0.1):
                return self
        self.kill()
        pytest.fail(f"{FAKE_GV_CAMERA} did not answer on {self.address}:{GVCP_PORT} within 10 s", pytrace=False)

    def kill(self) -> None:
        """SIGKILL, as a camera losing power: no goodbye on the network."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait(timeout=10)

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


@contextlib.contextmanager
def _machine_lock(name: str, timeout_s: float = 300.0):
    """An exclusive lock shared by every test session on this machine (the fake camera's GVCP port,
    127.0.0.1:3956, exists once per machine)."""
    path = Path(tempfile.gettempdir()) / name
    with open(path, "a+") as handle:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    pytest.fail(f"another test session has held {path} for {timeout_s:g} s", pytrace=False)
                time.sleep(0.1)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@pytest.fixture
def fake_gv_camera(aravis_module, tmp_path):
    """A running fake GigE Vision camera on 127.0.0.1, killed after the test.

    Test sessions running side by side on one machine take turns (a file lock), since the camera's
    address and port exist once.
    """
    with _machine_lock("sofast-station-arv-fake-gv-camera.lock"):
        camera = FakeGvCamera("SOFAST1", tmp_path / "arv-fake-gv-camera.log").start()
        try:
            yield camera
        finally:
            camera.kill()


# -- real hardware (opt-in) -------------------------------------------------------------------------


@pytest.fixture
def real_camera_options(request):
    """(kind, id, shape) of the real camera named on the command line."""
    serial = request.config.getoption("camera_serial", default=None)
    shape_text = request.config.getoption("camera_shape", default=None)
    if not shape_text:
        pytest.fail("--camera-shape ROWSxCOLUMNS is needed with --camera-serial", pytrace=False)
    try:
        rows, cols = (int(v) for v in shape_text.lower().split("x"))
    except ValueError:
        pytest.fail(f"--camera-shape must be ROWSxCOLUMNS, e.g. 1200x1600, got {shape_text!r}", pytrace=False)
    return request.config.getoption("camera_kind", default="basler"), serial, (rows, cols)
