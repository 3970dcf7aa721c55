"""ArUco markers whose corners have known 3-D positions: found in a photograph, and the camera's pose from them.

A marker table (:class:`MarkerTable`) lists each marker's four corners in a world frame (metres), in OpenCV's
corner order: the printed marker's top-left, top-right, bottom-right, bottom-left (OpenCSP's corner ids are
``4 * marker id + k`` in that order). :func:`detect_markers` finds the markers in a grey image (OpenCV's
``ArucoDetector``) with their corners refined to a fraction of a pixel; :func:`marker_correspondences`
pairs them with the table; :func:`solve_camera_pose` finds the world -> camera pose (OpenCV's ``solvePnP``,
then Gauss-Newton on the reprojection errors) with its covariance: the corners' noise is estimated from the
residuals themselves (so the survey errors of the table count as noise too), and the camera's intrinsics'
standard deviations, when known, are propagated through the same Jacobian.

Frames: ``world_to_camera`` maps world points into OpenCV's camera frame (``x_cam = R x_world + t``);
OpenCV's ``rvec`` is the rotation vector of R and ``tvec`` is t. OpenCSP's camera position calibration
reports the same ``rvec`` and, as its "tvec", ``R^T t`` (the vector from the camera to the world origin,
in world axes): :func:`opencsp_rvec_tvec`.

Pure functions of arrays (OpenCV, numpy); no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry import CameraIntrinsics, Pose
from .camera import pixel_rays

#: OpenCSP's dictionary for its calibration markers.
DEFAULT_DICTIONARY = "DICT_4X4_1000"
#: How detected corners are refined: OpenCV's contour-line fit ("contour"), cornerSubPix ("subpix"), the
#: AprilTag method ("apriltag"), none (the corners of the polygon OpenCV fits to the marker's outline, on
#: whole pixels: what OpenCSP's calibrations use), or ours ("edges", :func:`refine_corners`, after OpenCV's
#: cornerSubPix): the marker's four outer edges located to a fraction of a pixel and intersected.
REFINEMENTS = {"none": 0, "subpix": 1, "contour": 2, "apriltag": 3, "edges": 1}


@dataclass(frozen=True)
class MarkerTable:
    """Known 3-D corners of ArUco markers.

    Attributes
    ----------
    ids : (M,) int array
        Marker ids, each once.
    corners_m : (M, 4, 3) float array
        World positions of each marker's corners, metres, in OpenCV's corner order (top-left, top-right,
        bottom-right, bottom-left of the printed marker).
    """

    ids: np.ndarray
    corners_m: np.ndarray

    def __post_init__(self):
        ids = np.asarray(self.ids).astype(np.int64).ravel()
        corners = np.asarray(self.corners_m, dtype=np.float64)
        if corners.shape != (ids.size, 4, 3):
            raise ValueError(f"a marker table needs (M, 4, 3) corners for its M = {ids.size} ids, got {corners.shape}")
        if np.unique(ids).size != ids.size:
            raise ValueError("a marker table lists each marker id once")
        if not np.all(np.isfinite(corners)):
            raise ValueError("a marker table's corners must be finite numbers")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "corners_m", corners)

    def corners_of(self, marker_id: int) -> np.ndarray | None:
        """The (4, 3) corners of *marker_id*, or None when the table does not list it."""
        hit = np.flatnonzero(self.ids == int(marker_id))
        return self.corners_m[hit[0]] if hit.size else None

    def side_m(self) -> np.ndarray:
        """Each marker's mean side length, metres (a sanity check of a table: printed markers are squares)."""
        c = self.corners_m
        return np.linalg.norm(c - np.roll(c, -1, axis=1), axis=2).mean(axis=1)


def detect_markers(image: np.ndarray, dictionary: str = DEFAULT_DICTIONARY, refine: str = "edges",
                   adaptive_constant: float = 10.0, min_perimeter_rate: float = 0.01,
                   camera: CameraIntrinsics | None = None) -> dict[int, np.ndarray]:
    """ArUco markers in a grey image.

    Parameters
    ----------
    image : (H, W) uint8 array
    dictionary : str
        OpenCV's dictionary name (OpenCSP's markers: ``DICT_4X4_1000``).
    refine : str
        Corner refinement, one of :data:`REFINEMENTS`. ``edges`` (ours) is the most accurate on rendered
        photographs of known truth (docs/calibration.md); ``none`` reproduces OpenCSP's whole-pixel corners.
    adaptive_constant, min_perimeter_rate : float
        OpenCV's ``adaptiveThreshConstant`` and ``minMarkerPerimeterRate`` (OpenCSP's values by default:
        small markers in a large image are found).
    camera : CameraIntrinsics, optional
        With ``edges``: the edges are straight lines after the lens's distortion is taken out (a marker's
        side near the image's corner bends by a tenth of a pixel).

    Returns
    -------
    dict
        Marker id -> (4, 2) corner positions, pixels (OpenCV's image coordinates: pixel centres at integers).
        A marker id seen more than once is left out (it cannot be told which one the table means).
    """
    img = np.asarray(image)
    if img.ndim != 2 or img.dtype != np.uint8 or min(img.shape) < 8:
        raise ValueError(f"detect_markers needs a grey uint8 image, got {img.dtype} {img.shape}")
    if refine not in REFINEMENTS:
        raise ValueError(f"unknown corner refinement {refine!r}; use one of {sorted(REFINEMENTS)}")
    if not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"unknown ArUco dictionary {dictionary!r}; use an OpenCV name such as {DEFAULT_DICTIONARY}")
    params = cv2.aruco.DetectorParameters()
    params.adaptiveThreshConstant = float(adaptive_constant)
    params.minMarkerPerimeterRate = float(min_perimeter_rate)
    params.cornerRefinementMethod = REFINEMENTS[refine]
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)
    corners, ids, _ = detector.detectMarkers(img)
    if ids is None:
        return {}
    ids = ids.ravel().astype(int)
    seen, counts = np.unique(ids, return_counts=True)
    twice = set(seen[counts > 1].tolist())
    found = {int(i): np.asarray(c, np.float64).reshape(4, 2) for i, c in zip(ids, corners) if i not in twice}
    if refine == "edges":
        cells = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)).markerSize + 2
        found = {i: refine_corners(img, c, cells, camera) for i, c in found.items()}
    return found


def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Image values at fractional pixel positions (pixel centres at integers), NaN outside."""
    h, w = image.shape
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    out = np.full(u.shape, np.nan)
    uu, vv, fu, fv = u0[inside], v0[inside], u[inside] - u0[inside], v[inside] - v0[inside]
    at = lambda dv, du: image[vv + dv, uu + du].astype(np.float64)     # noqa: E731  (only the pixels needed)
    out[inside] = (1 - fv) * ((1 - fu) * at(0, 0) + fu * at(0, 1)) + fv * ((1 - fu) * at(1, 0) + fu * at(1, 1))
    return out


def _to_normalised(camera: CameraIntrinsics | None, px: np.ndarray) -> np.ndarray:
    if camera is None:
        return px
    rays = pixel_rays(camera, px[:, 0], px[:, 1])
    return (rays[:2] / rays[2]).T


def _to_pixels(camera: CameraIntrinsics | None, xy: np.ndarray) -> np.ndarray:
    if camera is None:
        return xy
    pts = np.column_stack([xy, np.ones(len(xy))])
    pix, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.matrix, camera.distortion)
    return pix.reshape(-1, 2)


def refine_corners(image: np.ndarray, corners_px: np.ndarray, cells: int = 6, camera: CameraIntrinsics | None = None,
                   max_shift_px: float = 2.0) -> np.ndarray:
    """A marker's corners from its four outer edges, each located to a fraction of a pixel.

    Along the middle 70 % of each side, about one profile per pixel is taken across the edge (bilinear
    samples every 0.1 px over +-0.6 of a bit cell, at most 3 px, so that it stays inside the marker's black
    border and on the white paper around it); where a profile crosses halfway between its dark and its
    light end is a point of the edge. A straight line is fitted through each side's points (in normalised
    camera coordinates when *camera* is given: straight after the lens's distortion is taken out), twice
    (the profiles re-centred on the first lines), and adjacent lines are intersected. A blurred straight
    edge crosses its half level at the edge itself, whatever the blur, so the corner is found without the
    bias of a corner detector's window.

    Parameters
    ----------
    image : (H, W) uint8 array
    corners_px : (4, 2) array
        The marker's corners in OpenCV's order (top-left, top-right, bottom-right, bottom-left), pixels.
    cells : int
        Bit cells across the marker, its black border included (6 for a 4 x 4 dictionary).
    camera : CameraIntrinsics, optional
    max_shift_px : float
        A corner that would move further than this keeps its starting position (a side hidden or
        cluttered).

    Returns
    -------
    (4, 2) array, pixels.
    """
    start = np.asarray(corners_px, np.float64).reshape(4, 2)
    centre = start.mean(axis=0)
    side_px = float(np.mean(np.linalg.norm(start - np.roll(start, -1, axis=0), axis=1)))
    half = min(3.0, 0.6 * side_px / cells)
    if half < 0.8:
        return start
    offsets = np.arange(-half, half + 1e-9, 0.1)
    lines = []                                # per side: a point and a unit direction, normalised coordinates
    current = start
    for _ in range(2):
        lines = []
        for k in range(4):
            a, b = current[k], current[(k + 1) % 4]
            length = float(np.linalg.norm(b - a))
            d = (b - a) / length
            n = np.array([-d[1], d[0]])
            if np.dot((a + b) / 2 - centre, n) < 0:
                n = -n                                                      # outward
            s = np.linspace(0.15, 0.85, max(5, int(0.7 * length)))
            base = a + s[:, None] * (b - a)
            u = base[:, 0, None] + offsets[None, :] * n[0]
            v = base[:, 1, None] + offsets[None, :] * n[1]
            prof = _bilinear(image, u, v)
            keep = np.all(np.isfinite(prof), axis=1)
            prof, base = prof[keep], base[keep]
            end = max(2, offsets.size // 6)
            dark, light = prof[:, :end].mean(axis=1), prof[:, -end:].mean(axis=1)
            good = light - dark > 20.0                       # a visible edge: a marker's is ~100 DN or more
            prof, base, dark, light = prof[good], base[good], dark[good], light[good]
            if prof.shape[0] < 3:
                return start
            level = (prof - ((dark + light) / 2)[:, None])
            points = []
            for row, p0 in zip(level, base):
                cross = np.flatnonzero((row[:-1] < 0) & (row[1:] >= 0))
                if cross.size != 1:
                    continue                                  # noise or clutter: no single crossing
                i = cross[0]
                o = offsets[i] + 0.1 * (-row[i]) / (row[i + 1] - row[i])
                points.append(p0 + o * n)
            if len(points) < 3:
                return start
            xy = _to_normalised(camera, np.asarray(points))
            mid = xy.mean(axis=0)
            _, _, vt = np.linalg.svd(xy - mid)
            lines.append((mid, vt[0]))
        out = []
        for k in range(4):
            (p, dp), (q, dq) = lines[k - 1], lines[k]
            m = np.column_stack([dp, -dq])
            if abs(np.linalg.det(m)) < 1e-9:
                return start
            s_, _ = np.linalg.solve(m, q - p)
            out.append(p + s_ * dp)
        current = _to_pixels(camera, np.asarray(out))
    if np.any(np.linalg.norm(current - start, axis=1) > max_shift_px):
        return start
    return current


def marker_correspondences(found: dict[int, np.ndarray],
                           table: MarkerTable) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """Pair detected markers with the table.

    Returns
    -------
    ids : (K,) int array
        The markers both found and listed, in increasing id.
    image_px : (4K, 2) array
        Their corners in the image, pixels, marker by marker in corner order.
    world_m : (4K, 3) array
        The same corners' world positions, metres.
    unlisted : list of int
        Markers found but not in the table (ignored).
    """
    ids = sorted(i for i in found if table.corners_of(i) is not None)
    unlisted = sorted(i for i in found if table.corners_of(i) is None)
    if not ids:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3)), unlisted
    image_px = np.concatenate([found[i] for i in ids])
    world_m = np.concatenate([table.corners_of(i) for i in ids])
    return np.asarray(ids, np.int64), image_px, world_m, unlisted


@dataclass(frozen=True)
class PoseFit:
    """The camera's pose from points of known world position.

    Attributes
    ----------
    world_to_camera : Pose
    rvec, tvec : (3,) arrays
        OpenCV's parameters of the pose (radians; metres).
    covariance : (6, 6) array
        Of (rvec, tvec): the corners' noise (estimated) and, when given, the intrinsics' standard deviations.
    covariance_noise : (6, 6) array
        The corners' noise alone.
    residuals_px : (N, 2) array
        Reprojection residuals (projected - measured), pixels.
    sigma_px : float
        The corners' noise estimated from the residuals (per coordinate, pixels).
    rms_px : float
        RMS of the residuals' lengths, pixels.
    """

    world_to_camera: Pose
    rvec: np.ndarray
    tvec: np.ndarray
    covariance: np.ndarray
    covariance_noise: np.ndarray
    residuals_px: np.ndarray
    sigma_px: float
    rms_px: float

    @property
    def camera_position_m(self) -> np.ndarray:
        """The camera's centre in the world frame, metres."""
        return self.world_to_camera.inverse().translation


def _project(camera: CameraIntrinsics, rvec: np.ndarray, tvec: np.ndarray, world_m: np.ndarray):
    pix, jac = cv2.projectPoints(world_m.reshape(-1, 1, 3), rvec.reshape(3, 1), tvec.reshape(3, 1), camera.matrix,
                                 camera.distortion)
    # OpenCV's Jacobian columns: rvec (3), tvec (3), fx fy (2), cx cy (2), distortion (5)
    return pix.reshape(-1, 2), jac


def solve_camera_pose(camera: CameraIntrinsics, world_m: np.ndarray, image_px: np.ndarray,
                      intrinsics_std: np.ndarray | None = None, iterations: int = 20) -> PoseFit:
    """The world -> camera pose from point correspondences, with its covariance.

    OpenCV's ``solvePnP`` (iterative: a homography start for coplanar points) gives the start; Gauss-Newton
    on the reprojection errors (in pixels, through the camera's distortion) refines it until the step is
    below 1e-12 rad and 1e-12 m, or *iterations* steps.

    Parameters
    ----------
    camera : CameraIntrinsics
    world_m : (N, 3) array
        Points, world frame, metres (N >= 4; at least 6 for an estimate of the noise).
    image_px : (N, 2) array
        Where they are seen, pixels.
    intrinsics_std : (9,) array, optional
        Standard deviations of (fx, fy, cx, cy, k1, k2, p1, p2, k3), pixels and unitless: propagated into the
        covariance (the intrinsics as independent inputs). None: the intrinsics are taken as exact.

    Returns
    -------
    PoseFit

    Raises
    ------
    ValueError
        Too few points, points behind the camera, or a pose the points do not determine.
    """
    world_m = np.asarray(world_m, np.float64).reshape(-1, 3)
    image_px = np.asarray(image_px, np.float64).reshape(-1, 2)
    n = world_m.shape[0]
    if image_px.shape[0] != n:
        raise ValueError(f"{n} world points but {image_px.shape[0]} image points")
    if n < 4:
        raise ValueError(f"a camera pose needs at least 4 points, got {n}")
    ok, rvec, tvec = cv2.solvePnP(world_m, image_px, camera.matrix, camera.distortion, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("OpenCV's solvePnP found no pose for these points")
    rvec, tvec = rvec.ravel().astype(np.float64), tvec.ravel().astype(np.float64)
    for _ in range(int(iterations)):
        pix, jac = _project(camera, rvec, tvec, world_m)
        j = jac[:, :6]
        r = (pix - image_px).ravel()
        step, *_ = np.linalg.lstsq(j, -r, rcond=None)
        rvec, tvec = rvec + step[:3], tvec + step[3:]
        if np.all(np.abs(step) < 1e-12):
            break
    pix, jac = _project(camera, rvec, tvec, world_m)
    residuals = pix - image_px
    rotation = cv2.Rodrigues(rvec.reshape(3, 1))[0]
    depth = world_m @ rotation[2] + tvec[2]
    if np.any(depth <= 0):
        raise ValueError(f"{int(np.sum(depth <= 0))} of the points lie behind the camera in the pose found: the "
                         "correspondences are wrong (a marker table of another frame or another corner order?)")
    j = jac[:, :6]
    normal = j.T @ j
    scaled = normal / np.sqrt(np.outer(np.diag(normal), np.diag(normal)))
    if np.linalg.cond(scaled) > 1e12:
        raise ValueError("the points do not determine the camera's pose (they lie on a line, or are too few)")
    dof = 2 * n - 6
    sigma = float(np.sqrt(np.sum(residuals ** 2) / dof)) if dof > 0 else float("nan")
    inv = np.linalg.inv(normal)
    cov_noise = sigma ** 2 * inv if dof > 0 else np.full((6, 6), np.nan)
    cov = cov_noise.copy()
    if intrinsics_std is not None:
        std = np.asarray(intrinsics_std, np.float64).ravel()
        if std.shape != (9,) or not np.all(np.isfinite(std)) or np.any(std < 0):
            raise ValueError("intrinsics_std must be 9 standard deviations >= 0 (fx fy cx cy k1 k2 p1 p2 k3)")
        # the pose moves with the intrinsics as the least-squares solution does: d pose = -(J^T J)^-1 J^T J_k d k
        sensitivity = -inv @ j.T @ jac[:, 6:15]
        cov = cov + sensitivity @ np.diag(std ** 2) @ sensitivity.T
    rms = float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1))))
    return PoseFit(Pose(rotation, tvec), rvec, tvec, cov, cov_noise, residuals, sigma, rms)


def propagate(function, x: np.ndarray, covariance: np.ndarray, step: float = 1e-7) -> tuple[np.ndarray, np.ndarray]:
    """``function(x)`` and its covariance, through the function's Jacobian (central differences, *step* in
    the units of x)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(function(x), np.float64)
    jac = np.empty((y.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = step
        jac[:, i] = (np.asarray(function(x + dx)) - np.asarray(function(x - dx))).ravel() / (2 * step)
    return y, jac @ covariance @ jac.T


def _opencsp_vector(params: np.ndarray) -> np.ndarray:
    rotation = cv2.Rodrigues(params[:3].reshape(3, 1))[0]
    return np.concatenate([params[:3], rotation.T @ params[3:6]])


def opencsp_rvec_tvec(fit: PoseFit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OpenCSP's camera position result: ``rvec`` (world -> camera rotation vector, radians), ``tvec`` =
    R^T t (camera to world origin, in world axes, metres), and the (6, 6) covariance of (rvec, tvec)."""
    y, cov = propagate(_opencsp_vector, np.concatenate([fit.rvec, fit.tvec]), fit.covariance)
    return y[:3], y[3:], cov


def camera_position(fit: PoseFit) -> tuple[np.ndarray, np.ndarray]:
    """The camera's centre in the world frame (metres) and its (3, 3) covariance."""
    y, cov = propagate(lambda p: -_opencsp_vector(p)[3:], np.concatenate([fit.rvec, fit.tvec]), fit.covariance)
    return y, cov


def drop_worst_marker(ids: np.ndarray, residuals_px: np.ndarray, limit_sigmas: float = 5.0,
                      floor_px: float = 2.0) -> int | None:
    """The marker whose corners fit worst, if its RMS residual exceeds both *limit_sigmas* times the corners'
    noise estimated from the other markers and *floor_px*; None when every marker fits.

    A marker moved since it was surveyed, or misread, bends the whole pose; taking it out (and saying so)
    is better than spreading its error over the others."""
    ids = np.asarray(ids)
    if ids.size < 3:
        return None
    per = np.sqrt(np.mean(np.sum(residuals_px.reshape(-1, 4, 2) ** 2, axis=2), axis=1))
    worst = int(np.argmax(per))
    others = np.delete(per, worst)
    noise = max(float(np.sqrt(np.mean(others ** 2))), 1e-9)   # the others' noise: the bad one would inflate it
    return int(ids[worst]) if per[worst] > max(limit_sigmas * noise, floor_px) else None
