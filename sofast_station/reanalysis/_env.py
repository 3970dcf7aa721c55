"""BLAS threads for bit-exact re-analysis (docs/conventions.md#determinism); imports nothing heavy.

The thread count of a BLAS library is read when the library loads, that is when numpy is first
imported; setting the variables afterwards has no effect. The command line therefore calls
:func:`single_thread_blas` before anything imports numpy, and worker processes (spawned, or Dask workers,
whose nanny sets the same variables by default) inherit them.
"""

from __future__ import annotations

import os
import sys

#: Environment variables that set the thread count of the BLAS/OpenMP libraries numpy may use.
BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def single_thread_blas() -> bool:
    """Ask for BLAS on one thread, unless the user set a thread count explicitly.

    Returns
    -------
    bool
        True when numpy was not loaded yet, so the setting takes effect in this process (it always
        takes effect in processes started afterwards).
    """
    for var in BLAS_THREAD_VARS:
        os.environ.setdefault(var, "1")
    return "numpy" not in sys.modules


def blas_threads() -> dict:
    """The BLAS thread variables as they are now (None: unset), for the re-analysis record."""
    return {var: os.environ.get(var) for var in BLAS_THREAD_VARS[:3]}


def blas_on_one_thread() -> bool:
    """Whether the OpenBLAS, OpenMP and MKL thread variables all say 1."""
    return all(v == "1" for v in blas_threads().values())
