"""What the photogrammetric calibrations (``calibrate camera-position``, ``calibrate dots``) read: photographs,
the table of ArUco marker corners, and the photographs' agreement with the camera's calibration.

The marker table is OpenCSP's CSV (``Marker ID, Corner ID, x, y, z``, metres, a comment line first; corner id
``4 * marker id + k`` for the marker's corners k = 0..3 in OpenCV's order: top-left, top-right, bottom-right,
bottom-left of the printed marker). Every problem is a one-line :class:`CalibrationError` naming the file and
what to do.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..geometry import CameraIntrinsics
from ..measure.markers import MarkerTable
from .errors import CalibrationError


def read_marker_table(path: str | Path) -> MarkerTable:
    """The markers' corners from a CSV of ``marker id, corner id, x, y, z`` (metres), lines starting with
    ``#`` ignored.

    Raises
    ------
    CalibrationError
        Unreadable file, a line that is not five numbers, corner ids that are not ``4 * marker + k``, a marker
        without its four corners, a corner listed twice.
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise CalibrationError(f"marker table {path} does not exist: give the CSV of the markers' surveyed corners "
                               "(marker id, corner id, x, y, z in metres)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"marker table {path} cannot be read as text ({exc})") from None
    rows = []
    for number, line in enumerate(lines, 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        fields = [f.strip() for f in text.split(",")]
        try:
            values = [float(f) for f in fields]
        except ValueError:
            if not rows and number == 1:
                continue                                   # a header line without '#'
            raise CalibrationError(f"marker table {path} line {number}: {text!r} is not five numbers (marker id, "
                                   "corner id, x, y, z in metres)") from None
        if len(values) != 5 or not np.all(np.isfinite(values)):
            raise CalibrationError(f"marker table {path} line {number}: need five finite numbers (marker id, corner "
                                   f"id, x, y, z in metres), got {text!r}")
        marker, corner = values[0], values[1]
        if marker != int(marker) or corner != int(corner) or marker < 0:
            raise CalibrationError(f"marker table {path} line {number}: marker and corner ids must be whole numbers "
                                   f">= 0, got {fields[0]}, {fields[1]}")
        k = int(corner) - 4 * int(marker)
        if not 0 <= k <= 3:
            raise CalibrationError(f"marker table {path} line {number}: corner id {int(corner)} does not belong to "
                                   f"marker {int(marker)} (its corners are {4 * int(marker)}..{4 * int(marker) + 3}: "
                                   "4 x marker id + corner 0..3)")
        rows.append((int(marker), k, values[2:], number))
    if not rows:
        raise CalibrationError(f"marker table {path} lists no corners")
    corners: dict[int, dict[int, list]] = {}
    for marker, k, xyz, number in rows:
        if k in corners.setdefault(marker, {}):
            raise CalibrationError(f"marker table {path} line {number}: marker {marker} corner {k} is listed twice")
        corners[marker][k] = xyz
    incomplete = sorted(m for m, c in corners.items() if len(c) != 4)
    if incomplete:
        raise CalibrationError(f"marker table {path}: marker(s) {incomplete} lack some of their four corners; list "
                               "all four or none")
    ids = sorted(corners)
    table = MarkerTable(np.array(ids), np.array([[corners[m][k] for k in range(4)] for m in ids]))
    sides = table.side_m()
    if np.any(sides <= 0) or np.any(sides > 10.0):
        bad = [ids[i] for i in np.flatnonzero((sides <= 0) | (sides > 10.0))]
        raise CalibrationError(f"marker table {path}: marker(s) {bad} have sides of {sides.max():.3g} m; are the "
                               "coordinates in metres?")
    return table


def read_photo(path: str | Path):
    """A photograph as a grey uint8 image (colour converted, 16-bit scaled to 8), or a CalibrationError naming
    the file."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"photograph {path} does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CalibrationError(f"photograph {path} cannot be read as an image (OpenCV reads PNG, JPEG, TIFF, BMP...)")
    if image.ndim == 3:
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2GRAY)
    if image.dtype == np.uint16:
        image = (image / 257.0).round().astype(np.uint8)
    if image.dtype != np.uint8 or image.ndim != 2:
        raise CalibrationError(f"photograph {path}: a {image.dtype} image with {image.ndim} dimensions; give an "
                               "8- or 16-bit grey or colour photograph")
    return image


def check_photo_size(image: np.ndarray, camera: CameraIntrinsics, name: str, camera_name: str) -> None:
    """A photograph must be of the camera's size: its intrinsics are in that image's pixels."""
    h, w = image.shape[:2]
    if (w, h) == (camera.width_px, camera.height_px):
        return
    hint = ""
    ratio = camera.width_px / w
    if abs(ratio - camera.height_px / h) < 1e-3 and ratio != 1:
        hint = (f" (the camera's image is {ratio:g} times the photograph's: a calibration of the full sensor for a "
                "downsampled photograph, or the reverse; use the camera calibration made at this photograph's size)")
    raise CalibrationError(f"{name} is {w} x {h} pixels but the camera calibration {camera_name} is for "
                           f"{camera.width_px} x {camera.height_px}{hint}")
