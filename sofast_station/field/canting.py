"""Every facet's corners in 3-D from several tower photos, each facet's normal and canting error with U, and
the factory record of the same heliostat beside them.

The DLR method's photogrammetry with the facets' corners as targets: the heliostat turns between the photos
(the camera stays), so in the heliostat's own frame the photos are views from different directions. One
bundle adjustment (``sofast_station.measure.bundle``, the line's own solver: Levenberg-Marquardt on the
normal equations, each kind of observation's noise estimated from its residuals, outliers left out, the
covariance of the solution) finds

* every corner seen in at least two photos, in the heliostat frame (3 unknowns each), and
* each photo's pose of the heliostat in the camera frame (6 each; the first photo's is held: it fixes the
  frame's position and turn),

from the corners found in every photo (:mod:`.detect`; ideal pixels weighted by their covariance) and each
facet's design size (its four sides and two diagonals, uncertain by the facet size's standard uncertainty:
they fix the scale, which the photos cannot). The commanded orientations only start the search and name
the facets in each photo; the fit needs nothing of the heliostat's drives or the camera's pointing.

Then, as on the line (docs/conventions.md#canting): the corners are laid onto the design's by the rigid
motion that fits them best (the heliostat frame), each facet's frame is the turn that best lays its design
corners onto its measured ones (its normal is that frame's z axis: the plane of its corners), and its
canting error is that frame in its design canting on the heliostat's frame turned by the common tilt that
leaves the errors zero mean. The field sees corners, not slopes: a facet whose mirror is bent under its
corners shows the factory a different optical frame from the field's corner frame (docs/field.md).

Uncertainty: the corners' covariance from the bundle (noise and facet sizes), through the canting's
derivatives (finite differences of the whole chain from corners to canting); the focal length's by
solving again with it moved by its standard uncertainty; combined and expanded with k = 2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..ensemble import EnsembleDesign, angles_mrad, rotation_mrad
from ..errors import AnalysisError
from ..geometry import CameraIntrinsics, Pose
from ..measure import bundle
from .geometry import azimuth_elevation, direction
from .orientation import facet_corners_h

K_COVERAGE = 2.0
#: The chi-square of 2 degrees of freedom that 95 % of differences stay below (a facet's field and factory
#: canting differ by more than their uncertainties when their difference lies outside this ellipse).
CHI2_2DOF_95 = 5.991
#: The tilt iteration of the zero-mean reference stops when both updates are below this, radians.
TILT_TOLERANCE_RAD = 1e-12


@dataclass(frozen=True)
class PhotoCorners:
    """One photo's part of the bundle.

    Attributes
    ----------
    name : str
    intrinsics : CameraIntrinsics
        Of the camera and zoom that took it (its matrix turns ideal pixels into rays).
    facets : dict
        Label -> an object with ``ideal_px`` (N, 2) and ``cov_px2`` (2N, 2N) (:class:`.detect.FacetFound`).
    initial : Pose or None
        A start for the heliostat frame -> camera frame pose (the commanded orientation and the camera's
        nominal pointing); None: from solvePnP on the corners.
    """

    name: str
    intrinsics: CameraIntrinsics
    facets: dict
    initial: Pose | None = None


@dataclass(frozen=True)
class Canting:
    """What the photos say of the heliostat's facets.

    Attributes
    ----------
    corners_m : dict
        Label -> (N, 3) measured corners in the heliostat frame (laid onto the design's), metres.
    normals : dict
        Label -> (3,) the facet's normal (its corners' plane), heliostat frame.
    canting_mrad : dict
        Label -> {"x", "y"} canting error; ``canting_mrad_U`` the same with U (k = 2); ``canting_rz_mrad``
        its turn about its normal (label -> mrad).
    flatness_mm : dict
        Label -> RMS distance of its measured corners from its design corners laid onto them (a facet bent
        or a corner misplaced), mm.
    photos : list of dict
        Per photo: name, facets used, corners' RMS reprojection (pixels), observations left out.
    corner_sigma_px : float
        The corners' noise as the bundle estimated it (one standard deviation, pixels), against their own
        covariance's (``corner_noise_scale``: 1 when as estimated).
    """

    corners_m: dict
    normals: dict
    canting_mrad: dict
    canting_mrad_U: dict
    canting_rz_mrad: dict
    flatness_mm: dict
    photos: list = field(default_factory=list)
    corner_noise_scale: float = 1.0
    facets_not_measured: dict = field(default_factory=dict)
    covariance_mrad2: dict = field(default_factory=dict)


def _kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rotation R and translation t that lay points *a* onto *b* best (b ~ R a + t)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def _whitening(cov: np.ndarray) -> np.ndarray:
    return np.linalg.inv(np.linalg.cholesky(0.5 * (cov + cov.T)))


def _initial_pose(photo: PhotoCorners, design: dict) -> Pose:
    labels = [k for k in photo.facets if k in design]
    obj = np.vstack([design[k] for k in labels])
    img = np.vstack([np.asarray(photo.facets[k].ideal_px, float) for k in labels])
    k = photo.intrinsics.matrix
    if photo.initial is not None:
        rvec, _ = cv2.Rodrigues(photo.initial.rotation)
        ok, rvec, tvec = cv2.solvePnP(obj, img, k, None, rvec=rvec.copy(),
                                      tvec=photo.initial.translation.reshape(3, 1).copy(), useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
        if ok:
            return Pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
    flat = obj.copy()
    flat[:, 2] = 0.0
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(flat, img, k, None, flags=cv2.SOLVEPNP_IPPE)
    best, best_err = None, math.inf
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, None, rvec.copy(), tvec.copy())
        proj, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
        err = float(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1)))
        if err < best_err:
            best, best_err = Pose(cv2.Rodrigues(rvec)[0], np.asarray(tvec, float).ravel()), err
    if best is None:
        raise AnalysisError(f"photo {photo.name}: no pose of the heliostat fits its corners (solvePnP failed)")
    return best


def _pairs(n: int) -> list:
    """Corner pairs whose distances a rigid facet of *n* corners keeps: its sides, and (a quadrilateral) its
    two diagonals."""
    out = [(i, (i + 1) % n) for i in range(n)]
    if n == 4:
        out += [(0, 2), (1, 3)]
    return out


def _bundle(photos: list, ensemble: EnsembleDesign, labels: list, facet_size_u_m: float, focal_change: float = 0.0,
            start: dict | None = None):
    """The bundle adjustment: returns (solution, corner index of each label)."""
    design = facet_corners_h(ensemble)
    index, rows = {}, 0
    for lab in labels:
        index[lab] = np.arange(rows, rows + len(design[lab]))
        rows += len(design[lab])
    x0 = np.vstack([design[lab] for lab in labels]).ravel() if start is None else start["X"]
    blocks = [bundle.Block("X", x0)]
    groups = []
    for k, photo in enumerate(photos):
        pose0 = _initial_pose(photo, design) if start is None else start[f"photo {k}"]
        blocks.append(bundle.Block(f"photo {k}", pose0, fixed=(k == 0)))
        used = [lab for lab in labels if lab in photo.facets]
        idx = np.concatenate([index[lab] for lab in used])
        obs = np.vstack([np.asarray(photo.facets[lab].ideal_px, float) for lab in used]).ravel()
        whiten = np.zeros((obs.size, obs.size))
        i = 0
        for lab in used:
            w = _whitening(np.asarray(photo.facets[lab].cov_px2, float))
            whiten[i:i + w.shape[0], i:i + w.shape[0]] = w
            i += w.shape[0]
        mat = photo.intrinsics.matrix
        cam = np.array([mat[0, 0] * (1 + focal_change), mat[1, 1] * (1 + focal_change), mat[0, 2], mat[1, 2],
                        0.0, 0.0, 0.0, 0.0, 0.0])

        def function(values, derivatives, k=k, idx=idx, obs=obs, whiten=whiten, cam=cam):
            pose = values[f"photo {k}"]
            pts = values["X"].reshape(-1, 3)[idx]
            x_cam = pose.apply(pts)
            if not derivatives:
                return whiten @ (bundle.project(cam, x_cam) - obs.reshape(-1, 2)).ravel()
            pix, d_pt, _ = bundle.project(cam, x_cam, derivatives=True)
            r = whiten @ (pix - obs.reshape(-1, 2)).ravel()
            d_pose = np.einsum("nij,njk->nik", d_pt, bundle.pose_derivative(pose, pts)).reshape(-1, 6)
            d_x = np.zeros((2 * len(idx), x0.size))
            local = np.einsum("nij,jk->nik", d_pt, pose.rotation)          # (n, 2, 3)
            for j, c in enumerate(idx):
                d_x[2 * j:2 * j + 2, 3 * c:3 * c + 3] = local[j]
            jac = {f"photo {k}": whiten @ d_pose, "X": whiten @ d_x}
            if k == 0:
                jac.pop("photo 0")
            return r, jac

        groups.append(bundle.Group("corners", ["X", f"photo {k}"], function, 1.0, label=photo.name))
    pairs = []
    for lab in labels:
        d = design[lab]
        for a, b in _pairs(len(d)):
            pairs.append((index[lab][a], index[lab][b], float(np.linalg.norm(d[a] - d[b]))))
    pa = np.array([p[0] for p in pairs])
    pb = np.array([p[1] for p in pairs])
    length = np.array([p[2] for p in pairs])

    def sizes(values, derivatives):
        pts = values["X"].reshape(-1, 3)
        v = pts[pa] - pts[pb]
        dist = np.linalg.norm(v, axis=1)
        r = dist - length
        if not derivatives:
            return r
        u = v / dist[:, None]
        jac = np.zeros((len(pairs), x0.size))
        for i, (a, b) in enumerate(zip(pa, pb)):
            jac[i, 3 * a:3 * a + 3] = u[i]
            jac[i, 3 * b:3 * b + 3] = -u[i]
        return r, {"X": jac}

    groups.append(bundle.Group("facet size", ["X"], sizes, facet_size_u_m, label="design sizes"))
    try:
        sol = bundle.solve(blocks, groups, known_noise=("facet size",))
    except ValueError as exc:
        raise AnalysisError(f"the photos do not determine the facets' corners: {exc}") from None
    return sol, index


def _facet_frames(corners: np.ndarray, index: dict, ensemble: EnsembleDesign, labels: list) -> tuple:
    """Laid onto the design (rigid), then each facet's frame (facet -> heliostat) from its corners."""
    design = facet_corners_h(ensemble)
    pts = corners.reshape(-1, 3)
    r, t = _kabsch(pts, np.vstack([design[lab] for lab in labels]))
    pts = pts @ r.T + t
    frames, laid = {}, {}
    for lab in labels:
        f = ensemble.facets[ensemble.index(lab)]
        local = f.design.corners_3d()
        rot, trans = _kabsch(local, pts[index[lab]])
        frames[lab] = rot
        laid[lab] = (pts[index[lab]], local @ rot.T + trans)
    return frames, laid


def _zero_mean(frames: dict, ensemble: EnsembleDesign) -> dict:
    """Canting errors (rx, ry, rz) in mrad of each facet frame against its design canting on the heliostat
    frame turned by the tilt that leaves rx and ry zero mean (docs/conventions.md#canting)."""
    design = {lab: ensemble.facets[ensemble.index(lab)].rotation for lab in frames}
    a = b = 0.0
    for _ in range(100):
        t = rotation_mrad(1e3 * a, 1e3 * b)
        ang = np.array([angles_mrad(design[lab].T @ t.T @ frames[lab])[:2] for lab in frames]) * 1e-3
        da, db = ang.mean(axis=0)
        a, b = a + da, b + db
        if abs(da) < TILT_TOLERANCE_RAD and abs(db) < TILT_TOLERANCE_RAD:
            break
    t = rotation_mrad(1e3 * a, 1e3 * b)
    return {lab: np.array(angles_mrad(design[lab].T @ t.T @ frames[lab])) for lab in frames}


def _canting_vector(x: np.ndarray, index: dict, ensemble: EnsembleDesign, labels: list) -> np.ndarray:
    frames, _ = _facet_frames(x, index, ensemble, labels)
    c = _zero_mean(frames, ensemble)
    return np.concatenate([c[lab][:2] for lab in labels])


def _canting_covariance(x: np.ndarray, cov_x: np.ndarray, index: dict, ensemble: EnsembleDesign,
                        labels: list) -> np.ndarray:
    """Covariance (mrad^2) of the canting vector (x, y of each facet in *labels*' order) from the corners'.

    To first order a facet's canting is its own tilt in the heliostat frame (a function of its own corners
    alone) less the facets' mean tilt: the frame's own turn moves every facet's tilt alike and the mean
    takes it out. So the derivatives are each facet's 2 x 3N block (finite differences of its own frame)
    and the centring (I - 1/n) across facets.
    """
    design = facet_corners_h(ensemble)
    pts = x.reshape(-1, 3)
    r, t = _kabsch(pts, np.vstack([design[lab] for lab in labels]))
    pts = pts @ r.T + t
    n = len(labels)
    jac = np.zeros((2 * n, x.size))
    step = 1e-6

    def tilt(lab, corners):
        f = ensemble.facets[ensemble.index(lab)]
        rot, _ = _kabsch(f.design.corners_3d(), corners)
        return np.array(angles_mrad(f.rotation.T @ rot)[:2])

    for j, lab in enumerate(labels):
        idx = index[lab]
        c0 = pts[idx]
        a0 = tilt(lab, c0)
        for i in range(len(idx)):
            for axis in range(3):
                c = c0.copy()
                c[i, axis] += step
                # the bundle's corners were turned by r onto the design frame: its coordinate b moves this one by
                # r[axis, b]
                d = (tilt(lab, c) - a0) / step
                jac[2 * j:2 * j + 2, 3 * idx[i]:3 * idx[i] + 3] += np.outer(d, r[axis])
    centring = np.kron(np.eye(n) - np.full((n, n), 1.0 / n), np.eye(2))
    jac = centring @ jac
    return jac @ cov_x @ jac.T


def solve_canting(photos: list, ensemble: EnsembleDesign, *, facet_size_u_mm: float = 1.0,
                  focal_length_rel: float = 0.002, min_photos_per_facet: int = 2) -> Canting:
    """Every facet's corners, normal and canting error from several photos (module docstring).

    Parameters
    ----------
    photos : list of PhotoCorners
        At least two, with the heliostat turned between them.
    ensemble : EnsembleDesign
    facet_size_u_mm : float
        Standard uncertainty of a facet's sides and diagonals against the design, mm.
    focal_length_rel : float
        Standard uncertainty of the focal length, relative.
    min_photos_per_facet : int
        A facet seen in fewer photos is not measured (its corners' depth is not determined).

    Raises
    ------
    AnalysisError
        Fewer than two photos, fewer than three facets seen often enough, or the bundle not determined.
    """
    if len(photos) < 2:
        raise AnalysisError(f"{len(photos)} photo(s): the canting needs at least 2, with the heliostat turned "
                            "between them (10 or more, over 30 degrees or more, for a milliradian)")
    seen = {lab: sum(lab in p.facets for p in photos) for lab in ensemble.labels}
    labels = [lab for lab in ensemble.labels if seen[lab] >= min_photos_per_facet]
    not_measured = {lab: f"seen in {seen[lab]} photo(s), fewer than {min_photos_per_facet}"
                    for lab in ensemble.labels if lab not in labels}
    if len(labels) < 3:
        raise AnalysisError(f"only {len(labels)} facet(s) seen in {min_photos_per_facet} or more photos: the canting "
                            "needs at least 3 (their mean is the reference)")
    if not photos[0].facets or not any(lab in photos[0].facets for lab in labels):
        raise AnalysisError(f"photo {photos[0].name} shows none of the facets measured: put a good photo first")
    used = [PhotoCorners(p.name, p.intrinsics, {k: v for k, v in p.facets.items() if k in labels}, p.initial)
            for p in photos]
    used = [p for p in used if len(p.facets) >= 2]
    sol, index = _bundle(used, ensemble, labels, 1e-3 * facet_size_u_mm)
    if sol.undetermined:
        raise AnalysisError("the photos do not determine the corners (" + ", ".join(sol.undetermined[:4]) + "): turn "
                            "the heliostat further between them")
    x = sol.values["X"]
    base = _canting_vector(x, index, ensemble, labels)
    cov = _canting_covariance(x, sol.covariance["X"], index, ensemble, labels)
    if focal_length_rel:
        start = {name: value for name, value in sol.values.items()}
        sol_f, _ = _bundle(used, ensemble, labels, 1e-3 * facet_size_u_mm, focal_change=focal_length_rel, start=start)
        delta = _canting_vector(sol_f.values["X"], index, ensemble, labels) - base
        cov = cov + np.outer(delta, delta)
    frames, laid = _facet_frames(x, index, ensemble, labels)
    full = _zero_mean(frames, ensemble)
    canting, canting_u, rz, normals, corners, flat, covs = {}, {}, {}, {}, {}, {}, {}
    for j, lab in enumerate(labels):
        c = cov[2 * j:2 * j + 2, 2 * j:2 * j + 2]
        canting[lab] = {"x": float(base[2 * j]), "y": float(base[2 * j + 1])}
        canting_u[lab] = {"x": K_COVERAGE * math.sqrt(max(c[0, 0], 0.0)),
                          "y": K_COVERAGE * math.sqrt(max(c[1, 1], 0.0))}
        covs[lab] = c
        rz[lab] = float(full[lab][2])
        normals[lab] = frames[lab][:, 2]
        measured, design_laid = laid[lab]
        corners[lab] = measured
        flat[lab] = 1e3 * float(np.sqrt(np.mean(np.sum((measured - design_laid) ** 2, axis=1))))
    per_photo = []
    for g, keep in zip(sol.groups, sol.keep):
        if g["kind"] != "corners":
            continue
        per_photo.append({"photo": g["label"], "observations": g["count"], "left_out": int((~keep).sum()),
                          "rms_whitened": g["rms"]})
    scale = float(sol.scales.get("corners", 1.0))
    for p, row in zip(used, per_photo):
        row["facets"] = len(p.facets)
        row["rms_px"] = _reprojection_px(p, sol.values[f"photo {used.index(p)}"], x.reshape(-1, 3), index)
    return Canting(corners_m=corners, normals=normals, canting_mrad=canting, canting_mrad_U=canting_u,
                   canting_rz_mrad=rz, flatness_mm=flat, photos=per_photo, corner_noise_scale=scale,
                   facets_not_measured=not_measured, covariance_mrad2=covs)


def _reprojection_px(photo: PhotoCorners, pose: Pose, pts: np.ndarray, index: dict) -> float:
    mat = photo.intrinsics.matrix
    cam = np.array([mat[0, 0], mat[1, 1], mat[0, 2], mat[1, 2], 0, 0, 0, 0, 0], dtype=float)
    res = []
    for lab, f in photo.facets.items():
        pix = bundle.project(cam, pose.apply(pts[index[lab]]))
        res.append(pix - np.asarray(f.ideal_px, float))
    r = np.vstack(res)
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def canting_figures(result: Canting) -> dict:
    """The canting's figures as JSON-ready data (docs/field.md#canting)."""
    facets = []
    for lab, c in result.canting_mrad.items():
        facets.append({"label": lab, "canting_mrad": c, "canting_mrad_U": result.canting_mrad_U[lab],
                       "canting_rz_mrad": result.canting_rz_mrad[lab], "normal": result.normals[lab].tolist(),
                       "corners_m": result.corners_m[lab].tolist(), "flatness_mm": result.flatness_mm[lab]})
    sizes = [math.hypot(c["x"], c["y"]) for c in result.canting_mrad.values()]
    worst = max(result.canting_mrad, key=lambda k: math.hypot(*result.canting_mrad[k].values()))
    return {"facets": facets, "not_measured": result.facets_not_measured, "photos": result.photos,
            "corner_noise_scale": result.corner_noise_scale,
            "canting_rms_mrad": float(math.sqrt(np.mean(np.square(sizes)))), "canting_max_mrad": float(max(sizes)),
            "canting_max_facet": worst}


def compare_with_factory(result: Canting, record: dict) -> dict:
    """Each facet's field canting beside the factory's (the line's heliostat record of the same serial).

    Both are re-referenced to zero mean over the facets both measured (each was zero mean over its own
    facets). A facet is flagged when the difference lies outside the 95 % ellipse of the two uncertainties
    combined: ``sum((d_a / u_a)^2) > 5.99`` over a = x, y, with u_a = sqrt(U_field^2 + U_factory^2) / 2
    (both U at k = 2).

    Returns
    -------
    dict
        ``serial``, ``facets`` (per facet ``label``, ``field``, ``factory``, ``difference_mrad`` {x, y},
        ``U_combined_mrad`` {x, y}, ``chi2``, ``flagged``), ``flagged`` (labels), ``not_compared``.
    """
    factory = {}
    for e in record.get("facets", []):
        c = e.get("canting_mrad")
        if isinstance(c, dict) and c.get("x") is not None and c.get("y") is not None:
            u = e.get("canting_mrad_U") or {}
            factory[str(e.get("label"))] = (float(c["x"]), float(c["y"]), float(u.get("x") or 0.0),
                                            float(u.get("y") or 0.0))
    common = [lab for lab in result.canting_mrad if lab in factory]
    not_compared = sorted((set(result.canting_mrad) | set(factory)) - set(common))
    if not common:
        return {"serial": record.get("serial"), "facets": [], "flagged": [], "not_compared": not_compared,
                "note": "no facet measured both in the field and at the factory"}
    fx = np.array([[result.canting_mrad[lab]["x"], result.canting_mrad[lab]["y"]] for lab in common])
    fc = np.array([factory[lab][:2] for lab in common])
    fx = fx - fx.mean(axis=0)
    fc = fc - fc.mean(axis=0)
    rows, flagged = [], []
    for j, lab in enumerate(common):
        d = fx[j] - fc[j]
        uf = result.canting_mrad_U[lab]
        ucomb = np.array([math.hypot(uf["x"], factory[lab][2]), math.hypot(uf["y"], factory[lab][3])])
        chi2 = float(np.sum((d / np.maximum(ucomb / K_COVERAGE, 1e-9)) ** 2))
        flag = chi2 > CHI2_2DOF_95
        if flag:
            flagged.append(lab)
        rows.append({"label": lab, "field_mrad": {"x": float(fx[j, 0]), "y": float(fx[j, 1])},
                     "factory_mrad": {"x": float(fc[j, 0]), "y": float(fc[j, 1])},
                     "difference_mrad": {"x": float(d[0]), "y": float(d[1])},
                     "U_combined_mrad": {"x": float(ucomb[0]), "y": float(ucomb[1])}, "chi2": chi2, "flagged": flag})
    return {"serial": record.get("serial"), "facets": rows, "flagged": flagged, "not_compared": not_compared}


def canting_orientations(camera_m, heliostat_m, *, count: int = 12, spread_deg: float = 30.0,
                         min_sky_elevation_deg: float = 10.0, sun=None, min_sun_angle_deg: float = 15.0) -> list:
    """Orientations (azimuth, elevation in radians) to command the heliostat to for its canting photos.

    They spread over *spread_deg* about the orientation that faces the camera (azimuth to either side, the
    elevation upwards from there), and keep only those whose mirrors show the camera the sky: the camera's
    line of sight to the heliostat, mirrored, at least *min_sky_elevation_deg* above the horizon (a mirror
    that shows the ground shows the camera what lies around it: its edges vanish) and, with *sun* (a unit
    vector), at least *min_sun_angle_deg* from the sun (the sun's reflection overexposes the photo).
    """
    c = np.asarray(camera_m, dtype=np.float64)
    h = np.asarray(heliostat_m, dtype=np.float64)
    az0, el0 = azimuth_elevation(c - h)
    view = (h - c) / np.linalg.norm(h - c)
    spread = math.radians(spread_deg)
    side = max(int(math.ceil(math.sqrt(4 * count))), 2)
    found = []
    for e in np.linspace(0.0, spread, side):
        for a in np.linspace(-spread, spread, side):
            az, el = az0 + a, min(el0 + e, math.radians(89.0))
            n = direction(az, el)
            r = view - 2.0 * float(view @ n) * n
            if math.degrees(math.asin(max(-1.0, min(1.0, r[2])))) < min_sky_elevation_deg:
                continue
            if sun is not None and math.degrees(math.acos(max(-1.0, min(1.0, float(r @ np.asarray(sun)))))) \
                    < min_sun_angle_deg:
                continue
            found.append((az % (2 * math.pi), el))
    if len(found) <= count:
        return found
    pick = np.round(np.linspace(0, len(found) - 1, count)).astype(int)
    return [found[i] for i in pick]
