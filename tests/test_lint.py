"""The tree passes its linter: ruff, configured in pyproject.toml ([tool.ruff]: pyflakes and pycodestyle's
errors and warnings at the code's line length of 120, and RUF100, so that a ``# noqa`` silencing nothing
is reported too). CI runs the test suite and nothing else, so the linter runs here."""

from __future__ import annotations

import subprocess
import sys
import tomllib

from tests.conftest import ROOT, require


def test_ruff_is_configured_with_pyflakes_and_pycodestyle():
    lint = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["ruff"]["lint"]
    assert {"E", "F", "W", "RUF100"} <= set(lint["select"]) and not lint.get("ignore")


def test_the_tree_passes_ruff():
    require("ruff")
    # --no-cache: no test writes into the source tree
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise",
                           str(ROOT)], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, \
        f"ruff finds problems (see them with: .venv/bin/python -m ruff check .):\n{proc.stdout}{proc.stderr}"
