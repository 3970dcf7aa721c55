"""The fixture's marks as the camera sees them: white discs on the fixture's frame, lit by the hall's lights.

Each mark (:class:`~sofast_station.geometry.FixtureMarks`) is a disc in the plane through its centre normal to
the fixture frame's z axis. Its image is the disc's outline, densely sampled on that circle, carried into the
true camera frame (the true fixture-to-camera pose) and projected through the twin's own camera model, lens
distortion included; the area of every pixel inside that polygon is exact
(:func:`~sofast_station.twin.edges.polygon_pixel_coverage`, the same area sampling the facet's edge uses). A
chord of the polygon departs from the circle's image by under a thousandth of a pixel (:data:`CHORD_PX`).

What the marks send the camera (:class:`~sofast_station.twin.render.TwinRenderer`): ``mark_radiance`` of the
display's white (``TwinOptics``), the same in every frame, dark and white alike, since the hall's lights, not
the screen, light them (the screen's own light on a matt disc 10 m away is some 1e-4 of its luminance, left
out); vignetting and the sensor's noise as every other pixel.

Written from the definitions above; nothing is shared with :mod:`sofast_station.measure`.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import GeometryError
from ..geometry import FixtureMarks, Pose
from .camera import TwinCamera
from .edges import polygon_pixel_coverage

#: Longest chord of a mark's polygon, pixels: a chord of length c on a circle of image radius r departs from
#: it by c^2 / (8 r), under 0.001 px for a mark of 3 px radius or more.
CHORD_PX = 0.15


def mark_outline_px(marks: FixtureMarks, fixture_to_camera: Pose, camera: TwinCamera, index: int) -> np.ndarray:
    """The image (M, 2) = (u, v) pixels of mark *index*'s circle, a closed polygon of chords under
    :data:`CHORD_PX`.

    Raises
    ------
    GeometryError
        If the mark lies behind the camera.
    """
    centre = marks.centres_m[index]
    radius = 0.5 * marks.diameter_m
    z_cam = fixture_to_camera.apply(centre)[2]
    if not z_cam > 0:
        raise GeometryError(f"fixture mark {index} lies behind the camera: check [marks] and the layout")
    # the image radius, from the camera's focal length and the mark's depth, sets how many chords it needs
    r_px = radius * max(camera.fx, camera.fy) / z_cam
    n = max(64, int(math.ceil(2.0 * math.pi * r_px / CHORD_PX)))
    t = 2.0 * math.pi * np.arange(n) / n
    circle = centre + radius * np.column_stack([np.cos(t), np.sin(t), np.zeros(n)])
    uv = camera.project(fixture_to_camera.apply(circle))
    if not np.all(np.isfinite(uv)):
        raise GeometryError(f"fixture mark {index} does not project into the camera: check [marks] and the layout")
    return uv


def mark_image_centres_px(marks: FixtureMarks, fixture_to_camera: Pose, camera: TwinCamera) -> np.ndarray:
    """Where each mark's disc centre projects, (N, 2) pixels (the truth a located centroid is held to: a
    disc's image centroid departs from its centre's image by perspective and distortion terms of order
    r^2 / D^2 of its image radius, 1e-4 px here)."""
    return camera.project(fixture_to_camera.apply(marks.centres_m))


def mark_coverage(marks: FixtureMarks, fixture_to_camera: Pose, camera: TwinCamera,
                  shape: tuple[int, int]) -> np.ndarray:
    """Fraction (H, W) of every pixel's area covered by a mark (0 off the marks; a mark wholly or partly outside
    the image is clipped to it).

    Parameters
    ----------
    marks : FixtureMarks
    fixture_to_camera : Pose
        The true fixture frame in the true camera frame.
    camera : TwinCamera
    shape : (height, width)
    """
    coverage = np.zeros(shape, dtype=np.float64)
    for k in range(len(marks)):
        coverage += polygon_pixel_coverage(mark_outline_px(marks, fixture_to_camera, camera, k), shape)
    return np.minimum(coverage, 1.0)
