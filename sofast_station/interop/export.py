"""A measured surface for the tools the field uses: CSV, PLY, OpenCSP's processed-result HDF5, SolTrace.

What is written, for every valid point of the analysis, in the facet frame (docs/conventions.md#frames):

- the point (x, y, z, metres): where the pixel's ray meets the fitted surface (the analysis' point);
- the measured unit normal (n_x, n_y, n_z), from the measured slopes (s = -n_xy / n_z);
- the slope error against the design (e_x, e_y, mrad, docs/conventions.md#residuals);
- the height error against the design (µm), integrated from those slope errors by least squares on a
  grid (:func:`~sofast_station.measure.heights.integrate_slopes`, zero mean) and taken at the point's cell.

Formats (each file names the facet's serial in its header and in its file name):

``csv``      one row per point, a commented header with the serial, facet, frame and units; the column
             names carry the units.
``ply``      binary little-endian PLY with ``x y z nx ny nz`` (and ``height_error_um``), units in comments.
``opencsp``  the layout of OpenCSP's SOFAST processing output (``DataSofastCalculation/facet/facet_000``):
             the slope coefficients (its (C, 2A, E1) and (D, E2, 2B)), the slopes and points at the valid
             pixels (raster order) and the pixel mask; read back by
             :func:`~sofast_station.interop.opencsp.read_opencsp_result` to the same figures.
``soltrace`` SolTrace's finite-element surface (``.fed``): a title line, the number of points, then
             ``x y z`` per point in metres, z the design's height plus the measured height error.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ..errors import ConfigError
from ..files import temp_path_for
from ..measure.heights import grid_slopes, integrate_slopes

FORMATS = ("csv", "ply", "opencsp", "soltrace")
SUFFIX = {"csv": ".csv", "ply": ".ply", "opencsp": ".h5", "soltrace": ".fed"}


@dataclass
class SurfacePoints:
    """A facet's measured points ready to write (arrays of N valid points, facet frame).

    Attributes
    ----------
    serial, facet : str
    points_m : (3, N) array
    normals : (3, N) array
        Unit normals, n_z > 0.
    slope_error_mrad : (2, N) array
        Against the design.
    height_error_um : (N,) array
        Against the design, NaN where the grid had no neighbour to integrate from.
    design_z_m : (N,) array
        The design surface's height at (x, y).
    slopes : (2, N) array
        Measured slopes (dimensionless).
    valid : (rows, columns) bool array
        The camera pixels the points come from (raster order).
    coefficients : dict
        The fitted parabola's A, B, C, D (1/m, -), and its separate twists E1, E2 (1/m).
    """

    serial: str
    facet: str
    points_m: np.ndarray
    normals: np.ndarray
    slope_error_mrad: np.ndarray
    height_error_um: np.ndarray
    design_z_m: np.ndarray
    slopes: np.ndarray
    valid: np.ndarray
    coefficients: dict


def surface_points(analysis, record: dict, design, cells_across: int = 160) -> SurfacePoints:
    """The export's arrays from an analysis (a reprocessed dump), its record and its facet design."""
    x, y, z = (np.asarray(c, np.float64) for c in analysis.points_facet_m)
    s = np.asarray(analysis.slopes, np.float64)
    n = np.stack([-s[0], -s[1], np.ones_like(s[0])])
    n /= np.linalg.norm(n, axis=0)
    ex, ey = (np.asarray(e, np.float64) for e in analysis.residuals_mrad["design"])
    spacing = math.sqrt(max(float(np.ptp(x)) * float(np.ptp(y)), 1e-18) / max(x.size, 1))
    cell = max(max(float(np.ptp(x)), float(np.ptp(y)), 1e-9) / cells_across, 1.5 * spacing)
    g = grid_slopes(x, y, np.tan(1e-3 * ex), np.tan(1e-3 * ey), cell, centred=True)
    heights = integrate_slopes(g["s_x"], g["s_y"], cell)
    x0, _, y0, _ = g["extent_m"]
    col = np.clip(((x - x0) / cell).astype(int), 0, heights.shape[1] - 1)
    row = np.clip(((y - y0) / cell).astype(int), 0, heights.shape[0] - 1)
    coef = record.get("coefficients") or {}
    e1, e2 = (record.get(k) for k in ("twist_e1_mrad_per_m", "twist_e2_mrad_per_m"))
    if not coef or e1 is None or e2 is None:
        raise ConfigError(f"the record of {record.get('serial')} has no fitted coefficients or twists (a fault?): "
                          "nothing to export")
    return SurfacePoints(str(record.get("serial", "")), str(record.get("facet", design.name)), np.stack([x, y, z]), n,
                         np.stack([ex, ey]), 1e6 * heights[row, col], np.asarray(design.z(x, y), np.float64), s,
                         np.asarray(analysis.valid, bool),
                         {"A": float(coef["A"]), "B": float(coef["B"]), "C": float(coef["C"]), "D": float(coef["D"]),
                          "E1": 1e-3 * float(e1), "E2": 1e-3 * float(e2)})


def _header(p: SurfacePoints) -> list[str]:
    return [f"serial: {p.serial}", f"facet: {p.facet}", "frame: the facet frame of sofast-station "
            "(docs/conventions.md#frames), z toward the viewer of the mirror side", f"points: {p.points_m.shape[1]}",
            "units: x, y, z in metres; normals unit vectors; slope errors in mrad; height error in micrometres, "
            "against the design"]


def write_csv(p: SurfacePoints, path: Path) -> None:
    columns = "x_m,y_m,z_m,n_x,n_y,n_z,slope_error_x_mrad,slope_error_y_mrad,height_error_um"
    data = np.column_stack([p.points_m.T, p.normals.T, p.slope_error_mrad.T, p.height_error_um])
    np.savetxt(path, data, delimiter=",", fmt="%.9g", header="\n".join(_header(p)) + "\n" + columns, comments="# ")


def write_ply(p: SurfacePoints, path: Path) -> None:
    vertex = np.empty(p.points_m.shape[1], dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"),
                                                  ("ny", "<f4"), ("nz", "<f4"), ("height_error_um", "<f4")])
    for name, values in zip(("x", "y", "z"), p.points_m):
        vertex[name] = values
    for name, values in zip(("nx", "ny", "nz"), p.normals):
        vertex[name] = values
    vertex["height_error_um"] = p.height_error_um
    head = ["ply", "format binary_little_endian 1.0", *(f"comment {line}" for line in _header(p)),
            f"element vertex {vertex.size}", "property double x", "property double y", "property double z",
            "property float nx", "property float ny", "property float nz", "property float height_error_um",
            "end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("ascii", "replace"))
        fh.write(vertex.tobytes())


def write_opencsp(p: SurfacePoints, path: Path) -> None:
    c = p.coefficients
    g = "DataSofastCalculation/facet/facet_000/"
    with h5py.File(path, "w") as h:
        h.attrs["written_by"] = "sofast-station export surface"
        h.attrs["serial"] = p.serial
        h.attrs["facet"] = p.facet
        h.attrs["units"] = "metres; slopes dimensionless; slope coefficients (C, 2A, E1), (D, E2, 2B) in 1/m and -"
        h[g + "SlopeSolverData/slope_coefs_facet"] = np.array([[c["C"], 2 * c["A"], c["E1"]],
                                                               [c["D"], c["E2"], 2 * c["B"]]])
        h[g + "SlopeSolverData/slopes_facet_xy"] = p.slopes
        h[g + "SlopeSolverData/v_surf_points_facet"] = p.points_m
        h[g + "CalculationImageProcessingFacet/mask_processed"] = p.valid
        h["DataSofastInput/optic_definition/facet_000/ParamsSurface/robust_least_squares"] = False


def write_soltrace(p: SurfacePoints, path: Path) -> None:
    z = p.design_z_m + 1e-6 * np.nan_to_num(p.height_error_um)
    with open(path, "w", encoding="ascii", errors="replace") as fh:
        fh.write(f"{p.serial} {p.facet} facet frame metres: design height plus measured height error\n")
        fh.write(f"{z.size}\n")
        np.savetxt(fh, np.column_stack([p.points_m[0], p.points_m[1], z]), fmt="%.9f")


WRITERS = {"csv": write_csv, "ply": write_ply, "opencsp": write_opencsp, "soltrace": write_soltrace}


def export_surface(points: SurfacePoints, fmt: str, path: Path) -> Path:
    """Write *points* as *fmt* (:data:`FORMATS`) to *path*, atomically (a temporary file renamed)."""
    if fmt not in WRITERS:
        raise ConfigError(f"unknown export format {fmt!r}: use one of {', '.join(FORMATS)}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path_for(path)
    try:
        WRITERS[fmt](points, tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
