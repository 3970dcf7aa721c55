"""Independent geometry helpers for the twin tests (they do not call the twin's own transforms)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def rotation_from_placement(placement_mrad) -> np.ndarray:
    """R = R_z(rz) R_y(ry) R_x(rx), built with scipy (independently of the twin's own helper)."""
    rx, ry, rz = (1e-3 * a for a in placement_mrad)
    return Rotation.from_euler("ZYX", [rz, ry, rx]).as_matrix()


def facet_to_fixture(facet, design) -> tuple[np.ndarray, np.ndarray]:
    """(R, t') with x_fixture = R x_facet + t', from the TrueFacet placement rule, computed in the test."""
    r = rotation_from_placement(facet.placement_mrad)
    cx, cy = design.centroid_m
    p_mid = np.array([cx, cy, (cx * cx + cy * cy) / (4 * design.focal_length_m)])
    return r, p_mid - r @ p_mid + 1e-3 * np.asarray(facet.placement_mm)


def facet_to_camera(station) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with x_camera = R x_facet + t, composed in the test from the geometry and the placement."""
    r_ff, t_ff = facet_to_fixture(station.facet, station.design)
    pose = station.geometry.fixture_to_camera
    return pose.rotation @ r_ff, pose.rotation @ t_ff + pose.translation


def screen_points_camera(station, u_scr_m: np.ndarray) -> np.ndarray:
    """3-D camera-frame points of screen coordinates (u_x, u_y) metres (docs/conventions.md#screen-positions)."""
    screen = station.geometry.screen
    p_scr = np.column_stack([u_scr_m[:, 0] - screen.width_m / 2, u_scr_m[:, 1] - screen.height_m / 2,
                             np.zeros(len(u_scr_m))])
    return station.geometry.screen_to_camera.apply(p_scr)
