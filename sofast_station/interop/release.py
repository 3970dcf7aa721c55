"""Figures on OpenCSP's real capture that stay put between versions, unless CHANGES.md says why they moved.

At each release, ``python -m sofast_station.interop.release --write`` keeps the station's figures on
OpenCSP's capture with their U (:func:`~sofast_station.interop.conformance.release_figures`) in
``fixtures/opencsp/release_figures.json``. Between releases, :func:`moved` names every figure that moved by
more than a third of its U (or the points kept by more than 1 %), and :func:`explained` reads which of them
the unreleased section of CHANGES.md names; tests/interop/test_release_figures.py fails on any moved and not
named. ``python -m sofast_station.interop.release`` prints the comparison.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

from .. import __version__
from .conformance import release_figures

ROOT = Path(__file__).resolve().parents[2]
RELEASE_FILE = ROOT / "fixtures/opencsp/release_figures.json"
CHANGES = ROOT / "CHANGES.md"
#: A figure has moved when it differs from the release's by more than this share of the release's U (k = 2).
SHARE_OF_U = 1.0 / 3.0
#: The points kept have moved when they differ by more than this fraction.
POINTS_FRACTION = 0.01


def moved(release: dict, current: dict) -> list[dict]:
    """The figures of *current* (:func:`~.conformance.release_figures`, values) that moved from *release*'s
    (the file's ``cases``: [value, U] pairs and ``n_points``): case, figure, before, after, U, and the move
    in units of U (or of the points' fraction)."""
    out = []
    for case, before in release.items():
        now = current.get(case)
        if now is None:
            out.append({"case": case, "figure": "*", "before": None, "after": None, "U": None,
                        "why": "the case was not computed"})
            continue
        for figure, old in before.items():
            new = now.get(figure)
            if figure == "n_points":
                if new is None or abs(new - old) > POINTS_FRACTION * old:
                    out.append({"case": case, "figure": figure, "before": old, "after": new, "U": None,
                                "moved_by": None if new is None else (new - old) / old})
                continue
            value, u = old
            if new is None or value is None:
                if new != value:
                    out.append({"case": case, "figure": figure, "before": value, "after": new, "U": u,
                                "moved_by": None})
                continue
            if u is None or abs(new - value) > SHARE_OF_U * u:
                out.append({"case": case, "figure": figure, "before": value, "after": new, "U": u,
                            "moved_by": None if not u else (new - value) / u})
    return out


def unreleased_section(text: str) -> str:
    """The text of CHANGES.md's first version section (the one being worked on: ``## X.Y.Z (unreleased)``);
    empty when the first section is a released one."""
    sections = re.split(r"^## ", text, flags=re.M)
    for s in sections[1:]:
        head = s.splitlines()[0] if s else ""
        return s if "unreleased" in head else ""
    return ""


def explained(text: str) -> set[tuple[str, str]]:
    """The (case, figure) pairs the unreleased section of CHANGES.md (*text*) names, each in a line
    ``- `CASE` `FIGURE`: ...`` (a line may name several pairs, case before figure)."""
    out = set()
    for line in unreleased_section(text).splitlines():
        ticks = re.findall(r"`([^`]+)`", line)
        case = None
        for t in ticks:
            if "/" in t:
                case = t
            elif case is not None:
                out.add((case, t))
    return out


def unexplained(moves: list[dict], text: str) -> list[dict]:
    """The *moves* (:func:`moved`) that CHANGES.md's unreleased section does not name."""
    named = explained(text)
    return [m for m in moves if (m["case"], m["figure"]) not in named]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m sofast_station.interop.release", description=__doc__.split("\n\n")[0])
    p.add_argument("--write", action="store_true", help="keep the current figures as this release's (at a release)")
    p.add_argument("--test-data", default=str(ROOT / "fixtures/opencsp/test_data"), metavar="DIR")
    args = p.parse_args(argv)

    if args.write:
        cases = release_figures(Path(args.test_data), with_u=True)
        previous = json.loads(RELEASE_FILE.read_text()) if RELEASE_FILE.exists() else {}

        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout.strip()
        RELEASE_FILE.write_text(json.dumps({"release": __version__, "commit": commit, "what": previous.get("what", ""),
                                            "cases": cases}, indent=1) + "\n")
        print(f"{RELEASE_FILE}: the figures of {__version__} ({len(cases)} cases)")
        return 0
    release = json.loads(RELEASE_FILE.read_text())
    moves = moved(release["cases"], release_figures(Path(args.test_data)))
    left = unexplained(moves, CHANGES.read_text() if CHANGES.exists() else "")
    for m in moves:
        tag = "NOT IN CHANGES.md" if m in left else "named in CHANGES.md"
        print(f"{m['case']} {m['figure']}: {m['before']} -> {m['after']} ({tag})")
    print(f"{len(moves)} figure(s) moved since {release['release']}, {len(left)} not named in CHANGES.md")
    return 1 if left else 0


if __name__ == "__main__":
    sys.exit(main())
