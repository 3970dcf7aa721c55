"""HDF5 data dumps: everything needed to redo a facet's analysis bit for bit (docs/conventions.md#archives).

A dump holds the raw frames cropped to the facet region (outside the crop the frames are defined as 0;
:func:`restore_frames` rebuilds the full stack), the fringe definition, the radiometric calibration
record, the station geometry, the facet design, the analysis settings, the measured distance, the
station's configuration files as text with the configuration hash, the software version and the result
record. It is self-describing (a ``description`` and a ``units`` attribute on every group and dataset)
and versioned (root attributes ``schema = "sofast-station-dump"`` and ``schema_version``); the layout is
documented in ``docs/dump-schema.md`` and in :data:`SCHEMA_V1`.

Frames are compressed losslessly (gzip level 4 with the shuffle filter, one chunk per frame, compressed on
all cores and written with direct chunk writes); a SHA-256 digest of every frame is stored and checked on
reading, so that a damaged file is detected rather than misread. A dump is written under a
temporary name in its folder, fsynced and renamed: a crash never leaves a partial dump under the final
name.

Re-analysis::

    content = read_dump("dump.h5")
    analysis = content.analyse()        # the same figures as content.record, timings excepted
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import ArchiveError, DumpError
from ._common import (fault_point, fsync_dir, fsync_file, is_temp_file, json_ready, now_iso, parse_time, safe_name,
                      temp_path_for, to_json)

log = logging.getLogger(__name__)

#: Root attribute ``schema`` of every dump.
SCHEMA = "sofast-station-dump"
#: Version of the layout this software writes (and the newest it reads).
SCHEMA_VERSION = 1

#: gzip level of the frames (lossless; level 4 is within 1 % of level 9's size at a third of the time).
COMPRESSION_LEVEL = 4

#: Figures of the result record copied to attributes of ``/result`` (dotted names flatten nested dicts).
KEY_FIGURES = ("verdict", "focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
               "twist_mrad_per_m", "slope_rms_mrad.design.magnitude", "slope_rms_mrad.parabola.magnitude",
               "slope_rms_mrad.higher_order.magnitude", "boresight_mrad.x", "boresight_mrad.y", "n_points",
               "valid_fraction", "median_modulation_dn", "measured_distance_m")

_MAGIC = ((b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"\xff\xd8\xff", "a JPEG image"),
          (b"PK\x03\x04", "a ZIP archive (an .xlsx, .npz or .zip file?)"), (b"II*\x00", "a TIFF image"),
          (b"MM\x00*", "a TIFF image"), (b"SQLite format 3", "an SQLite database"), (b"%PDF", "a PDF document"),
          (b"{", "JSON or other text"), (b"\x93NUMPY", "a NumPy .npy file"))

# -- the schema ---------------------------------------------------------------------------------------
#: Every group, dataset and root attribute of schema version 1:
#: (path, kind, dtype, units, description, required). ``*`` in a path matches any one name.
SCHEMA_V1: tuple[tuple[str, str, str, str, str, bool], ...] = (
    ("/@schema", "attribute", "str", "", 'always "sofast-station-dump"', True),
    ("/@schema_version", "attribute", "int64", "", "layout version of this file (1)", True),
    ("/@description", "attribute", "str", "", "what the file is", True),
    ("/@software_version", "attribute", "str", "", "sofast-station version that measured and wrote the dump", True),
    ("/@created", "attribute", "str", "ISO 8601", "when the dump file was written (local time with UTC offset)", True),
    ("/@cycle_id", "attribute", "str", "", "the inspection cycle's unique id (the journal's key)", True),
    ("/@serial", "attribute", "str", "", "the facet's serial number", True),
    ("/@time", "attribute", "str", "ISO 8601", "time of the measurement (the record's time, with UTC offset)", True),
    ("/@config_hash", "attribute", "str", "", "SHA-256 (16 hex digits) of the station and facet configuration", True),
    ("/@station", "attribute", "str", "", "station name from station.toml", False),
    ("/@facet", "attribute", "str", "", "facet design name", False),

    ("capture", "group", "", "", "the raw camera frames and the measured distance", True),
    ("capture/frames", "dataset", "uint8 (n, h, w)", "DN",
     "camera frames cropped to the facet region, in capture order (dark, white, then the fringe frames of "
     "fringes/, x then y, coarse to fine, phase steps in order); gzip 4 + shuffle, one chunk per frame; "
     "outside the crop the full frames are 0 by definition", True),
    ("capture/frames_sha256", "dataset", "str (n,)", "",
     "SHA-256 (hex) of each cropped frame's bytes in C order, checked by read_dump", True),
    ("capture/crop_box", "dataset", "int64 (2,)", "px",
     "(row0, col0): image row and column of the crop's top-left pixel in the full frame", True),
    ("capture/full_shape", "dataset", "int64 (2,)", "px", "(rows, columns) of the full camera frame", True),
    ("capture/patterns", "dataset", "str (n,)", "", "label of the display image shown for each frame", True),
    ("capture/measured_distance_m", "dataset", "float64", "m",
     "measured distance from the screen centre to the design's measure point", True),

    ("fringes", "group", "", "", "the fringe definition (station.toml [fringes])", True),
    ("fringes/periods_x", "dataset", "float64 (k,)", "cycles per screen width", "x fringe periods, coarse to fine", True),
    ("fringes/periods_y", "dataset", "float64 (k,)", "cycles per screen height", "y fringe periods, coarse to fine", True),
    ("fringes/phase_steps", "dataset", "int64", "", "phase steps per period (shifts 2 pi k / steps)", True),

    ("calibration", "group", "", "", "calibration records in force at the measurement", True),
    ("calibration/radiometric", "group", "", "", "the radiometric (display -> camera) calibration record", True),
    ("calibration/radiometric/schema", "dataset", "int64", "", "the record's own schema version", True),
    ("calibration/radiometric/kind", "dataset", "str", "", 'always "radiometric"', True),
    ("calibration/radiometric/record_id", "dataset", "str", "", "record id", True),
    ("calibration/radiometric/created", "dataset", "str", "ISO 8601", "when the calibration was made", True),
    ("calibration/radiometric/source", "dataset", "str", "", "how the record came to be", True),
    ("calibration/radiometric/lut", "dataset", "float64 (N,)", "command / 255",
     "lookup table: display command as a function of linear response level 0..1 (N even steps)", True),
    ("calibration/radiometric/floor_level", "dataset", "float64", "linear response level 0..1",
     "level of the fringe minimum (the calibrated floor)", True),
    ("calibration/radiometric/max_level", "dataset", "float64", "linear response level 0..1",
     "level of the fringe maximum", True),
    ("calibration/radiometric/exposure_s", "dataset", "float64", "s", "camera exposure time", True),
    ("calibration/radiometric/gain", "dataset", "float64", "1", "camera gain (linear factor)", True),
    ("calibration/radiometric/dark_level_dn", "dataset", "float64", "DN",
     "mean dark level at calibration (records from the daily routine)", False),
    ("calibration/radiometric/latency_frames", "dataset", "int64", "frames",
     "display-to-camera latency found by the routine", False),
    ("calibration/radiometric/settle_s", "dataset", "float64", "s", "settle time the latency implies", False),
    ("calibration/radiometric/refresh_hz", "dataset", "float64", "Hz", "display refresh rate used", False),

    ("geometry", "group", "", "",
     "station geometry: camera intrinsics, screen, poses (frames: docs/conventions.md#frames)", True),
    ("geometry/camera", "group", "", "", "camera intrinsics, OpenCV pinhole + 5-term distortion", True),
    ("geometry/camera/width_px", "dataset", "int64", "px", "image width", True),
    ("geometry/camera/height_px", "dataset", "int64", "px", "image height", True),
    ("geometry/camera/matrix", "dataset", "float64 (3, 3)", "px", "camera matrix K [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]", True),
    ("geometry/camera/distortion", "dataset", "float64 (5,)", "1", "distortion k1, k2, p1, p2, k3 (OpenCV)", True),
    ("geometry/screen", "group", "", "", "the flat display", True),
    ("geometry/screen/width_px", "dataset", "int64", "px", "display width", True),
    ("geometry/screen/height_px", "dataset", "int64", "px", "display height", True),
    ("geometry/screen/pitch_m", "dataset", "float64", "m", "display pixel pitch", True),
    ("geometry/screen_to_camera", "group", "", "", "pose mapping screen-frame points to the camera frame", True),
    ("geometry/screen_to_camera/rotation", "dataset", "float64 (3, 3)", "1", "rotation matrix", True),
    ("geometry/screen_to_camera/translation", "dataset", "float64 (3,)", "m", "screen origin in the camera frame", True),
    ("geometry/fixture_to_camera", "group", "", "", "pose of the nominal facet frame in the camera frame", True),
    ("geometry/fixture_to_camera/rotation", "dataset", "float64 (3, 3)", "1", "rotation matrix", True),
    ("geometry/fixture_to_camera/translation", "dataset", "float64 (3,)", "m", "fixture origin in the camera frame", True),

    ("design", "group", "", "", "the facet design (recipe), facet frame", True),
    ("design/name", "dataset", "str", "", "design name", True),
    ("design/kind", "dataset", "str", "", "dish, gore or heliostat", True),
    ("design/focal_length_m", "dataset", "float64", "m", "design focal length of z = (x^2 + y^2) / (4 f)", True),
    ("design/outline_m", "dataset", "float64 (N, 2)", "m", "outline corners (x, y), counter-clockwise from +z", True),
    ("design/measure_point_m", "dataset", "float64 (2,)", "m", "(x, y) of the range finder's point", True),
    ("design/alignment_point_m", "dataset", "float64 (2,)", "m", "(x, y) of the boresight alignment point", True),
    ("design/layout", "group", "", "", "the facet file's [facet.layout] table (may be empty)", True),
    ("design/layout/*", "dataset", "from the value", "from the name's suffix (_m: m, _mrad: mrad)",
     "one [facet.layout] entry", False),

    ("analysis", "group", "", "", "analysis settings (station.toml [analysis], defaults filled in)", True),
    ("analysis/mask_threshold_dn", "dataset", "int64 or float64", "DN", "facet pixel when white - dark exceeds this", True),
    ("analysis/min_modulation_dn", "dataset", "int64 or float64", "DN", "least fringe amplitude kept", True),
    ("analysis/consistency_sigmas", "dataset", "int64 or float64", "noise sigmas", "I0 + I2 = I1 + I3 check limit", True),
    ("analysis/guard_sigmas", "dataset", "int64 or float64", "position noise sigmas", "screen-edge guard band", True),
    ("analysis/subsample_step", "dataset", "int64", "pixels", "every n-th valid pixel while iterating", True),
    ("analysis/max_iterations", "dataset", "int64", "", "iteration limit", True),
    ("analysis/max_range_shift_m", "dataset", "float64", "m", "largest accepted range correction", True),
    ("analysis/corner_tolerance_px", "dataset", "float64", "px", "largest corner distance from nominal", True),
    ("analysis/max_hole_px", "dataset", "int64", "px", "holes up to this area are filled", True),
    ("analysis/max_saturated_fraction", "dataset", "float64", "1", "largest accepted saturated fraction", True),
    ("analysis/max_corner_rms_px", "dataset", "float64", "px", "largest accepted corner RMS", True),
    # added after the first dumps were written: optional, the analysis's defaults apply when absent
    ("analysis/robust_fit", "dataset", "bool", "", "parabola fitted by bisquare-weighted least squares", False),
    ("analysis/edge_window_px", "dataset", "int64", "px", "half-width of the window summed across a facet edge",
     False),
    ("analysis/threads", "dataset", "int64", "", "threads of the analysis (the figures do not depend on it)", False),

    ("config", "group", "", "", "the station configuration as loaded", True),
    ("config/station_toml", "dataset", "str", "", "raw text of station.toml (empty if it could not be read)", True),
    ("config/facet_toml", "dataset", "str", "", "raw text of the facet file (empty if it could not be read)", True),
    ("config/station_path", "dataset", "str", "", "where station.toml was read from", True),
    ("config/facet_path", "dataset", "str", "", "where the facet file was read from", True),
    ("config/config_hash", "dataset", "str", "", "configuration hash (StationConfig.config_hash)", True),
    ("config/station_name", "dataset", "str", "", "station name", True),

    ("result", "group", "", "", "the archived result; attributes: key figures (see below)", True),
    ("result/record_json", "dataset", "str", "", "the result record as JSON text (null: infinite or not a number)", True),
)

_PLAIN_ENCODING = "plain"
_JSON_ENCODING = "json"


def _schema_entry(path: str):
    import fnmatch

    for entry in SCHEMA_V1:
        if entry[0] == path or ("*" in entry[0] and fnmatch.fnmatchcase(path, entry[0])):
            return entry
    return None


def _units_from_name(name: str) -> str:
    for suffix, unit in (("_mrad", "mrad"), ("_m", "m"), ("_px", "px"), ("_s", "s"), ("_dn", "DN"), ("_rad", "rad")):
        if name.endswith(suffix):
            return unit
    return ""


def _describe(path: str) -> tuple[str, str]:
    entry = _schema_entry(path)
    if entry is None:
        log.warning("dump schema v%d has no description of %s", SCHEMA_VERSION, path)
        return f"{path.rsplit('/', 1)[-1]} (not described by schema version {SCHEMA_VERSION})", _units_from_name(path)
    units = entry[3]
    if entry[0].endswith("*"):
        units = _units_from_name(path)
    return entry[4], units


# -- content ----------------------------------------------------------------------------------------
@dataclass
class DumpContent:
    """Everything a dump holds (and everything the archiver spools).

    Attributes
    ----------
    cycle_id, serial, time : str
        The cycle's id, the facet's serial, the measurement's ISO 8601 time with UTC offset.
    software_version : str
    config_hash : str
    frames_cropped : (n, h, w) uint8 array
        Camera frames cropped to the facet region, DN.
    crop_box : (int, int)
        (row0, col0) of the crop in the full frame, pixels.
    full_shape : (int, int)
        (rows, columns) of the full frame, pixels.
    measured_distance_m : float
        Screen centre to the design's measure point, metres.
    fringes, radiometric, geometry, design, analysis : dict
        ``to_dict()`` of the FringeSet, RadiometricRecord, StationGeometry, FacetDesign, AnalysisSettings.
    station_toml, facet_toml : str
        Raw text of the configuration files.
    station_path, facet_path, station_name : str
    record : dict
        The result record (JSON-ready: null for infinite or NaN values); ``{}`` for a dump read with
        ``read_dump(..., require_result=False)`` that holds no result.
    schema_version : int
        Layout version of the file it was read from (or will be written with).
    created : str
        When the dump file was written (empty until then).
    path : Path or None
        The file it was read from.
    """

    cycle_id: str
    serial: str
    time: str
    software_version: str
    config_hash: str
    frames_cropped: np.ndarray | None
    crop_box: tuple[int, int]
    full_shape: tuple[int, int]
    measured_distance_m: float
    fringes: dict
    radiometric: dict
    geometry: dict
    design: dict
    analysis: dict
    station_toml: str
    facet_toml: str
    station_path: str
    facet_path: str
    station_name: str
    record: dict
    schema_version: int = SCHEMA_VERSION
    created: str = ""
    path: Path | None = field(default=None, compare=False)

    def __post_init__(self):
        if self.frames_cropped is not None:
            self.crop_box = _crop_origin(self.crop_box, np.shape(self.frames_cropped))
        else:
            self.crop_box = (int(self.crop_box[0]), int(self.crop_box[1]))
        self.full_shape = (int(self.full_shape[0]), int(self.full_shape[1]))

    # -- building -----------------------------------------------------------------------------------
    @classmethod
    def build(cls, config, radiometric, *, cycle_id: str, record: dict, frames_cropped: np.ndarray,
              crop_box, full_shape, measured_distance_m: float, design=None, analysis=None,
              facet_path: str | Path | None = None) -> "DumpContent":
        """Assemble a dump's content from a loaded configuration and calibration.

        Parameters
        ----------
        config : StationConfig
        radiometric : RadiometricRecord
        cycle_id : str
        record : dict
            The facet's result record (must hold ``serial`` and ``time``).
        frames_cropped : (n, h, w) uint8 array
            The capture cropped to the facet region (see :func:`crop_to_facet`), DN.
        crop_box : (row0, col0) or (row0, col0, row1, col1)
            Position of the crop in the full frame, pixels (a 4-tuple must match the crop's size).
        full_shape : (rows, columns)
        measured_distance_m : float
        design : FacetDesign, optional
            The facet design the analysis used (a recipe's); the station's by default.
        analysis : AnalysisSettings, optional
            The analysis settings used (a recipe's); the station's by default.
        facet_path : str or Path, optional
            The facet file of *design*, kept as text; the station's facet file by default.
        """
        frames_cropped = np.ascontiguousarray(frames_cropped)
        box = _crop_origin(crop_box, frames_cropped.shape)
        design = config.design if design is None else design
        analysis = config.analysis if analysis is None else analysis
        facet_path = config.facet_path if facet_path is None else Path(facet_path)
        texts = []
        for p in (config.path, facet_path):
            try:
                texts.append(Path(p).read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError) as exc:
                log.warning("cannot read %s for the dump of cycle %s (%s); the dump keeps the loaded "
                            "configuration only", p, cycle_id, exc)
                texts.append("")
        rec = json_ready(record)
        return cls(cycle_id=str(cycle_id), serial=str(rec["serial"]), time=str(rec["time"]),
                   software_version=str(rec.get("software_version", __version__)),
                   config_hash=config.config_hash, frames_cropped=frames_cropped,
                   crop_box=box, full_shape=(int(full_shape[0]), int(full_shape[1])),
                   measured_distance_m=float(measured_distance_m), fringes=json_ready(config.fringes.to_dict()),
                   radiometric=json_ready(radiometric.to_dict()), geometry=json_ready(config.geometry.to_dict()),
                   design=json_ready(design.to_dict()), analysis=json_ready(analysis.to_dict()),
                   station_toml=texts[0], facet_toml=texts[1], station_path=str(config.path),
                   facet_path=str(facet_path), station_name=str(config.name), record=rec)

    @classmethod
    def from_station(cls, station, **kwargs) -> "DumpContent":
        """:meth:`build` from a :class:`~sofast_station.station.inspect.Station` (its config and calibration)."""
        return cls.build(station.config, station.radiometric, **kwargs)

    # -- spooling -----------------------------------------------------------------------------------
    _META_FIELDS = ("serial", "time", "software_version", "config_hash", "crop_box", "full_shape",
                    "measured_distance_m", "fringes", "radiometric", "geometry", "design", "analysis", "station_toml",
                    "facet_toml", "station_path", "facet_path", "station_name", "record")

    def to_spool(self) -> tuple[dict, dict]:
        """(arrays, metadata) for :func:`~sofast_station.archive.spool.spool_put`."""
        meta = {k: getattr(self, k) for k in self._META_FIELDS}
        meta["crop_box"], meta["full_shape"] = list(self.crop_box), list(self.full_shape)
        meta["spool_kind"] = "sofast-station-dump-content"
        return {"frames_cropped": self.frames_cropped}, meta

    @classmethod
    def from_spool(cls, arrays: dict, metadata: dict) -> "DumpContent":
        """The content spooled by :meth:`to_spool`; raises ArchiveError when something is missing."""
        if metadata.get("spool_kind") != "sofast-station-dump-content" or "frames_cropped" not in arrays:
            raise ArchiveError("the spool does not hold a dump's content (no frames or wrong kind)")
        try:
            kw = {k: metadata[k] for k in cls._META_FIELDS}
        except KeyError as exc:
            raise ArchiveError(f"the spool lacks {exc.args[0]!r}") from None
        kw["crop_box"], kw["full_shape"] = tuple(kw["crop_box"]), tuple(kw["full_shape"])
        return cls(cycle_id=metadata["cycle_id"], frames_cropped=arrays["frames_cropped"], **kw)

    # -- use ----------------------------------------------------------------------------------------
    @property
    def patterns(self) -> list[str]:
        """Label of the display image of each frame."""
        return [p.label for p in self.fringe_set().patterns()]

    def frames(self) -> np.ndarray:
        """The full (n, rows, columns) frame stack, zero outside the crop (:func:`restore_frames`)."""
        if self.frames_cropped is None:
            raise DumpError(f"dump {self.path}: the frames were not loaded (read_dump(..., load_frames=True))")
        return restore_frames(self.frames_cropped, self.crop_box, self.full_shape)

    def fringe_set(self):
        from ..fringes import FringeSet
        return FringeSet.from_dict(self.fringes)

    def station_geometry(self):
        from ..geometry import StationGeometry
        return StationGeometry.from_dict(self.geometry)

    def facet_design(self):
        from ..facet import FacetDesign
        return FacetDesign.from_dict(self.design, source=f"dump {self.path}")

    def analysis_settings(self):
        from ..measure.pipeline import AnalysisSettings
        return AnalysisSettings(**self.analysis)

    def radiometric_record(self):
        from ..calibrate.records import RadiometricRecord
        r = self.radiometric
        return RadiometricRecord(r["record_id"], r["created"], r["source"], np.asarray(r["lut"], dtype=np.float64),
                                 r["floor_level"], r["max_level"], r["exposure_s"], r["gain"])

    def analyse(self, **overrides):
        """Rerun the analysis on the dumped frames with the dumped configuration.

        Keyword arguments replace any of ``fringes``, ``geometry``, ``design``, ``measured_distance_m``,
        ``settings`` (e.g. another facet model or alignment point).

        Returns
        -------
        sofast_station.measure.pipeline.Analysis
        """
        from ..measure.pipeline import analyse

        args = {"fringes": self.fringe_set(), "geometry": self.station_geometry(), "design": self.facet_design(),
                "measured_distance_m": self.measured_distance_m, "settings": self.analysis_settings()}
        unknown = set(overrides) - set(args)
        if unknown:
            raise TypeError(f"unknown override(s) {sorted(unknown)}; allowed: {sorted(args)}")
        args.update(overrides)
        return analyse(self.frames(), **args)


def _crop_origin(crop_box, shape) -> tuple[int, int]:
    """(row0, col0) from a 2-tuple, or from a (row0, col0, row1, col1) box that matches *shape* (n, h, w)."""
    box = [int(v) for v in crop_box]
    if len(box) == 4:
        if (box[2] - box[0], box[3] - box[1]) != tuple(shape[1:]):
            raise ArchiveError(f"crop box {tuple(box)} (row0, col0, row1, col1) does not match the cropped frames' "
                               f"size {shape[1]} x {shape[2]}")
        return box[0], box[1]
    if len(box) != 2:
        raise ArchiveError(f"crop box must be (row0, col0) or (row0, col0, row1, col1), got {tuple(box)}")
    return box[0], box[1]


def restore_frames(frames_cropped: np.ndarray, crop_box, full_shape) -> np.ndarray:
    """Rebuild the full frame stack from a crop: zero outside the crop by definition.

    Parameters
    ----------
    frames_cropped : (n, h, w) array
    crop_box : (row0, col0) or (row0, col0, row1, col1)
        Position of the crop's top-left pixel in the full frame, pixels (end-exclusive ends, when given,
        must match the crop's size).
    full_shape : (rows, columns)
        Full frame size, pixels.

    Returns
    -------
    (n, rows, columns) array of ``frames_cropped.dtype``
    """
    n, h, w = frames_cropped.shape
    r0, c0 = _crop_origin(crop_box, frames_cropped.shape)
    rows, cols = int(full_shape[0]), int(full_shape[1])
    if r0 < 0 or c0 < 0 or r0 + h > rows or c0 + w > cols:
        raise DumpError(f"crop {h} x {w} at (row {r0}, column {c0}) does not fit the {rows} x {cols} frame")
    full = np.zeros((n, rows, cols), dtype=frames_cropped.dtype)
    full[:, r0:r0 + h, c0:c0 + w] = frames_cropped
    return full


def crop_to_facet(frames: np.ndarray, threshold_dn: float = 20.0, margin_px: int = 32):
    """Crop a capture to the box around every pixel that responds to the screen, plus a margin.

    A pixel responds when white (frame 1) minus dark (frame 0) exceeds *threshold_dn*; the box covers
    every responding pixel (not only the facet's largest region), so the analysis of the restored
    frames sees the same facet region. When nothing responds the whole frame is kept.

    Parameters
    ----------
    frames : (n, rows, columns) uint8 array
    threshold_dn : float
        Use the analysis's ``mask_threshold_dn``, DN.
    margin_px : int
        Extra pixels on every side, pixels (the corner-finding windows reach 14 px beyond the edge).

    Returns
    -------
    frames_cropped : (n, h, w) array (a contiguous copy)
    crop_box : (row0, col0)
    full_shape : (rows, columns)
    """
    full_shape = (int(frames.shape[1]), int(frames.shape[2]))
    responsive = (frames[1].astype(np.int16) - frames[0].astype(np.int16)) > threshold_dn
    rows = np.flatnonzero(responsive.any(axis=1))
    cols = np.flatnonzero(responsive.any(axis=0))
    if rows.size == 0:
        return np.ascontiguousarray(frames), (0, 0), full_shape
    r0, r1 = max(int(rows[0]) - margin_px, 0), min(int(rows[-1]) + margin_px + 1, full_shape[0])
    c0, c1 = max(int(cols[0]) - margin_px, 0), min(int(cols[-1]) + margin_px + 1, full_shape[1])
    return np.ascontiguousarray(frames[:, r0:r1, c0:c1]), (r0, c0), full_shape


# -- writing ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DumpStats:
    """What writing a dump cost.

    Attributes
    ----------
    path : Path
    size_bytes : int
        File size, bytes.
    raw_bytes : int
        Uncompressed size of the cropped frames, bytes.
    seconds : float
        Wall time of the write including fsync and rename, seconds.
    """

    path: Path
    size_bytes: int
    raw_bytes: int
    seconds: float


def _set_description(obj, path: str) -> None:
    desc, units = _describe(path)
    obj.attrs["description"] = desc
    obj.attrs["units"] = units


def _write_value(group, name: str, value, path: str) -> None:
    import h5py

    if isinstance(value, dict):
        sub = group.create_group(name, track_order=True)
        _set_description(sub, path)
        for k, v in value.items():
            if "/" in str(k) or not str(k):
                raise ArchiveError(f"cannot store the key {k!r} of {path} in a dump")
            _write_value(sub, str(k), v, f"{path}/{k}")
        return
    encoding = _PLAIN_ENCODING
    if isinstance(value, str):
        ds = group.create_dataset(name, data=value, dtype=h5py.string_dtype("utf-8"))
    elif isinstance(value, bool):
        ds = group.create_dataset(name, data=np.bool_(value))
    elif isinstance(value, int):
        ds = group.create_dataset(name, data=np.int64(value))
    elif isinstance(value, float):
        ds = group.create_dataset(name, data=np.float64(value))
    else:
        arr = None
        if isinstance(value, (list, tuple)):
            try:
                arr = np.asarray(value)
            except ValueError:            # ragged
                arr = None
        if arr is not None and arr.dtype.kind in "biuf" and (arr.size or arr.ndim == 1):
            ds = group.create_dataset(name, data=arr.astype(np.int64 if arr.dtype.kind in "iu" else arr.dtype))
        elif arr is not None and arr.dtype.kind == "U" and arr.ndim == 1 and arr.size:
            ds = group.create_dataset(name, data=[str(v) for v in value], dtype=h5py.string_dtype("utf-8"))
        else:                              # None, ragged or mixed lists: JSON text
            ds = group.create_dataset(name, data=json.dumps(value), dtype=h5py.string_dtype("utf-8"))
            encoding = _JSON_ENCODING
    _set_description(ds, path)
    ds.attrs["encoding"] = encoding


def _frame_job(frame: np.ndarray, level: int) -> tuple[bytes, str]:
    # zlib and hashlib release the GIL on large buffers: frames compress in parallel, and the station's
    # own threads keep running meanwhile
    return zlib.compress(frame, level), hashlib.sha256(frame).hexdigest()


def _write_frames(ds, frames: np.ndarray, level: int) -> list[str]:
    """Compress each frame (a zlib stream: HDF5's deflate filter; shuffle is the identity on 1-byte data)
    on all cores and write it as the frame's chunk; return the frames' SHA-256 digests."""
    n = frames.shape[0]
    digests = []
    workers = max(1, min(n, os.cpu_count() or 1))
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="dump-zlib") as pool:
        for i, (blob, digest) in enumerate(pool.map(_frame_job, frames, [level] * n)):
            ds.id.write_direct_chunk((i, 0, 0), blob, 0)
            digests.append(digest)
            if i + 1 == n // 2:
                fault_point("dump-mid-write")
    return digests


def _flat_figures(record: dict) -> dict:
    out = {}
    for key in KEY_FIGURES:
        v = record
        for part in key.split("."):
            v = v.get(part) if isinstance(v, dict) else None
        if isinstance(v, (str, int, float, bool)):
            out[key] = v
    return out


def write_dump(path: str | Path, content: DumpContent, compression_level: int = COMPRESSION_LEVEL) -> DumpStats:
    """Write a data dump atomically.

    The file is written as ``.<name>.<pid>.<random>.tmp`` in the target folder, closed, fsynced and
    renamed to *path*; the folder is fsynced. On failure the temporary file is removed.

    Parameters
    ----------
    path : str or Path
        The final ``.h5`` file (replaced when it exists).
    content : DumpContent
    compression_level : int
        gzip level of the frames, 0..9.

    Returns
    -------
    DumpStats

    Raises
    ------
    ArchiveError
        When the content is inconsistent or the file cannot be written (disk full, permissions); the
        cause is chained.
    """
    import h5py

    t0 = time.perf_counter()
    path = Path(path)
    level = int(compression_level)
    if not 0 <= level <= 9:
        raise ArchiveError(f"dump {path}: compression level must be 0..9, got {compression_level}")
    frames = content.frames_cropped
    if frames is None or frames.ndim != 3 or frames.dtype != np.uint8 or min(frames.shape) < 1:
        raise ArchiveError(f"dump {path}: frames_cropped must be a non-empty (n, h, w) uint8 array, got "
                           f"{None if frames is None else (frames.shape, frames.dtype)}")
    frames = np.ascontiguousarray(frames)
    n, h, w = frames.shape
    restore_check = (content.crop_box[0] >= 0 and content.crop_box[1] >= 0
                     and content.crop_box[0] + h <= content.full_shape[0]
                     and content.crop_box[1] + w <= content.full_shape[1])
    if not restore_check:
        raise ArchiveError(f"dump {path}: the crop {h} x {w} at {tuple(content.crop_box)} does not fit the full "
                           f"frame {tuple(content.full_shape)}")
    try:
        patterns = content.patterns
    except Exception:                        # an unusable fringe definition still gets dumped
        patterns = []
    if len(patterns) != n:
        patterns = [f"frame {i}" for i in range(n)]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_for(path)
    created = now_iso()
    try:
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["schema"] = SCHEMA
            f.attrs["schema_version"] = np.int64(SCHEMA_VERSION)
            f.attrs["description"] = (f"sofast-station data dump of facet {content.serial}, cycle {content.cycle_id}: "
                                      "raw frames and everything needed to redo the analysis; layout: "
                                      "docs/dump-schema.md")
            f.attrs["software_version"] = content.software_version
            f.attrs["created"] = created
            f.attrs["cycle_id"] = content.cycle_id
            f.attrs["serial"] = content.serial
            f.attrs["time"] = content.time
            f.attrs["config_hash"] = content.config_hash
            f.attrs["station"] = content.station_name
            f.attrs["facet"] = str(content.design.get("name", ""))

            cap = f.create_group("capture", track_order=True)
            _set_description(cap, "capture")
            ds = cap.create_dataset("frames", shape=frames.shape, dtype=np.uint8, chunks=(1, h, w),
                                    compression="gzip", compression_opts=level, shuffle=True)
            _set_description(ds, "capture/frames")
            digests = _write_frames(ds, frames, level)
            _write_value(cap, "frames_sha256", digests, "capture/frames_sha256")
            _write_value(cap, "crop_box", [int(v) for v in content.crop_box], "capture/crop_box")
            _write_value(cap, "full_shape", [int(v) for v in content.full_shape], "capture/full_shape")
            _write_value(cap, "patterns", patterns, "capture/patterns")
            _write_value(cap, "measured_distance_m", float(content.measured_distance_m), "capture/measured_distance_m")

            _write_value(f, "fringes", content.fringes, "fringes")
            cal = f.create_group("calibration", track_order=True)
            _set_description(cal, "calibration")
            _write_value(cal, "radiometric", content.radiometric, "calibration/radiometric")
            _write_value(f, "geometry", content.geometry, "geometry")
            _write_value(f, "design", content.design, "design")
            _write_value(f, "analysis", content.analysis, "analysis")
            _write_value(f, "config", {"station_toml": content.station_toml, "facet_toml": content.facet_toml,
                                       "station_path": content.station_path, "facet_path": content.facet_path,
                                       "config_hash": content.config_hash, "station_name": content.station_name},
                         "config")
            res = f.create_group("result", track_order=True)
            _set_description(res, "result")
            _write_value(res, "record_json", to_json(content.record), "result/record_json")
            for k, v in _flat_figures(content.record).items():
                res.attrs[k] = v
        fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        try:
            tmp.unlink(missing_ok=True)
        except OSError as exc2:
            log.warning("could not remove the temporary dump %s: %s", tmp, exc2)
        if isinstance(exc, (OSError, ValueError, TypeError, RuntimeError)) and not isinstance(exc, ArchiveError):
            raise ArchiveError(f"could not write the dump {path}: {type(exc).__name__}: {exc}") from exc
        raise
    fsync_dir(path.parent)
    stats = DumpStats(path, path.stat().st_size, int(frames.nbytes), time.perf_counter() - t0)
    log.info("wrote dump %s: %.1f MB (frames %.1f MB raw) in %.2f s", path, stats.size_bytes / 1e6,
             stats.raw_bytes / 1e6, stats.seconds)
    return stats


# -- reading ----------------------------------------------------------------------------------------
def _read_value(obj):
    import h5py

    if isinstance(obj, h5py.Group):
        return {k: _read_value(obj[k]) for k in obj.keys()}
    encoding = obj.attrs.get("encoding", _PLAIN_ENCODING)
    if isinstance(encoding, bytes):
        encoding = encoding.decode()
    if obj.dtype.kind in "OS" or h5py.check_string_dtype(obj.dtype) is not None:
        value = obj.asstr()[()]
        if isinstance(value, np.ndarray):
            return [str(v) for v in value.tolist()]
        return json.loads(value) if encoding == _JSON_ENCODING else str(value)
    value = obj[()]
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value.item() if hasattr(value, "item") else value


def _what_is(path: Path) -> str:
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError:
        return "unreadable"
    for magic, name in _MAGIC:
        if head.startswith(magic):
            return name
    return f"unknown content starting with {head[:8]!r}"


def _attr_str(attrs, key: str, where: str) -> str:
    if key not in attrs:
        raise DumpError(f"dump {where}: the root attribute {key!r} is missing; the file is damaged or not "
                        "written by sofast-station")
    v = attrs[key]
    return v.decode() if isinstance(v, bytes) else str(v)


def read_dump(path: str | Path, load_frames: bool = True, require_result: bool = True) -> DumpContent:
    """Open a data dump, check its schema, and return its content.

    The reader dispatches on the file's ``schema_version`` (:data:`_READERS`): every layout version up to
    :data:`SCHEMA_VERSION` keeps its own reader, so dumps of earlier versions stay readable.

    Parameters
    ----------
    path : str or Path
    load_frames : bool
        Read (and checksum-verify) the frames; False reads the metadata only (``frames_cropped`` None).
    require_result : bool
        Refuse a dump without its ``result`` group (the archived record). Re-analysis passes False: the
        result is an output of the analysis, not an input, so a dump that lost it can still be redone;
        its ``record`` is then ``{}``.

    Returns
    -------
    DumpContent

    Raises
    ------
    DumpError
        Naming the file and the problem: missing, empty, not HDF5 (e.g. a PNG renamed ``.h5``), truncated
        or corrupt, an HDF5 file that is not a dump, a dump of a newer schema version (upgrade), or a
        dump that lacks a dataset.
    """
    import h5py

    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise DumpError(f"dump {path} does not exist") from None
    except OSError as exc:
        raise DumpError(f"dump {path} cannot be read: {exc}") from exc
    if path.is_dir():
        raise DumpError(f"dump {path} is a folder, not a file")
    if size == 0:
        raise DumpError(f"dump {path} is empty (0 bytes): its write was interrupted or it was truncated; "
                        "it holds no data")
    try:
        is_hdf5 = h5py.is_hdf5(str(path))
    except OSError as exc:
        raise DumpError(f"dump {path} cannot be read: {exc}") from exc
    if not is_hdf5:
        raise DumpError(f"dump {path} is not an HDF5 file (it looks like {_what_is(path)}); it is not a "
                        "sofast-station dump")
    try:
        f = h5py.File(path, "r", locking=False)      # readable on shares without file locking
    except OSError as exc:
        msg = str(exc)
        what = "is truncated (shorter than its header says: an interrupted copy?)" if "truncated" in msg else \
            "is corrupt"
        raise DumpError(f"dump {path} {what}; HDF5 says: {msg}") from exc
    try:
        with f:
            return _read_open(f, path, load_frames, require_result)
    except DumpError:
        raise
    except (OSError, KeyError, ValueError, RuntimeError, TypeError) as exc:
        raise DumpError(f"dump {path} is corrupt or truncated: reading it failed with {type(exc).__name__}: "
                        f"{exc}") from exc


def _read_open(f, path: Path, load_frames: bool, require_result: bool = True) -> DumpContent:
    schema = f.attrs.get("schema")
    if isinstance(schema, bytes):
        schema = schema.decode()
    if schema is None:
        top = ", ".join(sorted(f.keys())[:8]) or "nothing"
        raise DumpError(f"{path} is an HDF5 file but not a sofast-station dump (no 'schema' attribute at its "
                        f"root; it holds {top})")
    if schema != SCHEMA:
        raise DumpError(f"{path} is an HDF5 file of schema {schema!r}, not a sofast-station dump ({SCHEMA!r})")
    try:
        version = int(f.attrs.get("schema_version"))
    except (TypeError, ValueError):
        raise DumpError(f"dump {path} has no valid 'schema_version' attribute ({f.attrs.get('schema_version')!r})")
    if version > SCHEMA_VERSION:
        sw = f.attrs.get("software_version", "?")
        sw = sw.decode() if isinstance(sw, bytes) else sw
        raise DumpError(f"dump {path} was written by a newer sofast-station ({sw}, dump schema version {version}); "
                        f"this software ({__version__}) reads schema versions up to {SCHEMA_VERSION}: upgrade "
                        "sofast-station to read it")
    if version < 1:
        raise DumpError(f"dump {path} has an invalid schema_version {version}")
    reader = _READERS.get(version)
    if reader is None:                       # a version this software wrote but no longer reads: a bug
        raise DumpError(f"dump {path} has schema version {version}, for which this software ({__version__}) "
                        f"has no reader (it knows {sorted(_READERS)}); report this as a bug")
    return reader(f, path, version, load_frames, require_result)


def _read_v1(f, path: Path, version: int, load_frames: bool, require_result: bool) -> DumpContent:
    """Reader of schema version 1 (docs/dump-schema.md, :data:`SCHEMA_V1`)."""
    import h5py

    where = str(path)
    attrs = {k: _attr_str(f.attrs, k, where) for k in ("software_version", "cycle_id", "serial", "time",
                                                         "config_hash")}
    created = _attr_str(f.attrs, "created", where)
    optional = () if require_result else ("result", "result/record_json")
    missing = [p for p, kind, _, _, _, required in SCHEMA_V1
               if required and kind != "attribute" and "*" not in p and p not in f and p not in optional]
    if missing:
        raise DumpError(f"dump {path} lacks the dataset(s) {', '.join(missing)} required by schema version "
                        f"{version}; the file is damaged or incomplete")
    frames_ds = f["capture/frames"]
    if not isinstance(frames_ds, h5py.Dataset) or frames_ds.ndim != 3 or frames_ds.dtype != np.uint8:
        raise DumpError(f"dump {path}: capture/frames must be an (n, h, w) uint8 dataset, got "
                        f"{getattr(frames_ds, 'shape', None)} {getattr(frames_ds, 'dtype', None)}")
    cap = f["capture"]
    frames = None
    if load_frames:
        frames = frames_ds[()]
        digests = _read_value(cap["frames_sha256"])
        if len(digests) != frames.shape[0]:
            raise DumpError(f"dump {path}: {len(digests)} frame digests for {frames.shape[0]} frames")
        for i, frame in enumerate(frames):
            if hashlib.sha256(frame).hexdigest() != digests[i]:
                raise DumpError(f"dump {path} is corrupt: frame {i} does not match its SHA-256 digest")
    crop_box = tuple(int(v) for v in _read_value(cap["crop_box"]))
    full_shape = tuple(int(v) for v in _read_value(cap["full_shape"]))
    n, h, w = frames_ds.shape
    if len(crop_box) != 2 or len(full_shape) != 2 or crop_box[0] < 0 or crop_box[1] < 0 \
            or crop_box[0] + h > full_shape[0] or crop_box[1] + w > full_shape[1]:
        raise DumpError(f"dump {path}: the crop {h} x {w} at {crop_box} does not fit the full frame {full_shape}")
    cfg = _read_value(f["config"])
    record = {}
    if "result/record_json" in f:
        try:
            record = json.loads(_read_value(f["result/record_json"]))
        except json.JSONDecodeError as exc:
            raise DumpError(f"dump {path}: result/record_json is not valid JSON ({exc})") from exc
    else:
        log.warning("dump %s holds no archived result (no result/record_json); reading it for re-analysis only",
                    path)
    return DumpContent(
        cycle_id=attrs["cycle_id"], serial=attrs["serial"], time=attrs["time"],
        software_version=attrs["software_version"], config_hash=attrs["config_hash"], frames_cropped=frames,
        crop_box=crop_box, full_shape=full_shape,
        measured_distance_m=float(_read_value(cap["measured_distance_m"])),
        fringes=_read_value(f["fringes"]), radiometric=_read_value(f["calibration/radiometric"]),
        geometry=_read_value(f["geometry"]), design=_read_value(f["design"]), analysis=_read_value(f["analysis"]),
        station_toml=cfg["station_toml"], facet_toml=cfg["facet_toml"], station_path=cfg["station_path"],
        facet_path=cfg["facet_path"], station_name=cfg["station_name"], record=record, schema_version=version,
        created=created, path=path)


#: The reader of each schema version this software reads (a new layout adds its version here and keeps
#: the readers of the older ones).
_READERS = {1: _read_v1}


# -- retention and disk ---------------------------------------------------------------------------------
def list_dumps(folder: str | Path) -> list[Path]:
    """Every dump (``*.h5``, temporary files excluded) under *folder*, oldest first (by modification time)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    out = []
    for p in folder.rglob("*.h5"):
        if is_temp_file(p) or p.name.startswith("."):
            continue
        try:
            out.append((p.stat().st_mtime, p))
        except FileNotFoundError:
            continue
    return [p for _, p in sorted(out, key=lambda t: (t[0], str(t[1])))]


def prune_dumps(folder: str | Path, keep_days: float | None, max_total_gb: float | None) -> list[Path]:
    """Apply the retention rule: remove dumps older than *keep_days*, then the oldest until the total is at
    most *max_total_gb*.

    Parameters
    ----------
    folder : str or Path
        The dump folder (searched recursively; emptied day folders are removed).
    keep_days : float or None
        Largest age of a dump, days (by file modification time); None: no age limit.
    max_total_gb : float or None
        Largest total size of the dumps, GB (10^9 bytes); None: no size limit.

    Returns
    -------
    list of Path
        The dumps removed, oldest first.
    """
    folder = Path(folder)
    dumps = list_dumps(folder)
    sizes = {}
    for p in dumps:
        try:
            sizes[p] = p.stat().st_size
        except FileNotFoundError:
            sizes[p] = 0
    total = sum(sizes.values())
    cutoff = None if keep_days is None else time.time() - float(keep_days) * 86400.0
    limit = None if max_total_gb is None else float(max_total_gb) * 1e9
    removed = []
    for p in dumps:                          # oldest first
        try:
            mtime = p.stat().st_mtime
        except FileNotFoundError:
            continue
        too_old = cutoff is not None and mtime < cutoff
        too_big = limit is not None and total > limit
        if not (too_old or too_big):
            break                            # the rest are younger, and the total fits
        try:
            p.unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            log.warning("retention: could not remove %s: %s", p, exc)
            continue
        total -= sizes[p]
        removed.append(p)
    for d in sorted({p.parent for p in removed}, key=lambda d: len(d.parts), reverse=True):
        if d != folder:
            try:
                d.rmdir()                    # only when empty
            except OSError:
                pass
    if removed:
        log.info("retention: removed %d dump(s) from %s (%s days, %s GB); %.2f GB remain", len(removed), folder,
                 keep_days, max_total_gb, total / 1e9)
    return removed


def disk_ok(folder: str | Path, min_free_gb: float) -> tuple[bool, float]:
    """Whether the disk holding *folder* has at least *min_free_gb* free.

    Parameters
    ----------
    folder : str or Path
        Any path on the disk (the nearest existing parent is measured).
    min_free_gb : float
        Required free space, GB (10^9 bytes).

    Returns
    -------
    (bool, float)
        Whether the free space suffices, and the free space in GB.
    """
    p = Path(folder).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    free_gb = shutil.disk_usage(p).free / 1e9
    return free_gb >= float(min_free_gb), free_gb


def dump_name(serial: str, time_iso: str, cycle_id: str) -> str:
    """File name of a cycle's dump: ``<serial>_<local time YYYYMMDDTHHMMSS>_<cycle id>.h5`` (file-name safe)."""
    t = parse_time(time_iso)
    return f"{safe_name(serial, 60)}_{t.strftime('%Y%m%dT%H%M%S')}_{safe_name(cycle_id, 80)}.h5"


def dump_path_for(folder: str | Path, serial: str, time_iso: str, cycle_id: str) -> Path:
    """Where the archiver puts a cycle's dump: ``<folder>/<local date>/<dump_name>``."""
    return Path(folder) / parse_time(time_iso).date().isoformat() / dump_name(serial, time_iso, cycle_id)

