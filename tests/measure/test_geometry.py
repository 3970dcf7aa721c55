"""Screen points, ray/surface intersection and normals against hand computations (no twin involved)."""

import numpy as np
import pytest

from sofast_station.geometry import Pose
from sofast_station.measure.camera import to_frame
from sofast_station.measure.screen import FlatScreen
from sofast_station.measure.surface import intersect_quadratic, normal_slopes, surface_z


def rot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_flat_mirror_at_known_distance_and_tilt():
    """A flat mirror 3 m from the camera, tilted by (+4, -7) mrad: the screen points a camera pixel sees
    (hand-reflected here) map back through the screen model, and the pipeline's normals give the tilt."""
    # Facet (mirror) frame -> camera: mirror faces the camera, 3 m away, turned about y by pi.
    r_facet_cam = rot_y(np.pi) @ rot_x(0.01)
    facet_to_camera = Pose(r_facet_cam, np.array([0.02, -0.01, 3.0]))
    slope_x, slope_y = 0.004, -0.007                      # the mirror: z = slope_x x + slope_y y
    # Screen beside the camera, facing the mirror.
    w, h = 0.528, 0.297
    r_screen_cam = rot_y(np.pi + 0.03)
    screen_to_camera = Pose(r_screen_cam, np.array([-0.4, 0.0, 0.01]))
    screen = FlatScreen(w, h, screen_to_camera)

    # Hand computation in the camera frame: screen points, their mirror images in the plane, and the
    # camera rays toward those images (which meet the mirror where it reflects the screen point).
    u_x, u_y = np.meshgrid(np.linspace(0.01, w - 0.01, 7), np.linspace(0.01, h - 0.01, 5))
    u_x, u_y = u_x.ravel(), u_y.ravel()
    # screen frame: origin at the centre, so x = u_x - W/2, y = u_y - H/2
    t_cam = (u_x - w / 2)[:, None] * r_screen_cam[:, 0] + (u_y - h / 2)[:, None] * r_screen_cam[:, 1] \
        + screen_to_camera.translation
    n_cam = r_facet_cam @ unit(np.array([-slope_x, -slope_y, 1.0]))
    p0_cam = facet_to_camera.translation                 # a point on the mirror (the facet origin)
    image = t_cam - 2 * ((t_cam - p0_cam) @ n_cam)[:, None] * n_cam
    rays = unit(image)
    x_cam = rays * ((p0_cam @ n_cam) / (rays @ n_cam))[:, None]

    # Pipeline: screen model, then everything in the facet frame.
    assert np.abs(screen.points_camera(u_x, u_y).T - t_cam).max() < 1e-12
    cam_to_facet = facet_to_camera.inverse()
    cam_f = cam_to_facet.translation
    rays_f = to_frame(cam_to_facet, rays.T, translate=False)
    coeffs = np.array([0, 0, slope_x, slope_y, 0, 0.0])
    x_f = intersect_quadratic(coeffs, cam_f, rays_f)
    assert np.abs(x_f.T - cam_to_facet.apply(x_cam)).max() < 1e-12
    sx, sy = normal_slopes(x_f, cam_f, to_frame(cam_to_facet, screen.points_camera(u_x, u_y)))
    assert np.abs(sx - slope_x).max() < 1e-12 and np.abs(sy - slope_y).max() < 1e-12


def test_intersection_is_stable_for_a_nearly_flat_surface():
    """With A tiny the textbook root (-b - sqrt(b^2 - 4ac)) / 2a cancels; ours stays on the plane."""
    origin = np.array([0.1, -0.2, 10.0])
    dirs = unit(np.array([[0.01, 0.02, -1.0], [-0.03, 0.0, -1.0]]))
    for a in (1e-3, 1e-9, 1e-14, 0.0):
        coeffs = np.array([a, a, 0.0, 0.0, 0.0, 0.0])
        pts = intersect_quadratic(coeffs, origin, dirs.T)
        assert np.abs(pts[2] - surface_z(coeffs, pts[0], pts[1])).max() < 1e-12
    flat = intersect_quadratic(np.zeros(6), origin, dirs.T)
    tiny = intersect_quadratic(np.array([1e-14, 1e-14, 0, 0, 0, 0]), origin, dirs.T)
    assert np.abs(flat - tiny).max() < 1e-11


def test_intersection_takes_the_first_hit_and_reports_misses():
    coeffs = np.array([1 / (4 * 5.33), 1 / (4 * 5.33), 0, 0, 0, 0])
    origin = np.array([0.0, 0.0, 10.66])
    dirs = unit(np.array([[0.02, 0.0, -1.0], [0.0, 0.0, 1.0]]))   # second ray points away from it
    pts = intersect_quadratic(coeffs, origin, dirs.T).T
    assert pts[0, 2] == pytest.approx(surface_z(coeffs, pts[0, 0], pts[0, 1]), abs=1e-12)
    assert 0 < pts[0, 2] < 0.01
    assert np.all(np.isnan(pts[1]))
