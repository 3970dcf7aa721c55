"""The re-analysis commands plug into any `sofast-station` parser and keep BLAS on one thread."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

from sofast_station.reanalysis._env import BLAS_THREAD_VARS
from sofast_station.reanalysis.cli import cmd_batch, cmd_report, cmd_reprocess, overrides_from_args, register
from tests.conftest import ROOT


def test_register_adds_the_three_commands_to_a_fresh_parser():
    p = argparse.ArgumentParser(prog="sofast-station")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("inspect")
    register(sub)
    args = p.parse_args(["reprocess", "a.h5", "b.h5", "--focal-length", "5.6", "--alignment-point", "0.1", "-0.2",
                         "--distance", "10.7", "--mask-threshold", "25", "--json"])
    assert args.func is cmd_reprocess and args.dumps == ["a.h5", "b.h5"] and args.json
    ov = overrides_from_args(args)
    assert ov.to_dict() == {"focal_length_m": 5.6, "alignment_point_m": [0.1, -0.2], "measured_distance_m": 10.7,
                            "mask_threshold_dn": 25.0}
    args = p.parse_args(["batch", "dumps/", "--out", "o", "--workers", "2", "--scheduler", "tcp://h:8786"])
    assert args.func is cmd_batch and args.workers == 2 and args.scheduler == "tcp://h:8786"
    args = p.parse_args(["report", "trend", "--journal", "j.sqlite3", "--from", "2026-11-01", "--to", "2026-12-01"])
    assert args.func is cmd_report and args.targets == ["trend"] and args.since == "2026-11-01"


def _env_without_blas_vars() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARS}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    return env


def test_importing_the_commands_loads_no_numpy():
    code = ("import sys, argparse; from sofast_station.reanalysis.cli import register; "
            "register(argparse.ArgumentParser().add_subparsers()); print('numpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env_without_blas_vars(),
                         timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr


def test_reprocess_runs_with_blas_on_one_thread(station_dumps):
    proc = subprocess.run([sys.executable, "-m", "sofast_station.reanalysis.cli", "reprocess", "--json",
                           str(station_dumps.good[0])], capture_output=True, text=True, env=_env_without_blas_vars(),
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    obj = json.loads(proc.stdout)
    assert set(obj["reprocess"]["blas_threads"].values()) == {"1"}
    # and OpenCV's pool, whose idle worker otherwise spins on the second core (issue 32)
    code = ("from sofast_station.reanalysis._env import single_thread_blas; single_thread_blas(); import cv2; "
            "print(cv2.getNumThreads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env_without_blas_vars(),
                         timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "1", (out.stdout, out.stderr)
    assert obj["reprocess"]["exact"] is True and "BLAS on 1 thread" in obj["reprocess"]["summary"]
