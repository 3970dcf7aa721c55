"""A dot target's 3-D dot locations from photographs (``sofast-station calibrate dots``; OpenCSP's
``CalibrateSofastFixedDots``), and the dated ``dots`` record the fixed-pattern method reads.

The target (a board of round dots on a square lattice) and some surveyed ArUco markers are photographed from
a few places with one calibrated camera; in each photograph the technician gives the pixel of the same dot,
the origin, which gets index (0, 0). Per photograph the routine finds the markers and the dots and indexes the
dots from the origin (:mod:`sofast_station.measure.dots`); then one bundle adjustment locates every dot seen
in two photographs or more, in the markers' frame, with its covariance. The record keeps the grid
(x index, y index, xyz and each coordinate's U, k = 2) and what each photograph contributed;
:func:`dot_locations_from_record` turns it back into :class:`~sofast_station.measure.dots.DotLocations`.

The indices: x grows along the markers' frame's +x (or the first of its axes the lattice runs along), y
along the next, so two calibrations of one target agree on them whatever the photographs' orientation.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..geometry import CameraIntrinsics
from ..measure.dots import DotLocations, DotSolution, DotView, find_dots, index_dots, locate_dots
from ..measure.markers import DEFAULT_DICTIONARY, MarkerTable, detect_markers, marker_correspondences
from .errors import CalibrationError
from .photo_inputs import check_photo_size
from .store import read_record, write_record

log = logging.getLogger(__name__)

SCHEMA = 1
KIND = "dots"
#: RMS residuals (px) above which the calibration warns: dots found to a few hundredths of a pixel and
#: corners to a few tenths are normal; more means blur, a moved target or a poor camera calibration.
DOT_RMS_WARN_PX, MARKER_RMS_WARN_PX = 0.3, 1.0
#: Fewest of the table's markers per photograph (a pose from fewer rests on one square's shape).
MIN_MARKERS = 2


@dataclass
class DotPhoto:
    """One photograph's findings (for the record and the summary)."""

    name: str
    origin_px: tuple
    markers: list
    markers_unlisted: list
    dots_found: int
    dots_indexed: int

    def to_dict(self) -> dict:
        return {"name": self.name, "origin_px": list(self.origin_px), "markers": self.markers,
                "markers_unlisted": self.markers_unlisted, "dots_found": self.dots_found,
                "dots_indexed": self.dots_indexed}


@dataclass
class DotCalibration:
    """What :func:`calibrate_dots` found: per photograph its findings and observations, the solution, the
    settings, the verdict and its reasons."""

    camera: CameraIntrinsics
    photos: list
    solution: DotSolution
    settings: dict
    verdict: str = "pass"
    reasons: list = field(default_factory=list)
    views: list = field(default_factory=list)      # the observations adjusted (DotView per photograph)

    @property
    def locations(self) -> DotLocations:
        return self.solution.locations


def calibrate_dots(photos: list[tuple[str, np.ndarray]], origins_px: list, camera: CameraIntrinsics, camera_name: str,
                   table: MarkerTable, *, dictionary: str = DEFAULT_DICTIONARY, refine: str = "edges",
                   dark: bool = True, dot_area_px: tuple[float, float] = (3.0, 2000.0), min_circularity: float = 0.8,
                   min_views: int = 2, progress=None) -> DotCalibration:
    """Locate a dot target's dots from photographs of it and of surveyed markers.

    Parameters
    ----------
    photos : list of (name, image)
        Grey uint8 photographs of the camera's size, two or more, from different places.
    origins_px : list of (column, row)
        Per photograph, a pixel on or next to the same dot (index (0, 0)).
    camera : CameraIntrinsics
    camera_name : str
        For messages.
    table : MarkerTable
    dictionary, refine : str
        The markers' ArUco dictionary and corner refinement.
    dark : bool
        Dark dots on a light target.
    dot_area_px : (float, float)
        Accepted dot areas in the photographs, square pixels.
    min_circularity : float
        Of an accepted dot (1 for a disc; a square is 0.785).
    min_views : int
        A dot is located when this many photographs show it (at least 2).
    progress : callable, optional
        ``progress(text)``: a line per photograph and per adjustment round.

    Raises
    ------
    CalibrationError
        Fewer than two photographs, origins not one per photograph, a photograph of another size, too few
        markers in a photograph, no dots, dots not indexable from the origin, no dot in two photographs.
    """
    say = progress or (lambda text: None)
    if len(photos) < 2:
        raise CalibrationError(f"locating dots needs photographs from at least 2 places, got {len(photos)}")
    if len(origins_px) != len(photos):
        raise CalibrationError(f"give one origin per photograph (--origin COLUMN,ROW, in the photographs' order): "
                               f"{len(photos)} photograph(s), {len(origins_px)} origin(s)")
    views, found = [], []
    for n, ((name, image), origin) in enumerate(zip(photos, origins_px), 1):
        check_photo_size(image, camera, name, camera_name)
        markers = detect_markers(image, dictionary, refine, camera=camera)
        ids, marker_px, marker_world, unlisted = marker_correspondences(markers, table)
        if len(ids) < MIN_MARKERS:
            raise CalibrationError(f"too few markers in {name}: found {sorted(markers)}, of which {ids.tolist()} are "
                                   f"in the marker table; {MIN_MARKERS} or more are needed in every photograph (is it "
                                   f"the right table and dictionary, --dictionary {dictionary}?)")
        centres, _ = find_dots(image, dark=dark, min_area_px=dot_area_px[0], max_area_px=dot_area_px[1],
                               min_circularity=min_circularity)
        if len(centres) < 9:
            raise CalibrationError(f"no dot lattice in {name}: {len(centres)} dot(s) of {dot_area_px[0]:g} to "
                                   f"{dot_area_px[1]:g} px^2 found; is the target in focus and lit, --dot-area right "
                                   "for its dots, and --light-dots given when they are light on dark?")
        try:
            indices, dot_px = index_dots(centres, origin)
        except ValueError as exc:
            raise CalibrationError(f"the dots of {name} cannot be indexed from the origin {tuple(origin)}: {exc}; give "
                                   "the pixel of the origin dot in this photograph (--origin COLUMN,ROW)") from None
        if len(indices) < 9:
            raise CalibrationError(f"the dots of {name} cannot be indexed from the origin {tuple(origin)}: only "
                                   f"{len(indices)} dot(s) follow a lattice from it")
        views.append(DotView(name, marker_world, marker_px, indices, dot_px))
        found.append(DotPhoto(name, (float(origin[0]), float(origin[1])), ids.tolist(), unlisted, len(centres),
                              len(indices)))
        say(f"photograph {n}/{len(photos)} {name}: {len(ids)} marker(s), {len(centres)} dots found, {len(indices)} "
            "indexed")
    say(f"adjusting {len(views)} camera poses and the dots")
    try:
        solution = locate_dots(camera, views, min_views=min_views, progress=say)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    settings = {"dictionary": dictionary, "corner_refinement": refine, "dark_dots": dark,
                "dot_area_px": list(dot_area_px), "min_circularity": min_circularity, "min_views": min_views}
    cal = DotCalibration(camera, found, solution, settings, views=views)
    if solution.rms_px["dots"] > DOT_RMS_WARN_PX:
        cal.reasons.append(f"dot residuals {solution.rms_px['dots']:.3f} px RMS (over {DOT_RMS_WARN_PX:g} px): blur, a "
                           "target that moved between photographs, or a poor camera calibration")
    if solution.rms_px["markers"] > MARKER_RMS_WARN_PX:
        cal.reasons.append(f"marker corner residuals {solution.rms_px['markers']:.3f} px RMS (over "
                           f"{MARKER_RMS_WARN_PX:g} px): check the survey of the markers")
    if solution.dots_dropped:
        cal.reasons.append(f"{solution.dots_dropped} indexed dot(s) not located (seen in fewer than {min_views} "
                           "photographs after outliers)")
    cal.verdict = "warn" if any("RMS" in r for r in cal.reasons) else "pass"
    return cal


def _nested(values: np.ndarray) -> list:
    """An array as nested lists, NaN as None (JSON has no NaN)."""
    return np.where(np.isfinite(values), values, None).tolist()


def dot_record(cal: DotCalibration) -> dict:
    """The record's content (without its id, time and source)."""
    loc, sol = cal.locations, cal.solution
    return {"schema": SCHEMA, "kind": KIND, "x_index": loc.x_index.tolist(), "y_index": loc.y_index.tolist(),
            "xyz_m": _nested(loc.xyz_m), "xyz_m_U": _nested(loc.xyz_U_m), "k": 2,
            "dots_located": int(loc.located.sum()), "dots_dropped": sol.dots_dropped, "outliers": sol.outliers,
            "sigma_px": sol.sigma_px, "rms_px": sol.rms_px, "index_map": sol.index_map.tolist(),
            "camera": cal.camera.to_dict(), "settings": cal.settings,
            "photos": [dict(p.to_dict(), **{k: v for k, v in row.items() if k != "name"},
                            world_to_camera=pose.to_dict(), pose_std=std.tolist())
                       for p, row, pose, std in zip(cal.photos, sol.views, sol.poses, sol.pose_std)],
            "verdict": cal.verdict, "reasons": cal.reasons}


def save_dots(data_dir: str | Path, cal: DotCalibration, source: str, inputs: dict,
              station: dict | None = None) -> Path:
    """Write a ``dots`` record under ``data_dir/calibration/dots/`` (*station*: the identity of the station it
    is made on); returns its path."""
    content = dot_record(cal)

    def build(record_id: str, created: str) -> dict:
        return {"record_id": record_id, "created": created, "source": source, "inputs": inputs, **content}

    path, _ = write_record(data_dir, KIND, build, station=station)
    return path


def dot_locations_from_record(record: dict, where: str = "dots record") -> DotLocations:
    """The (rows, columns, 3) dot locations and their x and y indices (with each coordinate's U) from a
    ``dots`` record's content (a pure function of the parsed JSON); ConfigError naming *where* when it is not
    one."""
    if not isinstance(record, dict) or record.get("kind") != KIND:
        raise ConfigError(f"{where} is not a dots record")
    if record.get("schema") != SCHEMA:
        raise ConfigError(f"{where} has schema {record.get('schema')!r}; this software reads schema {SCHEMA}")
    try:
        xyz = np.array(record["xyz_m"], dtype=np.float64)            # None -> NaN
        u = np.array(record["xyz_m_U"], dtype=np.float64) if record.get("xyz_m_U") is not None else None
        return DotLocations(np.asarray(record["x_index"]), np.asarray(record["y_index"]), xyz, u)
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{where} is incomplete or damaged ({exc}); rerun 'sofast-station calibrate dots'") from None


def load_dots(path: str | Path) -> tuple[DotLocations, dict]:
    """A ``dots`` record: its dot locations and the whole record; ConfigError naming the file otherwise."""
    record = read_record(path, KIND, SCHEMA, "dots record", "rerun 'sofast-station calibrate dots'")
    return dot_locations_from_record(record, f"dots record {path}"), record


def summary_text(cal: DotCalibration, path: Path | None = None) -> str:
    """The command's summary: per photograph, the grid, residuals and U, the verdict."""
    loc, sol = cal.locations, cal.solution
    located = loc.located
    u = loc.xyz_U_m[located] * 1000.0
    lines = [f"Dot locations from {len(cal.photos)} photograph(s)" + (f"; record {path}" if path else "")]
    for p, row in zip(cal.photos, sol.views):
        lines.append(f"  {p.name}: markers {p.markers}, {p.dots_found} dots found, {p.dots_indexed} indexed; residuals "
                     f"corners {row['marker_rms_px']:.3f} px, dots {row['dot_rms_px']:.3f} px RMS"
                     + (f", {row['outliers']} outlier(s)" if row["outliers"] else ""))
    lines += [f"  grid x {loc.x_index[0]}..{loc.x_index[-1]}, y {loc.y_index[0]}..{loc.y_index[-1]}: "
              f"{int(located.sum())} of {located.size} dots located ({sol.dots_dropped} indexed but seen in too few "
              f"photographs, {sol.outliers} outlier observation(s))",
              f"  noise from the residuals: corners {sol.sigma_px['markers']:.3f} px, dots "
              f"{sol.sigma_px['dots']:.3f} px",
              "  U (k=2) of the dots, median (largest): x {:.3f} ({:.3f}) mm, y {:.3f} ({:.3f}) mm, z {:.3f} "
              "({:.3f}) mm".format(*np.ravel(np.column_stack([np.median(u, axis=0), u.max(axis=0)])))]
    lines += [f"    - {r}" for r in cal.reasons]
    lines.append(f"verdict: {cal.verdict.upper()}")
    return "\n".join(lines)
