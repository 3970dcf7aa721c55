"""Our reduction of OpenCSP's real captures beside OpenCSP's own processing of them, figure by figure.

For one of OpenCSP's processed results (:mod:`~sofast_station.interop.opencsp_results`), :func:`conform`
redoes the analysis the way OpenCSP did it (its calibration, read from the result file itself; its facet
definition or none; its surface model, robust or plain fit and subsample), on OpenCSP's own pixels, with
every figure's expanded uncertainty U (k = 2) from :func:`~sofast_station.measure.analysis.analyse`, and
sets each figure beside OpenCSP's:

* the focal lengths and the twist's E1 and E2 of the fit on every n-th pixel (what OpenCSP reports; ours
  with the subsample's U, :func:`subsample_u`);
* the fitted surface's normal at the alignment point, in the camera frame (no frame convention in it: the
  angle between the two programs' normals, against our U of the optical tilt);
* for the plano model, its tilt from the corner pose (OpenCSP's ``trans_alignment``, our boresight): each
  program's own corner pose is in it, so it is compared, and the corner poses' difference measured, too;
* every pixel's slopes, OpenCSP's turned into our frame through the camera frame, against our per-pixel
  U of the slopes from the capture's own intensity noise (the smallest part of a slope's U, so a strict
  test: both programs decode the same frames).

docs/opencsp.md tabulates what it gives on every dataset of OpenCSP's test data.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from .opencsp import _SensitivitiesOnly, read_opencsp
from .opencsp_results import OpenCspResult, read_opencsp_result, result_inputs

#: The datasets of OpenCSP's test data that :func:`conform` redoes: name -> (result file, what it is),
#: relative to the test-data folder (``opencsp/test/data``'s layout; ``fixtures/opencsp/test_data``).
FRINGE_RESULTS = {
    "robust": ("sofast_fringe/data_expected_facet/data.h5", "robust fit, 2-D distorted screen"),
    "plain": ("sofast_fringe/data_expected_facet/data_no_ls.h5", "plain least squares, 2-D distorted screen"),
    "rectangular": ("sofast_fringe/data_expected_facet/data_rectangular.h5", "robust fit, rectangular screen"),
    "distorted_3d": ("sofast_fringe/data_expected_facet/data_distorted_3d.h5", "robust fit, 3-D distorted screen"),
    "plano": ("sofast_fringe/data_expected_facet/data_plano.h5", "robust fit of a plane (plano surface)"),
    "undefined": ("sofast_fringe/data_expected_undefined_mirror/data.h5",
                  "mirror of unknown outline (no facet definition), plain fit, its own calibration"),
}
#: The capture every fringe result is a processing of.
MEASUREMENT = "sofast_fringe/data_measurement/measurement_facet.h5"


@dataclass(frozen=True)
class Row:
    """One figure of the comparison: OpenCSP's value, ours with its U (k = 2), the difference."""

    figure: str
    unit: str
    opencsp: float | None
    ours: float | None
    U: float | None
    difference: float | None
    note: str = ""

    @property
    def within_u(self) -> bool | None:
        """|difference| <= U (None when either is missing)."""
        if self.difference is None or self.U is None:
            return None
        return bool(abs(self.difference) <= self.U)

    def to_dict(self) -> dict:
        return {"figure": self.figure, "unit": self.unit, "opencsp": self.opencsp, "ours": self.ours, "U": self.U,
                "difference": self.difference, "within_U": self.within_u, "note": self.note}


@dataclass
class Conformance:
    """The comparison of one dataset (:func:`conform`)."""

    dataset: str
    what: str
    result: OpenCspResult
    rows: list[Row]
    slopes: dict
    figures: dict = field(repr=False, default_factory=dict)

    def to_dict(self) -> dict:
        return {"dataset": self.dataset, "what": self.what, "file": str(self.result.path),
                "surface": self.result.surface, "robust": self.result.robust, "optic": self.result.optic,
                "rows": [r.to_dict() for r in self.rows], "slopes": self.slopes}


def subsample_u(figures: dict, name: str) -> float | None:
    """U (k = 2) of figure *name* fitted on every n-th point (``subsample_fit``'s rule): the full fit's U with
    its intensity-noise part grown by sqrt(N / n) (that noise is independent from pixel to pixel; the rest
    moves every slope alike), from the uncertainty budget (3 significant digits)."""
    budget = figures.get("uncertainty_budget") or {}
    names = budget.get("figures") or []
    if name not in names:
        return None
    j = names.index(name)
    u = budget["combined_standard"][j]
    noise = next((r["contributions"][j] for r in budget["rows"] if r["group"] == "intensity noise"), 0.0) or 0.0
    sub = figures.get("subsample_fit") or {}
    if u is None or not sub.get("n_points"):
        return None
    more = max(float(figures["n_points"]) / float(sub["n_points"]) - 1.0, 0.0)
    return float(budget.get("coverage_factor", 2) * np.sqrt(u * u + more * noise * noise))


def _normal_angle_mrad(a: np.ndarray, b: np.ndarray) -> float:
    """The angle between unit vectors *a* and *b*, mrad (accurate for small angles)."""
    return 1000.0 * float(np.arctan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


def _tilt_u(figures: dict) -> float | None:
    """U (k = 2) of the direction of the fitted normal at the alignment point (a 2-D direction: the root sum
    of the optical tilt's U about x and y, a conservative circle around both)."""
    u = figures.get("optical_tilt_mrad_U") or {}
    if u.get("x") is None or u.get("y") is None:
        return None
    return float(np.hypot(u["x"], u["y"]))


def conform(root: Path, dataset: str, focal_length_m: float = 100.0, cache: dict | None = None) -> Conformance:
    """Redo OpenCSP's processed result *dataset* (a key of :data:`FRINGE_RESULTS`) of the test data in *root*
    with our pipeline, the way OpenCSP did it, and compare (module docstring).

    *cache* keeps the uncertainty's sensitivities between calls (a dict, or the station's store)."""
    from ..measure.analysis import finish_analysis
    from ..measure.pipeline import reduce_stages
    from ..measure.slope_noise import slope_covariance
    from ..precompute import ray_table

    if dataset not in FRINGE_RESULTS:
        raise ConfigError(f"unknown OpenCSP dataset {dataset!r}: one of {', '.join(FRINGE_RESULTS)}")
    root = Path(root)
    rel, what = FRINGE_RESULTS[dataset]
    ref = read_opencsp_result(root / rel)
    m = read_opencsp(root / MEASUREMENT, **result_inputs(root / rel), facet=None,
                     corners_m=ref.corners_m if ref.optic == "facet" else None, focal_length_m=focal_length_m)
    settings = replace(m.settings, robust_fit=ref.robust, surface=ref.surface, subsample_step=ref.downsample)
    reduction, timings = reduce_stages(m.frames, m.fringes, m.geometry, m.design, m.distance_m, settings,
                                       screen=m.screen, rays_cam=ray_table(m.geometry.camera), pixel_mask=ref.mask)
    analysis = finish_analysis(reduction, timings, fringes=m.fringes, geometry=m.geometry, design=m.design,
                               measured_distance_m=m.distance_m, settings=settings, screen=m.screen,
                               uncertainty=m.uncertainty, sensitivity_cache=_SensitivitiesOnly(cache))
    fig = analysis.figures
    rows: list[Row] = []
    if ref.surface == "parabolic":
        sub, sub_u = fig["subsample_fit"], fig.get("subsample_fit_U") or {}
        for axis in "xy":
            key = f"focal_length_{axis}_m"
            theirs, ours = getattr(ref, key), sub[key]
            rows.append(Row(f"f {axis} (fit on every {ref.downsample}th pixel)", "m", theirs, ours, sub_u.get(key),
                            ours - theirs))
        fit = reduction.shape.solution.fit            # the subsample's last fit: its E1 and E2
        for name, ours in (("twist_e1_mrad_per_m", 1000.0 * fit.e1), ("twist_e2_mrad_per_m", 1000.0 * fit.e2)):
            theirs = getattr(ref, name)
            rows.append(Row(f"twist {name.split('_')[1].upper()} (same fit)", "mrad/m", theirs, ours,
                            subsample_u(fig, name), ours - theirs))
    ours_to_cam = reduction.shape.boresighted_to_camera.rotation
    z = np.array([0.0, 0.0, 1.0])
    angle = _normal_angle_mrad(ours_to_cam @ z, ref.aligned_to_camera() @ z)
    rows.append(Row("fitted normal at the alignment point (camera frame): angle between", "mrad", 0.0, angle,
                    _tilt_u(fig), angle, "no frame convention in it"))
    if ref.surface == "plano":
        theirs_t, ours_t, ours_u = ref.tilt_mrad(), fig["boresight_mrad"], fig.get("boresight_mrad_U") or {}
        # the two corner poses' difference, in our corner pose's axes (small angles)
        d = reduction.pose.facet_to_camera.rotation.T @ ref.optic_to_camera
        corner = {"x": 1000.0 * float(np.arctan2(d[2, 1], d[2, 2])),
                  "y": -1000.0 * float(np.arcsin(np.clip(d[2, 0], -1.0, 1.0)))}
        for axis in "xy":
            diff = ours_t[axis] - theirs_t[axis]
            rows.append(Row(f"plane's tilt from the corner pose about {axis}", "mrad", theirs_t[axis], ours_t[axis],
                            ours_u.get(axis), diff,
                            f"OpenCSP's corner pose is turned {corner[axis]:+.1f} mrad about {axis} from ours"))
    slopes = _slope_comparison(ref, analysis, reduction, m, ours_to_cam, slope_covariance)
    return Conformance(dataset, what, ref, rows, slopes, fig)


def _slope_comparison(ref: OpenCspResult, analysis, reduction, m, ours_to_cam: np.ndarray, slope_covariance) -> dict:
    """Every common pixel's slope difference (mrad, as angles), OpenCSP's normals turned into our boresighted
    frame through the camera frame, against our per-pixel U (k = 2) from the capture's own intensity noise."""
    theirs_cam = ref.normals_camera()
    theirs = ours_to_cam.T @ theirs_cam
    theirs_s = np.full((2, *ref.mask.shape), np.nan)
    theirs_s[:, ref.mask] = -theirs[:2] / theirs[2]
    both = analysis.valid & ref.mask
    ours_idx = np.flatnonzero(both.ravel()[np.flatnonzero(analysis.valid.ravel())])
    ours = analysis.slopes[:, ours_idx]
    rows, cols = np.nonzero(both)
    th = theirs_s[:, rows, cols]
    d = 1000.0 * (np.arctan(ours) - np.arctan(th))
    vx, vy, _ = slope_covariance(reduction, m.fringes, m.screen, ours_idx)
    u = 2000.0 * np.sqrt(np.vstack([vx, vy])) / (1.0 + ours ** 2)          # d atan(s) = ds / (1 + s^2)
    inside = np.all(np.abs(d) <= u, axis=0)
    return {"pixels_compared": int(both.sum()), "pixels_opencsp": int(ref.mask.sum()),
            "rms_mrad": [float(np.sqrt(np.mean(d[i] ** 2))) for i in range(2)],
            "p99_mrad": [float(np.percentile(np.abs(d[i]), 99)) for i in range(2)],
            "max_mrad": [float(np.abs(d[i]).max()) for i in range(2)],
            "median_U_mrad": [float(np.median(u[i])) for i in range(2)],
            "fraction_within_U": float(np.mean(inside))}
