"""BLAS threads for bit-exact re-analysis (docs/conventions.md#determinism); imports nothing heavy.

The thread count of a BLAS library is read when the library loads, that is when numpy is first
imported; setting the variables afterwards has no effect. The command line therefore calls
:func:`single_thread_blas` before anything imports numpy, and worker processes (spawned, or Dask workers,
whose nanny sets the same variables by default) inherit them.
"""

from __future__ import annotations

import os

# Kept with the command registry, which every command (import-opencsp too) may import before numpy.
from ..commands import BLAS_THREAD_VARS, single_thread_blas  # noqa: F401  (this module's API)


def blas_threads() -> dict:
    """The BLAS thread variables as they are now (None: unset), for the re-analysis record."""
    return {var: os.environ.get(var) for var in BLAS_THREAD_VARS[:3]}


def blas_on_one_thread() -> bool:
    """Whether the OpenBLAS, OpenMP and MKL thread variables all say 1."""
    return all(v == "1" for v in blas_threads().values())
