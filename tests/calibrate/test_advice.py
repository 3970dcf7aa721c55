"""The calibration routines' advice names only options their commands have (issue 12, item 9).

Every ``--option`` written in a message of the radiometric routine (its errors and log warnings) must be an
option of ``sofast-station calibrate radiometric``; the camera calibration's refusal advice likewise for
``calibrate camera``. The messages are read from the sources' string literals (f-strings included), so a
message that is only printed in a rare failure is checked too.
"""

from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

import pytest

from sofast_station.station.calibrate_cli import register

CALIBRATE = Path(__file__).resolve().parents[2] / "sofast_station" / "calibrate"
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")


def message_options(path: Path) -> set[str]:
    """``--options`` named in the string literals of *path* (docstrings left out)."""
    tree = ast.parse(path.read_text())
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef)):
            body = getattr(node, "body", [])
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                docstrings.add(id(body[0].value))
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            found |= set(OPTION.findall(node.value))
    return found


def parser_options(command: str) -> set[str]:
    parser = argparse.ArgumentParser(prog="sofast-station")
    register(parser.add_subparsers(dest="command", required=True))
    sub = next(a for a in parser._subparsers._group_actions[0].choices["calibrate"]._actions
               if isinstance(a, argparse._SubParsersAction)).choices[command]
    return {s for a in sub._actions for s in a.option_strings}


@pytest.mark.parametrize("module, command", [("radiometric.py", "radiometric"), ("camera.py", "camera"),
                                             ("camera_position.py", "camera-position"), ("dot_locations.py", "dots")])
def test_advice_names_only_options_the_command_has(module, command):
    named = message_options(CALIBRATE / module)
    have = parser_options(command)
    print(f"\n{module}: names {sorted(named)}; 'calibrate {command}' has {sorted(have)}")
    assert named, f"{module} names no option at all: the test would prove nothing"
    assert named <= have, f"{module} advises {sorted(named - have)}, which 'calibrate {command}' does not have"


def test_the_check_sees_a_wrong_option(tmp_path):
    """The check itself: an option the command lacks is caught (an advice as it was before this issue)."""
    path = tmp_path / "probe.py"
    path.write_text('raise CalibrationError("lower the gain (--gain-maximum)")\n')
    assert message_options(path) == {"--gain-maximum"}
    assert not message_options(path) <= parser_options("radiometric")
