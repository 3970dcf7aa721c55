"""The field's files: the site file, the field layout, photographs and their notes, the factory's record.

The site file (TOML, docs/field.md#the-site-file)::

    [site]
    name = "north field"
    latitude_deg = 37.094            # the site, for the sun's position (pvlib)
    longitude_deg = -2.359
    altitude_m = 500.0
    layout = "layout.csv"            # the field layout (below), relative to this file
    heliostat = "../facets/heliostat_5x5.toml"   # the design of every heliostat whose layout row names none
    aim_point_m = [0.0, 0.0, 45.0]   # where the heliostats aim (field frame: x east, y north, z up, metres)
    pivot_offset_m = 0.0             # the mirrors' middle in front of the pivot, along the normal

    [camera]                         # the tower's camera
    position_m = [0.0, 0.0, 50.0]
    roll_mrad = 0.0                  # its turn about its optical axis from level (a levelled head: 0)
    width_px = 1000
    height_px = 800
    matrix = [[40000.0, 0.0, 499.5], [0.0, 40000.0, 399.5], [0.0, 0.0, 1.0]]
    distortion = [0.0, 0.0, 0.0, 0.0, 0.0]

    [uncertainty]                    # standard uncertainties (InputUncertainty's defaults otherwise)
    camera_position_m = 0.03

The field layout (CSV, as plant designers export it): a header row naming at least the heliostat's id and
its x, y (and z) in the field frame, metres; the names are matched loosely (``id``, ``serial``, ``name``,
``heliostat``; ``x``, ``x_m``, ``x position``, ``x [m]``...), and a ``design`` column may name each one's
heliostat file.

A photo's notes (``PHOTO.json`` beside ``PHOTO.png``): ``time`` (ISO 8601 with its time zone: the sun's
position, hence the commanded normal), ``heliostat`` (its serial), ``commanded`` ({azimuth_deg,
elevation_deg}: given instead of the time), ``focal_px`` (the zoom's focal length in pixels, replacing the
site's).
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..ensemble import load_ensemble
from ..errors import CaptureError, ConfigError
from ..files import read_toml
from ..geometry import CameraIntrinsics
from .orientation import HeliostatPlace, InputUncertainty, TowerCamera

_ID = {"id", "serial", "name", "heliostat", "heliostatid", "helio", "helioid", "number", "no"}
_AXES = {"x": {"x", "xm", "xposition", "xlocation", "xpos", "east", "eastm"},
         "y": {"y", "ym", "yposition", "ylocation", "ypos", "north", "northm"},
         "z": {"z", "zm", "zposition", "zlocation", "zpos", "height", "heightm", "elevation", "elevationm"}}


@dataclass(frozen=True)
class Site:
    """A site file, read (module docstring)."""

    path: Path
    name: str
    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    camera: TowerCamera
    aim_point_m: np.ndarray
    pivot_offset_m: float = 0.0
    heliostat_file: Path | None = None
    layout_file: Path | None = None
    uncertainty: InputUncertainty = field(default_factory=InputUncertainty)


def _vector(value, what: str, n: int = 3) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be {n} numbers, got {value!r}") from None
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise ConfigError(f"{what} must be {n} finite numbers, got {value!r}")
    return v


def _number(table: dict, key: str, where: str, default=None) -> float:
    if key not in table:
        if default is None:
            raise ConfigError(f"{where} needs {key}")
        return float(default)
    v = table[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{where}: {key} must be a finite number, got {v!r}")
    return float(v)


def load_site(path) -> Site:
    """Read a site file; ConfigError naming the file and the key when something is missing or wrong."""
    path = Path(path)
    data = read_toml(path, "site file")
    for table in ("site", "camera"):
        if not isinstance(data.get(table), dict):
            raise ConfigError(f"site file {path} needs a [{table}] table (docs/field.md#the-site-file)")
    s, c = data["site"], data["camera"]
    where, cwhere = f"site file {path} [site]", f"site file {path} [camera]"
    unknown = sorted(set(s) - {"name", "latitude_deg", "longitude_deg", "altitude_m", "layout", "heliostat",
                                "aim_point_m", "pivot_offset_m"})
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}")
    try:
        intr = CameraIntrinsics(int(c["width_px"]), int(c["height_px"]), np.asarray(c["matrix"], float),
                                np.asarray(c.get("distortion", [0.0] * 5), float))
    except KeyError as exc:
        raise ConfigError(f"{cwhere} needs {exc.args[0]} (width_px, height_px, matrix)") from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{cwhere}: {exc}") from None
    camera = TowerCamera(intr, _vector(c.get("position_m"), f"{cwhere} position_m"),
                         _number(c, "roll_mrad", cwhere, 0.0))
    u = data.get("uncertainty", {})
    if not isinstance(u, dict):
        raise ConfigError(f"site file {path}: [uncertainty] must be a table")
    known = InputUncertainty().to_dict()
    bad = sorted(set(u) - set(known))
    if bad:
        raise ConfigError(f"site file {path} [uncertainty] has unknown key(s) {', '.join(bad)}; use "
                          f"{', '.join(known)}")
    unc = InputUncertainty(**{k: _number(u, k, f"site file {path} [uncertainty]", v) for k, v in known.items()})
    lat = _number(s, "latitude_deg", where)
    lon = _number(s, "longitude_deg", where)
    if not (-90 <= lat <= 90 and -180 <= lon <= 360):
        raise ConfigError(f"{where}: latitude {lat} / longitude {lon} degrees are not a place on Earth")
    return Site(path=path, name=str(s.get("name", path.stem)), latitude_deg=lat, longitude_deg=lon,
                altitude_m=_number(s, "altitude_m", where, 0.0), camera=camera,
                aim_point_m=_vector(s.get("aim_point_m"), f"{where} aim_point_m"),
                pivot_offset_m=_number(s, "pivot_offset_m", where, 0.0),
                heliostat_file=(path.parent / s["heliostat"]).resolve() if "heliostat" in s else None,
                layout_file=(path.parent / s["layout"]).resolve() if "layout" in s else None, uncertainty=unc)


def _key(name: str) -> str:
    return re.sub(r"\[.*?\]|\(.*?\)|[^a-z0-9]", "", name.lower())


def read_layout(path) -> dict:
    """The field layout: {serial: {"position_m": (3,), "design": Path or None}} (module docstring)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"field layout {path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"field layout {path} cannot be read: {exc}") from None
    try:
        dialect = csv.Sniffer().sniff(text.splitlines()[0] if text else ",", delimiters=",;\t")
    except csv.Error:
        dialect = csv.excel
    rows = list(csv.reader(text.splitlines(), dialect))
    if not rows:
        raise ConfigError(f"field layout {path} is empty")
    header = [_key(h) for h in rows[0]]
    col = {}
    for i, h in enumerate(header):
        if h in _ID and "id" not in col:
            col["id"] = i
        for axis, names in _AXES.items():
            if h in names and axis not in col:
                col[axis] = i
        if h in ("design", "heliostatfile", "file") and "design" not in col:
            col["design"] = i
    missing = [k for k in ("id", "x", "y") if k not in col]
    if missing:
        raise ConfigError(f"field layout {path}: no column for {', '.join(missing)} in its header {rows[0]!r} "
                          "(name them e.g. id, x, y, z; metres, x east, y north)")
    out = {}
    for n, row in enumerate(rows[1:], start=2):
        if not row or not any(cell.strip() for cell in row):
            continue
        try:
            serial = row[col["id"]].strip()
            pos = [float(row[col[a]]) if a in col and row[col[a]].strip() else 0.0 for a in "xyz"]
        except (IndexError, ValueError):
            raise ConfigError(f"field layout {path} line {n}: {row!r} is not an id and numbers") from None
        if serial in out:
            raise ConfigError(f"field layout {path} line {n}: heliostat {serial!r} listed twice")
        design = None
        if "design" in col and col["design"] < len(row) and row[col["design"]].strip():
            design = (path.parent / row[col["design"]].strip()).resolve()
        out[serial] = {"position_m": np.array(pos), "design": design}
    if not out:
        raise ConfigError(f"field layout {path} lists no heliostat")
    return out


def heliostat_place(site: Site, heliostat: str, position=None) -> HeliostatPlace:
    """The heliostat named on the command line: a heliostat file (with *position*, or its serial in the
    layout by the file's name) or a serial of the site's layout."""
    given = Path(heliostat)
    layout = read_layout(site.layout_file) if site.layout_file is not None else {}
    if given.suffix == ".toml" and given.exists():
        ensemble = load_ensemble(given)
        serial = given.stem
        if position is None:
            raise ConfigError(f"--heliostat {heliostat} is a design file: give --position X,Y,Z (metres, field frame) "
                              "or the heliostat's serial from the site's layout")
        return HeliostatPlace(ensemble, _vector(position, "--position"), site.pivot_offset_m, serial)
    if heliostat not in layout:
        some = ", ".join(list(layout)[:5])
        raise ConfigError(f"heliostat {heliostat!r} is neither a heliostat file nor a serial of the site's layout"
                          + (f" ({site.layout_file}: {some}...)" if layout else " (the site file names no layout)"))
    row = layout[heliostat]
    design = row["design"] or site.heliostat_file
    if design is None:
        raise ConfigError(f"heliostat {heliostat!r}: its layout row names no design and the site file no "
                          "[site] heliostat")
    pos = row["position_m"] if position is None else _vector(position, "--position")
    return HeliostatPlace(load_ensemble(design), pos, site.pivot_offset_m, heliostat)


def read_photo(path) -> np.ndarray:
    """A photograph as an (H, W, 3) RGB or (H, W) grey array (8 or 16 bit); CaptureError when unreadable."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"photo {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise CaptureError(f"photo {path} cannot be read as an image (PNG, JPEG, TIFF...): is it whole?")
    if image.ndim == 3:
        image = image[..., [2, 1, 0]] if image.shape[2] >= 3 else image[..., 0]
    return np.ascontiguousarray(image)


def read_notes(photo) -> dict:
    """The photo's notes (``PHOTO.json`` beside it, or ``PHOTO.png.json``), {} when it has none."""
    photo = Path(photo)
    for candidate in (photo.with_suffix(".json"), photo.with_name(photo.name + ".json")):
        if candidate.is_file():
            try:
                notes = json.loads(candidate.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError) as exc:
                raise ConfigError(f"photo notes {candidate} are not valid JSON: {exc}") from None
            if not isinstance(notes, dict):
                raise ConfigError(f"photo notes {candidate} must be a JSON object")
            return notes
    return {}


def read_record(path, serial: str | None = None) -> dict:
    """The factory's record of a heliostat: a record as ``sofast-station inspect --json`` prints it (JSON), or
    the newest record of *serial* in a station's journal (its SQLite file)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"factory record {path} does not exist")
    if path.suffix.lower() == ".json":
        try:
            record = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"factory record {path} is not valid JSON: {exc}") from None
    else:
        # lazy: the journal, ~80 ms CPU (+24 modules); every field command loads this module, a journal rarely
        from ..archive.journal import Journal

        with Journal(path) as journal:
            rows = journal.rows(serial=serial)
        if not rows:
            raise ConfigError(f"the journal {path} has no record of heliostat {serial!r}")
        record = rows[-1].record
    if not isinstance(record, dict) or not isinstance(record.get("facets"), list):
        raise ConfigError(f"factory record {path} is not a heliostat's record (it has no facets list): give the "
                          "JSON of 'sofast-station inspect --json' for the heliostat, or the station's journal")
    return record


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float, np.integer, np.floating)):
        return repr(float(v)) if isinstance(v, (float, np.floating)) else str(int(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise ConfigError(f"cannot write {v!r} to a heliostat file")


def write_prescribed_heliostat(path, source_file, ensemble, prescription: dict, comment: str) -> Path:
    """A heliostat file (ensemble.py's format) for *ensemble* with each facet's canting from *prescription*
    ({label: {"x", "y"}} mrad), the rest (its facets' design files, adjusters, layout, measure point) as
    *source_file* (the heliostat file it was drawn from) says."""
    path = Path(path)
    source_file = Path(source_file)
    table = read_toml(source_file, "heliostat file").get("heliostat", {})
    lines = [f"# {line}" for line in comment.splitlines()] + ["[heliostat]", f"name = {_toml_value(ensemble.name)}"]
    if "facet" in table:
        lines.append(f"facet = {_toml_value((source_file.parent / table['facet']).resolve().as_posix())}")
    for key in ("measure_facet", "measure_point_m"):
        if key in table:
            lines.append(f"{key} = {_toml_value(table[key])}")
    per_facet = {e.get("label"): e for e in table.get("facets", []) if isinstance(e, dict)}
    for f in ensemble.facets:
        c = prescription[f.label]
        lines += ["", "[[heliostat.facets]]", f"label = {_toml_value(f.label)}",
                  f"position_m = {_toml_value(f.position_m.tolist())}",
                  f"canting_mrad = {_toml_value([c['x'], c['y']])}"]
        own = per_facet.get(f.label, {}).get("facet")
        if own:
            lines.append(f"facet = {_toml_value((source_file.parent / own).resolve().as_posix())}")
    for name in ("adjusters", "layout"):
        sub = table.get(name)
        if isinstance(sub, dict) and sub:
            lines += ["", f"[heliostat.{name}]"] + [f"{k} = {_toml_value(v)}" for k, v in sub.items()]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path
