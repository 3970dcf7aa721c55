"""Dumps of the small simulated station for the re-analysis tests (made once per test session).

Four facets go through the production loop with a dump of every facet: three good ones and one whose
capture is dark (a fault, dumped because ``dump_failed`` is on). Tests copy these files before changing
them; nothing writes into the source tree.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import ROOT, SMALL_STATION


@dataclass(frozen=True)
class StationDumps:
    """The dumps of one run: ``good`` (3 dumps), ``fault`` (the dark capture), the journal and its folder, the
    station file and the lines the line printed on its console."""

    good: tuple[Path, ...]
    fault: Path
    journal: Path
    folder: Path
    config: Path
    console: tuple[str, ...]


@pytest.fixture(scope="session")
def station_dumps(tmp_path_factory) -> StationDumps:
    from sofast_station.archive import Journal
    from sofast_station.config import load_config
    from sofast_station.station.service import Service

    d = tmp_path_factory.mktemp("reanalysis-station")
    path = d / "station.toml"
    text = SMALL_STATION.format(data_dir=d / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                radiometric=ROOT / "calibration/simulated_radiometric.json")
    text = text.replace("[simulation]\nseed = 3\n", '[simulation]\nseed = 3\nfaults = { "SIM-0004" = "dark" }\n')
    # Dumps, not a cycle-time test: a generous deadline keeps the fixture independent of machine load.
    path.write_text(text + "\n[run]\ndump_every_n = 1\ndeadline_s = 60\n")
    cfg = dataclasses.replace(load_config(path), data_dir=d / "data")
    console: list[str] = []
    service = Service(cfg, simulated_facets=4, console=console.append)
    try:
        service.runner.run()
    finally:
        service.close()
    journal = Journal(d / "data" / "journal.sqlite3")
    try:
        rows = {r.serial: r for r in journal.rows()}
    finally:
        journal.close()
    assert all(rows[s].dump_status == "written" for s in ("SIM-0001", "SIM-0002", "SIM-0003", "SIM-0004")), rows
    assert rows["SIM-0004"].verdict == "fault"
    good = tuple(Path(rows[s].dump_path) for s in ("SIM-0001", "SIM-0002", "SIM-0003"))
    return StationDumps(good=good, fault=Path(rows["SIM-0004"].dump_path), journal=d / "data" / "journal.sqlite3",
                        folder=d / "data" / "dumps", config=path, console=tuple(console))


def copy_dump(src: Path, dst: Path) -> Path:
    """A copy of a dump (the originals are shared by the whole session)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    return dst
