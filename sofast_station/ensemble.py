"""The design of a heliostat: its facets, where each sits on the frame and how each is canted.

A heliostat (an *ensemble* of facets, OpenCSP's ``DefinitionEnsemble``) is described in a TOML file with one
``[heliostat]`` table, beside the facet files in ``fixtures/facets/``::

    [heliostat]
    name = "heliostat-2x2"
    facet = "heliostat_0m6_100m.toml"   # the facets' shared design (a facet file, relative to this file)
    canting_focal_length_m = 100.0      # on-axis canting: see below (leave out for flat, uncanted facets)
    measure_facet = "R1C1"              # the facet the range finder's distance is taken to (its measure point)
    # measure_point_m = [0.0, 0.0]      # or anywhere on the design surface, gaps included ([x, y, z]: a mark
                                        # on the frame at that height); instead of measure_facet
    grid = { rows = 2, columns = 2, pitch_m = [0.65, 0.65] }   # facets R1C1 .. R2C2, row 1 at the top

    [[heliostat.facets]]                # or list the facets one by one (instead of grid)
    label = "R1C1"
    position_m = [-0.325, 0.325]        # x, y (and z) of the facet frame's origin, heliostat frame, metres
    canting_mrad = [-3.25, -3.25]       # rx, ry (and rz): R = R_z(rz) R_y(ry) R_x(rx), facet -> heliostat
    facet = "other_facet.toml"          # this facet's own design, if it differs from the shared one

    [heliostat.adjusters]               # optional: how a facet is turned (canting instructions in turns)
    points_m = [[0.25, -0.25], [0.25, 0.25], [-0.25, 0.0]]    # the adjusting screws, facet frame (x, y)
    names = ["A", "B", "C"]             # the labels marked on the frame at each screw (the facet map shows them)
    thread_pitch_mm = 1.0               # height change per full turn
    fixed = 2                           # index of a fixed pivot (not turned); leave out: all three turn
    raise_turn = "clockwise"            # which way a screw turns to raise the facet there (seen from the back)
    turn_step = 0.125                   # the finest turn a crew sets with a wrench: turns are rounded to it

    [heliostat.layout]                  # where the station's camera and screen go (sofast_station.layout)
    distance_m = 4.0
    max_slope_error_mrad = 2.0

Frames (docs/conventions.md#heliostat-frame): the **heliostat frame** has its origin at the middle of the
facets' layout, +z along the heliostat's optical axis (towards its focus), and +x to the right, +y up when
looking at the mirrors (OpenCSP's "ensemble coordinates"). Each facet's own frame is its facet file's
(docs/conventions.md#facet-frame); ``facet_to_heliostat(i)`` places it: ``x_heliostat = R_i x_facet + p_i``.

**On-axis canting** (``canting_focal_length_m = F``): each facet's origin lies on the paraboloid
``z = (x^2 + y^2) / (4 F)`` and its z axis is that paraboloid's normal there, turned by ``R_y(ry) R_x(rx)``
with no turn about z (``rx = -asin(n_y)``, ``ry = atan2(n_x, n_z)``): the facets focus the sun on the
heliostat's axis at about F. A facet's own ``position_m`` z or ``canting_mrad`` overrides the rule.

OpenCSP's ensemble definition JSON (``v_facet_locations``, ``r_facet_ensemble`` as rotation vectors that
turn facet vectors into ensemble vectors, ``ensemble_perimeter``, ``v_centroid_ensemble``) and its facet
definition JSON (``v_facet_corners``, ``v_centroid_facet``) are read by :func:`ensemble_from_opencsp`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ConfigError
from .facet import FacetDesign, load_facet, on_outline
from .files import read_toml
from .geometry import Pose

_TURNS = ("clockwise", "counterclockwise")


def rotation_mrad(rx_mrad: float, ry_mrad: float, rz_mrad: float = 0.0) -> np.ndarray:
    """R = R_z(rz) R_y(ry) R_x(rx) from angles in milliradians (the placement convention,
    docs/conventions.md#fixture-frame)."""
    rx, ry, rz = (1e-3 * float(a) for a in (rx_mrad, ry_mrad, rz_mrad))
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    return (np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
            @ np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
            @ np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]]))


def angles_mrad(rotation: np.ndarray) -> tuple[float, float, float]:
    """(rx, ry, rz) in mrad of R = R_z(rz) R_y(ry) R_x(rx); rx and ry tell where R's z axis points
    (they do not depend on rz)."""
    r = np.asarray(rotation, dtype=np.float64)
    return (1e3 * math.atan2(r[2, 1], r[2, 2]), -1e3 * math.asin(max(-1.0, min(1.0, r[2, 0]))),
            1e3 * math.atan2(r[1, 0], r[0, 0]))


@dataclass(frozen=True)
class Adjusters:
    """How a facet is turned on the frame: its adjusting screws (the same on every facet).

    Attributes
    ----------
    points_m : (K, 2) array
        The screws' (x, y) in the facet frame, metres (K >= 3, not all on one line).
    names : tuple of str
        What the assembler calls them.
    thread_pitch_mm : float
        Height change at a screw per full turn, mm.
    fixed : int or None
        Index of a screw that is a fixed pivot (never turned); None: every screw turns and the facet's
        middle keeps its height on average.
    raise_turn : str
        ``"clockwise"`` or ``"counterclockwise"``: the way a screw turns to raise the facet at it, seen
        from the back of the frame.
    turn_step : float
        The finest part of a turn a crew sets with a wrench (1/8 by default): the canting instructions'
        turns are whole multiples of it.
    """

    points_m: np.ndarray
    names: tuple
    thread_pitch_mm: float
    fixed: int | None = None
    raise_turn: str = "clockwise"
    turn_step: float = 0.125

    def __post_init__(self):
        pts = np.array(self.points_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 3 or not np.all(np.isfinite(pts)):
            raise ConfigError("heliostat adjusters: points_m must list at least 3 finite [x, y] screw positions "
                              "in the facet frame, metres")
        centred = pts - pts.mean(axis=0)
        if np.linalg.matrix_rank(centred, tol=1e-6) < 2:
            raise ConfigError("heliostat adjusters: the screws in points_m lie on one line; they cannot tilt the "
                              "facet about both axes")
        pts.setflags(write=False)
        object.__setattr__(self, "points_m", pts)
        names = tuple(str(n) for n in self.names) if self.names else tuple(f"screw {k + 1}" for k in range(len(pts)))
        if len(names) != len(pts):
            raise ConfigError(f"heliostat adjusters: {len(names)} names for {len(pts)} screws in points_m")
        object.__setattr__(self, "names", names)
        pitch = self.thread_pitch_mm
        if isinstance(pitch, bool) or not isinstance(pitch, (int, float)) or not (math.isfinite(pitch) and pitch > 0):
            raise ConfigError(f"heliostat adjusters: thread_pitch_mm must be a positive number of mm, got {pitch!r}")
        object.__setattr__(self, "thread_pitch_mm", float(pitch))
        if self.fixed is not None and (isinstance(self.fixed, bool) or not isinstance(self.fixed, int)
                                       or not 0 <= self.fixed < len(pts)):
            raise ConfigError(f"heliostat adjusters: fixed must be the index (0 to {len(pts) - 1}) of the screw "
                              f"that does not turn, got {self.fixed!r}")
        if self.raise_turn not in _TURNS:
            raise ConfigError(f"heliostat adjusters: raise_turn must be one of {_TURNS}, got {self.raise_turn!r}")
        step = self.turn_step
        if isinstance(step, bool) or not isinstance(step, (int, float)) or not (0.0 < step <= 1.0):
            raise ConfigError(f"heliostat adjusters: turn_step must be the finest part of a turn a crew sets (0 to 1, "
                              f"e.g. 0.125 for 1/8 turn), got {step!r}")
        object.__setattr__(self, "turn_step", float(step))

    def to_dict(self) -> dict:
        return {"points_m": self.points_m.tolist(), "names": list(self.names), "thread_pitch_mm": self.thread_pitch_mm,
                "fixed": self.fixed, "raise_turn": self.raise_turn, "turn_step": self.turn_step}

    @classmethod
    def from_dict(cls, d: dict, source: str = "heliostat") -> "Adjusters":
        unknown = sorted(set(d) - {"points_m", "names", "thread_pitch_mm", "fixed", "raise_turn", "turn_step"})
        if unknown:
            raise ConfigError(f"{source}: [heliostat.adjusters] has unknown key(s) {', '.join(unknown)}")
        if "points_m" not in d or "thread_pitch_mm" not in d:
            raise ConfigError(f"{source}: [heliostat.adjusters] needs points_m and thread_pitch_mm")
        return cls(points_m=d["points_m"], names=tuple(d.get("names", ())), thread_pitch_mm=d["thread_pitch_mm"],
                   fixed=d.get("fixed"), raise_turn=d.get("raise_turn", "clockwise"),
                   turn_step=d.get("turn_step", 0.125))


@dataclass(frozen=True)
class EnsembleFacet:
    """One facet of a heliostat: its label, design and design pose on the frame.

    Attributes
    ----------
    label : str
    design : FacetDesign
    position_m : (3,) array
        The facet frame's origin in the heliostat frame, metres.
    rotation : (3, 3) array
        Facet frame -> heliostat frame (its design canting).
    """

    label: str
    design: FacetDesign
    position_m: np.ndarray
    rotation: np.ndarray

    @property
    def to_heliostat(self) -> Pose:
        """The facet's design pose: facet frame -> heliostat frame."""
        return Pose(self.rotation, self.position_m)

    @property
    def canting_mrad(self) -> tuple[float, float, float]:
        """The design canting (rx, ry, rz), mrad (:func:`angles_mrad` of :attr:`rotation`)."""
        return angles_mrad(self.rotation)

    def corners_m(self) -> np.ndarray:
        """The outline's corners on the design surface, heliostat frame, (N, 3) metres."""
        return self.to_heliostat.apply(self.design.corners_3d())

    def point_m(self, xy_m) -> np.ndarray:
        """The design surface's point at facet-frame (x, y), in the heliostat frame, metres."""
        x, y = (float(v) for v in xy_m)
        return self.to_heliostat.apply(np.array([x, y, float(self.design.z(x, y))]))


@dataclass(frozen=True)
class EnsembleDesign:
    """A heliostat's design: its facets on the frame (heliostat frame, metres; see the module docstring).

    Attributes
    ----------
    name : str
    facets : tuple of EnsembleFacet
    canting_focal_length_m : float or None
        The on-axis canting's focal length, metres; None when the facets are not canted by the rule.
    measure_facet : int
        Index of the facet whose measure point the range finder's distance is taken to (with
        *measure_point_xyz_m*: the facet nearest that point, which must be found for the distance to be
        placed).
    measure_point_xyz_m : (3,) array or None
        The range finder's target in the heliostat frame when it is not a facet's measure point: anywhere on
        the heliostat's design surface, gaps between facets included (a mark on the torque tube, the middle
        of the layout), metres; None: the measure facet's measure point.
    adjusters : Adjusters or None
    layout : dict
        ``[heliostat.layout]``: the station layout's ``distance_m`` and ``max_slope_error_mrad``.
    """

    name: str
    facets: tuple
    canting_focal_length_m: float | None = None
    measure_facet: int = 0
    adjusters: Adjusters | None = None
    layout: dict = field(default_factory=dict)
    measure_point_xyz_m: np.ndarray | None = None

    def __post_init__(self):
        if len(self.facets) < 2:
            raise ConfigError(f"heliostat {self.name!r} has {len(self.facets)} facet(s): a heliostat needs at least 2 "
                              "(measure a single facet with a facet file)")
        labels = [f.label for f in self.facets]
        twice = sorted({lab for lab in labels if labels.count(lab) > 1})
        if twice:
            raise ConfigError(f"heliostat {self.name!r}: facet label(s) {', '.join(twice)} used more than once")
        if not 0 <= int(self.measure_facet) < len(self.facets):
            raise ConfigError(f"heliostat {self.name!r}: measure_facet {self.measure_facet} is not a facet index")
        object.__setattr__(self, "facets", tuple(self.facets))
        object.__setattr__(self, "measure_facet", int(self.measure_facet))
        if self.measure_point_xyz_m is not None:
            object.__setattr__(self, "measure_point_xyz_m", _vector3(self.measure_point_xyz_m, "measure_point_m"))
        _check_no_overlap(self)

    @property
    def n_facets(self) -> int:
        return len(self.facets)

    @property
    def labels(self) -> list[str]:
        return [f.label for f in self.facets]

    def index(self, label: str) -> int:
        """The index of the facet labelled *label* (ConfigError naming the labels when there is none)."""
        try:
            return self.labels.index(label)
        except ValueError:
            raise ConfigError(f"heliostat {self.name!r} has no facet {label!r}; its facets are "
                              f"{', '.join(self.labels)}") from None

    @property
    def focal_length_m(self) -> float:
        """The heliostat's design focal length: the canting's, else its facets' mean, metres."""
        if self.canting_focal_length_m is not None:
            return float(self.canting_focal_length_m)
        return float(np.mean([f.design.focal_length_m for f in self.facets]))

    def corners_m(self) -> np.ndarray:
        """Every facet's corners, facet after facet, heliostat frame, (sum N_i, 3) metres."""
        return np.concatenate([f.corners_m() for f in self.facets])

    @property
    def measure_point_m(self) -> np.ndarray:
        """The range finder's target, heliostat frame, metres: :attr:`measure_point_xyz_m`, else the measure
        facet's measure point."""
        if self.measure_point_xyz_m is not None:
            return np.array(self.measure_point_xyz_m)
        f = self.facets[self.measure_facet]
        return f.point_m(f.design.measure_point_m)

    def with_measure_point(self, xy_m, z_m: float | None = None) -> "EnsembleDesign":
        """This heliostat with the range finder's target at (x, y) of the heliostat frame (metres): on a facet,
        the point of its design surface (that facet's measure point moved there); in a gap between facets,
        the nearest facet's design surface extended to (x, y) (the heliostat's design surface there), or
        at height *z_m* when given (a mark on the frame). Raises ConfigError outside the layout's bounding
        rectangle."""
        x, y = (float(v) for v in xy_m)
        for i, f in enumerate(self.facets):
            local = f.rotation.T @ (np.array([x, y, 0.0]) - f.position_m)
            if on_outline(local[:2], f.design.outline_m) and z_m is None:
                local = _surface_above(f, x, y)
                facets = list(self.facets)
                facets[i] = dataclasses.replace(f, design=dataclasses.replace(f.design, measure_point_m=local.copy()))
                return dataclasses.replace(self, facets=tuple(facets), measure_facet=i, measure_point_xyz_m=None)
        (x0, y0), (x1, y1) = self.outline_m()[[3, 1]]
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise ConfigError(f"heliostat {self.name!r}: the measure point [{x:g}, {y:g}] m lies outside the facets' "
                              f"layout (x {x0:g} to {x1:g}, y {y0:g} to {y1:g} m, heliostat frame)")
        centres = np.array([f.point_m(f.design.centroid_m)[:2] for f in self.facets])
        i = int(np.argmin(np.hypot(centres[:, 0] - x, centres[:, 1] - y)))
        if z_m is None:
            f = self.facets[i]
            z_m = float(f.point_m(_surface_above(f, x, y))[2])
        return dataclasses.replace(self, measure_facet=i, measure_point_xyz_m=np.array([x, y, float(z_m)]))

    def outline_m(self) -> np.ndarray:
        """The facets' bounding rectangle in the heliostat's x-y plane, counter-clockwise, (4, 2) metres."""
        xy = self.corners_m()[:, :2]
        (x0, y0), (x1, y1) = xy.min(axis=0), xy.max(axis=0)
        return np.array([[x1, y0], [x1, y1], [x0, y1], [x0, y0]])

    def layout_design(self) -> FacetDesign:
        """The heliostat as one facet, for the station layout (``sofast_station.layout``) and the
        nominal view: its bounding rectangle, its focal length, its measure point and ``[heliostat.layout]``."""
        mp = self.measure_point_m[:2]
        return FacetDesign(name=self.name, kind="heliostat", focal_length_m=self.focal_length_m,
                           outline_m=self.outline_m(), measure_point_m=mp, alignment_point_m=mp,
                           layout=dict(self.layout))

    def to_dict(self) -> dict:
        """Plain data (what a data dump keeps): every facet's design and pose in full."""
        return {"name": self.name, "canting_focal_length_m": self.canting_focal_length_m,
                "measure_facet": self.measure_facet, "layout": dict(self.layout),
                **({} if self.measure_point_xyz_m is None else
                   {"measure_point_xyz_m": self.measure_point_xyz_m.tolist()}),
                "adjusters": None if self.adjusters is None else self.adjusters.to_dict(),
                "facets": [{"label": f.label, "design": f.design.to_dict(), "position_m": f.position_m.tolist(),
                            "rotation": f.rotation.tolist()} for f in self.facets]}

    @classmethod
    def from_dict(cls, d: dict) -> "EnsembleDesign":
        """The inverse of :meth:`to_dict`."""
        facets = tuple(EnsembleFacet(str(f["label"]), FacetDesign.from_dict(f["design"]),
                                     _vector3(f["position_m"], "position_m"), _rotation(f["rotation"]))
                       for f in d["facets"])
        adj = d.get("adjusters")
        return cls(name=str(d["name"]), facets=facets, canting_focal_length_m=d.get("canting_focal_length_m"),
                   measure_facet=int(d.get("measure_facet", 0)), layout=dict(d.get("layout", {})),
                   adjusters=None if adj is None else Adjusters.from_dict(adj),
                   measure_point_xyz_m=d.get("measure_point_xyz_m"))


def _surface_above(f: EnsembleFacet, x: float, y: float, steps: int = 5) -> np.ndarray:
    """The facet-frame (x, y) of the point of facet *f*'s design surface (extended beyond its outline) that lies
    above the heliostat frame's (*x*, *y*): fixed-point steps along the facet's small tilt (the error shrinks
    by the tilt's square each step)."""
    local = f.rotation.T @ (np.array([x, y, 0.0]) - f.position_m)
    for _ in range(steps):
        p = f.point_m(local[:2])
        local = f.rotation.T @ (np.array([x, y, p[2]]) - f.position_m)
    return local[:2]


def _vector3(v, what: str) -> np.ndarray:
    a = np.array(v, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ConfigError(f"{what} must be 3 finite numbers, got {v!r}")
    a.setflags(write=False)
    return a


def _rotation(r) -> np.ndarray:
    a = np.array(r, dtype=np.float64)
    if a.shape != (3, 3) or not np.allclose(a @ a.T, np.eye(3), atol=1e-9) or np.linalg.det(a) < 0:
        raise ConfigError("a facet's rotation must be a proper 3 x 3 rotation matrix")
    a.setflags(write=False)
    return a


def _check_no_overlap(ensemble: EnsembleDesign) -> None:
    """Facets whose outlines overlap in the heliostat's x-y plane cannot be told apart in a capture."""
    boxes = []
    for f in ensemble.facets:
        xy = f.corners_m()[:, :2]
        boxes.append((xy.min(axis=0), xy.max(axis=0)))
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            lo = np.maximum(boxes[i][0], boxes[j][0])
            hi = np.minimum(boxes[i][1], boxes[j][1])
            if np.all(hi - lo > 1e-6):
                a, b = ensemble.facets[i].label, ensemble.facets[j].label
                raise ConfigError(f"heliostat {ensemble.name!r}: facets {a} and {b} overlap on the frame; give them "
                                  "positions a gap apart")


def on_axis_canting(x_m: float, y_m: float, focal_length_m: float) -> tuple[float, float, np.ndarray]:
    """On-axis canting at (x, y): the paraboloid height z (metres), and the rotation R_y(ry) R_x(rx) that
    turns the facet's z axis onto the paraboloid's normal there."""
    f = float(focal_length_m)
    n = np.array([-x_m / (2.0 * f), -y_m / (2.0 * f), 1.0])
    n /= np.linalg.norm(n)
    rx, ry = -math.asin(n[1]), math.atan2(n[0], n[2])
    return (x_m * x_m + y_m * y_m) / (4.0 * f), 1e3 * rx, rotation_mrad(1e3 * rx, 1e3 * ry)


_KEYS = {"name", "facet", "canting_focal_length_m", "measure_facet", "measure_point_m", "grid", "facets", "adjusters",
         "layout"}
_FACET_KEYS = {"label", "position_m", "canting_mrad", "facet"}


def _number(value, what: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or (positive and value <= 0):
        raise ConfigError(f"{what} must be a {'positive ' if positive else ''}finite number, got {value!r}")
    return float(value)


def ensemble_from_dict(d: dict, base: Path, source: str) -> EnsembleDesign:
    """An :class:`EnsembleDesign` from a ``[heliostat]`` table; facet files are relative to *base*."""
    unknown = sorted(set(d) - _KEYS)
    if unknown:
        raise ConfigError(f"{source}: [heliostat] has unknown key(s) {', '.join(unknown)}; "
                          f"use {', '.join(sorted(_KEYS))}")
    name = str(d.get("name", Path(source).stem))
    designs: dict[str, FacetDesign] = {}

    def design(path) -> FacetDesign:
        if not isinstance(path, str):
            raise ConfigError(f"{source}: a facet design must be a facet file's path, got {path!r}")
        if path not in designs:
            designs[path] = load_facet((base / path).resolve())
        return designs[path]

    shared = design(d["facet"]) if "facet" in d else None
    focal = d.get("canting_focal_length_m")
    if focal is not None:
        focal = _number(focal, f"{source}: canting_focal_length_m", positive=True)
    if ("grid" in d) == ("facets" in d):
        raise ConfigError(f"{source}: [heliostat] needs either grid = {{rows, columns, pitch_m}} or a list of "
                          "[[heliostat.facets]] (one of the two)")
    if "grid" in d:
        g = d["grid"]
        if not isinstance(g, dict) or set(g) != {"rows", "columns", "pitch_m"}:
            raise ConfigError(f"{source}: grid must be {{rows = R, columns = C, pitch_m = [px, py]}}")
        rows, cols = g["rows"], g["columns"]
        if not (isinstance(rows, int) and isinstance(cols, int) and rows >= 1 and cols >= 1 and rows * cols >= 2):
            raise ConfigError(f"{source}: grid rows and columns must be whole numbers >= 1, {rows} x {cols} given")
        pitch = g["pitch_m"]
        pitch = [pitch, pitch] if isinstance(pitch, (int, float)) else pitch
        if not isinstance(pitch, list) or len(pitch) != 2:
            raise ConfigError(f"{source}: grid pitch_m must be [px, py] metres")
        px, py = (_number(p, f"{source}: grid pitch_m", positive=True) for p in pitch)
        entries = [{"label": f"R{r + 1}C{c + 1}", "position_m": [(c - 0.5 * (cols - 1)) * px,
                                                                 (0.5 * (rows - 1) - r) * py]}
                   for r in range(rows) for c in range(cols)]
    else:
        entries = d["facets"]
        if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
            raise ConfigError(f"{source}: [[heliostat.facets]] must be a list of tables")
    facets = []
    for k, e in enumerate(entries):
        where = f"{source}: facet {e.get('label', k + 1)!r}"
        bad = sorted(set(e) - _FACET_KEYS)
        if bad:
            raise ConfigError(f"{where} has unknown key(s) {', '.join(bad)}; use {', '.join(sorted(_FACET_KEYS))}")
        label = str(e.get("label", f"F{k + 1}"))
        if "facet" in e:
            fd = design(e["facet"])
        elif shared is not None:
            fd = shared
        else:
            raise ConfigError(f"{where} has no design: give [heliostat] facet = \"FILE\" or the facet's own facet")
        pos = e.get("position_m")
        if not isinstance(pos, list) or len(pos) not in (2, 3):
            raise ConfigError(f"{where}: position_m must be [x, y] or [x, y, z] metres, got {pos!r}")
        x, y = (_number(p, f"{where}: position_m") for p in pos[:2])
        z_rule, rotation = 0.0, np.eye(3)
        if focal is not None:
            z_rule, _, rotation = on_axis_canting(x, y, focal)
        z = _number(pos[2], f"{where}: position_m z") if len(pos) == 3 else z_rule
        if "canting_mrad" in e:
            c = e["canting_mrad"]
            if not isinstance(c, list) or len(c) not in (2, 3):
                raise ConfigError(f"{where}: canting_mrad must be [rx, ry] or [rx, ry, rz] mrad, got {c!r}")
            rotation = rotation_mrad(*(_number(v, f"{where}: canting_mrad") for v in c))
        facets.append(EnsembleFacet(label, fd, _vector3([x, y, z], "position_m"), _rotation(rotation)))
    labels = [f.label for f in facets]
    if "measure_facet" in d:
        mf = d["measure_facet"]
        if isinstance(mf, str):
            if mf not in labels:
                raise ConfigError(f"{source}: measure_facet {mf!r} is not one of the facets ({', '.join(labels)})")
            measure = labels.index(mf)
        elif isinstance(mf, int) and not isinstance(mf, bool) and 0 <= mf < len(facets):
            measure = mf
        else:
            raise ConfigError(f"{source}: measure_facet must be a facet's label or index, got {mf!r}")
    else:      # the facet nearest the middle of the layout
        xy = np.array([f.position_m[:2] for f in facets])
        measure = int(np.argmin(np.hypot(*(xy - xy.mean(axis=0)).T)))
    adjusters = d.get("adjusters")
    if adjusters is not None:
        if not isinstance(adjusters, dict):
            raise ConfigError(f"{source}: [heliostat.adjusters] must be a table")
        adjusters = Adjusters.from_dict(adjusters, source)
    layout = d.get("layout", {})
    if not isinstance(layout, dict):
        raise ConfigError(f"{source}: [heliostat.layout] must be a table")
    try:
        out = EnsembleDesign(name=name, facets=tuple(facets), canting_focal_length_m=focal, measure_facet=measure,
                             adjusters=adjusters, layout=dict(layout))
        if "measure_point_m" in d:
            if "measure_facet" in d:
                raise ConfigError("give measure_point_m or measure_facet, not both")
            mp = d["measure_point_m"]
            if not isinstance(mp, list) or len(mp) not in (2, 3):
                raise ConfigError(f"measure_point_m must be [x, y] (on the design surface) or [x, y, z] metres, "
                                  f"heliostat frame, got {mp!r}")
            values = [_number(v, "measure_point_m") for v in mp]
            out = out.with_measure_point(values[:2], values[2] if len(values) == 3 else None)
        return out
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def load_ensemble(path: str | Path) -> EnsembleDesign:
    """Read a heliostat file (see the module docstring); errors name the file."""
    path = Path(path)
    data = read_toml(path, "heliostat file")
    if "heliostat" not in data:
        raise ConfigError(f"heliostat file {path} has no [heliostat] table")
    if not isinstance(data["heliostat"], dict):
        raise ConfigError(f"heliostat file {path}: [heliostat] must be a table")
    return ensemble_from_dict(data["heliostat"], path.parent, str(path))


def is_ensemble_file(path: str | Path) -> bool:
    """Whether *path* is a heliostat file (a ``[heliostat]`` table) rather than a facet file."""
    try:
        return "heliostat" in read_toml(Path(path), "design file")
    except ConfigError:
        return False


# -- OpenCSP ---------------------------------------------------------------------------------------------
def _read_json(path: Path, what: str) -> dict:
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"OpenCSP {what} {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"OpenCSP {what} {path} is not valid JSON: {exc}") from None


def _xyz(d, what: str, path: Path) -> np.ndarray:
    try:
        a = np.array([d["x"], d["y"], d["z"]], dtype=np.float64).reshape(3, -1).T
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"{path}: {what} must hold lists x, y and z (OpenCSP's Vxyz)") from None
    if not np.all(np.isfinite(a)):
        raise ConfigError(f"{path}: {what} holds a value that is not a finite number")
    return a


def _rotvec_matrix(v) -> np.ndarray:
    """Rodrigues' formula: the rotation by |v| radians about v."""
    v = np.asarray(v, dtype=np.float64).ravel()
    theta = float(np.linalg.norm(v))
    if theta < 1e-15:
        return np.eye(3)
    k = v / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * (kx @ kx)


def facet_from_opencsp(path: str | Path, focal_length_m: float, name: str | None = None,
                       kind: str = "heliostat") -> FacetDesign:
    """A facet design from OpenCSP's facet definition JSON (``DefinitionFacet``: ``v_facet_corners``,
    ``v_centroid_facet``), with the design focal length OpenCSP keeps elsewhere (its surface definition).

    OpenCSP lists the corners clockwise seen from the mirror side; our outline runs counter-clockwise,
    so a clockwise list is reversed. The centroid is the measure and alignment point.
    """
    path = Path(path)
    data = _read_json(path, "facet definition")
    if "v_facet_corners" not in data:
        raise ConfigError(f"{path} has no v_facet_corners: is it an OpenCSP facet definition (DefinitionFacet)?")
    corners = _xyz(data["v_facet_corners"], "v_facet_corners", path)[:, :2]
    x, y = corners[:, 0], corners[:, 1]
    if float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) < 0:
        corners = corners[::-1]
    centroid = _xyz(data.get("v_centroid_facet", {"x": [0.0], "y": [0.0], "z": [0.0]}), "v_centroid_facet", path)
    c = centroid[0, :2].tolist()
    return FacetDesign(name=name or path.stem, kind=kind, focal_length_m=focal_length_m, outline_m=corners,
                       measure_point_m=c, alignment_point_m=c)


def ensemble_from_opencsp(ensemble_path: str | Path, facet_paths, focal_length_m: float,
                          name: str | None = None, measure_facet: int | None = None) -> EnsembleDesign:
    """A heliostat design from OpenCSP's ensemble definition JSON (``DefinitionEnsemble``) and its facets'
    definitions (one JSON shared by every facet, or one per facet).

    ``v_facet_locations`` are the facet origins in ensemble coordinates, ``r_facet_ensemble`` rotation
    vectors that turn facet vectors into ensemble vectors (OpenCSP applies them so: ``corners.rotate(R) +
    T``); ensemble coordinates are +x right, +y up seen from the mirrors, as our heliostat frame. OpenCSP's
    ``v_centroid_ensemble`` becomes our frame's origin (positions are taken relative to it).

    Parameters
    ----------
    ensemble_path : path
    facet_paths : path or list of paths
    focal_length_m : float
        The facets' design focal length (OpenCSP keeps it in its surface definition, not here).
    name : str, optional
    measure_facet : int, optional
        The facet the measured distance is taken to; default: the one nearest the centroid.
    """
    ensemble_path = Path(ensemble_path)
    data = _read_json(ensemble_path, "ensemble definition")
    for key in ("v_facet_locations", "r_facet_ensemble"):
        if key not in data:
            raise ConfigError(f"{ensemble_path} has no {key}: is it an OpenCSP ensemble definition "
                              "(DefinitionEnsemble)?")
    locations = _xyz(data["v_facet_locations"], "v_facet_locations", ensemble_path)
    rot = data["r_facet_ensemble"]
    rotvecs = [rot[k] for k in sorted(rot, key=int)] if isinstance(rot, dict) else list(rot)
    if len(rotvecs) != len(locations):
        raise ConfigError(f"{ensemble_path}: {len(locations)} facet locations but {len(rotvecs)} facet rotations")
    centroid = np.zeros(3)
    if "v_centroid_ensemble" in data:
        centroid = _xyz(data["v_centroid_ensemble"], "v_centroid_ensemble", ensemble_path)[0]
    paths = [facet_paths] * len(locations) if isinstance(facet_paths, (str, Path)) else list(facet_paths)
    if len(paths) != len(locations):
        raise ConfigError(f"{ensemble_path} has {len(locations)} facets but {len(paths)} facet definitions were given")
    designs: dict = {}
    facets = []
    for k, (loc, rv, fp) in enumerate(zip(locations, rotvecs, paths)):
        if str(fp) not in designs:
            designs[str(fp)] = facet_from_opencsp(fp, focal_length_m)
        facets.append(EnsembleFacet(f"F{k + 1}", designs[str(fp)], _vector3(loc - centroid, "v_facet_locations"),
                                    _rotation(_rotvec_matrix(rv))))
    if measure_facet is None:
        xy = np.array([f.position_m[:2] for f in facets])
        measure_facet = int(np.argmin(np.hypot(xy[:, 0], xy[:, 1])))
    try:
        return EnsembleDesign(name=name or ensemble_path.stem, facets=tuple(facets), measure_facet=measure_facet)
    except ConfigError as exc:          # name the files: the ensemble, and the facets it was given
        given = ", ".join(sorted({Path(p).name for p in paths}))
        raise ConfigError(f"{ensemble_path} with the facet definition {given}: {exc}") from None


def ensemble_to_opencsp(ensemble: EnsembleDesign) -> dict:
    """Our heliostat as OpenCSP's ensemble definition JSON (``DefinitionEnsemble.save_to_json``'s layout):
    what a twin capture written in OpenCSP's format carries."""
    rotvecs = {}
    for k, f in enumerate(ensemble.facets):
        r = f.rotation
        axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])       # 2 sin(angle) u
        norm = float(np.linalg.norm(axis))
        angle = math.atan2(0.5 * norm, 0.5 * (np.trace(r) - 1.0))       # accurate for small angles too
        rotvecs[str(k)] = (axis / norm * angle).tolist() if norm > 1e-15 else [0.0, 0.0, 0.0]
    loc = np.array([f.position_m for f in ensemble.facets])
    # The perimeter: for each corner of the facets' bounding rectangle, the facet corner nearest it.
    owners = [(k, c) for k, f in enumerate(ensemble.facets) for c in range(len(f.design.outline_m))]
    corners = ensemble.corners_m()[:, :2]
    perimeter_facets, perimeter_corners = [], []
    for box_corner in ensemble.outline_m():
        k, c = owners[int(np.argmin(np.hypot(*(corners - box_corner).T)))]
        perimeter_facets.append(k)
        perimeter_corners.append(c)
    return {"v_facet_locations": {"x": loc[:, 0].tolist(), "y": loc[:, 1].tolist(), "z": loc[:, 2].tolist()},
            "r_facet_ensemble": rotvecs,
            "ensemble_perimeter": {"facet_indices": perimeter_facets, "corner_indices": perimeter_corners},
            "v_centroid_ensemble": {"x": [0.0], "y": [0.0], "z": [0.0]}}
