"""The repository explains itself: no reference to a file outside it, and every pointer into
docs/conventions.md names a section that exists."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONVENTIONS = ROOT / "docs" / "conventions.md"
SOURCES = [ROOT / "README.md", ROOT / "station.toml"] + [
    p for d in ("sofast_station", "tests", "docs", "benchmarks", "fixtures", "calibration")
    for p in sorted((ROOT / d).rglob("*")) if p.suffix in (".py", ".md", ".toml", ".json", ".txt") and p.is_file()]

# Built here so that this file does not match itself.
OUTSIDE = ("SPEC" + ".md", "seeds" + "/")


def _anchors() -> set[str]:
    return set(re.findall(r'<a id="([a-z0-9-]+)"></a>', CONVENTIONS.read_text()))


def test_no_reference_to_files_outside_the_repository():
    found = [f"{p.relative_to(ROOT)}:{i}: {line.strip()}"
             for p in SOURCES if "LICENSE" not in p.name and "COPYRIGHT" not in p.name
             for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1)
             if any(o in line for o in OUTSIDE)]
    assert not found, "references to files outside the repository (point to docs/conventions.md instead):\n" + \
        "\n".join(found)


def test_every_pointer_into_the_conventions_names_a_section_that_exists():
    anchors = _anchors()
    assert {"frames", "phase", "unwrapping", "screen-positions", "slopes", "residuals", "focal-power", "twist",
            "boresight", "ground-truth", "determinism", "reported-figures"} <= anchors
    bad = []
    for p in SOURCES:
        for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if "conventions.md#" not in line:
                continue
            tail = line[line.index("conventions.md#"):]
            for name in re.findall(r"(?:conventions\.md|[\s`(,])#([a-z][a-z0-9-]*)", tail):
                if name not in anchors:
                    bad.append(f"{p.relative_to(ROOT)}:{i}: #{name}")
    internal = re.findall(r"\]\(#([a-z0-9-]+)\)", CONVENTIONS.read_text())
    bad += [f"docs/conventions.md link #{name}" for name in internal if name not in anchors]
    assert not bad, "pointers to missing sections of docs/conventions.md:\n" + "\n".join(bad)


# ---- every repository path the docs name exists ------------------------------------------------------------

#: The prose the checker reads: what a reader follows to a file.
DOCS = [ROOT / "README.md", ROOT / "CHANGES.md"] + sorted((ROOT / "docs").glob("*.md"))
#: A token whose first folder is one of these names a file or folder from the repository's root.
TOP_FOLDERS = ("sofast_station", "tests", "benchmarks", "fixtures", "docs", "calibration", ".ci")
#: Files at the root, named without a folder.
ROOT_FILES = ("station.toml", "setup-env", "pyproject.toml", "README.md", "CHANGES.md")
#: The package's subpackages: `measure/pipeline.py` is short for sofast_station/measure/pipeline.py.
SUBPACKAGES = tuple(sorted(p.parent.name for p in (ROOT / "sofast_station").glob("*/__init__.py")))
#: A maximal run of the characters a path is written with, and those that make it something else: a glob
#: (`*`), a placeholder (`<serial>`, `{date}`, `$DIR`), the user's home (`~/sofast-station-data`).
_RUN = re.compile(r"[\w./*<>{}~$%@+-]+")
_NOT_A_PATH = set("*<>{}~$%@+")
#: After a path, `name` or `, name` in backticks: a function, class or module constant defined in that file
#: (`station/runner.py` `StationRunner.cycle`, (`result/shift.py`, `ShiftTally`)).
_NAMED = re.compile(r"`?(?:,\s*|\s+)`([A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*)(?:\(\))?`")
_FILE_SUFFIXES = (".py", ".md", ".toml", ".json", ".h5", ".txt", ".csv", ".in", ".png")
#: A pointer into a docs page's section: `calibration.md#the-cameras-pose`.
_SECTION = re.compile(r"#([a-z0-9][a-z0-9-]*)")


def _repository_path(token: str) -> Path | None:
    """The file or folder *token* names in the repository, or None when it is not a repository path.

    Counted: paths under the top folders (`tests/station/test_run.py`, `fixtures/stations`), the root files,
    and module paths relative to the package (`measure/pipeline.py`; only with `.py`: without it,
    `result/record_json` and `calibration/radiometric` are HDF5 groups of a dump). Not counted: URLs and
    absolute paths, anything with a glob or a placeholder, the data folder's paths (`data_dir/...`,
    `opcua/server-key.pem`, `web/page-cert.pem`), a user's files (`DUMP.h5`, `batch.json`), OpenCSP's files.
    Bare module and page names (`soak.py`, `conventions.md`) are checked apart (:func:`stale_references`).
    """
    token = token.removeprefix("./")
    if not token or (token.startswith(("/", ".")) and not token.startswith(".ci/")):
        return None    # an absolute path, a URL's tail, .venv/..., an ellipsis
    first, _, rest = token.partition("/")
    suffix = Path(token).suffix
    if rest and first in TOP_FOLDERS:
        if first == "calibration" and not suffix:    # a dump's calibration group, not the repository's folder
            return None
        return ROOT / token
    if token in ROOT_FILES:
        return ROOT / token
    if rest and first in SUBPACKAGES and suffix == ".py":
        return ROOT / "sofast_station" / token
    return None


def _bare_names() -> dict[str, Path]:
    """Every .py and .md file name in the repository, with one file of that name (what a bare `soak.py` or
    `conventions.md` may name; a page's name is the docs page, as the docs use it)."""
    out = {p.name: p for d in ("sofast_station", "tests", "benchmarks", "calibration")
           for p in sorted((ROOT / d).rglob("*.py"))}
    out.update({p.name: p for p in DOCS})
    return out


def _sections(page: Path) -> set[str]:
    """The sections a link may name in *page*: its explicit anchors and its headings' GitHub slugs (lower
    case, punctuation dropped, spaces to hyphens)."""
    text = page.read_text()
    slugs = {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
             for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}
    return slugs | set(re.findall(r'<a id="([^"]+)"></a>', text))


def _defines(path: Path, name: str) -> bool:
    """Whether the Python file *path* defines *name*: a function, class or module-level name, a function or
    class nested anywhere in it, or ``Class.member``."""
    tree = ast.parse(path.read_text())

    def names(body) -> dict[str, ast.AST]:
        out = {}
        for node in body:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                out[node.name] = node
            elif isinstance(node, ast.Assign):
                out.update((t.id, node) for t in node.targets if isinstance(t, ast.Name))
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                out[node.target.id] = node
        return out

    head, *members = name.split(".")
    node = names(tree.body).get(head)
    if not members:
        return node is not None or any(isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                                       and n.name == head for n in ast.walk(tree))
    for member in members:
        if not isinstance(node, ast.ClassDef):
            return False
        node = names(node.body).get(member)
    return node is not None


def stale_references(text: str, where: str, bare_names: dict[str, Path]) -> list[str]:
    """What *text* cites in the repository and is not there, as ``where:line: what (why)``: a path, a bare
    module or page name of no file, a name not defined in the Python file beside it, a section not in the
    page before it (`docs/calibration.md#the-cameras-pose`)."""
    bad = []
    for i, line in enumerate(text.splitlines(), 1):
        for run in _RUN.finditer(line):
            token = run.group().rstrip(".,-")
            end = run.start() + len(token)
            if _NOT_A_PATH & set(token):
                continue
            path = _repository_path(token)
            if path is None and "/" not in token and not token.startswith(".") and Path(token).suffix in (".py", ".md"):
                path = bare_names.get(token)
                # OpenCSP's own files (OpenCSP's `example_process_facet_ensemble.py`) are not ours
                if path is None and not line[:run.start()].rstrip("` ").endswith("OpenCSP's"):
                    bad.append(f"{where}:{i}: {token} (no file of that name in the repository)")
                    continue
            if path is None:
                continue
            if not path.exists():
                bad.append(f"{where}:{i}: {token} (does not exist)")
                continue
            named = _NAMED.match(line, end)
            if path.suffix == ".py" and named and Path(named.group(1)).suffix not in _FILE_SUFFIXES:
                if not _defines(path, named.group(1)):
                    bad.append(f"{where}:{i}: {token} {named.group(1)} (not defined in that file)")
            section = _SECTION.match(line, end)
            if path.suffix == ".md" and section and section.group(1) not in _sections(path):
                bad.append(f"{where}:{i}: {token}#{section.group(1)} (no such section in that page)")
    return bad


def test_every_repository_path_the_docs_name_exists():
    """README.md, CHANGES.md and docs/*.md: every path into the repository they name exists, a function or
    class named beside its file is defined there, and a section named after its page is in it (what counts
    as a path: `_repository_path` and `stale_references`)."""
    names = _bare_names()
    bad = [b for p in DOCS for b in stale_references(p.read_text(), str(p.relative_to(ROOT)), names)]
    assert not bad, "the docs name files or definitions that do not exist (fix the reference):\n" + "\n".join(bad)


def test_every_pointer_into_a_docs_page_from_the_code_names_a_section_that_exists():
    """The package's, the benchmarks' and the tests' pointers into docs pages (`docs/calibration.md#...`, in
    docstrings and messages) name sections those pages have (this file's planted ones aside)."""
    bad = []
    for p in SOURCES:
        if p.suffix != ".py" or p == Path(__file__).resolve():
            continue
        for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            for page, name in re.findall(r"([\w-]+\.md)#([a-z0-9][a-z0-9-]*)", line):
                target = ROOT / "docs" / page
                if not target.exists() or name not in _sections(target):
                    bad.append(f"{p.relative_to(ROOT)}:{i}: {page}#{name}")
    assert not bad, "pointers to missing pages or sections of docs/:\n" + "\n".join(bad)


def test_the_path_check_finds_a_planted_stale_reference_and_nothing_that_is_not_a_path():
    """The checker against text whose answer is known: each planted stale reference is found (on its line),
    and none of the look-alikes that are not repository paths is."""
    names = _bare_names()
    planted = "\n".join([
        "see `benchmarks/corner_population.py` for the table",     # 1: a deleted benchmark
        "blocks of 16,384 points (measure/blocks.py).",            # 2: a deleted module, relative, bare prose
        "the fixture fixtures/stations/nowhere.toml, and docs/nowhere.md#frames",   # 3: two
        "the runner (`station/runner.py` `StationRunner.no_such_method`)",           # 4: a missing method
        "(`result/shift.py`, `no_such_function`)",                 # 5: a missing function
        "run `no_such_benchmark.py` or read `nowhere.md`",         # 6: bare names of no file
        "docs/calibration.md#no-such-section, opencsp.md#no-such-anchor",        # 7: sections
    ])
    found = stale_references(planted, "planted", names)
    assert [b.split(": ", 1)[1].split(" (")[0] for b in found] == [
        "benchmarks/corner_population.py", "measure/blocks.py", "fixtures/stations/nowhere.toml", "docs/nowhere.md",
        "station/runner.py StationRunner.no_such_method", "result/shift.py no_such_function",
        "no_such_benchmark.py", "nowhere.md", "docs/calibration.md#no-such-section",
        "opencsp.md#no-such-anchor"], found
    assert [int(b.split(":")[1]) for b in found] == [1, 2, 3, 3, 4, 5, 6, 6, 7, 7]
    fine = "\n".join([
        "`station/runner.py` `StationRunner.cycle`, (`result/shift.py`, `ShiftTally`), `measure/pipeline.py`.",
        "docs/calibration.md#the-cameras-pose (an anchor), opencsp.md#uncertainty-of-an-imported-measurement (a "
        "heading), conventions.md#frames",
        "https://github.com/sandialabs/OpenCSP/blob/main/tests/nowhere.py and /usr/bin/time",
        "~/sofast-station-data/dumps/x.h5, data_dir/calibration/camera, `DUMP.h5`, batch.json, A.h5",
        "tests/*/test_nowhere.py, sofast_station/{nowhere,elsewhere}.py, <serial>/nowhere.py, $DIR/tests/x.py",
        "the dump's result/record_json and calibration/radiometric/lut; web/page-cert.pem; robot/PLC; 1/f_x",
        "OpenCSP's `example_process_facet_ensemble.py`; ./setup-env test; .venv/bin/python; tests/test_docs.py:12",
    ])
    assert stale_references(fine, "fine", names) == []
def test_the_readme_is_short_and_opens_with_its_two_commands():
    """Issue 43: at most 150 lines, the two commands of its first lines as they were, and the heliostat
    station said in plain words (no powers of ten: its paragraph gave focal powers as +5.5e-4 /m)."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150, len(lines)
    assert lines[6:8] == ["    ./setup-env && .venv/bin/sofast-station inspect",
                          "    ./setup-env test && .venv/bin/python -m pytest -q"]
    assert not [line for line in lines if re.search(r"\de-\d", line)]
