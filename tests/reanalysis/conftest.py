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

import h5py
import numpy as np
import pytest

from tests.conftest import ROOT, SMALL_STATION


@dataclass(frozen=True)
class StationDumps:
    """The dumps of one run: ``good`` (3 dumps), ``fault`` (the dark capture), the journal and its folder."""

    good: tuple[Path, ...]
    fault: Path
    journal: Path
    folder: Path


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
    path.write_text(text + "\n[run]\ndump_every_n = 1\n")
    cfg = dataclasses.replace(load_config(path), data_dir=d / "data")
    service = Service(cfg, simulated_facets=4, console=lambda line: None)
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
                        folder=d / "data" / "dumps")


def copy_dump(src: Path, dst: Path) -> Path:
    """A copy of a dump (the originals are shared by the whole session)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
    return dst


# -- damaged and foreign files: each must give a clear error naming the file and the problem -----------------
def _zero(p, good):
    p.write_bytes(b"")


def _png(p, good):
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 200)


def _truncated(p, good):
    p.write_bytes(good.read_bytes()[: good.stat().st_size * 6 // 10])


def _corrupt(p, good):
    data = bytearray(good.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(b ^ 0xFF for b in data[mid:mid + 64])
    p.write_bytes(bytes(data))


def _foreign(p, good):
    with h5py.File(p, "w") as f:
        f.create_dataset("images", data=np.zeros((2, 3)))


def _newer(p, good):
    p.write_bytes(good.read_bytes())
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = np.int64(2)


def _missing(p, good):
    p.write_bytes(good.read_bytes())
    with h5py.File(p, "r+") as f:
        del f["geometry/camera/matrix"]


#: (name, how to make it from a good dump, what the error must say)
BAD_FILES = (
    ("zero-byte", _zero, "is empty (0 bytes)"),
    ("png", _png, "is not an HDF5 file (it looks like a PNG image)"),
    ("truncated", _truncated, "is truncated"),
    ("corrupt", _corrupt, "corrupt"),
    ("foreign", _foreign, "is an HDF5 file but not a sofast-station dump"),
    ("newer", _newer, "written by a newer sofast-station"),
    ("missing", _missing, "lacks the dataset(s) geometry/camera/matrix"),
)


def make_bad_files(folder: Path, good: Path) -> dict[Path, str]:
    """Every kind of bad file in *folder* (named ``bad-<kind>.h5``) -> the problem its error must state."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for name, make, problem in BAD_FILES:
        p = folder / f"bad-{name}.h5"
        make(p, good)
        out[p] = problem
    return out
