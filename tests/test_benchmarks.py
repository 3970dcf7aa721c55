"""The benchmarks run once in quick mode so they cannot rot; their numbers are printed, never asserted.

Every benchmark in benchmarks/ runs here, but opencsp_process.py, which needs OpenCSP (its absence is tested
through vs_opencsp.py). The CPU seconds a test names are its benchmark processes' (``resource`` of the
children), measured on the 2-core development machine at a load average of 5 to 12: the budget, not a check.
"""

import subprocess
import sys

from tests.benchmark_run import _run


def test_analysis_benchmark_quick(repo_root, small_station_toml):
    proc, _ = _run(repo_root, "analysis.py", "--quick", "--config", str(small_station_toml))
    for line in ("camera: 400 x 300", "valid pixels:", "total", "memory: peak resident"):
        assert line in proc.stdout


def test_cycle_benchmark_quick(repo_root, small_station_toml):
    proc, _ = _run(repo_root, "cycle.py", "--quick", "--config", str(small_station_toml))
    for line in ("camera 400 x 300", "the station alone: answers 3 pass", "trigger -> release",
                 "render and image one capture", "first   median", "with a 2-worker batch beside it"):
        assert line in proc.stdout


def test_web_benchmark_quick(repo_root, small_station_toml):
    """benchmarks/web.py: 3 facets without, 3 with the page open in chromium (which setup-env installs; its
    absence fails this test)."""
    from tests.conftest import require_chromium

    require_chromium()
    proc, _ = _run(repo_root, "web.py", "--quick", "--config", str(small_station_toml))
    for line in ("camera 400 x 300", "without the page: cycle median", "with the page   : cycle median",
                 "CPU during the facets: monitor", "each round, with against without", "median cycle: without"):
        assert line in proc.stdout


def test_analysis_benchmark_dump_and_opencsp_paths_quick(repo_root, small_station_toml):
    """The dump and OpenCSP paths of the analysis benchmark, each fit (OpenCSP at native size here)."""
    proc = subprocess.run([sys.executable, str(repo_root / "benchmarks" / "analysis.py"), "--quick", "--config",
                           str(small_station_toml), "--source", "dump", "--fit", "both"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    proc2 = subprocess.run([sys.executable, str(repo_root / "benchmarks" / "analysis.py"), "--quick", "--source",
                            "opencsp", "--opencsp-scale", "1", "--fit", "robust"],
                           capture_output=True, text=True, timeout=600)
    assert proc2.returncode == 0, proc2.stderr
    print(proc.stdout, proc2.stdout)
    for line in ("source dump, plain fit", "source dump, robust fit", "memory: peak resident", "load average"):
        assert line in proc.stdout
    assert "source opencsp, robust fit" in proc2.stdout and "valid pixels: 7," in proc2.stdout


def test_robust_ratio_benchmark_quick(repo_root, small_station_toml):
    """benchmarks/robust_ratio.py: the small station's twin capture, plain and robust in one process."""
    proc, _ = _run(repo_root, "robust_ratio.py", "--quick", "--config", str(small_station_toml), "--source", "twin")
    for line in ("== source twin: 400 x 300", "CPU s per analysis, median of 1", "robust/plain:", "summary:"):
        assert line in proc.stdout


def test_twin_render_benchmark_quick(repo_root, small_station_toml):
    proc, _ = _run(repo_root, "twin_render.py", "--quick", "--config", str(small_station_toml))
    for line in ("camera 400 x 300, 18 frames", "capture over 2 runs: wall", "cpu"):
        assert line in proc.stdout


def test_optics_benchmark_quick(repo_root, small_station_toml):
    proc, _ = _run(repo_root, "optics.py", "--quick", "--config", str(small_station_toml))
    for line in ("20,000 points", "per-facet optical figures: median", "load average", "intercept"):
        assert line in proc.stdout


def test_soak_benchmark_quick(repo_root):
    proc, _ = _run(repo_root, "soak.py", "--quick")
    for line in ("12 cycles in", "growth/100 cycles", "after warm-up", "high-water", "same ids as the journal: True",
                 "temporary files left: 0"):
        assert line in proc.stdout


def test_monitor_under_load_benchmark_quick(repo_root):
    """benchmarks/monitor_under_load.py: the monitor at its default nice beside one spinning process, three
    requests each (about 9 s of CPU, the spinning process's included)."""
    proc, _ = _run(repo_root, "monitor_under_load.py", "--quick", timeout=900)
    for line in ("1 spinning process(es)", "nice  page up, s  OPC UA up, s", "load average before -> after"):
        assert line in proc.stdout
    from sofast_station.web.settings import WebSettings

    assert proc.stdout.strip().splitlines()[-1].split()[0] == str(WebSettings().nice)   # the row of the default


def test_heliostat_benchmark_quick(repo_root):
    """benchmarks/heliostat.py at a quarter of the resolution: one facet, the 2x2 and the 5x5 heliostats."""
    proc, _ = _run(repo_root, "heliostat.py", "--quick", timeout=900)
    for line in ("single facet: dish-5.33, camera 400 x 300", "heliostat heliostat-2x2: 4 facets",
                 "heliostat heliostat-5x5: 25 facets", "2x2 against one facet:", "load average after"):
        assert line in proc.stdout


def test_commands_benchmark_quick(repo_root):
    """benchmarks/commands.py: --help and the usage errors, one run each (its table and the load it ran at;
    the heavy groups are the next test's, in -m slow: each of their commands has its own tests)."""
    proc, _ = _run(repo_root, "commands.py", "--quick", "--only", "help", "--only", "usage error")
    for line in ("sofast-station --help", "inspect --config nowhere.toml", "| command | wall s", "load average after"):
        assert line in proc.stdout


def test_commands_benchmark_reprocess_and_import_quick(repo_root):
    """benchmarks/commands.py: reprocess and import-opencsp (native), one run each on the small station
    (report's journal is left out: the slowest setup)."""
    proc, _ = _run(repo_root, "commands.py", "--quick", "--only", "reprocess", "--only", "import-opencsp")
    for line in ("reprocess DUMP (cache cold)", "import-opencsp --robust, native (cache warm)", "| command | wall s"):
        assert line in proc.stdout


def test_vs_opencsp_benchmark_says_what_is_missing_and_runs_its_pairs(repo_root, tmp_path):
    """benchmarks/vs_opencsp.py needs an environment with OpenCSP, which CI does not install: without one it
    says so and what to do; with /bin/echo standing in for OpenCSP's python (it prints its arguments and
    exits 0) the driver runs our import-opencsp against it in turn and prints its table."""
    script = str(repo_root / "benchmarks" / "vs_opencsp.py")
    for python, said in ((sys.executable, "cannot run OpenCSP's processing: OpenCSP is not importable"),
                         (str(tmp_path / "nowhere" / "python"), "no such interpreter")):
        proc = subprocess.run([sys.executable, script, "--opencsp-python", python], capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode != 0 and said in proc.stderr, proc.stderr[-1000:]
        assert "Traceback" not in proc.stderr
    proc = subprocess.run([sys.executable, script, "--opencsp-python", "/bin/echo", "--datasets", "robust",
                           "--sizes", "native", "--runs", "1"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    print(proc.stdout)
    for line in ("robust native: pair 1/1 done", "| robust | native | ", "ours   f x 120.3", "load after"):
        assert line in proc.stdout
    # every dataset has its command (issue 48 item 7); without OpenCSP only ours runs, and the table says so
    alone = subprocess.run([sys.executable, script, "--datasets", "plano,undefined,split_facet", "--sizes", "native",
                            "--runs", "1"], capture_output=True, text=True, timeout=600)
    assert alone.returncode == 0, alone.stdout[-2000:] + alone.stderr[-2000:]
    for line in ("OpenCSP not run: give --opencsp-python", "| plano | native | ", "| undefined | native | ",
                 "| split_facet | native | ", "| not run | not run |"):
        assert line in alone.stdout
    bad = subprocess.run([sys.executable, script, "--opencsp-python", "/bin/echo", "--sizes", "huge"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "neither 'native' nor an upsampling" in bad.stderr
