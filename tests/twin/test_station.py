"""The traced station against hand computations: reflection, a flat mirror, edge coverage, corners."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from sofast_station.errors import GeometryError

from .helpers import facet_to_camera, facet_to_fixture, screen_points_camera


def _sample_pixels(station, n, seed=0, full=True):
    """Random (row, column) pixels that see the facet (wholly, if *full*)."""
    mask = station.coverage >= 1.0 if full else station.coverage > 0
    rows, cols = np.nonzero(mask)
    pick = np.random.default_rng(seed).choice(rows.size, size=min(n, rows.size), replace=False)
    return rows[pick], cols[pick]


def test_surface_points_lie_on_the_true_surface_and_project_to_their_pixel(rich_station):
    rows, cols = _sample_pixels(rich_station, 3000, full=False)
    x_facet = rich_station.surface_point_facet_m[rows, cols]
    assert np.max(np.abs(x_facet[:, 2] - rich_station.surface.height(x_facet[:, 0], x_facet[:, 1]))) < 1e-12
    r, t = facet_to_camera(rich_station)
    cam = rich_station.geometry.camera
    uv, _ = cv2.projectPoints(x_facet @ r.T + t, np.zeros(3), np.zeros(3), cam.matrix, cam.distortion)
    assert np.max(np.abs(uv.reshape(-1, 2) - np.column_stack([cols, rows]))) < 1e-6


def test_law_of_reflection(rich_station):
    rows, cols = _sample_pixels(rich_station, 5000)
    station = rich_station
    x_facet = station.surface_point_facet_m[rows, cols]
    slope = station.slope_true[rows, cols]
    # slope_true is the derivative of the true height
    h = 1e-6
    fd_x = (station.surface.height(x_facet[:, 0] + h, x_facet[:, 1])
            - station.surface.height(x_facet[:, 0] - h, x_facet[:, 1])) / (2 * h)
    assert np.max(np.abs(fd_x - slope[:, 0])) < 1e-8
    normal = np.column_stack([-slope[:, 0], -slope[:, 1], np.ones(len(rows))])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    # camera centre and screen points in the true facet frame, from the geometry and the placement
    r, t = facet_to_camera(station)
    c_facet = -r.T @ t
    t_facet = (screen_points_camera(station, station.screen_position_m[rows, cols]) - t) @ r
    incident = x_facet - c_facet
    incident /= np.linalg.norm(incident, axis=1, keepdims=True)
    reflected = t_facet - x_facet
    reflected /= np.linalg.norm(reflected, axis=1, keepdims=True)
    cos_in = -np.sum(incident * normal, axis=1)
    cos_out = np.sum(reflected * normal, axis=1)
    assert np.all(cos_in > 0.99)
    assert np.max(np.abs(cos_in - cos_out)) < 1e-11                       # equal angles
    coplanar = np.einsum("ij,ij->i", np.cross(incident, reflected), normal)
    assert np.max(np.abs(coplanar)) < 1e-11                               # one plane
    assert np.max(np.abs(reflected - incident)) > 1e-3                    # and not a pass-through


def test_flat_mirror_reflects_the_mirror_image_of_the_camera(flat_station):
    station = flat_station
    rows, cols = _sample_pixels(station, 5000, seed=1, full=False)
    r_ff, t_ff = facet_to_fixture(station.facet, station.design)
    x_fix = station.surface_point_facet_m[rows, cols] @ r_ff.T + t_ff
    # the mirror plane: through the image of the facet origin, normal R e_z
    p0, n = t_ff, r_ff[:, 2]
    assert np.max(np.abs((x_fix - p0) @ n)) < 1e-12
    # the hit is on the pixel's ray
    f2c = station.geometry.fixture_to_camera
    cam = station.geometry.camera
    uv, _ = cv2.projectPoints(f2c.apply(x_fix), np.zeros(3), np.zeros(3), cam.matrix, cam.distortion)
    assert np.max(np.abs(uv.reshape(-1, 2) - np.column_stack([cols, rows]))) < 1e-6
    # the reflected ray comes from the camera's mirror image: intersect C' -> X with the screen plane
    c_fix = f2c.inverse().translation
    c_mirror = c_fix - 2 * np.dot(c_fix - p0, n) * n
    screen_to_fix = f2c.inverse().compose(station.geometry.screen_to_camera)
    s0, s_n = screen_to_fix.translation, screen_to_fix.rotation[:, 2]
    direction = x_fix - c_mirror
    lam = ((s0 - c_mirror) @ s_n) / (direction @ s_n)
    on_plane = c_mirror + lam[:, None] * direction
    p_scr = (on_plane - s0) @ screen_to_fix.rotation        # screen frame
    assert np.max(np.abs(p_scr[:, 2])) < 1e-12
    screen = station.geometry.screen
    expected = np.column_stack([p_scr[:, 0] + screen.width_m / 2, p_scr[:, 1] + screen.height_m / 2])
    assert np.max(np.abs(station.screen_position_m[rows, cols] - expected)) < 1e-10
    inside = (expected[:, 0] >= 0) & (expected[:, 0] < screen.width_m) & (expected[:, 1] >= 0) \
        & (expected[:, 1] < screen.height_m)
    assert np.array_equal(station.on_screen[rows, cols], inside)
    assert inside.any() and not inside.all()     # a flat mirror at 10 m shows more than the screen


def _projected_edge(station, corner_a, corner_b, n=4001):
    """Image points (u, v) of the true outline edge from corner a to b, on the true surface, via cv2."""
    s = np.linspace(0.0, 1.0, n)[:, None]
    xy = corner_a + s * (corner_b - corner_a)
    x_facet = np.column_stack([xy, station.surface.height(xy[:, 0], xy[:, 1])])
    r, t = facet_to_camera(station)
    cam = station.geometry.camera
    uv, _ = cv2.projectPoints(x_facet @ r.T + t, np.zeros(3), np.zeros(3), cam.matrix, cam.distortion)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("edge", ["left", "right", "top", "bottom"])
def test_coverage_integrates_to_the_projected_edge(rich_station, edge):
    station = rich_station
    outline = station.design.outline_m                     # ccw: (+,-), (+,+), (-,+), (-,-)
    corners = {"right": (outline[0], outline[1]), "top": (outline[1], outline[2]),
               "left": (outline[2], outline[3]), "bottom": (outline[3], outline[0])}[edge]
    uv = _projected_edge(station, *corners)
    coverage = station.coverage
    along = 1 if edge in ("left", "right") else 0          # image axis the edge runs along (1 = rows)
    lines = np.linspace(uv[:, along].min() + 20, uv[:, along].max() - 20, 7).round().astype(int)
    errors = []
    for line in lines:
        profile = coverage[line, :] if along == 1 else coverage[:, line]
        order = np.argsort(uv[:, along])
        centre = int(round(float(np.interp(line, uv[order, along], uv[order, 1 - along]))))
        a, b = centre - 5, centre + 5                      # the window holds this edge's transition only
        total = profile[a:b + 1].sum()
        # the edge's mean position across this pixel line (the strip line - 1/2 .. line + 1/2)
        edge_pos = np.mean(np.interp(np.linspace(line - 0.5, line + 0.5, 101), uv[order, along], uv[order, 1 - along]))
        facet_after = profile[b] == 1.0
        assert {profile[a], profile[b]} == {0.0, 1.0}
        expected = (b + 0.5) - edge_pos if facet_after else edge_pos - (a - 0.5)
        errors.append(total - expected)
    assert np.max(np.abs(errors)) < 0.02, (edge, errors)


def test_corner_pixels_match_cv2(rich_station):
    station = rich_station
    xy = station.design.outline_m
    x_facet = np.column_stack([xy, station.surface.height(xy[:, 0], xy[:, 1])])
    r, t = facet_to_camera(station)
    cam = station.geometry.camera
    uv, _ = cv2.projectPoints(x_facet @ r.T + t, np.zeros(3), np.zeros(3), cam.matrix, cam.distortion)
    assert np.max(np.abs(station.corner_pixels() - uv.reshape(-1, 2))) < 1e-9


def test_measured_distance(rich_station):
    station = rich_station
    x, y = station.design.measure_point_m
    point = np.array([x, y, station.surface.height(x, y)])
    r, t = facet_to_camera(station)
    screen_centre_cam = station.geometry.screen_to_camera.translation
    assert station.measured_distance_m() == pytest.approx(np.linalg.norm(r @ point + t - screen_centre_cam), abs=1e-12)
    assert 10.5 < station.measured_distance_m() < 10.8


def test_footprint_check(rich_station):
    report = rich_station.footprint_check(1.0)
    assert report["min_margin_m"] > 0 and report["max_widening_m"] == pytest.approx(2e-3 * 10.66, rel=0.01)
    with pytest.raises(GeometryError, match="leaves the screen"):
        rich_station.footprint_check(30.0)


def test_accessors_are_consistent(rich_station):
    station = rich_station
    cam = station.geometry.camera
    seen = station.coverage > 0
    assert station.coverage.shape == cam.shape and station.screen_position_m.shape == cam.shape + (2,)
    assert station.surface_point_facet_m.shape == cam.shape + (3,) and station.slope_true.shape == cam.shape + (2,)
    assert np.array_equal(np.isfinite(station.surface_point_facet_m[..., 0]), seen)
    assert np.array_equal(np.isfinite(station.slope_true[..., 1]), seen)
    assert not station.on_screen[~seen].any() and station.on_screen[seen].all()
    assert 0.3 < seen.mean() < 0.32                       # the facet is about 768 px square
