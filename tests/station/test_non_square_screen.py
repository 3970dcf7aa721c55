"""Issue 12, item 6: a display with non-square pixels (0.27 x 0.2703 mm) is described in station.toml and
measured as accurately as a square one; taken as square it would bias the focal length along y.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.geometry import ScreenSpec
from sofast_station.measure.analysis import analyse
from sofast_station.station.factory import open_station
from sofast_station.station.inspection import capture
from sofast_station.twin.truth import ground_truth
from tests.conftest import ROOT, SMALL_STATION


def station_toml(tmp_path, screen: str):
    text = SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                radiometric=ROOT / "calibration/simulated_radiometric.json")
    text = text.replace("pitch_m = 0.000275\n", screen)
    path = tmp_path / "station.toml"
    path.write_text(text)
    return path


def f_errors(cfg, geometry=None):
    """Relative focal-length errors (x, y) against truth of a noise-free capture, analysed with *geometry*."""
    station = open_station(cfg, noise=False)
    try:
        frames, distance = capture(station)
        a = analyse(frames, cfg.fringes, geometry or cfg.geometry, cfg.design, distance, cfg.analysis,
                    rays_cam=station.rays_cam)
        truth = ground_truth(station.twin, a.valid)
    finally:
        station.close()
    return np.array([a.figures[k] / truth[k] - 1 for k in ("focal_length_x_m", "focal_length_y_m")])


def test_pitch_in_x_and_y_from_station_toml(tmp_path):
    cfg = load_config(station_toml(tmp_path, "pitch_x_m = 0.00027\npitch_y_m = 0.0002703\n"))
    scr = cfg.geometry.screen
    assert (scr.pitch_x_m, scr.pitch_y_m) == (0.00027, 0.0002703) and not scr.square
    assert scr.width_m == pytest.approx(1920 * 0.00027) and scr.height_m == pytest.approx(1080 * 0.0002703)
    assert load_config(station_toml(tmp_path, "pitch_m = 0.00027\n")).geometry.screen == ScreenSpec(1920, 1080, 0.00027)
    for bad, match in (("pitch_x_m = 0.00027\n", "pitch_x_m alone"),
                       ("pitch_m = 0.00027\npitch_y_m = 0.00027\n", "not both")):
        with pytest.raises(ConfigError, match=match):
            load_config(station_toml(tmp_path, bad))


def test_non_square_screen_measured_as_accurately_as_a_square_one(tmp_path):
    (tmp_path / "sq").mkdir()
    (tmp_path / "ns").mkdir()
    square = load_config(station_toml(tmp_path / "sq", "pitch_m = 0.00027\n"))
    non_square = load_config(station_toml(tmp_path / "ns", "pitch_x_m = 0.00027\npitch_y_m = 0.0002703\n"))
    err_square = f_errors(square)
    err = f_errors(non_square)
    # the same frames analysed as if the pixels were square (0.27 mm both ways)
    as_square = dataclasses.replace(non_square.geometry, screen=ScreenSpec(1920, 1080, 0.00027))
    err_taken_square = f_errors(non_square, as_square)
    print(f"f errors: square screen {err_square * 100} %, non-square {err * 100} %, "
          f"non-square taken as square {err_taken_square * 100} %")
    assert np.all(np.abs(err) < np.abs(err_square) + 5e-5)
    assert np.all(np.abs(err) < 2e-4)
    # Ignoring the 0.11 % pitch difference biases f_y (only slightly here: the dish's reflection sits
    # at the screen's centre, where a scale error moves the screen points least); described, it is gone.
    assert abs(err_taken_square[1]) > 3 * abs(err[1])
