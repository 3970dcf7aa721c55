"""The field package's math is pure (docs/field.md, docs/architecture.md): geometry, sun, detect, orientation
and canting import, directly or indirectly, only themselves, measure/ and the plain data, and of libraries
numpy, scipy, OpenCV and pvlib (with pandas under it), no I/O; its files, pictures, command and twin studies
live in inputs, picture, cli and study. And the twin's field (twin/field.py) shares no code with it (the
twin's own rule, tests/test_architecture.py, rule 2)."""

from __future__ import annotations

import sys

import pytest

from tests.test_architecture import PACKAGE, PLAIN_DATA, STDLIB_IO, Graph, unit

MATH = ("geometry", "sun", "detect", "orientation", "canting", "prescription")
LIBRARIES = {"numpy", "scipy", "cv2", "numba", "pvlib", "pandas"}


@pytest.fixture(scope="module")
def graph():
    return Graph()


def test_the_field_math_imports_only_the_math_and_the_plain_data(graph):
    starts = [f"{PACKAGE}.field.{m}" for m in MATH]
    assert all(s in graph.modules for s in starts)
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    bad = []
    for name, chain in graph.reach(starts).items():
        if name in graph.modules:
            u = unit(name)
            ok = u in {"measure"} | PLAIN_DATA or name in starts or name == f"{PACKAGE}.field"
        else:
            lib = name.split(".")[0]
            ok = lib in LIBRARIES or (lib in stdlib and lib not in STDLIB_IO)
        if not ok:
            bad.append(" -> ".join([chain[0].source] + [f"{i.target} (line {i.line})" for i in chain]))
    assert not bad, "field math imports beyond the math and the plain data:\n" + "\n".join(bad)


def test_the_twin_field_does_not_reach_the_field_package(graph):
    reached = graph.reach([f"{PACKAGE}.twin.field"])
    assert not [m for m in reached if m.startswith(f"{PACKAGE}.field") or m.startswith(f"{PACKAGE}.measure")]
    assert "cv2" not in reached
    # the twin's spot, BCS photo and glare images on their own: not the field's, the optics' or the measure's
    reached = graph.reach([f"{PACKAGE}.twin.field_spot", f"{PACKAGE}.twin.glare_images"])
    banned = tuple(f"{PACKAGE}.{unit}" for unit in ("field", "measure", "optics"))
    assert not [m for m in reached if m in banned or m.startswith(tuple(b + "." for b in banned))]
