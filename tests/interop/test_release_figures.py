"""Issue 48 item 8: the station's figures on OpenCSP's real capture stay put between versions. Each case of
``fixtures/opencsp/release_figures.json`` (the last release's figures with their U) is computed again; a figure that
moved by more than a third of its U, or points kept that moved by more than 1 %, fails here until CHANGES.md's
unreleased section names it (``- `CASE` `FIGURE`: size and cause``)."""

from __future__ import annotations

import json

import pytest

from sofast_station.interop import release
from sofast_station.interop.conformance import RELEASE_CASES, release_figures


@pytest.fixture(scope="module")
def kept(repo_root):
    return json.loads((repo_root / "fixtures/opencsp/release_figures.json").read_text())


def test_every_figure_of_the_last_release_stays_put_or_changes_md_says_why(repo_root, kept, tmp_path):
    assert set(kept["cases"]) == set(RELEASE_CASES)
    now = release_figures(repo_root / "fixtures/opencsp/test_data", work=tmp_path)
    moves = release.moved(kept["cases"], now)
    for m in moves:
        print(m)
    left = release.unexplained(moves, (repo_root / "CHANGES.md").read_text())
    assert not left, (f"{len(left)} figure(s) on OpenCSP's real capture moved since {kept['release']} and CHANGES.md's "
                      f"unreleased section does not name them: {left}")


def test_a_moved_figure_fails_until_named_in_the_unreleased_section():
    """The gate itself: a move beyond U/3 is found, a move within it is not; only the unreleased section's
    lines count, case before figure."""
    kept = {"a/plain/x1": {"focal_length_x_m": [100.0, 1.5], "n_points": 1000}}
    assert release.moved(kept, {"a/plain/x1": {"focal_length_x_m": 100.4, "n_points": 1005}}) == []
    moves = release.moved(kept, {"a/plain/x1": {"focal_length_x_m": 100.6, "n_points": 980}})
    assert {(m["case"], m["figure"]) for m in moves} == {("a/plain/x1", "focal_length_x_m"), ("a/plain/x1", "n_points")}
    text = ("# Changes\n\n## 0.9.0 (unreleased)\n\n- `a/plain/x1` `focal_length_x_m`: +0.6 m: why\n\n"
            "## 0.8.0 (2026-01-01)\n\n- `a/plain/x1` `n_points`: an old entry does not count\n")
    assert [(m["case"], m["figure"]) for m in release.unexplained(moves, text)] == [("a/plain/x1", "n_points")]
    released = text.replace("(unreleased)", "(2026-02-01)")
    assert len(release.unexplained(moves, released)) == 2
