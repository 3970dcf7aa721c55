"""Read OpenCSP's fixed-pattern (dot grid) measurement (``MeasurementSofastFixed``, with its
``DotLocationsFixedPattern``) and analyse it with the fixed-pattern method (:mod:`sofast_station.measure.fixed`);
the fringe measurement's reader is :mod:`.opencsp`, whose conversions (camera, orientation, facet) this uses."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..facet import FacetDesign
from ..geometry import ScreenSpec, StationGeometry
from ..measure.dots import otsu_level, pattern_background
from ..measure.fixed import FixedSettings, analyse_fixed, dot_screen, reduce_fixed
from ..measure.pipeline import Analysis, AnalysisSettings
from ..measure.screen import InterpolatedScreen
from ..measure.uncertainty import InputUncertainties
from .opencsp import (
    _camera_values,
    _read,
    _SensitivitiesOnly,
    _uncertainty_assumptions,
    camera_from_opencsp,
    facet_from_opencsp,
    nominal_pose,
    opencsp_input_uncertainties,
    screen_to_camera,
    undefined_mirror_design,
)
from .opencsp_calibration import read_dot_locations

log = logging.getLogger(__name__)

#: OpenCSP's ``MeasurementSofastFixed`` group.
FIXED = "MeasurementSofastFixed/"


@dataclass
class OpenCspFixedMeasurement:
    """An OpenCSP fixed-pattern measurement (``MeasurementSofastFixed``: one image of the facet reflecting a dot
    grid, the pixel of the grid's origin, the distance and measure point) with its dot locations
    (``DotLocationsFixedPattern``), converted to the inputs of :func:`~sofast_station.measure.fixed.analyse_fixed`."""

    name: str
    date: str
    image: np.ndarray
    origin_px: np.ndarray
    dots: object
    geometry: StationGeometry
    screen: InterpolatedScreen
    design: FacetDesign
    distance_m: float
    settings: AnalysisSettings
    fixed: object
    #: What the import assumed or derived where OpenCSP's files say nothing, in words.
    assumptions: tuple = ()
    uncertainty: InputUncertainties | None = None

    def reduce(self, fixed=None):
        """The stages of the reduction (:func:`~sofast_station.measure.fixed.reduce_fixed`) without the
        uncertainty; *fixed* overrides the import's :class:`~sofast_station.measure.fixed.FixedSettings`."""
        return reduce_fixed(self.image, self.dots, self.geometry, self.design, self.distance_m, self.settings,
                            fixed or self.fixed, origin_px=self.origin_px, screen=self.screen)

    def analyse(self, uncertainty: InputUncertainties | None = None, sensitivity_cache: dict | None = None,
                fixed=None) -> Analysis:
        """Our analysis of the measurement (:func:`~sofast_station.measure.fixed.analyse_fixed`), with every
        figure's U (k = 2) when *uncertainty* is given (e.g. :attr:`uncertainty`); only the sensitivities go to and
        from *sensitivity_cache* (as :meth:`OpenCspMeasurement.analyse`)."""
        local = None if uncertainty is None else _SensitivitiesOnly(sensitivity_cache)
        return analyse_fixed(self.image, self.dots, self.geometry, self.design, self.distance_m, self.settings,
                             fixed or self.fixed, origin_px=self.origin_px, screen=self.screen,
                             uncertainty=uncertainty, sensitivity_cache=local)


def read_fixed_image(path: Path, shape: tuple[int, int], camera_path: Path | None = None) -> np.ndarray:
    """The dot frame of OpenCSP's fixed-pattern measurement *path*: 8-bit camera values as they are (the method
    needs no response calibration: a dot's centre does not move with the camera's response)."""
    image = np.asarray(_read(path, FIXED + "image"))
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim != 2:
        raise ConfigError(f"{path}: MeasurementSofastFixed/image must be one grey image, got shape {image.shape}")
    if image.shape != tuple(shape):
        raise ConfigError(f"{path}: the image is {image.shape[1]} x {image.shape[0]} px but the camera "
                          f"{camera_path or ''} is {shape[1]} x {shape[0]} (OpenCSP processes this capture with "
                          "its full-size camera, camera_sofast.h5)".replace("  ", " "))
    return _camera_values(image, path) if image.dtype != np.uint8 else image


def read_opencsp_fixed(measurement: Path, dots: Path, camera: Path, orientation: Path, facet: Path | None,
                       focal_length_m: float = 100.0, uncertainty: dict | None = None) -> OpenCspFixedMeasurement:
    """Read OpenCSP's fixed-pattern measurement: the ``MeasurementSofastFixed`` file, its dot locations
    (``DotLocationsFixedPattern``: in the screen frame of the ``SpatialOrientation`` *orientation*), the camera
    and the facet definition (None: a mirror of unknown outline). *uncertainty* (an ``[uncertainty]`` table)
    overrides input uncertainties (:func:`opencsp_input_uncertainties`; the screen pitch's is the dot
    locations' scale).

    OpenCSP's conventions, from its ``ProcessSofastFixed`` and ``BlobIndex``: the dots are indexed from the
    dot nearest the measurement's ``origin`` pixel (index (0, 0)), x index along the image's columns and y
    index along its rows; a dot's screen point is its ``xyz_dot_loc`` turned into the camera frame as the
    orientation says (as a fringe measurement's display points are). The nominal pose faces camera and screen
    at the lit region's centroid at the measured distance (OpenCSP has no fixture), and predicts the same
    index directions (:func:`~sofast_station.measure.fixed.predicted_index_axes`); the import takes OpenCSP's.
    """
    measurement, dots_path, camera, orientation = (Path(p) for p in (measurement, dots, camera, orientation))
    cam = camera_from_opencsp(camera)
    to_cam = screen_to_camera(orientation)
    grid = read_dot_locations(dots_path)
    if facet is not None:
        facet_from_opencsp(Path(facet), focal_length_m)
    image = read_fixed_image(measurement, cam.shape, camera)
    origin = np.asarray(_read(measurement, FIXED + "origin"), np.float64).ravel()
    if origin.size != 2 or not np.all(np.isfinite(origin)):
        raise ConfigError(f"{measurement}: MeasurementSofastFixed/origin must be one pixel (x, y), got "
                          f"{origin.tolist()}")
    distance = float(_read(measurement, FIXED + "dist_optic_screen"))
    mp = np.array(_read(measurement, FIXED + "v_measure_point_facet"), np.float64).ravel()
    name = str(_read(measurement, FIXED + "name"))
    fixed = FixedSettings(index_axes=np.eye(2, dtype=np.int64))
    screen = dot_screen(grid, to_cam)
    lit = pattern_background(image, fixed.max_dot_diameter_px)
    mask = lit > otsu_level(lit[::2, ::2].ravel())
    if facet is not None:
        design = facet_from_opencsp(Path(facet), focal_length_m, name=name)
        if design.outline_known and np.any(mp[:2] != design.measure_point_m):
            design = replace(design, measure_point_m=mp[:2].copy())
    else:
        design = undefined_mirror_design(cam, mask, distance, focal_length_m, name=name)
    nominal = nominal_pose(cam, mask, screen.centre_camera(), distance)
    geometry = StationGeometry(cam, ScreenSpec(1000, 1000, 0.001), to_cam, nominal)
    settings = AnalysisSettings(max_hole_px=2000, corner_tolerance_px=80.0, max_corner_rms_px=2.0)
    inputs = opencsp_input_uncertainties(cam, uncertainty)
    located = int(grid.located.sum())
    assumptions = (
        f"design focal length {focal_length_m:g} m (OpenCSP's facet file has none; --focal-length sets it)",
        f"dots: {located} of the {grid.x_index.size} x {grid.y_index.size} grid located "
        f"({Path(dots_path).name}), in the screen frame of {Path(orientation).name}; indexed from the dot nearest "
        f"the measurement's origin ({origin[0]:.1f}, {origin[1]:.1f}) px, x index along the image's columns and y "
        "along its rows (OpenCSP's BlobIndex)",
        "facet region: the dot frame's lit background with its dots filled in, brighter than Otsu's threshold "
        "(there is no dark or white frame)",
        f"nominal facet pose: the lit region's centre at the measured distance {distance:.4f} m (OpenCSP has no "
        "fixture)",
        "dots used: those indexed, located and clear of the facet's edge by the blur's reach and their own size "
        "(OpenCSP also uses the dots the edge cuts)",
    )
    log.info("OpenCSP fixed-pattern measurement %s: %d x %d px, %d dots located, distance %.3f m", design.name,
             cam.width_px, cam.height_px, located, distance)
    return OpenCspFixedMeasurement(name, str(_read(measurement, FIXED + "date")), image, origin, grid, geometry,
                                   screen, design, distance, settings, fixed,
                                   assumptions + _uncertainty_assumptions(inputs)[:1]
                                   + ("left out of the uncertainty: the fixture pose (OpenCSP has none); the dot "
                                      "locations' node-by-node errors (only their scale and pose are inputs; "
                                      "the screen pitch's is the dots' scale)",), inputs)
