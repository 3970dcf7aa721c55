"""The display checks its own response on every facet (docs/reliability.md#the-screen-checks-itself).

Each cycle's frames (cropped about the facet) give the fringes' mean level against the dark and white frames
(:func:`~sofast_station.measure.display_response.fringe_mean_levels`); the radiometric record's lookup table
draws it at ``(floor_level + max_level) / 2``. Beyond ``[run] display_level_tolerance`` of that, the display's
response has moved since the record was made: the station's alarm ``line-display`` (page, OPC UA's
Alarms/Line, the PLC's line bit while it holds, console) asks for ``calibrate radiometric``. It does not hold
the line: the facets are still judged (on the noise-free 400 x 300 twin a display at gamma 2.4 behind a table
made at 2.2, its mean level 0.017 low, moved f_x by +0.004 % and the slope error's RMS by 0.0007 mrad: four-step
phase shifting is blind to the second harmonic a gamma error mostly makes); the reference every shift judges
whether the station still measures right. The alarm
clears after ``CLEAR_AFTER`` cycles in a row within the tolerance (one noisy cycle neither raises nor clears
it: :data:`RAISE_AFTER`).
"""

from __future__ import annotations

import logging

import numpy as np

from ..measure.display_response import expected_mean_level, fringe_mean_levels

log = logging.getLogger(__name__)

ALARM = "line-display"
#: Cycles in a row beyond the tolerance that raise the alarm, and within it that clear it.
RAISE_AFTER = 2
CLEAR_AFTER = 3


class DisplayCheck:
    """The display's response on every facet (module docstring).

    Parameters
    ----------
    radiometric : RadiometricRecord
        The record in force (its ``floor_level``, ``max_level``, ``record_id``).
    fringes : FringeSet
    tolerance : float
        Largest departure of the fringes' mean level from the table's before the alarm (0: no check).
    min_span_dn : float
        Pixels whose white exceeds their dark by less are left out, DN (the default recipe's mask threshold).
    """

    def __init__(self, radiometric, fringes, tolerance: float, min_span_dn: float):
        self.expected = expected_mean_level(radiometric.floor_level, radiometric.max_level)
        self.record_id = getattr(radiometric, "record_id", None)
        self.slices = fringes.slices()
        self.tolerance = float(tolerance)
        self.min_span_dn = float(min_span_dn)
        self.alarm: str | None = None
        self._beyond = self._within = 0

    def check(self, frames: np.ndarray) -> dict:
        """This cycle's entry (the record's ``station_checks.display``); updates :attr:`alarm`."""
        found = fringe_mean_levels(frames, self.slices, self.min_span_dn)
        entry = {"expected_level": round(self.expected, 5), "tolerance": self.tolerance,
                 "radiometric_record": self.record_id, "pixels": found["n_pixels"]}
        if found["level"] is None:
            entry["note"] = "no pixel of the facet between the dark and the white usable: not checked"
            return entry
        error = found["level"] - self.expected
        entry.update(level=round(found["level"], 5), error=round(error, 5), spread=round(found["spread"], 5),
                     levels={k: round(v, 5) for k, v in found["levels"].items()})
        beyond = abs(error) > self.tolerance
        self._beyond = self._beyond + 1 if beyond else 0
        self._within = 0 if beyond else self._within + 1
        entry["beyond"] = beyond
        if self._beyond >= RAISE_AFTER and self.alarm is None:        # said once, not reworded every facet
            self.alarm = (f"the display's response has moved since the radiometric record {self.record_id}: the "
                          f"fringes' mean level reads {found['level']:.4f} of the white where its lookup table draws "
                          f"{self.expected:.4f} ({error:+.4f}, tolerance {self.tolerance:g}) on "
                          f"{self._beyond} facets in a row: the fringes are no longer sinusoids; rerun "
                          "'sofast-station calibrate radiometric' (check the display's picture mode, gamma and "
                          "brightness settings)")
        elif self._within >= CLEAR_AFTER:
            self.alarm = None
        return entry
