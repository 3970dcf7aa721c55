"""The benchmarks of the studies, the calibrations and the line's robustness, in quick mode (the rest:
tests/test_benchmarks.py, whose docstring says what these tests are; split in two so that the two test
processes share them)."""

import json
import math
import re

from tests.benchmark_run import _numbers, _run


def test_archiver_memory_benchmark_quick(repo_root, tmp_path):
    """benchmarks/archiver_memory.py at tiny sizes: 60 full-width rows, 10 a pass, into parts of 30 rows (so a
    new part is started and a pass writes onto a nearly full one), memory sampled every 10 rows. About 2 s CPU."""
    out = tmp_path / "figures.json"
    proc, _ = _run(repo_root, "archiver_memory.py", "--rows", "60", "--per-save", "10", "--part-rows", "30",
                   "--sample-every", "10", "--warmup", "20", "--json", str(out))
    assert "archiver memory: 60 rows of 236 columns, 10 per pass, 30 per part" in proc.stdout
    for line in ("growth per 100 rows", "after the warm-up of 20 rows", "a pass (10 rows): wall median",
                 "onto a nearly full part (>= 10 rows) median", "load average"):
        assert line in proc.stdout
    assert len([ln for ln in proc.stdout.splitlines() if re.match(r"\s+\d+ rows, .* RSS", ln)]) == 6
    figures = json.loads(out.read_text())
    assert figures["rows"] == 60 and len(figures["samples"]) == 6
    for key in ("rss_first_mb", "rss_max_mb", "growth_mb_per_100_rows_after_warmup", "pass_cpu_s_median",
                "pass_cpu_s_full_part_median"):
        assert math.isfinite(figures[key]), key


def test_commission_study_benchmark_quick(repo_root, tmp_path):
    """benchmarks/commission_study.py --quick: one drawn station (seed 1), calibrate screen from 3 views and
    calibrate pose from 2 placements, then its facet measured three ways. About 17 s CPU (the routines' own
    cost: 7 s the screen, 3.5 s the pose, 2.5 s the three analyses, the rest starting up)."""
    proc, _ = _run(repo_root, "commission_study.py", "--quick", "--out", str(tmp_path))
    lines = proc.stdout.splitlines()
    head = next(ln for ln in lines if ln.lstrip().startswith("seed"))
    for heading in ("sag mm", "pitch %", "stated: fx %", "records: fx %", "true: fx %", "model", "pitch found %"):
        assert heading in head
    row = next(ln for ln in lines if re.match(r"\s+1 ", ln))
    assert len(_numbers(row)) >= 15 and "refused" not in row
    assert "1 stations (0 refused): with the records the worst f error is" in proc.stdout
    study = json.loads((tmp_path / "study.json").read_text())
    assert [r["seed"] for r in study] == [1] and set(study[0]["errors"]) == {"stated", "records", "true"}
    assert all(math.isfinite(v) for e in study[0]["errors"].values() for v in e.values())


def test_commission_coverage_benchmark_quick(repo_root, tmp_path):
    """benchmarks/commission_coverage.py --quick: one drawn station (seed 1) commissioned with noise (screen from 3
    views, pose from 2 placements), then two captures measured with its records in force against the twin's
    truth; the records' fixture against the truth and the coverage table from both ends. About 15 s CPU."""
    proc, _ = _run(repo_root, "commission_coverage.py", "--quick", "--out", str(tmp_path))
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("station 1: fixture off the truth by"))
    assert len(_numbers(line)) >= 16 and "refused" not in line
    assert "2 captures on 1 commissioned stations" in proc.stdout
    assert "coverage and RMS of error / (U / 2) per figure" in proc.stdout
    saved = json.loads((tmp_path / "commission-coverage.json").read_text())
    assert len(saved["cases"]) == 2 and [f["seed"] for f in saved["fixtures"]] == [1]


def test_geometry_sensitivity_benchmark(repo_root, small_station_toml):
    """benchmarks/geometry_sensitivity.py as it is (its default is the tests' 400 x 300 station): one capture,
    then each of the twelve moves of the screen or the camera. About 3 s CPU."""
    proc, _ = _run(repo_root, "geometry_sensitivity.py", "--config", str(small_station_toml))
    assert re.search(r"camera 400 x 300, f_x \d+\.\d+ m, f_y \d+\.\d+ m", proc.stdout)
    lines = proc.stdout.splitlines()
    head = next(ln for ln in lines if ln.startswith("moved by 1 mrad / 1 mm"))
    for heading in ("df_x %", "df_y %", "dRMS mrad", "dtwist mrad/m"):
        assert heading in head
    for what in ("screen", "camera"):
        for how in ("about", "along"):
            for axis in "xyz":
                row = next(ln for ln in lines if ln.startswith(f"{what} {how} {axis} "))
                assert len(_numbers(row.split(axis, 1)[1])) == 4, row


def test_kill_campaign_benchmark_quick(repo_root):
    """benchmarks/kill_campaign.py --quick: the real ``run`` command killed three times, the archiver, the
    worker and the station once each, restarted, stopped with SIGTERM, and its archive checked. About 19 s CPU
    (two station starts with their workers and archivers, and a dozen facets)."""
    proc, _ = _run(repo_root, "kill_campaign.py", "--quick")
    assert "kills: {" in proc.stdout
    kills = re.search(r"kills: \{'station': (\d+), 'worker': (\d+), 'archiver': (\d+)\}; (\d+) facets answered",
                      proc.stdout)
    assert kills and kills.groups()[:3] == ("1", "1", "1") and int(kills.group(4)) >= 5, proc.stdout
    assert len(re.findall(r"kill +\d at +\d+ s: (?:station|worker|archiver)", proc.stdout)) == 3
    for line in ("journal_unique: True", "workbook_unique: True", "workbook_equals_journal: True", "dumps_bad: []",
                 "temp_files: []", "orphan_spools: []", "problems: none"):
        assert line in proc.stdout


def test_population_benchmark_quick(repo_root, tmp_path):
    """benchmarks/population.py at tiny sizes: one dish station, one good capture and the four planted faults,
    its table, JSON and picture; then ``--merge`` of that run (no analysis). About 7 s CPU and 1.5 s."""
    proc, _ = _run(repo_root, "population.py", "--captures", "1", "--per-station", "1", "--kinds", "dish",
                   "--edges", "area", "--out", str(tmp_path))
    assert "population study, seed 0: 1 good captures on 1 stations (1 each; kinds dish; edge models area)" in \
        proc.stdout
    for line in ("false INVALID / refusal on good captures:", "planted faults caught (refused or invalid):",
                 "validity checks on the good captures", "coverage and RMS of error / (U / 2) per figure",
                 "corners against the twin's true corner pixels per edge model"):
        assert line in proc.stdout
    for fault in ("swapped", "gamma", "obstruction", "misplaced"):
        assert re.search(rf"^  {fault} +\d of 1 ", proc.stdout, flags=re.M), fault
    focal = next(ln for ln in proc.stdout.splitlines() if ln.strip().startswith("focal_length_x_m"))
    assert len(_numbers(focal)) >= 4
    run = tmp_path / "population-0-1.json"
    assert run.exists() and (tmp_path / "population-0-1.png").stat().st_size > 0
    assert json.loads(run.read_text())["summary"]["good"]["n"] == 1
    merged, _ = _run(repo_root, "population.py", "--merge", str(run))
    assert "1 runs (seeds 0; 1 stations)" in merged.stdout and "planted faults caught" in merged.stdout


def test_uncertainty_coverage_benchmark_quick(repo_root, tmp_path):
    """benchmarks/uncertainty_coverage.py at tiny sizes: two captures of the 400 x 300 dish with the geometry
    drawn, each analysed twice (--split-brightness); then ``--merge`` of that file 17 times over with
    ``--explain``, so that the regression on the drawn inputs has the 33 captures it needs (34 copies of 2
    captures: its figures mean nothing here, it only runs). About 5 s CPU and 1 s."""
    out = tmp_path / "coverage.json"
    proc, _ = _run(repo_root, "uncertainty_coverage.py", "--captures", "2", "--split-brightness", "--out", str(out))
    assert re.search(r"station: .*, camera 400 x 300, facet .*; 2 captures", proc.stdout)
    lines = proc.stdout.splitlines()
    head = next(ln for ln in lines if ln.startswith("figure") and "coverage" in ln)
    for heading in ("median U", "mean err", "std err", "U/std", "U/rms"):
        assert heading in head
    for figure in ("focal_length_x_m", "twist_mrad_per_m", "noise-corrected slope_rms_mrad.design.magnitude"):
        row = next(ln for ln in lines if ln.startswith(figure + " "))
        assert len(_numbers(row.split("%")[0].replace(figure, ""))) == 1, row     # the coverage, in %
    assert "per capture:" in proc.stdout and "frame-to-frame brightness" in proc.stdout
    assert len(json.loads(out.read_text())["captures"]) == 2
    merged, _ = _run(repo_root, "uncertainty_coverage.py", "--merge", *[str(out)] * 17, "--explain")
    assert "34 captures from 17 file(s)" in merged.stdout
    assert "errors against the drawn inputs (least squares over 34 captures" in merged.stdout
    assert "residual std" in merged.stdout


def test_marks_benchmark_quick(repo_root):
    """benchmarks/marks.py: the check's cost on a 400 x 300 station, 5 good cycles, every camera move."""
    proc, _ = _run(repo_root, "marks.py", "--quick")
    for line in ("== cost of the check: camera 400 x 300", "wall ms per check", "good cycles: 5, false alarms",
                 "turn 0.2 mrad about x", "shift 1 mm along y"):
        assert line in proc.stdout


def test_placement_tilt_benchmark_quick(repo_root):
    """benchmarks/placement_tilt.py: 2 captures of the ideal 400 x 300 dish, the corners' and the slopes' tilt."""
    proc, _ = _run(repo_root, "placement_tilt.py", "--quick")
    for line in ("== ideal 400 x 300 dish: 2 captures", "about x: corners", "slopes", "own boresight"):
        assert line in proc.stdout


def test_display_check_benchmark_quick(repo_root):
    """benchmarks/display_check.py: the display's self-test's cost at 1600 x 1200 and 400 x 300."""
    proc, _ = _run(repo_root, "display_check.py", "--quick")
    for line in ("== the display's self-test", "camera 1600 x 1200: 20 checks", "camera 400 x 300: 20 checks"):
        assert line in proc.stdout


def test_camera_calibration_benchmark_quick(repo_root):
    """benchmarks/camera_calibration.py: five half-size photographs, the command once."""
    proc, _ = _run(repo_root, "camera_calibration.py", "--quick")
    for line in ("5 photographs of an 18 x 23 inner-corner board, 813 x 618 px", "whole command: wall", "found: ",
                 "images used", "load average after"):
        assert line in proc.stdout


def test_fixed_pattern_benchmark_quick(repo_root):
    """benchmarks/fixed_pattern.py: OpenCSP's fixed capture and fringe capture (native), the heliostat twin at a
    quarter of its resolution, each facet measured both ways (issue 42 item 6)."""
    proc, _ = _run(repo_root, "fixed_pattern.py", "--quick")
    for line in ("opencsp  fixed", "opencsp  fringe", "twin     fixed", "twin     fringe", "fixed over fringe",
                 "per round"):
        assert line in proc.stdout


def test_field_benchmark_quick(repo_root):
    """benchmarks/field.py: a heliostat's canting from 6 twin photos of 640 x 480 and one orientation."""
    proc, _ = _run(repo_root, "field.py", "--quick")
    for line in ("camera 640 x 480", "canting from", "the issue: under a minute", "orientation from one photo",
                 "spot on the target"):
        assert line in proc.stdout
