"""station.toml validation: errors name the file and the key."""

import pytest

from sofast_station.config import load_config
from sofast_station.errors import ConfigError


def test_default_station_is_the_full_resolution_dish(repo_root):
    cfg = load_config(repo_root / "station.toml")
    assert cfg.backend == "simulated"
    assert cfg.geometry.camera.shape == (1200, 1600)
    assert cfg.design.kind == "dish" and cfg.design.focal_length_m == pytest.approx(5.33)
    assert cfg.fringes.n_frames == 18
    assert len(cfg.config_hash) == 16


def test_data_dir_comes_from_the_environment_in_tests(small_station_toml, tmp_path):
    # conftest points SOFAST_DATA_DIR at the test's temporary folder: nothing is written into the source tree
    assert str(load_config(small_station_toml).data_dir).startswith(str(tmp_path))


@pytest.mark.parametrize("edit, message", [
    (("[camera]", "[camera]\nfocal_lenght_px = 3"), "unknown key(s) focal_lenght_px"),
    (("separation_m = 0.34", "separation_m = 0.1"), "inside the screen"),
    (("pitch_m = 0.000275", "pitch_m = -1"), "pitch_m"),
    (("[simulation]", "[fringes]\nperiods_x = [4, 1]\n[simulation]"), "must increase"),
    (("[simulation]", "[analysis]\nthreshold = 3\n[simulation]"), "[analysis] has unknown key(s) threshold"),
    (("[simulation]", "[analysis]\nthreads = 0\n[simulation]"), "threads must be a whole number of at least 1"),
])
def test_errors_name_the_key(small_station_toml, edit, message):
    text = small_station_toml.read_text().replace(*edit, 1)
    small_station_toml.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(small_station_toml)
    assert message in str(exc.value)


def test_broken_toml_names_the_file(tmp_path):
    p = tmp_path / "station.toml"
    p.write_text("[station\n")
    with pytest.raises(ConfigError, match="station.toml is not valid TOML"):
        load_config(p)
