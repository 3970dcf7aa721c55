"""The sofast-station command: mechanics on a small simulated station."""

import json
import subprocess
import sys

from sofast_station.cli import main
from sofast_station.files import json_ready as _json_safe

KEYS = {"serial", "focal_length_x_m", "focal_length_y_m", "twist_mrad_per_m", "slope_rms_mrad",
        "curvature_x_per_m", "curvature_y_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "n_points",
        "timings_s", "truth"}


def test_inspect_json_prints_one_object_and_nothing_else(small_station_toml, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "inspect", "--config", str(small_station_toml),
                           "--json", "--serial", "F-42"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rec = json.loads(proc.stdout)             # the whole of stdout is one JSON object
    assert KEYS <= set(rec)
    assert rec["serial"] == "F-42"
    for model in ("design", "parabola"):
        assert set(rec["slope_rms_mrad"][model]) == {"x", "y", "magnitude"}
    assert KEYS - {"serial", "timings_s", "truth"} <= set(rec["truth"])
    assert abs(rec["focal_length_x_m"] / rec["truth"]["focal_length_x_m"] - 1) < 0.01
    assert rec["coverage_factor"] == 2 and rec["focal_length_x_m_U"] > 0
    assert set(rec["slope_rms_mrad_U"]["design"]) == {"x", "y", "magnitude"}
    assert {"capture", "analysis", "total"} <= set(rec["timings_s"])
    assert "captured" in proc.stderr          # progress goes to stderr
    # SOFAST_DATA_DIR (set for every test by conftest) overrides the file's data_dir
    saved = list((tmp_path / "station-data" / "inspections").glob("F-42-*.json"))
    assert len(saved) == 1 and json.loads(saved[0].read_text())["serial"] == "F-42"


def test_inspect_summary_is_readable(small_station_toml, capsys):
    assert main(["inspect", "--config", str(small_station_toml), "--noise-free", "--budget"]) == 0
    out = capsys.readouterr().out
    assert "focal length x" in out and "truth" in out and "parabola" in out
    # every figure with its expanded uncertainty, and the budget table (docs/uncertainty.md)
    assert "(k=2)" in out and " ± " in out.split("focal length x")[1].splitlines()[0]
    assert "Uncertainty budget" in out and "measured distance" in out and "expanded U (k=2)" in out


def test_infinite_values_become_null():
    assert json.dumps(_json_safe({"f": float("inf"), "g": [float("nan"), 1.0]})) == '{"f": null, "g": [null, 1.0]}'


def test_bad_config_is_reported_without_a_traceback(tmp_path):
    bad = tmp_path / "station.toml"
    bad.write_text('[station]\nfacet = "nowhere.toml"\n')
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "inspect", "--config", str(bad)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == ""
    assert "nowhere.toml" in proc.stderr and "does not exist" in proc.stderr and "Traceback" not in proc.stderr
