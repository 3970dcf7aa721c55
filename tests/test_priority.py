"""`batch`, `report` and the web page run below the measuring loop's priority (issue 11), and SOFAST_NICE
sets or turns off that step. Checked in child processes, so the test run itself keeps its priority."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import ROOT

CHILD = "import os; from sofast_station.commands import lower_priority; lower_priority(); print(os.nice(0))"


def _niceness_after(env_nice: str | None) -> int:
    env = {k: v for k, v in os.environ.items() if k != "SOFAST_NICE"}
    if env_nice is not None:
        env["SOFAST_NICE"] = env_nice
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=120,
                         check=True)
    return int(out.stdout.strip())


@pytest.mark.skipif(not hasattr(os, "nice"), reason="no process priorities here")
def test_lower_priority_steps_down_by_default_and_obeys_sofast_nice():
    base = os.nice(0)
    assert _niceness_after(None) == max(base, 10)
    assert _niceness_after("0") == base
    assert _niceness_after("15") == max(base, 15)
