"""What a dump holds, in memory: :class:`DumpContent`, and the crop of the frames to the facet."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ... import __version__
from ...calibrate.records import RadiometricRecord
from ...errors import ArchiveError, DumpError
from ...facet import FacetDesign
from ...files import json_ready
from ...fringes import FringeSet
from ...geometry import StationGeometry
from .schema import FRINGE_SCHEMA_VERSION, SCHEMA_VERSION

log = logging.getLogger("sofast_station.archive.dumps")


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
    #: (what the writer labels it: a fringe capture 2, a fixed-pattern one 3)
    schema_version: int = FRINGE_SCHEMA_VERSION
    created: str = ""
    path: Path | None = field(default=None, compare=False)
    #: The uncertainty's sensitivities the station's analysis used
    #: (:mod:`~sofast_station.measure.sensitivity_record`), or None: re-analysis reuses them when its inputs
    #: are the same, instead of computing them from this capture.
    sensitivities: dict | None = field(default=None, compare=False)
    #: The input uncertainties in force when the facet was measured
    #: (:meth:`~sofast_station.measure.uncertainty.InputUncertainties.to_dict`: station.toml's ``[uncertainty]``
    #: with what the radiometric, camera and commissioning records state), or None (dumps before 0.4.0):
    #: re-analysis states the same U as the line.
    uncertainty_inputs: dict | None = field(default=None, compare=False)

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
              facet_path: str | Path | None = None, sensitivities: dict | None = None,
              heliostat: dict | None = None, uncertainty_inputs: dict | None = None) -> "DumpContent":
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
        sensitivities : dict, optional
            The uncertainty's sensitivities the analysis used (a record of
            :func:`~sofast_station.measure.sensitivity_record.to_record`; a heliostat's: one per facet label).
        heliostat : dict, optional
            A heliostat's analysis (``ensemble``, ``heliostat`` settings, ``max_canting_mrad``:
            :meth:`~sofast_station.job.heliostat.HeliostatJob.dumped`), kept in ``design`` beside the
            heliostat's bounding outline; re-analysis then analyses the heliostat (docs/dump-schema.md).
        uncertainty_inputs : dict, optional
            The input uncertainties the analysis used; the station's (``config.uncertainty``) by default.
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
                   design=json_ready({**design.to_dict(), **(heliostat or {})}),
                   analysis=json_ready(analysis.to_dict()),
                   station_toml=texts[0], facet_toml=texts[1], station_path=str(config.path),
                   facet_path=str(facet_path), station_name=str(config.name), record=rec,
                   schema_version=(SCHEMA_VERSION if (heliostat or {}).get("method") == "fixed"
                                   else FRINGE_SCHEMA_VERSION),
                   sensitivities=None if sensitivities is None else json_ready(sensitivities),
                   uncertainty_inputs=json_ready(uncertainty_inputs if uncertainty_inputs is not None else
                                                 (None if getattr(config, "uncertainty", None) is None
                                                  else config.uncertainty.to_dict())))

    @classmethod
    def from_station(cls, station, **kwargs) -> "DumpContent":
        """:meth:`build` from a :class:`~sofast_station.station.opened.Station` (its config and calibration)."""
        return cls.build(station.config, station.radiometric, **kwargs)

    # -- spooling -----------------------------------------------------------------------------------
    _META_FIELDS = ("serial", "time", "software_version", "config_hash", "crop_box", "full_shape",
                    "measured_distance_m", "fringes", "radiometric", "geometry", "design", "analysis", "station_toml",
                    "facet_toml", "station_path", "facet_path", "station_name", "record")

    def to_spool(self) -> tuple[dict, dict]:
        """(arrays, metadata) for :func:`~sofast_station.archive.spool.spool_put`."""
        meta = {k: getattr(self, k) for k in self._META_FIELDS}
        meta["crop_box"], meta["full_shape"] = list(self.crop_box), list(self.full_shape)
        meta["sensitivities"] = self.sensitivities
        meta["uncertainty_inputs"] = self.uncertainty_inputs
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
        return cls(cycle_id=metadata["cycle_id"], frames_cropped=arrays["frames_cropped"],
                   sensitivities=metadata.get("sensitivities"),           # (absent in older spools)
                   uncertainty_inputs=metadata.get("uncertainty_inputs"), **kw)

    # -- use ----------------------------------------------------------------------------------------
    @property
    def patterns(self) -> list[str]:
        """Label of the display image of each frame (a fixed-pattern capture's: dark, white and the dots, or the
        dots alone)."""
        fixed = self.design.get("fixed") if isinstance(self.design, dict) else None
        if isinstance(fixed, dict):
            dots = f"dot grid {fixed.get('grid', {}).get('pitch_px')} px"
            return ["dark", "white", dots] if fixed.get("white_frame") else [dots]
        return [p.label for p in self.fringe_set().patterns()]

    def frames(self) -> np.ndarray:
        """The full (n, rows, columns) frame stack, zero outside the crop (:func:`restore_frames`)."""
        if self.frames_cropped is None:
            raise DumpError(f"dump {self.path}: the frames were not loaded (read_dump(..., load_frames=True))")
        return restore_frames(self.frames_cropped, self.crop_box, self.full_shape)

    def fringe_set(self):
        return FringeSet.from_dict(self.fringes)

    def station_geometry(self):
        return StationGeometry.from_dict(self.geometry)

    def facet_design(self):
        return FacetDesign.from_dict(self.design, source=f"dump {self.path}")

    def analysis_settings(self):
        # lazy: measure/ costs ~170 ms CPU; the journal's users (report trend, spc, field) never analyse
        from ...measure.pipeline import AnalysisSettings
        return AnalysisSettings(**self.analysis)

    def radiometric_record(self):
        r = self.radiometric
        return RadiometricRecord(r["record_id"], r["created"], r["source"], np.asarray(r["lut"], dtype=np.float64),
                                 r["floor_level"], r["max_level"], r["exposure_s"], r["gain"])

    def analyse(self, **overrides):
        """Rerun the analysis on the dumped frames with the dumped configuration.

        Keyword arguments replace any of ``fringes``, ``geometry``, ``design``, ``measured_distance_m``,
        ``settings`` (e.g. another facet model or alignment point); ``uncertainty`` and
        ``sensitivity_cache`` are passed on (the figures' expanded uncertainties). A fixed-pattern capture
        (``design["method"] == "fixed"``, schema 3) is analysed by the fixed-pattern method, its dot locations
        from the dumped grid on the dumped screen (``fringes`` does not apply to it).

        Returns
        -------
        sofast_station.measure.pipeline.Analysis
        """
        # lazy: measure/ costs ~170 ms CPU; the journal's users (report trend, spc, field) never analyse
        from ...measure.analysis import analyse
        from ...precompute import ray_table

        args = {"fringes": self.fringe_set(), "geometry": self.station_geometry(), "design": self.facet_design(),
                "measured_distance_m": self.measured_distance_m, "settings": self.analysis_settings()}
        passed = {k: overrides.pop(k) for k in ("uncertainty", "sensitivity_cache") if k in overrides}
        unknown = set(overrides) - set(args)
        if unknown:
            raise TypeError(f"unknown override(s) {sorted(unknown)}; allowed: {sorted(args)}")
        args.update(overrides)
        args.update(passed)
        if isinstance(self.design, dict) and self.design.get("method") == "fixed":
            # lazy: measure/ costs ~170 ms CPU; the journal's users (report trend, spc, field) never analyse
            from ...measure.fixed import FixedCapture, analyse_fixed, lcd_dot_locations
            from ...measure.pipeline import default_screen

            if "fringes" in overrides:
                raise TypeError("a fixed-pattern capture has no fringes to replace")
            fixed = FixedCapture.from_dict(self.design["fixed"])
            frames, geometry = self.frames(), args["geometry"]
            dark, white = (frames[0], frames[1]) if fixed.white_frame else (None, None)
            return analyse_fixed(frames[fixed.n_frames - 1], lcd_dot_locations(fixed.grid, default_screen(geometry)),
                                 geometry, args["design"], args["measured_distance_m"], args["settings"],
                                 fixed.settings, white=white, dark=dark, **passed)
        # The camera's rays are kept per process: re-analysing many dumps of one station computes them once.
        return analyse(self.frames(), **args, rays_cam=ray_table(args["geometry"].camera))


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
