"""Issue 28: the archiver's memory stays flat at full resolution.

A dump reads a facet's frames from the spool and compresses them (12.5 MB at full resolution). With glibc's
default, once a block that size is freed the allocator may serve the next ones from its heaps, where small
objects allocated meanwhile pin them: the process keeps them. ``map_large_blocks`` (called first thing in
the archiver process) gives every block of 4 MB or more its own mapping, returned when freed. Run in a
fresh interpreter each way, since the setting is per process.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import sys
import numpy as np
from sofast_station.memory import map_large_blocks

def rss_mb():
    with open("/proc/self/status") as fh:
        return next(int(l.split()[1]) for l in fh if l.startswith("VmRSS:")) / 1024

if sys.argv[1] == "mapped":
    assert map_large_blocks()
base = rss_mb()
keep = []
for _ in range(6):
    frames = np.ones(12_500_000, np.uint8)     # a full-resolution capture's frames, every page touched
    keep.append(np.ones(1000))                 # what a dump allocates meanwhile: it pins the heap's top
    del frames
print(rss_mb() - base)
"""


def _kept_mb(mode: str) -> float:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True, env=env,
                         timeout=120, check=True)
    return float(out.stdout.strip())


@pytest.mark.skipif(not Path("/proc/self/status").exists() or not sys.platform.startswith("linux"),
                    reason="glibc and /proc only")
def test_freed_frames_go_back_to_the_system():
    # With the archiver's setting none of the six captures' frames is kept. (glibc's default kept one, 11.9
    # MB, in a fresh interpreter on this machine class, but not in every process state: the dynamic
    # threshold it raises depends on what was freed before, so the default is reported, not asserted.)
    mapped = _kept_mb("mapped")
    assert mapped < 3.0, (mapped, _kept_mb("default"))
