"""OpenCSP's geometry-calibration files: its cameras as the photogrammetric calibrations use them, its fixed-pattern
dot locations (``DotLocationsFixedPattern``), and its screen distortion data with what checks it.

* **camera** (``Camera``): OpenCV reads only fx, fy, cx, cy of a camera matrix, and OpenCSP's files may carry
  K[2,2] != 1: a matrix scaled whole for downsampled images (``camera_sofast_downsampled.h5``: 1/8; the dot
  calibration's Sony camera and the screen-shape camera: 1/4). fx, fy, cx, cy are then in the pixels of
  ``image_shape_xy``, which is the size of the photographs they come with (2160 x 1440 for the dot
  photographs; 4 x that, 8640 x 5760, would be the full sensor); :func:`opencsp_camera` says so;
* **dot locations**: ``DotLocationsFixedPattern/x_dot_index`` (C,), ``y_dot_index`` (R,), ``xyz_dot_loc``
  (R, C, 3) metres, NaN where a dot was not located: :func:`read_dot_locations`, :func:`write_dot_locations`;
* **screen distortion data** (``CalibrateDisplayShape``'s result): ``pts_xy_screen_fraction`` (2, M) and
  ``pts_xyz_screen_coords`` (3, M), in the frame of the marker table the calibration used; its second fraction
  counts from the top of the displayed image (1 minus the fraction the fringes give);
  ``screen_calibration_point_pairs.csv`` pairs each calibration fiducial (OpenCSP's 3 x 3 layout,
  :func:`fiducial_fractions`) with the marker whose corner 0 was surveyed at it: :func:`check_screen_data`.

Every problem is a one-line :class:`~sofast_station.errors.ConfigError` naming the file and what was expected.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from ..errors import ConfigError
from ..geometry import CameraIntrinsics
from ..measure.dots import DotLocations
from ..measure.screen_data import (
    affine_residuals,
    holdout_interpolation,
    local_quadratic,
    node_reproduction,
    screen_model,
    shape_at,
)
from .opencsp import camera_from_opencsp

DOTS_GROUP = "DotLocationsFixedPattern"


def _h5(path: Path, keys: list[str], what: str) -> dict:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path} does not exist (expected OpenCSP's {what})")
    try:
        with h5py.File(path, "r") as h:
            missing = [k for k in keys if k not in h]
            if missing:
                raise ConfigError(f"{path} is not OpenCSP's {what}: it has no {', '.join(missing)}")
            out = {}
            for k in keys:
                v = h[k][()]
                out[k] = v.decode() if isinstance(v, bytes) else v
            return out
    except OSError as exc:
        raise ConfigError(f"{path} is not a readable HDF5 file ({exc}); expected OpenCSP's {what}") from None


def opencsp_camera(path: str | Path) -> tuple[CameraIntrinsics, str | None]:
    """An OpenCSP ``Camera`` file as the calibrations use it, and a note when its K[2,2] is not 1.

    Raises
    ------
    ConfigError
        Not such a file, or a matrix that is not a camera's (zero skew row, positive focal lengths).
    """
    path = Path(path)
    d = _h5(path, ["Camera/intrinsic_mat", "Camera/distortion_coef", "Camera/image_shape_xy"], "Camera file")
    k = np.asarray(d["Camera/intrinsic_mat"], np.float64)
    shape = np.asarray(d["Camera/image_shape_xy"]).ravel()
    dist = np.asarray(d["Camera/distortion_coef"], np.float64).ravel()
    if k.shape != (3, 3) or k[1, 0] != 0 or k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] <= 0:
        raise ConfigError(f"{path}: Camera/intrinsic_mat is not a camera matrix: {k.tolist()}")
    if shape.size != 2 or dist.size not in (4, 5):
        raise ConfigError(f"{path}: need image_shape_xy (2 numbers) and 4 or 5 distortion coefficients, got "
                          f"{shape.tolist()} and {dist.size}")

    camera = camera_from_opencsp(path)
    note = None
    if k[2, 2] != 1.0:
        note = (f"{path.name}: K[2,2] = {k[2, 2]:g}: a matrix scaled whole for images downsampled "
                f"{1 / k[2, 2]:g} times; OpenCV reads only fx, fy, cx, cy, which are for {camera.width_px} x "
                f"{camera.height_px} images (image_shape_xy); K[2,2] is taken as 1")
    return camera, note


def read_dot_locations(path: str | Path) -> DotLocations:
    """OpenCSP's ``DotLocationsFixedPattern`` HDF5 file as :class:`DotLocations` (no uncertainties)."""
    keys = [f"{DOTS_GROUP}/x_dot_index", f"{DOTS_GROUP}/y_dot_index", f"{DOTS_GROUP}/xyz_dot_loc"]
    d = _h5(Path(path), keys, "DotLocationsFixedPattern file")
    x, y, xyz = (np.asarray(d[k]) for k in keys)
    if xyz.ndim != 3 or xyz.shape != (y.size, x.size, 3):
        raise ConfigError(f"{path}: xyz_dot_loc must be (len(y_dot_index), len(x_dot_index), 3) = ({y.size}, {x.size}, "
                          f"3), got {xyz.shape}")
    try:
        return DotLocations(x, y, np.asarray(xyz, np.float64))
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def write_dot_locations(path: str | Path, dots: DotLocations) -> Path:
    """Write *dots* as OpenCSP's ``DotLocationsFixedPattern`` HDF5 file (atomically: a temporary file renamed)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with h5py.File(tmp, "w") as h:
            h[f"{DOTS_GROUP}/x_dot_index"] = dots.x_index
            h[f"{DOTS_GROUP}/y_dot_index"] = dots.y_index
            h[f"{DOTS_GROUP}/xyz_dot_loc"] = dots.xyz_m
        os.replace(tmp, path)
    except OSError as exc:
        raise ConfigError(f"cannot write {path} ({exc})") from None
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_screen_distortion(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """OpenCSP's screen distortion data: (M, 2) fractions (the second from the top) and (M, 3) points, metres."""
    keys = ["pts_xy_screen_fraction", "pts_xyz_screen_coords"]
    d = _h5(Path(path), keys, "screen distortion data (CalibrateDisplayShape)")
    fr, xyz = np.asarray(d[keys[0]], np.float64), np.asarray(d[keys[1]], np.float64)
    if fr.ndim != 2 or xyz.ndim != 2 or fr.shape[0] != 2 or xyz.shape[0] != 3 or fr.shape[1] != xyz.shape[1]:
        raise ConfigError(f"{path}: need pts_xy_screen_fraction (2, M) and pts_xyz_screen_coords (3, M), got "
                          f"{fr.shape} and {xyz.shape}")
    if fr.shape[1] < 16 or not (np.all(np.isfinite(fr)) and np.all(np.isfinite(xyz))):
        raise ConfigError(f"{path}: the distortion data must hold at least 16 finite points")
    return fr.T.copy(), xyz.T.copy()


def read_point_pairs(path: str | Path) -> np.ndarray:
    """OpenCSP's ``screen_calibration_point_pairs.csv``: (K, 2) int, (fiducial index, marker id)."""
    path = Path(path)
    try:
        rows = [line.split(",") for line in path.read_text().splitlines()[1:] if line.strip()]
        pairs = np.array([[int(a), int(b)] for a, b in rows], np.int64)
    except FileNotFoundError:
        raise ConfigError(f"{path} does not exist (expected OpenCSP's screen calibration point pairs)") from None
    except (OSError, UnicodeDecodeError, ValueError):
        raise ConfigError(f"{path} is not OpenCSP's screen calibration point pairs (a header, then lines of "
                          "'fiducial index, marker id')") from None
    if pairs.size == 0 or np.any(pairs < 0):
        raise ConfigError(f"{path}: no point pairs, or negative ids")
    return pairs


def read_image_projection(path: str | Path) -> dict:
    """OpenCSP's ``ImageProjection`` file: the active area's size and position and the main window's size
    (display pixels)."""
    names = ["active_area_size_x", "active_area_size_y", "active_area_position_x", "active_area_position_y",
             "main_window_size_x", "main_window_size_y"]
    d = _h5(Path(path), [f"ImageProjection/{n}" for n in names], "ImageProjection file")
    out = {n: int(np.asarray(d[f"ImageProjection/{n}"]).ravel()[0]) for n in names}
    if out["active_area_size_x"] < 3 or out["active_area_size_y"] < 3:
        raise ConfigError(f"{path}: the active area {out['active_area_size_x']} x {out['active_area_size_y']} px is "
                          "too small")
    return out


def fiducial_fractions(size_x: int, size_y: int) -> np.ndarray:
    """OpenCSP's screen calibration fiducials (``ImageProjection.CalParams``): a 3 x 3 layout, index 0 at the
    top left of the displayed image, 1 % of the size in from its edges, as (9, 2) fractions in the distortion
    data's convention (x: 1 - (pixel + 1/2) / size, y: (pixel + 1/2) / size, from the top)."""
    xs = np.linspace(int(0.01 * size_x), size_x - int(0.01 * size_x), 3).astype(int)
    ys = np.linspace(int(0.01 * size_y), size_y - int(0.01 * size_y), 3).astype(int)
    px, py = np.meshgrid(xs, ys)
    return np.column_stack([1.0 - (px.ravel() + 0.5) / size_x, (py.ravel() + 0.5) / size_y])


def check_screen_data(fractions: np.ndarray, xyz_m: np.ndarray, table, pairs: np.ndarray, projection: dict,
                      display: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """What the published screen-shape files allow to check (docs/calibration.md):

    * ``reproduction``: our screen model built on the data returns its nodes;
    * ``holdout``: built on every other node, how far it strays at the others;
    * ``fiducials``: at each calibration fiducial the data's shape (a local quadratic over the nodes within
      5 % of the screen: the fiducials lie just outside the 1 %..99 % grid) against the surveyed corner 0 of
      the marker paired with it (metres, per fiducial and per axis);
    * ``display`` (with *display* = an OpenCSP display model's nodes and points, :func:`.opencsp.screen_nodes`):
      the data against that model over
      the active area, assuming the model spans the main window's width and the active area's rows (as
      OpenCSP's test data's models do): direct and after the best affine map.
    """
    out = {"nodes": int(len(fractions)), "reproduction": node_reproduction(fractions, xyz_m),
           "holdout": holdout_interpolation(fractions, xyz_m)}
    fid = fiducial_fractions(projection["active_area_size_x"], projection["active_area_size_y"])
    rows = []
    for index, marker in pairs:
        corners = table.corners_of(int(marker))
        if corners is None or not 0 <= index < len(fid):
            raise ConfigError(f"point pair ({index}, {marker}): fiducial {index} or marker {marker} is not known "
                              "(fiducials 0..8, markers of the table)")
        shape = local_quadratic(fractions, xyz_m, fid[index][None])[0]
        rows.append({"fiducial": int(index), "marker": int(marker), "fraction": fid[index].tolist(),
                     "data_m": shape.tolist(), "marker_corner_m": corners[0].tolist(),
                     "difference_m": (shape - corners[0]).tolist()})
    diff = np.array([r["difference_m"] for r in rows])
    out["fiducials"] = {"pairs": rows, "rms_m": np.sqrt(np.nanmean(diff ** 2, axis=0)).tolist(),
                        "max_m": np.nanmax(np.abs(diff), axis=0).tolist()}
    if display is not None:
        d_fr, d_xyz = display
        x0, width = projection["active_area_position_x"], projection["main_window_size_x"]
        mapped = np.column_stack([(x0 + fractions[:, 0] * projection["active_area_size_x"]) / width, fractions[:, 1]])

        model = shape_at(screen_model(d_fr, d_xyz), mapped)
        out["display"] = affine_residuals(model[:, :2], xyz_m[:, :2])
    return out
