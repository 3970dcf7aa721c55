"""Issue 7, item 2: `sofast-station batch` over many dumps, resumable, locally and on Dask."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from openpyxl import load_workbook

from sofast_station.reanalysis.batch import BatchError, read_result, run_batch
from sofast_station.reanalysis.cli import ProgressBar
from sofast_station.reanalysis.cli import main as cli_main
from tests.conftest import ROOT
from tests.bad_dumps import make_bad_files
from tests.reanalysis.conftest import copy_dump

#: Keys of a result that depend on when, where and how fast it was computed.
VOLATILE = {"timings_s"}
VOLATILE_REPROCESS = {"at", "host", "pid", "summary"}


def _stable(obj: dict) -> dict:
    out = {k: v for k, v in obj.items() if k not in VOLATILE}
    if "reprocess" in out:
        out["reprocess"] = {k: v for k, v in out["reprocess"].items() if k not in VOLATILE_REPROCESS}
    return out


def _copies(station_dumps, folder: Path, n: int) -> list[Path]:
    """*n* dumps in *folder*: copies of the three good dumps under distinct names."""
    out = []
    for i in range(n):
        src = station_dumps.good[i % len(station_dumps.good)]
        out.append(copy_dump(src, folder / f"day{i // 20}" / f"{src.stem}-copy{i:03d}.h5"))
    return out


def _env() -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("SOFAST_FAULT", None)
    return env


def test_a_killed_batch_of_50_resumes_without_redoing_or_losing_any(station_dumps, tmp_path):
    src = tmp_path / "dumps"
    _copies(station_dumps, src, 50)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "sofast_station.reanalysis.cli", "batch", str(src), "--out", str(out),
           "--workers", "2", "--no-progress"]
    # the parent and its two workers in a process group of their own, killed together
    proc = subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    results = out / "results"
    # Killed once some results exist, whatever the machine's speed (each dump's re-analysis also computes
    # its uncertainty's sensitivities: a few seconds on a busy machine).
    deadline = time.monotonic() + 600
    try:
        while time.monotonic() < deadline:
            n = len(list(results.glob("*.json"))) if results.is_dir() else 0
            if n >= 8 or proc.poll() is not None:
                break
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL, "the batch finished before it could be killed"
    first = {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in results.glob("*.json")}
    assert 8 <= len(first) < 50, len(first)
    for p in results.glob("*.json"):           # no half-written result under a result's name
        assert read_result(p) is not None, p
    assert not (out / "summary.csv").exists()  # the killed run never got to its summary

    proc = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert f"50 dump(s): {50 - len(first)} reprocessed now, {len(first)} already done" in proc.stdout
    assert "50 reproduced the archive exactly, 0 differ from it, 0 failed" in proc.stdout
    final = {p.name: p for p in results.glob("*.json")}
    assert len(final) == 50
    for name, (ino, mtime) in first.items():   # finished results were not redone
        st = final[name].stat()
        assert (st.st_ino, st.st_mtime_ns) == (ino, mtime), name
    for p in final.values():
        obj = read_result(p)
        assert obj is not None and obj["status"] == "ok" and obj["reprocess"]["exact"] is True, p
    assert not list(results.glob(".*.tmp"))    # temporary files of the killed run were cleaned up
    lines = (out / "summary.csv").read_text().splitlines()
    assert len(lines) == 51 and lines[0].startswith("dump,result,status,error")
    ws = load_workbook(out / "summary.xlsx", read_only=True).worksheets[0]
    assert sum(1 for _ in ws.iter_rows(values_only=True)) == 51


def test_failing_dumps_are_reported_and_the_batch_goes_on(station_dumps, tmp_path):
    src = tmp_path / "dumps"
    good = _copies(station_dumps, src, 2)
    bad = make_bad_files(src / "bad", station_dumps.good[0])
    seen = []
    summary = run_batch([src], tmp_path / "out", workers=2, progress=lambda *a: seen.append(a))
    assert summary.total == len(good) + len(bad) and summary.reprocessed == summary.total
    assert summary.exact == 2 and len(summary.failed) == len(bad)
    errors = dict(summary.failed)
    for path, problem in bad.items():
        assert str(path) in errors[str(path)] and problem in errors[str(path)], errors[str(path)]
    assert seen[0] == (0, summary.total, 0, "") and seen[-1][:3] == (summary.total, summary.total, len(bad))
    ws = load_workbook(summary.xlsx_path, read_only=True).worksheets[0]
    it = ws.iter_rows(values_only=True)
    header = next(it)
    rows = {r[header.index("dump")]: dict(zip(header, r)) for r in it}
    for path, problem in bad.items():
        assert rows[str(path)]["status"] == "error" and problem in rows[str(path)]["error"]
    for path in good:
        assert rows[str(path)]["status"] == "ok" and rows[str(path)]["exact"] is True
        assert rows[str(path)]["focal_length_x_m"] == pytest.approx(5.42, rel=0.01)
    assert "FAILED" in summary.text() and str(next(iter(bad))) in summary.text()
    # a second run redoes nothing, not even the failures (unless asked)
    again = run_batch([src], tmp_path / "out", workers=2)
    assert again.reprocessed == 0 and again.skipped == summary.total and len(again.failed) == len(bad)
    again = run_batch([src], tmp_path / "out", workers=2, retry_failed=True)
    assert again.reprocessed == len(bad)
    # the same folder with other overrides would mix two analyses: refused
    with pytest.raises(BatchError, match="other --out|choose another --out"):
        run_batch([src], tmp_path / "out", {"focal_length_m": 5.6}, workers=2)


def test_the_command_exits_1_when_a_dump_failed(station_dumps, tmp_path, capsys):
    src = tmp_path / "dumps"
    _copies(station_dumps, src, 1)
    make_bad_files(src, station_dumps.good[0])
    assert cli_main(["batch", str(src / "**" / "*.h5"), "--out", str(tmp_path / "out"), "--workers", "1",
                     "--no-progress", "--focal-length", "5.6"]) == 1
    out = capsys.readouterr().out
    assert "8 dump(s): 8 reprocessed now" in out
    assert "0 reproduced the archive exactly, 1 differ from it, 7 failed" in out
    obj = json.loads(next((tmp_path / "out" / "results").glob("*copy000.json")).read_text())
    assert obj["reprocess"]["overrides"] == {"focal_length_m": 5.6} and obj["verdict"] == "fail"


def test_a_dump_that_kills_its_worker_is_reported_and_the_others_finish(station_dumps, tmp_path, monkeypatch):
    src = tmp_path / "dumps"
    dumps = _copies(station_dumps, src, 4)
    poison = dumps[1]
    # the fault point SIGKILLs the worker process that reprocesses this dump (children inherit the variable)
    monkeypatch.setenv("SOFAST_FAULT", f"reprocess:{poison.name}")
    summary = run_batch([src], tmp_path / "out", workers=2)
    assert summary.reprocessed == 4 and summary.exact == 3
    (failed,) = summary.failed
    assert failed[0] == str(poison) and "worker process died" in failed[1]


def test_dask_cluster_gives_the_same_results_as_the_local_run(station_dumps, tmp_path):
    import distributed  # a test dependency: its absence must fail, not skip
    src = tmp_path / "dumps"
    _copies(station_dumps, src, 6)
    local = run_batch([src], tmp_path / "local", workers=2)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        remote = run_batch([src], tmp_path / "dask", scheduler=cluster.scheduler_address)
    assert local.exact == remote.exact == 6 and not remote.failed
    a = sorted((tmp_path / "local" / "results").glob("*.json"))
    b = sorted((tmp_path / "dask" / "results").glob("*.json"))
    assert [p.name for p in a] == [p.name for p in b] and len(a) == 6
    for pa, pb in zip(a, b):
        oa, ob = json.loads(pa.read_text()), json.loads(pb.read_text())
        assert ob["reprocess"]["pid"] != os.getpid()           # computed on a Dask worker
        assert _stable(oa) == _stable(ob), pa.name


def test_an_unreachable_scheduler_is_a_clear_error(station_dumps, tmp_path):
    import distributed  # noqa: F401  (a test dependency)
    src = tmp_path / "dumps"
    _copies(station_dumps, src, 1)
    with pytest.raises(BatchError, match="cannot reach the Dask scheduler tcp://127.0.0.1:9"):
        run_batch([src], tmp_path / "out", scheduler="tcp://127.0.0.1:9", connect_timeout_s=2)


def test_a_bad_override_file_stops_the_batch_before_any_dump(station_dumps, tmp_path):
    from sofast_station.errors import ConfigError

    src = tmp_path / "dumps"
    _copies(station_dumps, src, 1)
    with pytest.raises(ConfigError, match="nowhere.toml does not exist"):
        run_batch([src], tmp_path / "out", {"facet_path": str(tmp_path / "nowhere.toml")})
    assert not (tmp_path / "out").exists()


def test_no_dumps_is_a_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(BatchError, match="no dumps"):
        run_batch([tmp_path / "empty"], tmp_path / "out")
    with pytest.raises(BatchError, match="matches no file"):
        run_batch([str(tmp_path / "nothing" / "*.h5")], tmp_path / "out")


def test_progress_bar_on_a_log_file_prints_a_line_per_tenth():
    import io

    stream = io.StringIO()
    bar = ProgressBar(stream)
    for i in range(0, 101):
        bar(i, 100, 0, "x")
    bar.close()
    lines = stream.getvalue().splitlines()
    assert 10 <= len(lines) <= 12 and lines[-1].startswith("[" + "#" * 30 + "] 100/100 dumps 100%")


def test_a_batch_killed_alone_leaves_no_worker_behind(station_dumps, tmp_path):
    """SIGKILL of the batch process only (not its group): its pool's workers exit by themselves."""
    src = tmp_path / "dumps"
    _copies(station_dumps, src, 12)
    cmd = [sys.executable, "-m", "sofast_station.reanalysis.cli", "batch", str(src), "--out", str(tmp_path / "out"),
           "--workers", "2", "--no-progress"]
    proc = subprocess.Popen(cmd, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    children_file = Path(f"/proc/{proc.pid}/task/{proc.pid}/children")
    if not children_file.exists():
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.skip("needs Linux /proc children lists")
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 300            # the pool is up whatever the machine's speed
        while time.monotonic() < deadline and len(workers) < 2 and proc.poll() is None:
            workers = {int(p) for p in children_file.read_text().split()} - {proc.pid}
            workers = {p for p in workers if "spawn_main" in Path(f"/proc/{p}/cmdline").read_text(errors="replace")}
            time.sleep(0.05)
        assert len(workers) >= 2, "the batch never started its two workers"
        proc.kill()                                  # the parent only: nothing can stop the pool for it
        proc.wait(timeout=60)
        deadline = time.monotonic() + 120
        alive = set(workers)
        while alive and time.monotonic() < deadline:
            alive = {p for p in alive if Path(f"/proc/{p}").exists()
                     and Path(f"/proc/{p}/stat").read_text().split()[2] != "Z"}
            time.sleep(0.1)
        assert not alive, f"batch workers {sorted(alive)} outlived their killed parent"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)      # whatever is left of the group, if the test failed
        except ProcessLookupError:
            pass
