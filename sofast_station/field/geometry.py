"""The field's frames: where the heliostats stand, how one points, where the tower's camera looks.

Field frame
    Metres; origin at the tower's foot, +x east, +y north, +z up (a plant designer's layout frame).
Azimuth and elevation
    Of a direction: azimuth clockwise from north (east is +pi/2; pvlib's convention), elevation above the
    horizon, radians. A unit vector ``(sin az cos el, cos az cos el, sin el)``.
Heliostat frame in the field
    ``docs/conventions.md#heliostat-frame``: +z the heliostat's normal (its optical axis), +x to the right
    and +y up seen from the mirrors. An azimuth-elevation heliostat at (az, el) keeps its x axis level:
    ``x = (-cos az, sin az, 0)``, ``y = z x x``; its *spin* turns it about its normal from there
    (``R = R_kinematic(az, el) R_z(spin)``). Its frame's origin (the middle of the facets' layout) stands
    ``pivot_offset_m`` in front of its pivot (where the two axes cross) along the normal.
Camera frame
    OpenCV's (``sofast_station.geometry``): +z along the optical axis, +x along image columns, +y down the
    rows. A camera *looking at* a point with *roll* has its x axis level when roll is 0 and turned by roll
    about its optical axis (clockwise in the image for a positive roll).
Pointing errors
    Of a measured normal against a reference one: ``azimuth_mrad`` is the change of azimuth times the
    cosine of the elevation (the angle on the sky, east-going positive), ``elevation_mrad`` the change of
    elevation, ``angle_mrad`` the angle between the two.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import GeometryError


def direction(azimuth_rad: float, elevation_rad: float) -> np.ndarray:
    """The unit vector (field frame) of a direction's azimuth and elevation, radians."""
    ca, sa = math.cos(azimuth_rad), math.sin(azimuth_rad)
    ce, se = math.cos(elevation_rad), math.sin(elevation_rad)
    return np.array([sa * ce, ca * ce, se])


def azimuth_elevation(v) -> tuple[float, float]:
    """(azimuth, elevation) in radians of the direction *v* (field frame; need not be unit), azimuth in
    [0, 2 pi)."""
    v = np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(v))
    if not n > 0:
        raise GeometryError("a direction of zero length has no azimuth or elevation")
    az = math.atan2(v[0], v[1]) % (2.0 * math.pi)
    return az, math.asin(max(-1.0, min(1.0, v[2] / n)))


def heliostat_rotation(azimuth_rad: float, elevation_rad: float, spin_rad: float = 0.0) -> np.ndarray:
    """Heliostat frame -> field frame of a heliostat whose normal is at (azimuth, elevation), turned by
    *spin* about it (radians; see the module docstring)."""
    z = direction(azimuth_rad, elevation_rad)
    x = np.array([-math.cos(azimuth_rad), math.sin(azimuth_rad), 0.0])
    y = np.cross(z, x)
    kinematic = np.column_stack([x, y, z])
    c, s = math.cos(spin_rad), math.sin(spin_rad)
    return kinematic @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def heliostat_angles(rotation: np.ndarray) -> tuple[float, float, float]:
    """(azimuth, elevation, spin) in radians of a heliostat frame -> field frame rotation (the inverse of
    :func:`heliostat_rotation`)."""
    r = np.asarray(rotation, dtype=np.float64)
    az, el = azimuth_elevation(r[:, 2])
    kinematic = heliostat_rotation(az, el)
    x = kinematic.T @ r[:, 0]
    return az, el, math.atan2(x[1], x[0])


def look_at(camera_m, target_m, roll_rad: float = 0.0) -> np.ndarray:
    """Field frame -> camera frame rotation of a camera at *camera_m* whose optical axis goes through
    *target_m* (metres, field frame), turned by *roll_rad* about that axis from level."""
    z = np.asarray(target_m, dtype=np.float64) - np.asarray(camera_m, dtype=np.float64)
    n = float(np.linalg.norm(z))
    if not n > 0:
        raise GeometryError("the camera cannot look at its own position")
    z /= n
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:
        raise GeometryError("the camera looks straight up or down: its level x axis is undefined")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    return np.vstack([x, y, z])


def small_rotation(omega) -> np.ndarray:
    """The rotation by the rotation vector *omega* (radians; Rodrigues' formula)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(omega))
    k = np.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + k + 0.5 * k @ k
    return np.eye(3) + math.sin(theta) / theta * k + (1.0 - math.cos(theta)) / theta ** 2 * k @ k


def pointing_error_mrad(measured, reference) -> dict:
    """How far the direction *measured* lies from *reference* (field frame): ``azimuth_mrad`` (the change
    of azimuth times cos(elevation)), ``elevation_mrad`` and ``angle_mrad`` (module docstring)."""
    az_m, el_m = azimuth_elevation(measured)
    az_r, el_r = azimuth_elevation(reference)
    d_az = (az_m - az_r + math.pi) % (2.0 * math.pi) - math.pi
    m = np.asarray(measured, float) / np.linalg.norm(measured)
    r = np.asarray(reference, float) / np.linalg.norm(reference)
    angle = math.atan2(float(np.linalg.norm(np.cross(m, r))), float(m @ r))
    return {"azimuth_mrad": 1e3 * d_az * math.cos(el_r), "elevation_mrad": 1e3 * (el_m - el_r),
            "angle_mrad": 1e3 * angle}
