"""The import rules of docs/architecture.md, checked by reading the sources (no module is imported).

Every ``import`` statement of ``sofast_station`` counts, at module level ("eager": loaded with the module)
or inside a function ("lazy": loaded when the function runs). A rule on what a package may depend on, and
the rule against import cycles, use both; a rule on what loading a package loads uses the eager ones.

A failure names the importing file and line and the chain of imports that breaks the rule. If the rule
itself has to change, change it in docs/architecture.md and here together.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict, deque
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "sofast_station"

#: The plain-data modules the math, the twin and everyone else share (records and their TOML reader).
PLAIN_DATA = {"errors", "geometry", "facet", "ensemble", "fringes", "files"}
#: The floors of docs/architecture.md's picture, top to bottom (units: sub-packages, or top-level modules by
#: name). A unit imports only its own floor and those below it; no two units import each other.
FLOORS: tuple[tuple[str, frozenset], ...] = (
    ("entry", frozenset({"__main__", "cli"})),
    ("programs", frozenset({"reanalysis", "station", "interop", "field"})),
    ("the jobs", frozenset({"job"})),
    ("the monitor", frozenset({"web"})),
    ("shown and shared", frozenset({"report", "live"})),
    ("configured and kept", frozenset({"config", "config_schema", "recipes", "archive", "precompute", "cache",
                                               "build_kernels"})),
    ("the result", frozenset({"result"})),
    ("routines, devices, oracle, math", frozenset({"calibrate", "devices", "twin", "measure", "qc", "optics",
                                                   "layout"})),
    ("plain data", frozenset({"errors", "geometry", "facet", "ensemble", "fringes", "files", "times", "memory",
                              "serials", "commands",
                              "gum",
                              "(package)"})),
)
#: Standard-library modules that do I/O or run processes: none of them in the pure math.
STDLIB_IO = {"sqlite3", "socket", "subprocess", "multiprocessing", "signal", "shutil", "tempfile", "urllib", "http",
             "asyncio", "selectors", "ssl", "ftplib", "smtplib", "tkinter"}


@dataclass(frozen=True)
class Import:
    source: str          # importing module, e.g. sofast_station.measure.fit
    target: str          # imported module (project modules resolved to a module that exists), or a library
    line: int
    eager: bool          # at module level (also inside if/try at module level)


def _module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def scan(root: Path = ROOT) -> tuple[set[str], list[Import]]:
    """Every module of the package under *root* and every import statement in it."""
    files = sorted((root / PACKAGE).rglob("*.py"))
    modules = {_module_name(p, root) for p in files}
    imports: list[Import] = []
    for path in files:
        name = _module_name(path, root)
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        tree = ast.parse(path.read_text(), filename=str(path))
        for node, eager in _import_statements(tree):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                # "from pkg import name": name may be a submodule or an attribute of pkg
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            for target in targets:
                if target.split(".")[0] == PACKAGE:
                    while target not in modules and "." in target:
                        target = target.rsplit(".", 1)[0]
                imports.append(Import(name, target, node.lineno, eager))
    return modules, imports


def _import_statements(tree: ast.Module) -> list[tuple[ast.stmt, bool]]:
    """Every import statement of *tree*, in ast.walk's order (breadth first), each with whether it runs with
    the module (eager) or only when a function that holds it runs. Only statements are visited (an import is
    one, and no expression holds a statement): a twentieth of the nodes, a third of the scan's time."""
    found = []
    todo = deque([(tree, True)])
    while todo:
        node, eager = todo.popleft()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found.append((node, eager))
            continue
        inner = eager and not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))
        for field in ("body", "orelse", "finalbody", "handlers", "cases"):
            for child in getattr(node, field, ()):
                if isinstance(child, (ast.stmt, ast.excepthandler, ast.match_case)):
                    todo.append((child, inner))
    return found


def unit(module: str) -> str:
    """The architectural unit of a project module: its sub-package, or its top-level module's name."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "(package)"


def floor_of(name: str) -> int | None:
    """The floor (0 = top) of the unit *name* in :data:`FLOORS`; None when it has none."""
    return next((i for i, (_, units) in enumerate(FLOORS) if name in units), None)


class Graph:
    def __init__(self, root: Path = ROOT):
        self.modules, self.imports = scan(root)
        self.out: dict[str, list[Import]] = defaultdict(list)
        for imp in self.imports:
            self.out[imp.source].append(imp)

    def in_unit(self, name: str) -> list[str]:
        return sorted(m for m in self.modules if unit(m) == name and m.startswith(PACKAGE + "."))

    def reach(self, starts, eager_only: bool = False) -> dict[str, list[Import]]:
        """Every module reachable from *starts* (project modules and libraries), each with one import chain."""
        chains: dict[str, list[Import]] = {s: [] for s in starts}
        todo = list(starts)
        while todo:
            m = todo.pop()
            for imp in self.out.get(m, ()):
                if eager_only and not imp.eager:
                    continue
                if imp.target not in chains:
                    chains[imp.target] = chains[m] + [imp]
                    if imp.target in self.modules:
                        todo.append(imp.target)
        return chains


def _chain(chain: list[Import]) -> str:
    return " -> ".join([chain[0].source] + [f"{i.target} (line {i.line}{'' if i.eager else ', lazy'})" for i in chain])


def check_rules(graph: Graph) -> list[str]:
    """Every broken rule of docs/architecture.md, one message each (empty when all hold)."""
    bad: list[str] = []
    project = graph.modules

    def forbid(starts, allowed_unit, libraries_ok, rule, eager_only=False):
        """Report each forbidden module reached from *starts* once, with the chain that reaches it (the
        search does not go on through a forbidden module: its own imports are its rules' business)."""
        chains = {s: [] for s in starts}
        todo = list(starts)
        while todo:
            for imp in graph.out.get(todo.pop(), ()):
                if (eager_only and not imp.eager) or imp.target in chains:
                    continue
                chains[imp.target] = chain = chains[imp.source] + [imp]
                if imp.target in project:
                    if allowed_unit(unit(imp.target)):
                        todo.append(imp.target)
                    else:
                        bad.append(f"{rule}: {_chain(chain)}")
                elif not libraries_ok(imp.target.split(".")[0]):
                    bad.append(f"{rule}: {_chain(chain)}")

    stdlib = set(sys.stdlib_module_names) | {"__future__"}

    # 1. the math: only itself and the plain data, directly or indirectly; numpy, scipy, OpenCV; no I/O
    forbid(graph.in_unit("measure"), lambda u: u == "measure" or u in PLAIN_DATA,
           lambda lib: lib in {"numpy", "scipy", "cv2", "numba"} or (lib in stdlib and lib not in STDLIB_IO),
           "measure/ may import only itself, the plain-data modules, numpy, scipy, cv2, numba and non-I/O stdlib")
    # 1b. the statistics: pure as well
    forbid(graph.in_unit("qc"), lambda u: u in {"qc", "errors"},
           lambda lib: lib in {"numpy", "scipy"} or (lib in stdlib and lib not in STDLIB_IO),
           "qc/ may import only itself, errors, numpy, scipy and non-I/O stdlib")
    # 1c. the optics (ray trace of a facet in sunlight): pure as well
    forbid(graph.in_unit("optics"), lambda u: u == "optics" or u in PLAIN_DATA,
           lambda lib: lib == "numpy" or (lib in stdlib and lib not in STDLIB_IO),
           "optics/ may import only itself, the plain-data modules, numpy and non-I/O stdlib")
    # 2. the twin: nothing of the math nor of the optics it checks (nor calibration, nor OpenCV), directly or
    #    indirectly
    forbid(graph.in_unit("twin"), lambda u: u in {"twin"} | PLAIN_DATA,
           lambda lib: lib in {"numpy", "scipy"} or lib in stdlib,
           "twin/ shares no code with measure/ or optics/ (only itself, the plain data, numpy, scipy and the stdlib)")
    # 3. calibration: never names the twin; loading it loads no twin module
    for imp in graph.imports:
        if unit(imp.source) == "calibrate" and imp.target in project and unit(imp.target) == "twin":
            bad.append(f"calibrate/ never imports twin/: {imp.source} line {imp.line} imports {imp.target}")
    forbid(graph.in_unit("calibrate"), lambda u: u != "twin", lambda lib: True,
           "loading calibrate/ loads no twin/ module", eager_only=True)
    # 4. devices: the leaves the loop drives
    forbid(graph.in_unit("devices"), lambda u: u in {"devices"} | PLAIN_DATA, lambda lib: True,
           "devices/ imports only itself and the plain data")
    # 5. the archive keeps; it never drives the station, the devices or the twin
    for imp in graph.imports:
        if (unit(imp.source) == "archive" and imp.target in project
                and unit(imp.target) in {"station", "devices", "twin", "cli", "commands"}):
            bad.append(f"archive/ imports nothing from station/, devices/, twin/ or the command line: "
                       f"{imp.source} line {imp.line} imports {imp.target}")
    # 6. one registry of commands: only the entry point imports cli.py; commands.py imports no command module
    for imp in graph.imports:
        if imp.target == f"{PACKAGE}.cli" and imp.source != f"{PACKAGE}.__main__":
            bad.append(f"only __main__ imports {PACKAGE}.cli: {imp.source} line {imp.line} imports it")
    forbid([f"{PACKAGE}.commands"], lambda u: u in {"commands", "errors", "(package)"}, lambda lib: lib in stdlib,
           "commands.py (the registry) imports only the standard library, errors and the package's version")
    # 9. a job analyses, judges and records a measurement: the math, the optics, the result and its reports, the
    #    plain data; never the devices, the loop, the archive, the twin or a program
    allowed_by_job = {"job", "measure", "optics", "result", "report"} | PLAIN_DATA
    for imp in graph.imports:
        if unit(imp.source) == "job" and imp.target in project and unit(imp.target) not in allowed_by_job:
            bad.append(f"job/ imports only the math, the optics, the result, its reports and the plain data: "
                       f"{imp.source} line {imp.line} imports {imp.target}")
    # 8. the floors: no import runs back up a floor, no two units import each other
    units = {unit(m) for m in project}
    for name in sorted(u for u in units if floor_of(u) is None):
        bad.append(f"every unit has a floor: {name} has none in FLOORS (give it one here and in docs/architecture.md)")
    ties: dict = {}
    for imp in graph.imports:
        if imp.target not in project or unit(imp.source) == unit(imp.target):
            continue
        a, b = unit(imp.source), unit(imp.target)
        ties.setdefault((a, b), imp)
        fa, fb = floor_of(a), floor_of(b)
        if fa is not None and fb is not None and fb < fa:
            bad.append(f"no import runs back up a floor: {imp.source} line {imp.line} imports {imp.target} "
                       f"({FLOORS[fa][0]} -> {FLOORS[fb][0]})")
    for (a, b), imp in sorted(ties.items()):
        if a < b and (b, a) in ties:
            back = ties[(b, a)]
            bad.append(f"no two units import each other: {imp.source} line {imp.line} imports {imp.target}, "
                       f"{back.source} line {back.line} imports {back.target}")
    return bad


def import_cycles(graph: Graph) -> list[list[str]]:
    """Import cycles among the package's modules (each once, as a list of modules), counting imports inside
    functions too: a lazy import defers the loading, not the dependency, so two modules that import each
    other at any level are one knot."""
    index, low, stack, on, out = {}, {}, [], set(), []
    edges = {m: sorted({i.target for i in graph.out.get(m, ()) if i.target in graph.modules
                        and i.target != m and not m.startswith(i.target + ".")}) for m in graph.modules}

    def strong(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for m in sorted(graph.modules):
        if m not in index:
            strong(m)
    return out


@pytest.fixture(scope="module")
def graph():
    return Graph()


def test_the_scan_sees_the_package(graph):
    """Guard against a rule that passes because the scan saw nothing."""
    assert {"sofast_station.measure.pipeline", "sofast_station.twin.truth", "sofast_station.station.calibrate_cli",
            "sofast_station.commands"} <= graph.modules
    measure_reach = graph.reach(graph.in_unit("measure"))
    assert "sofast_station.geometry" in measure_reach and "numpy" in measure_reach
    assert "sofast_station.twin.truth" in graph.reach(["sofast_station.station.factory"])


def test_the_import_rules_of_docs_architecture_hold(graph):
    broken = check_rules(graph)
    assert not broken, "import rules broken (docs/architecture.md):\n  " + "\n  ".join(broken)


def test_no_import_cycle(graph):
    cycles = import_cycles(graph)
    assert not cycles, "import cycles (imports inside functions counted): " + "; ".join(
        " <-> ".join(c) for c in cycles)


def test_the_cycle_rule_counts_imports_inside_functions(tmp_path):
    """A circle closed only by an import inside a function is still a circle (the two circles this rule
    once missed were closed that way)."""
    import shutil

    shutil.copytree(ROOT / PACKAGE, tmp_path / PACKAGE, ignore=shutil.ignore_patterns("__pycache__"))
    path = tmp_path / PACKAGE / "measure" / "pipeline.py"
    path.write_text(path.read_text() + "\n\ndef _planted():\n    from .analysis import analyse\n")
    cycles = import_cycles(Graph(tmp_path))
    assert any({"sofast_station.measure.analysis", "sofast_station.measure.pipeline"} <= set(c) for c in cycles), cycles


def test_each_rule_catches_a_violation(tmp_path):
    """Plant one violation of each rule in a copy of the package: each is reported."""
    import shutil

    shutil.copytree(ROOT / PACKAGE, tmp_path / PACKAGE, ignore=shutil.ignore_patterns("__pycache__"))
    pkg = tmp_path / PACKAGE
    planted = {
        "measure/fit.py": "from ..archive.journal import Journal\n",
        "measure/phase.py": "import sqlite3\n",
        "twin/surface.py": "def f():\n    from ..measure.fit import fit_parabola\n",
        "twin/sunlight.py": "def h():\n    from ..optics import facet_optics\n",
        "calibrate/store.py": "from ..twin import station\n",
        "devices/lcd.py": "from ..station import runner\n",
        "archive/journal.py": "from ..station.runner import Runner\n",
        "reanalysis/batch.py": "from ..cli import main\n",
        "commands.py": "from .station import cli\n",
        "qc/spc.py": "import h5py\n",
        "optics/trace.py": "from ..station import optics\n",
        "result/record.py": "def f():\n    from ..station import runner\n",
        "live/status.py": "def f():\n    from ..web import data\n",
        "job/facet.py": "def g():\n    from ..archive import journal\n",
    }
    for rel, code in planted.items():
        path = pkg / rel
        path.write_text(path.read_text() + "\n" + code)
    broken = check_rules(Graph(tmp_path))
    for rule in ("measure/ may import", "qc/ may import", "optics/ may import", "twin/ shares no code",
                 "calibrate/ never imports twin/", "devices/ imports only", "archive/ imports nothing",
                 "only __main__ imports", "commands.py (the registry)", "no import runs back up a floor",
                 "no two units import each other", "job/ imports only"):
        assert any(b.startswith(rule) for b in broken), f"{rule!r} not reported; got:\n" + "\n".join(broken)
    assert any("sqlite3" in b for b in broken) and any("lazy" in b and "twin" in b for b in broken)
    assert any(b.startswith("twin/ shares no code") and "sofast_station.optics" in b for b in broken), broken
