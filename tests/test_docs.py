"""The repository explains itself: no reference to a file outside it, and every pointer into
docs/conventions.md names a section that exists."""

from __future__ import annotations

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


def test_the_readme_is_short_and_opens_with_its_two_commands():
    """Issue 43: at most 150 lines, the two commands of its first lines as they were, and the heliostat
    station said in plain words (no powers of ten: its paragraph gave focal powers as +5.5e-4 /m)."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150, len(lines)
    assert lines[6:8] == ["    ./setup-env && .venv/bin/sofast-station inspect",
                          "    ./setup-env test && .venv/bin/python -m pytest -q"]
    assert not [line for line in lines if re.search(r"\de-\d", line)]
