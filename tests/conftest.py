"""Shared fixtures: nothing here writes into the source tree (runtime data goes to tmp_path)."""

from __future__ import annotations

import importlib
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: Debian's chromium, which the page's browser tests drive through Playwright (setup-env test installs it).
CHROMIUM = "/usr/bin/chromium"


def require(module: str):
    """Import a test dependency: when it is missing the suite FAILS (a collection error naming it and how
    to install it), never skips (CI has what setup-env installs; a skipped test proves nothing)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        pytest.fail(f"the test dependency {module} is missing ({exc}): run ./setup-env test", pytrace=False)


def require_chromium() -> str:
    """Debian's chromium for the browser tests, or a failure saying how to install it."""
    if not (os.path.exists(CHROMIUM) and os.access(CHROMIUM, os.X_OK)):
        pytest.fail(f"the test dependency chromium is missing ({CHROMIUM}): run ./setup-env test "
                    "(it installs Debian's chromium)", pytrace=False)
    return CHROMIUM


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return ROOT


#: The user's own data folder (files.DEFAULT_DATA_DIR under the real home), which no test may read or write.
USER_DATA = Path("~/sofast-station-data").expanduser()


def _listing(folder: Path) -> dict:
    """{path: (size, mtime_ns)} of everything under *folder* ({} when it does not exist)."""
    out = {}
    for top, dirs, files in os.walk(folder):
        for name in dirs + files:
            try:
                st = os.lstat(os.path.join(top, name))
            except OSError:
                continue
            out[os.path.join(top, name)] = (st.st_size, st.st_mtime_ns)
    return out


@pytest.fixture(scope="session", autouse=True)
def _never_the_users_data():
    """Fail any test that reads or writes the user's ~/sofast-station-data (issue 43).

    Every station resolves its data folder through ``files.resolve_data_dir``; here it raises when the folder
    it resolves lies in the user's (a module or session fixture that loads a station file before the
    per-test ``SOFAST_DATA_DIR`` below is set, or a station file whose data_dir is the default). Session
    scoped, so it is in place before any module fixture runs. Commands run as subprocesses resolve in their
    own process: what they write there is caught by comparing the folder's listing (sizes, mtimes) at the
    session's end with its start.
    """
    from sofast_station import files

    resolve = files.resolve_data_dir

    def guarded(value, base):
        path = resolve(value, base)
        if path.absolute() == USER_DATA or USER_DATA in path.absolute().parents:
            pytest.fail(f"a test resolved the user's data folder {path} (data_dir {str(value)!r}): a station file "
                        "loaded outside a test's SOFAST_DATA_DIR (a module fixture?) or with the default data_dir; "
                        "give it a tmp_path data_dir or set SOFAST_DATA_DIR", pytrace=True)
        return path

    before = _listing(USER_DATA)
    files.resolve_data_dir = guarded
    try:
        yield
    finally:
        files.resolve_data_dir = resolve
    after = _listing(USER_DATA)
    if after != before:
        changed = sorted(set(after.items()) ^ set(before.items()))
        pytest.fail(f"the test session changed the user's data folder {USER_DATA}: {len(changed)} entries, e.g. "
                    f"{changed[0][0]}", pytrace=False)


@pytest.fixture(autouse=True)
def _data_dir(tmp_path, monkeypatch):
    """Every test's station data (journal, results, records) goes to its own temporary folder."""
    monkeypatch.setenv("SOFAST_DATA_DIR", str(tmp_path / "station-data"))
    # A cycle deadline far beyond any facet's time on a loaded machine, where a test does not set one on
    # purpose: the tests do not depend on the machine's speed (issue 11).
    monkeypatch.setenv("SOFAST_DEFAULT_DEADLINE_S", "120")
    # `batch` and `report` lower their own process's priority (issue 11). Called in-process from a test,
    # that would renice the whole pytest run for every later test; tests/test_priority.py checks it apart.
    monkeypatch.setenv("SOFAST_NICE", "0")


def load_station(path, data_dir, **kwargs):
    """``load_config(path)`` with the station's data in *data_dir* (``SOFAST_DATA_DIR`` set while it loads, so
    the records it reads are that folder's): for a module or session fixture, which runs before the per-test
    ``SOFAST_DATA_DIR`` of :func:`_data_dir` is set."""
    from sofast_station.config import load_config

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SOFAST_DATA_DIR", str(data_dir))
        return load_config(path, **kwargs)


#: The small simulated dish station (400 x 300 camera) as a str.format template of {data_dir}, {facet} and
#: {radiometric}; the benchmarks fill in the same shared template (fixtures/stations/small_dish.toml.in).
SMALL_STATION = (ROOT / "fixtures/stations/small_dish.toml.in").read_text().format(
    name="Small simulated dish station (tests)", data_dir_line='data_dir = "{data_dir}"\n', facet="{facet}",
    analysis="", radiometric="{radiometric}", twist="0.1")


@pytest.fixture
def small_station_toml(tmp_path) -> Path:
    """A quarter-resolution simulated dish station for mechanics tests (CLI, configuration)."""
    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    return path


# The camera tests' --camera-serial / --camera-kind / --camera-shape options (real hardware, opt-in)
# must be known wherever pytest starts.
from tests.devices.cameras.conftest import pytest_addoption  # noqa: E402,F401


#: Long tests left out of the README's test command (CI: it must stay under 15 minutes on two cores) and run
#: with ``pytest -m slow`` (before a release: ``pytest -m "slow or not slow"`` runs everything). Each is a long
#: run of a claim that a test or a benchmark's quick mode in the default set also checks, named beside it.
LONG_TESTS = {
    # the line's robustness: the kill campaign's and the soak's quick modes run the real `run` command
    "tests/station/test_robustness.py::test_a_late_result_keeps_its_figures_its_dump_and_the_timeout_as_its_cycle_time":
        "test_worker_load.py (late results kept), soak --quick",
    "tests/station/test_robustness.py::test_a_killed_worker_is_replaced_and_the_line_goes_on": "kill_campaign --quick",
    "tests/station/test_robustness.py::test_the_stations_children_die_with_it_and_a_second_run_is_refused":
        "kill_campaign --quick",
    "tests/station/test_standby.py::test_the_facet_after_a_hung_analysis_is_measured_while_the_hung_one_is_still_in_"
    "its_grace": "test_standby.py's hung-worker rerun, test_worker_load.py",
    "tests/reanalysis/test_batch.py::test_a_killed_batch_of_50_resumes_without_redoing_or_losing_any":
        "test_batch.py's resume tests",
    "tests/reanalysis/test_batch.py::test_dask_cluster_gives_the_same_results_as_the_local_run": "test_batch.py",
    "tests/station/test_robustness.py::test_a_worker_dead_before_the_analysis_began_costs_the_facet_nothing":
        "kill_campaign --quick (the worker killed)",
    "tests/station/test_robustness.py::test_a_killed_archiver_is_replaced_and_nothing_is_lost":
        "kill_campaign --quick (the archiver killed)",
    "tests/station/test_robustness.py::test_the_archiver_starts_afresh_past_its_memory_bound":
        "archiver_memory --rows 60 (test_benchmarks_studies.py)",
    "tests/web/test_run_serve.py::test_run_serve_starts_and_stops_the_page":
        "test_verdict_box.py and test_monitor_stop.py (serve's page in chromium, and its end as run --serve ends it)",
    "tests/reanalysis/test_reprocess.py::test_alignment_point_changes_exactly_the_figures_that_depend_on_it":
        "test_reprocess.py's design focal length override",
    "tests/calibrate/test_radiometric.py::test_inspection_after_calibration_meets_the_noisy_repeat_tolerances":
        "commission_coverage --quick (calibrate, then inspect)",
    # the line's twenty facets: the soak's and the kill campaign's quick runs run the real `run` command
    "tests/station/test_run.py::test_twenty_answers_and_the_line_goes_on": "soak --quick, kill_campaign --quick",
    "tests/station/test_run.py::test_good_facets_meet_the_core_tolerances": "test_facets.py, test_population.py",
    "tests/station/test_run.py::test_journal_workbook_and_dumps": "soak --quick (journal, dumps), tests/archive",
    "tests/station/test_run.py::test_a_dump_reprocesses_to_exactly_its_archived_figures":
        "test_front_doors.py, test_reprocess.py",
    # accuracy and coverage over repeats: the population's both-ends coverage test covers them in CI
    "tests/station/test_accuracy.py::test_ten_noisy_repeats": "test_population.py (both ends)",
    "tests/station/test_capture_causes.py::test_shipped_heliostat_station_fails_on_focal_power_not_invalid_for_seeds_"
    "1_to_10": "test_capture_causes.py's other seeds",
    "tests/station/test_population.py::test_blurred_and_defocused_edges_leave_the_fit_figures_and_slope_rms_covered":
        "test_population.py's edge models",
    "tests/station/test_heliostat_accuracy.py::test_canting_within_0_05_mrad_of_truth_over_a_population":
        "test_heliostat_station.py (canting against truth)",
    "tests/station/test_heliostat_accuracy.py::test_canting_is_covered_by_its_u_when_the_station_is_not_known_exactly":
        "test_heliostat_station.py",
    "tests/station/test_population_line.py::test_the_simulated_line_makes_different_facets_and_its_drift_raises_"
    "the_alarm": "test_drift.py (the drift alarm on the line)",
    "tests/archive/test_workbook.py::test_the_memory_of_a_save_does_not_grow_with_the_rows_of_its_part":
        "archiver_memory --rows 60 (test_benchmarks_studies.py)",
    "tests/station/test_facets.py::test_gore_misplaced_in_the_fixture": "test_population.py (drawn placements)",
    # the plant's view: the web benchmark's quick run follows three facets with the page open in chromium, and
    # test_opcua.py runs docs/opcua.md's client against the server
    "tests/web/test_page.py::test_the_page_follows_the_line":
        "test_page.py's other test on the same line, test_verdict_box.py (the page in chromium)",
    "tests/web/test_opcua.py::test_opcua_client_sees_the_tree_and_the_verdict_change": "test_opcua.py's docs example",
    # calibrations: the commissioning benchmarks' quick modes run `calibrate commission` on drawn stations
    "tests/calibrate/test_commission.py": "commission_coverage --quick",
    "tests/calibrate/test_store.py::test_room_light_change_mid_run_marks_the_rows_or_refuses_the_facets":
        "test_store.py's staleness tests",
    "tests/calibrate/test_camera.py::test_charuco_images": "test_camera_photos.py",
    # benchmarks' quick runs whose harness the default set's benchmark tests share and whose work other tests do
    "tests/test_benchmarks.py::test_commands_benchmark_reprocess_and_import_quick":
        "test_commands_benchmark_quick (the harness), test_reprocess.py, test_opencsp.py (the commands)",
    "tests/test_benchmarks.py::test_heliostat_benchmark_quick":
        "test_heliostat_station.py (a heliostat measured on the line), test_line_prescription.py (the 5x5)",
    "tests/test_benchmarks.py::test_monitor_under_load_benchmark_quick":
        "test_monitor_stop.py (the monitor starved and stopped), test_verdict_box.py (its page)",
    "tests/test_benchmarks.py::test_robust_ratio_benchmark_quick":
        "test_analysis_benchmark_quick (the harness), test_fit.py (plain and robust fits)",
    "tests/test_benchmarks.py::test_analysis_benchmark_dump_and_opencsp_paths_quick":
        "test_analysis_benchmark_quick (the harness), test_reprocess.py, test_opencsp.py (the dump and OpenCSP paths)",
    "tests/test_benchmarks.py::test_vs_opencsp_benchmark_says_what_is_missing_and_runs_its_pairs":
        "tests/interop (every OpenCSP dataset through import-opencsp)",
    "tests/test_benchmarks_studies.py::test_fixed_pattern_benchmark_quick":
        "test_fixed_job.py, test_opencsp_fixed.py (both methods' analyses of the same facet)",
    "tests/test_benchmarks_studies.py::test_population_benchmark_quick": "test_population.py (the same study)",
    "tests/test_benchmarks_studies.py::test_uncertainty_coverage_benchmark_quick":
        "test_population.py (coverage from both ends)",
    "tests/test_benchmarks_studies.py::test_geometry_sensitivity_benchmark": "test_uncertainty.py (the geometry rows)",
    "tests/test_benchmarks_studies.py::test_field_benchmark_quick": "tests/field (each field command on the twin)",
    "tests/test_benchmarks.py::test_web_benchmark_quick":
        "test_commands_benchmark_quick (the harness), test_verdict_box.py (the page in chromium), test_page.py",
    "tests/test_benchmarks_studies.py::test_camera_calibration_benchmark_quick":
        "test_camera_photos.py and test_camera.py (calibrate camera on rendered photographs)",
    "tests/test_benchmarks.py::test_cycle_benchmark_quick":
        "test_commands_benchmark_quick (the harness), kill_campaign --quick and test_run.py (the line's cycles)",
    "tests/test_benchmarks_studies.py::test_commission_study_benchmark_quick":
        "commission_coverage --quick (`calibrate commission` on a drawn station, then its facets measured)",
    # a parameter of a test whose other parameters stay in the default set
    "tests/station/test_heliostat_far.py::test_focal_length_within_0_002_percent_of_truth[3]": "its seed 9",
    "tests/station/test_heliostat_far.py::test_focal_length_within_0_002_percent_of_truth[17]": "its seed 9",
    "tests/station/test_corners_on_twin.py::test_gore_twist_at_its_own_resolution_on_a_coarse_supersampled_edge"
    "[3.0]": "its turn of -8 mrad",
    # 2026-12-07: this machine runs the default set in 11:42-12:13 (the day before's, 8:39), and setup-env in 2:37
    "tests/station/test_heliostat_near.py::test_focal_length_against_truth_stage_by_stage[2]": "its station 10",
    # 2026-12-07 afternoon: the default set took 12:40 (setup-env's kernel build 69 s, 48 s on a day the set took
    # 8:25), which put a fresh clone's CI at 14:56; these went to the long set
    "tests/station/test_heliostat_near.py::test_focal_length_against_truth_stage_by_stage[6]": "its station 10",
    "tests/station/test_facets.py::test_noise_free_against_truth[heliostat]":
        "test_heliostat_far.py and test_heliostat_near.py (the heliostat facet against truth, stage by stage)",
    "tests/station/test_facets.py::test_noise_free_against_truth[gore]":
        "test_boresight_all_points.py (the gore's captures against truth), its dish",
    "tests/reanalysis/test_report.py::test_report_writes_a_png_per_dump":
        "test_slope_error_maps_show_the_measured_pixels_and_the_reported_figures (the report of a dump), "
        "test_opencsp.py::test_report_draws_maps_of_an_opencsp_measurement",
    "tests/calibrate/test_pose_covariance.py::test_joint_covariance_predicts_the_scatter_of_the_seated_facets_tilt":
        "test_the_record_states_the_joint_covariance_and_older_records_load (the record), "
        "commission_coverage --quick (the commissioned figures covered by their U)",
    "tests/test_benchmarks.py::test_soak_benchmark_quick":
        "kill_campaign --quick and test_run.py (the line run, killed and restarted)",
    # and, the machine slower still (a fresh clone's CI 14:52 with the six above moved), these
    "tests/measure/test_noise_floor.py::test_the_noise_floor_is_the_slope_noise_the_points_carry_within_its_u":
        "test_noise_corrected.py, test_population.py (the noise-corrected slope RMS covered by its U)",
    "tests/measure/test_heights.py::test_centred_cells_leave_no_large_scale_height_error_on_a_pixel_lattice":
        "test_kernels.py (height_grid bit for bit against its numpy steps), test_heliostat_far.py (f at 10 m)",
    "tests/station/test_methods_study.py::test_both_methods_measure_the_same_captures":
        "test_fixed_job.py and test_opencsp_fixed.py (both methods on the same facet)",
    "tests/field/test_line_prescription.py::test_the_line_judges_the_heliostat_against_its_own_prescription":
        "its other tests (the prescription chosen and kept), tests/field/test_canting.py",
    "tests/station/test_heliostat_blurred.py::test_a_blurred_heliostats_focal_length_with_and_without_the_blurs_shift"
    "[42]": "its station 34",
    "tests/station/test_heliostat_blurred.py::"
    "test_the_sharpened_fit_takes_most_of_the_blurs_smoothing_off_f_and_the_budget_carries_the_rest":
        "test_deblur.py (the sharpening on an independent image model), test_sharpening_row.py (the row), and "
        "the first test's station 34 (the pipeline's path through it)",
    "tests/station/test_dark_rim.py::test_a_dark_rim_declared_dark_puts_the_corners_on_the_outline[heliostat-2]":
        "its dish",
    "tests/station/test_dark_rim.py::test_a_rim_declared_dark_that_shows_the_screen_is_named_and_put_midway"
    "[heliostat-2]": "its dish",
    "tests/station/test_corners_on_twin.py::test_corners_within_a_tenth_of_a_pixel[blurred-heliostat]":
        "its sharp heliostat, its blurred dish and gore",
    "tests/station/test_standby.py::test_a_hung_worker_costs_its_facet_a_rerun_on_the_standby_not_a_timeout":
        "test_worker_load.py (a hung rerun gives the first answer)",
    "tests/station/test_robustness.py::test_a_killed_stations_leftovers_are_recovered":
        "kill_campaign --quick (the station killed and restarted: no temp files, no orphan spools)",
}


#: The longest test files, longest first (each 35-100 s of a worker in the default run, 2026-12-06). The run hands whole
#: files to its workers in collection order (``--dist loadfile``), so these go first: started last, the
#: benchmarks' quick runs left one worker running them alone for minutes while the other had finished
#: (longest-processing-time-first scheduling). Only the order changes, never what runs.
LONGEST_FILES = ("tests/station/test_population.py", "tests/test_benchmarks_studies.py",
                 "tests/reanalysis/test_reprocess.py", "tests/station/test_heliostat_station.py",
                 "tests/station/test_corners_on_twin.py", "tests/station/test_robustness.py",
                 "tests/test_benchmarks.py", "tests/reanalysis/test_compiled_kernels.py",
                 "tests/interop/test_opencsp.py", "tests/reanalysis/test_batch.py",
                 "tests/cli/test_user_mistakes.py")


def pytest_collection_modifyitems(config, items):
    for item in items:
        nodeid = item.nodeid.split("[")[0]
        if item.nodeid in LONG_TESTS or nodeid in LONG_TESTS or nodeid.split("::")[0] in LONG_TESTS:
            item.add_marker(pytest.mark.slow)
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    order = {id(item): i for i, item in enumerate(items)}
    items.sort(key=lambda item: (rank.get(item.nodeid.split("::")[0], len(rank)), order[id(item)]))
