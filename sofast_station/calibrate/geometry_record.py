"""The geometry record (``calibrate geometry``): the station's geometry with its provenance and the
reference check, stored as dated JSON under ``data_dir/calibration/geometry/``, and what a record within
tolerance lends the uncertainty budget.

Records only: the routine that measures the reference facet is :mod:`sofast_station.calibrate.geometry`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import ConfigError
from .store import write_record

SCHEMA = 1


def budget_std(record: dict | None, geometry=None) -> dict:
    """The standard uncertainties a geometry record lends the budget (``[uncertainty]`` keys): the
    fixture pose's, and the distance's, from a check that was within tolerance and made with the station's
    present geometry (*geometry*, a StationGeometry, compared with the record's); else {}."""
    if not isinstance(record, dict):
        return {}
    check = record.get("reference_check") or {}
    if not check.get("within_tolerance"):
        return {}
    if geometry is not None and (record.get("screen_to_camera") != geometry.screen_to_camera.to_dict()
                                 or record.get("screen") != geometry.screen.to_dict()
                                 or record.get("measured_screen") != (None if geometry.measured_screen is None
                                                                      else geometry.measured_screen.record_id)):
        return {}
    det = check.get("determined") or {}
    out = {}
    for key in ("fixture_translation_mm", "fixture_rotation_mrad"):
        std = (det.get(key) or {}).get("std")
        if isinstance(std, list) and len(std) == 3 and all(isinstance(v, (int, float)) for v in std):
            out[key] = tuple(float(v) for v in std)
    std = (det.get("distance_mm") or {}).get("std")
    if isinstance(std, (int, float)) and math.isfinite(std):
        out["distance_mm"] = float(std)
    return out


def geometry_provenance(config) -> dict:
    """The station's geometry as the analysis uses it, with where each part comes from."""
    geometry = config.geometry
    provenance = {"screen": f"{config.path} [screen] (width_px, height_px, pitch_m as entered)",
                  "screen_to_camera": f"{config.path} [layout] (the designed assembly: separation "
                                      f"{config.raw.get('layout', {}).get('separation_m')} m along "
                                      f"{config.raw.get('layout', {}).get('separation_axis', 'x')})",
                  "camera": f"{config.path} [camera]"}
    commissioned = getattr(config, "commissioned", None) or {}
    if "screen" in commissioned:
        provenance["screen"] = (f"screen record {commissioned['screen']['record_id']} "
                                "(calibrate screen: its shape and pitch)")
    if "pose" in commissioned:
        provenance["screen_to_camera"] = f"pose record {commissioned['pose']['record_id']} (calibrate pose)"
        provenance["fixture_to_camera"] = f"pose record {commissioned['pose']['record_id']} (calibrate pose)"
    out = {"screen": geometry.screen.to_dict(), "screen_to_camera": geometry.screen_to_camera.to_dict(),
           "camera": geometry.camera.to_dict(), "provenance": provenance}
    if geometry.measured_screen is not None:
        out["measured_screen"] = geometry.measured_screen.record_id
    return out


def save_geometry(data_dir: str | Path, config, check: dict | None, source: str,
                  station: dict | None = None) -> Path:
    """Write a geometry record (the station's geometry, its provenance and the reference check; *station*: the
    identity of the station it is made on)."""
    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": "geometry", "record_id": record_id, "created": created, "source": source,
                **geometry_provenance(config), "reference_check": check}
    path, _ = write_record(data_dir, "geometry", build, station=station)
    return path


def load_geometry_record(path: str | Path) -> dict:
    """Read a geometry record; ConfigError naming the file when it is unusable."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"geometry record {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"geometry record {path} is corrupt ({exc})") from None
    if not isinstance(d, dict) or d.get("kind") != "geometry" or d.get("schema") != SCHEMA:
        raise ConfigError(f"{path} is not a geometry record of schema {SCHEMA}")
    return d
