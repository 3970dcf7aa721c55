"""Where the camera and screen go for a facet (docs/conventions.md#station-layout).

The centre of curvature of the facet's middle (off-axis: midway between its sagittal and meridional
centres) lies halfway between the camera and the screen centre; the camera sits beside the screen, never
in front of it. A nearly flat facet (heliostat) states its distance instead. The camera looks at the
facet's middle; the screen faces it.
"""

from __future__ import annotations

import numpy as np

from .errors import ConfigError
from .facet import FacetDesign
from .geometry import CameraIntrinsics, Pose, ScreenSpec, StationGeometry

_AXES = {"x": np.array([1.0, 0.0, 0.0]), "y": np.array([0.0, 1.0, 0.0])}


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _perpendicular_part(v: np.ndarray, n: np.ndarray) -> np.ndarray:
    return _unit(v - np.dot(v, n) * n)


def layout_distance_m(design: FacetDesign) -> float:
    """Distance (metres) from the facet's middle to the point halfway between camera and screen.

    The mean of the meridional and sagittal radii of curvature of the design paraboloid at the facet's
    middle (the centre of its outline's bounding box), unless the facet file sets ``layout.distance_m`` (nearly flat
    facets).
    """
    if "distance_m" in design.layout:
        d = float(design.layout["distance_m"])
        if not (np.isfinite(d) and d > 0):
            raise ConfigError(f"facet {design.name!r}: layout.distance_m must be positive, got {d}")
        return d
    f = design.focal_length_m
    rho2 = float(np.sum(design.middle_m ** 2))
    stretch = 1.0 + rho2 / (4.0 * f * f)
    r_meridional = 2.0 * f * stretch ** 1.5
    r_sagittal = 2.0 * f * stretch ** 0.5
    return 0.5 * (r_meridional + r_sagittal)


def layout_station(design: FacetDesign, camera: CameraIntrinsics, screen: ScreenSpec,
                   separation_m: float, separation_axis: str = "x",
                   screen_offset_m: tuple[float, float] = (0.0, 0.0)) -> StationGeometry:
    """Place camera and screen for *design* by the layout rule.

    Parameters
    ----------
    separation_m : float
        Camera-to-screen-centre distance, metres. Must keep the camera outside the screen.
    separation_axis : {"x", "y"}
        Facet axis along which camera and screen sit side by side.
    screen_offset_m : (float, float)
        Shift of the screen within its own plane (screen x, y), metres, after the rule has placed it.
        An off-axis facet's reflection is not centred on the point the rule aims at (a 3 m gore's
        footprint lies to one side of it); the shift centres it, which the twin's footprint check confirms.
    """
    if separation_axis not in _AXES:
        raise ConfigError(f"layout separation_axis must be 'x' or 'y', got {separation_axis!r}")
    half_extent = 0.5 * (screen.width_m if separation_axis == "x" else screen.height_m)
    if not separation_m > half_extent:
        raise ConfigError(f"layout separation_m = {separation_m} m puts the camera inside the screen: it must "
                          f"exceed half the screen's extent along {separation_axis} ({half_extent:.3f} m)")
    centre_xy = design.middle_m
    p_mid_fix = np.array([centre_xy[0], centre_xy[1], float(design.z(*centre_xy))])
    f = design.focal_length_m
    n_mid_fix = _unit(np.array([-centre_xy[0] / (2 * f), -centre_xy[1] / (2 * f), 1.0]))
    m_fix = p_mid_fix + layout_distance_m(design) * n_mid_fix
    e_sep = _perpendicular_part(_AXES[separation_axis], n_mid_fix)
    v_cam_fix = m_fix + 0.5 * separation_m * e_sep
    v_screen_fix = m_fix - 0.5 * separation_m * e_sep

    # Camera: optical axis toward the facet's middle, image "up" (-y_cam) toward facet +y.
    z_cam = _unit(p_mid_fix - v_cam_fix)
    y_cam = -_perpendicular_part(_AXES["y"], z_cam)
    x_cam = np.cross(y_cam, z_cam)
    r_fix_cam = np.vstack([x_cam, y_cam, z_cam])            # rows: camera axes in the fixture frame
    fixture_to_camera = Pose(r_fix_cam, -r_fix_cam @ v_cam_fix)

    # Screen: +z toward the facet's middle, +y (up) toward facet +y.
    z_scr = _unit(p_mid_fix - v_screen_fix)
    y_scr = _perpendicular_part(_AXES["y"], z_scr)
    x_scr = np.cross(y_scr, z_scr)
    r_scr_fix = np.column_stack([x_scr, y_scr, z_scr])      # columns: screen axes in the fixture frame
    v_screen_fix = v_screen_fix + screen_offset_m[0] * x_scr + screen_offset_m[1] * y_scr
    if np.linalg.norm(v_screen_fix - v_cam_fix) <= half_extent:
        raise ConfigError("layout screen_offset_m moves the screen in front of the camera; the camera must "
                          "stay beside the screen")
    screen_to_fixture = Pose(r_scr_fix, v_screen_fix)
    return StationGeometry(camera=camera, screen=screen,
                           screen_to_camera=fixture_to_camera.compose(screen_to_fixture),
                           fixture_to_camera=fixture_to_camera)


def mirror_seat(design: FacetDesign, window_centre_target_m) -> Pose:
    """Where a flat reference target seated in the fixture lies: ``target_to_fixture``.

    The fixture's locating pins hold it with its face in the design's tangent plane at the facet's middle
    and the centre of its window (*window_centre_target_m*, target frame) on the middle; its x axis along
    the fixture's x, its z axis (OpenCV's board frame: into the glass) away from the camera and screen.
    """
    centre_xy = design.middle_m
    p_mid_fix = np.array([centre_xy[0], centre_xy[1], float(design.z(*centre_xy))])
    f = design.focal_length_m
    n_mid_fix = _unit(np.array([-centre_xy[0] / (2 * f), -centre_xy[1] / (2 * f), 1.0]))
    z_t = -n_mid_fix
    x_t = _perpendicular_part(_AXES["x"], z_t)
    y_t = np.cross(z_t, x_t)
    r = np.column_stack([x_t, y_t, z_t])                    # columns: target axes in the fixture frame
    return Pose(r, p_mid_fix - r @ np.asarray(window_centre_target_m, dtype=np.float64))
