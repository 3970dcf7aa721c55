"""station.toml -> a validated :class:`StationConfig`.

Every error names the file and the key. Relative paths in the file are relative to the file's folder.
``data_dir`` (where everything the station writes goes) may start with ``~`` and may be overridden by the
environment variable ``SOFAST_DATA_DIR``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from .calibrate.commissioned import geometry_in_force
from .calibrate.geometry_record import budget_std, load_geometry_record
from .calibrate.records import load_radiometric
from .calibrate.settings import CALIBRATION_KEYS, parse_calibration_table
from .calibrate.store import newest_record_path, record_dir
from .config_schema import add_dataclass_keys, validate
from .ensemble import EnsembleDesign, is_ensemble_file, load_ensemble
from .errors import ConfigError, check_table
from .facet import FacetDesign, load_facet
from .files import data_dir_of, read_toml
from .fringes import FringeSet
from .geometry import CameraIntrinsics, ScreenSpec, StationGeometry
from .layout import layout_station
from .measure.heliostat import HeliostatSettings
from .measure.pipeline import AnalysisSettings
from .measure.uncertainty import InputUncertainties
from .result.optical_figures import optics_for
from .result.verdict import OPTICAL_LIMITS, Limits, Quality, limits_from_table, quality_from_table

log = logging.getLogger(__name__)

for _section, _cls in (("analysis", AnalysisSettings), ("limits", Limits), ("quality", Quality),
                       ("heliostat", HeliostatSettings)):
    add_dataclass_keys(_section, _cls)

_STATION_KEYS = {"name", "id", "data_dir", "backend", "facet"}
_CAMERA_KEYS = {"width_px", "height_px", "focal_length_px", "principal_point_px", "distortion", "intrinsics"}
_LAYOUT_KEYS = {"separation_m", "separation_axis", "screen_offset_m"}
_BACKENDS = ("simulated", "hardware")


def _check_keys(table: dict, allowed: set, where: str) -> None:
    check_table(table, allowed, where)


def _need(table: dict, key: str, where: str):
    if key not in table:
        raise ConfigError(f"{where} is missing the key {key!r}")
    return table[key]


@dataclass(frozen=True)
class StationConfig:
    """A loaded station.toml.

    ``simulation`` holds the raw ``[simulation]`` table; the simulated backend turns it into the twin's
    own records, so nothing here depends on the twin.
    """

    path: Path
    name: str
    data_dir: Path
    backend: str
    facet_path: Path
    design: FacetDesign
    geometry: StationGeometry
    fringes: FringeSet
    analysis: AnalysisSettings
    limits: Limits
    quality: Quality
    radiometric_path: Path | None
    simulation: dict = field(default_factory=dict)
    raw: dict = field(default_factory=dict)
    #: With ``[camera] intrinsics = "record"``: the camera record in force (``record_id``, ``path``) and
    #: ``stated``, the [camera] table's intrinsics (the simulated station's true camera); else None.
    camera_record: dict | None = None
    #: ``[optics]``: how the facet's optical figures are computed (None: ``enabled = false``).
    optics: object | None = None
    #: Standard uncertainties of the station's inputs (``[uncertainty]``; docs/uncertainty.md), with a camera
    #: record's stated standard deviations where it has them, and the screen and pose records'.
    uncertainty: InputUncertainties = field(default_factory=InputUncertainties)
    #: When ``[station] facet`` names a heliostat file: the heliostat (``design`` is then its bounding outline,
    #: what the station is laid out for; docs/heliostats.md); None for a single facet.
    ensemble: EnsembleDesign | None = None
    #: ``[heliostat]``: how a heliostat's facets are told apart.
    heliostat: HeliostatSettings = field(default_factory=HeliostatSettings)
    #: The geometry station.toml states ([camera] or its record, [screen], [layout]); ``geometry`` is what the
    #: analysis uses: this, or the screen and pose records in force (:mod:`sofast_station.calibrate.commissioned`).
    stated_geometry: StationGeometry | None = None
    #: The screen and pose records in force (``screen``, ``pose``: record id and path; ``warnings``), or None.
    commissioned: dict | None = None
    #: ``[station] id``: the station's identity, which every calibration record it makes carries (its name when
    #: the file gives none); a record made by another station is refused (:mod:`sofast_station.calibrate.store`).
    station_id: str = ""

    @property
    def identity(self) -> dict:
        """What a calibration record keeps of the station that made it (``id``, ``name``, ``file``)."""
        return {"id": self.station_id or self.name, "name": self.name, "file": str(self.path)}

    @property
    def config_hash(self) -> str:
        """SHA-256 (first 16 hex digits) of the station file and the facet (or heliostat) file as loaded."""
        design = self.design.to_dict() if self.ensemble is None else self.ensemble.to_dict()
        blob = json.dumps({"station": self.raw, "facet": design}, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


def _camera(table: dict, where: str) -> CameraIntrinsics:
    _check_keys(table, _CAMERA_KEYS, where)
    w = _need(table, "width_px", where)
    h = _need(table, "height_px", where)
    f = _need(table, "focal_length_px", where)
    fx, fy = (f, f) if np.isscalar(f) else tuple(f)
    cx, cy = table.get("principal_point_px", [(w - 1) / 2.0, (h - 1) / 2.0])
    dist = list(table.get("distortion", [0.0] * 5))
    if len(dist) == 4:                   # OpenCV's k1, k2, p1, p2: k3 = 0 (the schema allows 4 or 5 terms)
        dist.append(0.0)
    try:
        return CameraIntrinsics(w, h, [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dist)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def load_config(path: str | Path, use_camera_record: bool = True) -> StationConfig:
    """Read and validate a station file.

    With ``[camera] intrinsics = "record"`` the camera intrinsics come from the newest camera record under
    ``data_dir`` (*use_camera_record* False keeps the table's: for ``calibrate camera``, which makes the record).
    """
    path = Path(path).expanduser().resolve()
    raw = read_toml(path, "station file", "pass --config or run from the project folder")
    where = str(path)
    validate(raw, where)              # every section, key, type and range, before anything is built
    base = path.parent
    st = raw.get("station", {})
    _check_keys(st, _STATION_KEYS, f"{where} [station]")
    backend = st.get("backend", "simulated")
    if backend not in _BACKENDS:
        raise ConfigError(f"{where} [station] backend must be one of {_BACKENDS}, got {backend!r}")
    data_dir = data_dir_of(st, base)
    name = str(st.get("name", path.stem))
    station_id = st.get("id", name)
    if not isinstance(station_id, str) or not station_id.strip():
        raise ConfigError(f"{where} [station] id = {station_id!r}: must be a non-empty string naming this station "
                          "(every calibration record it makes carries it), e.g. \"line-2-dish\"")
    identity = {"id": station_id.strip(), "name": name, "file": str(path)}
    facet_path = base / _need(st, "facet", f"{where} [station]")
    ensemble = None
    if is_ensemble_file(facet_path):      # a heliostat: laid out for its bounding outline
        ensemble = load_ensemble(facet_path)
        design = ensemble.layout_design()
    else:
        design = load_facet(facet_path)
    camera = _camera(raw.get("camera", {}), f"{where} [camera]")
    scr = raw.get("screen", {})
    _check_keys(scr, {"width_px", "height_px", "pitch_m", "pitch_x_m", "pitch_y_m"}, f"{where} [screen]")
    try:
        size = (_need(scr, "width_px", f"{where} [screen]"), _need(scr, "height_px", f"{where} [screen]"))
        if "pitch_x_m" in scr or "pitch_y_m" in scr:      # non-square display pixels
            screen = ScreenSpec(*size, _need(scr, "pitch_x_m", f"{where} [screen]"),
                                _need(scr, "pitch_y_m", f"{where} [screen]"))
        else:
            screen = ScreenSpec(*size, _need(scr, "pitch_m", f"{where} [screen]"))
    except ConfigError as exc:
        raise ConfigError(f"{where} [screen]: {exc}") from None
    lay = raw.get("layout", {})
    _check_keys(lay, _LAYOUT_KEYS, f"{where} [layout]")
    try:
        offset = lay.get("screen_offset_m", [0.0, 0.0])
        if len(offset) != 2 or not all(isinstance(v, (int, float)) for v in offset):
            raise ConfigError("screen_offset_m must be [x, y] in metres")
        geometry = layout_station(design, camera, screen, float(_need(lay, "separation_m", f"{where} [layout]")),
                                  lay.get("separation_axis", "x"), (float(offset[0]), float(offset[1])))
    except ConfigError as exc:
        raise ConfigError(f"{where} [layout]: {exc}") from None
    try:
        fringes = FringeSet.from_dict(raw.get("fringes", {}))
    except (ConfigError, TypeError) as exc:
        raise ConfigError(f"{where} [fringes]: {exc}") from None
    an = raw.get("analysis", {})
    _check_keys(an, {f.name for f in fields(AnalysisSettings)}, f"{where} [analysis]")
    threads = an.get("threads", AnalysisSettings.threads)
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"{where} [analysis] threads must be a whole number of at least 1, got {threads!r}")
    analysis = AnalysisSettings(**an)
    limits = limits_from_table(raw.get("limits", {}), f"{where} [limits]")
    quality = quality_from_table(raw.get("quality", {}), f"{where} [quality]")
    cal = raw.get("calibration", {})
    _check_keys(cal, CALIBRATION_KEYS, f"{where} [calibration]")
    parse_calibration_table(cal, f"{where} [calibration]")       # validates policy and routine settings
    radiometric = base / cal["radiometric"] if "radiometric" in cal else None
    camera_record = None
    source = raw.get("camera", {}).get("intrinsics", "station.toml")
    if source == "record" and use_camera_record:
        recorded, camera_record = camera_from_record(data_dir, geometry.camera, f"{where} [camera]", identity)
        geometry = dataclasses.replace(geometry, camera=recorded)
    elif source not in ("station.toml", "record"):
        raise ConfigError(f"{where} [camera] intrinsics must be \"station.toml\" (the table's values) or "
                          f"\"record\" (the newest 'calibrate camera' record), got {source!r}")
    stated_geometry = geometry
    geometry, commissioned, commissioned_std = geometry_in_force(data_dir, stated_geometry, where,
                                                                 cal.get("geometry", "records"), identity)
    uncertainty = InputUncertainties.from_table(raw.get("uncertainty", {}), f"{where} [uncertainty]")
    _check_camera_uncertainty(uncertainty, geometry.camera, f"{where} [uncertainty]")
    if camera_record is not None:
        uncertainty = uncertainty.with_camera_record(camera_record)
    uncertainty = uncertainty.with_commission_records(commissioned_std)
    checked = _geometry_record_std(data_dir, geometry, identity)
    if "fixture_rotation_mrad" in commissioned_std:
        # the fixture pose measured by the pose calibration; a reference check that confirmed it better wins
        for key in ("fixture_rotation_mrad", "fixture_translation_mm"):
            if key in checked and max(checked[key]) >= max(commissioned_std[key]):
                del checked[key]
    uncertainty = uncertainty.with_geometry_record(checked)
    uncertainty, fringes = _with_radiometric_record(uncertainty, data_dir, radiometric, geometry, fringes, identity)
    heliostat = HeliostatSettings(**raw.get("heliostat", {}))
    if ensemble is None and (raw.get("heliostat") or limits.max_canting_mrad is not None):
        raise ConfigError(f"{where}: [heliostat] and [limits] max_canting_mrad are for a heliostat, but [station] "
                          f"facet = {str(st['facet'])!r} is a single facet's file; name a heliostat file "
                          "(a [heliostat] table, docs/heliostats.md) or remove them")
    return StationConfig(path=path, name=name, data_dir=data_dir, backend=backend,
                         facet_path=facet_path, design=design, geometry=geometry, fringes=fringes,
                         analysis=analysis, limits=limits, quality=quality, radiometric_path=radiometric,
                         simulation=raw.get("simulation", {}), raw=raw, camera_record=camera_record,
                         optics=_optics(raw, where), uncertainty=uncertainty, ensemble=ensemble,
                         heliostat=heliostat, stated_geometry=stated_geometry, commissioned=commissioned,
                         station_id=identity["id"])


def _check_camera_uncertainty(uncertainty, camera, where: str) -> None:
    """A camera's focal length or principal point uncertain by a fifth of its focal length is no calibrated
    camera's: the uncertainty's reruns would move the lens to nonsense (a negative focal length), and the
    first facet would fail with a message about its corners. Named here, at load."""
    f_px = float(min(camera.matrix[0, 0], camera.matrix[1, 1]))
    for key, what in (("camera_focal_px", "focal length"), ("camera_principal_px", "principal point")):
        u = float(getattr(uncertainty, key))
        if u > 0.2 * f_px:
            raise ConfigError(f"{where} {key} = {u:g} px is {u / f_px:.3g} times the camera's focal length "
                              f"({f_px:g} px): not the standard uncertainty of a calibrated camera's {what} (a few "
                              "pixels; `calibrate camera` states it); correct it")


def _optics(raw: dict, where: str):
    """``[optics]`` as OpticsSettings (None when disabled); validated in
    :mod:`sofast_station.result.optical_figures`."""
    optics = optics_for(raw, where)
    used = [k for k in OPTICAL_LIMITS if raw.get("limits", {}).get(k) is not None]
    if optics is None and used:
        raise ConfigError(f"{where} [limits] sets {', '.join(used)} but [optics] enabled = false: the optical "
                          "figures are not computed; enable [optics] or remove those limits")
    return optics


def _geometry_record_std(data_dir: Path, geometry, station: dict | None = None) -> dict:
    """What the newest geometry record (``calibrate geometry``) lends the uncertainty budget, if it was
    within tolerance and made with this geometry (:func:`~sofast_station.calibrate.geometry_record.budget_std`);
    {} when there is none, it does not apply, or it cannot be read (logged: what it would have lent is then
    left to ``[uncertainty]``)."""
    path = newest_record_path(data_dir, "geometry", station)
    if path is None:
        return {}
    try:
        record = load_geometry_record(path)
    except ConfigError as exc:
        log.warning("the geometry record lends the uncertainty budget nothing: %s; the fixture pose and the "
                    "distance keep their [uncertainty] values (run 'sofast-station calibrate geometry' again)", exc)
        return {}
    lent = budget_std(record, geometry)
    if not lent:
        log.info("the geometry record %s lends the uncertainty budget nothing (outside tolerance, made with "
                 "another geometry, or it determined nothing)", path)
    return lent


def _with_radiometric_record(uncertainty, data_dir: Path, shipped: Path | None, geometry, fringes,
                             station: dict | None = None):
    """*uncertainty* with the display-response part the radiometric record in force states (the newest
    under *data_dir*, else the shipped default; :meth:`InputUncertainties.with_radiometric_record`), and
    *fringes* as the display draws them through its table (:meth:`FringeSet.drawn_through`); both
    unchanged when there is none or it cannot be read (logged; opening the station reports it too)."""
    path = newest_record_path(data_dir, "radiometric", station) or shipped
    if path is None:
        return uncertainty, fringes
    try:
        record = load_radiometric(path)
    except (ConfigError, OSError) as exc:
        log.warning("the radiometric record %s cannot be read (%s): the uncertainty budget's display response "
                    "leaves out the rounding of its lookup table to 8-bit commands", path, exc)
        return uncertainty, fringes
    scr = geometry.screen
    samples = (scr.width_px / fringes.periods_x[-1], scr.height_px / fringes.periods_y[-1])
    return (uncertainty.with_radiometric_record(record.lut, record.floor_level, record.max_level, samples),
            fringes.drawn_through(record.lut, record.floor_level, record.max_level, scr.width_px, scr.height_px))


def camera_from_record(data_dir: Path, stated: CameraIntrinsics, where: str,
                       station: dict | None = None) -> tuple[CameraIntrinsics, dict]:
    """The intrinsics of the newest camera record under *data_dir* (``[camera] intrinsics = "record"``).

    The record must be for a camera of the [camera] table's size; a missing, corrupt or mismatched record
    is a ConfigError naming the file and what to do.
    """
    # lazy: calibrate.camera, ~20-30 ms at every start (-X importtime); only intrinsics = "record" needs it
    from .calibrate.camera import load_camera_record

    path = newest_record_path(data_dir, "camera", station)
    if path is None:
        raise ConfigError(f"{where}: intrinsics = \"record\" but there is no camera record in "
                          f"{record_dir(data_dir, 'camera')}: run 'sofast-station calibrate camera IMAGES...', or "
                          "set intrinsics = \"station.toml\" to use the table's values")
    camera, record = load_camera_record(path)
    if camera.shape != stated.shape:
        raise ConfigError(f"camera record {path} is for a {camera.width_px} x {camera.height_px} camera, but {where} "
                          f"says {stated.width_px} x {stated.height_px}: calibrate this camera, or fix width_px and "
                          "height_px")
    return camera, {"record_id": str(record.get("record_id", path.stem)), "path": path, "stated": stated,
                    "std": record.get("std_intrinsics")}
