"""Where calibration records live, which one is in force, and whether it may still be used.

Records are JSON files under ``data_dir/calibration/<kind>/`` (kind ``radiometric``, ``camera`` or
``geometry``), named ``<kind>-<UTC date and time>Z-<sequence>.json``; a file is created exclusively and
never overwritten, so the folder is the history. The newest record is the last file name in sort order
(the name carries the creation time in UTC). Companion files (the radiometric routine's PNG plot) share
the record's stem.

Every record a command makes carries the identity of the station that made it (``station``: its ``id``, name
and file; ``[station] id`` in station.toml, else its name), and a station never uses another station's record:
:func:`newest_record_path` given the station's identity refuses (ConfigError) a newest record made by another
station, e.g. one copied from another station's data_dir, or two stations sharing one ``SOFAST_DATA_DIR``. A
record made before records carried it (or written by a test without it) names no station and is used.

The radiometric record in force is the newest one under ``data_dir``, else the shipped default named by
``[calibration] radiometric`` (reported as such), else none (a linear display assumed). It is stale when
it is older than ``max_age_h`` (the simulated station's shipped default is exempt: the twin does not age),
or when the dark level the camera sees now differs from the one stored in the record by more than
``max_dark_shift_dn`` (room lighting changed); a stale record makes the station warn or refuse
(``[calibration] stale``). The optional warm-up interlock refuses until the camera has run for
``warmup_min`` minutes.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..devices.renderer import identity_lut
from ..errors import ConfigError
from ..files import write_json_atomic
from ..fringes import Pattern
from .errors import StaleCalibrationError, WarmupError
from .records import RadiometricRecord, load_radiometric
from .settings import CalibrationPolicy, calibration_settings

log = logging.getLogger(__name__)

KINDS = ("radiometric", "camera", "geometry", "screen", "pose", "handheld", "cameraposition", "dots", "marks")

_NAME = re.compile(r"^(?P<kind>[a-z]+)-(?P<stamp>\d{8}T\d{6})Z-(?P<seq>\d{3,})\.json$")


# -- files --------------------------------------------------------------------------------------------
def record_dir(data_dir: str | Path, kind: str) -> Path:
    """The folder of *kind* records under *data_dir*."""
    if kind not in KINDS:
        raise ValueError(f"unknown calibration record kind {kind!r}; use one of {KINDS}")
    return Path(data_dir) / "calibration" / kind


def list_records(data_dir: str | Path, kind: str) -> list[Path]:
    """Record files of *kind*, oldest first (other files in the folder are ignored)."""
    folder = record_dir(data_dir, kind)
    if not folder.is_dir():
        return []
    names = [p for p in folder.iterdir() if p.is_file() and (m := _NAME.match(p.name)) and m["kind"] == kind]
    return sorted(names, key=lambda p: p.name)


#: The command that makes a record of each kind (for the message refusing another station's record).
_MADE_BY = {"radiometric": "calibrate radiometric", "camera": "calibrate camera IMAGES...",
            "geometry": "calibrate geometry", "screen": "calibrate screen", "pose": "calibrate pose",
            "handheld": "calibrate camera --handheld IMAGES...", "cameraposition": "calibrate camera-position",
            "dots": "calibrate dots", "marks": "calibrate marks"}


def newest_record_path(data_dir: str | Path, kind: str, station: dict | None = None) -> Path | None:
    """The newest record file of *kind*, or None.

    Parameters
    ----------
    data_dir : path
    kind : str
    station : dict, optional
        The identity of the station that will use the record (``StationConfig.identity``): a newest record
        made by another station is refused (:func:`check_station`).
    """
    records = list_records(data_dir, kind)
    if not records:
        return None
    if station is not None:
        check_station(records[-1], kind, station)
    return records[-1]


def check_station(path: str | Path, kind: str, station: dict) -> None:
    """Refuse the record file *path* when another station made it.

    Parameters
    ----------
    path : path
        A record file.
    kind : str
        Its kind (for the message: the command that makes this station its own).
    station : dict
        ``id``, ``name`` and ``file`` of the station that would use it.

    Raises
    ------
    ConfigError
        The record names a station whose id is not *station*'s: which station made it, which one is asking,
        and what to do. A record naming no station (made before records carried it) passes, and so does one
        that cannot be read (its reader names that problem).
    """
    try:
        made = json.loads(Path(path).read_text()).get("station")
    except (OSError, ValueError, AttributeError):
        return
    if made is None:
        return
    made = made if isinstance(made, dict) else {"id": made}
    if made.get("id") == station["id"]:
        return
    by = f"station {made.get('id')!r}" + (f" ({made['file']})" if made.get("file") else "")
    raise ConfigError(f"{kind} record {path} was made by {by}, not by this station {station['id']!r} "
                      f"({station.get('file', '')}): a station never uses another station's calibration. Give each "
                      "station a data_dir of its own ([station] data_dir; SOFAST_DATA_DIR overrides it for every "
                      f"station), or run 'sofast-station {_MADE_BY.get(kind, 'calibrate')}' on this station")


def now_local() -> _dt.datetime:
    """The current local time with its UTC offset."""
    return _dt.datetime.now().astimezone()


def write_record(data_dir: str | Path, kind: str, build: Callable[[str, str], dict],
                 created: _dt.datetime | None = None, station: dict | None = None) -> tuple[Path, str]:
    """Write a new record file exclusively (never replacing one), atomically and durably.

    Parameters
    ----------
    data_dir : path
        The station's data folder.
    kind : str
        ``radiometric``, ``camera`` or ``geometry``.
    build : callable
        ``build(record_id, created_iso) -> dict``: the JSON content, given the record's id and creation
        time (ISO 8601 with the local UTC offset).
    created : datetime, optional
        Creation time (tz-aware); now by default.
    station : dict, optional
        The identity of the station the record is made on (``StationConfig.identity``), stored as its
        ``station``: another station never uses the record (:func:`check_station`).

    Returns
    -------
    (Path, str)
        The file written and the record id.
    """
    created = now_local() if created is None else created
    if created.tzinfo is None:
        raise ValueError("created must carry a time zone")
    folder = record_dir(data_dir, kind)
    folder.mkdir(parents=True, exist_ok=True)
    stamp = created.astimezone(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    created_iso = created.isoformat(timespec="seconds")
    seq = 1
    while True:
        record_id = f"{kind}-{stamp}Z-{seq:03d}"
        path = folder / f"{record_id}.json"
        if path.exists():
            seq += 1
            continue
        data = build(record_id, created_iso)
        if station is not None:
            data = {**data, "station": dict(station)}
        try:
            write_json_atomic(path, data, replace=False)     # never overwrite: the name may be taken meanwhile
        except FileExistsError:
            seq += 1
            continue
        log.info("wrote %s record %s", kind, path)
        return path, record_id


def read_record(path: str | Path, kind: str, schema: int, what: str, redo: str) -> dict:
    """A record file's JSON content, checked for its *kind* and *schema*; ConfigError naming the file (*what*:
    e.g. "dots record") and what to do (*redo*) otherwise."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{what} {path} does not exist; {redo}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{what} {path} is corrupt ({exc}); {redo}") from None
    if not isinstance(d, dict) or d.get("kind") != kind:
        raise ConfigError(f"{path} is not a {what}")
    if d.get("schema") != schema:
        raise ConfigError(f"{path} has schema {d.get('schema')!r}; this software reads schema {schema}")
    return d


def parse_created(record: RadiometricRecord, where: str) -> _dt.datetime:
    """The record's creation time (tz-aware); ConfigError naming *where* when it is unusable."""
    try:
        created = _dt.datetime.fromisoformat(record.created)
    except (TypeError, ValueError):
        raise ConfigError(f"calibration record {where}: created {record.created!r} is not an ISO 8601 date and "
                          "time; rerun the calibration") from None
    if created.tzinfo is None:
        raise ConfigError(f"calibration record {where}: created {record.created!r} has no time zone; rerun the "
                          "calibration")
    return created


# -- the record in force -----------------------------------------------------------------------------
@dataclass
class CalibrationStatus:
    """The radiometric record in force and what the checks found.

    Attributes
    ----------
    record : RadiometricRecord
    origin : str
        ``"data_dir"`` (made by the routine on this station), ``"shipped default"`` or ``"none"``.
    path : Path or None
        The record's file.
    exempt : bool
        Exempt from the age check (the simulated station's shipped default).
    age_h : float or None
        Age of the record, hours.
    dark_shift_dn : float or None
        Dark level now minus the record's, DN (when measured).
    warnings : list of str
        What the checks warned about (also logged, unless *announce* is false).
    announce : bool
        Log each warning as it is found (False for the checks repeated on every facet, whose caller logs
        only changes).
    """

    record: RadiometricRecord
    origin: str
    path: Path | None
    exempt: bool = False
    age_h: float | None = None
    dark_shift_dn: float | None = None
    warnings: list[str] = field(default_factory=list)
    announce: bool = True

    @property
    def describe(self) -> str:
        """One line: which record, from where."""
        if self.origin == "none":
            return "no radiometric calibration (linear display assumed)"
        return f"radiometric record {self.record.record_id} ({self.origin}, {self.path})"


def _no_calibration(config) -> CalibrationStatus:
    record = RadiometricRecord("none", "", "no calibration: linear display assumed", identity_lut(), 0.0, 1.0,
                               1 / 60, 1.0)
    return CalibrationStatus(record, "none", None, exempt=config.backend == "simulated")


def select_radiometric(config, tolerant: bool = False) -> CalibrationStatus:
    """The radiometric record in force for a station (newest under ``data_dir``, else the shipped default).

    Parameters
    ----------
    config : StationConfig
    tolerant : bool
        Fall back to no calibration (a linear display), with a warning, instead of raising when the record
        cannot be read: for the calibration routine, which replaces it.

    Raises
    ------
    ConfigError
        The newest record under ``data_dir``, or the shipped default, is missing, corrupt or invalid (the
        message names the file).
    """
    try:
        newest = newest_record_path(config.data_dir, "radiometric", getattr(config, "identity", None))
        if newest is not None:
            record = load_radiometric(newest)
            return CalibrationStatus(record, "data_dir", newest)
        if config.radiometric_path is not None:
            record = load_radiometric(config.radiometric_path)
            exempt = config.backend == "simulated"
            return CalibrationStatus(record, "shipped default", Path(config.radiometric_path), exempt=exempt)
    except ConfigError as exc:
        if not tolerant:
            raise
        log.warning("%s; going on without a radiometric calibration", exc)
    return _no_calibration(config)


def _stale(policy: CalibrationPolicy, status: CalibrationStatus, message: str) -> None:
    if policy.stale == "refuse":
        raise StaleCalibrationError(message + " (the station is configured to refuse: [calibration] stale = "
                                    "\"refuse\")")
    if status.announce:
        log.warning("%s", message)
    status.warnings.append(message)


def check_age(status: CalibrationStatus, policy: CalibrationPolicy, now: _dt.datetime | None = None) -> None:
    """Warn or refuse (per *policy*) when the record in force is older than ``max_age_h``.

    No record, or a shipped default on a station other than the simulated one, counts as stale too: it
    was not measured on this station.
    """
    if status.exempt:
        log.debug("%s is exempt from the age check", status.describe)
        return
    if status.origin in ("none", "shipped default"):
        # A shipped default was not measured on this station's hardware, whatever its date.
        what = "" if status.origin == "none" else f" (the shipped default {status.path} is in force)"
        _stale(policy, status, f"no radiometric calibration has been made on this station{what}: run "
                               "'sofast-station calibrate radiometric'")
        return
    now = now_local() if now is None else now
    created = parse_created(status.record, str(status.path))
    status.age_h = (now - created).total_seconds() / 3600.0
    if status.age_h > policy.max_age_h:
        _stale(policy, status, f"{status.describe} is {status.age_h:.1f} h old, older than max_age_h = "
                               f"{policy.max_age_h:g} h: run 'sofast-station calibrate radiometric'")


def measure_dark_level(display, camera, frames: int = 1) -> float:
    """Mean DN of the whole camera frame with the screen dark (command 0), over *frames* grabs."""
    display.show(Pattern("uniform", command=0))
    total = 0.0
    for _ in range(int(frames)):
        total += float(np.mean(camera.grab(), dtype=np.float64))
    return total / int(frames)


def check_dark_level(status: CalibrationStatus, policy: CalibrationPolicy, dark_level_dn: float) -> None:
    """Warn or refuse (per *policy*) when the dark level moved by more than ``max_dark_shift_dn``.

    Parameters
    ----------
    status : CalibrationStatus
    policy : CalibrationPolicy
    dark_level_dn : float
        Mean DN of a whole frame with the screen dark, at the record's exposure and gain (an
        inspection's dark frame serves as well).
    """
    ref = status.record.dark_level_dn
    if ref is None or policy.max_dark_shift_dn <= 0:
        return
    status.dark_shift_dn = float(dark_level_dn) - ref
    log.debug("dark level %.2f DN, %.2f DN at calibration", dark_level_dn, ref)
    if abs(status.dark_shift_dn) > policy.max_dark_shift_dn:
        _stale(policy, status, f"the dark level moved from {ref:.2f} DN to {dark_level_dn:.2f} DN since "
                               f"{status.describe} (more than max_dark_shift_dn = {policy.max_dark_shift_dn:g} "
                               "DN): room lighting or the camera changed; run 'sofast-station calibrate radiometric'")


# -- warm-up ------------------------------------------------------------------------------------------
def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:               # not Linux: the boot time is the best we have
        return f"boot-{int(time.time() - time.monotonic())}"


def _marker(data_dir: Path) -> Path:
    return Path(data_dir) / "calibration" / "camera-started.json"


def mark_camera_started(data_dir: str | Path, started_epoch_s: float) -> None:
    """Record when the camera started (this boot), epoch seconds: the warm-up is counted from it."""
    marker = _marker(Path(data_dir))
    marker.parent.mkdir(parents=True, exist_ok=True)
    when = _dt.datetime.fromtimestamp(started_epoch_s).astimezone().isoformat(timespec="seconds")
    marker.write_text(json.dumps({"boot_id": _boot_id(), "started_epoch_s": float(started_epoch_s),
                                  "started": when}) + "\n")


def camera_started(data_dir: str | Path, camera, now_epoch_s: float | None = None) -> float:
    """When the camera started, epoch seconds.

    A camera backend that knows (an attribute ``started_at``, epoch seconds) is believed; otherwise the
    first time this station opened a camera since the computer booted (kept in
    ``data_dir/calibration/camera-started.json``; cameras on USB or PoE are powered with the computer).
    """
    started = getattr(camera, "started_at", None)
    if started is not None:
        return float(started)
    now = time.time() if now_epoch_s is None else now_epoch_s
    marker = _marker(Path(data_dir))
    try:
        d = json.loads(marker.read_text())
        if d.get("boot_id") == _boot_id():
            return float(d["started_epoch_s"])
    except (OSError, ValueError, KeyError, TypeError):
        pass
    mark_camera_started(data_dir, now)
    return now


def check_warmup(policy: CalibrationPolicy, data_dir: str | Path, camera, now_epoch_s: float | None = None) -> None:
    """Refuse (WarmupError) while the camera has run for less than ``warmup_min`` minutes, if the interlock is on."""
    if not policy.warmup:
        return
    now = time.time() if now_epoch_s is None else now_epoch_s
    started = camera_started(data_dir, camera, now)
    running_min = (now - started) / 60.0
    if running_min < policy.warmup_min:
        since = _dt.datetime.fromtimestamp(started).astimezone().strftime("%H:%M:%S")
        ready = _dt.datetime.fromtimestamp(started + 60 * policy.warmup_min).astimezone().strftime("%H:%M")
        raise WarmupError(f"the camera started at {since} and has warmed up for {running_min:.1f} min of the "
                          f"{policy.warmup_min:g} min required: wait {policy.warmup_min - running_min:.1f} min more "
                          f"(until {ready}), or turn the interlock off ([calibration] warmup = false)")


# -- for open_station -----------------------------------------------------------------------------------
def open_calibration(config, now: _dt.datetime | None = None, checks: bool = True) -> CalibrationStatus:
    """Choose the radiometric record for a station about to open and check its age (warn or refuse).

    Parameters
    ----------
    config : StationConfig
    now : datetime, optional
        The time to judge the age at (tz-aware); now by default.
    checks : bool
        False for the calibration routines: no age check, and an unreadable record is replaced by none.

    Raises
    ------
    ConfigError
        Bad ``[calibration]`` settings, or a missing or corrupt record (naming the file).
    StaleCalibrationError
        The record is too old and the station refuses stale records.
    """
    policy, _ = calibration_settings(config)
    status = select_radiometric(config, tolerant=not checks)
    log.info("using %s", status.describe)
    if checks:
        check_age(status, policy, now)
    return status


def check_cycle(status: CalibrationStatus, policy: CalibrationPolicy, dark_level_dn: float | None,
                now: _dt.datetime | None = None) -> CalibrationStatus:
    """The checks repeated for every facet of a run, on the record in force when the station opened.

    A station left running past ``max_age_h`` goes stale mid-shift, and room light can change after the
    station opened: the record's age is judged again, and the facet's own dark frame (*dark_level_dn*,
    the mean DN of the whole frame with the screen dark; None to skip) is compared with the record's.

    Returns
    -------
    CalibrationStatus
        A fresh status for this facet: its ``warnings`` go into the facet's record (nothing is logged).

    Raises
    ------
    StaleCalibrationError
        The record went stale and the station refuses stale records.
    """
    probe = CalibrationStatus(status.record, status.origin, status.path, exempt=status.exempt, announce=False)
    check_age(probe, policy, now)
    if dark_level_dn is not None:
        check_dark_level(probe, policy, dark_level_dn)
    return probe


def check_opened_station(station, status: CalibrationStatus) -> None:
    """The checks that need the devices: the warm-up interlock, then the dark-level drift (one dark frame)."""
    policy, _ = calibration_settings(station.config)
    check_warmup(policy, station.config.data_dir, station.camera)
    if status.record.dark_level_dn is not None and policy.max_dark_shift_dn > 0:
        check_dark_level(status, policy, measure_dark_level(station.display, station.camera))
