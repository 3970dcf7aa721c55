"""Temperature as an input of the budget: what the screen's and the fixture's thermal expansion since
commissioning leave unknown (docs/reliability.md#temperature).

The geometry is commissioned at one temperature; a warmer hall expands what it measured:

* the screen's pixel pitch grows by ``alpha_s dT_screen`` (relative): the budget's ``screen pitch`` rows, whose
  sensitivities the analysis computed at the pitch's standard uncertainty u_p, reach the figures by their
  contribution c times ``u_thermal / u_p`` (both axes expand together, so up to sqrt(2) c per axis' worth:
  taken so, the larger); the expansion is not corrected (the panel's glass and its mount do not expand alike),
  it is an uncertainty;
* the structure from the camera to the fixture grows by ``alpha_f L dT_hall`` along the camera's line of sight
  (L the camera's distance to the fixture): the fixture's pose moves by that along the camera's z axis, which
  reaches the facet's placement 1:1 (the measured distance, which the range finder takes each facet, is not
  affected: the shape is measured in the boresight frame, docs/uncertainty.md).

Each is taken as a standard uncertainty, with the reading's own: ``u = alpha sqrt(dT^2 + u_T^2)``.

Pure functions; no I/O.
"""

from __future__ import annotations

import math

import numpy as np

from .budget_rows import add_budget_row, group_contributions


def thermal_u(delta_screen_k: float, delta_hall_k: float, u_reading_k: float, screen_per_k: float,
              fixture_per_k: float, distance_m: float, fixture_to_camera_rotation: np.ndarray) -> dict:
    """The standard uncertainties the expansion since commissioning leaves (module docstring).

    Returns
    -------
    dict
        ``screen_pitch_relative`` (dimensionless) and ``fixture_translation_mm`` ((3,) list along the fixture's
        x, y, z: the camera's line of sight, carried into the fixture's axes).
    """
    pitch = screen_per_k * math.hypot(delta_screen_k, u_reading_k)
    along = 1e3 * fixture_per_k * float(distance_m) * math.hypot(delta_hall_k, u_reading_k)
    r = np.asarray(fixture_to_camera_rotation, dtype=np.float64)
    translation = np.abs(r.T @ np.array([0.0, 0.0, along]))
    return {"screen_pitch_relative": float(pitch), "fixture_translation_mm": translation.tolist()}


def widen_for_temperature(figures: dict, u: dict, pitch_u_in_force: float, coverage_factor: float = 2.0) -> dict:
    """Add the thermal expansion (*u*, :func:`thermal_u`) to the figures' budget as the row ``thermal expansion``
    and grow the U's it reaches (:func:`~sofast_station.measure.budget_rows.add_budget_row`); *pitch_u_in_force*
    is the screen pitch's standard uncertainty the budget's ``screen pitch`` rows were computed at. Returns what
    was added to each U (k = 2)."""
    contributions: dict[str, float] = {}
    pitch = float(u.get("screen_pitch_relative", 0.0))
    if pitch > 0 and pitch_u_in_force > 0:
        ratio = math.sqrt(2.0) * pitch / pitch_u_in_force
        contributions = {path: c * ratio for path, c in group_contributions(figures, "screen pitch").items()}
    for i, t in enumerate(u.get("fixture_translation_mm", (0.0, 0.0, 0.0))):
        path = f"placement.mm.{i}"
        contributions[path] = math.hypot(contributions.get(path, 0.0), float(t))
    inputs = [f"screen pitch, relative ({pitch:.3g})",
              "fixture along the camera's line of sight (" + ", ".join(
                  f"{float(t):.3g}" for t in u.get("fixture_translation_mm", ())) + " mm)"]
    return add_budget_row(figures, "thermal expansion", inputs, contributions, coverage_factor)
