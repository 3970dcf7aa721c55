"""Calibration records: what the radiometric calibration found, stored as dated JSON.

The simulated station ships a default record in ``calibration/``; a real station writes its records
under ``data_dir`` (the daily routine arrives with the calibration issue).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
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
    """

    record_id: str
    created: str
    source: str
    lut: np.ndarray
    floor_level: float
    max_level: float
    exposure_s: float
    gain: float

    def to_dict(self) -> dict:
        return {"schema": SCHEMA, "kind": "radiometric", "record_id": self.record_id, "created": self.created,
                "source": self.source, "lut": [float(v) for v in self.lut], "floor_level": self.floor_level,
                "max_level": self.max_level, "exposure_s": self.exposure_s, "gain": self.gain}


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
    lut = np.asarray(d["lut"], dtype=np.float64)
    numbers = np.array([d["floor_level"], d["max_level"], d["exposure_s"], d["gain"]], dtype=np.float64)
    if lut.ndim != 1 or lut.size < 2 or not np.all(np.isfinite(lut)) or not np.all(np.isfinite(numbers)):
        raise ConfigError(f"radiometric calibration record {path} holds non-finite values; rerun the calibration")
    if np.any(np.diff(lut) < 0) or lut[0] < 0 or lut[-1] > 1:
        raise ConfigError(f"radiometric calibration record {path}: the lookup table must increase within 0..1")
    if not 0 <= d["floor_level"] < d["max_level"] <= 1:
        raise ConfigError(f"radiometric calibration record {path}: need 0 <= floor_level < max_level <= 1")
    return RadiometricRecord(str(d["record_id"]), str(d["created"]), str(d.get("source", "")), lut,
                             float(d["floor_level"]), float(d["max_level"]), float(d["exposure_s"]), float(d["gain"]))
