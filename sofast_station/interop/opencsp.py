"""Read a SOFAST fringe measurement from Sandia's OpenCSP and analyse it with our pipeline.

OpenCSP's files (``opencsp/app/sofast``): the measurement (``MeasurementSofastFringe``: dark and light
mask images, fringe images, fringe periods, optic-to-screen distance, measure point), the camera
(``Camera``), the display shape (``DisplayShape``: rectangular2D, distorted2D or distorted3D), the
spatial orientation (``SpatialOrientation``: camera/screen), the image calibration
(``ImageCalibrationScaling``: camera -> display value response) and the facet definition (JSON corners).

Their conventions differ from ours; each conversion is a function of its own here, and has a test:

* **fringe order**: OpenCSP stores the y sets first, then x; we capture x first (:func:`reorder_frames`);
* **period list**: 0.9, 3.9, 15.9, 63.9 fractional screens (the first just below one, to avoid the edge
  ambiguity); our unwrapping takes any increasing list;
* **phase direction**: OpenCSP shows ``cos(theta - k pi/2)`` with ``theta = 2 pi p (1 - i/(N-1))`` for
  display pixel i (decreasing across the screen, pixel centres at i/(N-1)); our phase formula is the
  same, so our decoded position u = theta / (2 pi p) is OpenCSP's fractional x, and 1 - its fractional
  y (OpenCSP flips y after unwrapping); the screen model is built on OpenCSP's fractions with
  ``v_from_top`` (:func:`screen_nodes`);
* **screen axes and pose**: OpenCSP's screen points come from its display model in its screen frame,
  and ``r_cam_screen`` (a rotation vector) turns camera-frame vectors into the screen frame, so
  screen -> camera is its inverse plus ``v_cam_screen_cam`` (:func:`screen_to_camera`);
* **camera matrix**: OpenCSP's downsampled camera divides the whole matrix by 8, leaving K[2,2] = 1/8,
  which OpenCV ignores; we keep fx, fy, cx, cy and set K[2,2] = 1 (:func:`camera_from_opencsp`);
* **facet corners**: listed clockwise seen from the mirror side; our outline runs counter-clockwise.

The camera frames are passed through OpenCSP's image calibration (camera values -> display values, the
interpolated response curve) and scaled by 256 into integer counts, so our checks and thresholds work
unchanged (thresholds scaled likewise).
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import h5py
import numpy as np

from ..cache import load_screen_split, save_screen_split
from ..ensemble import ensemble_from_opencsp, ensemble_to_opencsp
from ..ensemble import facet_from_opencsp as read_facet
from ..errors import ConfigError, GeometryError
from ..facet import FacetDesign
from ..fringes import FringeSet
from ..geometry import CameraIntrinsics, Pose, ScreenSpec, StationGeometry
from ..measure.analysis import analyse
from ..measure.checks import stale_frames
from ..measure.heliostat import HeliostatSettings, analyse_heliostat
from ..measure.pipeline import Analysis, AnalysisSettings
from ..measure.pose import mask_centroid_px, pose_facing
from ..measure.screen import InterpolatedScreen
from ..measure.uncertainty import InputUncertainties, Sensitivities
from ..precompute import ray_table
from .identify import describe
from .opencsp_results import OpenCspResult, read_opencsp_result  # noqa: F401  (their public place until now)
from .paths import opencsp_test_data_paths

log = logging.getLogger(__name__)

#: Calibrated display values (0..255) are stored as integer counts times this.
COUNT_SCALE = 256


def _read(path: Path, key: str):
    """Dataset *key* of the HDF5 file *path*; a ConfigError names what the file holds when it has no *key*."""
    try:
        with h5py.File(path, "r") as h:
            if key not in h:
                raise ConfigError(f"{path} has no {key!r}: it is {describe(path)}")
            value = h[key][()]
    except OSError as exc:
        raise ConfigError(f"{path} is not a readable HDF5 file ({exc}): it is {describe(path)}") from None
    return value.decode() if isinstance(value, bytes) else value


def _rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """A rotation vector (radians about its axis) as a 3 x 3 matrix: OpenCV's Rodrigues formula, already
    loaded for the corners (scipy.spatial.transform, which OpenCSP uses, costs 0.2-0.4 s of imports)."""
    return cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))[0]


def camera_from_opencsp(path: Path) -> CameraIntrinsics:
    """OpenCSP ``Camera``: the intrinsic matrix with K[2,2] normalised to 1 (see module docstring)."""
    k = np.array(_read(path, "Camera/intrinsic_mat"), dtype=np.float64)
    # (OpenCSP has saved these as (2,), (2, 1), (5,) and (1, 5) arrays)
    shape = np.asarray(_read(path, "Camera/image_shape_xy")).ravel()
    dist = np.asarray(_read(path, "Camera/distortion_coef"), np.float64).ravel()
    if k.shape != (3, 3) or shape.size != 2 or dist.size not in (4, 5):
        raise ConfigError(f"{path}: a Camera with an intrinsic matrix of shape {k.shape}, image shape {shape.tolist()} "
                          f"and {dist.size} distortion coefficients: expected 3 x 3, [width, height] and OpenCV's 4 or "
                          "5 (k1 k2 p1 p2 [k3])")
    w, h = (int(v) for v in shape)
    matrix = np.array([[k[0, 0], k[0, 1], k[0, 2]], [0.0, k[1, 1], k[1, 2]], [0.0, 0.0, 1.0]])
    # OpenCV's 4-term model (k1 k2 p1 p2, OpenCSP's other cameras) is the 5-term one with k3 = 0
    return CameraIntrinsics(w, h, matrix, np.pad(dist, (0, 5 - dist.size)))


def screen_to_camera(path: Path) -> Pose:
    """OpenCSP ``SpatialOrientation``: screen frame -> camera frame."""
    r_cam_screen = _rotvec_to_matrix(_read(path, "SpatialOrientation/r_cam_screen"))
    v_cam_screen_cam = np.array(_read(path, "SpatialOrientation/v_cam_screen_cam"), np.float64).ravel()
    return Pose(r_cam_screen.T, v_cam_screen_cam)


def screen_nodes(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """OpenCSP ``DisplayShape`` as grid nodes: OpenCSP's (fraction x, fraction y) and the screen-frame
    points (metres). Our position u_y is 1 - fraction y: build the screen with ``v_from_top=True``."""
    model = _read(path, "DisplayShape/screen_model")
    if model == "rectangular2D":
        sx, sy = float(_read(path, "DisplayShape/screen_x")), float(_read(path, "DisplayShape/screen_y"))
        frac = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
        pts = np.column_stack([(frac[:, 0] - 0.5) * sx, (frac[:, 1] - 0.5) * sy, np.zeros(4)])
    elif model in ("distorted2D", "distorted3D"):
        frac = np.array(_read(path, "DisplayShape/xy_screen_fraction"), np.float64).T
        key = "DisplayShape/xy_screen_coords" if model == "distorted2D" else "DisplayShape/xyz_screen_coords"
        coords = np.array(_read(path, key), np.float64).T
        pts = coords if coords.shape[1] == 3 else np.column_stack([coords, np.zeros(len(coords))])
    else:
        raise ConfigError(f"{path}: unknown OpenCSP screen model {model!r}")
    return frac, pts


def reorder_frames(fringe_images: np.ndarray, n_y_sets: int, n_x_sets: int) -> np.ndarray:
    """OpenCSP (rows, cols, 4 (n_y + n_x)) with y sets first -> ours (4 (n_x + n_y), rows, cols), x first."""
    stack = np.moveaxis(fringe_images, 2, 0)
    return stack[fringe_order(fringe_images.shape[2], n_y_sets, n_x_sets)]


def fringe_order(n_frames: int, n_y_sets: int, n_x_sets: int) -> list[int]:
    """OpenCSP's fringe image index of each of our fringe frames: its x sets (stored after the y sets) first,
    then its y sets (:func:`reorder_frames`)."""
    n_y = 4 * n_y_sets
    if n_frames != n_y + 4 * n_x_sets:
        raise ConfigError(f"OpenCSP fringe images hold {n_frames} frames, expected "
                          f"{n_y + 4 * n_x_sets} for {n_y_sets} y and {n_x_sets} x period(s)")
    return list(range(n_y, n_frames)) + list(range(n_y))


def response_function(camera_values: np.ndarray, display_values: np.ndarray):
    """OpenCSP's image calibration: camera value -> display value, linear between samples, clamped."""
    cam = np.asarray(camera_values, np.float64)
    disp = np.asarray(display_values, np.float64)
    keep = np.concatenate([[True], np.diff(cam) > 0])      # OpenCSP drops non-increasing samples
    cam, disp = cam[keep], disp[keep]
    table = np.interp(np.arange(256, dtype=np.float64), cam, disp, left=disp[0], right=disp[-1])
    return lambda img: table[np.asarray(img)]


def count_table(camera_values: np.ndarray, display_values: np.ndarray) -> np.ndarray:
    """(256,) uint16: our integer count (display value x :data:`COUNT_SCALE`, rounded) of each 8-bit camera
    value, through OpenCSP's image calibration (:func:`response_function`). Rounding each of the 256
    entries gives every pixel the bits rounding its own display value gives."""
    respond = response_function(camera_values, display_values)
    return np.rint(respond(np.arange(256)) * COUNT_SCALE).astype(np.uint16)


def _camera_values(block: np.ndarray, path: Path) -> np.ndarray:
    """*block* of OpenCSP images as camera values 0..255 (its image calibration is an 8-bit table)."""
    block = np.asarray(block)
    if block.dtype == np.uint8:
        return block
    if block.dtype.kind not in "iu" or (block.size and (block.min() < 0 or block.max() > 255)):
        raise ConfigError(f"{path}: images of {block.dtype} values outside 0..255; the OpenCSP image calibration "
                          "converts 8-bit camera values")
    return block.astype(np.uint8)


#: Camera rows converted at a time by :func:`read_frames` (a block of 32 fringe images at 1624 columns is
#: 1.7 MB of 8-bit values).
ROWS_PER_BLOCK = 32


def read_frames(path: Path, counts: np.ndarray, n_y_sets: int, n_x_sets: int, shape: tuple[int, int],
                camera_path: Path | None = None) -> np.ndarray:
    """Our frames (dark, white, then the fringe frames in our order) from OpenCSP's measurement *path*, as
    integer counts through the (256,) uint16 table *counts* (:func:`count_table`).

    OpenCSP keeps its images pixel-major, (rows, columns, frames) of camera values. They are read a block of
    :data:`ROWS_PER_BLOCK` rows at a time and each block is looked up in *counts* straight into its place
    in our frame-major stack: the file's values are converted once, to 16-bit counts, with no float copy of
    the capture (a 1624 x 1232 capture of 34 frames is 136 MB of counts; in float64 it was 1.1 GB, twice).
    """
    g = "MeasurementSofastFringe/"
    try:
        with h5py.File(path, "r") as h:
            for key in ("fringe_images", "mask_images"):
                if g + key not in h:
                    raise ConfigError(f"{path} has no {g + key!r}: it is {describe(path)}")
            fringe, masks = h[g + "fringe_images"], h[g + "mask_images"]
            if fringe.shape[:2] != tuple(shape) or masks.shape[:2] != tuple(shape):
                raise ConfigError(f"{path}: images are {fringe.shape[1]} x {fringe.shape[0]} px but the camera "
                                  f"{camera_path or ''} is {shape[1]} x {shape[0]}".replace("  ", " "))
            if fringe.ndim != 3 or masks.ndim != 3 or masks.shape[2] < 2:
                raise ConfigError(f"{path}: fringe and mask images must be (rows, columns, frames) stacks "
                                  "holding the dark and white images and every fringe image")
            order = fringe_order(fringe.shape[2], n_y_sets, n_x_sets)
            frames = np.empty((2 + len(order), *shape), dtype=np.uint16)
            for r0 in range(0, shape[0], ROWS_PER_BLOCK):
                r1 = min(r0 + ROWS_PER_BLOCK, shape[0])
                mask_block = _camera_values(masks[r0:r1, :, :2], path)
                fringe_block = _camera_values(fringe[r0:r1], path)
                for k in range(2):
                    np.take(counts, mask_block[:, :, k], out=frames[k, r0:r1], mode="clip")
                for i, k in enumerate(order):
                    np.take(counts, fringe_block[:, :, k], out=frames[2 + i, r0:r1], mode="clip")
    except OSError as exc:
        raise ConfigError(f"{path} is not a readable HDF5 file ({exc})") from None
    return frames


def mask_threshold(dark: np.ndarray, light: np.ndarray) -> float:
    """White-minus-dark threshold (counts) between the lit room and the facet.

    A projection screen lights its room, so (unlike our LCD station, where only the facet reflects the
    screen) the background responds too; Otsu's threshold on the difference image separates the facet's
    bright mode from the room's, as OpenCSP's histogram threshold does.
    """
    diff = np.clip((light.astype(np.int64) - dark) / COUNT_SCALE, 0, 255).astype(np.uint8)
    level, _ = cv2.threshold(diff, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    return float(level) * COUNT_SCALE


def facet_from_opencsp(path: Path, focal_length_m: float, name: str = "opencsp-facet") -> FacetDesign:
    """OpenCSP facet JSON (corners and centroid) as our FacetDesign (outline counter-clockwise): the plain-data
    reader (:func:`sofast_station.ensemble.facet_from_opencsp`), a heliostat facet above f = 20 m."""
    return read_facet(path, focal_length_m, name=name, kind="heliostat" if focal_length_m > 20 else "dish")


def nominal_pose(camera: CameraIntrinsics, mask: np.ndarray, screen_centre_cam: np.ndarray,
                 distance_m: float) -> Pose:
    """Where the facet is expected, for ordering its corners and starting the pose search (OpenCSP has no
    fixture): facing camera and screen at the mask's centroid, at the measured distance from the screen
    centre (:func:`~sofast_station.measure.pose.pose_facing`, as OpenCSP places a facet before its corners
    refine it)."""
    try:
        return pose_facing(camera, mask_centroid_px(mask)[0], screen_centre_cam, distance_m)
    except GeometryError as exc:
        raise ConfigError(f"{exc} (OpenCSP measurement's dist_optic_screen)") from None


#: Standard uncertainties (k = 1) of an OpenCSP/SOFAST setup's inputs where the camera matrix does not set
#: them (docs/opencsp.md, "Uncertainty of an imported measurement"): key -> (value, why).
OPENCSP_UNCERTAINTY = {
    "distance_mm": (1.0, "dist_optic_screen by tape or laser to a projection screen's marked centre over ~10 m"),
    "camera_distortion": ((2e-3, 1e-2, 5e-5, 5e-5, 0.0), "the station's (a chessboard calibration of a low-"
                          "distortion lens; dimensionless, so the same at any resolution)"),
    "screen_rotation_mrad": ((0.5, 0.5, 0.5), "OpenCSP's camera-position calibration against the screen's "
                             "photogrammetric markers"),
    "screen_translation_mm": ((1.0, 1.0, 1.0), "the same calibration, over a screen several metres wide"),
    "screen_pitch_relative": (2e-4, "scale of the photogrammetric screen-shape measurement per axis (scale "
                              "bars to 5e-5, the bundle's scale over an 8.7 m screen about 1.5e-4)"),
    "fixture_rotation_mrad": ((0.0, 0.0, 0.0), "none: OpenCSP has no fixture"),
    "fixture_translation_mm": ((0.0, 0.0, 0.0), "none: OpenCSP has no fixture"),
}
#: The camera's focal lengths and principal point: relative to the focal length in pixels, so that the same
#: calibration holds at the native and at a resampled resolution (a full-resolution calibration of the
#: NSTTF camera, f about 5,500 px: about 1 px for f, 1.6 px for the principal point).
OPENCSP_CAMERA_FOCAL_RELATIVE = 2e-4
OPENCSP_CAMERA_PRINCIPAL_RELATIVE = 3e-4


def opencsp_input_uncertainties(camera: CameraIntrinsics, table: dict | None = None,
                                where: str = "--uncertainty") -> InputUncertainties:
    """The input uncertainties of an OpenCSP measurement: :data:`OPENCSP_UNCERTAINTY`, the camera's from
    its focal length, the rest the station's defaults (display response from the capture's own evidence,
    corner and frame brightness from the capture); *table* (station.toml's ``[uncertainty]`` keys,
    validated) overrides any of them."""
    f_px = 0.5 * float(camera.matrix[0, 0] + camera.matrix[1, 1])
    values = {k: v for k, (v, _) in OPENCSP_UNCERTAINTY.items()}
    values.update(camera_focal_px=OPENCSP_CAMERA_FOCAL_RELATIVE * f_px,
                  camera_principal_px=OPENCSP_CAMERA_PRINCIPAL_RELATIVE * f_px)
    out = replace(InputUncertainties(), **values)
    if table:
        given = InputUncertainties.from_table(table, where)
        out = replace(out, **{k: getattr(given, k) for k in table})
    return out


def _uncertainty_assumptions(u: InputUncertainties) -> tuple:
    """The input uncertainties as lines of the "assumed" list."""
    def fmt(v):
        return ", ".join(f"{x:g}" for x in v) if isinstance(v, tuple) else f"{v:.3g}"

    return (f"input standard uncertainties (k = 1; docs/opencsp.md): distance {fmt(u.distance_mm)} mm, camera f "
            f"{fmt(u.camera_focal_px)} px and principal point {fmt(u.camera_principal_px)} px "
            f"({OPENCSP_CAMERA_FOCAL_RELATIVE:g} and {OPENCSP_CAMERA_PRINCIPAL_RELATIVE:g} of f), "
            f"distortion {fmt(u.camera_distortion)}, screen rotation {fmt(u.screen_rotation_mrad)} mrad and "
            f"translation {fmt(u.screen_translation_mm)} mm, screen-shape scale "
            f"{fmt(u.screen_pitch_relative)} per axis; display response, frame brightness, corners and intensity noise "
            "from the capture itself",
            "left out of the uncertainty: the fixture pose (OpenCSP has none; the nominal pose is a guess from the "
            "mask), so placement and optical tilt are not reported; the screen shape's node-by-node measurement "
            "errors (only its scale and pose are inputs)")


@dataclass
class OpenCspMeasurement:
    """An OpenCSP measurement converted to our inputs."""

    name: str
    date: str
    frames: np.ndarray
    fringes: FringeSet
    geometry: StationGeometry
    screen: InterpolatedScreen
    design: FacetDesign
    distance_m: float
    settings: AnalysisSettings
    #: What the import assumed or derived where OpenCSP's files say nothing, in words (printed by
    #: ``import-opencsp``).
    assumptions: tuple = ()
    #: The inputs' standard uncertainties for this setup (:func:`opencsp_input_uncertainties`).
    uncertainty: InputUncertainties | None = None
    #: A multi-facet measurement's ensemble (OpenCSP's DefinitionEnsemble); None for one facet.
    ensemble: object | None = None

    def analyse_heliostat(self, uncertainty: InputUncertainties | None = None, sensitivity_cache: dict | None = None):
        """Our analysis of a multi-facet measurement (:func:`~sofast_station.measure.heliostat.analyse_heliostat`):
        every facet's figures and canting error."""
        if self.ensemble is None:
            raise ConfigError(f"measurement {self.name} is a single facet's: it has no ensemble definition")
        # OpenCSP has no fixture: the nominal pose is the mask's centre, so each facet's window is wider. Its
        # captures are downsampled 8x, where a heliostat's gaps are not resolved (its facets are told apart by
        # the outer outline: split_joined) and a small facet holds a few hundred pixels, not thousands.
        return analyse_heliostat(self.frames, self.fringes, self.geometry, self.ensemble, self.distance_m,
                                 replace(self.settings, min_valid_px=100),
                                 HeliostatSettings(window_margin=0.15, window_margin_px=20, split_joined=True),
                                 screen=self.screen, rays_cam=ray_table(self.geometry.camera),
                                 uncertainty=uncertainty, sensitivity_cache=sensitivity_cache)

    def analyse(self, robust: bool = False, pixel_mask: np.ndarray | None = None,
                uncertainty: InputUncertainties | None = None, sensitivity_cache: dict | None = None,
                **overrides) -> Analysis:
        """Our analysis of the measurement (``design``, ``distance_m`` may be overridden).

        With *uncertainty* (e.g. :attr:`uncertainty`) every figure also carries its expanded uncertainty
        (k = 2). The sensitivities are kept in *sensitivity_cache* (the caller's, per geometry, recipe and
        inputs) so that analysing again pays only the per-capture part. An OpenCSP measurement is one
        capture: its frame-to-frame brightness is its own, never pooled with analyses of itself again
        (which would count the same sets twice), so only the sensitivities go to and from the cache.
        """
        settings = replace(self.settings, robust_fit=robust)
        local = None if uncertainty is None else _SensitivitiesOnly(sensitivity_cache)
        return analyse(self.frames, self.fringes, self.geometry, overrides.get("design", self.design),
                       overrides.get("distance_m", self.distance_m), settings, screen=self.screen,
                       pixel_mask=pixel_mask, rays_cam=ray_table(self.geometry.camera), uncertainty=uncertainty,
                       sensitivity_cache=local)


def _per_recipe(value) -> bool:
    """Whether a cached *value* is the same for every capture of a recipe (:class:`_SensitivitiesOnly`)."""
    return isinstance(value, Sensitivities) or bool(getattr(type(value), "per_recipe", False))


class _SensitivitiesOnly(dict):
    """One analysis's cache: the sensitivities, and anything else the same for every capture of a recipe (a
    value whose type says ``per_recipe``: a fixed pattern's predicted grid picture,
    :class:`~sofast_station.measure.fixed.GridPrediction`), are read from and written to the caller's *shared*
    cache (a dict, or a :class:`~sofast_station.cache.SensitivityStore` that also keeps the sensitivities on
    disk); anything else the analysis keeps (the frame-brightness pool) stays with this analysis."""

    def __init__(self, shared: dict | None):
        super().__init__()
        self._shared = shared

    def get(self, key, default=None):
        if dict.__contains__(self, key):
            return dict.__getitem__(self, key)
        found = None if self._shared is None else self._shared.get(key)
        if _per_recipe(found):
            dict.__setitem__(self, key, found)
            return found
        return default

    def __setitem__(self, key, value) -> None:
        dict.__setitem__(self, key, value)
        if self._shared is not None and _per_recipe(value):
            self._shared[key] = value


def read_opencsp(measurement: Path, camera: Path, display: Path, orientation: Path, calibration: Path,
                 facet: Path | None, focal_length_m: float = 100.0, uncertainty: dict | None = None,
                 ensemble: Path | None = None, cache=None, corners_m: np.ndarray | None = None) -> OpenCspMeasurement:
    """Read the six OpenCSP files of one facet measurement (see the module docstring); *uncertainty* (an
    ``[uncertainty]`` table) overrides input uncertainties (:func:`opencsp_input_uncertainties`). *cache*
    (a :class:`~sofast_station.cache.DiskCache`) keeps the display grid's triangulation between runs.

    With *ensemble* (OpenCSP's ensemble definition JSON) the measurement is a multi-facet one: every facet
    has the design of *facet*, placed and canted as the ensemble says; the measure point
    (``v_measure_point_facet``, in ensemble coordinates for an ensemble) picks the facet the distance was
    taken to (:meth:`OpenCspMeasurement.analyse_heliostat`).

    Without *facet* (None) the mirror's outline is unknown (OpenCSP's "undefined" optic): no corners are
    used, its frame is placed at the lit region's centroid (:func:`undefined_mirror_design`); *corners_m*
    ((n, 2) metres, as OpenCSP lists them) gives the facet's corners instead of a facet JSON (a processed
    result's own ``DefinitionFacet``)."""
    measurement, camera, display, orientation, calibration = (
        Path(p) for p in (measurement, camera, display, orientation, calibration))
    facet = None if facet is None else Path(facet)
    # the small files first, so that a wrong one is named before the frames are read
    cam = camera_from_opencsp(camera)
    g = "MeasurementSofastFringe/"
    periods_x = [float(v) for v in np.ravel(_read(measurement, g + "fringe_periods_x"))]
    periods_y = [float(v) for v in np.ravel(_read(measurement, g + "fringe_periods_y"))]
    cal_type = _read(calibration, "ImageCalibration/calibration_type")
    if cal_type not in ("ImageCalibrationScaling", "ImageCalibrationGlobal"):
        raise ConfigError(f"{calibration}: unsupported image calibration {cal_type!r}")
    counts = count_table(_read(calibration, "ImageCalibration/camera_values"),
                         _read(calibration, "ImageCalibration/display_values"))
    uv, pts = screen_nodes(display)
    to_cam = screen_to_camera(orientation)
    if facet is not None:
        facet_from_opencsp(facet, focal_length_m)
    if ensemble is not None:
        ensemble_from_opencsp(ensemble, facet, focal_length_m)
    # C order (frame by frame): gathering the facet's pixels from OpenCSP's pixel-major layout is ten times
    # slower.
    frames = read_frames(measurement, counts, len(periods_y), len(periods_x), cam.shape, camera)

    split = load_screen_split(cache, uv)
    screen = InterpolatedScreen(1.0, 1.0, uv, pts, to_cam, v_from_top=True, split=split)
    if split is None:
        save_screen_split(cache, uv, screen.split)
    distance = float(_read(measurement, g + "dist_optic_screen"))
    mp = np.array(_read(measurement, g + "v_measure_point_facet"), np.float64).ravel()
    threshold = mask_threshold(frames[0], frames[1])
    mask = (frames[1].astype(np.int64) - frames[0]) > threshold
    fringes = FringeSet(tuple(periods_x), tuple(periods_y))
    frames, fringes, dropped = drop_stale_sets(frames, fringes, mask)
    name = str(_read(measurement, g + "name"))
    if facet is not None:
        design = facet_from_opencsp(facet, focal_length_m, name=name)
    elif corners_m is not None:
        design = facet_from_corners(corners_m, focal_length_m, name=name)
    else:
        design = undefined_mirror_design(cam, mask, distance, focal_length_m, name=name)
    ens = None
    if ensemble is not None:
        ens = ensemble_with_measure_point(Path(ensemble), facet, focal_length_m, mp)
        design = ens.layout_design()
    elif np.any(mp[:2] != design.measure_point_m) and design.outline_known:
        design = replace(design, measure_point_m=mp[:2].copy())
    nominal = nominal_pose(cam, mask, screen.centre_camera(), distance)
    geometry = StationGeometry(cam, ScreenSpec(1000, 1000, 0.001), to_cam, nominal)
    settings = AnalysisSettings(mask_threshold_dn=threshold, min_modulation_dn=4.0 * COUNT_SCALE,
                                max_hole_px=200, corner_tolerance_px=25.0, max_corner_rms_px=2.0, edge_window_px=3)
    log.info("OpenCSP measurement %s: %d x %d px, periods x %s, y %s, distance %.3f m", design.name,
             cam.width_px, cam.height_px, periods_x, periods_y, distance)
    where = (f"alignment point {design.alignment_point_m.tolist()} m and measure point "
             f"{design.measure_point_m.tolist()} m (facet frame; the measure point from the measurement)"
             if design.outline_known else
             "a mirror of unknown outline (no facet definition): its frame is placed at the lit region's centroid, "
             "at the measured distance, facing camera and screen; measured and aligned there (OpenCSP's undefined "
             "optic); placement and boresight are not measured (no corners)")
    assumptions = (
        f"design focal length {focal_length_m:g} m (OpenCSP's facet file has none; --focal-length sets it): the "
        "boresight aligns the fitted normal with this design's at the alignment point",
        where,
        f"facet pixels: white - dark above {threshold:.0f} counts (x{COUNT_SCALE} after OpenCSP's response "
        "calibration), holes up to 200 px filled",
        f"nominal facet pose: the mask's centre at the measured distance {distance:.4f} m (OpenCSP has no fixture)",
        "display: OpenCSP's measured 2-D grid of screen points (no flat screen or pixel pitch assumed, so "
        "non-square display pixels need nothing more)",
        "corners: matched within 25 px of the nominal pose, 2 px RMS allowed, 3 px edge window"
        if design.outline_known else "corners: none (unknown outline)",
    )
    assumptions += tuple(dropped)
    inputs = opencsp_input_uncertainties(cam, uncertainty)
    if ens is not None:
        to = (f"facet {ens.facets[ens.measure_facet].label}" if ens.measure_point_xyz_m is None else
              f"the point {[round(v, 4) for v in ens.measure_point_xyz_m.tolist()]} m between the facets (ensemble "
              "coordinates)")
        assumptions += (f"ensemble {Path(ensemble).name}: {ens.n_facets} facets of {Path(facet).name}, the distance "
                        f"taken to {to}",)
    return OpenCspMeasurement(design.name, str(_read(measurement, g + "date")), frames, fringes, geometry, screen,
                              design, distance,
                              settings, assumptions + _uncertainty_assumptions(inputs), inputs, ens)


def drop_stale_sets(frames: np.ndarray, fringes: FringeSet, mask: np.ndarray) -> tuple[np.ndarray, FringeSet, list]:
    """*frames* and *fringes* without the middle fringe sets with a frame captured before the display had
    changed (:func:`~sofast_station.measure.checks.stale_frames`; OpenCSP does not check, and uses the set).
    The station refuses such a capture (the set fails the four-step check at most of the facet); an
    imported one cannot be taken again, and without the set the coarser and finer sets still unwrap (a pixel
    whose phases then disagree is dropped and counted, as ever). The first and last sets of an axis are kept:
    the analysis refuses the capture if one of them fails. Returns the frames, the fringes and a sentence
    per dropped set."""
    bad = stale_frames(frames, fringes, mask)
    if not bad:
        return frames, fringes, []
    keep = list(range(2))
    periods = {"x": [], "y": []}
    said = []
    for axis, slices in fringes.slices().items():
        ps = list(getattr(fringes, f"periods_{axis}"))
        for j, (p, sl) in enumerate(zip(ps, slices)):
            name = f"{axis} p={p:g}"
            if name in bad and 0 < j < len(ps) - 1:
                k, r = bad[name]
                said.append(f"the {name} fringe set's frame {k} repeats frame {(k - 1) % 4} (it differs by {r:.2f} of "
                            "the set's other steps: captured before the display had changed): the set is left "
                            f"out, and the {axis} phases unwrap from p={ps[j - 1]:g} to p={ps[j + 1]:g} directly "
                            "(OpenCSP uses the set as it is)")
                continue
            periods[axis].append(p)
            keep.extend(range(sl.start, sl.stop))
    if not said:
        return frames, fringes, []
    out = FringeSet(tuple(periods["x"]), tuple(periods["y"]), phase_steps=fringes.phase_steps)
    log.warning("%s", "; ".join(said))
    return np.ascontiguousarray(frames[keep]), out, said


def facet_from_corners(corners_m: np.ndarray, focal_length_m: float, name: str = "opencsp-facet") -> FacetDesign:
    """A facet design from OpenCSP's corner list ((n, 2) metres, as a ``DefinitionFacet`` lists them), measured
    and aligned at the origin: what a processed result's own facet definition gives."""
    corners = np.asarray(corners_m, np.float64)
    x, y = corners[:, 0], corners[:, 1]
    if float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0:
        corners = corners[::-1]
    return FacetDesign(name=name, kind="heliostat" if focal_length_m > 20 else "dish", focal_length_m=focal_length_m,
                       outline_m=corners, measure_point_m=[0.0, 0.0], alignment_point_m=[0.0, 0.0])


def undefined_mirror_design(camera: CameraIntrinsics, mask: np.ndarray, distance_m: float, focal_length_m: float,
                            name: str = "opencsp-mirror") -> FacetDesign:
    """The design of a mirror of unknown outline (``outline_known`` False): its expected extent, a square about
    its middle 1.5 times the lit region's larger image extent at the measured distance (only what the
    region's checks expect of its size), and the design focal length; measured and aligned at its middle."""
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        raise ConfigError("the measurement's mask images show no lit mirror (white - dark is nowhere above the "
                          "threshold): is it the right measurement?")
    f_px = 0.5 * float(camera.matrix[0, 0] + camera.matrix[1, 1])
    half = 0.75 * max(np.ptp(cols) + 1, np.ptp(rows) + 1) * distance_m / f_px
    outline = np.array([[half, -half], [half, half], [-half, half], [-half, -half]])
    return FacetDesign(name=name, kind="heliostat" if focal_length_m > 20 else "dish", focal_length_m=focal_length_m,
                       outline_m=outline, measure_point_m=[0.0, 0.0], alignment_point_m=[0.0, 0.0],
                       outline_known=False)


def ensemble_with_measure_point(path: Path, facet: Path, focal_length_m: float, measure_point: np.ndarray):
    """OpenCSP's ensemble definition *path*, every facet of the facet definition *facet*, the distance taken
    to *measure_point* (ensemble coordinates, as OpenCSP takes it): on a facet, that facet's design surface
    there; in a gap between facets (a heliostat's centre often is), the point itself
    (:meth:`~sofast_station.ensemble.EnsembleDesign.with_measure_point`)."""
    ens = ensemble_from_opencsp(path, facet, focal_length_m, name=Path(path).stem)
    p = np.asarray(measure_point, np.float64).ravel()
    try:
        on_facet = ens.with_measure_point(p[:2])
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc} (the measurement's v_measure_point_facet)") from None
    if on_facet.measure_point_xyz_m is None:
        return on_facet
    return ens.with_measure_point(p[:2], float(p[2]) if p.size > 2 else 0.0)


def export_opencsp(folder: Path, frames: np.ndarray, fringes: FringeSet, geometry: StationGeometry,
                   distance_m: float, measure_point_m, design: FacetDesign, ensemble=None, name: str = "measurement",
                   date: str = "") -> dict[str, Path]:
    """Write a capture as OpenCSP's files (what :func:`read_opencsp` reads; a twin capture to test it with, or
    a station capture for OpenCSP): the measurement (mask and fringe images, y sets first; periods;
    the distance and measure point: ensemble coordinates for an *ensemble*), the camera, a rectangular display
    of the screen's size, the spatial orientation (OpenCSP's screen frame has y down the screen and z into it:
    ours turned half a turn about x), an identity image calibration, the facet definition (corners clockwise
    seen from the mirror) and, with *ensemble*, its ensemble definition. Returns the paths, keyed as
    :func:`read_opencsp`'s arguments."""
    # lazy: scipy.spatial.transform costs ~300 ms CPU; only writing OpenCSP's files needs it, no reader does
    from scipy.spatial.transform import Rotation

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {"measurement": folder / ("measurement_ensemble.h5" if ensemble is not None else "measurement_facet.h5"),
             "camera": folder / "camera.h5", "display": folder / "display_rectangular.h5",
             "orientation": folder / "spatial_orientation.h5", "calibration": folder / "image_calibration.h5",
             "facet": folder / "facet.json"}
    n_x, n_y = 4 * len(fringes.periods_x), 4 * len(fringes.periods_y)
    if frames.shape[0] != 2 + n_x + n_y:
        raise ConfigError(f"export_opencsp: {frames.shape[0]} frames, expected {2 + n_x + n_y} for these fringes")
    fringe = np.concatenate([frames[2 + n_x:], frames[2:2 + n_x]])          # OpenCSP: y sets first
    g = "MeasurementSofastFringe/"
    with h5py.File(paths["measurement"], "w") as h:
        h[g + "mask_images"] = np.moveaxis(frames[:2], 0, 2)
        h[g + "fringe_images"] = np.moveaxis(fringe, 0, 2)
        h[g + "fringe_periods_x"] = np.asarray(fringes.periods_x, np.float64)
        h[g + "fringe_periods_y"] = np.asarray(fringes.periods_y, np.float64)
        h[g + "dist_optic_screen"] = float(distance_m)
        h[g + "v_measure_point_facet"] = np.asarray(measure_point_m, np.float64).reshape(3)
        h[g + "name"] = name
        h[g + "date"] = date
    cam = geometry.camera
    with h5py.File(paths["camera"], "w") as h:
        h["Camera/intrinsic_mat"] = np.asarray(cam.matrix, np.float64)
        h["Camera/image_shape_xy"] = np.array([cam.width_px, cam.height_px])
        h["Camera/distortion_coef"] = np.asarray(cam.distortion, np.float64)
    with h5py.File(paths["display"], "w") as h:
        h["DisplayShape/screen_model"] = "rectangular2D"
        h["DisplayShape/screen_x"] = float(geometry.screen.width_m)
        h["DisplayShape/screen_y"] = float(geometry.screen.height_m)
    flip = np.diag([1.0, -1.0, -1.0])                 # OpenCSP's screen frame in ours
    r_screen_cam = geometry.screen_to_camera.rotation @ flip
    with h5py.File(paths["orientation"], "w") as h:
        h["SpatialOrientation/r_cam_screen"] = Rotation.from_matrix(r_screen_cam.T).as_rotvec()
        h["SpatialOrientation/v_cam_screen_cam"] = np.asarray(geometry.screen_to_camera.translation, np.float64)
    with h5py.File(paths["calibration"], "w") as h:
        h["ImageCalibration/calibration_type"] = "ImageCalibrationScaling"
        h["ImageCalibration/camera_values"] = np.arange(256, dtype=np.float64)
        h["ImageCalibration/display_values"] = np.arange(256, dtype=np.float64)
    corners = design.outline_m[::-1]                   # clockwise seen from the mirror, as OpenCSP lists them
    c = design.measure_point_m
    paths["facet"].write_text(json.dumps({
        "v_facet_corners": {"x": corners[:, 0].tolist(), "y": corners[:, 1].tolist(), "z": [0.0] * len(corners)},
        "v_centroid_facet": {"x": [float(c[0])], "y": [float(c[1])], "z": [0.0]}}, indent=1))
    if ensemble is not None:
        paths["ensemble"] = folder / "ensemble.json"
        paths["ensemble"].write_text(json.dumps(ensemble_to_opencsp(ensemble), indent=1))
    return paths


def upsample_test_data(src: Path, dst: Path, scale: int) -> dict[str, Path]:
    """The single-facet files of OpenCSP's test data *src* copied to *dst* (its layout), the measurement's
    frames and the camera *scale* times larger: a full-resolution capture made from the real one (what
    OpenCSP's own camera took before it was downsampled 8x). Returns the copies' paths (as
    :func:`opencsp_test_data_paths`).

    Frames are resized bilinearly (OpenCV's pixel-centre convention: destination pixel x samples source
    position (x + 1/2)/scale - 1/2), so the camera matrix scales as f' = scale f, c' = scale c +
    (scale - 1)/2; the distortion coefficients (normalised coordinates) are unchanged.
    """
    src_paths, dst_paths = opencsp_test_data_paths(Path(src)), opencsp_test_data_paths(Path(dst))
    for key, path in src_paths.items():
        dst_paths[key].parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, dst_paths[key])

    def resize(stack):
        h, w, n = stack.shape
        return np.stack([cv2.resize(stack[:, :, k], (w * scale, h * scale), interpolation=cv2.INTER_LINEAR)
                         for k in range(n)], axis=2)

    def replace_in(h, key, value):
        del h[key]
        h[key] = value

    with h5py.File(dst_paths["measurement"], "r+") as h:
        g = "MeasurementSofastFringe/"
        for key in ("fringe_images", "mask_images"):
            replace_in(h, g + key, resize(np.asarray(h[g + key])))
    with h5py.File(dst_paths["camera"], "r+") as h:
        k = np.array(h["Camera/intrinsic_mat"], np.float64)
        # OpenCSP's downsampled camera keeps K[2,2] = 1/8, which OpenCV ignores: fx, fy, cx, cy are pixels
        # as they stand, so the half-pixel shift is (scale - 1)/2 pixels, not scaled by K[2,2]
        k[0, 0] *= scale
        k[1, 1] *= scale
        k[0, 1] *= scale
        k[0, 2] = scale * k[0, 2] + 0.5 * (scale - 1)
        k[1, 2] = scale * k[1, 2] + 0.5 * (scale - 1)
        replace_in(h, "Camera/intrinsic_mat", k)
        shape = np.array(h["Camera/image_shape_xy"])
        replace_in(h, "Camera/image_shape_xy", (shape * scale).astype(shape.dtype))
    return dst_paths

