"""Memory a long-lived process hands back to the system (glibc's ``malloc_trim`` and mmap threshold;
nothing where they do not exist)."""

from __future__ import annotations

import ctypes
import gc


def release_memory() -> None:
    """Give the memory a large piece of work freed back to the system (a full garbage collection, then
    glibc's ``malloc_trim``; nothing where that does not exist).

    A workbook save (a part streamed from the journal), a dump (a facet's frames) allocate and free a few
    MB; freed, that memory would otherwise stay with the long-lived archiver process at its high-water
    mark.
    """
    gc.collect()
    trim_heap()


def trim_heap() -> None:
    """Hand the heap's free pages back to the system (glibc's ``malloc_trim``; nothing elsewhere).

    A long-lived process that frees hundreds of MB per cycle (the analysis worker's per-pixel arrays)
    otherwise keeps them at its high-water mark and, with several threads' arenas, lets that mark creep
    up (the full-resolution soak: about 30 MB per 100 facets). An analysis loop at full resolution rose
    from 558 to 585 MB over 30 facets without it and stayed between 454 and 485 MB over 60 with it.
    Costs about a millisecond.
    """
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


#: Allocations of at least this many bytes get a mapping of their own (glibc), see :func:`map_large_blocks`.
LARGE_BLOCK_BYTES = 4 << 20


def map_large_blocks(threshold_bytes: int = LARGE_BLOCK_BYTES) -> bool:
    """Make glibc serve every allocation of at least *threshold_bytes* from a mapping of its own, handed
    back to the system when freed (``mallopt(M_MMAP_THRESHOLD)``; False where that does not exist).

    By default glibc raises that threshold to the size of the largest block freed so far (up to 32 MB):
    after the first facet's frames (12.5 MB at full resolution) a process serves such blocks from its
    heaps, where they fragment and stay. The archiver reads a spool and writes a dump per faulted or
    scheduled facet: with the default it rose by 9 MB per 100 full-resolution cycles in steps (a
    320-cycle soak); in a loop of 240 dumps, run with and without, its memory was 24 MB lower and flat
    (72.8 -> 75.3 MB against 96.8 -> 103.1 MB) with this threshold. Call once, early in the process.
    Not in the station or the analysis worker: they allocate and free dozens of such blocks per facet (the
    twin's renders, the per-pixel arrays), and a fresh mapping is zeroed page by page each time (the
    simulated line's cycle took 48 % longer with it in the station); the worker trims its heap instead.
    """
    try:
        return bool(ctypes.CDLL("libc.so.6").mallopt(-3, int(threshold_bytes)))   # -3: M_MMAP_THRESHOLD
    except (OSError, AttributeError):
        return False
