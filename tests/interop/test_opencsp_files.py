"""Issue 48 item 6: no traceback for any file a peer could hand us. Every file of OpenCSP's published SOFAST data
(fixtures/opencsp) is given to every option of ``import-opencsp`` in turn (the others right): it is read, or
refused with a StationError naming the file and what it holds; never another exception."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from sofast_station.errors import StationError
from sofast_station.interop.identify import describe
from sofast_station.interop.opencsp import read_opencsp
from sofast_station.interop.opencsp_results import read_opencsp_result
from sofast_station.interop.paths import opencsp_test_data_paths

ROLES = ("measurement", "camera", "display", "orientation", "calibration", "facet", "ensemble", "compare")


@pytest.fixture(scope="module")
def files(repo_root):
    root = repo_root / "fixtures/opencsp"
    found = sorted(p for p in root.rglob("*") if p.is_file() and ("test_data" in p.parts or "app_data" in p.parts))
    assert len(found) >= 30
    return found


def test_every_file_in_every_role_is_read_or_refused_by_name(repo_root, files, tmp_path):
    base = opencsp_test_data_paths(repo_root / "fixtures/opencsp/test_data")
    cut = tmp_path / "cut.h5"            # a file cut short, as a copy interrupted
    cut.write_bytes(base["measurement"].read_bytes()[:5000])
    refused = 0
    for f in [*files, cut]:
        for role in ROLES:
            try:
                if role == "compare":
                    read_opencsp_result(f)
                else:
                    read_opencsp(**{**base, role: f})
            except StationError as exc:
                refused += 1
                assert str(f) in str(exc) or f.name in str(exc), (role, f, str(exc))
            except Exception as exc:
                pytest.fail(f"{f} as --{role}: {type(exc).__name__}: {exc}")
    assert refused > 100                # most files are not what most options take


def test_what_says_what_each_file_holds_from_its_contents(repo_root, files, tmp_path):
    said = {f.name: describe(f) for f in files}
    assert said["measurement_facet.h5"] in (  # two files of that name: the fringe and the fixed-pattern one
        describe(repo_root / "fixtures/opencsp/test_data/sofast_fringe/data_measurement/measurement_facet.h5"),
        describe(repo_root / "fixtures/opencsp/test_data/sofast_fixed/data_measurement/measurement_facet.h5"))
    assert "Camera" in said["camera_sofast.h5"] and "ImageProjection" in said["image_projection.h5"]
    assert "fixed pattern's dots" in said["fixed_pattern_dot_locations.h5"]
    assert "facet definition" in said["Facet_NSTTF.json"] and "ensemble definition" in said["Ensemble_lab_6x4.json"]
    assert "ArUco" in said["aruco_corner_locations.csv"] and "statistics" in said["stats_fringe.json"]
    renamed = tmp_path / "looks_like_a_camera.h5"          # the contents decide, not the name
    renamed.write_bytes((repo_root / "fixtures/opencsp/test_data/sofast_common/display_rectangular.h5").read_bytes())
    assert "DisplayShape" in describe(renamed)
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "import-opencsp", "--what", str(renamed)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "a screen's shape (DisplayShape)" in proc.stdout


def test_a_camera_file_given_as_the_measurement_is_named_for_what_it_is(repo_root):
    data = repo_root / "fixtures/opencsp/test_data"
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "import-opencsp", "--test-data", str(data),
                           "--measurement", str(data / "sofast_common/camera_sofast.h5")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "camera_sofast.h5" in proc.stderr and "a camera's intrinsics and distortion (Camera)" in proc.stderr


def test_import_of_a_mirror_of_unknown_outline_and_of_the_plano_model(repo_root):
    """The two new kinds of measurement through the command: each figure it cannot know is None and named with
    its reason; those it reports carry U."""
    data = repo_root / "fixtures/opencsp/test_data"
    runs = {}
    for name, flags in (("undefined", ["--undefined"]), ("plano", ["--surface", "plano", "--robust"])):
        proc = subprocess.run([sys.executable, "-m", "sofast_station", "import-opencsp", "--test-data", str(data),
                               *flags, "--json"], capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs[name] = json.loads(proc.stdout)
    u = runs["undefined"]
    assert u["outline"] == "unknown" and u["boresight_mrad"] is None and "boresight_mrad" in u["not_measured"]
    assert u["focal_length_x_m_U"] > 0 and abs(u["focal_length_x_m"] / 115.7 - 1) < 0.02
    p = runs["plano"]
    assert p["surface"] == "plano" and p["focal_length_x_m"] is None and p["optics"] is None
    assert "focal_length_x_m" in p["not_measured"] and p["boresight_mrad_U"]["x"] > 0
