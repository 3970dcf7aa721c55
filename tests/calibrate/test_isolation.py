"""The calibration code sees the hardware only through the device protocols: it imports nothing from
the digital twin (directly or through another module)."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CALIBRATE = REPO / "sofast_station" / "calibrate"


def test_importing_every_calibration_module_loads_no_twin_module():
    modules = sorted(p.stem for p in CALIBRATE.glob("*.py") if p.stem != "__init__")
    assert {"radiometric", "store", "camera", "geometry", "geometry_record", "records", "settings"} <= set(modules)
    code = ("import importlib, json, sys\n"
            f"for name in {modules!r}:\n"
            "    importlib.import_module('sofast_station.calibrate.' + name)\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith('sofast_station.twin'))))\n")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def test_calibration_sources_never_name_the_twin():
    for path in sorted(CALIBRATE.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [("." * node.level) + (node.module or "")]
            else:
                continue
            for name in names:
                assert "twin" not in name.split("."), f"{path.name} imports {name}"
