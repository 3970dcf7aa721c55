"""The camera's position from one photograph of ArUco markers whose corners were surveyed
(``sofast-station calibrate camera-position``; OpenCSP's ``CalibrationCameraPosition``).

The station's camera photographs markers fixed around the screen, whose corners are known in the markers'
frame (the screen frame when the survey was made in it). The routine finds the markers
(:func:`~sofast_station.measure.markers.detect_markers`: OpenCV's detector, then each marker's four edges
located to a fraction of a pixel), pairs them with the table, and solves the camera's pose with its
covariance (:func:`~sofast_station.measure.markers.solve_camera_pose`). A marker whose corners fit far worse
than the others' (moved since the survey, or misread) is left out and named. The record holds the pose in
OpenCV's form (``rvec``, ``tvec``: markers' frame -> camera), in OpenCSP's (its ``tvec`` is R^T t, the camera
to the frame's origin in the frame's axes), the camera's centre in the markers' frame, and every figure's
expanded uncertainty (k = 2).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry import CameraIntrinsics
from ..gum import value_and_u
from ..measure.markers import (
    DEFAULT_DICTIONARY,
    MarkerTable,
    PoseFit,
    camera_position,
    detect_markers,
    drop_worst_marker,
    marker_correspondences,
    opencsp_rvec_tvec,
    solve_camera_pose,
)
from .errors import CalibrationError
from .photo_inputs import check_photo_size
from .store import read_record, write_record

log = logging.getLogger(__name__)

SCHEMA = 1
KIND = "cameraposition"
#: Reprojection RMS of the marker corners (px): a warning above the first, no record above the second (the
#: table does not describe what the photograph shows: another frame, another corner order, markers moved).
RMS_WARN_PX, RMS_REFUSE_PX = 1.0, 5.0
#: Fewest markers for a record; with fewer, a pose rests on one or two squares' shapes.
MIN_MARKERS = 3


@dataclass
class CameraPosition:
    """What :func:`calibrate_camera_position` found.

    Attributes
    ----------
    image : str
        The photograph.
    fit : PoseFit
        The pose (markers' frame -> camera) and its covariance.
    rvec, tvec_opencsp : (3,) arrays
        OpenCSP's rvec (radians) and tvec (metres), ...
    cov_opencsp : (6, 6) array
        ... and their covariance.
    position_m : (3,) array
        The camera's centre in the markers' frame, metres, ...
    cov_position : (3, 3) array
        ... and its covariance.
    markers_used, markers_unlisted, markers_dropped : list of int
    marker_scale : float
        The markers' mean size in the photograph over their size projected from the table (1 when the
        table's corners are where the photograph's edges are).
    verdict : str
        ``pass`` or ``warn``.
    reasons : list of str
    """

    image: str
    camera: CameraIntrinsics
    fit: PoseFit
    rvec: np.ndarray
    tvec_opencsp: np.ndarray
    cov_opencsp: np.ndarray
    position_m: np.ndarray
    cov_position: np.ndarray
    markers_used: list
    markers_unlisted: list
    markers_dropped: list
    marker_scale: float
    refine: str
    verdict: str = "pass"
    reasons: list = field(default_factory=list)

    def to_dict(self) -> dict:
        u = lambda cov: (2.0 * np.sqrt(np.clip(np.diag(cov), 0.0, None))).tolist()   # noqa: E731
        return {"image": self.image, "camera": self.camera.to_dict(),
                "rvec": self.fit.rvec.tolist(), "tvec": self.fit.tvec.tolist(), "rvec_tvec_U": u(self.fit.covariance),
                "covariance_rvec_tvec": self.fit.covariance.tolist(),
                "opencsp": {"rvec": self.rvec.tolist(), "tvec": self.tvec_opencsp.tolist(), "U": u(self.cov_opencsp)},
                "camera_position_m": self.position_m.tolist(), "camera_position_m_U": u(self.cov_position), "k": 2,
                "world_to_camera": self.fit.world_to_camera.to_dict(),
                "reprojection_rms_px": self.fit.rms_px, "corner_sigma_px": self.fit.sigma_px,
                "residuals_px": self.fit.residuals_px.tolist(), "markers_used": self.markers_used,
                "markers_unlisted": self.markers_unlisted, "markers_dropped": self.markers_dropped,
                "marker_scale": self.marker_scale, "corner_refinement": self.refine,
                "verdict": self.verdict, "reasons": self.reasons}


def _marker_scale(image_px: np.ndarray, projected_px: np.ndarray) -> float:
    """Mean distance of the corners from their marker's centre, seen over projected."""
    seen = image_px.reshape(-1, 4, 2)
    proj = projected_px.reshape(-1, 4, 2)
    d_seen = np.linalg.norm(seen - seen.mean(axis=1, keepdims=True), axis=2).mean()
    d_proj = np.linalg.norm(proj - proj.mean(axis=1, keepdims=True), axis=2).mean()
    return float(d_seen / d_proj)


def calibrate_camera_position(image: np.ndarray, name: str, camera: CameraIntrinsics, camera_name: str,
                              table: MarkerTable, *, intrinsics_std: np.ndarray | None = None,
                              dictionary: str = DEFAULT_DICTIONARY, refine: str = "edges",
                              min_markers: int = MIN_MARKERS) -> CameraPosition:
    """The camera's pose from one photograph of surveyed ArUco markers.

    Parameters
    ----------
    image : (H, W) uint8 array
        The photograph, of the camera's size.
    name, camera_name : str
        For messages: the photograph's and the camera calibration's names.
    camera : CameraIntrinsics
    table : MarkerTable
        The markers' surveyed corners.
    intrinsics_std : (9,) array, optional
        The camera's intrinsics' standard deviations (a camera record's), propagated into the pose's.
    dictionary, refine : str
        ArUco dictionary; corner refinement (:data:`~sofast_station.measure.markers.REFINEMENTS`).
    min_markers : int
        Fewest markers of the table that must be seen.

    Raises
    ------
    CalibrationError
        Wrong image size, no or too few markers, a pose the markers do not determine, or a reprojection RMS
        above :data:`RMS_REFUSE_PX`.
    """
    check_photo_size(image, camera, name, camera_name)
    try:
        found = detect_markers(image, dictionary, refine, camera=camera)
    except ValueError as exc:
        raise CalibrationError(f"{name}: {exc}") from None
    if not found:
        raise CalibrationError(f"no ArUco markers of {dictionary} found in {name}: are they in the picture, in focus "
                               "and not saturated, and is it their dictionary (--dictionary)?")
    ids, image_px, world_m, unlisted = marker_correspondences(found, table)
    log.info("%s: %d marker(s) found (%s), %d in the table", name, len(found), sorted(found), len(ids))
    if len(ids) < min_markers:
        raise CalibrationError(f"too few markers in {name}: found {sorted(found)}, of which {ids.tolist()} are in the "
                               f"marker table; {min_markers} or more are needed (is it the right table?)")
    dropped: list[int] = []
    while True:
        try:
            fit = solve_camera_pose(camera, world_m, image_px, intrinsics_std)
        except ValueError as exc:
            raise CalibrationError(f"{name}: {exc}") from None
        if len(ids) <= min_markers:
            break
        worst = drop_worst_marker(ids, fit.residuals_px)
        if worst is None:
            break
        keep = np.repeat(ids != worst, 4)
        ids, image_px, world_m = ids[ids != worst], image_px[keep], world_m[keep]
        dropped.append(worst)
        log.warning("%s: marker %d fits far worse than the others (moved since the survey, or misread): left out",
                    name, worst)
    if fit.rms_px > RMS_REFUSE_PX:
        raise CalibrationError(f"the markers in {name} do not fit the table: reprojection RMS {fit.rms_px:.1f} px "
                               f"(over {RMS_REFUSE_PX:g} px): is the table for these markers, in one frame, corners "
                               "in OpenCV's order?")
    rvec, tvec, cov = opencsp_rvec_tvec(fit)
    position, cov_position = camera_position(fit)
    scale = _marker_scale(image_px, image_px + fit.residuals_px)
    result = CameraPosition(name, camera, fit, rvec, tvec, cov, position, cov_position, ids.tolist(), unlisted, dropped,
                            scale, refine)
    if fit.rms_px > RMS_WARN_PX:
        result.reasons.append(f"reprojection RMS {fit.rms_px:.2f} px is over {RMS_WARN_PX:g} px: check the survey of "
                              "the markers and the camera's calibration")
    if abs(scale - 1.0) > 0.005:
        result.reasons.append(f"the markers look {100 * (scale - 1):+.2f} % in size against the table: were its "
                              "corners surveyed inside (or outside) the markers' printed edges, e.g. on whole pixels? "
                              "That biases the pose, most in depth: check the survey")
    if dropped:
        result.reasons.append(f"marker(s) {dropped} left out: they fit far worse than the others (moved since the "
                              "survey, or misread)")
    if intrinsics_std is None:
        result.reasons.append("the camera's intrinsics carry no standard deviations: U covers the corners' noise only")
    result.verdict = "warn" if any("left out" in r or "RMS" in r for r in result.reasons) else "pass"
    return result


def save_camera_position(data_dir: str | Path, result: CameraPosition, source: str, inputs: dict,
                         station: dict | None = None) -> Path:
    """Write a ``cameraposition`` record under ``data_dir/calibration/cameraposition/`` (*station*: the identity
    of the station it is made on); returns its path."""
    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": KIND, "record_id": record_id, "created": created, "source": source,
                "inputs": inputs, **result.to_dict()}

    path, _ = write_record(data_dir, KIND, build, station=station)
    return path


def load_camera_position(path: str | Path) -> dict:
    """A ``cameraposition`` record as plain data (checked: kind, schema, the pose's numbers); ConfigError
    naming the file otherwise."""
    d = read_record(path, KIND, SCHEMA, "camera position record", "rerun 'sofast-station calibrate camera-position'")
    try:
        for key in ("rvec", "tvec", "camera_position_m", "camera_position_m_U"):
            values = np.asarray(d[key], np.float64)
            if values.shape != (3,) or not np.all(np.isfinite(values)):
                raise ValueError(f"{key} must be 3 finite numbers")
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"camera position record {path} is incomplete or damaged ({exc}); rerun the calibration") \
            from None
    return d


def summary_text(result: CameraPosition, path: Path | None = None) -> str:
    """The command's summary: the pose with its U, OpenCSP's form, the residuals, the verdict."""
    def vec(values, cov, scale=1.0, unit=""):
        u = 2.0 * np.sqrt(np.clip(np.diag(cov), 0.0, None))
        parts = []
        for v, uu in zip(values, u):
            text, utext = value_and_u(float(v), float(uu), scale=scale, sign=True)
            parts.append(f"{text} ± {utext}" if utext else text)
        return "(" + ", ".join(parts) + ")" + unit

    fit = result.fit
    lines = [f"Camera position from {result.image}" + (f"; record {path}" if path else ""),
             f"  markers used: {result.markers_used}"
             + (f"; not in the table: {result.markers_unlisted}" if result.markers_unlisted else "")
             + (f"; left out: {result.markers_dropped}" if result.markers_dropped else ""),
             f"  reprojection RMS {fit.rms_px:.3f} px over {len(fit.residuals_px)} corners (noise "
             f"{fit.sigma_px:.3f} px per coordinate); markers {100 * (result.marker_scale - 1):+.2f} % in size "
             "against the table",
             "  camera centre in the markers' frame "
             f"{vec(result.position_m, result.cov_position, 1000.0, ' mm')} (k=2)",
             f"  rvec {vec(fit.rvec, fit.covariance[:3, :3], 1000.0, ' mrad')}, tvec "
             f"{vec(fit.tvec, fit.covariance[3:, 3:], 1000.0, ' mm')} (OpenCV: markers' frame -> camera)",
             f"  OpenCSP's form: rvec {np.array2string(result.rvec, precision=6)}, tvec "
             f"{np.array2string(result.tvec_opencsp, precision=6)} m"]
    lines += [f"    - {r}" for r in result.reasons]
    lines.append(f"verdict: {result.verdict.upper()}")
    return "\n".join(lines)
