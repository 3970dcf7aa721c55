"""Calibration records: what the calibrations found, stored as dated JSON.

The simulated station ships a default radiometric record in ``calibration/``; a station writes its own
records under ``data_dir/calibration/<kind>/`` (:mod:`sofast_station.calibrate.store`), one file per run,
never overwritten.

A radiometric record made by the daily routine (:mod:`sofast_station.calibrate.radiometric`) carries,
besides the fields every radiometric record has, the dark level it saw, the display latency and the
settle time derived from it, the refresh rate, and the measured and fitted response (``curve``); these
optional fields are absent from the shipped default and from older records.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError

SCHEMA = 1


@dataclass(frozen=True)
class RadiometricRecord:
    """End-to-end display -> camera response and the lookup table that linearises fringes.

    Attributes
    ----------
    record_id : str
    created : str
        ISO 8601 date and time with time zone.
    source : str
        How the record came to be (a calibration run, or a shipped default and why).
    lut : (N,) array
        Command / 255 as a function of linear response level 0..1, increasing.
    floor_level, max_level : float
        Linear response levels of the fringe minimum (the calibrated floor) and maximum.
    exposure_s, gain : float
        Camera settings the record was made with.
    dark_level_dn : float or None
        Mean DN of the whole camera frame with the screen dark (command 0) at ``exposure_s`` and ``gain``
        when the record was made: the reference for the dark-level drift check.
    latency_frames : int or None
        Camera frames grabbed after a display change that still showed the previous image.
    settle_s : float or None
        Display settle time derived from the latency, seconds (covers it with one refresh to spare).
    refresh_hz : float or None
        Display refresh rate the exposure was chosen for, Hz.
    curve : dict or None
        The routine's measurements and fit (ramp commands, responses, floor, top, fit method and
        coefficients, search history); plain JSON data.
    path : Path or None
        The file the record was read from (not stored in it).
    """

    record_id: str
    created: str
    source: str
    lut: np.ndarray
    floor_level: float
    max_level: float
    exposure_s: float
    gain: float
    dark_level_dn: float | None = None
    latency_frames: int | None = None
    settle_s: float | None = None
    refresh_hz: float | None = None
    curve: dict | None = field(default=None, compare=False)
    path: Path | None = field(default=None, compare=False)

    def to_dict(self, curve: bool = False) -> dict:
        """Plain data: what a data dump keeps of the record in force; with *curve* also the routine's
        measurements, as the record's own file holds them."""
        out = {"schema": SCHEMA, "kind": "radiometric", "record_id": self.record_id, "created": self.created,
               "source": self.source, "lut": [float(v) for v in self.lut], "floor_level": self.floor_level,
               "max_level": self.max_level, "exposure_s": self.exposure_s, "gain": self.gain}
        for key in _OPTIONAL:
            value = getattr(self, key)
            if value is not None:
                out[key] = value
        if curve and self.curve is not None:
            out["curve"] = self.curve
        return out


#: Optional scalar fields of a radiometric record, written only when set (the shipped default has none).
_OPTIONAL = ("dark_level_dn", "latency_frames", "settle_s", "refresh_hz")


def load_radiometric(path: str | Path) -> RadiometricRecord:
    """Read a radiometric record; every problem names the file and what to do."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"radiometric calibration record {path} does not exist; run "
                          "'sofast-station calibrate radiometric' or fix [calibration] in station.toml") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"radiometric calibration record {path} is corrupt ({exc}); rerun the calibration") from None
    if not isinstance(d, dict) or d.get("kind") != "radiometric":
        raise ConfigError(f"{path} is not a radiometric calibration record")
    if d.get("schema") != SCHEMA:
        raise ConfigError(f"{path} has schema {d.get('schema')!r}; this software reads schema {SCHEMA}")
    missing = [k for k in ("record_id", "created", "lut", "floor_level", "max_level", "exposure_s", "gain")
               if k not in d]
    if missing:
        raise ConfigError(f"radiometric calibration record {path} lacks {', '.join(missing)}; rerun the calibration")
    try:
        lut = np.asarray(d["lut"], dtype=np.float64)
        numbers = np.array([d["floor_level"], d["max_level"], d["exposure_s"], d["gain"]], dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"radiometric calibration record {path} holds values that are not numbers (lut, "
                          "floor_level, max_level, exposure_s, gain); rerun the calibration") from None
    redo = ("rerun 'sofast-station calibrate radiometric', or point [calibration] radiometric in station.toml "
            "at a good record")
    if lut.ndim != 1 or lut.size < 2:
        raise ConfigError(f"radiometric calibration record {path}: lut must be a list of at least 2 numbers; {redo}")
    bad = np.flatnonzero(~np.isfinite(lut))
    if bad.size:
        raise ConfigError(f"radiometric calibration record {path} holds non-finite values: lut[{bad[0]}] = "
                          f"{lut[bad[0]]} ({bad.size} of {lut.size} entries); {redo}")
    for key, value in zip(("floor_level", "max_level", "exposure_s", "gain"), numbers):
        if not np.isfinite(value):
            raise ConfigError(f"radiometric calibration record {path} holds non-finite values: {key} = {value}; {redo}")
    falls = np.flatnonzero(np.diff(lut) < 0)
    if falls.size:
        i = int(falls[0])
        raise ConfigError(f"radiometric calibration record {path}: the response curve (lut) is not monotone: lut[{i}] "
                          f"= {lut[i]:.6g} > lut[{i + 1}] = {lut[i + 1]:.6g} ({falls.size} fall(s)); it must increase "
                          f"within 0..1; {redo}")
    if lut[0] < 0 or lut[-1] > 1:
        raise ConfigError(f"radiometric calibration record {path}: the lookup table must increase within 0..1, runs "
                          f"from {lut[0]:.6g} to {lut[-1]:.6g}; {redo}")
    if not (numbers[2] > 0 and numbers[3] > 0):
        raise ConfigError(f"radiometric calibration record {path}: exposure_s = {numbers[2]:g} and gain = "
                          f"{numbers[3]:g} must be positive; {redo}")
    if not 0 <= d["floor_level"] < d["max_level"] <= 1:
        raise ConfigError(f"radiometric calibration record {path}: need 0 <= floor_level < max_level <= 1")
    optional = {}
    for key, kind in (("dark_level_dn", float), ("settle_s", float), ("refresh_hz", float), ("latency_frames", int)):
        value = d.get(key)
        if value is None:
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
            raise ConfigError(f"radiometric calibration record {path}: {key} must be a number >= 0, got {value!r}; "
                              "rerun the calibration")
        optional[key] = kind(value)
    if d.get("curve") is not None and not isinstance(d["curve"], dict):
        raise ConfigError(f"radiometric calibration record {path}: curve must be a table; rerun the calibration")
    return RadiometricRecord(str(d["record_id"]), str(d["created"]), str(d.get("source", "")), lut,
                             float(d["floor_level"]), float(d["max_level"]), float(d["exposure_s"]), float(d["gain"]),
                             curve=d.get("curve"), path=path, **optional)
