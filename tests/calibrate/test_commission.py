"""Commissioning the geometry on the twin (issue 31): a bowed, twisted screen of another pitch and a camera
misplaced by millimetres, drawn from seeds; ``calibrate screen`` and ``calibrate pose`` measure them, and the
analysis with their records in force gets the focal lengths and the slope RMS back to the twin's truth.

The claims rest on 2 drawn stations here (seeds 1 and 2, station 1 with the issue's 1 % pitch error; CI's
budget); ``benchmarks/commission_study.py`` repeats them over more (docs/calibration.md says how many and what
they gave).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sofast_station.config import load_config

from .commission_stations import draw_assembly, figure_errors, station_file

SEEDS = (1, 2)


@pytest.fixture(scope="module")
def commissioned(tmp_path_factory):
    """Every drawn station: its assembly, the screen and pose steps, the figures before and after."""
    from sofast_station.station.commissioning import run_pose, run_screen

    out = {}
    for seed in SEEDS:
        assembly = draw_assembly(seed)
        if seed == 1:
            assembly["screen_pitch_scale"] = [1.01, 1.01]        # the case: the pitch 1 % off
        path = station_file(tmp_path_factory.mktemp(f"commission-{seed}"), assembly)
        with pytest.MonkeyPatch.context() as mp:                # each station its own records
            mp.setenv("SOFAST_DATA_DIR", str(path.parent / "data"))
            screen = run_screen(load_config(path))
            pose = run_pose(load_config(path))
            station_id = load_config(path).identity["id"]
            # the figures of a noise-free capture: what is left is the geometry's (the calibrations ran on
            # noisy frames); a noisy quarter-resolution capture scatters f by 0.004 % by itself
            errors = figure_errors(path, noise=False)
        out[seed] = {"assembly": assembly, "path": path, "screen": screen, "pose": pose, "errors": errors,
                     "station_id": station_id}
        print(f"\nstation {seed}: {assembly}\n  screen {screen.verdict}: {screen.data.get('headline')}\n  pose "
              f"{pose.verdict}: {pose.data.get('headline')}")
        for k, v in errors.items():
            print(f"  {k}: f_x {100 * v['f_x']:+.4f} %, f_y {100 * v['f_y']:+.4f} %, "
                  f"slope RMS {v['rms_mrad']:+.5f} mrad")
    return out


def test_after_screen_and_pose_the_figures_are_back_to_the_truth(commissioned):
    """On every drawn station: with the stated geometry f is off by more than 0.005 % (a camera 2-5 mm off
    along its axis moves f by 0.0046 %/mm) and the slope RMS by more than 0.003 mrad (a 0.6-1 % pitch error);
    with the records in force both are back within the issue's 0.005 % and 0.005 mrad. The pose's depth is
    known to about 0.25 mm (f to 0.0012 %, k=1) and the screen's pitch to 3e-5 after the pose's refinement,
    so 0.005 % is four standard uncertainties: a failure means a bias, not bad luck."""
    for seed, c in commissioned.items():
        stated, records = c["errors"]["stated"], c["errors"]["records"]
        assert max(abs(stated["f_x"]), abs(stated["f_y"])) > 5e-5, seed
        assert abs(stated["rms_mrad"]) > 0.003, seed
        assert abs(records["f_x"]) < 5e-5 and abs(records["f_y"]) < 5e-5, seed
        assert abs(records["rms_mrad"]) < 0.005, seed


def test_the_screen_record_finds_the_bow_and_the_pitch(commissioned):
    """The screen record's pitch is the twin's (0.6-1 % off station.toml's) within three of its stated standard
    uncertainties, and so is the pose record's refined pitch; a bow of 0.3 mm or more is found (3-D model)
    with its sag within 0.1 mm."""
    for seed, c in commissioned.items():
        rec = json.loads(Path(c["screen"].path).read_text())
        true_scale = c["assembly"]["screen_pitch_scale"][0]
        for axis in ("x", "y"):
            p = rec["pitch_m"][axis]
            assert abs(p["value"] / 0.000275 - true_scale) < 3 * p["std"] / 0.000275, (seed, axis)
        assert abs(rec["pitch_vs_stated_relative"][0]) > 0.005           # found: station.toml is off
        pose = json.loads(Path(c["pose"].path).read_text())
        # both carry the station that made them (issue 43: another station never uses them)
        made_by = {"id": c["station_id"], "name": c["station_id"], "file": str(c["path"].resolve())}
        assert rec["station"] == made_by and pose["station"] == made_by
        assert abs(pose["pitch_scale"][0] - true_scale) < 1e-4
        if c["assembly"]["screen_sag_mm"] >= 0.3:
            assert rec["model"] == "distorted3d"
            assert abs(1e3 * rec["heights"]["sag_m"] - c["assembly"]["screen_sag_mm"]) < 0.1


def test_a_one_percent_pitch_error_is_found(commissioned):
    """Station 1's screen is 1 % larger than station.toml says (the issue's case): the routine's summary
    names station.toml's pitch and the difference, the record holds it within 3 of its standard uncertainties
    (about 6e-4 here: 1 % is 16 of them), and the pose calibration's refined pitch (informative: the analysis
    takes the screen record's) comes within 1.5e-4 of the truth on both axes (measured 0.03e-4 and 1.3e-4)."""
    c = commissioned[1]
    assert "station.toml says 275.000 um (+0.9" in c["screen"].summary or "station.toml says 275.000 um (+1.0" in \
        c["screen"].summary
    rec = json.loads(Path(c["screen"].path).read_text())
    for i, axis in enumerate("xy"):
        rel = rec["pitch_vs_stated_relative"][i]
        assert abs(rel - 0.01) < 3 * rec["pitch_m"][axis]["std"] / 0.000275
    pose = json.loads(Path(c["pose"].path).read_text())
    assert abs(pose["pitch_scale"][0] - 1.01) < 1.5e-4 and abs(pose["pitch_scale"][1] - 1.01) < 1.5e-4, \
        pose["pitch_scale"]


def test_the_budget_takes_the_records_uncertainties(commissioned, monkeypatch):
    """With the records in force the budget's geometry rows are the records' stated standard uncertainties,
    not [uncertainty]'s defaults (0.5 mm, 0.5 mrad, 1e-4), and the measured shape brings its own rows."""
    from sofast_station.measure.pipeline import default_screen

    c = commissioned[1]
    monkeypatch.setenv("SOFAST_DATA_DIR", str(c["path"].parent / "data"))
    config = load_config(c["path"])
    pose = json.loads(Path(c["pose"].path).read_text())
    screen = json.loads(Path(c["screen"].path).read_text())
    u = config.uncertainty
    assert u.screen_translation_mm == pytest.approx(tuple(pose["screen_std"]["translation_mm"]))
    assert u.screen_rotation_mrad == pytest.approx(tuple(pose["screen_std"]["rotation_mrad"]))
    assert u.fixture_translation_mm == pytest.approx(tuple(pose["fixture_std"]["translation_mm"]))
    assert u.screen_pitch_relative == pytest.approx(max(screen["pitch_m"][a]["std"] / screen["pitch_m"][a]["value"]
                                                        for a in "xy"))
    # the record's joint covariance of the screen's and the fixture's poses (mrad, mm), its diagonal the stds
    joint = np.asarray(u.pose_covariance)
    np.testing.assert_allclose(joint, 1e6 * np.asarray(pose["joint_covariance"]["matrix"]))
    np.testing.assert_allclose(np.sqrt(np.diag(joint)), [*pose["screen_std"]["rotation_mrad"],
                               *pose["screen_std"]["translation_mm"], *pose["fixture_std"]["rotation_mrad"],
                               *pose["fixture_std"]["translation_mm"]], rtol=1e-9)
    assert config.geometry.measured_screen.record_id == screen["record_id"]
    model = default_screen(config.geometry)
    assert model.n_modes == len(screen["grid"]["modes_m"]) > 0
    from sofast_station.measure.uncertainty.inputs import screen_shape_inputs
    assert [r.group for r in screen_shape_inputs(model)] == ["screen shape"] * model.n_modes
    # the records name themselves in every result's calibration entry, and the status says so
    assert config.commissioned["pose"]["record_id"] == pose["record_id"]


def test_every_step_ends_with_its_verdict(commissioned):
    for c in commissioned.values():
        for step in (c["screen"], c["pose"]):
            assert step.verdict in ("pass", "warn")
            assert step.summary.splitlines()[-1] == f"verdict: {step.verdict.upper()}"
