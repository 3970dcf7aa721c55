"""A heliostat in one capture: its facets found and told apart, each analysed as a facet of its own, and
each facet's canting error against the design (docs/conventions.md#heliostats).

The steps (:func:`analyse_heliostat`):

1. **Facets found** (:func:`find_facets`): the pixels that respond to the screen, in connected regions;
   each region belongs to the facet whose nominal image (its design outline where the fixture's nominal
   heliostat pose puts it) holds most of it. A facet with no region is *missing*, one whose region is much
   smaller than its nominal image *hidden* (partly covered), one whose region leaves its window or touches
   the image border *cut off*; two facets in one region (no gap between them in the image) are refused.
2. **Each facet's window** (:func:`facet_windows`): its nominal image's bounding box, widened; fixed by the
   station's geometry, so each facet's analysis sees the same camera (the principal point moved by the
   window's corner) capture after capture, and its uncertainty's sensitivities are computed once. In its
   window a facet's neighbours are blanked (their pixels set to the dark frame's).
3. **The heliostat's corner pose** (:func:`heliostat_pose`): every found facet's corners
   (:func:`~sofast_station.measure.corners.fit_outline`) against the design's corners in the heliostat frame,
   one solvePnP; its range fixed by the measured distance to the measure facet's measure point. It gives each
   facet's distance (screen centre to its measure point).
4. **Each facet's analysis**: :func:`~sofast_station.measure.pipeline.analyse` on its window, with its
   nominal frame (the nominal heliostat pose composed with its design pose) as the fixture and its distance:
   every single-facet figure with its U. A facet the analysis refuses gets that reason as its status; the
   others go on.
5. **Canting** (:func:`canting_errors`): each facet's optical (boresight) frame in the heliostat's optical
   frame, against its design canting; the optical frame is the corner pose turned until the canting errors
   have zero mean.
6. **Uncertainty** (:func:`combined_u`): a canting error is a difference of facets' tilts, so the station
   inputs that move every facet alike (camera, screen, fixture, distance) mostly cancel in it: each facet's
   own sensitivities (the single-facet analysis's, by finite differences of its whole reduction) are
   combined with the weights of that difference; the random parts (noise, corners) are independent between
   facets.

Pure functions: arrays and records in, a :class:`HeliostatAnalysis` out; no file, no hardware, no state.
"""

from __future__ import annotations

import dataclasses
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..ensemble import EnsembleDesign
from ..errors import AnalysisError, CaptureError, FacetNotFoundError, GeometryError, StationError
from ..facet import FacetDesign
from ..fringes import FringeSet
from ..geometry import CameraIntrinsics, Pose, StationGeometry
from . import corners as corners_mod
from .analysis import finish_analysis
from .camera import project
from .pipeline import (
    Analysis,
    AnalysisSettings,
    default_screen,
    outline_image_points,
    pose_from_corners,
    reduce_stages,
    rerun,
    sharpened_fit,
    thread_pool,
)
from .pose import fix_range, solve_corner_pose
from .screen import ScreenModel
from .sensitivity_record import from_record

#: Facet statuses: analysed, or why not.
STATUSES = ("measured", "missing", "hidden", "cut off", "invalid")

#: The canting reference's tilt iteration stops when both updates are below this, radians.
TILT_TOLERANCE_RAD = 1e-12


@dataclass(frozen=True)
class HeliostatSettings:
    """How facets are told apart (``[heliostat]`` analysis keys).

    Attributes
    ----------
    window_margin : float
        Each facet's window is its nominal image's bounding box widened by this fraction of its size ...
    window_margin_px : int
        ... plus this many pixels (room for the heliostat's misplacement in the fixture).
    min_area_fraction : float
        A facet whose region covers less than this fraction of its nominal image is *hidden*.
    blank_dilation_px : int
        Neighbours are blanked this many pixels beyond their regions (their blurred or partly covered edge).
    min_region_px : int
        Responsive regions smaller than this are specks (dust, a reflection), not facets.
    facet_height_mm : float
        Standard uncertainty of a facet's height on the frame, along its normal, mm. A facet's distance comes
        from the heliostat's pose and the facet's design position, so its own height error is not measured:
        it enters its canting's U as an input of its own (independent between facets).
    split_joined : bool
        Facets whose regions touch in the image (gaps finer than the camera resolves, as in OpenCSP's
        8x-downsampled captures, or one mirror analysed as several) are told apart by the heliostat's outer
        outline and the design's layout (:func:`joined_pose`): the heliostat's pose from the outline's
        corners, each facet's corners and pixels from its design outline there, its pointing from its own
        slopes. False (the station's default): such a capture is refused, since on the line touching facets
        mean a facet misplaced onto its neighbour.
    joined_inset_px : float
        A joined facet's pixels stop this far inside its design outline's image (beyond the edge's blur):
        room for the unresolved gap and the outline's placement, pixels.
    """

    window_margin: float = 0.08
    window_margin_px: int = 12
    min_area_fraction: float = 0.6
    blank_dilation_px: int = 2
    min_region_px: int = 50
    facet_height_mm: float = 0.5
    split_joined: bool = False
    joined_inset_px: float = 1.0

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if not self.split_joined:       # (absent when off: settings and hashes from before it)
            del d["split_joined"], d["joined_inset_px"]
        return d


@dataclass(frozen=True)
class FacetRegion:
    """Where one facet is in the capture.

    Attributes
    ----------
    index : int
    label : str
    status : str
        ``"measured"`` (found; its analysis may still refuse it), ``"missing"``, ``"hidden"``, ``"cut off"``.
    window : (row0, col0, row1, col1)
        Its window, end-exclusive, in the image.
    components : tuple of int
        Labels (in the capture's labelling) of the regions that are its.
    area_px : int
    expected_area_px : float
        Its nominal image's area.
    reason : str
        Why it is not measured (empty when it is).
    joined : bool
        Its region touches its neighbours' (``HeliostatSettings.split_joined``): its corners and pixels come
        from the heliostat's outline and its design (:func:`joined_pose`), not from its own edges.
    """

    index: int
    label: str
    status: str
    window: tuple
    components: tuple
    area_px: int
    expected_area_px: float
    reason: str = ""
    joined: bool = False


def facet_frame_nominal(geometry: StationGeometry, ensemble: EnsembleDesign, i: int) -> Pose:
    """Facet *i*'s nominal frame in the camera: the fixture's nominal heliostat pose composed with its design
    pose."""
    return geometry.fixture_to_camera.compose(ensemble.facets[i].to_heliostat)


def nominal_outlines(geometry: StationGeometry, ensemble: EnsembleDesign) -> list[np.ndarray]:
    """Each facet's design outline where the fixture's nominal heliostat pose puts it, (M, 2) image points."""
    return [outline_image_points(f.design, geometry.camera, facet_frame_nominal(geometry, ensemble, i))
            for i, f in enumerate(ensemble.facets)]


def facet_windows(geometry: StationGeometry, ensemble: EnsembleDesign,
                  settings: HeliostatSettings = HeliostatSettings()) -> list[tuple]:
    """Each facet's window (row0, col0, row1, col1), end-exclusive: its nominal image's bounding box widened by
    ``window_margin`` of its size plus ``window_margin_px``, clipped to the image."""
    h, w = geometry.camera.shape
    out = []
    for pts in nominal_outlines(geometry, ensemble):
        if not np.all(np.isfinite(pts)):
            raise GeometryError("a facet's design outline does not project into the camera: check the station "
                                "layout and the heliostat design")
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        pad = settings.window_margin * (hi - lo) + settings.window_margin_px
        c0, r0 = (int(max(0, math.floor(v))) for v in lo - pad)
        c1, r1 = int(min(w, math.ceil(hi[0] + pad[0]) + 1)), int(min(h, math.ceil(hi[1] + pad[1]) + 1))
        if c1 <= c0 or r1 <= r0:
            raise GeometryError("a facet's nominal image lies outside the camera's view: check the station layout "
                                "and the heliostat design")
        out.append((r0, c0, r1, c1))
    return out


def find_facets(dark: np.ndarray, white: np.ndarray, geometry: StationGeometry, ensemble: EnsembleDesign,
                threshold_dn: float, settings: HeliostatSettings = HeliostatSettings()
                ) -> tuple[list[FacetRegion], np.ndarray]:
    """Step 1: the facets in the capture, each found or named as missing, hidden or cut off.

    Parameters
    ----------
    dark, white : (H, W) arrays
        The dark and full-white frames, DN.
    geometry : StationGeometry
        ``fixture_to_camera`` is the nominal heliostat frame.
    ensemble : EnsembleDesign
    threshold_dn : float
        A pixel responds when white - dark exceeds this, DN.

    Returns
    -------
    (regions, labels)
        One :class:`FacetRegion` per facet of the design, and the (H, W) int32 labelling of responsive regions.

    Raises
    ------
    FacetNotFoundError
        When nothing responds, or one region spans two facets' nominal images (no gap between them).
    """
    # lazy: scipy.ndimage, ~360 ms CPU; config.py loads this at every start
    from scipy.ndimage import find_objects

    h, w = geometry.camera.shape
    if white.dtype == dark.dtype and white.dtype in (np.uint8, np.uint16) and threshold_dn >= 0:
        # white - dark clipped at zero in the counts' own type, against the threshold's whole part (the same
        # pixels as the signed difference: see measure/mask.py)
        responsive = np.greater(cv2.subtract(white, dark), min(int(np.floor(threshold_dn)),
                                                               int(np.iinfo(white.dtype).max)))
    else:
        responsive = (white.astype(np.int64) - dark.astype(np.int64)) > threshold_dn
    n, labels = cv2.connectedComponents(responsive.view(np.uint8), connectivity=8)
    areas = np.bincount(labels.ravel(), minlength=n).astype(np.int64)
    areas[0] = 0
    boxes = find_objects(labels)            # (rows, columns) slices of region c at boxes[c - 1]
    if not np.any(areas >= settings.min_region_px):
        raise FacetNotFoundError("nothing in the image responds to the screen: no heliostat in the fixture, or the "
                                 "display is not showing")
    outlines = nominal_outlines(geometry, ensemble)
    windows = facet_windows(geometry, ensemble, settings)
    # overlap[i, c]: pixels of region c inside facet i's nominal image
    overlap = np.zeros((ensemble.n_facets, n), dtype=np.int64)
    expected = np.zeros(ensemble.n_facets)
    for i, pts in enumerate(outlines):
        r0, c0, r1, c1 = windows[i]           # the nominal image lies inside the window
        poly = np.zeros((r1 - r0, c1 - c0), dtype=np.uint8)
        cv2.fillPoly(poly, [np.round((pts - np.array([c0, r0])) * 16).astype(np.int32)], 1, shift=4)
        inside = poly.view(bool)
        expected[i] = float(np.count_nonzero(inside))
        overlap[i] = np.bincount(labels[r0:r1, c0:c1][inside], minlength=n)
    overlap[:, 0] = 0
    owner = np.argmax(overlap, axis=0)
    belongs = [[c for c in range(1, n) if areas[c] >= settings.min_region_px and owner[c] == i and overlap[i, c] > 0]
               for i in range(ensemble.n_facets)]
    # one region, two facets: a large share of each of two nominal images
    joined: dict[int, int] = {}
    for c in range(1, n):
        if areas[c] < settings.min_region_px:
            continue
        big = [i for i in range(ensemble.n_facets) if overlap[i, c] > 0.25 * expected[i]]
        if len(big) > 1 and settings.split_joined:
            joined.update({i: c for i in big})
        elif len(big) > 1:
            names = ", ".join(ensemble.facets[i].label for i in big)
            raise FacetNotFoundError(f"facets {names} are one region in the image: no gap between them is seen (a "
                                     "facet misplaced onto its neighbour, or the camera out of focus); the facets "
                                     "must be apart in the image to be told apart")
    regions = []
    for i, f in enumerate(ensemble.facets):
        comps = tuple(belongs[i])
        area = int(sum(areas[c] for c in comps))
        r0, c0, r1, c1 = windows[i]
        status, reason = "measured", ""
        if i in joined:
            # its share of the joined region; where exactly it lies comes from the heliostat's outline
            c = joined[i]
            area = int(overlap[i, c])
            if area < settings.min_area_fraction * expected[i]:
                status = "hidden"
                reason = (f"facet {f.label} is partly hidden: {area} pixels respond where the design expects about "
                          f"{expected[i]:.0f}; something covers it, or it is turned far from its design canting")
            regions.append(FacetRegion(index=i, label=f.label, status=status, window=windows[i], components=(c,),
                                       area_px=area, expected_area_px=float(expected[i]), reason=reason, joined=True))
            continue
        if not comps:
            status = "missing"
            reason = (f"facet {f.label} is missing: nothing responds where the design puts it (not mounted, covered, "
                      "or turned far from its design canting)")
        else:
            y0 = min(boxes[c - 1][0].start for c in comps)
            x0 = min(boxes[c - 1][1].start for c in comps)
            y1 = max(boxes[c - 1][0].stop for c in comps) - 1
            x1 = max(boxes[c - 1][1].stop for c in comps) - 1
            border = y0 == 0 or x0 == 0 or y1 == h - 1 or x1 == w - 1
            outside = y0 < r0 or x0 < c0 or y1 >= r1 or x1 >= c1
            if border or outside:
                status = "cut off"
                reason = (f"facet {f.label} is cut off at the {'image border' if border else 'edge of its window'}: "
                          "the heliostat is misplaced in the fixture or the camera is aimed wrongly")
            elif area < settings.min_area_fraction * expected[i]:
                status = "hidden"
                reason = (f"facet {f.label} is partly hidden: {area} pixels respond where the design expects about "
                          f"{expected[i]:.0f}; something covers it, or it is turned far from its design canting")
        regions.append(FacetRegion(index=i, label=f.label, status=status, window=windows[i], components=comps,
                                   area_px=area, expected_area_px=float(expected[i]), reason=reason))
    return regions, labels


def window_camera(camera: CameraIntrinsics, window: tuple) -> CameraIntrinsics:
    """The camera of a window of the image: the same lens, the principal point moved by the window's corner."""
    r0, c0, r1, c1 = window
    k = np.array(camera.matrix, dtype=np.float64)
    k[0, 2] -= c0
    k[1, 2] -= r0
    return CameraIntrinsics(c1 - c0, r1 - r0, k, camera.distortion)


class WindowRays:
    """The pixel rays of a window, taken from the whole camera's ray table (the same bits)."""

    def __init__(self, table, window: tuple, width_px: int):
        self._table = table
        self._r0, self._c0, _, c1 = window
        self._w = c1 - self._c0
        self._full_w = int(width_px)

    def take(self, flat_idx: np.ndarray) -> np.ndarray:
        rows, cols = np.divmod(np.asarray(flat_idx, dtype=np.int64), self._w)
        return self._table.take((rows + self._r0) * self._full_w + cols + self._c0)


def facet_frames(frames: np.ndarray, region: FacetRegion, labels: np.ndarray, dilation_px: int) -> np.ndarray:
    """The frames of *region*'s window, its neighbours (every other responsive region, widened by
    *dilation_px*) set to the dark frame's counts in every frame."""
    r0, c0, r1, c1 = region.window
    out = np.array(frames[:, r0:r1, c0:c1], copy=True)
    lab = labels[r0:r1, c0:c1]
    other = (lab > 0) & ~np.isin(lab, region.components)
    if dilation_px > 0 and other.any():
        k = 2 * dilation_px + 1
        other = cv2.dilate(other.view(np.uint8), np.ones((k, k), np.uint8)).view(bool)
        other &= ~np.isin(lab, region.components)
    if other.any():
        dark = out[0]
        out[:, other] = dark[other]
    return out


@dataclass(frozen=True)
class JoinedPose:
    """The heliostat's pose from the outer outline of its joined facets (:func:`joined_pose`).

    Attributes
    ----------
    heliostat_to_camera : Pose
        Range fixed by the measured distance.
    corners_px : (4, 2) array
        The outline's corners found, in :func:`outer_corners`' order.
    corner_sigma_px : float
        Standard uncertainty of each corner coordinate (as a facet's, from its sides' fits), pixels.
    reprojection_rms_px : float
    edge_blur_px : float
        The outline's edge blur (its pixels' reach inside it), pixels.
    """

    heliostat_to_camera: Pose
    corners_px: np.ndarray
    corner_sigma_px: float
    reprojection_rms_px: float
    edge_blur_px: float


def outer_corners(ensemble: EnsembleDesign, indices) -> np.ndarray:
    """The corners of the rectangle the facets *indices* fill (a grid of facets, or one mirror cut in parts),
    counter-clockwise from (+x, -y) as a facet's outline: each the nearest of those facets' own corners, (4, 3)
    metres, heliostat frame."""
    corners = np.concatenate([ensemble.facets[i].corners_m() for i in indices])
    (x0, y0), (x1, y1) = corners[:, :2].min(axis=0), corners[:, :2].max(axis=0)
    out = []
    for x, y in ((x1, y0), (x1, y1), (x0, y1), (x0, y0)):
        out.append(corners[int(np.argmin(np.hypot(corners[:, 0] - x, corners[:, 1] - y)))])
    return np.array(out)


def joined_pose(contrast: np.ndarray, region: np.ndarray, geometry: StationGeometry, ensemble: EnsembleDesign,
                indices, screen_centre_cam_m: np.ndarray, measured_distance_m: float,
                settings: AnalysisSettings) -> JoinedPose:
    """The heliostat's pose from the outer outline of facets whose regions touch (*region*, their union):
    the outline's four corners (:func:`~sofast_station.measure.corners.fit_outline`) against
    :func:`outer_corners`, one solvePnP from the fixture's nominal pose, the range fixed by the measured
    distance. What OpenCSP does with its ensemble's perimeter before it looks for each facet's corners.

    Raises
    ------
    FacetNotFoundError
        The outline has no four corners near the design's, or they do not fit it.
    """
    cam = geometry.camera
    outer = outer_corners(ensemble, indices)
    # the outline as one facet, for the sides' bows where the fixture puts it (a hint; its surface is the
    # heliostat's layout paraboloid, within millimetres of the facets' at the corners)
    layout = FacetDesign(name=f"{ensemble.name} outline", kind="heliostat", focal_length_m=ensemble.focal_length_m,
                         outline_m=outer[:, :2], measure_point_m=outer[:, :2].mean(axis=0),
                         alignment_point_m=outer[:, :2].mean(axis=0))
    try:
        outline = corners_mod.fit_outline(contrast, region, 4, settings.edge_window_px,
                                          **corners_mod.outline_hints(layout, cam, geometry.fixture_to_camera))
        corners_px, blur = outline.corners_px, float(outline.edge_blur_px)
        sigma = float(np.median(3.0 * np.asarray(outline.edge_rms_px, float)
                                / np.sqrt(np.maximum(outline.n_edge_points, 1))))
    except FacetNotFoundError:
        # too near the image's border for the edges' profiles: the lines of the mask's boundary pixels
        corners_px, sigma = corners_mod.mask_outline_corners(region, 4)
        blur = 1.0
    expected = project(cam, geometry.fixture_to_camera, outer)
    found = corners_mod.match_corners(corners_px, expected, settings.corner_tolerance_px)
    pose = solve_corner_pose(cam, found, outer, geometry.fixture_to_camera)
    if pose.reprojection_rms_px > settings.max_corner_rms_px:
        raise FacetNotFoundError(f"the joined facets' outer corners do not fit the heliostat's design "
                                 f"({pose.reprojection_rms_px:.1f} px RMS): a facet missing from the outline's "
                                 "edge, or not this heliostat")
    h2c, _ = fix_range(pose.facet_to_camera, ensemble.measure_point_m, screen_centre_cam_m, measured_distance_m,
                       settings.max_range_shift_m)
    return JoinedPose(h2c, found, sigma, pose.reprojection_rms_px, blur)


def joined_facet(geometry: StationGeometry, ensemble: EnsembleDesign, region: FacetRegion, pose: JoinedPose,
                 settings: HeliostatSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A joined facet where the heliostat's outline puts it, in its window: its design corners (n, 2), the
    pixels it may use (its design outline's image less the edge's reach and ``joined_inset_px``) and the
    pixels it owns (that image widened by ``blank_dilation_px``: the rest of the window is blanked)."""
    f = ensemble.facets[region.index]
    f2c = pose.heliostat_to_camera.compose(f.to_heliostat)
    r0, c0, r1, c1 = region.window
    shift = np.array([c0, r0], dtype=np.float64)
    corners = project(geometry.camera, f2c, f.design.corners_3d()) - shift
    outline = outline_image_points(f.design, geometry.camera, f2c) - shift
    poly = np.zeros((r1 - r0, c1 - c0), dtype=np.uint8)
    cv2.fillPoly(poly, [np.round(outline * 16).astype(np.int32)], 1, shift=4)
    # distance of each pixel centre inside the polygon to its boundary (pixels), and outside it
    inside = cv2.distanceTransform(poly, cv2.DIST_L2, 5)
    outside = cv2.distanceTransform(1 - poly, cv2.DIST_L2, 5)
    keep = inside > corners_mod.edge_inset_px(pose.edge_blur_px) + settings.joined_inset_px
    owned = (poly > 0) | (outside <= settings.blank_dilation_px)
    return corners, keep, owned


@dataclass(frozen=True)
class HeliostatPose:
    """Step 3: the heliostat's corner pose.

    Attributes
    ----------
    heliostat_to_camera : Pose
        Range fixed by the measured distance.
    corners_px : dict
        Facet index -> its found corners (N, 2), image pixels, design order.
    corner_cov_px2 : dict
        Facet index -> their covariance (2N x 2N) or None.
    reprojection_rms_px : float
    range_shift_m : float
    distances_m : dict
        Facet index -> distance from the screen centre to its measure point, metres.
    """

    heliostat_to_camera: Pose
    corners_px: dict
    corner_cov_px2: dict
    reprojection_rms_px: float
    range_shift_m: float
    distances_m: dict


def heliostat_pose(corners_px: dict, corner_cov: dict, geometry: StationGeometry, ensemble: EnsembleDesign,
                   screen_centre_cam_m: np.ndarray, measured_distance_m: float, max_range_shift_m: float,
                   max_corner_rms_px: float) -> HeliostatPose:
    """Step 3: the corner pose of the whole heliostat from the found facets' corners, its range fixed by the
    measured distance (to the measure facet's measure point), and every facet's distance."""
    if ensemble.measure_facet not in corners_px:
        raise FacetNotFoundError(f"the range finder's facet {ensemble.facets[ensemble.measure_facet].label} was not "
                                 "found: the measured distance cannot be placed; mount or uncover it (or name "
                                 "another measure_facet in the heliostat file)")
    if len(corners_px) < 2:
        raise FacetNotFoundError("fewer than two facets were found: the heliostat's pose cannot be measured")
    keys = sorted(corners_px)
    found = np.concatenate([corners_px[i] for i in keys])
    design = np.concatenate([ensemble.facets[i].corners_m() for i in keys])
    pose = solve_corner_pose(geometry.camera, found, design, geometry.fixture_to_camera)
    if pose.reprojection_rms_px > max_corner_rms_px:
        raise FacetNotFoundError("the facets' corners do not fit the heliostat's design "
                                 f"({pose.reprojection_rms_px:.1f} "
                                 "px RMS): a facet far off its place on the frame, or not this heliostat")
    h2c, shift = fix_range(pose.facet_to_camera, ensemble.measure_point_m, screen_centre_cam_m, measured_distance_m,
                           max_range_shift_m)
    return HeliostatPose(h2c, dict(corners_px), dict(corner_cov), pose.reprojection_rms_px, shift,
                         facet_distances(h2c, ensemble, screen_centre_cam_m))


def facet_distances(heliostat_to_camera: Pose, ensemble: EnsembleDesign, screen_centre_cam_m: np.ndarray) -> dict:
    """Facet index -> distance from the screen centre to its measure point (at its design pose on the
    heliostat placed by *heliostat_to_camera*), metres."""
    centre = np.asarray(screen_centre_cam_m, np.float64)
    return {i: float(np.linalg.norm(heliostat_to_camera.apply(f.point_m(f.design.measure_point_m)) - centre))
            for i, f in enumerate(ensemble.facets)}


def tilted(heliostat_to_camera: Pose, ensemble: EnsembleDesign, tilt_mrad: tuple) -> Pose:
    """The heliostat pose turned by R_y(b) R_x(a) about its own axes, (a, b) = *tilt_mrad*, through its measure
    point (which keeps the measured distance)."""
    r0 = heliostat_to_camera.rotation
    r1 = r0 @ _rot_xy(1e-3 * tilt_mrad[0], 1e-3 * tilt_mrad[1])
    p = ensemble.measure_point_m
    return Pose(r1, heliostat_to_camera.apply(p) - r1 @ p)


def _rot_xy(a: float, b: float) -> np.ndarray:
    """R_y(b) R_x(a), radians."""
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    return np.array([[cb, 0.0, sb], [0.0, 1.0, 0.0], [-sb, 0.0, cb]]) @ np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa],
                                                                                  [0.0, sa, ca]])


def _rx_ry(r: np.ndarray) -> tuple[float, float]:
    """(rx, ry), radians, of R = R_z R_y R_x: from its third row (independent of rz)."""
    return math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1.0, min(1.0, r[2, 0])))


def canting_errors(design_rotations: dict, optical_in_frame: dict) -> dict:
    """Step 5: every facet's canting error (docs/conventions.md#canting).

    Parameters
    ----------
    design_rotations : dict
        Facet index -> R_i, its design canting (facet -> heliostat frame).
    optical_in_frame : dict
        Facet index -> its optical frame's orientation in the heliostat's corner-pose frame (3 x 3).

    Returns
    -------
    dict
        ``canting_mrad``: {index: (rx, ry)}, ``rz_mrad``: {index: rz}, ``tilt_mrad``: (a, b) the optical
        frame's tilt R_y(b) R_x(a) against the corner-pose frame, ``errors``: {index: E_i (3 x 3)}.
    """
    keys = sorted(optical_in_frame)
    if not keys:
        raise AnalysisError("no facet was measured: there is no canting to report")
    a = b = 0.0
    for _ in range(100):
        t_inv = _rot_xy(a, b).T
        rel = np.array([_rx_ry(design_rotations[i].T @ t_inv @ optical_in_frame[i]) for i in keys])
        da, db = (float(v) for v in rel.mean(axis=0))
        a, b = a + da, b + db
        if abs(da) < TILT_TOLERANCE_RAD and abs(db) < TILT_TOLERANCE_RAD:
            break
    t_inv = _rot_xy(a, b).T
    errors = {i: design_rotations[i].T @ t_inv @ optical_in_frame[i] for i in keys}
    return {"canting_mrad": {i: tuple(1e3 * v for v in _rx_ry(e)) for i, e in errors.items()},
            "rz_mrad": {i: 1e3 * math.atan2(e[1, 0], e[0, 0]) for i, e in errors.items()},
            "tilt_mrad": (1e3 * a, 1e3 * b), "errors": errors}


def combined_u(weights: dict, sensitivities: dict, u_random: dict, path: tuple) -> float | None:
    """Step 6: the expanded uncertainty (k = 2) of ``sum_i w_i x_i``, x_i facet i's figure at *path*.

    Parameters
    ----------
    weights : dict
        Facet index -> w_i.
    sensitivities : dict
        Facet index -> its :class:`~sofast_station.measure.uncertainty.Sensitivities` (or None).
    u_random : dict
        Facet index -> the random part of x_i's expanded uncertainty (k = 2) (or None).
    path : tuple
        The figure, e.g. ``("optical_tilt_mrad", "x")``.

    The systematic inputs (every row of kind ``"systematic"``) are the same for every facet of a capture:
    their signed contributions c_ik (and curvatures q_ik) add with the weights before squaring,
    ``sqrt((sum_i w_i c_ik)^2 + 2 (sum_i w_i q_ik)^2)`` per input; as in the single facet's budget
    (:func:`~sofast_station.measure.uncertainty.budget.combine`) the curvatures' signed sum over the inputs,
    ``sum_k sum_i w_i q_ik``, is an offset the value keeps, added in quadrature. The random parts (the
    capture's noise, the corners) are independent between facets: ``sum_i (w_i u_i)^2``.
    """
    keys = list(weights)
    table = _systematic_table(keys, sensitivities, u_random, path)
    if table is None:
        return None
    lin, cur, rand = table
    w = np.array([weights[i] for i in keys])
    sys2 = np.sum((w @ lin) ** 2 + 2.0 * (w @ cur) ** 2) + np.sum(w @ cur) ** 2
    return float(2.0 * np.sqrt(sys2 + np.sum((w * 0.5 * rand) ** 2)))


def _systematic_table(keys: list, sensitivities: dict, u_random: dict, path: tuple):
    """(linear (n, k), curvature (n, k), random U (n,)) of *path* for facets *keys* and the systematic inputs
    (by name, in the first facet's order; an input a facet lacks counts 0 for it); None when a facet has no
    sensitivities or random part."""
    names: list = []
    for i in keys:
        sens = sensitivities.get(i)
        if sens is None or u_random.get(i) is None or path not in sens.paths:
            return None
        for inp in sens.inputs:
            if inp.kind == "systematic" and inp.name not in names:
                names.append(inp.name)
    col = {n: c for c, n in enumerate(names)}
    lin = np.zeros((len(keys), len(names)))
    cur = np.zeros_like(lin)
    for r, i in enumerate(keys):
        sens = sensitivities[i]
        j = sens.paths.index(path)
        for k, inp in enumerate(sens.inputs):
            if inp.kind == "systematic":
                lin[r, col[inp.name]] = sens.linear[k, j]
                cur[r, col[inp.name]] = sens.curvature[k, j]
    return lin, cur, np.array([float(u_random[i]) for i in keys])


def capture_scaled(sens, figures: dict):
    """A facet's cached sensitivities with its systematic rows at the values its capture's own evidence gave
    them, as the single facet's budget uses them (:func:`~sofast_station.measure.uncertainty.capture_evidence.
    capture_scales`): the display response's rows, computed at ``[uncertainty] response_phase_rad``, scaled to
    the capture's estimate (``uncertainty_budget.display_response.u_rad``: its second harmonic, and the
    radiometric record's rounding) -- linear parts by the ratio, curvatures by its square. The random rows are
    the facet's ``_U_random`` already. *sens* itself is not changed."""
    response = ((figures.get("uncertainty_budget") or {}).get("display_response") or {}).get("u_rad")
    rows = [k for k, inp in enumerate(sens.inputs) if inp.group == "display response" and inp.u > 0]
    if response is None or not rows:
        return sens
    scale = np.ones(len(sens.inputs))
    scale[rows] = [float(response) / sens.inputs[k].u for k in rows]
    return dataclasses.replace(sens, linear=sens.linear * scale[:, None],
                               curvature=sens.curvature * (scale ** 2)[:, None])


def canting_u(sensitivities: dict, u_random: dict, path: tuple) -> dict:
    """Every facet's canting U (k = 2) at once: :func:`combined_u` with the weights of x_i less the facets'
    mean (``e_i - 1/n``), for the facets of *sensitivities*."""
    keys = sorted(sensitivities)
    table = _systematic_table(keys, sensitivities, u_random, path)
    if table is None:
        return {i: None for i in keys}
    lin, cur, rand = table
    n = len(keys)
    w = np.eye(n) - 1.0 / n
    sys2 = np.sum((w @ lin) ** 2 + 2.0 * (w @ cur) ** 2, axis=1) + np.sum(w @ cur, axis=1) ** 2
    rand2 = (w ** 2) @ ((0.5 * rand) ** 2)
    return {i: float(2.0 * np.sqrt(sys2[r] + rand2[r])) for r, i in enumerate(keys)}


@dataclass
class HeliostatAnalysis:
    """What :func:`analyse_heliostat` returns.

    Attributes
    ----------
    figures : dict
        JSON-ready: ``heliostat`` (pose, tilts, counts) and ``facets`` (one dict per facet of the design:
        label, status, window, and for a measured facet its figures with U and ``canting_mrad``).
    regions : list of FacetRegion
    analyses : dict
        Facet index -> its :class:`~sofast_station.measure.pipeline.Analysis` (in its window).
    pose : HeliostatPose or None
    valid : (H, W) bool array
        Every measured facet's valid pixels, in the whole image.
    timings_s : dict
    """

    figures: dict
    regions: list
    analyses: dict
    pose: HeliostatPose | None
    valid: np.ndarray
    timings_s: dict = field(default_factory=dict)

    def facet_to_camera(self, i: int) -> Pose:
        """Facet *i*'s optical (boresighted) frame in the camera."""
        return self.analyses[i].facet_to_camera

    def facet_in_heliostat(self, i: int, corrected: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Facet *i*'s optical frame in the heliostat's optical frame: (rotation, translation of its origin);
        *corrected*: with its canting error turned out (about its own origin; its rotation about its normal
        kept), i.e. its design canting turned by that rotation."""
        to_frame = self._optical_to_camera.inverse().compose(self.analyses[i].facet_to_camera)
        if not corrected:
            return to_frame.rotation, to_frame.translation
        e = self._errors[i]
        rz = math.atan2(e[1, 0], e[0, 0])
        c, s = math.cos(rz), math.sin(rz)
        return self._design_rotations[i] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), to_frame.translation

    # set by analyse_heliostat
    _optical_to_camera: Pose | None = None
    _errors: dict = field(default_factory=dict)
    _design_rotations: dict = field(default_factory=dict)


def _placement_about_origin(fixture_to_camera: Pose, frame_to_camera: Pose) -> dict:
    """A frame's placement in the fixture, about the frame's origin: {"mm": t, "mrad": (rx, ry, rz)}."""
    to_fix = fixture_to_camera.inverse().compose(frame_to_camera)
    r = to_fix.rotation
    rx, ry = _rx_ry(r)
    return {"mm": (1000.0 * to_fix.translation).tolist(),
            "mrad": [1000.0 * rx, 1000.0 * ry, 1000.0 * math.atan2(r[1, 0], r[0, 0])]}


def _placement_of(pose6: np.ndarray, geometry: StationGeometry, ensemble: EnsembleDesign, centre: np.ndarray,
                  distance_m: float, max_shift_m: float) -> np.ndarray:
    """The heliostat's placement (mm, mrad) of the corner pose (rvec, tvec) *pose6*, range fixed."""
    pose = Pose(cv2.Rodrigues(np.asarray(pose6[:3], np.float64))[0], np.asarray(pose6[3:], np.float64))
    h2c, _ = fix_range(pose, ensemble.measure_point_m, centre, distance_m, max_shift_m)
    pl = _placement_about_origin(geometry.fixture_to_camera, h2c)
    return np.array([*pl["mm"], *pl["mrad"]])


def _pose_uncertainty(hp: HeliostatPose, geometry: StationGeometry, ensemble: EnsembleDesign, centre: np.ndarray,
                      distance_m: float, settings: AnalysisSettings, inputs) -> dict:
    """Expanded uncertainty (k = 2) of the heliostat's placement (mm, mrad), linearised about the found pose:
    its corners' covariance (each facet's sides' fits) through the least-squares pose
    (``(J^T J)^-1 J^T``, J the projection's Jacobian), the camera's focal lengths and principal point the
    same way, the measured distance through the range fix, and the fixture pose (its uncertainty is the
    placement's own, one to one)."""
    keys = sorted(hp.corners_px)
    design = np.concatenate([ensemble.facets[i].corners_m() for i in keys])
    # the corner pose itself (before the range fix): what the range-fixed pose came from, to first order
    r0 = hp.heliostat_to_camera.rotation
    rvec = cv2.Rodrigues(r0)[0].ravel()
    pose6 = np.concatenate([rvec, hp.heliostat_to_camera.translation])
    cam = geometry.camera
    _, jac = cv2.projectPoints(design.reshape(-1, 1, 3), rvec, hp.heliostat_to_camera.translation, cam.matrix,
                               cam.distortion)
    j_pose, j_cam = jac[:, :6], jac[:, 6:10]            # d(image)/d(rvec, tvec), d(image)/d(fx, fy, cx, cy)
    solve = np.linalg.pinv(j_pose)                       # d(pose)/d(image), least squares
    base = _placement_of(pose6, geometry, ensemble, centre, distance_m, settings.max_range_shift_m)
    g = np.zeros((6, 6))
    for k in range(6):
        step = np.zeros(6)
        step[k] = 1e-6                                    # rad, or m
        g[:, k] = (_placement_of(pose6 + step, geometry, ensemble, centre, distance_m, settings.max_range_shift_m)
                   - base) / step[k]
    cov_img = np.zeros((2 * len(design), 2 * len(design)))
    at = 0
    for i in keys:
        n = 2 * len(hp.corners_px[i])
        cov = hp.corner_cov_px2.get(i)
        cov_img[at:at + n, at:at + n] = cov if cov is not None and np.all(np.isfinite(cov)) else 0.0
        at += n
    # the found corners move with the camera's intrinsics as the design's image does: the pose moves by the
    # opposite of what explains that motion
    var = np.diag(g @ solve @ cov_img @ solve.T @ g.T).copy()
    if inputs is not None:
        for col, u in ((0, inputs.camera_focal_px), (1, inputs.camera_focal_px), (2, inputs.camera_principal_px),
                       (3, inputs.camera_principal_px)):
            if u > 0:
                var += (g @ solve @ (j_cam[:, col] * u)) ** 2
        if inputs.distance_mm > 0:
            moved = _placement_of(pose6, geometry, ensemble, centre, distance_m + 1e-3 * inputs.distance_mm,
                                  settings.max_range_shift_m)
            var += (moved - base) ** 2
        var[:3] += np.square(inputs.fixture_translation_mm)
        var[3:] += np.square(inputs.fixture_rotation_mrad)
    u = 2.0 * np.sqrt(np.maximum(var, 0.0))
    return {"mm": [float(v) if np.isfinite(v) else None for v in u[:3]],
            "mrad": [float(v) if np.isfinite(v) else None for v in u[3:]]}


def _each(fn, items: list, threads: int):
    """``fn(x)`` for every item, in order, *threads* items at a time (a generator: each result as soon as it
    and those before it are done). The facets' analyses wait on tasks of the analysis's own pool
    (:func:`~sofast_station.measure.pipeline.thread_pool`), so they run on threads of their own."""
    if threads <= 1 or len(items) <= 1:
        yield from (fn(x) for x in items)
        return
    with ThreadPoolExecutor(max_workers=min(threads, len(items)), thread_name_prefix="facet") as pool:
        yield from pool.map(fn, items)


def _facet_geometry(geometry: StationGeometry, ensemble: EnsembleDesign, region: FacetRegion) -> StationGeometry:
    """The geometry a facet's analysis sees: its window's camera, and its nominal frame as the fixture."""
    return StationGeometry(camera=window_camera(geometry.camera, region.window), screen=geometry.screen,
                           screen_to_camera=geometry.screen_to_camera,
                           fixture_to_camera=facet_frame_nominal(geometry, ensemble, region.index))


def analyse_heliostat(frames: np.ndarray, fringes: FringeSet, geometry: StationGeometry, ensemble: EnsembleDesign,
                      measured_distance_m: float, settings: AnalysisSettings = AnalysisSettings(),
                      heliostat: HeliostatSettings = HeliostatSettings(), screen: ScreenModel | None = None,
                      rays_cam=None, uncertainty=None, sensitivity_cache: dict | None = None,
                      progress=None) -> HeliostatAnalysis:
    """Reduce one capture of a heliostat to every facet's figures and canting error (see the module docstring).

    Each facet is reduced in two parts: first, with a distance from the fixture's nominal heliostat pose, the
    stages of :func:`~sofast_station.measure.pipeline.reduce_stages` up to shape and boresight on the
    subsample, which give its corners and its optical frame; the heliostat's corner pose comes from all
    corners and its tilt from the optical frames (the corners of a nearly flat heliostat resolve its tilt to
    milliradians, the facets' normals to hundredths); then each facet's shape over every pixel, its fits and
    figures from its corner pose with the distance that pose gives it (:func:`~sofast_station.measure.
    pipeline.rerun` from the shape), finished with their uncertainties
    (:func:`~sofast_station.measure.analysis.finish_analysis`).

    The steps, each a function of its own: :func:`find_facets`, :func:`reduce_to_boresight`,
    :func:`corner_pose_tilted`, :func:`finish_facets`, :func:`canting_errors`, and the record's parts
    :func:`facet_tilt_spread`, :func:`facet_entries` and :func:`heliostat_entry`.

    Parameters
    ----------
    frames : (n, rows, columns) integer array
        Dark, white, then the fringe frames, DN.
    fringes : FringeSet
    geometry : StationGeometry
        ``fixture_to_camera`` is the fixture's nominal heliostat frame.
    ensemble : EnsembleDesign
    measured_distance_m : float
        The range finder's distance from the screen centre to the measure facet's measure point, metres.
    settings : AnalysisSettings
        Every facet's analysis settings.
    heliostat : HeliostatSettings
    screen : ScreenModel, optional
    rays_cam : RayTable, optional
        The whole camera's ray table (each facet takes its window's rays from it).
    uncertainty : InputUncertainties, optional
        With it every figure carries its U (k = 2), canting included.
    sensitivity_cache : dict, optional
        Kept by the caller between captures: every facet's sensitivities are computed once.
    progress : callable, optional
        ``progress(done, total)`` after each facet's first reduction and after each facet's last.

    Returns
    -------
    HeliostatAnalysis

    Raises
    ------
    CaptureError
        The frames do not fit the camera.
    FacetNotFoundError
        Nothing responds, two facets are one region, the range finder's facet is not found, or the corners do
        not fit the heliostat.
    AnalysisError
        No facet could be analysed (every facet's reason is named).
    """
    t0 = time.perf_counter()
    timings: dict = {}
    _check_capture(frames, geometry, measured_distance_m)
    screen = screen if screen is not None else default_screen(geometry)
    centre = screen.centre_camera()
    regions, labels = find_facets(frames[0], frames[1], geometry, ensemble, settings.mask_threshold_dn, heliostat)
    timings["find_facets"] = time.perf_counter() - t0
    todo = [r for r in regions if r.status == "measured"]
    tick = _counter(progress, 2 * len(todo))
    geometries = {reg.index: _facet_geometry(geometry, ensemble, reg) for reg in todo}

    reductions, reasons = reduce_to_boresight(frames, fringes, geometry, ensemble, regions, labels, geometries,
                                              centre, measured_distance_m, settings, heliostat, screen, rays_cam,
                                              timings, tick)
    t = time.perf_counter()
    pose = corner_pose_tilted(reductions, regions, geometry, ensemble, centre, measured_distance_m, settings)
    timings["heliostat_pose"] = time.perf_counter() - t
    analyses = finish_facets(reductions, fringes, geometries, ensemble, pose.distances_m, settings, screen,
                             uncertainty, sensitivity_cache, reasons, timings, tick)
    t = time.perf_counter()
    h2c = pose.heliostat_to_camera
    design_rot = {i: ensemble.facets[i].rotation for i in analyses}
    cant = canting_errors(design_rot, {i: h2c.rotation.T @ a.facet_to_camera.rotation for i, a in analyses.items()})
    tilt = cant["tilt_mrad"]
    optical_to_camera = Pose(h2c.rotation @ _rot_xy(1e-3 * tilt[0], 1e-3 * tilt[1]), h2c.translation)
    spread = None if uncertainty is None else facet_tilt_spread(analyses, heliostat)
    facets_out, valid = facet_entries(regions, reasons, analyses, cant, pose.distances_m, spread,
                                      geometry.camera.shape)
    helio = heliostat_entry(ensemble, regions, analyses, pose, cant, optical_to_camera, geometry, centre,
                            measured_distance_m, settings, uncertainty, spread)
    timings["canting"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t0
    out = HeliostatAnalysis(figures={"heliostat": helio, "facets": facets_out}, regions=regions, analyses=analyses,
                            pose=pose, valid=valid, timings_s=timings)
    out._optical_to_camera = optical_to_camera
    out._errors = cant["errors"]
    out._design_rotations = design_rot
    return out


def _check_capture(frames: np.ndarray, geometry: StationGeometry, measured_distance_m: float) -> None:
    """Refuse frames that do not fit the camera, and a distance that is not a positive number of metres."""
    if frames.ndim != 3 or frames.shape[1:] != geometry.camera.shape:
        raise CaptureError(f"frames have shape {frames.shape}, expected (n, {geometry.camera.shape[0]}, "
                           f"{geometry.camera.shape[1]}) for this camera")
    if not (np.isfinite(measured_distance_m) and measured_distance_m > 0):
        raise GeometryError(f"measured distance must be a positive number of metres, got {measured_distance_m}")


def _counter(progress, total: int):
    """A callable that counts one more step done and reports ``progress(done, total)`` (if given)."""
    done = [0]

    def tick():
        done[0] += 1
        if progress:
            progress(done[0], total)
    return tick


def _no_facet(ensemble: EnsembleDesign, reasons: dict, regions: list = ()) -> AnalysisError:
    """The error when no facet could be analysed, every facet's reason named."""
    return AnalysisError("no facet of the heliostat could be analysed: "
                         + "; ".join(f"{ensemble.facets[i].label}: {m}" for i, m in sorted(reasons.items()))
                         + "".join(f"; {r.label}: {r.reason}" for r in regions if r.status != "measured"))


def reduce_to_boresight(frames: np.ndarray, fringes: FringeSet, geometry: StationGeometry, ensemble: EnsembleDesign,
                        regions: list, labels: np.ndarray, geometries: dict, centre: np.ndarray,
                        measured_distance_m: float, settings: AnalysisSettings, heliostat: HeliostatSettings,
                        screen: ScreenModel, rays_cam, timings: dict, tick) -> tuple[dict, dict]:
    """First pass: every found facet reduced up to its boresight on the subsample
    (:func:`~sofast_station.measure.pipeline.reduce_stages`), with the distance the fixture's nominal pose
    gives it (shifted as the measured distance is from the measure point's own nominal distance). Facets whose
    regions touch (``HeliostatSettings.split_joined``) are placed by the heliostat's outer outline
    (:func:`joined_pose`). Facets run *settings.threads* at a time (:func:`_each`): a facet's arithmetic is the
    same on any thread, so the same bits.

    Returns (reductions, reasons): facet index -> (Reduction, its timings); facet index -> why it was refused.
    Raises AnalysisError when no facet could be reduced."""
    todo = [r for r in regions if r.status == "measured"]
    nominal = facet_distances(geometry.fixture_to_camera, ensemble, centre)
    shift = measured_distance_m - float(np.linalg.norm(geometry.fixture_to_camera.apply(ensemble.measure_point_m)
                                                       - centre))
    joined, jp = {}, None
    together = [r for r in todo if r.joined]
    if together:
        t = time.perf_counter()
        union = np.isin(labels, sorted({c for r in together for c in r.components}))
        contrast = np.subtract(frames[1], frames[0], dtype=np.float32)
        jp = joined_pose(contrast, union, geometry, ensemble, [r.index for r in together], centre,
                         measured_distance_m, settings)
        joined = {r.index: joined_facet(geometry, ensemble, r, jp, heliostat) for r in together}
        timings["joined_pose"] = time.perf_counter() - t

    def first(reg: FacetRegion):
        t = time.perf_counter()
        rays = None if rays_cam is None else WindowRays(rays_cam, reg.window, geometry.camera.width_px)
        given = {}
        if reg.index in joined:
            corners, keep, owned = joined[reg.index]
            r0, c0, r1, c1 = reg.window
            window = np.array(frames[:, r0:r1, c0:c1], copy=True)
            window[:, ~owned] = window[0][~owned]           # its neighbours blanked by its design outline
            given = {"corners_px": corners, "corner_sigma_px": jp.corner_sigma_px, "pixel_mask": keep}
        else:
            window = facet_frames(frames, reg, labels, heliostat.blank_dilation_px)
        try:
            return reduce_stages(window, fringes, geometries[reg.index], ensemble.facets[reg.index].design,
                                 nominal[reg.index] + shift, settings, screen, rays,
                                 stop_after_boresight=True, **given), time.perf_counter() - t
        except StationError as exc:
            return exc, time.perf_counter() - t

    reductions, reasons = {}, {}
    for reg, (out, timings[f"reduce_{reg.label}"]) in zip(todo, _each(first, todo, settings.threads)):
        if isinstance(out, StationError):
            reasons[reg.index] = str(out)
        else:
            reductions[reg.index] = out
        tick()
    if not reductions:
        raise _no_facet(ensemble, reasons, regions)
    return reductions, reasons


def corner_pose_tilted(reductions: dict, regions: list, geometry: StationGeometry, ensemble: EnsembleDesign,
                       centre: np.ndarray, measured_distance_m: float, settings: AnalysisSettings) -> HeliostatPose:
    """The heliostat's corner pose from every reduced facet's corners (:func:`heliostat_pose`), and each facet's
    distance from that pose turned to the facets' mean optical tilt (the corners of a nearly flat heliostat
    resolve its tilt to milliradians, the facets' normals to hundredths)."""
    corners, covs = {}, {}
    for i, (red, _) in reductions.items():
        r0, c0, _, _ = regions[i].window
        corners[i] = red.pose.corners_px + np.array([c0, r0])
        covs[i] = red.pose.corner_cov_px2
    pose = heliostat_pose(corners, covs, geometry, ensemble, centre, measured_distance_m, settings.max_range_shift_m,
                          settings.max_corner_rms_px)
    h2c = pose.heliostat_to_camera
    first_cant = canting_errors({i: ensemble.facets[i].rotation for i in reductions},
                                {i: h2c.rotation.T @ red.shape.boresighted_to_camera.rotation
                                 for i, (red, _) in reductions.items()})
    distances = facet_distances(tilted(h2c, ensemble, first_cant["tilt_mrad"]), ensemble, centre)
    return dataclasses.replace(pose, distances_m=distances)


def finish_facets(reductions: dict, fringes: FringeSet, geometries: dict, ensemble: EnsembleDesign, distances: dict,
                  settings: AnalysisSettings, screen: ScreenModel, uncertainty, sensitivity_cache: dict | None,
                  reasons: dict, timings: dict, tick) -> dict:
    """Second pass: every reduced facet's corner pose at its distance
    (:func:`~sofast_station.measure.pipeline.pose_from_corners`), its shape over every pixel and its fits and
    figures (:func:`~sofast_station.measure.pipeline.rerun` from the shape), finished with their uncertainties
    (:func:`~sofast_station.measure.analysis.finish_analysis`).

    Returns facet index -> Analysis; a facet refused here has its reason added to *reasons*. Raises
    AnalysisError when no facet could be analysed."""
    def second(i: int):
        t = time.perf_counter()
        red, tim = reductions[i]
        f, g = ensemble.facets[i], geometries[i]
        try:
            p = pose_from_corners(red.pose.corners_px, red.region, red.rays, g, f.design, distances[i], settings,
                                  agreement=red.pose.outline_agreement)
            p = dataclasses.replace(p, corner_sigma_px=red.pose.corner_sigma_px,
                                    corner_cov_px2=red.pose.corner_cov_px2)
            with thread_pool(settings.threads) as pool:
                again = rerun(red, "shape", fringes=fringes, geometry=g, design=f.design,
                              measured_distance_m=distances[i], settings=settings, screen=screen, pose=p,
                              pool=pool)
                again = sharpened_fit(again, geometry=g, design=f.design, measured_distance_m=distances[i],
                                      settings=settings, screen=screen, pool=pool)
            tim = dict(tim, rerun=time.perf_counter() - t)
            done_ = finish_analysis(again, tim, fringes=fringes, geometry=g, design=f.design,
                                    measured_distance_m=distances[i], settings=settings, screen=screen,
                                    uncertainty=uncertainty, sensitivity_cache=sensitivity_cache)
            return done_, time.perf_counter() - t
        except StationError as exc:
            return exc, time.perf_counter() - t

    analyses: dict[int, Analysis] = {}
    keys = sorted(reductions)
    for i, (out, timings[f"facet_{ensemble.facets[i].label}"]) in zip(keys, _each(second, keys, settings.threads)):
        if isinstance(out, StationError):
            reasons[i] = str(out)
        else:
            analyses[i] = out
        tick()
    if not analyses:
        raise _no_facet(ensemble, reasons)
    return analyses


@dataclass(frozen=True)
class TiltSpread:
    """What a canting error's U is made of, per measured facet: its optical tilt's sensitivities to the
    station's inputs (scaled to this capture; None when it has none) and its random U (k = 2, mrad, per
    axis "x", "y"; a facet's own height on the frame included)."""

    sensitivities: dict
    u_random: dict

    def random(self, ax: str) -> dict:
        """Facet index -> its random U about axis *ax* (or None)."""
        return {j: None if u is None else u[ax] for j, u in self.u_random.items()}


def facet_tilt_spread(analyses: dict, heliostat: HeliostatSettings) -> TiltSpread:
    """Every measured facet's optical-tilt sensitivities and random U (:class:`TiltSpread`): a facet's height on
    the frame is its own, its share of the distance, independent between facets
    (``HeliostatSettings.facet_height_mm``)."""
    sens, u_rand = {}, {}
    for i, a in analyses.items():
        rec = from_record(a.sensitivities) if a.sensitivities is not None else None
        sens[i] = None if not rec else capture_scaled(rec[1], a.figures)
        u = a.figures.get("optical_tilt_mrad_U_random")
        u_rand[i] = None if u is None else dict(u)
        if sens[i] is not None and u_rand[i] is not None and heliostat.facet_height_mm > 0:
            r = [k for k, inp in enumerate(sens[i].inputs) if inp.name == "distance"]
            if r:
                scale = heliostat.facet_height_mm / sens[i].inputs[r[0]].u
                for ax in "xy":
                    c = float(sens[i].linear[r[0], sens[i].paths.index(("optical_tilt_mrad", ax))]) * scale
                    u_rand[i][ax] = math.hypot(u_rand[i][ax], 2.0 * c)
    return TiltSpread(sens, u_rand)


def facet_entries(regions: list, reasons: dict, analyses: dict, cant: dict, distances: dict,
                  spread: TiltSpread | None, shape: tuple) -> tuple[list, np.ndarray]:
    """One JSON-ready entry per facet of the design (label, status, window; a measured facet's figures, corners in
    the whole image, canting and distance, and with *spread* the canting's U), and every measured facet's valid
    pixels in the whole image (*shape*)."""
    cant_u = {}
    if spread is not None:
        cant_u = {ax: canting_u(spread.sensitivities, spread.random(ax), ("optical_tilt_mrad", ax)) for ax in "xy"}
    facets_out = []
    valid = np.zeros(shape, dtype=bool)
    for reg in regions:
        i = reg.index
        entry = {"index": i, "label": reg.label, "status": reg.status, "window": list(reg.window),
                 "area_px": reg.area_px, "expected_area_px": round(reg.expected_area_px, 1)}
        if i in reasons:
            entry["status"], entry["reason"] = "invalid", reasons[i]
        elif reg.status != "measured":
            entry["reason"] = reg.reason
        if i in analyses:
            a = analyses[i]
            r0, c0, r1, c1 = reg.window
            valid[r0:r1, c0:c1] |= a.valid
            entry.update({k: v for k, v in a.figures.items() if k != "timings_s"})
            entry["corners_px"] = (a.corners_px + np.array([c0, r0])).tolist()
            rx, ry = cant["canting_mrad"][i]
            entry["canting_mrad"] = {"x": rx, "y": ry}
            entry["canting_rz_mrad"] = cant["rz_mrad"][i]
            entry["measured_distance_m"] = distances[i]
            if spread is not None:
                entry["canting_mrad_U"] = {ax: cant_u[ax][i] for ax in "xy"}
        facets_out.append(entry)
    return facets_out, valid


def heliostat_entry(ensemble: EnsembleDesign, regions: list, analyses: dict, pose: HeliostatPose, cant: dict,
                    optical_to_camera: Pose, geometry: StationGeometry, centre: np.ndarray,
                    measured_distance_m: float, settings: AnalysisSettings, uncertainty,
                    spread: TiltSpread | None) -> dict:
    """The heliostat's own JSON-ready figures: its placement in the fixture, counts, common and optical tilt,
    canting RMS and maximum; with *uncertainty* (and *spread*) their U (k = 2)."""
    keys = sorted(analyses)
    h2c = pose.heliostat_to_camera
    tilt = cant["tilt_mrad"]
    in_fixture = _placement_about_origin(geometry.fixture_to_camera, optical_to_camera)["mrad"]
    magnitudes = [math.hypot(*cant["canting_mrad"][i]) for i in keys]
    helio = {
        "name": ensemble.name,
        "n_facets": ensemble.n_facets,
        "n_measured": len(analyses),
        "n_missing": sum(r.status == "missing" for r in regions),
        "placement": _placement_about_origin(geometry.fixture_to_camera, h2c),
        "corner_reprojection_rms_px": pose.reprojection_rms_px,
        "range_correction_m": pose.range_shift_m,
        "measured_distance_m": float(measured_distance_m),
        "common_tilt_mrad": {"x": tilt[0], "y": tilt[1]},
        "optical_tilt_mrad": {"x": in_fixture[0], "y": in_fixture[1]},
        "canting_rms_mrad": float(np.sqrt(np.mean(np.square(magnitudes)))),
        "canting_max_mrad": float(max(magnitudes)),
        "canting_max_facet": ensemble.facets[keys[int(np.argmax(magnitudes))]].label,
    }
    if uncertainty is None or spread is None:
        return helio
    mean_w = {j: 1.0 / len(keys) for j in keys}
    helio["optical_tilt_mrad_U"] = {ax: combined_u(mean_w, spread.sensitivities, spread.random(ax),
                                                   ("optical_tilt_mrad", ax)) for ax in "xy"}
    pu = _pose_uncertainty(pose, geometry, ensemble, centre, measured_distance_m, settings, uncertainty)
    helio["placement_U"] = pu
    # The common tilt is the optical frame's tilt less the corner pose's: the fixture cancels, the corners'
    # own tilt error dominates.
    fix = 2.0 * np.asarray(uncertainty.fixture_rotation_mrad, float)
    ot = helio["optical_tilt_mrad_U"]
    helio["common_tilt_mrad_U"] = {
        ax: (None if ot[ax] is None or pu["mrad"][k] is None else
             float(math.sqrt(max(ot[ax] ** 2 - fix[k] ** 2, 0.0) + max(pu["mrad"][k] ** 2 - fix[k] ** 2, 0.0))))
        for k, ax in enumerate("xy")}
    helio["coverage_factor"] = 2
    return helio
