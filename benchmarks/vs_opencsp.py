"""Benchmark: ``import-opencsp`` against OpenCSP's own processing of the same files, side by side, for every
dataset of OpenCSP's published SOFAST test data (fixtures/opencsp).

    .venv/bin/python benchmarks/vs_opencsp.py                                    # ours alone, every dataset
    .venv/bin/python benchmarks/vs_opencsp.py --opencsp-python /path/to/opencsp-venv/bin/python
    .venv/bin/python benchmarks/vs_opencsp.py --opencsp-python PY --datasets robust,plano --sizes native --runs 9

The datasets (``--datasets``, default all): the single facet with a robust and a plain parabolic fit, with a
rectangular and a 3-D distorted screen, with the plano surface, as a mirror of unknown outline, the lab
heliostat of 24 facets (``measurement_ensemble.h5``) and the single facet as two halves. Each runs, as fresh
processes, ``sofast-station import-opencsp`` with that dataset's options (ours: every figure with its
uncertainty, and the optics) and ``benchmarks/opencsp_process.py DATA --dataset NAME`` with OpenCSP's Python
(theirs: what OpenCSP's examples do for that optic). The single-facet datasets also run upsampled (``--sizes``;
8x: 1624 x 1232 px, made as ``benchmarks/analysis.py`` makes it).

Like for like: both with their bytecode written (``PYTHONDONTWRITEBYTECODE`` removed from the environment:
an installed package runs from its bytecode, and a shell that sets it makes both compile their modules on
every run), both on one BLAS thread (ours always is; OpenCSP gets ``OPENBLAS_NUM_THREADS=1``: OpenBLAS's
two threads on a loaded 2-core machine made its processing 0.5-2 s instead of 0.3 s), ours with the
station's cache warm (a temporary ``SOFAST_DATA_DIR``, filled by the uncounted first run). Each case: one
uncounted run of each, then ``--runs`` runs of each in turn (A B A B ...). Printed: median and range of
wall time, median CPU (user + system of the finished child) and peak memory, and the median over the pairs
of ours / theirs. Never asserted; the machine's load before and after is printed with them. Without
``--opencsp-python`` only our side runs, and the table says OpenCSP was not run.

OpenCSP is not a dependency of this repository: install it in an environment of its own (its
``pyproject.toml``; docs/performance.md says which commit was measured).
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))              # run from a checkout, installed or not
sys.path.insert(0, str(ROOT / "benchmarks"))

from commands import OPENCSP, load, run_process  # noqa: E402  (benchmarks/commands.py)

RUNNER = ROOT / "benchmarks" / "opencsp_process.py"


def environments(data_dir: Path) -> tuple[dict, dict]:
    """(ours, theirs): the caller's environment without PYTHONDONTWRITEBYTECODE; ours with its own station
    data folder, theirs on one BLAS thread and matplotlib's file backend."""
    base = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    ours = {**base, "SOFAST_DATA_DIR": str(data_dir)}
    theirs = {**base, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "MPLBACKEND": "Agg"}
    return ours, theirs


def check_opencsp(python: str, env: dict) -> None:
    """Exit with a clear message when *python* cannot run OpenCSP's processing."""
    if not Path(python).exists() and shutil.which(python) is None:
        raise SystemExit(f"--opencsp-python {python}: no such interpreter (give the python of an environment "
                         "where OpenCSP is installed)")
    proc = subprocess.run([python, str(RUNNER), "--help"], capture_output=True, text=True, env=env, timeout=300)
    if proc.returncode != 0:
        said = (proc.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise SystemExit(f"--opencsp-python {python} cannot run OpenCSP's processing: {said}. Install OpenCSP in "
                         "that environment (pip install -e <OpenCSP checkout>) and run this again.")


def first_lines(log: Path, marker: str, n: int = 3) -> list[str]:
    """The first *n* lines of *log* from the first line that holds *marker* (what a run printed)."""
    lines = log.read_text(errors="replace").splitlines()
    for i, line in enumerate(lines):
        if marker in line:
            return lines[i:i + n]
    return lines[:n]


#: Each dataset: (our import-opencsp options, the OpenCSP runner's --dataset, whether it has an upsampled size).
DATASETS = {
    "robust": (["--robust"], True),
    "plain": ([], True),
    "rectangular": (["--robust", "--display", "{data}/sofast_common/display_rectangular.h5"], True),
    "distorted_3d": (["--robust", "--display", "{data}/sofast_common/display_distorted_3d.h5"], True),
    "plano": (["--robust", "--surface", "plano"], True),
    "undefined": (["--undefined"], True),
    "multi_facet": (["--multi-facet"], False),
    "split_facet": (["--split-facet"], False),
}


def compare(name: str, size: str, data: Path, python: str | None, runs: int, tmp: Path) -> dict:
    """One dataset at one size: the uncounted pair, then *runs* pairs in turn; the medians and the pairs'
    ratios (ours alone without *python*)."""
    ours_env, theirs_env = environments(tmp / f"data-{name}-{size}")
    flags = [f.format(data=data) for f in DATASETS[name][0]]
    cmds = {"ours": ([sys.executable, "-m", "sofast_station", "import-opencsp", *flags, "--test-data", str(data)],
                     ours_env)}
    if python is not None:
        cmds["theirs"] = ([python, str(RUNNER), str(data), "--dataset", name], theirs_env)
    logs = {who: tmp / f"{who}-{name}-{size}.log" for who in cmds}
    got: dict = {who: [] for who in cmds}
    for i in range(runs + 1):
        for who, (cmd, env) in cmds.items():
            r = run_process(cmd, env, tmp, logs[who])
            if r.code != 0:
                raise SystemExit(f"{name} {size}: {who} exited {r.code}; its output: {logs[who]}")
            if i > 0:                      # the first of each is the uncounted warm-up
                got[who].append(r)
        print(f"  {name} {size}: pair {i}/{runs} done" + (" (uncounted)" if i == 0 else ""), flush=True)
    out: dict = {}
    for who in got:
        wall = [r.wall_s for r in got[who]]
        out[who] = {"wall": statistics.median(wall), "lo": min(wall), "hi": max(wall),
                    "cpu": statistics.median(r.cpu_s for r in got[who]),
                    "peak": statistics.median(r.peak_mb for r in got[who])}
    if "theirs" in got:
        ratios = [a.wall_s / max(b.wall_s, 1e-9) for a, b in zip(got["ours"], got["theirs"])]
        cpu_ratios = [a.cpu_s / max(b.cpu_s, 1e-9) for a, b in zip(got["ours"], got["theirs"])]
        out["ratio"] = {"wall": statistics.median(ratios), "lo": min(ratios), "hi": max(ratios),
                        "cpu": statistics.median(cpu_ratios)}
    out["said"] = {"ours": first_lines(logs["ours"], "f x", 2)}
    if "theirs" in logs:
        out["said"]["theirs"] = first_lines(logs["theirs"], "f x", 1)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--opencsp-python", default=None,
                   help="the python of an environment where OpenCSP is installed (not this repository's); without it "
                        "only our side runs")
    p.add_argument("--datasets", default=",".join(DATASETS),
                   help=f"comma-separated, of {', '.join(DATASETS)} (default: all)")
    p.add_argument("--sizes", default="native,8x", help="comma-separated: native and/or Nx (upsampled N times; the "
                   "single-facet datasets only)")
    p.add_argument("--runs", type=int, default=5, help="counted runs of each, in turn (median quoted)")
    args = p.parse_args(argv)
    sizes = [s.strip() for s in args.sizes.split(",") if s.strip()]
    for s in sizes:
        if s != "native" and not (s.endswith("x") and s[:-1].isdigit() and int(s[:-1]) >= 2):
            p.error(f"--sizes: {s!r} is neither 'native' nor an upsampling such as '8x'")
    names = [d.strip() for d in args.datasets.split(",") if d.strip()]
    for d in names:
        if d not in DATASETS:
            p.error(f"--datasets: {d!r} is none of {', '.join(DATASETS)}")
    if args.runs < 1:
        p.error("--runs must be at least 1")
    tmp = Path(tempfile.mkdtemp(prefix="sofast-vs-opencsp-"))
    try:
        if args.opencsp_python is not None:
            check_opencsp(args.opencsp_python, environments(tmp)[1])
        against = (f"against OpenCSP's processing ({args.opencsp_python})" if args.opencsp_python else
                   "alone (OpenCSP not run: give --opencsp-python)")
        print(f"import-opencsp {against}; {args.runs} counted pair(s) after 1 uncounted; {os.cpu_count()} CPU(s); "
              f"load before: {load()}", flush=True)
        results = {}
        folders = {"native": OPENCSP}
        for s in sizes:
            if s != "native":
                import analysis as bench_analysis

                folders[s] = tmp / f"opencsp-{s}"
                bench_analysis.upsample_opencsp(OPENCSP, folders[s], int(s[:-1]))
        for name in names:
            for s in sizes:
                if s != "native" and not DATASETS[name][1]:
                    continue
                results[(name, s)] = compare(name, s, folders[s], args.opencsp_python, args.runs, tmp)
        print(f"load after: {load()}")
        print("| dataset | capture | ours: wall s (min-max) / CPU s / peak MB | OpenCSP: wall s (min-max) / CPU s / "
              "peak MB | ours / OpenCSP, median of the pairs: wall (min-max) / CPU |")
        print("| --- | --- | --- | --- | --- |")
        for (name, s), r in results.items():
            o = r["ours"]
            ours = f"{o['wall']:.2f} ({o['lo']:.2f}-{o['hi']:.2f}) / {o['cpu']:.2f} / {o['peak']:.0f}"
            if "theirs" in r:
                t, q = r["theirs"], r["ratio"]
                theirs = f"{t['wall']:.2f} ({t['lo']:.2f}-{t['hi']:.2f}) / {t['cpu']:.2f} / {t['peak']:.0f}"
                ratio = f"{q['wall']:.2f} ({q['lo']:.2f}-{q['hi']:.2f}) / {q['cpu']:.2f}"
            else:
                theirs = ratio = "not run"
            print(f"| {name} | {s} | {ours} | {theirs} | {ratio} |")
        for (name, s), r in results.items():
            print(f"{name} {s}, what each printed:")
            for who, lines in r["said"].items():
                for line in lines:
                    print(f"  {who:6s} {line.strip()}")
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
