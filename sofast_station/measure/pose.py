"""The facet's pose relative to the camera: corners by solvePnP, range by the measured distance."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import GeometryError
from ..geometry import CameraIntrinsics, Pose
from .camera import pixel_rays, project


@dataclass(frozen=True)
class CornerPose:
    """Facet pose from the corners.

    Attributes
    ----------
    facet_to_camera : Pose
    reprojection_rms_px : float
        RMS distance between found corners and the design corners projected with the pose.
    """

    facet_to_camera: Pose
    reprojection_rms_px: float


def solve_corner_pose(camera: CameraIntrinsics, corners_px: np.ndarray, corners_facet_m: np.ndarray,
                      initial: Pose) -> CornerPose:
    """Camera-from-facet pose that projects the design corners onto the found ones (OpenCV solvePnP).

    Parameters
    ----------
    corners_px : (N, 2) array
        Found corners (column, row), pixels, in the order of *corners_facet_m*.
    corners_facet_m : (N, 3) array
        Design corners on the design surface, facet frame, metres.
    initial : Pose
        Starting pose (the fixture's nominal one); Levenberg-Marquardt refines it, which keeps the
        near-planar corner set from flipping to its mirror solution.
    """
    rvec0, _ = cv2.Rodrigues(initial.rotation)
    ok, rvec, tvec = cv2.solvePnP(np.asarray(corners_facet_m, np.float64).reshape(-1, 1, 3),
                                  np.asarray(corners_px, np.float64).reshape(-1, 1, 2),
                                  camera.matrix, camera.distortion, rvec=rvec0.copy(),
                                  tvec=initial.translation.reshape(3, 1).copy(), useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        raise GeometryError("solvePnP found no camera pose for the facet corners; check the facet design's "
                            "outline and the camera calibration")
    pose = Pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
    rms = float(np.sqrt(np.mean(np.sum((project(camera, pose, corners_facet_m) - corners_px) ** 2, axis=1))))
    return CornerPose(pose, rms)


def refine_corner_pose(camera: CameraIntrinsics, corners_px: np.ndarray, corners_facet_m: np.ndarray,
                       initial: Pose, steps: int = 3) -> Pose:
    """:func:`solve_corner_pose`'s least squares for corners moved a little (micrometres) from those *initial*
    was solved with: Gauss-Newton steps from *initial* with the projection's Jacobian (OpenCV's
    ``projectPoints``), a smooth function of its inputs. A new ``solvePnP`` from *initial* would stop where its
    20 steps end along the long, flat valley of four nearly frontal corners, which moves with the last digits
    of its input (two analyses of equal inputs then differ by 1e-5 of their figures' U instead of 1e-11)."""
    pts = np.asarray(corners_facet_m, np.float64).reshape(-1, 1, 3)
    target = np.asarray(corners_px, np.float64).reshape(-1)
    rvec = cv2.Rodrigues(initial.rotation)[0].ravel()
    tvec = initial.translation.astype(np.float64).ravel()
    for _ in range(steps):
        proj, jac = cv2.projectPoints(pts, rvec, tvec, camera.matrix, camera.distortion)
        step = np.linalg.lstsq(jac[:, :6], target - proj.reshape(-1), rcond=None)[0]
        rvec, tvec = rvec + step[:3], tvec + step[3:]
    if not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        return initial
    return Pose(cv2.Rodrigues(rvec)[0], tvec)


def fix_range(facet_to_camera: Pose, measure_point_facet_m: np.ndarray, screen_centre_cam_m: np.ndarray,
              distance_m: float, max_shift_m: float) -> tuple[Pose, float]:
    """Slide the facet along the camera's line of sight to the measure point until the screen centre is
    *distance_m* from it.

    The corner pose fixes directions well but range poorly; the range finder's distance fixes range.
    Moving the facet along the ray through the measure point keeps that point's image where it is.

    Parameters
    ----------
    measure_point_facet_m : (3,) array
        The range finder's target on the design surface, facet frame, metres.
    screen_centre_cam_m : (3,) array
        Screen centre in the camera frame, metres.
    distance_m : float
        Measured distance from the screen centre to the measure point, metres.
    max_shift_m : float
        Largest plausible correction of the corner pose's range, metres.

    Returns
    -------
    (Pose, float)
        The corrected facet-to-camera pose and the shift applied along the line of sight, metres.
    """
    if not (np.isfinite(distance_m) and distance_m > 0):
        raise GeometryError(f"measured distance must be a positive number of metres, got {distance_m}; "
                            "re-enter or re-measure it")
    p_cam = facet_to_camera.apply(np.asarray(measure_point_facet_m, np.float64))
    u = p_cam / np.linalg.norm(p_cam)
    w = np.asarray(screen_centre_cam_m, np.float64) - p_cam
    uw = float(u @ w)
    disc = uw * uw - float(w @ w) + distance_m * distance_m
    corner_range = float(np.linalg.norm(w))
    if disc < 0:
        raise GeometryError(f"measured distance {distance_m:.4f} m cannot be met along the line of sight "
                            f"(the corner pose puts the measure point {corner_range:.4f} m from the screen "
                            "centre); re-measure the distance or check the facet recipe")
    roots = (uw - np.sqrt(disc), uw + np.sqrt(disc))
    mu = min(roots, key=abs)
    if abs(mu) > max_shift_m:
        raise GeometryError(f"measured distance {distance_m:.4f} m differs from the corner pose's "
                            f"{corner_range:.4f} m by more than {max_shift_m} m; re-measure the distance or "
                            "check the facet recipe")
    return Pose(facet_to_camera.rotation, facet_to_camera.translation + mu * u), float(mu)


def departure_from_design_m(design, height_m, slopes, xy_m: np.ndarray) -> np.ndarray:
    """The measured surface's height above the design surface at facet-frame points *xy_m* (n, 2), less that
    departure's tangent plane at the outline's centroid, metres.

    A facet whose focal lengths, twist or higher-order shape differ from the design's has its corners off
    the design surface: in the frame where its surface touches the design at its middle (height and
    normal, the twin's true facet frame, ``twin/surface.py``) they lie this far above it. For the quadratic
    part that is ``dA u^2 + dB v^2 + dE u v`` about the centroid (u, v): no tilt of the frame enters it,
    only the surface's second and higher derivatives, which the fringes measure to a fraction of a per
    cent. On the gore a twist of 0.12 mrad/m lifts its wide end's corners by -+0.08 mm, and four corners
    at design height then turned the corner pose by 0.40 mrad about x (docs/method.md, "The corner pose on
    the measured surface").

    Parameters
    ----------
    design : FacetDesign
    height_m : callable (x, y) -> z
        The measured surface's height, metres, up to a constant (it cancels).
    slopes : callable (x, y) -> (dz/dx, dz/dy)
        Its slopes.
    xy_m : (n, 2) array
        Facet-frame points, metres.
    """
    xy = np.asarray(xy_m, np.float64).reshape(-1, 2)
    cx, cy = (float(v) for v in design.centroid_m)
    x, y = xy[:, 0], xy[:, 1]
    sx, sy = (float(np.ravel(v)[0]) for v in slopes(np.array([cx]), np.array([cy])))
    k = 1.0 / (2.0 * design.focal_length_m)           # the design's slopes are k (x, y)
    offset = float(np.ravel(height_m(np.array([cx]), np.array([cy])))[0]) - float(design.z(cx, cy))
    return (height_m(x, y) - design.z(x, y) - offset - (sx - k * cx) * (x - cx) - (sy - k * cy) * (y - cy))


def placement(fixture_to_camera: Pose, facet_to_camera: Pose, design) -> dict:
    """The facet's placement in the fixture, as found by the corner pose.

    Expressed like the fixture's tolerance: a rotation R = R_z(rz) R_y(ry) R_x(rx) about the facet's
    middle P_mid = (cx, cy, z_design(cx, cy)) and a translation t, with
    ``x_fixture = R (x_facet - P_mid) + P_mid + t``. Returns ``{"mm": [tx, ty, tz], "mrad": [rx, ry, rz]}``.
    """
    facet_to_fixture = fixture_to_camera.inverse().compose(facet_to_camera)
    r = facet_to_fixture.rotation
    cx, cy = (float(v) for v in design.centroid_m)
    p_mid = np.array([cx, cy, float(design.z(cx, cy))])
    t = facet_to_fixture.apply(p_mid) - p_mid
    ry = -np.arcsin(np.clip(r[2, 0], -1.0, 1.0))
    rx = np.arctan2(r[2, 1], r[2, 2])
    rz = np.arctan2(r[1, 0], r[0, 0])
    return {"mm": (1000.0 * t).tolist(), "mrad": [1000.0 * float(rx), 1000.0 * float(ry), 1000.0 * float(rz)]}


def pose_facing(camera: CameraIntrinsics, point_px: np.ndarray, screen_centre_cam_m: np.ndarray,
                distance_m: float) -> Pose:
    """A mirror's frame placed by one image point and the measured distance, facing camera and screen.

    The frame's origin lies on the camera ray through *point_px* (column, row), *distance_m* from the screen
    centre (the far root: the mirror is beyond the screen's closest approach to the ray); its z axis bisects
    the directions from there to the camera and to the screen centre (a mirror that shows the screen's
    centre at that pixel); its x axis is the camera's x axis (image columns) laid into that plane, and y
    completes the right-handed frame (up the image). This is how a mirror of unknown outline is placed
    (OpenCSP places its "undefined" optic the same way, but turns its frame from the camera's by the
    smallest rotation instead of laying x in the plane: the two differ by a turn about z of the order of
    the square of the tilt, 0.1 mrad at OpenCSP's 0.18 rad).

    Raises
    ------
    GeometryError
        When the distance cannot be met along the ray (the screen centre is farther from the ray than
        *distance_m*).
    """
    if not (np.isfinite(distance_m) and distance_m > 0):
        raise GeometryError(f"measured distance must be a positive number of metres, got {distance_m}; "
                            "re-enter or re-measure it")
    point = np.asarray(point_px, np.float64).ravel()
    ray = pixel_rays(camera, np.array([point[0]]), np.array([point[1]]))[:, 0]
    centre = np.asarray(screen_centre_cam_m, np.float64)
    # |t ray - s| = d  ->  t^2 - 2 t (ray . s) + |s|^2 - d^2 = 0, the far root
    b = float(ray @ centre)
    disc = b * b - float(centre @ centre) + distance_m ** 2
    if disc < 0:
        raise GeometryError(f"the measured distance {distance_m:.4f} m cannot be met along the camera's line of "
                            "sight to the mirror's middle (the screen centre is farther from it); re-measure the "
                            "distance or check the camera/screen calibration")
    p = (b + np.sqrt(disc)) * ray
    to_cam = -p / np.linalg.norm(p)
    to_screen = (centre - p) / np.linalg.norm(centre - p)
    z = (to_cam + to_screen) / np.linalg.norm(to_cam + to_screen)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.column_stack([x, y, z]), p)


def mask_centroid_px(region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The centroid (column, row) of a boolean *region*, pixels, and its 2 x 2 covariance, pixels squared.

    The region's area is known to its boundary: each boundary pixel (one with a neighbour outside) may
    hold anything from none to all of the mirror's light, uniformly (variance 1/12 of a pixel's area), and
    moves the centroid by (r_j - c) / N per unit of area, so cov = sum_j (r_j - c)(r_j - c)^T / (12 N^2).
    Interior pixels are certain.
    """
    region = np.asarray(region, dtype=bool)
    rows, cols = np.nonzero(region)
    n = rows.size
    if n == 0:
        raise GeometryError("the lit region is empty: no mirror to place")
    c = np.array([cols.mean(), rows.mean()])
    padded = np.pad(region, 1)
    inner = (padded[:-2, 1:-1] & padded[2:, 1:-1] & padded[1:-1, :-2] & padded[1:-1, 2:])
    edge = region & ~inner
    er, ec = np.nonzero(edge)
    d = np.column_stack([ec - c[0], er - c[1]])
    cov = np.einsum("ij,ik->jk", d, d) / (12.0 * n * n)     # einsum's own loop: the same bits on any BLAS
    return c, cov
