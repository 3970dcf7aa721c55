"""Camera intrinsics and distortion from images of a chessboard or ChArUco board (OpenCV).

Every image is either used or rejected with a reason:

* the file cannot be read, or its size differs from the first image's;
* the board is not found (chessboard: ``cv2.findChessboardCornersSB``; ChArUco: no marker or corner);
* too few corners (ChArUco: fewer than ``min_corners``, or all on one line);
* blurred: the board's edges are wider than ``max_edge_width_px`` (contrast over the steepest gradients
  near the corners; a focused edge is about 2 px wide, a Gaussian blur of sigma adds about 2.5 sigma);
* after the first calibration, a reprojection RMS more than three times the median of the images (and
  above 0.5 px): the corners were misdetected; the rest is calibrated again.

The model is OpenCV's pinhole with distortion k1, k2, p1, p2, k3 (k3 held at 0 unless asked for: a
long-focus lens cannot tell it from k1 and k2; k2 too may be held at 0). The result is stored as a camera
record under ``data_dir/calibration/camera/`` with the reprojection RMS, the standard deviation of every
parameter and the verdict on every image.

The calibration judges itself (:func:`judge_calibration`, thresholds below, argued in
docs/calibration.md): ``pass``, ``warn`` (recorded, with the warnings) or ``refused`` (no record: the
parameters are not determined by the views) from the reprojection RMS, OpenCV's standard deviations of
the parameters (focal length relative, principal point against the image width, distortion as the
displacement it leaves uncertain at the image's corners) and how the views' points cover the image.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry import CameraIntrinsics
from .errors import CalibrationError
from .store import write_record

log = logging.getLogger(__name__)

SCHEMA = 1

#: Verdict thresholds (warn, refuse) of :func:`judge_calibration`; docs/calibration.md argues them.
#: Reprojection RMS over the used images, pixels (a sharp board on a good lens gives 0.05-0.2 px).
RMS_PX = (0.3, 1.0)
#: Standard deviation of each focal length over the focal length.
FOCAL_RELATIVE = (1e-3, 5e-3)
#: Standard deviation of each principal point coordinate over the image width.
PRINCIPAL_OF_WIDTH = (5e-3, 2e-2)
#: Displacement the distortion terms' standard deviations leave at the image's corners, pixels.
DISTORTION_CORNER_PX = (0.5, 2.0)
#: Coverage: the image is cut into COVERAGE_GRID cells (across, down); warn under this fraction holding
#: a point of some view, and when a corner zone (CORNER_ZONE of the width and height from a corner)
#: holds none.
COVERAGE_GRID = (8, 6)
MIN_COVERAGE = 0.6
CORNER_ZONE = 0.2


@dataclass(frozen=True)
class BoardSpec:
    """A calibration board.

    Attributes
    ----------
    kind : str
        ``"chessboard"`` or ``"charuco"``.
    squares_x, squares_y : int
        Squares along the board's width and height (a chessboard has (squares_x - 1) x (squares_y - 1)
        inner corners).
    square_m : float
        Side of a square, metres.
    marker_m : float
        Side of a ChArUco marker, metres.
    dictionary : str
        ChArUco marker dictionary (an OpenCV name, e.g. ``"DICT_5X5_100"``).
    legacy : bool
        ChArUco boards printed with OpenCV before 4.6 (even row counts differ).
    """

    kind: str
    squares_x: int
    squares_y: int
    square_m: float
    marker_m: float = 0.0
    dictionary: str = "DICT_5X5_100"
    legacy: bool = False

    def __post_init__(self):
        if self.kind not in ("chessboard", "charuco"):
            raise ConfigError(f"board kind must be 'chessboard' or 'charuco', got {self.kind!r}")
        if int(self.squares_x) < 3 or int(self.squares_y) < 3:
            raise ConfigError(f"a board needs at least 3 x 3 squares, got {self.squares_x} x {self.squares_y}")
        if not (np.isfinite(self.square_m) and 0 < self.square_m < 1):
            raise ConfigError(f"square size must be metres in (0, 1), got {self.square_m}")
        if self.kind == "charuco" and not (0 < self.marker_m < self.square_m):
            raise ConfigError(f"a ChArUco marker must be smaller than its square ({self.square_m} m), got "
                              f"{self.marker_m} m")
        object.__setattr__(self, "squares_x", int(self.squares_x))
        object.__setattr__(self, "squares_y", int(self.squares_y))

    @property
    def n_corners(self) -> int:
        """Inner corners of the board."""
        return (self.squares_x - 1) * (self.squares_y - 1)

    def chessboard_points(self) -> np.ndarray:
        """Board-frame points (n_corners, 3), metres, in OpenCV's chessboard corner order (rows of x)."""
        j, i = np.mgrid[1:self.squares_y, 1:self.squares_x]
        return np.column_stack([i.ravel() * self.square_m, j.ravel() * self.square_m,
                                np.zeros(i.size)]).astype(np.float32)

    def charuco(self):
        """The OpenCV CharucoBoard."""
        import cv2
        name = self.dictionary
        if not hasattr(cv2.aruco, name):
            raise ConfigError(f"unknown ArUco dictionary {name!r}; use an OpenCV name such as DICT_5X5_100")
        board = cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m, self.marker_m,
                                       cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)))
        board.setLegacyPattern(bool(self.legacy))
        return board

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class ImageResult:
    """What became of one image.

    Attributes
    ----------
    name : str
    accepted : bool
    reason : str
        Why it was rejected ("" when used).
    corners : int
        Corners found.
    edge_width_px : float or None
        Median edge width near the corners, pixels.
    rms_px : float or None
        Reprojection RMS of its corners after calibration, pixels.
    """

    name: str
    accepted: bool = False
    reason: str = ""
    corners: int = 0
    edge_width_px: float | None = None
    rms_px: float | None = None
    object_points: np.ndarray | None = field(default=None, repr=False)
    image_points: np.ndarray | None = field(default=None, repr=False)

    def to_dict(self) -> dict:
        return {"name": self.name, "accepted": self.accepted, "reason": self.reason, "corners": self.corners,
                "edge_width_px": self.edge_width_px, "rms_px": self.rms_px}


@dataclass
class CameraCalibration:
    """The calibrated camera and the verdict on every image.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
    rms_px : float
        Reprojection RMS over the used images, pixels.
    std_intrinsics : dict
        Standard deviations of fx, fy, cx, cy (pixels) and the distortion terms, from OpenCV.
    images : list of ImageResult
    board : BoardSpec
    fix_k3 : bool
    fix_k2 : bool
        k2 (and k3) held at 0.
    quality : dict
        :func:`judge_calibration`'s verdict, reasons, measures and advice.
    """

    intrinsics: CameraIntrinsics
    rms_px: float
    std_intrinsics: dict
    images: list
    board: BoardSpec
    fix_k3: bool
    fix_k2: bool = False
    quality: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return self.quality.get("verdict", "pass")

    @property
    def used(self) -> int:
        return sum(1 for r in self.images if r.accepted)


def edge_width_px(image: np.ndarray, points: np.ndarray, spacing_px: float, max_points: int = 40) -> float:
    """Median width of the board's edges near the given corners, pixels.

    For each corner (at most *max_points*, evenly picked), in a window of about a third of the corner
    spacing: the local contrast (95th - 5th percentile) over the mean of the steepest gradients (central
    differences). A sharp edge is about 2 px wide; a Gaussian blur of sigma px makes it about 2.5 sigma.
    """
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    half = int(max(3, min(40, round(0.35 * spacing_px))))
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pick = pts[np.linspace(0, len(pts) - 1, min(max_points, len(pts))).astype(int)] if len(pts) else pts
    widths = []
    for x, y in pick:
        c, r = int(round(x)), int(round(y))
        if r - half < 1 or c - half < 1 or r + half >= h - 1 or c + half >= w - 1:
            continue
        patch = img[r - half:r + half + 1, c - half:c + half + 1]
        gy, gx = np.gradient(patch)
        grad = np.hypot(gx, gy).ravel()
        lo, hi = np.percentile(patch, [5, 95])
        top = np.sort(grad)[-half:].mean()
        if top > 0 and hi - lo > 10:
            widths.append((hi - lo) / top)
    return float(np.median(widths)) if widths else float("nan")


def _spacing(points: np.ndarray) -> float:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return 20.0
    d = np.hypot(*(pts[:, None, :] - pts[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    return float(np.median(d.min(axis=1)))


def _refine(img: np.ndarray, corners: np.ndarray, clear_fraction: float = 0.5) -> np.ndarray:
    """Saddle-point refinement of chessboard corners.

    The sector-based chessboard detector places corners to about 0.15 px; the classic refinement, in a
    window reaching half of *clear_fraction* of the corner spacing (at most 11 px) from the corner, brings
    that to a few hundredths.
    """
    import cv2
    pts = np.asarray(corners, dtype=np.float32).reshape(-1, 1, 2)
    half = int(np.clip(round(0.5 * clear_fraction * _spacing(pts)), 2, 11))
    out = cv2.cornerSubPix(img, pts.copy(), (half, half), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3))
    return out.reshape(-1, 2).astype(np.float32)


def detect_board(image: np.ndarray, board: BoardSpec, name: str = "", min_corners: int = 12,
                 max_edge_width_px: float = 4.0) -> ImageResult:
    """Find the board's corners in a grey image and judge the image.

    Parameters
    ----------
    image : (H, W) uint8 array
    board : BoardSpec
    name : str
        For messages.
    min_corners : int
        ChArUco: fewest corners accepted (a chessboard is found whole or not at all).
    max_edge_width_px : float
        Images whose edges are wider are rejected as blurred, pixels.

    Returns
    -------
    ImageResult
        ``accepted`` with object and image points, or a reason.
    """
    import cv2

    out = ImageResult(name)
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        raise CalibrationError(f"{name}: board images must be 8-bit, got {img.dtype}")
    if board.kind == "chessboard":
        pattern = (board.squares_x - 1, board.squares_y - 1)
        found, corners = cv2.findChessboardCornersSB(img, pattern, flags=cv2.CALIB_CB_NORMALIZE_IMAGE
                                                     | cv2.CALIB_CB_EXHAUSTIVE)
        if not found or corners is None:
            out.reason = (f"board not found (a {pattern[0]} x {pattern[1]} inner-corner chessboard, whole and with "
                          "a white border, must be in view)")
            return out
        img_pts = _refine(img, corners)
        obj_pts = board.chessboard_points()
    else:
        cb = board.charuco()
        detector = cv2.aruco.CharucoDetector(cb)
        ch_corners, ch_ids, _, marker_ids = detector.detectBoard(img)
        n = 0 if ch_ids is None else len(ch_ids)
        if n == 0:
            out.reason = ("board not found (no ChArUco corner; markers seen: "
                          f"{0 if marker_ids is None else len(marker_ids)})")
            return out
        if n < min_corners:
            out.corners = n
            out.reason = f"too few corners: {n} of {board.n_corners} found, at least {min_corners} needed"
            return out
        if cb.checkCharucoCornersCollinear(ch_ids):
            out.corners = n
            out.reason = f"too few corners: the {n} corners found lie on one line"
            return out
        # (the detector refines its interpolated corners itself, in a window clear of the markers)
        obj_pts, img_pts = cb.matchImagePoints(ch_corners, ch_ids)
        obj_pts = obj_pts.reshape(-1, 3).astype(np.float32)
        img_pts = img_pts.reshape(-1, 2).astype(np.float32)
    out.corners = len(img_pts)
    out.edge_width_px = edge_width_px(img, img_pts, _spacing(img_pts))
    if not np.isfinite(out.edge_width_px):
        out.reason = "blurred: no edge near the corners has enough contrast"
        return out
    if out.edge_width_px > max_edge_width_px:
        out.reason = (f"blurred: edges {out.edge_width_px:.1f} px wide (at most {max_edge_width_px:g} px accepted); "
                      "focus the lens, or hold the board still")
        return out
    out.accepted = True
    out.object_points, out.image_points = obj_pts, img_pts
    return out


def coverage(points: list[np.ndarray], width_px: int, height_px: int, grid: tuple[int, int] = COVERAGE_GRID,
             corner_zone: float = CORNER_ZONE) -> dict:
    """How the detected points of all views cover the image.

    Returns
    -------
    dict
        ``cells``: fraction of the grid's cells holding a point; ``corners``: how many of the image's four
        corner zones (*corner_zone* of the width and height from each corner) hold one; ``border``:
        fraction of the grid's outer ring of cells holding one; ``grid``.
    """
    gx, gy = grid
    pts = np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points]) if points else np.empty((0, 2))
    hit = np.zeros((gy, gx), dtype=bool)
    if len(pts):
        cx = np.clip((pts[:, 0] / width_px * gx).astype(int), 0, gx - 1)
        cy = np.clip((pts[:, 1] / height_px * gy).astype(int), 0, gy - 1)
        hit[cy, cx] = True
    ring = np.ones_like(hit)
    ring[1:-1, 1:-1] = False
    zx, zy = corner_zone * width_px, corner_zone * height_px
    corners = 0
    for left in (True, False):
        for top in (True, False):
            inx = pts[:, 0] < zx if left else pts[:, 0] > width_px - zx
            iny = pts[:, 1] < zy if top else pts[:, 1] > height_px - zy
            corners += int(np.any(inx & iny))
    return {"cells": float(hit.mean()), "border": float(hit[ring].mean()), "corners": corners, "grid": [gx, gy]}


def distortion_corner_px(intrinsics: CameraIntrinsics, std_distortion) -> float:
    """Displacement (pixels) at the image's farthest corner that one standard deviation of each distortion
    term leaves, combined in quadrature (radial terms k r^2, k r^4, k r^6 of the normalised radius r,
    tangential p about 3 r^2)."""
    k = intrinsics.matrix
    f = 0.5 * (k[0, 0] + k[1, 1])
    w, h = intrinsics.width_px, intrinsics.height_px
    dx = max(k[0, 2], w - k[0, 2])
    dy = max(k[1, 2], h - k[1, 2])
    r = float(np.hypot(dx, dy) / f)
    s = np.zeros(5)
    sd = np.asarray(std_distortion, float).ravel()[:5]
    s[:sd.size] = np.nan_to_num(sd)
    k1, k2, p1, p2, k3 = s
    radial = np.hypot(np.hypot(k1 * r ** 2, k2 * r ** 4), k3 * r ** 6) * r
    tangential = np.hypot(p1, p2) * 3.0 * r ** 2
    return float(f * np.hypot(radial, tangential))


def judge_calibration(intrinsics: CameraIntrinsics, rms_px: float, std: dict, points: list[np.ndarray], *,
                      fix_k2: bool = False, fix_k3: bool = True) -> dict:
    """The calibration's verdict: ``pass``, ``warn`` or ``refused`` (parameters not determined).

    Each measure is compared with its (warn, refuse) thresholds (module constants); the coverage only
    warns (it explains a refusal, it does not make one).

    Returns
    -------
    dict
        ``verdict``, ``reasons`` (what is beyond a threshold), ``measures`` (rms_px, focal_relative,
        principal_of_width, distortion_corner_px, coverage), ``thresholds`` and ``advice`` (what to do).
    """
    k = intrinsics.matrix
    w = intrinsics.width_px
    focal_rel = max(std["fx"] / k[0, 0], std["fy"] / k[1, 1])
    principal = max(std["cx"], std["cy"]) / w
    dist_px = distortion_corner_px(intrinsics, std["distortion"])
    cov = coverage(points, intrinsics.width_px, intrinsics.height_px)
    measures = {"rms_px": float(rms_px), "focal_relative": float(focal_rel), "principal_of_width": float(principal),
                "distortion_corner_px": dist_px, "coverage": cov}
    thresholds = {"rms_px": RMS_PX, "focal_relative": FOCAL_RELATIVE, "principal_of_width": PRINCIPAL_OF_WIDTH,
                  "distortion_corner_px": DISTORTION_CORNER_PX, "min_coverage": MIN_COVERAGE,
                  "corner_zone": CORNER_ZONE}
    text = {
        "rms_px": lambda v, t: f"reprojection RMS {v:.3f} px (over {t:g} px)",
        "focal_relative": lambda v, t: (f"focal length +- {100 * v:.2f} % (fx +- {std['fx']:.2f}, fy +- "
                                        f"{std['fy']:.2f} px; over {100 * t:g} %)"),
        "principal_of_width": lambda v, t: (f"principal point +- ({std['cx']:.1f}, {std['cy']:.1f}) px, "
                                            f"{100 * v:.2f} % of the image width (over {100 * t:g} %)"),
        "distortion_corner_px": lambda v, t: (f"distortion uncertain by {v:.2f} px at the image corners "
                                              f"(k1 +- {std['distortion'][0]:.3g}, k2 +- {std['distortion'][1]:.3g}; "
                                              f"over {t:g} px)"),
    }
    refuse, warn = [], []
    for key, (t_warn, t_refuse) in (("rms_px", RMS_PX), ("focal_relative", FOCAL_RELATIVE),
                                    ("principal_of_width", PRINCIPAL_OF_WIDTH),
                                    ("distortion_corner_px", DISTORTION_CORNER_PX)):
        v = measures[key]
        if not np.isfinite(v) or v > t_refuse:
            refuse.append(text[key](v, t_refuse))
        elif v > t_warn:
            warn.append(text[key](v, t_warn))
    cover = (f"the views' points cover {100 * cov['cells']:.0f} % of the image ({cov['grid'][0]} x {cov['grid'][1]} "
             f"cells) and reach {cov['corners']} of its 4 corners")
    if cov["cells"] < MIN_COVERAGE or cov["corners"] < 4:
        warn.append(cover + f" (at least {100 * MIN_COVERAGE:g} % and all 4 wanted)")
    advice = []
    if cov["cells"] < MIN_COVERAGE or cov["corners"] < 4:
        advice.append("take views with the board reaching into the image's corners and along its edges")
    if refuse or warn:
        advice.append("take more views (15-25), the board tilted 20-40 degrees about both of its axes, "
                      "at several distances")
    if (measures["distortion_corner_px"] > DISTORTION_CORNER_PX[0] or principal > PRINCIPAL_OF_WIDTH[0]) \
            and not fix_k2:
        advice.append("for a long lens, whose small distortion the views cannot separate from the principal "
                      "point, hold k2 at 0 (--fix-k2)" + ("" if fix_k3 else " and k3 (leave out --k3)"))
    if principal > PRINCIPAL_OF_WIDTH[1]:
        fov = float(np.degrees(2 * np.arctan(0.5 * w / k[0, 0])))
        advice.append(f"a lens whose field of view is narrow ({fov:.1f} degrees across) locates its principal point "
                      "poorly whatever the views: if more views do not help, keep the [camera] table's values "
                      "and state their uncertainty in [uncertainty] camera_principal_px")
    if rms_px > RMS_PX[0]:
        advice.append("check --squares and --square-mm against the board, its flatness, and the focus")
    verdict = "refused" if refuse else ("warn" if warn else "pass")
    return {"verdict": verdict, "reasons": refuse + warn, "refuse_reasons": refuse, "warnings": warn,
            "measures": measures, "thresholds": thresholds, "advice": advice, "coverage_text": cover}


def calibrate_camera_images(images: list[tuple[str, np.ndarray | None]], board: BoardSpec, *, fix_k3: bool = True,
                            min_images: int = 5, min_corners: int = 12, max_edge_width_px: float = 4.0,
                            outlier_factor: float = 3.0, fix_k2: bool = False,
                            refuse: bool = True) -> CameraCalibration:
    """Intrinsics and distortion from board images.

    Parameters
    ----------
    images : list of (name, image)
        Grey uint8 images (None: the file could not be read).
    board : BoardSpec
    fix_k3 : bool
        Hold k3 at 0.
    min_images : int
        Fewest usable images.
    min_corners, max_edge_width_px : see :func:`detect_board`
    outlier_factor : float
        Images whose reprojection RMS exceeds this times the median (and 0.5 px) are dropped once.
    fix_k2 : bool
        Hold k2 (and k3) at 0.
    refuse : bool
        Raise when :func:`judge_calibration` refuses (else the refused calibration is returned, its
        ``quality`` saying so).

    Returns
    -------
    CameraCalibration
        With ``quality`` (:func:`judge_calibration`).

    Raises
    ------
    CalibrationError
        Fewer than *min_images* usable images (the message lists why each was rejected), or parameters not
        determined (the message says which and what to do).
    """
    import cv2

    results: list[ImageResult] = []
    size = None
    for name, img in images:
        if img is None:
            results.append(ImageResult(name, reason="cannot be read as an image"))
            continue
        shape = np.asarray(img).shape[:2]
        if size is None:
            size = shape
        if shape != size:
            results.append(ImageResult(name, reason=f"size {shape[1]} x {shape[0]} differs from the first image's "
                                                    f"{size[1]} x {size[0]}"))
            continue
        res = detect_board(img, board, name, min_corners, max_edge_width_px)
        log.info("%s: %s", name, f"{res.corners} corners, edges {res.edge_width_px:.1f} px" if res.accepted
                 else f"rejected: {res.reason}")
        results.append(res)

    def solve(used: list[ImageResult]):
        flags = cv2.CALIB_FIX_K3 if (fix_k3 or fix_k2) else 0
        flags |= cv2.CALIB_FIX_K2 if fix_k2 else 0
        return cv2.calibrateCameraExtended([r.object_points for r in used], [r.image_points for r in used],
                                           (size[1], size[0]), None, None, flags=flags)

    def need(used):
        if len(used) < min_images:
            lines = "\n".join(f"  {r.name}: {r.reason or 'used'}" for r in results)
            raise CalibrationError(f"only {len(used)} usable board image(s), at least {min_images} needed:\n{lines}")

    used = [r for r in results if r.accepted]
    need(used)
    rms, k, dist, _, _, std_int, _, per_view = solve(used)
    per_view = per_view.ravel()
    median = float(np.median(per_view))
    bad = [r for r, e in zip(used, per_view) if e > outlier_factor * median and e > 0.5]
    if bad:
        for r, e in zip(used, per_view):
            if r in bad:
                r.accepted = False
                r.reason = (f"reprojection RMS {e:.2f} px, more than {outlier_factor:g} x the median {median:.2f} px: "
                            "corners misdetected")
        used = [r for r in used if r.accepted]
        need(used)
        rms, k, dist, _, _, std_int, _, per_view = solve(used)
        per_view = per_view.ravel()
    for r, e in zip(used, per_view):
        r.rms_px = float(e)
    d = np.zeros(5)
    d[:min(5, dist.size)] = dist.ravel()[:5]
    intrinsics = CameraIntrinsics(size[1], size[0], k, d)
    s = std_int.ravel()
    std = {"fx": float(s[0]), "fy": float(s[1]), "cx": float(s[2]), "cy": float(s[3]),
           "distortion": [float(v) for v in s[4:9]]}
    quality = judge_calibration(intrinsics, float(rms), std, [r.image_points for r in used], fix_k2=fix_k2,
                                fix_k3=fix_k3)
    cal = CameraCalibration(intrinsics, float(rms), std, results, board, fix_k3 or fix_k2, fix_k2, quality)
    if quality["verdict"] == "refused":
        if refuse:
            raise CalibrationError(refusal_text(cal))
        log.warning("camera calibration refused: %s", "; ".join(quality["refuse_reasons"]))
    return cal


def refusal_text(cal: CameraCalibration) -> str:
    """Why a calibration was refused and what to do (no record is written)."""
    q = cal.quality
    k = cal.intrinsics.matrix
    d = cal.intrinsics.distortion
    lines = [f"camera calibration refused: the parameters are not determined by the {cal.used} view(s) used "
             f"(fx {k[0, 0]:.1f}, principal point ({k[0, 2]:.1f}, {k[1, 2]:.1f}) px, k1 {d[0]:+.4g}, k2 {d[1]:+.4g}); "
             "no record was written:"]
    lines += [f"  - {r}" for r in q["refuse_reasons"]]
    lines += [f"  - {r}" for r in q["warnings"]]
    if not any(r.startswith(q["coverage_text"]) for r in q["warnings"]):
        lines.append(f"  ({q['coverage_text']})")
    lines.append("What to do: " + "; ".join(q["advice"]) + ".")
    return "\n".join(lines)


def read_images(paths: list[str | Path]) -> list[tuple[str, np.ndarray | None]]:
    """Read image files as grey uint8 (None for a file OpenCV cannot read)."""
    import cv2
    return [(str(p), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in paths]


def save_camera(data_dir: str | Path, cal: CameraCalibration, source: str, folder: str = "camera",
                station: dict | None = None) -> Path:
    """Write a camera record under ``data_dir/calibration/<folder>/``; returns its path. *folder* is
    ``camera`` (the station camera's records) or ``handheld`` (the second camera of ``calibrate screen``,
    never taken for the station camera); *station*, the identity of the station it is made on
    (:func:`~sofast_station.calibrate.store.write_record`).

    A refused calibration (parameters not determined) is never written: CalibrationError saying why."""
    if cal.verdict == "refused":
        raise CalibrationError(refusal_text(cal))
    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": "camera", "record_id": record_id, "created": created, "source": source,
                "camera": cal.intrinsics.to_dict(), "rms_px": cal.rms_px, "std_intrinsics": cal.std_intrinsics,
                "fix_k3": cal.fix_k3, "fix_k2": cal.fix_k2, "quality": cal.quality, "board": cal.board.to_dict(),
                "images": [r.to_dict() for r in cal.images]}
    if folder not in ("camera", "handheld"):
        raise ValueError(f"camera records go to 'camera' or 'handheld', not {folder!r}")
    path, _ = write_record(data_dir, folder, build, station=station)
    return path


def load_camera_record(path: str | Path) -> tuple[CameraIntrinsics, dict]:
    """Read a camera record: the intrinsics and the whole record; ConfigError naming the file otherwise."""
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"camera calibration record {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"camera calibration record {path} is corrupt ({exc}); rerun the calibration") from None
    if not isinstance(d, dict) or d.get("kind") != "camera" or d.get("schema") != SCHEMA:
        raise ConfigError(f"{path} is not a camera calibration record of schema {SCHEMA}")
    try:
        return CameraIntrinsics.from_dict(d["camera"]), d
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"camera calibration record {path} is incomplete ({exc}); rerun the calibration") from None


def summary_text(cal: CameraCalibration, path: Path | None = None) -> str:
    """A readable summary of a camera calibration."""
    k = cal.intrinsics.matrix
    s = cal.std_intrinsics
    lines = [f"Camera calibration from {len(cal.images)} image(s) of a {cal.board.squares_x} x {cal.board.squares_y} "
             f"{cal.board.kind}: {cal.used} used" + (f"; record {path}" if path else ""),
             f"  reprojection RMS {cal.rms_px:.3f} px",
             f"  fx {k[0, 0]:.2f} +- {s['fx']:.2f} px, fy {k[1, 1]:.2f} +- {s['fy']:.2f} px, "
             f"principal point ({k[0, 2]:.2f}, {k[1, 2]:.2f}) +- ({s['cx']:.2f}, {s['cy']:.2f}) px",
             "  distortion k1 k2 p1 p2 k3: " + " ".join(f"{v:+.5f}" for v in cal.intrinsics.distortion)
             + "  +- " + " ".join(f"{v:.5f}" for v in s["distortion"])]
    q = cal.quality
    if q:
        m = q["measures"]
        lines.append(f"  verdict: {q['verdict'].upper()} (focal length +- {100 * m['focal_relative']:.3f} %, principal "
                     f"point +- {100 * m['principal_of_width']:.2f} % of the width, distortion +- "
                     f"{m['distortion_corner_px']:.2f} px at the corners; {q['coverage_text']})")
        lines += [f"    - {r}" for r in q["reasons"]]
        if q["verdict"] != "pass" and q["advice"]:
            lines.append("    what to do: " + "; ".join(q["advice"]))
    for r in cal.images:
        if r.accepted:
            lines.append(f"  {r.name}: used, {r.corners} corners, RMS {r.rms_px:.3f} px, edges "
                         f"{r.edge_width_px:.1f} px")
        else:
            lines.append(f"  {r.name}: rejected: {r.reason}")
    return "\n".join(lines)
