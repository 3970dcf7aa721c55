"""Running a benchmark script to its end from a test (tests/test_benchmarks*.py)."""

import math
import re
import resource
import subprocess
import sys


def _run(repo_root, script: str, *args: str, timeout: float = 600) -> tuple[subprocess.CompletedProcess, float]:
    """Run ``benchmarks/<script> args`` to its end; its output and the CPU seconds its processes took (the
    figure each test's docstring names, printed with the output; never asserted)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([sys.executable, str(repo_root / "benchmarks" / script), *args], capture_output=True,
                          text=True, timeout=timeout)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime
    print(f"benchmarks/{script}: {cpu:.1f} s CPU\n{proc.stdout}")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
    return proc, cpu


def _numbers(line: str) -> list[float]:
    """The numbers printed on *line* (signed, decimal or exponent), each required finite."""
    values = [float(v) for v in re.findall(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?", line)]
    assert values and all(math.isfinite(v) for v in values), line
    return values
