"""The ``[calibration]`` table of station.toml: which records to trust, and how the routines run.

::

    [calibration]
    radiometric = "calibration/simulated_radiometric.json"  # shipped default, used until a routine has run
    stale = "warn"              # or "refuse": what a stale record or a moved dark level does
    max_age_h = 24.0            # a radiometric record older than this is stale (shipped simulated default exempt)
    max_dark_shift_dn = 4.0     # dark level moved by more than this since calibration: stale (0 turns it off)
    warmup = false              # refuse to calibrate or inspect before the camera has warmed up
    warmup_min = 30.0           # ... for this long after the camera started

    geometry = "records"       # measure with the newest screen and pose records ("station.toml": as entered)

    [calibration.routine]       # the daily radiometric routine (defaults shown)
    refresh_hz = 60.0           # the display's refresh rate: exposures are whole numbers of its periods
    max_exposure_periods = 2
    gain_min = 1.0
    gain_max = 16.0
    target_dn = 250.0           # full white at the target percentile of the active pixels
    target_percentile = 99.5
    max_saturated_fraction = 0.001
    gain_step = 0.005           # relative: the gain search stops when its bracket is this narrow
    search_frames = 4           # frames averaged for each full-white measurement of the searches
    percentile_smoothing_px = 5 # box mean before the percentile (the signal, not its noise)
    mask_threshold_dn = 20.0
    ramp_step = 5               # commands 0, 5, ..., 255 (255 always included)
    frames_per_level = 2        # at least this many frames per ramp level ...
    max_frames_per_level = 8    # ... and up to this many, to know each level's mean to ramp_noise_dn
    ramp_noise_dn = 0.1
    floor_rise_fraction = 0.02
    fit_order = 11              # the paper's 7 leaves a camera knee under-fitted (docs/calibration.md)
    lut_size = 1024
    initial_settle_s = 0.5
    latency_max_frames = 12
    latency_repeats = 3
    discard_frames = 1

``[calibration.screen]`` and ``[calibration.pose]`` (the geometry commissioning) are described and checked
by :mod:`sofast_station.calibrate.commission_settings`.

This module imports nothing from the rest of the station, so that ``config.py`` can use
:data:`CALIBRATION_KEYS` and :func:`parse_calibration_table` when it loads the file.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..errors import ConfigError
from .commission_settings import PoseSettings, ScreenSettings

#: Keys the ``[calibration]`` table may hold.
CALIBRATION_KEYS = {"radiometric", "stale", "max_age_h", "max_dark_shift_dn", "warmup", "warmup_min", "routine",
                    "geometry", "screen", "pose"}


@dataclass(frozen=True)
class CalibrationPolicy:
    """What the station does with the calibration in force.

    Attributes
    ----------
    stale : str
        ``"warn"`` (log a warning and go on) or ``"refuse"`` (raise StaleCalibrationError).
    max_age_h : float
        Age, hours, beyond which a radiometric record is stale.
    max_dark_shift_dn : float
        Change of the dark level since calibration, DN, beyond which the record is stale; 0 disables
        the check.
    warmup : bool
        Whether the warm-up interlock is on.
    warmup_min : float
        Warm-up time from camera start, minutes.
    """

    stale: str = "warn"
    max_age_h: float = 24.0
    max_dark_shift_dn: float = 4.0
    warmup: bool = False
    warmup_min: float = 30.0


@dataclass(frozen=True)
class RadiometricSettings:
    """How the daily radiometric routine runs (``[calibration.routine]``).

    Attributes
    ----------
    refresh_hz : float
        Display refresh rate, Hz; every exposure is a whole number of its periods (flicker).
    max_exposure_periods : int
        Longest exposure allowed, in refresh periods (two keeps a capture fast).
    gain_min, gain_max : float
        The camera's gain range to use (linear factor, the camera's unit); the exposure is chosen at
        ``gain_min``.
    target_dn : float
        Full white should read this at ``target_percentile`` of the active pixels, DN.
    target_percentile : float
        Percentile of the active pixels held at ``target_dn`` (99.5: a mean of 250 would clip the bright
        centre of a vignetted image).
    max_saturated_fraction : float
        Largest fraction of active pixels allowed at the saturation count on full white.
    saturation_dn : float
        The count at which the camera saturates, DN (255 for 8-bit frames).
    gain_step : float
        Relative width at which the gain search stops (the search step).
    search_frames : int
        Frames averaged for each full-white measurement of the exposure and gain searches.
    percentile_smoothing_px : int
        Side of the box mean (within the active pixels) applied before the percentile, pixels; 1 for none.
    mask_threshold_dn : float
        A pixel is active when white - dark exceeds this, DN.
    ramp_step : int
        Command step of the 0..255 ramp (255 is always measured).
    frames_per_level : int
        Frames averaged for every measurement (at least, for the ramp levels).
    max_frames_per_level : int
        Most frames averaged per ramp level.
    ramp_noise_dn : float
        Standard deviation, DN, to which each ramp level's mean response should be known; the frames per
        level follow from the frame-to-frame variation seen on full white.
    floor_rise_fraction : float
        The floor is the lowest command from which every ramp step rises by more than this fraction of
        the mean step (and by more than three times its noise).
    fit_order : int
        Order of the response polynomial, at most half the number of ramp levels between floor and top.
        The paper uses 7; 11 is the default because a 7th-order polynomial cannot follow a camera's knee
        before saturation closely enough (on the twin with a knee at 243 DN: 0.13 DN RMS residual without
        noise, which leaves the phase error from nonlinearity only 13 times smaller than uncalibrated;
        order 11: 0.06 DN and more than 40 times).
    lut_size : int
        Entries of the lookup table.
    initial_settle_s : float
        Display settle time used before the latency has been measured, seconds.
    latency_max_frames : int
        Give up when a display change has not been seen after this many frames.
    latency_repeats : int
        Display changes timed (the largest latency counts).
    discard_frames : int
        Frames dropped after every exposure or gain change (a free-running camera may deliver a frame
        exposed with the old setting).
    """

    refresh_hz: float = 60.0
    max_exposure_periods: int = 2
    gain_min: float = 1.0
    gain_max: float = 16.0
    target_dn: float = 250.0
    target_percentile: float = 99.5
    max_saturated_fraction: float = 0.001
    saturation_dn: float = 255.0
    gain_step: float = 0.005
    search_frames: int = 4
    percentile_smoothing_px: int = 5
    mask_threshold_dn: float = 20.0
    ramp_step: int = 5
    frames_per_level: int = 2
    max_frames_per_level: int = 8
    ramp_noise_dn: float = 0.1
    floor_rise_fraction: float = 0.02
    fit_order: int = 11
    lut_size: int = 1024
    initial_settle_s: float = 0.5
    latency_max_frames: int = 12
    latency_repeats: int = 3
    discard_frames: int = 1

    def __post_init__(self):
        where = "[calibration.routine]"
        ints = {"max_exposure_periods", "search_frames", "percentile_smoothing_px", "ramp_step", "frames_per_level",
                "max_frames_per_level", "fit_order", "lut_size", "latency_max_frames", "latency_repeats",
                "discard_frames"}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"{where} {f.name} must be a finite number, got {value!r}")
            if f.name in ints:
                if value != int(value):
                    raise ConfigError(f"{where} {f.name} must be a whole number, got {value!r}")
                object.__setattr__(self, f.name, int(value))
            else:
                object.__setattr__(self, f.name, float(value))
        rules = [
            ("refresh_hz", self.refresh_hz > 0, "must be a positive frequency in Hz"),
            ("max_exposure_periods", self.max_exposure_periods >= 1, "must be at least 1"),
            ("gain_min", self.gain_min > 0, "must be positive"),
            ("gain_max", self.gain_max >= self.gain_min, "must be at least gain_min"),
            ("target_dn", 0 < self.target_dn < self.saturation_dn, "must lie between 0 and saturation_dn"),
            ("target_percentile", 50 <= self.target_percentile < 100, "must lie in [50, 100)"),
            ("max_saturated_fraction", 0 <= self.max_saturated_fraction < 0.5, "must lie in [0, 0.5)"),
            ("gain_step", 0 < self.gain_step < 0.5, "must lie in (0, 0.5)"),
            ("search_frames", self.search_frames >= 1, "must be at least 1"),
            ("percentile_smoothing_px", 1 <= self.percentile_smoothing_px <= 31, "must lie in 1..31"),
            ("mask_threshold_dn", self.mask_threshold_dn > 0, "must be positive"),
            ("ramp_step", 1 <= self.ramp_step <= 64, "must lie in 1..64"),
            ("frames_per_level", self.frames_per_level >= 1, "must be at least 1"),
            ("max_frames_per_level", self.max_frames_per_level >= 1, "must be at least 1"),
            ("ramp_noise_dn", self.ramp_noise_dn > 0, "must be positive"),
            ("floor_rise_fraction", 0 < self.floor_rise_fraction < 1, "must lie in (0, 1)"),
            ("fit_order", 1 <= self.fit_order <= 12, "must lie in 1..12"),
            ("lut_size", 2 <= self.lut_size <= 65536, "must lie in 2..65536"),
            ("initial_settle_s", self.initial_settle_s >= 0, "must be >= 0 seconds"),
            ("latency_max_frames", self.latency_max_frames >= 1, "must be at least 1"),
            ("latency_repeats", self.latency_repeats >= 1, "must be at least 1"),
            ("discard_frames", self.discard_frames >= 0, "must be >= 0"),
        ]
        for key, ok, rule in rules:
            if not ok:
                raise ConfigError(f"{where} {key} {rule}, got {getattr(self, key)!r}")

    @property
    def refresh_period_s(self) -> float:
        """One display refresh period, seconds."""
        return 1.0 / self.refresh_hz


def parse_calibration_table(table: dict, where: str) -> tuple[CalibrationPolicy, RadiometricSettings]:
    """Validate a ``[calibration]`` table.

    Parameters
    ----------
    table : dict
        The table as read from TOML.
    where : str
        The file and table, for messages (``"/path/station.toml [calibration]"``).

    Returns
    -------
    (CalibrationPolicy, RadiometricSettings)

    Raises
    ------
    ConfigError
        Naming the file and the key.
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    unknown = sorted(set(table) - CALIBRATION_KEYS)
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(CALIBRATION_KEYS))}")
    stale = table.get("stale", "warn")
    if stale not in ("warn", "refuse"):
        raise ConfigError(f"{where} stale must be \"warn\" or \"refuse\", got {stale!r}")
    numbers = {}
    for key, default, low in (("max_age_h", 24.0, 0.0), ("max_dark_shift_dn", 4.0, 0.0), ("warmup_min", 30.0, 0.0)):
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < low:
            raise ConfigError(f"{where} {key} must be a number >= {low:g}, got {value!r}")
        numbers[key] = float(value)
    if numbers["max_age_h"] == 0:
        raise ConfigError(f"{where} max_age_h must be positive hours, got 0")
    warmup = table.get("warmup", False)
    if not isinstance(warmup, bool):
        raise ConfigError(f"{where} warmup must be true or false, got {warmup!r}")
    policy = CalibrationPolicy(stale=stale, warmup=warmup, **numbers)
    geometry = table.get("geometry", "records")
    if geometry not in ("records", "station.toml"):
        raise ConfigError(f"{where} geometry must be \"records\" (measure with the newest screen and pose records) "
                          f"or \"station.toml\" ([screen] and [layout] as entered), got {geometry!r}")
    base = where.rsplit(" ", 1)[0]
    ScreenSettings.from_table(table.get("screen", {}), f"{base} [calibration.screen]")
    PoseSettings.from_table(table.get("pose", {}), f"{base} [calibration.pose]")
    routine = table.get("routine", {})
    if not isinstance(routine, dict):
        raise ConfigError(f"{where} routine must be a table ([calibration.routine])")
    known = {f.name for f in dataclasses.fields(RadiometricSettings)}
    unknown = sorted(set(routine) - known)
    if unknown:
        raise ConfigError(f"{where[:-1]}.routine] has unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(known))}")
    try:
        settings = RadiometricSettings(**routine)
    except ConfigError as exc:
        raise ConfigError(f"{where.rsplit(' ', 1)[0]} {exc}") from None
    return policy, settings


def calibration_settings(config) -> tuple[CalibrationPolicy, RadiometricSettings]:
    """The validated ``[calibration]`` settings of a loaded :class:`~sofast_station.config.StationConfig`."""
    return parse_calibration_table(config.raw.get("calibration", {}), f"{config.path} [calibration]")
