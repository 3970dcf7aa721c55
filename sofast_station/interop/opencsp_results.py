"""OpenCSP's processed SOFAST results (its ``data.h5`` files), read into one record whatever their layout.

OpenCSP's ``ProcessSofastFringe.save_to_hdf`` has written two layouts over its history, and its fixed-pattern
processing a third; the test data has all three:

* **facet** (``data_expected_facet/*.h5``): ``DataSofastCalculation/facet/facet_000/SlopeSolverData/...``,
  the optic's final pose under ``CalculationDataGeometryFacet/SpatialOrientation`` and its inputs under
  ``DataSofastInput/optic_definition/facet_000`` (the facet's corners, the surface's parameters);
* **older** (``data_expected_undefined_mirror/data.h5``): the slope solver's data straight under
  ``DataSofastCalculation/facet/facet_000``, the geometry under ``DataSofastCalculation/geometry`` and the
  surface's parameters under ``DataSofastInput/surface_params``;
* **fixed** (``sofast_fixed/data_expected/calculation_facet.h5``): slopes and surface points only (no mask,
  no coefficients): the dots' points, not pixels.

Each file also carries the inputs it was processed with (``Camera``, ``DisplayShape``, ``ImageCalibration``,
``SpatialOrientation`` at its top level, for the fringe layouts), so a result can be redone with exactly
its own calibration (:func:`result_inputs`).

OpenCSP's conventions, as the files show them (each checked against our own reduction of the same capture
in tests/interop/test_conformance.py): the slope coefficients are (C, 2A, E1) for x and (D, E2, 2B) for y
of a parabolic fit on every ``downsample``-th point, or (C, D) of a plano fit; ``trans_alignment`` turns the
optic's frame onto the aligned one (the fitted normal at the alignment point onto the design's) and the
slopes are in the aligned frame; the optic's final pose is the rotation vector ``r_optic_cam`` (optic ->
camera; stored as its inverse ``r_cam_optic`` in the facet layout) and ``v_cam_optic_cam``. So a slope's
unit normal n (aligned frame) is ``R_optic_cam @ R_align.T @ n`` in the camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np

from ..errors import ConfigError
from .identify import LAYOUTS, describe, result_layout  # noqa: F401  (LAYOUTS: their public place here too)


@dataclass(frozen=True)
class OpenCspResult:
    """What OpenCSP reported for one processed facet (or mirror of unknown outline).

    Attributes
    ----------
    path : Path
    layout : str
        One of :data:`LAYOUTS`.
    optic : str
        ``"facet"`` (a facet definition: corners) or ``"undefined"`` (a mirror of unknown outline).
    surface : str
        ``"parabolic"`` or ``"plano"`` (from the coefficients' shape: OpenCSP's plano results still say
        "parabolic" in their surface parameters).
    robust : bool
        Bisquare-weighted (robust) least squares.
    downsample : int
        The fit used every n-th point (OpenCSP's coefficients are that fit's).
    mask : (rows, columns) bool array or None
        The pixels whose slopes it reports (raster order); None for a fixed-pattern result.
    slopes : (2, N) array
        (s_x, s_y) in the aligned frame.
    points_m : (3, N) array
        Surface points in the aligned frame, metres.
    slope_coefficients : array
        (2, 3) parabolic or (2,) plano, as stored; None for a fixed-pattern result.
    alignment : (3, 3) array or None
        The rotation part of ``trans_alignment``.
    optic_to_camera : (3, 3) array or None
        The optic's final orientation (optic vectors -> camera vectors).
    optic_origin_cam_m : (3,) array or None
        ``v_cam_optic_cam``, metres.
    corners_m : (n, 2) array or None
        The facet definition's corners (x, y), as listed (clockwise seen from the mirror); None undefined.
    distance_m : float or None
        ``measure_point_screen_distance``.
    """

    path: Path
    layout: str
    optic: str
    surface: str
    robust: bool
    downsample: int
    mask: np.ndarray | None
    slopes: np.ndarray
    points_m: np.ndarray
    slope_coefficients: np.ndarray | None
    alignment: np.ndarray | None
    optic_to_camera: np.ndarray | None
    optic_origin_cam_m: np.ndarray | None
    corners_m: np.ndarray | None
    distance_m: float | None

    # -- figures in our terms -------------------------------------------------------------------------------
    @property
    def focal_length_x_m(self) -> float | None:
        """f_x = 1/(4A) of the parabolic fit (None for a plano one or a fixed-pattern result)."""
        sc = self.slope_coefficients
        return None if sc is None or sc.shape != (2, 3) else 1.0 / (2.0 * float(sc[0, 1]))

    @property
    def focal_length_y_m(self) -> float | None:
        sc = self.slope_coefficients
        return None if sc is None or sc.shape != (2, 3) else 1.0 / (2.0 * float(sc[1, 2]))

    @property
    def twist_e1_mrad_per_m(self) -> float | None:
        sc = self.slope_coefficients
        return None if sc is None or sc.shape != (2, 3) else 1000.0 * float(sc[0, 2])

    @property
    def twist_e2_mrad_per_m(self) -> float | None:
        sc = self.slope_coefficients
        return None if sc is None or sc.shape != (2, 3) else 1000.0 * float(sc[1, 1])

    @property
    def twist_mrad_per_m(self) -> float | None:
        e1, e2 = self.twist_e1_mrad_per_m, self.twist_e2_mrad_per_m
        return None if e1 is None else 0.5 * (e1 + e2)

    def tilt_mrad(self) -> dict | None:
        """The alignment's turn of the optic's frame, mrad about x and y (small angles: the rotation's
        off-diagonal terms), as our boresight reports its own: the fitted normal's tilt from the corner
        pose's frame."""
        if self.alignment is None:
            return None
        r = self.alignment
        return {"x": 1000.0 * float(np.arctan2(r[2, 1], r[2, 2])),
                "y": -1000.0 * float(np.arcsin(np.clip(r[2, 0], -1.0, 1.0)))}

    def aligned_to_camera(self) -> np.ndarray | None:
        """The aligned frame's axes in the camera frame (aligned vectors -> camera vectors)."""
        if self.optic_to_camera is None or self.alignment is None:
            return None
        return self.optic_to_camera @ self.alignment.T

    def normals_camera(self) -> np.ndarray | None:
        """(3, N) unit normals of the reported slopes in the camera frame (None without the pose)."""
        to_cam = self.aligned_to_camera()
        if to_cam is None:
            return None
        n = np.vstack([-self.slopes[0], -self.slopes[1], np.ones(self.slopes.shape[1])])
        return to_cam @ (n / np.linalg.norm(n, axis=0))


def _dataset(h, key: str, path: Path, what: str):
    if key not in h:
        raise ConfigError(f"{path}: OpenCSP result without {key!r} ({what}); it may come from a version of "
                          "OpenCSP this reader does not know")
    value = h[key][()]
    return value.decode() if isinstance(value, bytes) else value


def _optional(h, key: str):
    """Dataset *key* of the open file *h*, or None when it has none."""
    return h[key][()] if key in h else None


def _rotation(rotvec) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rotvec, np.float64).reshape(3, 1))[0]


def read_opencsp_result(path: Path) -> OpenCspResult:
    """OpenCSP's processed result *path* of a single facet or mirror (any of :data:`LAYOUTS`).

    Raises
    ------
    ConfigError
        When the file cannot be read, or holds none of the layouts (one line naming the file and what it
        holds instead: :func:`~sofast_station.interop.identify.identify`).
    """
    path = Path(path)
    try:
        h = h5py.File(path, "r")
    except OSError as exc:
        raise ConfigError(f"{path} is not a readable HDF5 file ({exc})") from None
    with h:
        layout = result_layout(h)
        if layout is None:
            raise ConfigError(f"{path} is not an OpenCSP processing result: {describe(path)}")
        f = "DataSofastCalculation/facet/facet_000/"
        if layout == "fixed":
            g = f + "SlopeSolverData/"
            inp = "DataSofastInput/optic_definition/facet_000/"
            corners = h.get(inp + "DefinitionFacet/v_facet_corners")
            return OpenCspResult(
                path, layout, "facet" if corners is not None else "undefined", "parabolic",
                bool(_dataset(h, inp + "ParamsSurface/robust_least_squares", path, "the fit")),
                int(_dataset(h, inp + "ParamsSurface/downsample", path, "the fit")), None,
                np.asarray(_dataset(h, g + "slopes_facet_xy", path, "slopes"), np.float64),
                np.asarray(_dataset(h, g + "v_surf_points_facet", path, "points"), np.float64),
                None, None, None, None,
                None if corners is None else np.asarray(corners[()], np.float64)[:2].T, None)
        if layout == "facet":
            g = f + "SlopeSolverData/"
            geo = f + "CalculationDataGeometryFacet/"
            inp = "DataSofastInput/optic_definition/facet_000/"
            params = inp + "ParamsSurface/"
            mask = _dataset(h, f + "CalculationImageProcessingFacet/mask_processed", path, "the processed mask")
            # (the geometry is OpenCSP's own; a file written by `export surface` has only the surface)
            r_cam_optic = _optional(h, geo + "SpatialOrientation/r_cam_optic")
            optic_to_cam = None if r_cam_optic is None else _rotation(r_cam_optic).T
            origin = _optional(h, geo + "SpatialOrientation/v_cam_optic_cam")
            distance = _optional(h, geo + "measure_point_screen_distance")
            corners_key = inp + "DefinitionFacet/v_facet_corners"
        else:
            g = f
            geo = "DataSofastCalculation/geometry/"
            params = "DataSofastInput/surface_params/facet_000/"
            mask = _dataset(h, "DataSofastCalculation/image_processing/facet_000/mask_processed", path,
                            "the processed mask")
            optic_to_cam = _rotation(_dataset(h, geo + "general/r_optic_cam", path, "the optic's pose"))
            origin = _dataset(h, geo + "general/v_cam_optic_cam", path, "the optic's pose")
            distance = _dataset(h, geo + "facet_000/measure_point_screen_distance", path, "the distance")
            corners_key = "DataSofastInput/optic_definition/facet_000/DefinitionFacet/v_facet_corners"
        corners = np.asarray(h[corners_key][()], np.float64)[:2].T if corners_key in h else None
        coefs = np.asarray(_dataset(h, g + "slope_coefs_facet", path, "the fit"), np.float64)
        surface = "plano" if coefs.shape == (2,) else "parabolic"
        if coefs.shape not in ((2,), (2, 3)):
            raise ConfigError(f"{path}: slope coefficients of shape {coefs.shape}: neither OpenCSP's parabolic "
                              "(2 x 3) nor its plano (2) surface; this reader supports those two")
        alignment = _optional(h, g + "trans_alignment")
        downsample = _optional(h, params + "downsample")
        return OpenCspResult(
            path, layout, "facet" if corners is not None or layout == "facet" else "undefined", surface,
            bool(_dataset(h, params + "robust_least_squares", path, "the fit")),
            1 if downsample is None else int(downsample), np.asarray(mask, bool),
            np.asarray(_dataset(h, g + "slopes_facet_xy", path, "slopes"), np.float64),
            np.asarray(_dataset(h, g + "v_surf_points_facet", path, "points"), np.float64), coefs,
            None if alignment is None else np.asarray(alignment, np.float64)[:3, :3], optic_to_cam,
            None if origin is None else np.asarray(origin, np.float64).ravel(), corners,
            None if distance is None else float(distance))


def result_inputs(path: Path) -> dict[str, Path]:
    """The files of :func:`~sofast_station.interop.opencsp.read_opencsp` that a fringe result *path* holds
    itself (camera, display, orientation, image calibration: the calibration it was processed with)."""
    return {"camera": Path(path), "display": Path(path), "orientation": Path(path), "calibration": Path(path)}
