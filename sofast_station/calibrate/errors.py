"""Errors of the calibration routines and of the calibration checks made when a station opens."""

from __future__ import annotations

from ..errors import StationError


class CalibrationError(StationError):
    """A calibration routine could not finish: the message says what it saw and what to change."""


class StaleCalibrationError(CalibrationError):
    """The calibration in force is too old, or the dark level has moved since it was made, and the station
    is configured to refuse (``[calibration] stale = "refuse"``)."""


class WarmupError(CalibrationError):
    """The camera has not warmed up for the configured time (``[calibration] warmup``); the message says
    how long to wait."""
