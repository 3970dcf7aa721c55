"""The twin shares no code with the measurement pipeline it is the oracle for."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
TWIN = REPO / "sofast_station" / "twin"
# The plain data (records and their readers) the twin shares with everyone: a heliostat's design is one.
ALLOWED_PROJECT_MODULES = {"sofast_station.geometry", "sofast_station.facet", "sofast_station.ensemble",
                           "sofast_station.errors"}


def test_importing_the_twin_loads_neither_measure_nor_optics_nor_calibrate_nor_cv2():
    """The twin, its optical truth (twin/sunlight.py) among it, loads nothing of the pipeline it checks."""
    code = ("import json, sys\n"
            "import sofast_station.twin, sofast_station.twin.truth, sofast_station.twin.station\n"
            "import sofast_station.twin.board, sofast_station.twin.heliostat, sofast_station.twin.sunlight\n"
            "import sofast_station.twin.trace, sofast_station.twin.render, sofast_station.twin.sensor\n"
            "bad = sorted(m for m in sys.modules if m.startswith('sofast_station.measure') or m == 'cv2'"
            " or m.startswith('cv2.') or m.startswith('sofast_station.calibrate')"
            " or m.startswith('sofast_station.optics'))\n"
            "print(json.dumps(bad))\n")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


def _imports(path: Path) -> list[str]:
    """Absolute module names imported by a twin source file."""
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                names.append(node.module)
            else:
                package = ["sofast_station", "twin"][: 3 - node.level]
                names.append(".".join(package + ([node.module] if node.module else [])))
    return names


def test_twin_sources_import_only_allowed_modules():
    stdlib = set(sys.stdlib_module_names)
    for path in sorted(TWIN.glob("*.py")):
        for name in _imports(path):
            top = name.split(".")[0]
            ok = (top in stdlib or top in ("numpy", "scipy", "__future__")
                  or name in ALLOWED_PROJECT_MODULES or name.startswith("sofast_station.twin"))
            assert ok, f"{path.name} imports {name}"
