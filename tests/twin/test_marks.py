"""The twin's fixture marks (twin/marks.py): discs drawn with their exact area where the true poses put them, lit
by the hall in every frame alike."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sofast_station.geometry import CameraIntrinsics, FixtureMarks
from sofast_station.layout import layout_station
from sofast_station.facet import load_facet
from sofast_station.geometry import ScreenSpec
from sofast_station.twin.camera import TwinCamera
from sofast_station.twin.marks import mark_coverage, mark_image_centres_px
from sofast_station.twin.parameters import TwinOptics
from sofast_station.twin.station import TwinStation

MARKS = FixtureMarks(np.array([[-0.45, -0.38, 0.0], [0.45, -0.38, 0.0], [0.0, 0.38, 0.0], [-0.5, 0.0, 0.01]]), 0.02)


@pytest.fixture(scope="module")
def geometry(repo_root):
    design = load_facet(repo_root / "fixtures/facets/dish_5m33.toml")
    camera = CameraIntrinsics(400, 300, [[3409.0, 0, 199.5], [0, 3409.0, 149.5], [0, 0, 1]], [0.0] * 5)
    return design, layout_station(design, camera, ScreenSpec(1920, 1080, 0.000275), 0.34, "x", (0.0, 0.0))


def test_each_mark_covers_its_projected_disc(geometry):
    """Without lens distortion a small disc of area A at p (camera frame) with unit normal n images, on the plane
    z = 1, with area A |n . p| / Z^3 (its solid angle A |n . p| / |p|^3 times (|p| / Z)^3), f^2 times that in
    pixels, and its centroid at its centre's image, to second order in r / Z (1e-6 here). The polygon of chords
    under 0.15 px loses (2 pi / n)^2 / 6 of the area, 4e-4 for the 134 chords of a 3.2 px radius: the area is
    held to 1e-3. The centroid of the pixel centres weighted by their covered areas is not the covered area's
    own (an edge pixel's covered part is not centred on it): for a disc of 3.2 px radius a few thousandths of a
    pixel (what a camera's centroid of the same disc does too), so it is held to 0.01 px."""
    _, geo = geometry
    cam = TwinCamera(geo.camera)
    cov = mark_coverage(MARKS, geo.fixture_to_camera, cam, geo.camera.shape)
    centres = mark_image_centres_px(MARKS, geo.fixture_to_camera, cam)
    rows, cols = np.mgrid[0:300, 0:400]
    normal_cam = geo.fixture_to_camera.apply_vector(np.array([0.0, 0.0, 1.0]))
    for k, c in enumerate(centres):
        near = np.hypot(cols - c[0], rows - c[1]) < 10
        p = geo.fixture_to_camera.apply(MARKS.centres_m[k])
        want = 3409.0 ** 2 * math.pi * 0.01 ** 2 * abs(float(normal_cam @ p)) / p[2] ** 3
        area = cov[near].sum()
        assert area == pytest.approx(want, rel=1e-3)
        centroid = np.array([(cov * cols)[near].sum(), (cov * rows)[near].sum()]) / area
        assert np.hypot(*(centroid - c)) < 0.01


def test_marks_are_lit_by_the_hall_in_every_frame(geometry):
    """A wholly covered mark pixel reads the same in the dark and the white frame (the hall lights it, not the
    screen): mark_radiance of the white a pixel of the facet at the same vignetting would read, to the half count
    of rounding; and the facet's pixels are untouched by the marks."""
    design, geo = geometry
    optics = TwinOptics.noise_free()
    with_marks = TwinStation(geo, design, optics=optics, marks=MARKS)
    without = TwinStation(geo, design, optics=optics)
    scr = geo.screen
    dark = np.zeros((scr.height_px, scr.width_px), np.uint8)
    white = np.full_like(dark, 255)
    frames = {name: (twin.capture(dark), twin.capture(white)) for name, twin in (("with", with_marks),
                                                                                 ("without", without))}
    full = np.asarray(with_marks.mark_coverage) >= 1.0
    assert full.sum() > 4 * 20
    d, w = frames["with"]
    assert np.array_equal(d[full], w[full])
    vig = with_marks.vignetting_factor[full]
    want = optics.camera_offset_dn + with_marks.gain_dn * vig * optics.mark_radiance
    assert np.max(np.abs(w[full].astype(float) - want)) <= 0.5 + 1e-6
    facet = np.asarray(with_marks.coverage) > 0
    assert np.array_equal(frames["with"][1][facet], frames["without"][1][facet])
    assert not np.any(np.asarray(with_marks.mark_coverage)[facet])


def test_marks_follow_the_true_camera(geometry):
    """The twin's marks move with its true camera: a camera turned by 1 mrad about its y axis shifts every mark's
    image by f tan(1 mrad) = 3.409 px along the image's columns (and a hair along its rows)."""
    from sofast_station.twin.assembly import TrueAssembly, true_geometry

    _, geo = geometry
    cam = TwinCamera(geo.camera)
    turned = true_geometry(geo, TrueAssembly(camera_turn_mrad=(0.0, 1.0, 0.0)))
    a = mark_image_centres_px(MARKS, geo.fixture_to_camera, cam)
    b = mark_image_centres_px(MARKS, turned.fixture_to_camera, cam)
    assert np.allclose(np.abs(b[:, 0] - a[:, 0]), 3.409, atol=0.01)
    assert np.max(np.abs(b[:, 1] - a[:, 1])) < 0.01
