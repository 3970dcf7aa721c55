"""The layout of a data dump: its name and version, every group and dataset with units and description.

:data:`SCHEMA_CURRENT` (:data:`SCHEMA_V2`) is the reference the writer labels every object from and
``docs/dump-schema.md`` documents (a test keeps the two in step); :data:`SCHEMA_V1` is the first layout,
still read. A new layout gets a new table and version here, and a reader
in :mod:`.reader`.
"""

from __future__ import annotations

import fnmatch
import logging

log = logging.getLogger("sofast_station.archive.dumps")

#: Root attribute ``schema`` of every dump.
SCHEMA = "sofast-station-dump"
#: Version of the layout this software writes (and the newest it reads). Version 2 (non-square display
#: pixels): ``geometry/screen`` holds ``pitch_x_m`` and ``pitch_y_m`` where the pixels are not square,
#: ``pitch_m`` where they are; version 1 always had ``pitch_m``. Version 3 (the fixed-pattern method): a
#: facet measured from a dot grid (``design/method`` "fixed", ``design/fixed``: the grid and the method's
#: settings; ``capture/frames`` the dot frame, after a dark and a white one when the recipe took them), which
#: a reader of version 2 would take for a fringe capture: it refuses it instead.
SCHEMA_VERSION = 3
#: The version of a fringe capture's dump: 2, read by every reader since (a fringe dump has nothing of 3's).
FRINGE_SCHEMA_VERSION = 2

#: gzip level of the frames (lossless; level 4 is within 1 % of level 9's size at a third of the time).
COMPRESSION_LEVEL = 4

#: Figures of the result record copied to attributes of ``/result`` (dotted names flatten nested dicts).
KEY_FIGURES = ("verdict", "focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
               "twist_mrad_per_m", "slope_rms_mrad.design.magnitude", "slope_rms_mrad.parabola.magnitude",
               "slope_rms_mrad.higher_order.magnitude", "boresight_mrad.x", "boresight_mrad.y", "n_points",
               "valid_fraction", "median_modulation_dn", "measured_distance_m",
               # expanded uncertainties (k = 2) of the figures above, where the record has them
               "focal_length_x_m_U", "focal_length_y_m_U", "curvature_x_per_m_U", "curvature_y_per_m_U",
               "twist_mrad_per_m_U", "slope_rms_mrad_U.design.magnitude", "slope_rms_mrad_U.parabola.magnitude",
               "slope_rms_mrad_U.higher_order.magnitude", "boresight_mrad_U.x", "boresight_mrad_U.y")

# -- the schema ---------------------------------------------------------------------------------------
#: Every group, dataset and root attribute of schema version 1:
#: (path, kind, dtype, units, description, required). ``*`` in a path matches any one name.
SCHEMA_V1: tuple[tuple[str, str, str, str, str, bool], ...] = (
    ("/@schema", "attribute", "str", "", 'always "sofast-station-dump"', True),
    ("/@schema_version", "attribute", "int64", "", "layout version of this file (1)", True),
    ("/@description", "attribute", "str", "", "what the file is", True),
    ("/@software_version", "attribute", "str", "", "sofast-station version that measured and wrote the dump", True),
    ("/@created", "attribute", "str", "ISO 8601", "when the dump file was written (local time with UTC offset)", True),
    ("/@cycle_id", "attribute", "str", "", "the inspection cycle's unique id (the journal's key)", True),
    ("/@serial", "attribute", "str", "", "the facet's serial number", True),
    ("/@time", "attribute", "str", "ISO 8601", "time of the measurement (the record's time, with UTC offset)", True),
    ("/@config_hash", "attribute", "str", "", "SHA-256 (16 hex digits) of the station and facet configuration", True),
    ("/@station", "attribute", "str", "", "station name from station.toml", False),
    ("/@facet", "attribute", "str", "", "facet design name", False),

    ("capture", "group", "", "", "the raw camera frames and the measured distance", True),
    ("capture/frames", "dataset", "uint8 or uint16 (n, h, w)", "DN",
     "camera frames cropped to the facet region, in capture order (dark, white, then the fringe frames of "
     "fringes/, x then y, coarse to fine, phase steps in order); gzip 4 + shuffle, one chunk per frame; "
     "outside the crop the full frames are 0 by definition; uint16 (little-endian) for a camera of more "
     "than 8 bits", True),
    ("capture/frames_sha256", "dataset", "str (n,)", "",
     "SHA-256 (hex) of each cropped frame's bytes in C order, checked by read_dump", True),
    ("capture/crop_box", "dataset", "int64 (2,)", "px",
     "(row0, col0): image row and column of the crop's top-left pixel in the full frame", True),
    ("capture/full_shape", "dataset", "int64 (2,)", "px", "(rows, columns) of the full camera frame", True),
    ("capture/patterns", "dataset", "str (n,)", "", "label of the display image shown for each frame", True),
    ("capture/measured_distance_m", "dataset", "float64", "m",
     "measured distance from the screen centre to the design's measure point", True),

    ("fringes", "group", "", "", "the fringe definition (station.toml [fringes])", True),
    ("fringes/periods_x", "dataset", "float64 (k,)", "cycles per screen width", "x fringe periods, coarse to fine",
     True),
    ("fringes/periods_y", "dataset", "float64 (k,)", "cycles per screen height", "y fringe periods, coarse to fine",
     True),
    ("fringes/phase_steps", "dataset", "int64", "", "phase steps per period (shifts 2 pi k / steps)", True),
    ("fringes/drawn", "group", "", "", "how the display drew the fringes (the radiometric record's table and "
     "the display's size), from which the analysis takes the fringes' rounding to 8-bit commands off the "
     "positions; absent when the station had no radiometric record", False),
    ("fringes/drawn/lut", "dataset", "float64 (N,)", "command / 255",
     "the table the fringes went through (the radiometric record's lut)", False),
    ("fringes/drawn/floor_level", "dataset", "float64", "linear response level 0..1", "the fringes' minimum", False),
    ("fringes/drawn/max_level", "dataset", "float64", "linear response level 0..1", "the fringes' maximum", False),
    ("fringes/drawn/display_px", "dataset", "int64 (2,)", "px", "(width, height) of the display's active area",
     False),

    ("calibration", "group", "", "", "calibration records in force at the measurement", True),
    ("calibration/radiometric", "group", "", "", "the radiometric (display -> camera) calibration record", True),
    ("calibration/radiometric/schema", "dataset", "int64", "", "the record's own schema version", True),
    ("calibration/radiometric/kind", "dataset", "str", "", 'always "radiometric"', True),
    ("calibration/radiometric/record_id", "dataset", "str", "", "record id", True),
    ("calibration/radiometric/created", "dataset", "str", "ISO 8601", "when the calibration was made", True),
    ("calibration/radiometric/source", "dataset", "str", "", "how the record came to be", True),
    ("calibration/radiometric/lut", "dataset", "float64 (N,)", "command / 255",
     "lookup table: display command as a function of linear response level 0..1 (N even steps)", True),
    ("calibration/radiometric/floor_level", "dataset", "float64", "linear response level 0..1",
     "level of the fringe minimum (the calibrated floor)", True),
    ("calibration/radiometric/max_level", "dataset", "float64", "linear response level 0..1",
     "level of the fringe maximum", True),
    ("calibration/radiometric/exposure_s", "dataset", "float64", "s", "camera exposure time", True),
    ("calibration/radiometric/gain", "dataset", "float64", "1", "camera gain (linear factor)", True),
    ("calibration/radiometric/dark_level_dn", "dataset", "float64", "DN",
     "mean dark level at calibration (records from the daily routine)", False),
    ("calibration/radiometric/latency_frames", "dataset", "int64", "frames",
     "display-to-camera latency found by the routine", False),
    ("calibration/radiometric/settle_s", "dataset", "float64", "s", "settle time the latency implies", False),
    ("calibration/radiometric/refresh_hz", "dataset", "float64", "Hz", "display refresh rate used", False),

    ("geometry", "group", "", "",
     "station geometry: camera intrinsics, screen, poses (frames: docs/conventions.md#frames)", True),
    ("geometry/camera", "group", "", "", "camera intrinsics, OpenCV pinhole + 5-term distortion", True),
    ("geometry/camera/width_px", "dataset", "int64", "px", "image width", True),
    ("geometry/camera/height_px", "dataset", "int64", "px", "image height", True),
    ("geometry/camera/matrix", "dataset", "float64 (3, 3)", "px",
     "camera matrix K [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]", True),
    ("geometry/camera/distortion", "dataset", "float64 (5,)", "1", "distortion k1, k2, p1, p2, k3 (OpenCV)", True),
    ("geometry/screen", "group", "", "", "the flat display", True),
    ("geometry/screen/width_px", "dataset", "int64", "px", "display width", True),
    ("geometry/screen/height_px", "dataset", "int64", "px", "display height", True),
    ("geometry/screen/pitch_m", "dataset", "float64", "m", "display pixel pitch", True),
    ("geometry/screen_to_camera", "group", "", "", "pose mapping screen-frame points to the camera frame", True),
    ("geometry/screen_to_camera/rotation", "dataset", "float64 (3, 3)", "1", "rotation matrix", True),
    ("geometry/screen_to_camera/translation", "dataset", "float64 (3,)", "m", "screen origin in the camera frame",
     True),
    ("geometry/fixture_to_camera", "group", "", "", "pose of the nominal facet frame in the camera frame", True),
    ("geometry/fixture_to_camera/rotation", "dataset", "float64 (3, 3)", "1", "rotation matrix", True),
    ("geometry/fixture_to_camera/translation", "dataset", "float64 (3,)", "m", "fixture origin in the camera frame",
     True),

    ("design", "group", "", "", "the facet design (recipe), facet frame", True),
    ("design/name", "dataset", "str", "", "design name", True),
    ("design/kind", "dataset", "str", "", "dish, gore or heliostat", True),
    ("design/focal_length_m", "dataset", "float64", "m", "design focal length of z = (x^2 + y^2) / (4 f)", True),
    ("design/outline_m", "dataset", "float64 (N, 2)", "m", "outline corners (x, y), counter-clockwise from +z", True),
    ("design/measure_point_m", "dataset", "float64 (2,)", "m", "(x, y) of the range finder's point", True),
    ("design/alignment_point_m", "dataset", "float64 (2,)", "m", "(x, y) of the boresight alignment point", True),
    ("design/layout", "group", "", "", "the facet file's [facet.layout] table (may be empty)", True),
    ("design/layout/*", "dataset", "from the value", "from the name's suffix (_m: m, _mrad: mrad)",
     "one [facet.layout] entry", False),

    ("analysis", "group", "", "", "analysis settings (station.toml [analysis], defaults filled in)", True),
    ("analysis/mask_threshold_dn", "dataset", "int64 or float64", "DN", "facet pixel when white - dark exceeds this",
     True),
    ("analysis/min_modulation_dn", "dataset", "int64 or float64", "DN", "least fringe amplitude kept", True),
    ("analysis/consistency_sigmas", "dataset", "int64 or float64", "noise sigmas", "I0 + I2 = I1 + I3 check limit",
     True),
    ("analysis/guard_sigmas", "dataset", "int64 or float64", "position noise sigmas", "screen-edge guard band", True),
    ("analysis/subsample_step", "dataset", "int64", "pixels", "every n-th valid pixel while iterating", True),
    ("analysis/max_iterations", "dataset", "int64", "", "iteration limit", True),
    ("analysis/max_range_shift_m", "dataset", "float64", "m", "largest accepted range correction", True),
    ("analysis/corner_tolerance_px", "dataset", "float64", "px", "largest corner distance from nominal", True),
    ("analysis/max_hole_px", "dataset", "int64", "px", "holes up to this area are filled", True),
    ("analysis/max_saturated_fraction", "dataset", "float64", "1", "largest accepted saturated fraction", True),
    ("analysis/max_corner_rms_px", "dataset", "float64", "px", "largest accepted corner RMS", True),
    # added after the first dumps were written: optional, the analysis's defaults apply when absent
    ("analysis/robust_fit", "dataset", "bool", "", "parabola fitted by bisquare-weighted least squares", False),
    ("analysis/edge_window_px", "dataset", "int64", "px", "half-width of the window summed across a facet edge",
     False),
    ("analysis/threads", "dataset", "int64", "", "threads of the analysis (the figures do not depend on it)", False),

    ("config", "group", "", "", "the station configuration as loaded", True),
    ("config/station_toml", "dataset", "str", "", "raw text of station.toml (empty if it could not be read)", True),
    ("config/facet_toml", "dataset", "str", "", "raw text of the facet file (empty if it could not be read)", True),
    ("config/station_path", "dataset", "str", "", "where station.toml was read from", True),
    ("config/facet_path", "dataset", "str", "", "where the facet file was read from", True),
    ("config/config_hash", "dataset", "str", "", "configuration hash (StationConfig.config_hash)", True),
    ("config/station_name", "dataset", "str", "", "station name", True),

    ("result", "group", "", "", "the archived result; attributes: key figures (see below)", True),
    ("result/record_json", "dataset", "str", "", "the result record as JSON text (null: infinite or not a number)",
     True),
)


def _v2(entry):
    path = entry[0]
    if path == "/@schema_version":
        return (path, *entry[1:4], "layout version of this file (2)", True)
    if path == "geometry/screen/pitch_m":
        return (path, "dataset", "float64", "m", "display pixel pitch, square pixels (else pitch_x_m, pitch_y_m)",
                False)
    return entry


#: Schema version 2: version 1 with non-square display pixels (``pitch_x_m``, ``pitch_y_m``) allowed.
SCHEMA_V2: tuple[tuple[str, str, str, str, str, bool], ...] = tuple(
    e for entry in SCHEMA_V1 for e in ((_v2(entry),) if entry[0] != "geometry/screen/pitch_m" else (
        _v2(entry),
        ("geometry/screen/pitch_x_m", "dataset", "float64", "m",
         "display pixel pitch along x (columns), non-square pixels", False),
        ("geometry/screen/pitch_y_m", "dataset", "float64", "m",
         "display pixel pitch along y (rows), non-square pixels", False))))

# Optional in version 2 (written since the station keeps them): older readers ignore them.
SCHEMA_V2 = SCHEMA_V2 + (
    ("geometry/measured_screen", "group", "", "",
     "the screen's measured shape the analysis used (calibrate screen's record), when one was in force", False),
    ("geometry/measured_screen/nodes_px", "dataset", "float64 (M, 2)", "px",
     "grid nodes, display pixels from the active area's left and bottom edges", False),
    ("geometry/measured_screen/nodes_screen_m", "dataset", "float64 (M, 3)", "m",
     "the nodes' points in the screen frame (origin the display's centre point, +z its normal there)", False),
    ("geometry/measured_screen/modes_m", "dataset", "float64 (K, M, 3) or (0,)", "m",
     "the shape's independent uncertainty fields, every node's displacement at one standard deviation", False),
    ("geometry/measured_screen/record_id", "dataset", "str", "", "the screen record it came from", False),
    ("result/sensitivities_json", "dataset", "str", "",
     "the uncertainty's sensitivities the analysis used, as JSON text (re-analysis reuses them for the same "
     "inputs)", False),
    ("result/uncertainty_inputs_json", "dataset", "str", "",
     "the input uncertainties in force (station.toml's [uncertainty] with what the radiometric, camera and "
     "commissioning records state), as JSON text: re-analysis states the same U as the line (0.4.0 on)", False),)

def _v3(entry):
    if entry[0] == "/@schema_version":
        return (entry[0], *entry[1:4], "layout version of this file (3: a fixed-pattern capture; 2: a fringe one)",
                True)
    if entry[0] == "capture/frames":
        return (entry[0], *entry[1:4], entry[4] + "; a fixed-pattern capture (design/method \"fixed\"): the dot "
                "frame, after a dark and a white frame when design/fixed/white_frame", True)
    return entry


#: Schema version 3: version 2 and a facet measured by the fixed-pattern (dot grid) method.
SCHEMA_V3: tuple[tuple[str, str, str, str, str, bool], ...] = tuple(_v3(e) for e in SCHEMA_V2) + (
    ("design/method", "dataset", "str", "", '"fixed": measured from one frame of a dot grid (absent: the fringes)',
     False),
    ("design/fixed", "group", "", "", "the fixed pattern (required when design/method is \"fixed\")", False),
    ("design/fixed/white_frame", "dataset", "bool", "", "a dark and a white frame came before the dot frame", False),
    ("design/fixed/grid", "group", "", "", "the dot grid the display showed (LcdDotGrid)", False),
    ("design/fixed/grid/*", "dataset", "from the value", "display px (background: command 0..255; mark_offset: "
     "pitches)", "width_px, height_px, pitch_px, diameter_px, background, mark_diameter_px, mark_offset", False),
    ("design/fixed/settings", "group", "", "", "the fixed-pattern method's settings (FixedSettings)", False),
    ("design/fixed/settings/*", "dataset", "from the value", "px where the name ends _px; index_tolerance: lattice "
     "steps", "dark_dots, max_dot_diameter_px, index_tolerance, min_dots, origin_index, index_axes, "
     "second_lattice_fraction, subsample_step, edge_margin_px", False),
)

#: The layout this software writes.
SCHEMA_CURRENT = SCHEMA_V3

_PLAIN_ENCODING = "plain"
_JSON_ENCODING = "json"


def _schema_entry(path: str):
    for entry in SCHEMA_CURRENT:
        if entry[0] == path or ("*" in entry[0] and fnmatch.fnmatchcase(path, entry[0])):
            return entry
    return None


def _units_from_name(name: str) -> str:
    for suffix, unit in (("_mrad", "mrad"), ("_m", "m"), ("_px", "px"), ("_s", "s"), ("_dn", "DN"), ("_rad", "rad")):
        if name.endswith(suffix):
            return unit
    return ""


def _describe(path: str) -> tuple[str, str]:
    entry = _schema_entry(path)
    if entry is None:
        log.warning("dump schema v%d has no description of %s", SCHEMA_VERSION, path)
        return f"{path.rsplit('/', 1)[-1]} (not described by schema version {SCHEMA_VERSION})", _units_from_name(path)
    units = entry[3]
    if entry[0].endswith("*"):
        units = _units_from_name(path)
    return entry[4], units
