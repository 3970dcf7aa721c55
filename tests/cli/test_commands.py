"""The command registry: every command is reachable from ``sofast-station``, described, and every option
has a help text; the help is plain text."""

from __future__ import annotations

import argparse
import itertools
import subprocess
import sys

import pytest

from sofast_station.cli import build_parser
from sofast_station.commands import COMMAND_MODULES


def _commands(parser: argparse.ArgumentParser, path=()):
    """(path, parser) of every command and subcommand under *parser*."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield path + (name,), sub
                yield from _commands(sub, path + (name,))


ALL = list(_commands(build_parser()))


def test_every_command_of_the_registry_and_its_entry_points_is_there():
    names = {" ".join(p) for p, _ in ALL}
    for expected in ("inspect", "run", "dump-next", "archive export", "calibrate radiometric", "calibrate camera",
                     "calibrate geometry", "calibrate status", "reprocess", "batch", "report", "import-opencsp"):
        assert expected in names
    assert len(COMMAND_MODULES) == len(set(COMMAND_MODULES))


@pytest.mark.parametrize("path,parser", ALL, ids=[" ".join(p) for p, _ in ALL])
def test_each_command_has_a_description_and_every_option_a_help(path, parser):
    assert parser.description and len(parser.description.split()) >= 8, f"{' '.join(path)}: no description"
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            continue
        assert action.help, f"{' '.join(path)} {'/'.join(action.option_strings) or action.dest}: no help"
    text = parser.format_help()
    for markup in ("``", ":class:", ":func:", ":data:", ".. "):
        assert markup not in text, f"{' '.join(path)} --help shows reST markup {markup!r}"


def test_a_non_obvious_default_is_shown():
    helps = dict(ALL)
    text = helps[("calibrate", "camera")].format_help()
    assert "(default: 5)" in text and "(default: chessboard)" in text
    assert "(default: SIM-0001)" in helps[("inspect",)].format_help()


def test_top_level_help_is_plain_text_and_lists_the_commands():
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "--help"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    for markup in ("``", ":class:", ":func:", ":data:"):
        assert markup not in out
    for name in ("inspect", "run", "calibrate", "reprocess", "batch", "report", "import-opencsp", "archive"):
        assert f"\n    {name}" in out, name


def _listed_by_user(help_text: str) -> set[str]:
    """The commands the help's "Commands by user" block names ("calibrate screen | pose" is both), each as its
    words up to the first placeholder or option ("report certificate SERIAL" -> "report certificate")."""
    block = help_text.split("Commands by user:\n")[1].split("\n\n")[0]
    out = set()
    for line in block.splitlines():
        for item in line.strip().split("  ")[-1].strip().split(", "):
            first, *more = item.split(" | ")
            head = first.split(" ")[0]
            for said in [first] + [f"{head} {m}" for m in more]:
                words = [w for w in said.split(" ")]
                kept = list(itertools.takewhile(lambda w: not (w.isupper() or w.startswith("-")), words))
                out.add(" ".join(kept))
    return out


def test_help_lists_every_command_and_subcommand_by_its_user():
    """Issue 43: --help's "Commands by user" left out calibrate screen, pose and commission, batch's neighbours
    export surface and report flux, and the study commands. Now every command and subcommand the parser has
    (and every report 'report' makes, and export's one kind) is in it, under its user."""
    from sofast_station.reanalysis.cli import REPORT_WORDS
    from sofast_station.reanalysis.quality_reports import REPORTS

    listed = _listed_by_user(build_parser().format_help())
    wanted = set()
    for path, sub in ALL:
        if any(isinstance(a, argparse._SubParsersAction) for a in sub._actions):
            continue                                    # calibrate, study, archive: their subcommands are
        kinds = [a for a in sub._actions if not a.option_strings and a.choices]
        # a command whose first word picks what it does (export surface) is listed with that word
        wanted |= {" ".join(path + (c,)) for c in kinds[0].choices} if kinds else {" ".join(path)}
    wanted |= {f"report {w}" for w in REPORT_WORDS}
    assert set(REPORTS) <= set(REPORT_WORDS)
    assert not wanted - listed, f"not in --help: {sorted(wanted - listed)}"
    assert not listed - wanted, f"listed but no such command: {sorted(listed - wanted)}"


def test_building_the_parser_loads_no_numpy():
    """--help and argument errors answer at once: the commands load numpy only when they run."""
    code = "import sys; from sofast_station.cli import build_parser; build_parser(); print('numpy' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == "False", proc.stderr


def test_a_mistyped_command_is_a_usage_error_not_a_traceback():
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "inspekt"], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2 and "invalid choice" in proc.stderr and "Traceback" not in proc.stderr
