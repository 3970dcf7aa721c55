"""Reading OpenCSP's geometry-calibration files (interop/opencsp_calibration.py): cameras, fixed-pattern dot
locations, screen distortion data, point pairs, image projection; each wrong file a one-line error."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from sofast_station.errors import ConfigError
from sofast_station.interop.opencsp import camera_from_opencsp
from sofast_station.interop.opencsp_calibration import (fiducial_fractions, opencsp_camera, read_dot_locations,
                                                        read_image_projection, read_point_pairs,
                                                        read_screen_distortion, write_dot_locations)
from sofast_station.measure.dots import DotLocations
from tests.conftest import ROOT

DATA = ROOT / "fixtures/opencsp/test_data"


def test_camera_from_opencsp_reads_four_term_distortion_and_a_column_image_shape():
    """Regression: OpenCSP's cameras with OpenCV's 4-term distortion (the dot calibration's Sony, the
    screen-shape camera) and with image_shape_xy stored as a (2, 1) column (camera_sofast.h5) were refused
    ("camera distortion must have shape (5,)"; "only 0-dimensional arrays can be converted")."""
    sony = camera_from_opencsp(DATA / "dot_location_calibration/data_measurement/camera_calibration.h5")
    assert sony.distortion[4] == 0.0 and sony.shape == (1440, 2160)
    basler = camera_from_opencsp(DATA / "sofast_common/camera_sofast.h5")
    assert basler.shape == (1236, 1626) and basler.matrix[0, 0] == pytest.approx(5492.06431, abs=1e-3)


def test_opencsp_camera_says_when_its_matrix_was_scaled_whole():
    """The screen-shape camera: K[2,2] = 0.25, image 406 x 309 (a 1626 x 1236 Basler read 4x downsampled);
    camera_sofast.h5 has K[2,2] = 1 and gets no note."""
    camera, note = opencsp_camera(DATA / "display_shape_calibration/data_measurement/camera_screen_shape.h5")
    assert camera.shape == (309, 406) and "K[2,2] = 0.25" in note and camera.matrix[2, 2] == 1.0
    assert opencsp_camera(DATA / "sofast_common/camera_sofast.h5")[1] is None


def test_dot_locations_read_and_written_like_opencsp(tmp_path):
    """OpenCSP's expected dot file: 64 x 64, x -32..31, y -31..32, two dots NaN; written back it reads the
    same, in OpenCSP's layout (rows = y)."""
    dots = read_dot_locations(DATA / "dot_location_calibration/data_expected/fixed_pattern_dot_locations.h5")
    assert dots.xyz_m.shape == (64, 64, 3) and dots.x_index[0] == -32 and dots.y_index[-1] == 32
    assert (~dots.located).sum() == 2 and dots.xyz_U_m is None
    path = write_dot_locations(tmp_path / "dots.h5", dots)
    with h5py.File(path) as h:
        assert h["DotLocationsFixedPattern/xyz_dot_loc"].shape == (64, 64, 3)
    back = read_dot_locations(path)
    np.testing.assert_array_equal(back.xyz_m, dots.xyz_m)
    np.testing.assert_array_equal(back.x_index, dots.x_index)


def test_wrong_files_are_one_line_errors(tmp_path):
    wrong = tmp_path / "wrong.h5"
    with h5py.File(wrong, "w") as h:
        h["DotLocationsFixedPattern/x_dot_index"] = np.arange(3)
        h["DotLocationsFixedPattern/y_dot_index"] = np.arange(2)
        h["DotLocationsFixedPattern/xyz_dot_loc"] = np.zeros((3, 2, 3))
    with pytest.raises(ConfigError, match=r"xyz_dot_loc must be \(len\(y_dot_index\), len\(x_dot_index\), 3\)"):
        read_dot_locations(wrong)
    with pytest.raises(ConfigError, match="is not OpenCSP's screen distortion data .*: it has no pts_xy"):
        read_screen_distortion(wrong)
    text = tmp_path / "text.h5"
    text.write_text("not hdf5")
    with pytest.raises(ConfigError, match="is not a readable HDF5 file"):
        opencsp_camera(text)
    with pytest.raises(ConfigError, match="does not exist"):
        read_image_projection(tmp_path / "none.h5")
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("Display calibration point,Marker ID\n0,x\n")
    with pytest.raises(ConfigError, match="is not OpenCSP's screen calibration point pairs"):
        read_point_pairs(pairs)
    with pytest.raises(ValueError, match="consecutive"):
        DotLocations(np.array([1, 3]), np.array([0]), np.zeros((1, 2, 3)))


def test_the_fiducial_layout_is_opencsps():
    """OpenCSP's CalParams for a 760 x 760 active area: pixels 7, 380, 753 along each axis; x fraction
    1 - (p + 1/2) / 760, y counted from the top in the distortion data."""
    fr = fiducial_fractions(760, 760)
    np.testing.assert_allclose(fr[0], [1 - 7.5 / 760, 7.5 / 760])
    np.testing.assert_allclose(fr[4], [1 - 380.5 / 760, 380.5 / 760])
    np.testing.assert_allclose(fr[8], [1 - 753.5 / 760, 753.5 / 760])
    projection = read_image_projection(DATA / "sofast_common/image_projection.h5")
    assert (projection["active_area_size_x"], projection["active_area_position_x"]) == (760, 580)
    assert read_point_pairs(DATA / "display_shape_calibration/data_measurement/screen_calibration_point_pairs.csv"
                            ).tolist()[0] == [0, 36]
