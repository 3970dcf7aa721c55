"""Where the files of an OpenCSP measurement are (standard library only, so that ``import-opencsp`` can
check its inputs before it loads numpy and HDF5)."""

from __future__ import annotations

from pathlib import Path

from ..errors import ConfigError

#: What each file of an OpenCSP SOFAST fringe measurement holds (``import-opencsp``'s options).
FILES = {"measurement": "MeasurementSofastFringe HDF5", "camera": "Camera HDF5", "display": "DisplayShape HDF5",
         "orientation": "SpatialOrientation HDF5", "calibration": "ImageCalibration HDF5",
         "facet": "facet definition JSON", "ensemble": "ensemble definition JSON"}


def opencsp_test_data_paths(root: Path, multi_facet: bool = False, split_facet: bool = False) -> dict[str, Path]:
    """The file layout of OpenCSP's ``opencsp/test/data`` (and of ``fixtures/opencsp``).

    *multi_facet*: its multi-facet fringe measurement, ``measurement_ensemble.h5``, a lab heliostat of 24
    facets (``Facet_lab_6x4.json``, ``Ensemble_lab_6x4.json``; OpenCSP's example_process_facet_ensemble
    pairs them so). *split_facet*: the single NSTTF facet's measurement analysed as two halves
    (``Facet_split_NSTTF.json``, ``Ensemble_split_NSTTF_facet.json``; OpenCSP pairs these with its fixed-pattern
    ensemble capture, which its public test data lacks)."""
    root = Path(root)
    paths = {"measurement": root / "sofast_fringe/data_measurement/measurement_facet.h5",
             "camera": root / "sofast_common/camera_sofast_downsampled.h5",
             "display": root / "sofast_common/display_distorted_2d.h5",
             "orientation": root / "sofast_common/spatial_orientation.h5",
             "calibration": root / "sofast_fringe/data_measurement/image_calibration.h5",
             "facet": root / "sofast_common/Facet_NSTTF.json"}
    if multi_facet and split_facet:
        raise ConfigError("--multi-facet and --split-facet are two different measurements: give one")
    if multi_facet:
        paths.update(measurement=root / "sofast_fringe/data_measurement/measurement_ensemble.h5",
                     facet=root / "sofast_common/Facet_lab_6x4.json",
                     ensemble=root / "sofast_common/Ensemble_lab_6x4.json")
    if split_facet:
        paths.update(facet=root / "sofast_common/Facet_split_NSTTF.json",
                     ensemble=root / "sofast_common/Ensemble_split_NSTTF_facet.json")
    return paths


#: What each file of an OpenCSP fixed-pattern (dot grid) measurement holds (``import-opencsp --fixed``).
FIXED_FILES = {"measurement": "MeasurementSofastFixed HDF5", "dots": "DotLocationsFixedPattern HDF5",
               "camera": "Camera HDF5", "orientation": "SpatialOrientation HDF5", "facet": "facet definition JSON"}


def opencsp_fixed_paths(root: Path) -> dict[str, Path]:
    """The files of the fixed-pattern measurement in OpenCSP's ``opencsp/test/data`` layout (and
    ``fixtures/opencsp``): its one dot frame, the dots' locations, the full-size camera (OpenCSP processes this
    capture with ``camera_sofast.h5``: it was not downsampled), the spatial orientation and the NSTTF facet."""
    root = Path(root)
    return {"measurement": root / "sofast_fixed/data_measurement/measurement_facet.h5",
            "dots": root / "sofast_fixed/data_measurement/fixed_pattern_dot_locations.h5",
            "camera": root / "sofast_common/camera_sofast.h5",
            "orientation": root / "sofast_common/spatial_orientation.h5",
            "facet": root / "sofast_common/Facet_NSTTF.json"}


def check_files(paths: dict[str, Path], test_data: Path | None = None) -> None:
    """Every file of *paths* (keys of :data:`FILES`) exists, or a ConfigError names the first missing one
    (and the ``--test-data`` folder it was looked for in)."""
    if test_data is not None and not Path(test_data).is_dir():
        raise ConfigError(f"--test-data {test_data} is not a folder: give the folder in the layout of OpenCSP's "
                          "opencsp/test/data (fixtures/opencsp/test_data is one)")
    for key, path in paths.items():
        if not Path(path).is_file():
            raise ConfigError(f"the {FILES.get(key) or FIXED_FILES.get(key, key)} file {path} does not exist (--{key}"
                              f"{' or --test-data' if test_data is not None else ''})")
