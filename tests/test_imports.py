"""Imports where a reader sees them (docs/architecture.md, "Where imports are"; issue 46 item 4).

The command modules (``commands.COMMAND_MODULES``, the entry point ``cli.py``, and
``reanalysis/quality_reports.py``, the half of the ``report`` command whose options build ``--help``) are the
one lazy layer: they import the heavy modules inside their commands' functions. Every other module imports at
its top, unless an import inside a function carries its reason in a comment on its line or on the line right
above it (that comment covers the unbroken run of imports under it):

- ``# optional:`` the library is an extra (asyncua, pypylon, PyGObject/Aravis, glfw, Dask) or a driver of one
  device backend (pymodbus, pyusb),
- ``# cycle:`` a top import would close an import cycle (name it),
- ``# lazy:`` a measured start-up cost says so (the milliseconds, and who imports the module without needing it).

The packages already moved (:data:`DONE`) must have no import inside a function without such a reason. The
others (:data:`NOT_YET`) are being moved; their current counts of unmarked imports inside functions are a
ceiling, so the count cannot grow: lower a ceiling when the count drops, and move a unit to :data:`DONE` when
it reaches 0.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

from sofast_station.commands import COMMAND_MODULES

PACKAGE_DIR = Path(__file__).resolve().parents[1] / "sofast_station"

#: Modules (relative to the package) that are the lazy layer: each command module, the entry point, and the
#: report command's quality reports (reanalysis/cli.py gives their add_options the report parser).
COMMAND_LAYER = ({m.removeprefix("sofast_station.").replace(".", "/") + ".py" for m in COMMAND_MODULES}
                 | {"cli.py", "reanalysis/quality_reports.py"})

#: Units (sub-packages, or top-level modules) whose imports are at their tops, or marked with a reason.
DONE = {"reanalysis", "interop", "report", "web", "calibrate", "archive", "devices", "result", "optics", "qc",
        "live", "cache.py", "precompute.py", "memory.py", "files.py", "commands.py", "build_kernels.py",
        "errors.py", "geometry.py", "facet.py", "ensemble.py", "serials.py", "times.py", "gum.py", "layout.py",
        "__init__.py", "__main__.py", "cli.py", "job", "twin", "fringes.py", "recipes.py",
        "config.py", "config_schema.py", "field", "measure", "station"}

#: Units not moved yet: their unmarked imports inside functions today (a ceiling; lower it as they move).
NOT_YET: dict[str, int] = {}

MARK = re.compile(r"#\s*(lazy|optional|cycle):\s*\S")
_IMPORT_LINE = re.compile(r"\s*(from\s+\S+\s+import\b|import\s)")


def unmarked_lazy_imports(source: str) -> list[int]:
    """Line numbers of the imports inside function bodies of *source* that carry no reason comment (on their own
    lines, or on the line right above the run of import lines they stand in)."""
    lines = source.splitlines()
    tree = ast.parse(source)
    seen: set[int] = set()
    bad = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        for node in ast.walk(fn):
            if not isinstance(node, (ast.Import, ast.ImportFrom)) or id(node) in seen:
                continue
            seen.add(id(node))
            own = lines[node.lineno - 1:node.end_lineno]
            above = node.lineno - 2
            while above >= 0 and _IMPORT_LINE.match(lines[above]) and not MARK.search(lines[above]):
                above -= 1
            marked = any(MARK.search(line) for line in own) or (
                above >= 0 and lines[above].strip().startswith("#") and MARK.search(lines[above]))
            if not marked:
                bad.append(node.lineno)
    return sorted(bad)


def unit_of(rel: str) -> str:
    return rel.split("/")[0]


@functools.cache
def scan() -> dict[str, list[str]]:
    """Per unit, every unmarked import inside a function outside the command layer (``path:line``)."""
    found: dict[str, list[str]] = {}
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        rel = path.relative_to(PACKAGE_DIR).as_posix()
        found.setdefault(unit_of(rel), [])
        if rel in COMMAND_LAYER:
            continue
        found[unit_of(rel)] += [f"{rel}:{n}" for n in unmarked_lazy_imports(path.read_text())]
    return found


def test_the_scanner_finds_and_excuses_what_it_should():
    """Planted cases: an unmarked import in a function is found, a marked one (its line, the line above, or a
    run of imports under a mark) is excused, a module-level import is nobody's business, and a mark with no
    reason after it does not count."""
    src = '''import os

def a():
    import json
    return json

def b():
    import cv2  # optional: the hardware extra
    # lazy: matplotlib costs 650 ms and only the PNG needs it
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    import h5py
    # cycle:
    import numpy
    return cv2, Figure, Circle, h5py, numpy

f = lambda: __import__("x")

def c():
    def inner():
        # lazy: 40 ms, only the cluster
        import distributed
        import zlib
        return distributed, zlib
    return inner
'''
    assert unmarked_lazy_imports(src) == [4, 13, 15]


def test_the_command_layer_is_what_commands_names():
    """The lazy layer is the registry's command modules and the two named beside them; each exists."""
    for rel in COMMAND_LAYER:
        assert (PACKAGE_DIR / rel).is_file(), rel
    assert "reanalysis/cli.py" in COMMAND_LAYER and "station/calibrate_cli.py" in COMMAND_LAYER


def test_every_unit_is_done_or_not_yet():
    placeless = set(scan()) - DONE - set(NOT_YET)
    assert not placeless, f"give these units a place in DONE or NOT_YET: {sorted(placeless)}"
    assert not DONE & set(NOT_YET)


def test_imports_of_the_moved_packages_are_at_the_top_or_say_why():
    found = scan()
    bad = [where for unit in sorted(DONE) for where in found.get(unit, [])]
    assert not bad, ("imports inside functions without '# lazy:', '# optional:' or '# cycle:' and a reason "
                     "(move them to the module's top, or say why; docs/architecture.md, 'Where imports are'):\n  "
                     + "\n  ".join(bad))


def test_the_packages_not_yet_moved_do_not_grow():
    found = scan()
    over = {unit: (len(found.get(unit, [])), ceiling) for unit, ceiling in NOT_YET.items()
            if len(found.get(unit, [])) > ceiling}
    assert not over, ("more unmarked imports inside functions than the ceiling (count, ceiling): "
                      f"{over}; put the new ones at the module's top (or mark them with their reason)")
