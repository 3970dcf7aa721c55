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

import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..errors import ConfigError
from ..measure.analysis import finish_analysis
from ..measure.fit import fit_parabola
from ..measure.fixed import DotPattern, fixed_settings_for, reduce_fixed
from ..measure.pipeline import pose_on_measured_surface, reduce_stages
from ..measure.slope_noise import slope_covariance, slope_jacobian
from ..precompute import ray_table
from .identify import describe
from .opencsp import _SensitivitiesOnly, read_opencsp, upsample_test_data
from .opencsp_fixed import read_opencsp_fixed
from .opencsp_results import OpenCspResult, read_opencsp_result, result_inputs
from .paths import opencsp_fixed_paths, opencsp_test_data_paths

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
#: OpenCSP's processing of its fixed-pattern (dot grid) capture: slopes and surface points at its dots, in its
#: aligned facet frame; no fit and no pose kept (:func:`conform_fixed`).
FIXED_RESULT = "sofast_fixed/data_expected/calculation_facet.h5"


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
    with our pipeline, the way OpenCSP did it, and compare (:func:`conform_file`)."""
    if dataset not in FRINGE_RESULTS:
        raise ConfigError(f"unknown OpenCSP dataset {dataset!r}: one of {', '.join(FRINGE_RESULTS)}")
    root = Path(root)
    rel, what = FRINGE_RESULTS[dataset]
    return conform_file(root / rel, root / MEASUREMENT, focal_length_m, cache, dataset=dataset, what=what)


def conform_file(result: Path, measurement: Path, focal_length_m: float = 100.0, cache: dict | None = None,
                 dataset: str = "", what: str = "") -> Conformance:
    """Redo OpenCSP's processed *result* of the fringe *measurement* with our pipeline, the way OpenCSP did it,
    and compare (module docstring). *cache* keeps the uncertainty's sensitivities between calls (a dict, or
    the station's store).

    Raises
    ------
    ConfigError
        When *result* is not a fringe processing of one facet or mirror (a fixed-pattern one, say), naming
        what it is."""
    ref = read_opencsp_result(Path(result))
    if ref.mask is None:
        raise ConfigError(f"{result} is {describe(Path(result))}: slopes at a fixed pattern's dots, which the fringe "
                          "measurement's pixels cannot be compared with (compare it with the fixed-pattern "
                          "measurement: import-opencsp --fixed --compare)")
    what = what or (f"{'robust' if ref.robust else 'plain'} {ref.surface} fit"
                    f"{', mirror of unknown outline' if ref.optic == 'undefined' else ''}")
    m = read_opencsp(Path(measurement), **result_inputs(Path(result)), facet=None,
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
        # the two corner poses' difference, in our corner pose's axes (small angles): ours with the corners on
        # the measured surface, the one our boresight is stated from
        ours_pose = pose_on_measured_surface(reduction.pose, reduction.fits, reduction.rays, m.geometry, m.design,
                                             m.distance_m, settings)
        d = ours_pose.rotation.T @ ref.optic_to_camera
        corner = {"x": 1000.0 * float(np.arctan2(d[2, 1], d[2, 2])),
                  "y": -1000.0 * float(np.arcsin(np.clip(d[2, 0], -1.0, 1.0)))}
        for axis in "xy":
            diff = ours_t[axis] - theirs_t[axis]
            rows.append(Row(f"plane's tilt from the corner pose about {axis}", "mrad", theirs_t[axis], ours_t[axis],
                            ours_u.get(axis), diff,
                            f"OpenCSP's corner pose is turned {corner[axis]:+.1f} mrad about {axis} from ours"))
    slopes = _slope_comparison(ref, analysis, reduction, m, ours_to_cam, slope_covariance)
    return Conformance(dataset or Path(result).stem, what, ref, rows, slopes, fig)


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


def register_points(theirs_xy: np.ndarray, ours_xy: np.ndarray, start_m: float = 0.008, tol_m: float = 0.003,
                    rounds: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray]:
    """OpenCSP's points matched to ours on the facet: the 2-D rigid motion (rotation about z, shift) that best
    lays its points (N, 2) onto ours (M, 2), from nearest neighbours within *start_m*, then within *tol_m*
    (each program places its facet frame by its own corners: millimetres apart), least squares on the pairs
    (Kabsch). Returns the pairs' indices into ours and into theirs, the residual distances (metres), the
    rotation (mrad) and the shift (metres)."""
    tree = cKDTree(ours_xy)
    rot, shift = np.eye(2), np.zeros(2)
    for k in range(rounds):
        d, nn = tree.query(theirs_xy @ rot.T + shift)
        m = d < (start_m if k == 0 else tol_m)
        if m.sum() < 3:
            raise ConfigError(f"OpenCSP's points and ours do not overlap on the facet ({int(m.sum())} within "
                              f"{1000 * (start_m if k == 0 else tol_m):g} mm): is it the same capture and facet?")
        a, b = theirs_xy[m], ours_xy[nn[m]]
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
        rot = (u @ vt).T
        if np.linalg.det(rot) < 0:                       # a rotation, never a reflection
            vt[-1] *= -1
            rot = (u @ vt).T
        shift = cb - ca @ rot.T
    d, nn = tree.query(theirs_xy @ rot.T + shift)
    m = d < tol_m
    return nn[m], np.flatnonzero(m), d[m], 1000.0 * float(np.arctan2(rot[1, 0], rot[0, 0])), shift


def conform_fixed(paths: dict, result: Path, focal_length_m: float = 100.0, cache: dict | None = None,
                  dataset: str = "fixed", what: str = "") -> Conformance:
    """Our fixed-pattern analysis of OpenCSP's dot-grid capture (*paths*: :func:`~.paths.opencsp_fixed_paths`'s
    keys) beside OpenCSP's processing of it (*result*, its ``calculation_facet.h5``: slopes and surface points
    at its dots in its aligned frame, no fit and no pose).

    Its dots are matched to ours on the facet (:func:`register_points`). OpenCSP's figures are the fit its
    parameters say it made (a plain parabola on every dot, ``ParamsSurface``) redone on its own final slopes at
    its own points (the file keeps no coefficients): on every dot each program uses (OpenCSP's include the dots
    the facet's edge cuts, ours not), and on the dots both use. Every slope is compared in each program's own
    aligned frame, less the two frames' mean difference (each is turned onto its own fit's normal at the
    alignment point, over different dots), against our per-dot U from the image's noise through the centroids.
    """
    ref = read_opencsp_result(Path(result))
    if ref.layout != "fixed":
        raise ConfigError(f"{result} is {describe(Path(result))}: not a fixed-pattern processing (give the fringe "
                          "result to a fringe measurement's --compare)")
    m = read_opencsp_fixed(**paths, focal_length_m=focal_length_m)
    settings = replace(m.settings, robust_fit=ref.robust, surface=ref.surface)
    reduction, timings = reduce_fixed(m.image, m.dots, m.geometry, m.design, m.distance_m, settings, m.fixed,
                                      origin_px=m.origin_px, screen=m.screen)
    analysis = finish_analysis(reduction, timings, fringes=DotPattern(m.fixed), geometry=m.geometry,
                               design=m.design, measured_distance_m=m.distance_m,
                               settings=fixed_settings_for(settings, m.fixed), screen=m.screen,
                               uncertainty=m.uncertainty, sensitivity_cache=_SensitivitiesOnly(cache))
    fig = analysis.figures
    ours_p, ours_s = analysis.points_facet_m, analysis.slopes
    a, b, dist, turn_mrad, shift = register_points(ref.points_m[:2].T, ours_p[:2].T)
    theirs_all = fit_parabola(*ref.points_m[:2], *ref.slopes)
    theirs_common = fit_parabola(*ref.points_m[:2, b], *ref.slopes[:, b])
    ours_common = fit_parabola(*ours_p[:2, a], *ours_s[:, a])
    n_t, n_o, n_c = ref.slopes.shape[1], ours_s.shape[1], len(a)
    rows: list[Row] = []
    for axis, k in (("x", "a"), ("y", "b")):
        key = f"focal_length_{axis}_m"
        theirs = 1.0 / (4.0 * getattr(theirs_all, k))
        rows.append(Row(f"f {axis} (plain fit, every dot each uses: OpenCSP {n_t}, ours {n_o})", "m", theirs,
                        fig[key], fig.get(f"{key}_U"), fig[key] - theirs,
                        "OpenCSP's fit includes the dots the facet's edge cuts"))
    for axis, k in (("x", "a"), ("y", "b")):
        key = f"focal_length_{axis}_m"
        theirs, ours = 1.0 / (4.0 * getattr(theirs_common, k)), 1.0 / (4.0 * getattr(ours_common, k))
        rows.append(Row(f"f {axis} (plain fit on the {n_c} dots both use)", "m", theirs, ours, fig.get(f"{key}_U"),
                        ours - theirs))
    for name, k in (("twist_e1_mrad_per_m", "e1"), ("twist_e2_mrad_per_m", "e2")):
        theirs, ours = 1000.0 * getattr(theirs_common, k), 1000.0 * getattr(ours_common, k)
        rows.append(Row(f"twist {k.upper()} (plain fit on the {n_c} dots both use)", "mrad/m", theirs, ours,
                        fig.get(f"{name}_U"), ours - theirs))
    # slopes, each in its program's own aligned frame, less the frames' mean difference
    d = 1000.0 * (np.arctan(ours_s[:, a]) - np.arctan(ref.slopes[:, b]))
    tilt = d.mean(axis=1)
    for i, axis in enumerate("xy"):
        rows.append(Row(f"the two aligned frames' mean slope difference, {axis}", "mrad", 0.0, float(tilt[i]), None,
                        float(tilt[i]), "each frame is turned onto its own fit's normal, over different dots"))
    dd = d - tilt[:, None]
    # per-dot U (k = 2) from the image's noise through the centroids: the rays' order is the valid dots'
    vx, vy, _ = slope_covariance(reduction, DotPattern(m.fixed), m.screen, a)
    u = 2000.0 * np.sqrt(np.vstack([vx, vy])) / (1.0 + ours_s[:, a] ** 2)
    inside = np.all(np.abs(dd) <= u, axis=0)
    centres = _centre_differences(reduction, m, a, dd)
    slopes = {"points": "dots", "pixels_compared": int(n_c), "pixels_opencsp": int(n_t),
              "registration": {"rotation_mrad": turn_mrad, "shift_mm": (1000.0 * shift).tolist(),
                               "residual_median_mm": 1000.0 * float(np.median(dist)),
                               "residual_max_mm": 1000.0 * float(dist.max())},
              "frames_mean_difference_mrad": tilt.tolist(),
              "rms_mrad": [float(np.sqrt(np.mean(dd[i] ** 2))) for i in range(2)],
              "p99_mrad": [float(np.percentile(np.abs(dd[i]), 99)) for i in range(2)],
              "max_mrad": [float(np.abs(dd[i]).max()) for i in range(2)],
              "median_U_mrad": [float(np.median(u[i])) for i in range(2)],
              "fraction_within_U": float(np.mean(inside)),
              "fraction_within_U_both": float(np.mean(np.all(np.abs(dd) <= np.sqrt(2.0) * u, axis=0))),
              "centres": centres}
    if centres.get("dots"):
        sel = centres.pop("_selection")
        rest = centres.pop("_rest")
        centres["fraction_within_U_after"] = float(np.mean(np.all(np.abs(rest) <= u[:, sel], axis=0)))
    return Conformance(dataset, what or "fixed pattern (dot grid), plain fit on every dot", ref, rows, slopes, fig)


#: OpenCSP's blob detector for its fixed pattern (``ProcessSofastFixed.__init__``): OpenCV's, dark blobs of 3 to
#: 30 px, no shape filters, OpenCV's default thresholds.
OPENCSP_BLOBS = {"minDistBetweenBlobs": 2.0, "filterByArea": True, "minArea": 3.0, "maxArea": 30.0,
                 "filterByCircularity": False, "filterByConvexity": False, "filterByInertia": False}


def opencsp_dot_centres(image: np.ndarray) -> np.ndarray:
    """The dots' centres (N, 2) as OpenCSP finds them: OpenCV's blob detector with OpenCSP's parameters
    (:data:`OPENCSP_BLOBS`; each centre the mean of its blob's contour centres over the thresholds)."""
    params = cv2.SimpleBlobDetector_Params()
    for k, v in OPENCSP_BLOBS.items():
        setattr(params, k, v)
    return np.array([k.pt for k in cv2.SimpleBlobDetector_create(params).detect(np.asarray(image, np.uint8))])


def _centre_differences(reduction, m, ours_idx: np.ndarray, diff_mrad: np.ndarray) -> dict:
    """How much of the slope differences at our valid dots *ours_idx* (*diff_mrad*, (2, n), less the frames'
    mean) the two programs' centres of the same dots explain: OpenCSP's (:func:`opencsp_dot_centres`) against
    ours, each offset d (pixels) making its ray see the grid J d away from the dot it is given (J:
    ``DotPhases.index_per_px``), which puts its slope -G J d off (G: the slope's derivative with respect to the
    grid position, :func:`~sofast_station.measure.slope_noise.slope_jacobian`): ours less its, G J d."""
    theirs = opencsp_dot_centres(m.image)
    take = np.flatnonzero(reduction.rays.ok)[ours_idx]            # the dots in the region's (phases') order
    ours_px = reduction.region.points_px[take]
    d, nn = cKDTree(theirs).query(ours_px)
    sel = d < 1.0
    if sel.sum() < 3:
        return {}
    dp = theirs[nn[sel]] - ours_px[sel]
    ph = reduction.phases
    pts = reduction.shape.points_m[:, ours_idx[sel]]
    cam_to_b = reduction.shape.boresighted_to_camera.inverse()
    _, gx, gy = slope_jacobian(pts, cam_to_b, m.screen, ph.positions_m["x"][take[sel]], ph.positions_m["y"][take[sel]])
    du = np.einsum("nij,nj->ni", ph.index_per_px[take[sel]], dp)    # grid steps (x, y) their centre is off ours
    # ours minus theirs: its ray truly sees the grid du further than the dot it is given, so its slope is off
    # by -G du, and ours less its is G du
    predicted = 1000.0 * (gx * du[:, 0] + gy * du[:, 1])
    predicted = predicted / (1.0 + reduction.shape.slopes[:, ours_idx[sel]] ** 2)
    predicted -= predicted.mean(axis=1, keepdims=True)
    observed = diff_mrad[:, sel]
    rest = observed - predicted
    return {"dots": int(sel.sum()),
            "centre_difference_rms_px": [float(np.sqrt(np.mean(dp[:, i] ** 2))) for i in range(2)],
            "predicted_rms_mrad": [float(np.sqrt(np.mean(predicted[i] ** 2))) for i in range(2)],
            "remaining_rms_mrad": [float(np.sqrt(np.mean(rest[i] ** 2))) for i in range(2)],
            "correlation": [float(np.corrcoef(observed[i], predicted[i])[0, 1]) for i in range(2)],
            "_selection": np.flatnonzero(sel), "_rest": rest}


def split_facet_check(root: Path, focal_length_m: float = 100.0, cache: dict | None = None) -> dict:
    """The single NSTTF facet's capture analysed whole and as two halves (OpenCSP's split-facet ensemble, the
    measure point in the 42 mm gap between them), and each half's pointing set beside the whole facet's.

    A half's pointing is its fitted normal at its centre (its optical frame's z). The whole facet predicts
    it two ways: its fitted parabola's normal at the half's centre, and the mean of its measured slopes over
    the half's pixels (the parabola plus its residual's mean there: the shape the half's own fit sees). The
    second is the like-for-like one, checked within U: the two analyses read the same frames through the
    same calibration, so the station inputs move both alike and cancel; what is left is each one's random
    part (noise, corners, frame brightness), combined as if independent (U of the difference, k = 2).
    Differences are slopes (mrad) along the half's x and y; every normal is compared in the camera frame.
    """
    root = Path(root)
    whole_m = read_opencsp(**opencsp_test_data_paths(root), focal_length_m=focal_length_m)
    whole = whole_m.analyse(uncertainty=whole_m.uncertainty, sensitivity_cache=_SensitivitiesOnly(cache))
    halves_m = read_opencsp(**opencsp_test_data_paths(root, split_facet=True), focal_length_m=focal_length_m)
    halves = halves_m.analyse_heliostat(uncertainty=halves_m.uncertainty, sensitivity_cache={})
    z = np.array([0.0, 0.0, 1.0])
    co, w2c = whole.coefficients, whole.facet_to_camera
    u_whole = whole.figures.get("optical_tilt_mrad_U_random") or {}
    out = []
    for i, a in sorted(halves.analyses.items()):
        f2c = halves.facet_to_camera(i)
        centre = w2c.inverse().apply(f2c.translation)
        sx = 2.0 * co[0] * centre[0] + co[2] + co[4] * centre[1]
        sy = 2.0 * co[1] * centre[1] + co[3] + co[4] * centre[0]
        r0, c0, r1, c1 = halves.regions[i].window
        pixels = np.zeros(whole.valid.shape, dtype=bool)
        pixels[r0:r1, c0:c1] = a.valid
        sel = pixels[whole.valid]
        mean = whole.slopes[:, sel].mean(axis=1)

        def diff(s_x, s_y):
            """The half's normal less the whole's of slopes (s_x, s_y), as slopes in the half's frame, mrad."""
            n = w2c.rotation @ np.array([-s_x, -s_y, 1.0])
            p, q = f2c.rotation.T @ (f2c.rotation @ z), f2c.rotation.T @ n
            return [1000.0 * float(-p[0] / p[2] + q[0] / q[2]), 1000.0 * float(-p[1] / p[2] + q[1] / q[2])]
        u_half = a.figures.get("optical_tilt_mrad_U_random") or {}
        # a slope along x is a tilt about y, and along y about x
        u = [float(np.hypot(u_half["y"], u_whole["y"])), float(np.hypot(u_half["x"], u_whole["x"]))]
        d_mean = diff(*mean)
        out.append({"facet": halves.regions[i].label, "centre_in_whole_m": [float(centre[0]), float(centre[1])],
                    "pixels": int(sel.sum()), "half_minus_whole_parabola_mrad": diff(sx, sy),
                    "half_minus_whole_mean_slope_mrad": d_mean, "U_mrad": u,
                    "within_U": bool(all(abs(d) <= uu for d, uu in zip(d_mean, u))),
                    "canting_mrad": halves.figures["facets"][i].get("canting_mrad"),
                    "canting_mrad_U": halves.figures["facets"][i].get("canting_mrad_U")})
    return {"halves": out, "measure_point": halves_m.ensemble.measure_point_m.tolist(),
            "whole_focal_length_m": [whole.figures["focal_length_x_m"], whole.figures["focal_length_y_m"]]}


def ensemble_check(root: Path, focal_length_m: float = 100.0, cache: dict | None = None) -> dict:
    """OpenCSP's multi-facet capture (a lab heliostat of 24 facets, ``measurement_ensemble.h5``; OpenCSP's
    public data holds no processing of it to compare with) analysed facet by facet, and each facet's pointing
    checked against the same capture analysed whole, as one mirror of unknown outline: the mean of the
    whole's measured slopes over the facet's pixels (as :func:`split_facet_check`; U of the difference from
    the two analyses' random parts, k = 2). Returns each facet's canting with U and the check."""
    root = Path(root)
    paths = opencsp_test_data_paths(root, multi_facet=True)
    heli_m = read_opencsp(**paths, focal_length_m=focal_length_m)
    heli = heli_m.analyse_heliostat(uncertainty=heli_m.uncertainty, sensitivity_cache={})
    whole_m = read_opencsp(**{**paths, "facet": None, "ensemble": None}, focal_length_m=focal_length_m)
    whole = whole_m.analyse(uncertainty=whole_m.uncertainty, sensitivity_cache=_SensitivitiesOnly(cache))
    w2c = whole.facet_to_camera
    u_whole = whole.figures.get("optical_tilt_mrad_U_random") or {}
    z = np.array([0.0, 0.0, 1.0])
    out = []
    for i, a in sorted(heli.analyses.items()):
        f2c = heli.facet_to_camera(i)
        r0, c0, r1, c1 = heli.regions[i].window
        pixels = np.zeros(whole.valid.shape, dtype=bool)
        pixels[r0:r1, c0:c1] = a.valid
        sel = pixels[whole.valid]
        mean = whole.slopes[:, sel].mean(axis=1)
        n = w2c.rotation @ np.array([-mean[0], -mean[1], 1.0])
        p, q = f2c.rotation.T @ (f2c.rotation @ z), f2c.rotation.T @ n
        d = [1000.0 * float(-p[0] / p[2] + q[0] / q[2]), 1000.0 * float(-p[1] / p[2] + q[1] / q[2])]
        u_f = a.figures.get("optical_tilt_mrad_U_random") or {}
        u = [float(np.hypot(u_f["y"], u_whole["y"])), float(np.hypot(u_f["x"], u_whole["x"]))]
        entry = heli.figures["facets"][i]
        out.append({"facet": entry["label"], "pixels": int(sel.sum()), "facet_minus_whole_mean_slope_mrad": d,
                    "U_mrad": u, "within_U": bool(all(abs(v) <= uu for v, uu in zip(d, u))),
                    "canting_mrad": entry.get("canting_mrad"), "canting_mrad_U": entry.get("canting_mrad_U")})
    return {"facets": out, "n_facets": heli.figures["heliostat"]["n_facets"],
            "n_measured": heli.figures["heliostat"]["n_measured"], "assumptions": list(heli_m.assumptions)}


#: The figures of OpenCSP's real capture that a release keeps (``fixtures/opencsp/release_figures.json``):
#: the station's own analysis (its pixels, every point's fit), each screen model and fit, native and the
#: capture upsampled 8x (what OpenCSP's camera took before it was downsampled).
RELEASE_DISPLAYS = {"distorted2D": "sofast_common/display_distorted_2d.h5",
                    "rectangular2D": "sofast_common/display_rectangular.h5",
                    "distorted3D": "sofast_common/display_distorted_3d.h5"}
RELEASE_CASES = tuple(f"{d}/{fit}/x1" for d in RELEASE_DISPLAYS for fit in ("plain", "robust")) + (
    "distorted2D/plain/x8", "distorted2D/robust/x8", "fixed/plain/x1")
#: The fixed-pattern capture's case (``sofast_fixed/``, the fixed-pattern method; its own dots, not a display).
FIXED_CASE = "fixed/plain/x1"
#: Scalar figures kept, and where each is in the figures.
RELEASE_FIGURES = {"focal_length_x_m": ("focal_length_x_m",), "focal_length_y_m": ("focal_length_y_m",),
                   "twist_mrad_per_m": ("twist_mrad_per_m",), "twist_e1_mrad_per_m": ("twist_e1_mrad_per_m",),
                   "twist_e2_mrad_per_m": ("twist_e2_mrad_per_m",),
                   "slope_rms_design_magnitude_mrad": ("slope_rms_mrad", "design", "magnitude"),
                   "slope_rms_parabola_magnitude_mrad": ("slope_rms_mrad", "parabola", "magnitude"),
                   "slope_rms_higher_order_magnitude_mrad": ("slope_rms_mrad", "higher_order", "magnitude"),
                   "boresight_x_mrad": ("boresight_mrad", "x"), "boresight_y_mrad": ("boresight_mrad", "y")}


def release_figures(root: Path, cases=RELEASE_CASES, work: Path | None = None, with_u: bool = False) -> dict:
    """``{case: {figure: value (or [value, U] with *with_u*), "n_points": n}}`` of :data:`RELEASE_CASES` on the
    test data in *root*; the 8x cases upsample the capture into *work* (a temporary folder)."""
    root = Path(root)
    out: dict = {}
    tmp = None
    for case in cases:
        display, fit, scale = case.split("/")
        scale = int(scale[1:])
        if display == "fixed":
            fm = read_opencsp_fixed(**opencsp_fixed_paths(root))
            out[case] = _release_entry(fm.analyse(uncertainty=fm.uncertainty if with_u else None,
                                                  sensitivity_cache={} if with_u else None).figures, with_u)
            continue
        if scale == 1:
            paths = opencsp_test_data_paths(root)
        else:
            if work is None:
                tmp = tempfile.TemporaryDirectory()
                work = Path(tmp.name)
            folder = Path(work) / f"x{scale}"
            paths = (opencsp_test_data_paths(folder) if folder.exists() else upsample_test_data(root, folder, scale))
        paths = {**paths, "display": root / RELEASE_DISPLAYS[display]}
        m = read_opencsp(**paths)
        a = m.analyse(robust=fit == "robust", uncertainty=m.uncertainty if with_u else None,
                      sensitivity_cache={} if with_u else None)
        out[case] = _release_entry(a.figures, with_u)
    if tmp is not None:
        tmp.cleanup()
    return out


def _release_entry(fig: dict, with_u: bool) -> dict:
    """The figures of :data:`RELEASE_FIGURES` (each [value, U] with *with_u*) and the points kept."""
    entry = {}
    for name, path in RELEASE_FIGURES.items():
        v, u = fig, fig.get(f"{path[0]}_U") if with_u else None
        for p in path:
            v = v[p]
        for p in path[1:]:
            u = None if u is None else u[p]
        entry[name] = [v, u] if with_u else v
    entry["n_points"] = fig["n_points"]
    return entry


def conformance_text(c: Conformance) -> str:
    """The comparison *c* as console lines: each figure as OpenCSP's, ours ± U (k = 2), the difference and
    whether U holds it; then the slopes."""
    def num(v, digits=4):
        return "-" if v is None else f"{v:.{digits}g}"

    where = "on its pixels" if c.slopes.get("points", "pixels") == "pixels" else "on our own dots"
    lines = [f"OpenCSP's processing {c.result.path.name} ({c.what}): ours redone {where}, each figure ± U (k=2)"]
    for r in c.rows:
        verdict = {True: "within U", False: "outside U", None: ""}[r.within_u]
        lines.append(f"  {r.figure}: OpenCSP {num(r.opencsp, 6)} {r.unit}, ours {num(r.ours, 6)} ± {num(r.U, 2)} "
                     f"{r.unit}, difference {num(r.difference, 2)} {verdict}{f' ({r.note})' if r.note else ''}")
    s = c.slopes
    what = s.get("points", "pixels")
    if "registration" in s:
        r = s["registration"]
        lines.append(f"  its {what} matched to ours on the facet after turning its points "
                     f"{r['rotation_mrad']:+.2f} mrad and shifting them ({r['shift_mm'][0]:+.2f}, "
                     f"{r['shift_mm'][1]:+.2f}) mm (each program's corners place its frame): "
                     f"{r['residual_median_mm']:.2f} mm apart (median), at most "
                     f"{r['residual_max_mm']:.2f}; slopes less the frames' mean difference")
    lines.append(f"  slopes at {s['pixels_compared']} of its {s['pixels_opencsp']} {what}: difference RMS "
                 f"{s['rms_mrad'][0]:.4f} x, {s['rms_mrad'][1]:.4f} y mrad, 99th percentile {s['p99_mrad'][0]:.4f}, "
                 f"{s['p99_mrad'][1]:.4f}; our per-{what[:-1]} U from the noise alone {s['median_U_mrad'][0]:.3f}, "
                 f"{s['median_U_mrad'][1]:.3f} (median); {100 * s['fraction_within_U']:.1f} % of {what} within it"
                 + (f", {100 * s['fraction_within_U_both']:.1f} % within sqrt(2) of it (OpenCSP's centres noisy as "
                    "ours)" if "fraction_within_U_both" in s else ""))
    cs = s.get("centres") or {}
    if cs.get("dots"):
        lines.append(f"  OpenCSP's centres of the same dots (its blob detector) lie "
                     f"{cs['centre_difference_rms_px'][0]:.3f}, {cs['centre_difference_rms_px'][1]:.3f} px from ours "
                     "(RMS); through each dot's geometry that is "
                     f"{cs['predicted_rms_mrad'][0]:.4f}, {cs['predicted_rms_mrad'][1]:.4f} mrad of slope (correlation "
                     f"{cs['correlation'][0]:.2f}, {cs['correlation'][1]:.2f} with the differences); left: "
                     f"{cs['remaining_rms_mrad'][0]:.4f}, {cs['remaining_rms_mrad'][1]:.4f} mrad RMS, "
                     f"{100 * cs['fraction_within_U_after']:.1f} % of dots within our U")
    return "\n".join(lines)
