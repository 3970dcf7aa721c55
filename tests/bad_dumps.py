"""Damaged and foreign files made from a good dump: each must give a clear error naming the file and the
problem (the dump reader's tests and the reprocess/batch tests use the same set)."""

from __future__ import annotations

import zlib
from pathlib import Path

import h5py
import numpy as np

from sofast_station.archive.dumps import SCHEMA_VERSION


def zero(p, good):
    p.write_bytes(b"")


def png(p, good):
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 200)


def truncated(p, good):
    p.write_bytes(good.read_bytes()[: good.stat().st_size * 6 // 10])


def corrupt(p, good):
    data = bytearray(good.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(b ^ 0xFF for b in data[mid:mid + 64])
    p.write_bytes(bytes(data))


def tampered(p, good):                     # a valid chunk with other pixels: only the digest notices
    p.write_bytes(good.read_bytes())
    with h5py.File(p, "r+") as f:
        ds = f["capture/frames"]
        frame = ds[3]
        frame[0, 0] ^= 1
        ds.id.write_direct_chunk((3, 0, 0), zlib.compress(frame.tobytes(), 4), 0)


def foreign(p, good):
    with h5py.File(p, "w") as f:
        f.create_dataset("images", data=np.zeros((2, 3)))


def newer(p, good):
    p.write_bytes(good.read_bytes())
    with h5py.File(p, "r+") as f:
        f.attrs["schema_version"] = np.int64(SCHEMA_VERSION + 1)


def missing(p, good):
    p.write_bytes(good.read_bytes())
    with h5py.File(p, "r+") as f:
        del f["geometry/camera/matrix"]


#: (name, how to make it from a good dump, what the error must say)
BAD_FILES = (
    ("zero-byte", zero, "is empty (0 bytes)"),
    ("png", png, "is not an HDF5 file (it looks like a PNG image)"),
    ("truncated", truncated, "is truncated"),
    ("corrupt", corrupt, "corrupt"),
    ("foreign", foreign, "is an HDF5 file but not a sofast-station dump"),
    ("newer", newer, "written by a newer sofast-station"),
    ("missing", missing, "lacks the dataset(s) geometry/camera/matrix"),
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
