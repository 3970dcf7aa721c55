"""What an OpenCSP file holds, and what this station does with it: one line for any file a peer may hand us.

OpenCSP saves each of its objects as an HDF5 group named after its class (``Camera``, ``DisplayShape``,
``MeasurementSofastFringe``, ...), its definitions as JSON and some calibration inputs as CSV files and
photographs. :func:`describe` names the object a file holds from its own contents (never from its name) and
says where the station reads it, or that it does not; the readers use it in their errors, so a wrong file
given to an option is named for what it is. ``sofast-station import-opencsp --what FILE...`` prints it.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py

#: The layouts of OpenCSP's processed results (:func:`~.opencsp_results.read_opencsp_result` reads them): key
#: -> (the group that tells it, what it is).
LAYOUTS = {
    "facet": ("DataSofastCalculation/facet/facet_000/SlopeSolverData/slope_coefs_facet",
              "a fringe measurement's processing (ProcessSofastFringe, current layout)"),
    "older": ("DataSofastCalculation/facet/facet_000/slope_coefs_facet",
              "a fringe measurement's processing (ProcessSofastFringe, earlier layout)"),
    "fixed": ("DataSofastInput/ParamsSofastFixed",
              "a fixed-pattern measurement's processing (ProcessSofastFixed): slopes at the dots"),
}


def result_layout(h) -> str | None:
    """Which of :data:`LAYOUTS` the open HDF5 file *h* holds (None: none of them)."""
    for name, (key, _) in LAYOUTS.items():
        if key in h:
            return name
    return None


#: HDF5 top-level groups or datasets -> (what OpenCSP object it is, what the station does with it).
HDF5_KINDS = (
    ("MeasurementSofastFringe", "a SOFAST fringe measurement (MeasurementSofastFringe)",
     "read by `import-opencsp --measurement`"),
    ("MeasurementSofastFixed", "a SOFAST fixed-pattern (dot grid) measurement (MeasurementSofastFixed)",
     "read by `import-opencsp --fixed` (or `--measurement` with `--dots`): the fixed-pattern method "
     "(docs/method.md)"),
    ("DataSofastCalculation", "OpenCSP's processing of a measurement (its data.h5)",
     "read by `import-opencsp --compare` (fringe results of one facet or mirror; a multi-facet result is not "
     "read)"),
    ("DotLocationsFixedPattern", "the 3-D locations of a fixed pattern's dots (DotLocationsFixedPattern)",
     "read by `import-opencsp --dots` (a fixed-pattern measurement's dots) and by `calibrate dots --compare` "
     "(beside dots located from photographs)"),
    ("Camera", "a camera's intrinsics and distortion (Camera)", "read by `import-opencsp --camera`"),
    ("DisplayShape", "a screen's shape (DisplayShape)", "read by `import-opencsp --display`"),
    ("SpatialOrientation", "the camera-to-screen pose (SpatialOrientation)", "read by `import-opencsp --orientation`"),
    ("ImageCalibration", "a display-to-camera response (ImageCalibration)", "read by `import-opencsp --calibration`"),
    ("ImageProjection", "the projector window's layout on the desktop (ImageProjection)",
     "read by `calibrate screen-data --projection` (the screen's pixel layout); import-opencsp does not need it: "
     "the station's own display draws its fringes"),
    ("pts_xy_screen_fraction", "a screen-shape calibration's distortion data (screen fractions and 3-D points)",
     "checked by `calibrate screen-data` (docs/calibration.md); import-opencsp reads the same grid from a "
     "DisplayShape file"),
)


def _hdf5_kind(path: Path) -> str | None:
    try:
        with h5py.File(path, "r") as h:
            keys = set(h.keys())
    except OSError:
        return None
    for key, what, support in HDF5_KINDS:
        if key in keys:
            if key == "DataSofastCalculation":
                with h5py.File(path, "r") as h:
                    layout = result_layout(h)
                if layout is None:
                    return ("OpenCSP's processing of a measurement, of no layout this reader knows (a multi-facet "
                            "result, or another version's); not read")
                if layout == "fixed":
                    return f"{LAYOUTS['fixed'][1]}; read by `import-opencsp --fixed --compare`"
                return f"{LAYOUTS[layout][1]}; read by `import-opencsp --compare`"
            return f"{what}; {support}"
    return f"an HDF5 file with {', '.join(sorted(keys)) or 'nothing'} at its top level, none of OpenCSP's objects"


def _json_kind(path: Path) -> str | None:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if isinstance(data, dict) and "v_facet_corners" in data:
        return "a facet definition (DefinitionFacet JSON); read by `import-opencsp --facet`"
    if isinstance(data, dict) and "v_facet_locations" in data:
        return "an ensemble definition (DefinitionEnsemble JSON); read by `import-opencsp --ensemble`"
    if isinstance(data, list) and data and isinstance(data[0], dict) and "number_samples" in data[0]:
        return ("a SOFAST configuration's statistics (SofastConfiguration JSON: sample spacing and focal lengths); "
                "not read (the station states its own)")
    return "a JSON file of none of OpenCSP's definitions"


def _csv_kind(path: Path) -> str:
    try:
        head = path.read_text(errors="replace").splitlines()[:1]
    except OSError:
        return "a file that cannot be read"
    first = head[0].lower() if head else ""
    if "marker id" in first and "corner id" in first:
        return ("ArUco markers' corner locations (marker, corner, x, y, z in metres); read by `calibrate "
                "camera-position --markers` and `calibrate dots --markers` (docs/calibration.md)")
    if "display calibration point" in first:
        return ("a screen-shape calibration's point pairs (screen point, marker); read by `calibrate screen-data "
                "--point-pairs` (docs/calibration.md)")
    if first and all(_is_number(v) for v in first.split(",")):
        return "a CSV of numbers (OpenCSP's camera_rvec_tvec.csv holds a rotation vector and a translation)"
    return "a CSV file of none of OpenCSP's layouts"


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


def describe(path: Path) -> str:
    """One line: what OpenCSP object *path* holds (from its contents) and what the station does with it."""
    path = Path(path)
    if not path.exists():
        return "a file that does not exist"
    if path.is_dir():
        return "a folder (give a file; --test-data takes a folder in OpenCSP's test-data layout)"
    suffix = path.suffix.lower()
    with open(path, "rb") as f:
        magic = f.read(8)
    if magic.startswith(b"\x89HDF"):
        return _hdf5_kind(path) or "an HDF5 file that cannot be read (damaged or cut short)"
    if magic.startswith(b"\x89PNG") or magic.startswith(b"\xff\xd8"):
        return ("a photograph (PNG or JPEG): `calibrate camera-position` locates the camera from one of markers, "
                "`calibrate dots` a dot target from several, `calibrate camera` the intrinsics from a board's "
                "(docs/calibration.md); import-opencsp does not read photographs")
    if suffix == ".json":
        return _json_kind(path) or "a JSON file that cannot be read"
    if suffix == ".csv":
        return _csv_kind(path)
    return f"a file of none of OpenCSP's formats ({suffix or 'no extension'})"
