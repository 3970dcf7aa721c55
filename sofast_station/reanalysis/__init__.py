"""Re-analysis for the process engineer (docs/reanalysis.md).

- ``reprocess.py``: rerun the analysis of an HDF5 data dump from its raw frames, with optional overrides
  (facet model, design focal length, alignment point, measured distance, mask threshold, calibration
  record), and compare every figure with the archived result (:func:`reprocess_dump`).
- ``batch.py``: reprocess a folder or glob of dumps on the local cores or on a Dask cluster, resumably,
  with a summary workbook and CSV (:func:`run_batch`).
- ``cli.py``: ``register(subparsers)`` adds ``reprocess``, ``batch`` and ``report`` to ``sofast-station``
  (the pictures themselves live in :mod:`sofast_station.report`).

Nothing here is imported by the station loop; the modules import numpy only when used, so that the
command line can put BLAS on one thread before numpy loads (docs/conventions.md#determinism).
"""
