"""The twin of a heliostat: several facets on a frame, each with its own true shape and canting error.

Every facet is traced as the single-facet twin traces one (:class:`~sofast_station.twin.trace.FacetTrace`,
in the frame where that facet really is), and the traces are merged pixel by pixel: a pixel that sees
several facets sees the nearest (a facet hiding part of another), and its coverage is the sum of theirs
(the edge pixels of neighbours a gap of less than a pixel apart). The merged picture is captured by the
single-facet twin's own renderer and sensor. A ray reflected by one facet and blocked by another on its way
to the screen is not modelled: the facets of a heliostat turn by a few milliradians against each other.

Frames (docs/conventions.md#heliostat-frame): the true heliostat frame is placed in the fixture by
:attr:`TrueHeliostat.placement_mm` / ``placement_mrad`` (``x_fixture = R x_heliostat + t``, about the
heliostat frame's origin); facet i's true frame is its design pose on that frame, then its own
:class:`~sofast_station.twin.parameters.TrueFacet` placement (its canting and position errors, about its
middle, in its design frame).

Ground truth (:func:`heliostat_truth`) applies the conventions' definitions to the exact surfaces
(docs/conventions.md#canting); nothing here is shared with ``sofast_station.measure``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from ..ensemble import EnsembleDesign
from ..errors import ConfigError, GeometryError
from ..geometry import Pose, StationGeometry
from .camera import TwinCamera
from .parameters import TrueFacet, TwinOptics, _check_keys, _vector
from .station import TwinStation
from .trace import TRACE_ARRAYS, FacetTrace, facet_to_fixture_pose, rotation_zyx
from .truth import truth_from_samples

#: The heliostat optical frame's tilt iteration stops when both updates are below this, radians.
TILT_TOLERANCE_RAD = 1e-12


@dataclass(frozen=True)
class TrueHeliostat:
    """A heliostat as it really is: every facet's true shape and canting error, and where it sits.

    Parameters
    ----------
    facets : tuple of TrueFacet
        One per facet of the design, in its order. A facet's ``placement_mrad`` is its canting error (the
        rotation R_z R_y R_x about its middle, in its design frame, from its design canting), its
        ``placement_mm`` its position error on the frame.
    placement_mm, placement_mrad : (3,) tuples
        The heliostat frame in the fixture: ``x_fixture = R x_heliostat + t``, R = R_z R_y R_x (mrad), t (mm).
    missing : tuple of str
        Labels of facets not mounted (nothing there to see).
    obstructed : dict
        Label -> fraction (0 to 1) of the facet's width, from its +x side, that something in front of it
        hides from the camera.
    """

    facets: tuple
    placement_mm: tuple = (0.0, 0.0, 0.0)
    placement_mrad: tuple = (0.0, 0.0, 0.0)
    missing: tuple = ()
    obstructed: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        owner = "TrueHeliostat"
        facets = tuple(f if isinstance(f, TrueFacet) else TrueFacet.from_dict(f) for f in self.facets)
        object.__setattr__(self, "facets", facets)
        object.__setattr__(self, "placement_mm", _vector(owner, "placement_mm", self.placement_mm, 3))
        object.__setattr__(self, "placement_mrad", _vector(owner, "placement_mrad", self.placement_mrad, 3))
        object.__setattr__(self, "missing", tuple(str(m) for m in self.missing))
        obstructed = {}
        for label, frac in dict(self.obstructed).items():
            if isinstance(frac, bool) or not isinstance(frac, (int, float)) or not 0.0 <= frac <= 1.0:
                raise ConfigError(f"{owner}.obstructed[{label!r}] must be a fraction from 0 to 1, got {frac!r}")
            obstructed[str(label)] = float(frac)
        object.__setattr__(self, "obstructed", obstructed)

    def to_dict(self) -> dict:
        return {"facets": [f.to_dict() for f in self.facets], "placement_mm": list(self.placement_mm),
                "placement_mrad": list(self.placement_mrad), "missing": list(self.missing),
                "obstructed": dict(self.obstructed)}

    @classmethod
    def from_dict(cls, d: dict, n_facets: int | None = None) -> "TrueHeliostat":
        """From plain data; ``facets`` may be one table (every facet alike) or a list of them; with
        *n_facets* a single table is repeated."""
        _check_keys("TrueHeliostat", d, cls)
        d = dict(d)
        facets = d.get("facets", {})
        if isinstance(facets, dict):
            if n_facets is None:
                raise ConfigError("TrueHeliostat.facets must list one table per facet")
            facets = [facets] * n_facets
        d["facets"] = tuple(facets)
        return cls(**d)


def heliostat_from_simulation(sim: dict, ensemble: EnsembleDesign, where: str = "[simulation]") -> TrueHeliostat:
    """The true heliostat a station file's ``[simulation]`` describes::

        [simulation]
        facet = { slope_error_rms_mrad = 0.2 }           # every facet's true shape (TrueFacet), the default
        [simulation.heliostat]
        placement_mm = [1.0, -0.5, 0.5]                  # the heliostat in the fixture
        placement_mrad = [0.4, -0.3, 0.2]
        missing = ["R1C2"]                               # facets not mounted
        obstructed = { R2C1 = 0.3 }                      # a facet partly hidden (fraction of its width)
        [simulation.heliostat.facets.R1C1]               # one facet over the default: its canting error
        placement_mrad = [0.6, -0.3, 0.4]                # (rx, ry, rz about its middle) and its own shape
        surface_seed = 4

    Errors name *where* and the key."""
    base = dict(sim.get("facet", {}))
    table = dict(sim.get("heliostat", {}))
    per = table.pop("facets", {})
    if not isinstance(per, dict):
        raise ConfigError(f"{where} heliostat.facets must be tables keyed by the facets' labels "
                          f"([simulation.heliostat.facets.R1C1])")
    unknown = sorted(set(per) - set(ensemble.labels))
    if unknown:
        raise ConfigError(f"{where} heliostat.facets names {', '.join(unknown)}, not facets of {ensemble.name!r} "
                          f"({', '.join(ensemble.labels)})")
    try:
        facets = tuple(TrueFacet.from_dict({**base, **per.get(label, {})}) for label in ensemble.labels)
        _check_keys("TrueHeliostat", {**table, "facets": ()}, TrueHeliostat)
        return TrueHeliostat(facets=facets, **table)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def heliostat_to_fixture(heliostat: TrueHeliostat) -> Pose:
    """The true heliostat frame in the fixture (rotation about the heliostat frame's origin)."""
    return Pose(rotation_zyx(*(1e-3 * np.asarray(heliostat.placement_mrad, float))),
                1e-3 * np.asarray(heliostat.placement_mm, float))


def draw_heliostat(ensemble: EnsembleDesign, rng: np.random.Generator, *, canting_mrad: float = 0.5,
                   spin_mrad: float = 1.0, position_mm: float = 0.5, placement_mm: float = 3.0,
                   placement_mrad: float = 2.0, focal_spread: float = 0.05, twist_mrad_per_m: float = 0.1,
                   slope_error_mrad: tuple = (0.1, 0.4), correlation_m: tuple = (0.02, 0.05)) -> TrueHeliostat:
    """A heliostat as assembly makes them: every facet drawn on its own.

    Per facet: canting error rx, ry ~ N(0, *canting_mrad*), its spin rz ~ N(0, *spin_mrad*), its position
    error ~ N(0, *position_mm*) per axis; focal lengths f (1 + N(0, *focal_spread*)) per axis, twist
    ~ N(0, *twist_mrad_per_m*), a random slope error of RMS and correlation length uniform in the given
    ranges, its own surface seed. The heliostat's placement in the fixture: uniform in +-*placement_mm*
    and +-*placement_mrad* per axis.
    """
    facets = []
    for f in ensemble.facets:
        focal = f.design.focal_length_m
        facets.append(TrueFacet(
            focal_length_x_m=focal * (1.0 + focal_spread * float(rng.standard_normal())),
            focal_length_y_m=focal * (1.0 + focal_spread * float(rng.standard_normal())),
            twist_mrad_per_m=twist_mrad_per_m * float(rng.standard_normal()),
            placement_mm=tuple(position_mm * rng.standard_normal(3)),
            placement_mrad=(canting_mrad * float(rng.standard_normal()), canting_mrad * float(rng.standard_normal()),
                            spin_mrad * float(rng.standard_normal())),
            slope_error_rms_mrad=float(rng.uniform(*slope_error_mrad)),
            slope_error_correlation_m=float(rng.uniform(*correlation_m)),
            surface_seed=int(rng.integers(0, 2**31))))
    return TrueHeliostat(facets=tuple(facets), placement_mm=tuple(rng.uniform(-placement_mm, placement_mm, 3)),
                         placement_mrad=tuple(rng.uniform(-placement_mrad, placement_mrad, 3)))


class TwinHeliostat(TwinStation):
    """Digital twin of the station with a heliostat in the fixture (see the module docstring).

    Parameters
    ----------
    geometry : StationGeometry
        Camera, screen and the fixture: ``fixture_to_camera`` is the nominal heliostat frame.
    ensemble : EnsembleDesign
    heliostat : TrueHeliostat
    optics, edge_band_px
        As :class:`~sofast_station.twin.station.TwinStation`'s, for every facet (the edge's image model is
        in *optics*).

    Attributes
    ----------
    facet_twins : dict
        Facet index -> its trace (a :class:`~sofast_station.twin.trace.FacetTrace`, in the frame where it
        really is).
    heliostat_to_fixture : Pose
    """

    def __init__(self, geometry: StationGeometry, ensemble: EnsembleDesign, heliostat: TrueHeliostat,
                 optics: TwinOptics = TwinOptics(), edge_band_px: float = 2.0):
        if len(heliostat.facets) != ensemble.n_facets:
            raise ConfigError(f"the true heliostat has {len(heliostat.facets)} facets, its design "
                              f"{ensemble.name!r} {ensemble.n_facets}")
        unknown = sorted((set(heliostat.missing) | set(heliostat.obstructed)) - set(ensemble.labels))
        if unknown:
            raise ConfigError(f"the true heliostat names facet(s) {', '.join(unknown)} that {ensemble.name!r} does "
                              f"not have (its facets: {', '.join(ensemble.labels)})")
        if optics.bevel_width_mm > 0:
            raise ConfigError(f"the heliostat twin draws no bevelled rim (bevel_width_mm = {optics.bevel_width_mm:g}): "
                              "set it to 0 for a heliostat station")
        start = time.perf_counter()
        self.geometry = geometry
        self.ensemble = ensemble
        self.heliostat = heliostat
        self.optics = optics
        self.camera = TwinCamera(geometry.camera)
        self.heliostat_to_fixture = heliostat_to_fixture(heliostat)
        self.facet_twins: dict[int, FacetTrace] = {}
        for i, (ef, tf) in enumerate(zip(ensemble.facets, heliostat.facets)):
            if ef.label in heliostat.missing:
                continue
            nominal = geometry.fixture_to_camera.compose(self.heliostat_to_fixture).compose(ef.to_heliostat)
            trace = FacetTrace(dataclasses.replace(geometry, fixture_to_camera=nominal), ef.design, tf, optics,
                               edge_band_px=edge_band_px)
            if ef.label in heliostat.obstructed:
                _obstruct(trace, heliostat.obstructed[ef.label])
            trace.seen_coverage = trace.coverage.ravel()[trace.seen_idx]
            trace.coverage = None           # a full image each: only the merged one is kept
            self.facet_twins[i] = trace
        if not self.facet_twins:
            raise GeometryError("every facet of the heliostat is missing: there is nothing to see")
        first = next(iter(self.facet_twins.values()))
        # What the single-facet twin's own methods read (the measure facet's, for the distance).
        self.design = ensemble.layout_design()
        self.facet = first.facet
        self.surface = first.surface
        coverage, seen, owner, arrays = merge_traces(self.facet_twins, geometry.camera.shape)
        self.owner = owner
        self.adopt_trace(coverage, seen, arrays)
        self.trace_seconds = time.perf_counter() - start

    # ---------------------------------------------------------------- geometry
    def measured_distance_m(self) -> float:
        """Distance (m) from the true screen centre to the measure facet's true surface at its measure point."""
        i = self.ensemble.measure_facet
        if i not in self.facet_twins:
            raise GeometryError(f"the range finder's facet {self.ensemble.facets[i].label} is missing: it reads "
                                "no distance")
        return self.facet_twins[i].measured_distance_m()

    def corner_pixels(self) -> np.ndarray:
        """Image positions of every present facet's true corners, facet after facet, (sum N_i, 2) pixels."""
        return np.concatenate([t.corner_pixels() for t in self.facet_twins.values()])

    @property
    def owner_image(self) -> np.ndarray:
        """(H, W) int: the index of the facet each pixel sees, -1 where it sees none."""
        out = np.full(self.geometry.camera.shape[0] * self.geometry.camera.shape[1], -1, dtype=np.int32)
        out[self.trace.seen_idx] = self.owner
        return out.reshape(self.geometry.camera.shape)


def _obstruct(trace: FacetTrace, fraction: float) -> None:
    """Hide the facet's +x side (*fraction* of its width) from the camera in a facet's trace."""
    outline = trace.design.outline_m
    x_cut = outline[:, 0].max() - fraction * (outline[:, 0].max() - outline[:, 0].min())
    keep = trace.x_facet_m[:, 0] < x_cut
    hidden = trace.seen_idx[~keep]
    trace.coverage.ravel()[hidden] = 0.0
    trace.seen_idx = trace.seen_idx[keep]
    for name in TRACE_ARRAYS:
        setattr(trace, name, getattr(trace, name)[keep])


def merge_traces(twins: dict, shape: tuple) -> tuple:
    """The picture several traces make together: at each pixel the nearest hit, the coverages summed.

    *twins* maps a key to a trace (:class:`~sofast_station.twin.trace.FacetTrace`) with ``seen_coverage``, its
    seen pixels' coverage.

    Returns
    -------
    coverage : (H, W) array
    seen_idx : (n,) int array
        Flat indices of the pixels that see a facet, increasing.
    owner : (n,) int array
        The facet (key of *twins*) each sees.
    arrays : dict
        Each of :data:`~sofast_station.twin.trace.TRACE_ARRAYS` for those pixels.
    """
    keys = list(twins)
    idx = np.concatenate([twins[k].seen_idx for k in keys])
    which = np.concatenate([np.full(twins[k].seen_idx.size, j, dtype=np.int32) for j, k in enumerate(keys)])
    row = np.concatenate([np.arange(twins[k].seen_idx.size) for k in keys])
    cov = np.concatenate([twins[k].seen_coverage for k in keys])
    hit = np.concatenate([twins[k].hit_range_m for k in keys])
    order = np.lexsort((hit, idx))                  # by pixel, nearest first
    idx, which, row, cov = idx[order], which[order], row[order], cov[order]
    first = np.ones(idx.size, dtype=bool)
    first[1:] = idx[1:] != idx[:-1]
    seen = idx[first]
    coverage = np.zeros(shape[0] * shape[1])
    np.add.at(coverage, idx, cov)
    np.minimum(coverage, 1.0, out=coverage)
    pick_which, pick_row = which[first], row[first]
    arrays = {}
    for name in TRACE_ARRAYS:
        parts = [getattr(twins[k], name) for k in keys]
        out = np.empty((seen.size, *parts[0].shape[1:]), dtype=parts[0].dtype)
        for j, part in enumerate(parts):
            sel = pick_which == j
            out[sel] = part[pick_row[sel]]
        arrays[name] = out
    owner = np.asarray(keys, dtype=np.int32)[pick_which]
    return coverage.reshape(shape), seen, owner, arrays


# ------------------------------------------------------------------------------------------- truth
def _tilt(rx: float, ry: float) -> np.ndarray:
    return rotation_zyx(rx, ry, 0.0)


def _angles(r: np.ndarray) -> tuple[float, float]:
    """(rx, ry) of R = R_z R_y R_x, radians (from its third row: independent of rz)."""
    return math.atan2(r[2, 1], r[2, 2]), -math.asin(max(-1.0, min(1.0, r[2, 0])))


def heliostat_truth(twin: TwinHeliostat, kept: np.ndarray) -> dict:
    """Ground truth of a heliostat capture: every facet's figures and canting error, and the heliostat's
    optical frame (docs/conventions.md#canting), at the pixels the analysis kept.

    Each facet's figures are :func:`~sofast_station.twin.truth.ground_truth`'s of its exact samples (the
    kept pixels that see it); its optical frame's orientation in its design frame on the true heliostat is
    ``R_p R_b^T`` (R_p its true canting error, R_b the truth's boresight rotation). The heliostat's optical
    frame is the true frame turned by T = R_y(b) R_x(a) with the facets' canting errors
    ``angles(R_i^T T^T R_i R_p R_b^T)`` of zero mean (iterated to 1e-12 rad).

    Parameters
    ----------
    twin : TwinHeliostat
    kept : (H, W) bool array
        Pixels the analysis kept (of every facet).

    Returns
    -------
    dict
        ``facets``: {label: figures (as ``ground_truth``; ``placement`` and ``optical_tilt_mrad`` against the
        facet's nominal frame in the fixture, as the analysis states them) + ``canting_mrad`` {x, y} +
        ``canting_rz_mrad``} for each facet with kept pixels; ``heliostat``: ``common_tilt_mrad`` {x, y} (the
        optical frame against the true frame), ``optical_tilt_mrad`` {x, y} (the optical frame in the fixture),
        ``placement`` (the true placement, echoed).
    """
    kept = np.asarray(kept, dtype=bool).ravel()
    on = kept[twin.trace.seen_idx]
    figures, errors = {}, {}
    for i, ft in twin.facet_twins.items():
        sel = on & (twin.owner == i)
        if np.count_nonzero(sel) < 9:
            continue
        # the facet's own trace, at the pixels of the merged picture that see it and were kept
        pos = np.searchsorted(ft.seen_idx, twin.trace.seen_idx[sel])
        points = np.array(ft.x_facet_m[pos], dtype=np.float64)
        slopes = ft.slope[pos]
        normals = np.column_stack([-slopes[:, 0], -slopes[:, 1], np.ones(len(slopes))])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        truth = truth_from_samples(points, normals, ft.design, ft.facet)
        r_place = rotation_zyx(*(1e-3 * np.asarray(ft.facet.placement_mrad, float)))
        r_bore = _tilt(1e-3 * truth["boresight_mrad"]["x"], 1e-3 * truth["boresight_mrad"]["y"])
        errors[i] = r_place @ r_bore.T
        # placement and optical tilt against the facet's nominal frame in the fixture (the design pose on the
        # nominal heliostat), as the analysis states them: D^-1 P_H D P_facet
        design_pose = twin.ensemble.facets[i].to_heliostat
        rel = design_pose.inverse().compose(twin.heliostat_to_fixture).compose(design_pose).compose(
            facet_to_fixture_pose(ft.facet, ft.design))
        cx, cy = (float(v) for v in ft.design.centroid_m)
        p_mid = np.array([cx, cy, float(ft.design.z(cx, cy))])
        r = rel.rotation
        truth["placement"] = {"mm": (1e3 * (rel.apply(p_mid) - p_mid)).tolist(),
                              "mrad": [1e3 * v for v in (*_angles(r), math.atan2(r[1, 0], r[0, 0]))]}
        ox, oy = _angles(r @ r_bore.T)
        truth["optical_tilt_mrad"] = {"x": 1e3 * ox, "y": 1e3 * oy}
        figures[i] = truth
    if not figures:
        raise GeometryError("no facet of the heliostat has kept pixels: there is no truth to give")
    rot = {i: twin.ensemble.facets[i].rotation for i in figures}
    a = b = 0.0
    for _ in range(100):
        t = _tilt(a, b)
        angles = np.array([_angles(rot[i].T @ t.T @ rot[i] @ errors[i]) for i in figures])
        da, db = angles.mean(axis=0)
        a, b = a + da, b + db
        if abs(da) < TILT_TOLERANCE_RAD and abs(db) < TILT_TOLERANCE_RAD:
            break
    t = _tilt(a, b)
    out = {}
    for i, truth in figures.items():
        e = rot[i].T @ t.T @ rot[i] @ errors[i]
        rx, ry = _angles(e)
        truth["canting_mrad"] = {"x": 1e3 * rx, "y": 1e3 * ry}
        truth["canting_rz_mrad"] = 1e3 * math.atan2(e[1, 0], e[0, 0])
        out[twin.ensemble.facets[i].label] = truth
    in_fixture = twin.heliostat_to_fixture.rotation @ t
    ox, oy = _angles(in_fixture)
    return {"facets": out,
            "heliostat": {"common_tilt_mrad": {"x": 1e3 * a, "y": 1e3 * b},
                          "optical_tilt_mrad": {"x": 1e3 * ox, "y": 1e3 * oy},
                          "placement": {"mm": list(twin.heliostat.placement_mm),
                                        "mrad": list(twin.heliostat.placement_mrad)}}}
