"""The station's archive: the journal, the Excel workbooks and the HDF5 data dumps
(docs/conventions.md#archives).

- :class:`Journal` (``journal.py``): append-only SQLite journal; a row is durable when ``append`` returns.
- ``workbook.py``: one workbook per day (or shift), rows flattened from the records, saved atomically.
- ``dumps/``: HDF5 data dumps (:func:`write_dump`, :func:`read_dump`, :func:`restore_frames`), retention
  (:func:`prune_dumps`) and the free-disk watch (:func:`disk_ok`); layout in ``docs/dump-schema.md``.
- ``spool.py``: the fast crash-safe spool of a facet's frames before the robot is released.
- :class:`Archiver` (``archiver.py``): drains journal and spool into workbooks and dumps, in the background.
"""

from .archiver import Archiver, ArchiverSettings, ArchiveReport
from .dumps import (SCHEMA, SCHEMA_VERSION, DumpContent, DumpStats, crop_to_facet, disk_ok, prune_dumps, read_dump,
                    restore_frames, write_dump)
from .journal import Journal, JournalRow, new_cycle_id
from .spool import spool_get, spool_list, spool_path, spool_put
from .workbook import WorkbookSettings, export_workbook, read_workbook, write_pending

__all__ = ["Archiver", "ArchiverSettings", "ArchiveReport", "SCHEMA", "SCHEMA_VERSION", "DumpContent", "DumpStats",
           "crop_to_facet", "disk_ok", "prune_dumps", "read_dump", "restore_frames", "write_dump", "Journal",
           "JournalRow", "new_cycle_id", "spool_get", "spool_list", "spool_path", "spool_put", "WorkbookSettings",
           "export_workbook", "read_workbook", "write_pending"]
