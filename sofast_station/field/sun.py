"""Where the sun is (pvlib's solar position), and where a heliostat is commanded to point.

pvlib's ``get_solarposition`` (NREL's solar position algorithm) gives the sun's azimuth (clockwise from
north) and its apparent elevation (with the atmosphere's refraction, which is what a heliostat sees) to
well within a hundredth of a degree; nothing here computes an ephemeris of its own. pvlib (and pandas under
it) is imported when a position is asked for, not with this module.
"""

from __future__ import annotations

import datetime as dt
import math

import numpy as np

from ..errors import ConfigError, GeometryError
from .geometry import direction


def parse_time(text) -> dt.datetime:
    """A moment from ISO 8601 text (or a datetime) that names its time zone (``2027-03-21T10:30:00+01:00``,
    ``...Z``); a time without one is refused (a field spans no time zone, but a photo's clock may)."""
    if isinstance(text, dt.datetime):
        moment = text
    else:
        try:
            moment = dt.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))
        except ValueError:
            raise ConfigError(f"time {text!r} is not ISO 8601 (e.g. 2027-03-21T10:30:00+01:00)") from None
    if moment.tzinfo is None or moment.utcoffset() is None:
        raise ConfigError(f"time {text!r} has no time zone: give it as 2027-03-21T10:30:00+01:00 or ...Z (UTC)")
    return moment


def sun_position(times, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0) -> np.ndarray:
    """The sun's apparent azimuth and elevation (radians) at each of *times*, (N, 2), from pvlib.

    Parameters
    ----------
    times : sequence of datetime or ISO 8601 text (with time zone)
    latitude_deg, longitude_deg : float
        The site, degrees (north and east positive).
    altitude_m : float
        The site's height above sea level, metres (for the refraction's pressure).
    """
    # lazy: pandas and pvlib, ~770 ms CPU (+876 modules); spot.py and glare.py load this for commanded_normal
    import pandas as pd
    from pvlib.solarposition import get_solarposition

    if not (-90.0 <= float(latitude_deg) <= 90.0 and -180.0 <= float(longitude_deg) <= 360.0):
        raise ConfigError(f"site latitude {latitude_deg} / longitude {longitude_deg} degrees are not a place on Earth")
    moments = [parse_time(t) for t in (times if isinstance(times, (list, tuple)) else [times])]
    index = pd.DatetimeIndex([pd.Timestamp(m).tz_convert("UTC") for m in moments])
    pos = get_solarposition(index, float(latitude_deg), float(longitude_deg), altitude=float(altitude_m))
    return np.column_stack([np.radians(pos["azimuth"].to_numpy(dtype=float)),
                            np.radians(pos["apparent_elevation"].to_numpy(dtype=float))])


def sun_direction(time, latitude_deg: float, longitude_deg: float, altitude_m: float = 0.0) -> np.ndarray:
    """Unit vector towards the sun (field frame) at *time*; GeometryError when the sun is down."""
    az, el = sun_position([time], latitude_deg, longitude_deg, altitude_m)[0]
    if el <= 0.0:
        raise GeometryError(f"the sun is below the horizon at {time} (elevation {math.degrees(el):.1f} deg): "
                            "no heliostat tracks it")
    return direction(az, el)


def commanded_normal(sun_dir, heliostat_m, aim_m) -> np.ndarray:
    """The normal that reflects the sun's central ray from *heliostat_m* onto *aim_m* (metres, field frame):
    the bisector of the unit vectors towards the sun and towards the aim point."""
    s = np.asarray(sun_dir, dtype=np.float64)
    t = np.asarray(aim_m, dtype=np.float64) - np.asarray(heliostat_m, dtype=np.float64)
    n = s / np.linalg.norm(s) + t / np.linalg.norm(t)
    norm = float(np.linalg.norm(n))
    if norm < 1e-9:
        raise GeometryError("the sun stands exactly behind the aim point as seen from the heliostat: no normal "
                            "reflects it there")
    return n / norm
