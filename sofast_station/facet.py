"""The design of a facet: its shape, outline and named points, in the facet frame.

A facet file (TOML, in ``fixtures/facets/``) holds one ``[facet]`` table::

    [facet]
    name = "dish-5.33"
    kind = "dish"                    # dish | gore | heliostat
    focal_length_m = 5.33            # design paraboloid of revolution z = (x^2 + y^2) / (4 f)
    outline_m = [[0.3, -0.3], [0.3, 0.3], [-0.3, 0.3], [-0.3, -0.3]]   # corners, counter-clockwise
    measure_point_m = [0.0, 0.0]     # where the range finder's distance is taken to
    alignment_point_m = [0.0, 0.0]   # the electronic boresight's alignment point
    edge_rim_m = 0.0                 # optional: a rim along the outline that may not reflect like the
                                     # mirror (a seamed or bevelled glass edge), metres wide
    edge_rim_dark = false            # optional: true when that rim never shows the screen to the camera
                                     # (a ground seam, a steep bevel)
    outline_known = true             # optional: false for a mirror of unknown outline (outline_m is then
                                     # only its expected extent about its middle; no corners are used)

The facet frame's origin is the paraboloid vertex: the facet centre for on-axis facets, a point off the
facet for gore facets (docs/conventions.md#facet-frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ConfigError
from .files import read_toml

KINDS = ("dish", "gore", "heliostat")


@dataclass(frozen=True)
class FacetDesign:
    """Design shape and outline of a facet (all lengths in metres, facet frame).

    Attributes
    ----------
    focal_length_m : float
        Design focal length of the paraboloid of revolution ``z = (x^2 + y^2) / (4 f)``.
    outline_m : (N, 2) array
        Corner points (x, y) of the reflective outline, counter-clockwise seen from +z.
    measure_point_m, alignment_point_m : (2,) arrays
        (x, y) of the range-finder point and of the boresight alignment point.
    layout : dict
        The ``[facet.layout]`` table (the station layout's hints).
    edge_rim_m : float
        Width of a rim inside the outline whose surface is not the mirror's (a seamed or bevelled glass
        edge), metres: it may look lit or dark in the camera, so the corners' uncertainty includes it
        (docs/method.md, facet outline). 0: the mirror reaches the outline.
    edge_rim_dark : bool
        The rim never reflects the screen into the camera (a ground seam, or a bevel turned so steeply that
        its reflection misses the screen): the edge found in the image is the rim's inner edge and the
        outline lies the rim's width outside it. False (default): the rim may look lit or dark, and the
        outline is put midway, uncertain by the rim's width / sqrt(12). Only with ``edge_rim_m > 0``.
    outline_known : bool
        True (default): the outline is the mirror's, and the analysis finds its corners and places the facet
        by them. False: a mirror of unknown outline (a calibration flat or sphere, a mirror cut to no
        drawing; OpenCSP's "undefined" optic): ``outline_m`` is only its expected extent, the facet frame is
        placed by the lit region's centroid at the measured distance, facing the camera and the screen, and
        the figures measured against its corners (placement, boresight) are not reported (docs/method.md,
        mirror of unknown outline). Its measure and alignment points are the frame's origin, the middle of
        the lit region, and its optical tilt is the fitted normal's there.
    """

    name: str
    kind: str
    focal_length_m: float
    outline_m: np.ndarray
    measure_point_m: np.ndarray
    alignment_point_m: np.ndarray
    layout: dict = field(default_factory=dict)
    edge_rim_m: float = 0.0
    edge_rim_dark: bool = False
    outline_known: bool = True

    def __post_init__(self):
        where = f"facet {self.name!r}"
        if self.kind not in KINDS:
            raise ConfigError(f"{where}: kind must be one of {KINDS}, got {self.kind!r}")
        f = float(self.focal_length_m)
        if not (np.isfinite(f) and f > 0):
            raise ConfigError(f"{where}: focal_length_m must be a positive number of metres, got {f}")
        object.__setattr__(self, "focal_length_m", f)
        outline = np.array(self.outline_m, dtype=np.float64)
        if outline.ndim != 2 or outline.shape[1] != 2 or outline.shape[0] < 3 or not np.all(np.isfinite(outline)):
            raise ConfigError(f"{where}: outline_m must be a list of at least 3 finite [x, y] corners")
        x, y = outline[:, 0], outline[:, 1]
        area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
        if area2 <= 0:
            raise ConfigError(f"{where}: outline_m corners must run counter-clockwise seen from +z")
        outline.setflags(write=False)
        object.__setattr__(self, "outline_m", outline)
        rim = self.edge_rim_m
        if isinstance(rim, bool) or not isinstance(rim, (int, float)) or not np.isfinite(rim) or rim < 0:
            raise ConfigError(f"{where}: edge_rim_m must be a width >= 0 in metres, got {rim!r}")
        sides = np.linalg.norm(np.roll(outline, -1, axis=0) - outline, axis=1)
        if rim >= 0.25 * sides.min():
            raise ConfigError(f"{where}: edge_rim_m = {rim:g} m is not a narrow rim of this outline (its "
                              f"shortest side is {sides.min():g} m); give the rim's width in metres")
        object.__setattr__(self, "edge_rim_m", float(rim))
        if not isinstance(self.edge_rim_dark, (bool, np.bool_)):
            raise ConfigError(f"{where}: edge_rim_dark must be true or false, got {self.edge_rim_dark!r}")
        if self.edge_rim_dark and not rim:
            raise ConfigError(f"{where}: edge_rim_dark = true needs the rim's width, edge_rim_m (metres)")
        object.__setattr__(self, "edge_rim_dark", bool(self.edge_rim_dark))
        if not isinstance(self.outline_known, (bool, np.bool_)):
            raise ConfigError(f"{where}: outline_known must be true or false, got {self.outline_known!r}")
        object.__setattr__(self, "outline_known", bool(self.outline_known))
        if not self.outline_known:
            if rim:
                raise ConfigError(f"{where}: a mirror of unknown outline (outline_known = false) has no rim to "
                                  "declare; leave edge_rim_m out")
            for key in ("measure_point_m", "alignment_point_m"):
                if np.any(np.asarray(getattr(self, key), dtype=np.float64) != 0.0):
                    raise ConfigError(f"{where}: a mirror of unknown outline (outline_known = false) is measured "
                                      f"and aligned at its middle, the origin of its frame: leave {key} out")
        for key in ("measure_point_m", "alignment_point_m"):
            p = np.array(getattr(self, key), dtype=np.float64)
            if p.shape != (2,) or not np.all(np.isfinite(p)):
                raise ConfigError(f"{where}: {key} must be a finite [x, y] pair in metres")
            if not on_outline(p, outline):
                lo, hi = outline.min(axis=0), outline.max(axis=0)
                raise ConfigError(f"{where}: {key} = [{p[0]:g}, {p[1]:g}] lies outside the facet's outline (x "
                                  f"{lo[0]:g} to {hi[0]:g} m, y {lo[1]:g} to {hi[1]:g} m, facet frame); give a "
                                  f"point on the facet, or leave {key} out for the outline's centre")
            p.setflags(write=False)
            object.__setattr__(self, key, p)

    @property
    def curvature_per_m(self) -> float:
        """Design focal power kappa = 1/f, 1/m."""
        return 1.0 / self.focal_length_m

    @property
    def coefficients(self) -> np.ndarray:
        """Design surface as (A, B, C, D, E, F) of z = A x^2 + B y^2 + C x + D y + E xy + F."""
        a = 1.0 / (4.0 * self.focal_length_m)
        return np.array([a, a, 0.0, 0.0, 0.0, 0.0])

    def z(self, x, y):
        """Design surface height (metres) at facet-frame (x, y)."""
        return (np.asarray(x) ** 2 + np.asarray(y) ** 2) / (4.0 * self.focal_length_m)

    @property
    def middle_m(self) -> np.ndarray:
        """Centre (x, y) of the outline's bounding box, metres: where the station aims."""
        return 0.5 * (self.outline_m.min(axis=0) + self.outline_m.max(axis=0))

    @property
    def centroid_m(self) -> np.ndarray:
        """Area centroid (x, y) of the outline polygon, metres."""
        x, y = self.outline_m[:, 0], self.outline_m[:, 1]
        xn, yn = np.roll(x, -1), np.roll(y, -1)
        cross = x * yn - xn * y
        area = cross.sum() / 2.0
        return np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)

    def corners_3d(self) -> np.ndarray:
        """Outline corners on the design surface, (N, 3) metres."""
        x, y = self.outline_m[:, 0], self.outline_m[:, 1]
        return np.column_stack([x, y, self.z(x, y)])

    def to_dict(self) -> dict:
        d = {"name": self.name, "kind": self.kind, "focal_length_m": self.focal_length_m,
             "outline_m": self.outline_m.tolist(), "measure_point_m": self.measure_point_m.tolist(),
             "alignment_point_m": self.alignment_point_m.tolist(), "layout": dict(self.layout)}
        if self.edge_rim_m:         # (absent when there is none: designs and hashes from before it)
            d["edge_rim_m"] = self.edge_rim_m
        if self.edge_rim_dark:
            d["edge_rim_dark"] = True
        if not self.outline_known:  # (absent for a known outline: designs and hashes from before it)
            d["outline_known"] = False
        return d

    @classmethod
    def from_dict(cls, d: dict, source: str = "facet") -> "FacetDesign":
        missing = [k for k in ("name", "kind", "focal_length_m", "outline_m") if k not in d]
        if missing:
            raise ConfigError(f"{source}: [facet] is missing {', '.join(missing)}")
        outline = np.asarray(d["outline_m"], dtype=np.float64)
        known = d.get("outline_known", True)
        centre = outline.mean(axis=0).tolist() if outline.ndim == 2 and known is not False else [0.0, 0.0]
        try:
            return cls(name=str(d["name"]), kind=str(d["kind"]), focal_length_m=d["focal_length_m"],
                       outline_m=outline, measure_point_m=d.get("measure_point_m", centre),
                       alignment_point_m=d.get("alignment_point_m", centre), layout=dict(d.get("layout", {})),
                       edge_rim_m=d.get("edge_rim_m", 0.0), edge_rim_dark=d.get("edge_rim_dark", False),
                       outline_known=known)
        except ConfigError as exc:            # name where the design came from (a file, a recipe)
            msg = str(exc)
            raise ConfigError(msg if source == "facet" or source in msg else f"{source}: {msg}") from None


def on_outline(point: np.ndarray, outline_m: np.ndarray, tol_m: float = 1e-9) -> bool:
    """Whether the (x, y) *point* lies inside the polygon *outline_m* or on its edge (even-odd rule)."""
    x, y = float(point[0]), float(point[1])
    a, b = outline_m, np.roll(outline_m, -1, axis=0)
    d = b - a
    t = np.clip(((x - a[:, 0]) * d[:, 0] + (y - a[:, 1]) * d[:, 1]) / np.maximum((d ** 2).sum(axis=1), 1e-300), 0, 1)
    if np.min(np.hypot(a[:, 0] + t * d[:, 0] - x, a[:, 1] + t * d[:, 1] - y)) <= tol_m:
        return True
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_cross = a[:, 0] + (y - a[:, 1]) * d[:, 0] / d[:, 1]
    return bool(np.count_nonzero(crosses & (x < x_cross)) % 2)


def load_facet(path: str | Path) -> FacetDesign:
    """Read a facet file (see the module docstring); errors name the file."""
    path = Path(path)
    data = read_toml(path, "facet file")
    if "facet" not in data:
        raise ConfigError(f"facet file {path} has no [facet] table")
    try:
        return FacetDesign.from_dict(data["facet"], source=str(path))
    except ConfigError as exc:
        msg = str(exc)
        raise ConfigError(msg if str(path) in msg else f"{path}: {msg}") from None
