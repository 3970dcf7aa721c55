"""Where a process's memory grows: a tracemalloc hook for leak hunts, off unless asked for.

``SOFAST_TRACEMALLOC_S=N`` in the environment (``benchmarks/soak.py --trace`` sets it for the archiver
and the analysis worker) makes :func:`start_from_env` follow the process's Python allocations: a baseline
snapshot after the first N seconds, then every N seconds one log line per top growth site since the
baseline (size, blocks, the allocating lines). It costs time and memory; it is for finding a leak, not for
production.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import tracemalloc

log = logging.getLogger(__name__)

ENV = "SOFAST_TRACEMALLOC_S"


def growth_lines(snapshot, baseline, top: int = 8, strip: str = "") -> list[str]:
    """The *top* sites of *snapshot* that grew most since *baseline* (tracemalloc snapshots), as text."""
    snapshot = snapshot.filter_traces([tracemalloc.Filter(False, tracemalloc.__file__),
                                       tracemalloc.Filter(False, "<frozen*")])
    stats = snapshot.compare_to(baseline, "traceback")
    lines = [f"{sum(s.size_diff for s in stats) / 1e6:+.3f} MB traced since the baseline"]
    for st in stats[:top]:
        if st.size_diff <= 0:
            break
        where = " <- ".join(f"{f.filename.replace(strip, '')}:{f.lineno}" for f in reversed(list(st.traceback)[-4:]))
        lines.append(f"{st.size_diff / 1e3:+9.1f} kB {st.count_diff:+6d} blocks  {where}")
    return lines


def start_from_env(name: str) -> bool:
    """In a station process called *name*: start the tracemalloc hook when ``SOFAST_TRACEMALLOC_S`` is set."""
    try:
        period = float(os.environ.get(ENV, "") or 0)
    except ValueError:
        return False
    if period <= 0:
        return False
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))) + "/"

    def watch():
        time.sleep(period)
        tracemalloc.start(8)
        baseline = tracemalloc.take_snapshot()
        log.warning("%s memory trace: baseline taken (pid %d); growth sites every %g s", name, os.getpid(), period)
        while True:
            time.sleep(period)
            for line in growth_lines(tracemalloc.take_snapshot(), baseline, strip=root):
                log.warning("%s memory trace: %s", name, line)

    threading.Thread(target=watch, name="memory-trace", daemon=True).start()
    return True
