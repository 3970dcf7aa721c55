"""The twin's image-formation models of the facet edge (twin/edges.py), each against its own physics.

The checks are computed here independently of the twin's code under test: pixel rays by OpenCV
(``cv2.undistortPoints``), outlines by ``cv2.projectPoints``, point-in-polygon by matplotlib, polygon
areas by clipping in this file. Small cameras (400 x 300, as the population studies use) with the lens
distortion the studies draw up to (k1 = -0.3).
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest
from matplotlib.path import Path as PolygonPath

from sofast_station.errors import ConfigError
from sofast_station.facet import load_facet
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.twin import TrueFacet, TwinOptics, TwinStation
from sofast_station.twin.edges import disk_kernel, polygon_pixel_coverage

from .conftest import REPO
from .helpers import facet_to_camera, screen_points_camera

DARK = dict(ambient=0.0, background=0.0)        # only the display's light reaches the sensor


def _geometry(kind: str, k1: float):
    design = load_facet(REPO / "fixtures" / "facets" / f"{kind}_5m33.toml")
    camera = CameraIntrinsics(400, 300, [[3409, 0, 199.5], [0, 3409, 149.5], [0, 0, 1]], [k1, 0.0, 0.0, 0.0, 0.0])
    return layout_station(design, camera, ScreenSpec(1920, 1080, 0.000275), separation_m=0.34), design


def _flat_dish(k1: float, flat: bool = True, **optics) -> TwinStation:
    """A flat facet (z = 0 in its frame: the dish design touches it at its centre) turned 20 mrad about
    the normal and tilted a little, so its sides cross rows and columns. With *flat* False, the dish
    itself (f 5.33 m), placed the same way: it reflects the screen to every pixel (a flat mirror at 10 m
    shows the screen on only part of itself)."""
    geometry, design = _geometry("dish", k1)
    focal = dict(focal_length_x_m=math.inf, focal_length_y_m=math.inf) if flat else {}
    facet = TrueFacet(**focal, placement_mm=(1.0, -2.0, 0.5), placement_mrad=(1.5, -1.0, 20.0))
    return TwinStation(geometry, design, facet, TwinOptics(**optics).noise_free())


def _corners_px(station, outline_m) -> np.ndarray:
    """Image points (N, 2) of facet-frame (x, y) on the plane z = 0, by OpenCV."""
    r, t = facet_to_camera(station)
    points = np.column_stack([outline_m, np.zeros(len(outline_m))])
    cam = station.geometry.camera
    uv, _ = cv2.projectPoints(points @ r.T + t, np.zeros(3), np.zeros(3), cam.matrix, cam.distortion)
    return uv.reshape(-1, 2)


def _shoelace(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _clip_to_square(poly: np.ndarray, u: int, v: int) -> np.ndarray:
    """The convex polygon clipped to pixel (u, v)'s square, by the four half-planes in turn."""
    for axis, bound, sign in ((0, u - 0.5, 1), (0, u + 0.5, -1), (1, v - 0.5, 1), (1, v + 0.5, -1)):
        out = []
        for i in range(len(poly)):
            p, q = poly[i], poly[(i + 1) % len(poly)]
            p_in, q_in = sign * (p[axis] - bound) >= 0, sign * (q[axis] - bound) >= 0
            if p_in:
                out.append(p)
            if p_in != q_in:
                out.append(p + (bound - p[axis]) / (q[axis] - p[axis]) * (q - p))
        poly = np.array(out).reshape(-1, 2)
        if len(poly) == 0:
            break
    return poly


def _pixel_rays_facet(station, u: np.ndarray, v: np.ndarray):
    """Camera centre and unit ray directions (facet frame) through image points, by OpenCV's undistortion."""
    cam = station.geometry.camera
    pts = np.column_stack([u, v]).reshape(-1, 1, 2).astype(np.float64)
    xy = cv2.undistortPoints(pts, cam.matrix, cam.distortion,
                             criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    r, t = facet_to_camera(station)
    return -r.T @ t, rays @ r                                       # x_facet = R^T (x_cam - t)


def test_point_sampled_pixels_are_wholly_facet_or_background_by_their_centre_ray():
    station = _flat_dish(-0.3, edge_sampling="point")
    coverage = station.coverage
    assert set(np.unique(coverage)) == {0.0, 1.0}
    # every pixel near the outline: its centre ray meets the plane z = 0 inside or outside the outline
    area = _flat_dish(-0.3)                                           # the exact-area station marks the edge
    rows, cols = np.nonzero((area.coverage > 0) & (area.coverage < 1))
    rows = np.concatenate([rows, rows + 1, rows - 1])
    cols = np.concatenate([cols, cols - 1, cols + 1])
    c, d = _pixel_rays_facet(station, cols.astype(float), rows.astype(float))
    hit = c + (-c[2] / d[:, 2])[:, None] * d
    inside = PolygonPath(station.design.outline_m).contains_points(hit[:, :2])
    assert rows.size > 1000
    assert np.array_equal(coverage[rows, cols] == 1.0, inside)


def test_area_sampled_coverage_is_each_pixels_share_of_the_outline_polygon():
    """Flat facet, no distortion: the outline's image is a quadrilateral (OpenCV projects its corners);
    every pixel's coverage is the area of its square inside it, clipped here."""
    station = _flat_dish(0.0)
    poly = _corners_px(station, station.design.outline_m)
    u0, v0 = np.floor(poly.min(axis=0)).astype(int) - 1
    u1, v1 = np.ceil(poly.max(axis=0)).astype(int) + 1
    expected = np.zeros_like(station.coverage)
    for v in range(v0, v1 + 1):
        for u in range(u0, u1 + 1):
            clipped = _clip_to_square(poly, u, v)
            expected[v, u] = _shoelace(clipped) if len(clipped) >= 3 else 0.0
    assert np.max(np.abs(station.coverage - expected)) < 1e-6
    assert abs(station.coverage.sum() - _shoelace(poly)) < 1e-6
    assert np.count_nonzero((expected > 0) & (expected < 1)) > 600       # the edges were tried


def test_area_sampled_coverage_on_a_curved_distorted_edge_matches_fine_sub_rays():
    """Gore facet (slopes to 0.4, twisted, dented) through k1 = -0.3: the outline's image is curved. The
    exact coverage of 80 edge pixels against 128 x 128 sub-rays each (OpenCV's rays, the true surface):
    a fine grid's own error is a few 1e-4 of a pixel's area."""
    geometry, design = _geometry("gore", -0.3)
    facet = TrueFacet(focal_length_x_m=5.45, twist_mrad_per_m=0.4, placement_mrad=(2.0, -1.0, 8.0),
                      dents=({"x_m": 4.4, "y_m": 0.5, "depth_m": -5e-4, "radius_m": 0.05},))
    station = TwinStation(geometry, design, facet, TwinOptics.noise_free())
    rows, cols = np.nonzero((station.coverage > 0.02) & (station.coverage < 0.98))
    pick = np.random.default_rng(3).choice(rows.size, 80, replace=False)
    n = 128
    s = (np.arange(n) + 0.5) / n - 0.5
    du, dv = (a.ravel() for a in np.meshgrid(s, s))
    outline = PolygonPath(design.outline_m)
    errors = []
    for r, c in zip(rows[pick], cols[pick]):
        origin, rays = _pixel_rays_facet(station, c + du, r + dv)
        t = station.surface.intersect(origin, rays)
        hit = origin + t[:, None] * rays
        errors.append(outline.contains_points(hit[:, :2]).mean() - station.coverage[r, c])
    print(f"exact area vs 128^2 sub-rays: max {np.max(np.abs(errors)):.2e}, mean {np.mean(errors):+.1e}")
    assert np.max(np.abs(errors)) < 1e-3
    assert abs(np.mean(errors)) < 2e-4


def test_polygon_pixel_coverage_clips_to_the_image_and_keeps_orientation_free():
    square = np.array([[-3.2, -1.7], [5.3, -1.7], [5.3, 2.4], [-3.2, 2.4]])   # pixels -0.5 .. 3.5 hold part
    cov = polygon_pixel_coverage(square, (4, 4))
    inside = np.clip(np.minimum(5.3, np.arange(4) + 0.5) - np.maximum(-3.2, np.arange(4) - 0.5), 0, 1)
    rows = np.clip(np.minimum(2.4, np.arange(4) + 0.5) - np.maximum(-1.7, np.arange(4) - 0.5), 0, 1)
    assert np.allclose(cov, rows[:, None] * inside[None, :], atol=1e-12)
    assert np.array_equal(cov, polygon_pixel_coverage(square[::-1], (4, 4)))


def test_grid_sampling_averages_its_sub_rays():
    """edge_grid = 2: an edge pixel is 0, 1/4, 1/2, 3/4 or 1 facet (a half-pixel staircase); a fine grid
    (16 x 16) agrees with the exact area to its own resolution."""
    coarse = _flat_dish(-0.3, edge_sampling="grid", edge_grid=2)
    quarters = coarse.coverage * 4
    assert np.array_equal(quarters, np.round(quarters))
    assert np.count_nonzero((coarse.coverage > 0) & (coarse.coverage < 1)) > 300
    fine = _flat_dish(-0.3, edge_sampling="grid", edge_grid=16)
    area = _flat_dish(-0.3)
    edge = (area.coverage > 0) & (area.coverage < 1)
    diff = fine.coverage[edge] - area.coverage[edge]
    assert np.max(np.abs(diff)) < 1 / 16 and abs(diff.mean()) < 2e-3


def test_point_spread_functions_conserve_the_light_and_have_their_width():
    sharp = _flat_dish(-0.3, flat=False, **DARK)
    blurred = sharp.with_optics(dataclasses.replace(sharp.optics, blur_px=1.2, defocus_px=2.0))
    white = np.full((1080, 1920), 255, dtype=np.uint8)
    offset = sharp.optics.camera_offset_dn
    light = (sharp.linear_dn(white).astype(np.float64) - offset)
    spread = (blurred.linear_dn(white).astype(np.float64) - offset)
    assert light.sum() > 1e6
    assert spread.sum() == pytest.approx(light.sum(), rel=1e-5)
    assert np.abs(spread - light).max() > 50                          # the edge did spread
    for radius in (0.7, 1.5, 2.5, 4.0):
        k = disk_kernel(radius)
        assert k.sum() == pytest.approx(1.0) and np.allclose(k, k.T) and np.allclose(k, k[::-1, ::-1])
        # each kernel column holds the disk's share between the column's bounds (the disk's area left of
        # u, over pi R^2, is left_of(u))
        def left_of(u, r=radius):
            u = np.clip(u, -r, r)
            return (u * np.sqrt(r * r - u * u) + r * r * np.arcsin(u / r) + r * r * np.pi / 2) / (np.pi * r * r)
        c = np.arange(k.shape[1]) - k.shape[1] // 2
        assert np.allclose(k.sum(axis=0), left_of(c + 0.5) - left_of(c - 0.5), atol=2e-3)


def _rim_station(k1: float, flat: bool = False, **optics) -> TwinStation:
    """The dish with an 8 mm rim (2.6 px here, so some pixels lie wholly on it)."""
    return _flat_dish(k1, flat=flat, bevel_width_mm=8.0, **DARK, **optics)


def test_bevel_rim_covers_the_band_between_the_outline_and_its_inset():
    station = _rim_station(0.0, flat=True, bevel_tilt_mrad=300.0)
    outline = station.design.outline_m
    inner = np.sign(outline) * (np.abs(outline) - 0.008)              # the square dish, 8 mm in on each side
    band = _shoelace(_corners_px(station, outline)) - _shoelace(_corners_px(station, inner))
    assert station.rim_coverage.sum() == pytest.approx(band, rel=1e-6)
    assert np.all(station.rim_coverage <= station.coverage + 1e-12)


def test_steep_bevel_looks_past_the_screen_and_is_dark():
    station = _rim_station(-0.3, bevel_tilt_mrad=300.0)
    white = station.capture(np.full((1080, 1920), 255, dtype=np.uint8))
    on_rim = station.rim_coverage >= 1.0
    inner = (station.coverage >= 1.0) & (station.rim_coverage == 0)
    assert on_rim.sum() > 200
    assert np.all(np.isnan(station.rim_screen_position_m[on_rim]).any(axis=-1)
                  | ~_on_screen(station, station.rim_screen_position_m[on_rim]))
    assert np.all(white[on_rim] == round(station.optics.camera_offset_dn))     # no light: the black level
    assert np.median(white[inner]) > 200


def _on_screen(station, u_scr_m):
    screen = station.geometry.screen
    return (u_scr_m[:, 0] >= 0) & (u_scr_m[:, 0] < screen.width_m) & (u_scr_m[:, 1] >= 0) \
        & (u_scr_m[:, 1] < screen.height_m)


def test_shallow_bevel_reflects_the_screen_turned_by_twice_its_tilt():
    """A rim tilted by theta turns the reflected ray by 2 theta when it tilts in the plane of incidence,
    less (down to 2 theta cos i, i the incidence angle) across it: its pixels show other fringes."""
    tilt = 5e-3
    station = _rim_station(-0.3, bevel_tilt_mrad=1e3 * tilt)
    on_rim = station.rim_coverage >= 1.0
    rows, cols = np.nonzero(on_rim)
    x = station.surface_point_facet_m[rows, cols]
    r, t = facet_to_camera(station)
    to_facet = lambda p_cam: (p_cam - t) @ r                                        # noqa: E731
    direction = {}
    for name, u_scr in (("facet", station.screen_position_m[rows, cols]),
                        ("rim", station.rim_screen_position_m[rows, cols])):
        d = to_facet(screen_points_camera(station, u_scr)) - x
        direction[name] = d / np.linalg.norm(d, axis=1, keepdims=True)
    turn = np.arccos(np.clip(np.sum(direction["facet"] * direction["rim"], axis=1), -1, 1))
    slope = station.slope_true[rows, cols]
    normal = np.column_stack([-slope, np.ones(len(slope))])
    cos_i = np.sum(direction["facet"] * normal, axis=1) / np.linalg.norm(normal, axis=1)
    assert np.all(turn <= 2 * tilt * (1 + 1e-6))
    assert np.all(turn >= 2 * tilt * cos_i.min() * (1 - 1e-3) - 1e-9)
    white = station.capture(np.full((1080, 1920), 255, dtype=np.uint8))
    assert np.median(white[on_rim]) > 200                               # lit: the screen is there


def test_bevel_reflectance_dims_the_rim():
    full = _rim_station(-0.3, bevel_tilt_mrad=0.0)
    half = full.with_optics(dataclasses.replace(full.optics, bevel_reflectance=0.5))
    white = np.full((1080, 1920), 255, dtype=np.uint8)
    offset = full.optics.camera_offset_dn
    on_rim = full.rim_coverage >= 1.0
    inner = (full.coverage >= 1.0) & (full.rim_coverage == 0)
    a, b = full.linear_dn(white) - offset, half.linear_dn(white) - offset
    assert np.allclose(b[on_rim], 0.5 * a[on_rim], rtol=1e-5)
    assert np.array_equal(a[inner], b[inner])


def test_vignetting_falls_off_as_its_power_of_the_radius():
    geometry, design = _geometry("dish", 0.0)
    station = TwinStation(geometry, design, TrueFacet(), TwinOptics(vignetting=0.6, vignetting_exponent=4.0))
    factor = station.vignetting_factor
    assert factor[0, 0] == pytest.approx(0.4) and factor[150, 200] == pytest.approx(1.0, abs=1e-5)
    r_corner = math.hypot(199.5, 149.5)
    assert factor[150, 200 + 100] == pytest.approx(1 - 0.6 * (math.hypot(100.5, 0.5) / r_corner) ** 4, rel=1e-9)
    quadratic = station.with_optics(TwinOptics(vignetting=0.6)).vignetting_factor
    assert quadratic[150, 300] == pytest.approx(1 - 0.6 * (math.hypot(100.5, 0.5) / r_corner) ** 2, rel=1e-9)


def test_edge_models_are_chosen_by_name_and_checked():
    optics = TwinOptics.from_dict({"edge_sampling": "grid", "edge_grid": 3, "defocus_px": 1.0,
                                   "bevel_width_mm": 1.5, "bevel_tilt_mrad": 200, "bevel_reflectance": 0.3})
    assert optics.to_dict()["edge_sampling"] == "grid" and optics.edge_grid == 3
    with pytest.raises(ConfigError, match="edge_sampling"):
        TwinOptics(edge_sampling="supersampled")
    with pytest.raises(ConfigError, match="edge_grid"):
        TwinOptics(edge_grid=1)
    with pytest.raises(ConfigError, match="bevel_reflectance"):
        TwinOptics(bevel_reflectance=1.5)
    # a model that changes the trace gives a newly traced station
    area = _flat_dish(-0.3)
    point = area.with_optics(dataclasses.replace(area.optics, edge_sampling="point"))
    assert set(np.unique(point.coverage)) == {0.0, 1.0} and len(np.unique(area.coverage)) > 100
