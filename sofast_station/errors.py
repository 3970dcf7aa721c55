"""The station's error hierarchy.

Every error a user can cause or meet derives from :class:`StationError` and says what was wrong and
what to do about it. Callers that must keep the line running catch ``StationError``; anything else is a
bug in this software.
"""

from __future__ import annotations


class StationError(Exception):
    """Base of every error the station reports to its users."""


class ConfigError(StationError):
    """The configuration (station.toml, a facet file, a calibration record) is missing or invalid."""


def check_table(table, allowed, where: str) -> dict:
    """*table* of a station or facet file, checked: a table (dict) holding only the *allowed* keys.

    Raises
    ------
    ConfigError
        ``"<where> must be a table"``, or naming the unknown keys and every allowed one.
    """
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return table


class UnknownRecipeError(ConfigError):
    """The PLC asked for a recipe that station.toml does not define (its own fault code, "recipe")."""


class CommandError(StationError):
    """An operator command that cannot be posted to the running station: unknown, or with a bad argument."""


class CaptureError(StationError):
    """The frames handed to the analysis are not a usable capture (wrong count, size, dark, saturated)."""


class FacetNotFoundError(CaptureError):
    """No facet, or not the whole facet, is visible in the capture."""


class DisplayNotShowingError(CaptureError):
    """The white and dark frames are the same: the display shows nothing the camera can see."""


class DotPatternError(CaptureError):
    """A fixed-pattern (dot grid) capture that cannot be measured (:mod:`sofast_station.measure.fixed`)."""


class DotsNotFoundError(DotPatternError):
    """No dot grid stands out in the frame."""


class OriginNotFoundError(DotPatternError):
    """The dot grid's origin (its mark, or the pixel the capture gives) has no dot beside it."""


class TooFewDotsError(DotPatternError):
    """Too few dots could be indexed and located on the facet."""


class DoubleLatticeError(DotPatternError):
    """The frame shows the dot grid twice (a second lattice beside the first: a second reflection)."""


class DisplayError(StationError):
    """The fringe display could not be created or did not show what was asked."""


class GeometryError(StationError):
    """The station geometry, the facet pose or the measured distance are inconsistent."""


class AnalysisError(StationError):
    """The analysis could not produce a trustworthy result from otherwise valid frames."""


class AnalysisTimeout(StationError):
    """The analysis did not finish before the cycle's deadline; the standby worker took over.

    Attributes
    ----------
    late : concurrent.futures.Future or None
        The abandoned analysis, still running in its retired worker for up to the late grace: resolves to
        the worker's result when it finishes in time, to None when it does not (the worker is then killed),
        or to the analysis's own error. None when there is nothing to wait for.
    """

    def __init__(self, message: str = "", late=None):
        super().__init__(message)
        self.late = late


class WorkerDied(StationError):
    """The analysis worker process died (killed, out of memory); the standby took over."""


class CameraError(StationError):
    """The camera failed: no frame in time, gone from the bus, or frames of the wrong size."""


class CameraTimeoutError(CameraError):
    """No frame arrived within the timeout."""


class CameraDisconnectedError(CameraError):
    """The camera went away (unplugged, power, network); it must be reopened."""


class TriggerError(StationError):
    """The robot/PLC handshake failed: disconnected, no acknowledgement, or a protocol violation."""


class ArchiveError(StationError):
    """A journal, workbook or dump could not be read or written."""


class ReportError(StationError):
    """A picture or report cannot be made: no analysis (the capture was refused), or no data in the period."""


class DumpError(ArchiveError):
    """A data dump is unreadable, truncated, foreign, or of an unknown schema."""
