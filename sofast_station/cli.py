"""The ``sofast-station`` command: the parser of every registered command, and ``main``.

The commands live with the program that runs them (``station/cli.py``, ``station/calibrate_cli.py``,
``reanalysis/cli.py``, ``interop/cli.py``) and are listed once, in
:data:`sofast_station.commands.COMMAND_MODULES`. Nothing imports this module but the entry points
(``sofast-station``, ``python -m sofast_station``).
"""

from __future__ import annotations

import argparse
import sys

from . import commands

#: Every command, by the user who runs it: what ``--help`` lists (tests/cli/test_commands.py checks that every
#: command and subcommand the parser has is here, so a new one cannot be left out of ``--help``).
USERS = (
    ("the production line", ("inspect", "run", "dump-next", "archive export")),
    ("the operator", ("serve", "run --serve")),
    ("the morning calibration", ("calibrate radiometric", "calibrate status", "calibrate camera",
                                 "calibrate geometry")),
    ("commissioning", ("calibrate commission", "calibrate screen", "calibrate pose", "calibrate marks",
                       "calibrate confirm-geometry", "calibrate camera-position", "calibrate dots",
                       "calibrate screen-data")),
    ("the process engineer", ("reprocess", "batch", "report DUMP", "report trend", "report flux", "export surface",
                              "import-opencsp")),
    ("the quality engineer", ("report spc", "report acceptance", "report certificate SERIAL", "report diff A B")),
    ("the metrologist", ("study repeatability", "study population", "study methods")),
    ("the field engineer", ("field orientation", "field canting", "field prescription", "field spot", "field glare")),
)


def users_text(users=USERS) -> str:
    """The "Commands by user" lines: a command's subcommands after its first one joined by " | "."""
    lines = []
    for user, theirs in users:
        said: list[str] = []
        for command in theirs:
            head, _, rest = command.partition(" ")
            if said and rest and not rest.startswith("-") and said[-1].split(" ")[0] == head:
                said[-1] += f" | {rest}"
            else:
                said.append(command)
        lines.append(f"  {user:<25} {', '.join(said)}")
    return "\n".join(lines)


DESCRIPTION = f"""\
sofast-station measures concentrating-solar mirror facets by fringe reflection (deflectometry), after
Sandia's SOFAST: an LCD shows phase-shifted fringes, a camera watches their reflection in the facet, and
the station reports focal lengths, twist and slope errors for every facet, with a verdict. With no
hardware attached the station is simulated by a ray-traced digital twin whose facet has a known shape.

The station is described by a station file (--config; ./station.toml by default). Everything it writes
goes under the file's data_dir (one folder per station; ~/sofast-station-data unless set; the environment
variable SOFAST_DATA_DIR overrides it).

Commands by user:
{users_text()}
"""

EPILOG = """\
examples:
  sofast-station inspect                      measure the facet in the fixture once
  sofast-station run --facets 50              the simulated robot places 50 facets
  sofast-station calibrate radiometric        the daily radiometric calibration
  sofast-station reprocess DUMP.h5            recompute a data dump and compare with the archive

'sofast-station COMMAND --help' describes a command and its options. Definitions of every figure:
docs/conventions.md; the method: docs/method.md.
"""


def build_parser() -> argparse.ArgumentParser:
    """The ``sofast-station`` parser with every command of :data:`~sofast_station.commands.COMMAND_MODULES`."""
    return commands.build_parser(description=DESCRIPTION, epilog=EPILOG)


def main(argv: list[str] | None = None) -> int:
    return commands.run(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
