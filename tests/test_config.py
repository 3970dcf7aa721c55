"""station.toml validation: errors name the file and the key."""

import pytest

from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from tests.conftest import ROOT, SMALL_STATION


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


@pytest.mark.parametrize("section, line, message", [
    ("run", 'dump_every_n = "two"', "[run] dump_every_n must be a whole number of at least 0, got 'two'"),
    ("run", "deadline_s = 0", "[run] deadline_s must be a number above 0, got 0"),
    ("run", "camera_timeout_s = 20.0", "[run] camera_timeout_s = 20.0: must be shorter than deadline_s"),
    ("run", "dump_failed = 1", "[run] dump_failed must be true or false, got 1"),
    ("run", "deadline = 3", "[run] has unknown key(s) deadline; allowed:"),
    # issue 43: an abandoned analysis given 1e12 s of grace was accepted (never killed)
    ("run", "late_grace_s = 1e12",
     "[run] late_grace_s must be a number of at least 0 and at most 600, got 1000000000000.0"),
    ("station", 'id = ""', "[station] id = '': must be a non-empty string naming this station"),
    ("camera", 'width_px = "1600"', "[camera] width_px must be a whole number of at least 1, got '1600'"),
    ("camera", "distortion = [0.1, 0.2]", "[camera] distortion must be a list of numbers of length 4 or 5, got"),
    # issue 28: the schema allowed an 8-term model that the camera loader then refused
    ("camera", "distortion = [-0.05, 0.1, 0.0002, -0.0001, 0.0, 0.01, 0.0, 0.0]",
     "[camera] distortion must be a list of numbers of length 4 or 5, got [-0.05, 0.1, 0.0002, -0.0001, 0.0, 0.01, "
     "0.0, 0.0] (OpenCV's k1, k2, p1, p2[, k3]: the 5-term model"),
    ("limits", "focal_length_tolerance = -0.02",
     "[limits] focal_length_tolerance must be a number above 0 and at most 1, got -0.02"),
    ("limits", "max_slope_rms_mrad = { design = -3.0 }", "[limits.max_slope_rms_mrad] design must be a number above 0"),
    ("quality", "min_valid_fraction = 1.5",
     "[quality] min_valid_fraction must be a number of at least 0 and at most 1"),
    ("analysis", "robust_fit = \"yes\"", "[analysis] robust_fit must be true or false, got 'yes'"),
    ("archive", 'workbook_period = "week"', "[archive] workbook_period must be one of 'day', 'shift', got 'week'"),
    ("devices", 'trigger = "plc"', "[devices] trigger must be one of 'simulated', 'modbus', 'usb', got 'plc'"),
    ("recipes.gore", "serial_pattern = 3", "[recipes.gore] serial_pattern must be a string, got 3"),
    ("recipes.gore", "analysis = { threads = 0 }",
     "[recipes.gore.analysis] threads must be a whole number of at least 1"),
    ("runn", "deadline_s = 3", "has unknown section(s) runn; allowed:"),
])
def test_every_key_is_checked_at_load(small_station_toml, section, line, message):
    """Issue 11: types, ranges and cross-key rules at load, naming the file, section, key and value."""
    text = small_station_toml.read_text()
    table = f"[{section}]"
    key = line.split(" =")[0]
    existing = [ln for ln in text.splitlines() if ln.startswith(f"{key} =")]
    if existing and section == "camera":
        text = text.replace(existing[0], line, 1)
    elif table in text:
        text = text.replace(table, f"{table}\n{line}", 1)
    else:
        text = text.replace("[simulation]", f"{table}\n{line}\n\n[simulation]", 1)
    small_station_toml.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(small_station_toml)
    assert message in str(exc.value)
    assert str(small_station_toml) in str(exc.value)


def test_shipped_station_documents_every_key(repo_root):
    """Every key the schema knows appears in the shipped station.toml (set or in a comment)."""
    from sofast_station.config_schema import SECTIONS, TOP_LEVEL

    text = (repo_root / "station.toml").read_text()
    for section in TOP_LEVEL:
        assert f"[{section}" in text, section
        for key in SECTIONS[section]:
            if key not in ("*", "routine"):
                assert f"{key} =" in text or f"{key}," in text, (section, key)
    cfg = load_config(repo_root / "station.toml")
    assert cfg.raw["run"]["dump_every_n"] > 0


def test_workbook_parts_are_bounded_by_default(small_station_toml):
    """The archiver writes a workbook part whole on every save: a busy line's day is split into
    parts of [archive] workbook_max_rows rows (1000 unless set), so a save's work does not grow with the day."""
    from sofast_station.station.service import WORKBOOK_MAX_ROWS, archiver_settings, run_settings

    cfg = load_config(small_station_toml)
    assert archiver_settings(cfg, run_settings(cfg)).workbook.rows_per_part() == WORKBOOK_MAX_ROWS == 1000
    small_station_toml.write_text(small_station_toml.read_text() + "\n[archive]\nworkbook_max_rows = 50\n")
    cfg = load_config(small_station_toml)
    assert archiver_settings(cfg, run_settings(cfg)).workbook.rows_per_part() == 50
    small_station_toml.write_text(small_station_toml.read_text().replace("= 50", "= 0"))
    with pytest.raises(ConfigError, match=r"\[archive\] workbook_max_rows must be a whole number of at least 1"):
        load_config(small_station_toml)


def test_a_camera_focal_length_uncertainty_of_a_million_pixels_is_named_at_load(tmp_path):
    """Issue 26: [uncertainty] camera_focal_px = 1e6 loaded, and the first facet's uncertainty reran the
    analysis with a focal length of -996,591 px: refused as "partly lit or obstructed". It is a wrong camera
    focal length uncertainty, said when the station file is read."""
    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json")
                    + "\n[uncertainty]\ncamera_focal_px = 1e6\n")
    says = r"camera_focal_px = 1e\+06 px is 293 times the camera's focal length"
    with pytest.raises(ConfigError, match=says) as info:
        load_config(path)
    assert "obstructed" not in str(info.value)


@pytest.mark.parametrize("kind, says", [
    ("geometry", "the fixture pose and the distance keep their [uncertainty] values"),
    ("radiometric", "the uncertainty budget's display response leaves out the rounding of its lookup table"),
])
def test_an_unreadable_calibration_record_is_named_when_its_part_of_the_budget_is_left_out(
        small_station_toml, kind, says, caplog):
    """Issue 27: a geometry or radiometric record that cannot be read drops what it lends the uncertainty
    budget; loading the configuration says so, naming the file, and the budget keeps the table's values."""
    import logging

    before = load_config(small_station_toml).uncertainty
    folder = load_config(small_station_toml).data_dir / "calibration" / kind
    folder.mkdir(parents=True)
    bad = folder / f"{kind}-20261201T060000Z-001.json"
    bad.write_text('{"schema": 1, "kind": "' + kind + '", "record_id": "cut off mid-wr')
    with caplog.at_level(logging.WARNING, logger="sofast_station.config"):
        after = load_config(small_station_toml).uncertainty
    assert str(bad) in caplog.text and says in caplog.text, caplog.text
    if kind == "geometry":
        assert after == before
    else:                     # the shipped record's rounding was in the budget; the unreadable newest has none
        assert before.response_record_rad is not None and after.response_record_rad is None


def test_a_four_term_distortion_loads_with_k3_zero(small_station_toml):
    """Issue 28: what the schema allows, the camera loader takes: OpenCV's four terms mean k3 = 0."""
    text = small_station_toml.read_text()
    line = next(ln for ln in text.splitlines() if ln.startswith("distortion ="))
    small_station_toml.write_text(text.replace(line, "distortion = [-0.05, 0.1, 0.0002, -0.0001]", 1))
    cam = load_config(small_station_toml).geometry.camera
    assert cam.distortion.tolist() == [-0.05, 0.1, 0.0002, -0.0001, 0.0]
