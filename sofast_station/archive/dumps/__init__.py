"""HDF5 data dumps: everything needed to redo a facet's analysis bit for bit (docs/conventions.md#archives).

A dump holds the raw frames cropped to the facet region (outside the crop the frames are defined as 0;
:func:`restore_frames` rebuilds the full stack), the fringe definition, the radiometric calibration
record, the station geometry, the facet design, the analysis settings, the measured distance, the
station's configuration files as text with the configuration hash, the software version and the result
record. It is self-describing (a ``description`` and a ``units`` attribute on every group and dataset)
and versioned (root attributes ``schema = "sofast-station-dump"`` and ``schema_version``); the layout is
documented in ``docs/dump-schema.md`` and in :data:`SCHEMA_V1`.

The package's parts: ``schema.py`` (names, version, :data:`SCHEMA_V1`), ``content.py`` (:class:`DumpContent`,
the crop), ``writer.py`` (:func:`write_dump`), ``reader.py`` (:func:`read_dump` and its checks) and
``retention.py`` (names, listing, pruning, free disk). Import from the package: the names below are its
interface.

Frames are compressed losslessly (gzip level 4 with the shuffle filter, one chunk per frame, compressed on
all cores and written with direct chunk writes); a SHA-256 digest of every frame is stored and checked on
reading, so that a damaged file is detected rather than misread. A dump is written under a
temporary name in its folder, fsynced and renamed: a crash never leaves a partial dump under the final
name.

Re-analysis::

    content = read_dump("dump.h5")
    analysis = content.analyse()        # the same figures as content.record, timings excepted
"""

from .content import DumpContent, crop_to_facet, restore_frames
from .reader import read_dump
from .retention import disk_ok, dump_name, dump_path_for, list_dumps, prune_dumps
from .schema import COMPRESSION_LEVEL, KEY_FIGURES, SCHEMA, SCHEMA_V1, SCHEMA_V2, SCHEMA_V3, SCHEMA_VERSION
from .writer import DumpStats, write_dump

__all__ = ["COMPRESSION_LEVEL", "KEY_FIGURES", "SCHEMA", "SCHEMA_V1", "SCHEMA_V2", "SCHEMA_V3", "SCHEMA_VERSION",
           "DumpContent", "DumpStats",
           "crop_to_facet", "disk_ok", "dump_name", "dump_path_for", "list_dumps", "prune_dumps", "read_dump",
           "restore_frames", "write_dump"]
