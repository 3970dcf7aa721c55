"""open_camera: known kinds, clear errors for unknown kinds and options, lazy backend imports."""

import subprocess
import sys

import numpy as np
import pytest

from sofast_station.devices.cameras import BACKENDS, ReplayCamera, open_camera
from sofast_station.devices.protocols import Camera
from sofast_station.errors import CameraError, ConfigError


def test_opens_a_replay_camera():
    frames = np.zeros((2, 3, 4), np.uint8)
    cam = open_camera("Replay", frames=frames, frame_delay_s=0.0)
    assert isinstance(cam, ReplayCamera)
    assert cam.grab().shape == (3, 4)
    cam.close()


def test_unknown_kind_is_a_config_error_listing_the_kinds():
    with pytest.raises(ConfigError, match="unknown camera kind 'uvc'.*aravis, basler, replay"):
        open_camera("uvc")


def test_unknown_option_is_a_config_error_listing_the_options():
    with pytest.raises(ConfigError, match="camera kind 'replay'.*frame_delay_s"):
        open_camera("replay", frames=np.zeros((1, 2, 2), np.uint8), exposure=3)


@pytest.mark.parametrize("kind", sorted(BACKENDS))
def test_every_backend_implements_the_camera_protocol(kind):
    import importlib
    module_name, class_name = BACKENDS[kind]
    cls = getattr(importlib.import_module(f"sofast_station.devices.cameras.{module_name}"), class_name)
    for member in ("set_exposure", "set_gain", "grab", "close"):
        assert callable(getattr(cls, member)), (kind, member)
    protocol_members = {name for name in vars(Camera) if not name.startswith("_")}
    assert protocol_members <= set(dir(cls)) | {"shape"}


_MISSING = r"""
import sys, numpy
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in ("pypylon", "gi"):
            raise ImportError("blocked for the test: " + name)
sys.meta_path.insert(0, Block())
import sofast_station.devices.cameras as cams
assert "pypylon" not in sys.modules and "gi" not in sys.modules
cam = cams.open_camera("replay", frames=numpy.zeros((1, 2, 2), numpy.uint8))   # unaffected
for kind, package in (("basler", "pip install 'pypylon==26.9'"), ("aravis", "PyGObject<3.51")):
    try:
        cams.open_camera(kind, **{"serial" if kind == "basler" else "device_id": None}, expected_shape=(2, 2))
    except cams.CameraBackendMissingError as exc:
        assert package in str(exc), str(exc)
        print(kind, "ok")
    else:
        raise SystemExit(kind + ": no error")
"""


def test_missing_library_fails_only_for_its_backend_and_names_the_package():
    out = subprocess.run([sys.executable, "-c", _MISSING], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["basler", "ok", "aravis", "ok"]


def test_backend_missing_error_is_a_camera_error():
    from sofast_station.devices.cameras import CameraBackendMissingError
    assert issubclass(CameraBackendMissingError, CameraError)
