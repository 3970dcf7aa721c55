"""A heliostat's orientation, and its tracking error, from one photograph taken from the tower.

The DLR method compares the side ratios and angles of the facets' images with those a central projection
gives for a trial azimuth and elevation. Here the same information is used whole: every found corner
(:mod:`.detect`) against the design's corners projected through the camera, for six unknowns

* the heliostat's azimuth, elevation and its spin about its normal (docs/field.md#frames),
* the camera's pointing, its optical axis's azimuth and elevation (pan and tilt: a pan-tilt head's readback
  is not good to a milliradian; the heliostat's known position, where the photo shows it, fixes them; the
  camera's roll about its axis from level stays as given whichever way it points), and
* the image's scale (a zoom factor): as in DLR's side ratios and angles, only the facets' shape in the
  photo decides the orientation, not their size. Their size is the focal length over the range times the
  facets' size, and each of those is known to a few tenths of a percent at best; through the
  foreshortening (a width times the cosine of the viewing angle) 0.2 % of size would turn the normal by
  10 mrad where the heliostat faces the camera within 10 degrees,

with the camera's position, its roll about the optical axis (a levelled head), its intrinsics, and the
heliostat's position (its pivot) and design held as given. Least squares (scipy's Levenberg-Marquardt) on
the corners weighted by their covariance, started from OpenCV's solvePnP (both of IPPE's planar solutions,
and the commanded orientation when there is one: the best of them).

Uncertainty (GUM, docs/uncertainty.md): the corners' noise through the fit's covariance (scaled up when
the residuals say the noise is larger than the corners' own estimate); each given input (camera position,
heliostat position, camera roll, focal length, facet size, pivot offset) by its standard uncertainty and
the change of the whole solution when it moves by that much (finite differences of the fit, re-solved);
each facet's canting about each of its axes through the fit's linear response (75 inputs on a 5 x 5);
combined in quadrature and expanded with k = 2. The figures are the normal's pointing components
(azimuth times cos(elevation), and elevation: the angles on the sky), their U, and the tracking error
against the commanded normal with the same U (the commanded normal is exact by definition).

Pure numpy, scipy and OpenCV; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.optimize import least_squares

from ..ensemble import EnsembleDesign
from ..errors import AnalysisError, GeometryError
from ..geometry import CameraIntrinsics
from .geometry import (azimuth_elevation, direction, heliostat_angles, heliostat_rotation, look_at,
                       pointing_error_mrad, small_rotation)

K_COVERAGE = 2.0


@dataclass(frozen=True)
class TowerCamera:
    """What is known of the tower's camera for one photo.

    Attributes
    ----------
    intrinsics : CameraIntrinsics
        At the zoom the photo was taken with.
    position_m : (3,) array
        Its projection centre, field frame, metres.
    roll_mrad : float
        Its turn about its optical axis from level (docs/field.md#frames).
    """

    intrinsics: CameraIntrinsics
    position_m: np.ndarray
    roll_mrad: float = 0.0

    def __post_init__(self):
        p = np.asarray(self.position_m, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise GeometryError(f"the tower camera's position must be 3 finite metres, got {self.position_m!r}")
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "roll_mrad", float(self.roll_mrad))


@dataclass(frozen=True)
class InputUncertainty:
    """Standard uncertainties of the given inputs (docs/field.md#uncertainty). Defaults: the DLR paper's
    Table 3 (30 mm for the camera's and the heliostat's positions per axis, 1 mm for a facet's size), a
    levelled head's roll (0.5 mrad), a calibrated zoom's focal length (0.2 %), the pivot's offset (1 cm) and
    each facet's canting about its own axes (0.5 mrad: the line's canting limit; a facet turned on the frame
    moves its corners together, which the corners' own noise does not describe).
    """

    camera_position_m: float = 0.03
    heliostat_position_m: float = 0.03
    camera_roll_mrad: float = 0.5
    focal_length_rel: float = 0.002
    facet_size_mm: float = 1.0
    pivot_offset_m: float = 0.01
    facet_canting_mrad: float = 0.5

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class HeliostatPlace:
    """What is known of the heliostat in the field: its design, its pivot (field frame, metres) and the
    distance of its frame's origin in front of the pivot along the normal (metres)."""

    ensemble: EnsembleDesign
    position_m: np.ndarray
    pivot_offset_m: float = 0.0
    serial: str = ""

    def __post_init__(self):
        p = np.asarray(self.position_m, dtype=np.float64).reshape(-1)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise GeometryError(f"the heliostat's position must be 3 finite metres, got {self.position_m!r}")
        object.__setattr__(self, "position_m", p)


def facet_corners_h(ensemble: EnsembleDesign, size_change_m: float = 0.0) -> dict:
    """Every facet's design corners in the heliostat frame {label: (N, 3)}, each outline grown by
    *size_change_m* in width and height about its middle (the facet-size input)."""
    out = {}
    for f in ensemble.facets:
        local = f.design.corners_3d()
        if size_change_m:
            mid = local[:, :2].mean(axis=0)
            half = 0.5 * np.ptp(local[:, :2], axis=0)
            local = local.copy()
            local[:, :2] = mid + (local[:, :2] - mid) * (1.0 + 0.5 * size_change_m / np.maximum(half, 1e-9))
        out[f.label] = f.to_heliostat.apply(local)
    return out


def heliostat_origin(place: HeliostatPlace, rotation: np.ndarray) -> np.ndarray:
    """The heliostat frame's origin in the field for a heliostat frame -> field rotation."""
    return place.position_m + place.pivot_offset_m * rotation[:, 2]


def predict_corners(place: HeliostatPlace, rotation: np.ndarray, camera: TowerCamera,
                    camera_rotation: np.ndarray) -> dict:
    """Where each facet's design corners appear in the photo {label: (N, 2) pixels, distorted} for the
    heliostat turned by *rotation* (heliostat -> field) and the camera turned by *camera_rotation* (field ->
    camera): only facets whose mirror faces the camera."""
    out = {}
    origin = heliostat_origin(place, rotation)
    k = camera.intrinsics
    for label, corners in facet_corners_h(place.ensemble).items():
        world = corners @ rotation.T + origin
        f = place.ensemble.facets[place.ensemble.index(label)]
        n = rotation @ f.rotation[:, 2]
        if float(n @ (camera.position_m - world.mean(axis=0))) <= 0:
            continue
        cam = (world - camera.position_m) @ camera_rotation.T
        if np.any(cam[:, 2] <= 0):
            continue
        px, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k.matrix, k.distortion)
        out[label] = px.reshape(-1, 2)
    return out


def nominal_pointing(camera: TowerCamera, place: HeliostatPlace) -> np.ndarray:
    """The camera's rotation (field -> camera) pointed at the heliostat's pivot with its stated roll."""
    return look_at(camera.position_m, place.position_m, 1e-3 * camera.roll_mrad)


@dataclass
class _Problem:
    corners_h: np.ndarray          # (M, 3) design corners, heliostat frame
    observed: np.ndarray           # (M, 2) ideal pixels
    whiten: np.ndarray             # (2M, 2M) block-diagonal inverse Cholesky factors
    place: HeliostatPlace
    camera: TowerCamera
    r_fc0: np.ndarray              # nominal camera rotation

    def __post_init__(self):
        self.axis = azimuth_elevation(self.r_fc0[2])

    def pointing(self, d_az: float, d_el: float) -> np.ndarray:
        """The camera's rotation with its optical axis moved by (d_az, d_el) in azimuth and elevation from
        the nominal, its roll about it kept (a level camera stays level whichever way it points)."""
        c = self.camera.position_m
        return look_at(c, c + direction(self.axis[0] + d_az, self.axis[1] + d_el), 1e-3 * self.camera.roll_mrad)

    def project(self, params: np.ndarray) -> np.ndarray:
        az, el, spin, d_az, d_el, log_scale = params
        r_h = heliostat_rotation(az, el, spin)
        world = self.corners_h @ r_h.T + heliostat_origin(self.place, r_h)
        r_fc = self.pointing(d_az, d_el)
        cam = (world - self.camera.position_m) @ r_fc.T
        k = self.camera.intrinsics.matrix
        m = math.exp(log_scale)
        return np.column_stack([m * k[0, 0] * cam[:, 0] / cam[:, 2] + k[0, 2],
                                m * k[1, 1] * cam[:, 1] / cam[:, 2] + k[1, 2]])

    def residuals(self, params: np.ndarray) -> np.ndarray:
        return self.whiten @ (self.project(params) - self.observed).ravel()


@dataclass(frozen=True)
class Orientation:
    """The heliostat's orientation from one photo.

    Attributes
    ----------
    normal : (3,) array
        Unit normal, field frame.
    azimuth_rad, elevation_rad, spin_rad : float
    camera_correction_mrad : (2,) array
        How far the camera's optical axis pointed from the heliostat's pivot: (azimuth, elevation), mrad.
    covariance_mrad2 : (2, 2) array
        Combined covariance of the normal's (azimuth x cos(elevation), elevation) components, mrad^2.
    budget : list of dict
        Per input: ``input``, ``u`` and ``unit``, the normal's change ``azimuth_mrad`` and ``elevation_mrad``
        when it moves by u; the corners' noise as ``corners (random)`` with its standard deviations.
    reprojection_rms_px : float
        RMS of the corners' distances from the fitted projection, pixels.
    chi2_per_dof : float
        The residuals against the corners' covariance (1 when the corners' noise is as estimated).
    n_facets, n_corners : int
    alternative : dict or None
        A second, distinct minimum of nearly the same cost (``normal``, ``cost_ratio``): the photo cannot tell
        the two orientations apart well (the normal points near the camera).
    """

    normal: np.ndarray
    azimuth_rad: float
    elevation_rad: float
    spin_rad: float
    camera_correction_mrad: np.ndarray
    covariance_mrad2: np.ndarray
    budget: list = field(default_factory=list)
    reprojection_rms_px: float = 0.0
    chi2_per_dof: float = 1.0
    n_facets: int = 0
    n_corners: int = 0
    alternative: dict | None = None

    @property
    def u_mrad(self) -> np.ndarray:
        """Standard uncertainties of (azimuth x cos(elevation), elevation), mrad."""
        return np.sqrt(np.clip(np.diag(self.covariance_mrad2), 0.0, None))

    @property
    def u_angle_mrad(self) -> float:
        """The largest standard uncertainty of the normal's direction over all directions on the sky, mrad."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.covariance_mrad2).max(), 0.0)))

    @property
    def u_azimuth_mrad(self) -> float:
        """Standard uncertainty of the azimuth angle itself (not times cos(elevation)), mrad."""
        return float(self.u_mrad[0] / max(math.cos(self.elevation_rad), 1e-6))


def _whitening(covs: list) -> np.ndarray:
    blocks = []
    for c in covs:
        c = 0.5 * (c + c.T)
        l_inv = np.linalg.inv(np.linalg.cholesky(c))
        blocks.append(l_inv)
    n = sum(b.shape[0] for b in blocks)
    out = np.zeros((n, n))
    i = 0
    for b in blocks:
        out[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    return out


def _solve(problem: _Problem, starts: list) -> tuple:
    fits = []
    for x0 in starts:
        try:
            # a soft-L1 loss beyond 3 standard deviations: a corner pulled by a glint in a gap (a neighbour's
            # bright sliver seen through it) leans on the fit less than its square would
            r = least_squares(problem.residuals, np.asarray(x0, dtype=np.float64), method="trf", loss="soft_l1",
                              f_scale=3.0, x_scale=1e-3, xtol=1e-12, ftol=1e-12, max_nfev=400)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if np.all(np.isfinite(r.x)):
            fits.append(r)
    if not fits:
        raise AnalysisError("the orientation fit did not converge from any start: check the heliostat's position, "
                            "its design and the camera's intrinsics")
    fits.sort(key=lambda r: r.cost)
    return fits[0], fits


def _starts(problem: _Problem, commanded: tuple | None) -> list:
    """Starting points: the commanded orientation, and each of IPPE's planar solutions for the corners."""
    starts = []
    if commanded is not None:
        starts.append([commanded[0], commanded[1], 0.0, 0.0, 0.0, 0.0])
    obj = problem.corners_h.copy()
    obj[:, 2] = 0.0           # IPPE wants a plane: the canting's millimetres do not matter for a start
    k = problem.camera.intrinsics.matrix
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj.astype(np.float64), problem.observed.astype(np.float64), k, None,
                                                  flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        n, rvecs, tvecs = 0, [], []
    for rvec, tvec in zip(rvecs[:n], tvecs[:n]):
        r_rel, _ = cv2.Rodrigues(rvec)
        t = np.asarray(tvec, float).ravel()
        # the camera's pointing from where the photo shows the heliostat's middle
        seen = problem.camera.position_m + problem.r_fc0.T @ t
        a0 = azimuth_elevation(problem.place.position_m - problem.camera.position_m)
        a1 = azimuth_elevation(seen - problem.camera.position_m)
        d_az = -((a1[0] - a0[0] + math.pi) % (2 * math.pi) - math.pi)
        d_el = -(a1[1] - a0[1])
        az, el, spin = heliostat_angles(problem.pointing(d_az, d_el).T @ r_rel)
        starts.append([az, el, spin, d_az, d_el, 0.0])
    return starts


def _problem(found: dict, place: HeliostatPlace, camera: TowerCamera, size_change_m: float = 0.0) -> _Problem:
    corners = facet_corners_h(place.ensemble, size_change_m)
    labels = [k for k in found if k in corners]
    obs = np.vstack([np.asarray(found[k].ideal_px, float) for k in labels])
    covs = [np.asarray(found[k].cov_px2, float) for k in labels]
    return _Problem(np.vstack([corners[k] for k in labels]), obs, _whitening(covs), place, camera,
                    nominal_pointing(camera, place))


def _components(params: np.ndarray) -> np.ndarray:
    """(azimuth x cos(elevation), elevation) of the normal, mrad (for differences)."""
    return 1e3 * np.array([params[0] * math.cos(params[1]), params[1]])


def solve_orientation(found: dict, place: HeliostatPlace, camera: TowerCamera, *,
                      commanded: tuple | None = None, uncertainty: InputUncertainty = InputUncertainty()
                      ) -> Orientation:
    """The heliostat's orientation from the corners found in one photo, with its uncertainty budget.

    Parameters
    ----------
    found : dict
        Label -> an object with ``ideal_px`` (N, 2) and ``cov_px2`` (2N, 2N) (:class:`.detect.FacetFound`).
    place : HeliostatPlace
    camera : TowerCamera
    commanded : (azimuth, elevation) radians, optional
        The commanded orientation: a start of the fit (the nearer of two near-equal minima).
    uncertainty : InputUncertainty

    Raises
    ------
    AnalysisError
        Fewer than two facets' corners, or the fit did not converge.
    """
    if len(found) < 2:
        raise AnalysisError(f"{len(found)} facet(s) found: the orientation needs the corners of at least 2")
    problem = _problem(found, place, camera)
    best, fits = _solve(problem, _starts(problem, commanded))
    x = best.x
    x[0] %= 2.0 * math.pi
    m = problem.observed.size
    dof = max(m - 6, 1)
    chi2 = 2.0 * best.cost / dof
    alternative = None
    for r in fits[1:]:
        d = float(np.hypot(*(_components(r.x) - _components(x))))
        if d > 5.0 and r.cost < 2.0 * best.cost + 10.0:
            az, el = r.x[0] % (2 * math.pi), r.x[1]
            alternative = {"normal": direction(az, el).tolist(), "cost_ratio": float(r.cost / max(best.cost, 1e-12)),
                           "apart_mrad": d}
            break
    # random: the corners through the fit's covariance, scaled when the residuals exceed their estimate
    jac = best.jac
    try:
        cov_params = np.linalg.inv(jac.T @ jac) * max(1.0, chi2)
    except np.linalg.LinAlgError:
        raise AnalysisError("the corners do not determine the orientation (singular fit)") from None
    d = np.diag([1e3 * math.cos(x[1]), 1e3])
    cov_random = d @ cov_params[:2, :2] @ d
    budget = [{"input": "corners (random)", "u": float(math.sqrt(max(1.0, chi2))), "unit": "x the corners' own u",
               "azimuth_mrad": float(math.sqrt(cov_random[0, 0])),
               "elevation_mrad": float(math.sqrt(cov_random[1, 1]))}]
    total = cov_random.copy()
    base = _components(x)

    def moved(label, u, unit, **changes):
        nonlocal total
        if not u:
            return
        cam = camera
        pl = place
        size = 0.0
        if "camera_position" in changes:
            cam = replace(camera, position_m=camera.position_m + changes["camera_position"])
        if "roll" in changes:
            cam = replace(camera, roll_mrad=camera.roll_mrad + changes["roll"])
        if "focal" in changes:
            k = camera.intrinsics
            mat = k.matrix.copy()
            mat[0, 0] *= 1.0 + changes["focal"]
            mat[1, 1] *= 1.0 + changes["focal"]
            cam = replace(camera, intrinsics=CameraIntrinsics(k.width_px, k.height_px, mat, k.distortion))
        if "heliostat_position" in changes:
            pl = replace(place, position_m=place.position_m + changes["heliostat_position"])
        if "pivot" in changes:
            pl = replace(pl, pivot_offset_m=place.pivot_offset_m + changes["pivot"])
        if "size" in changes:
            size = changes["size"]
        p2 = _problem(found, pl, cam, size)        # the corners' pixels stay: they are what was measured
        r = least_squares(p2.residuals, x, method="trf", loss="soft_l1", f_scale=3.0, x_scale=1e-3, xtol=1e-12,
                          ftol=1e-12, max_nfev=200)
        delta = _components(r.x) - base
        total = total + np.outer(delta, delta)
        budget.append({"input": label, "u": float(u), "unit": unit, "azimuth_mrad": float(delta[0]),
                       "elevation_mrad": float(delta[1])})

    uc = uncertainty
    for axis, name in enumerate("xyz"):
        e = np.zeros(3)
        e[axis] = uc.camera_position_m
        moved(f"camera position {name}", uc.camera_position_m, "m", camera_position=e)
    for axis, name in enumerate("xyz"):
        e = np.zeros(3)
        e[axis] = uc.heliostat_position_m
        moved(f"heliostat position {name}", uc.heliostat_position_m, "m", heliostat_position=e)
    moved("camera roll", uc.camera_roll_mrad, "mrad", roll=uc.camera_roll_mrad)
    moved("focal length", uc.focal_length_rel, "relative", focal=uc.focal_length_rel)
    moved("facet size", uc.facet_size_mm, "mm", size=1e-3 * uc.facet_size_mm)
    moved("pivot offset", uc.pivot_offset_m, "m", pivot=uc.pivot_offset_m)
    # each facet's canting (independent between facets, about each of its axes), through the fit's linear
    # response: the parameters move by -pinv(J) (the residuals' change when that facet turns by u)
    if uc.facet_canting_mrad:
        pinv = np.linalg.pinv(jac)
        base_px = problem.project(x)
        acc = np.zeros((2, 2))
        design = facet_corners_h(place.ensemble)
        start = 0
        for label in [k for k in found if k in design]:
            f = place.ensemble.facets[place.ensemble.index(label)]
            n = len(design[label])
            local = f.design.corners_3d()
            mid = local.mean(axis=0)
            for axis in range(3):
                omega = np.zeros(3)
                omega[axis] = 1e-3 * uc.facet_canting_mrad
                turned = f.to_heliostat.apply(mid + (local - mid) @ small_rotation(omega).T)
                moved_corners = problem.corners_h.copy()
                moved_corners[start:start + n] = turned
                trial = _Problem(moved_corners, problem.observed, problem.whiten, place, camera, problem.r_fc0)
                dr = problem.whiten @ (trial.project(x) - base_px).ravel()
                dx = -pinv @ dr
                dc = np.array([1e3 * dx[0] * math.cos(x[1]), 1e3 * dx[1]])
                acc += np.outer(dc, dc)
            start += n
        total = total + acc
        budget.append({"input": "facet canting (each facet, each axis)", "u": float(uc.facet_canting_mrad),
                       "unit": "mrad", "azimuth_mrad": float(math.sqrt(acc[0, 0])),
                       "elevation_mrad": float(math.sqrt(acc[1, 1]))})
    residual_px = problem.project(x) - problem.observed
    return Orientation(normal=direction(x[0], x[1]), azimuth_rad=float(x[0]), elevation_rad=float(x[1]),
                       spin_rad=float(x[2]), camera_correction_mrad=1e3 * np.array([x[3], x[4]]),
                       covariance_mrad2=total, budget=budget,
                       reprojection_rms_px=float(np.sqrt(np.mean(np.sum(residual_px ** 2, axis=1)))),
                       chi2_per_dof=float(chi2), n_facets=len(found), n_corners=int(m // 2), alternative=alternative)


def orientation_figures(result: Orientation, commanded_normal=None) -> dict:
    """The orientation's figures as JSON-ready data (docs/field.md#orientation): the normal, its azimuth and
    elevation with U (k = 2), and the tracking error against *commanded_normal* when given."""
    u = result.u_mrad
    big_u = K_COVERAGE * u
    az, el = azimuth_elevation(result.normal)
    out = {"normal": result.normal.tolist(),
           "azimuth_deg": math.degrees(az), "azimuth_deg_U": math.degrees(1e-3 * K_COVERAGE * result.u_azimuth_mrad),
           "elevation_deg": math.degrees(el), "elevation_deg_U": math.degrees(1e-3 * big_u[1]),
           "pointing_U_mrad": {"azimuth": float(big_u[0]), "elevation": float(big_u[1]),
                               "largest": K_COVERAGE * result.u_angle_mrad, "k": K_COVERAGE},
           "spin_mrad": 1e3 * result.spin_rad,
           "camera_correction_mrad": {"azimuth": float(result.camera_correction_mrad[0]),
                                      "elevation": float(result.camera_correction_mrad[1])},
           "facets_used": result.n_facets, "corners_used": result.n_corners,
           "reprojection_rms_px": result.reprojection_rms_px, "chi2_per_dof": result.chi2_per_dof,
           "uncertainty_budget": result.budget}
    if result.alternative is not None:
        out["alternative"] = result.alternative
    if commanded_normal is not None:
        err = pointing_error_mrad(result.normal, commanded_normal)
        c_az, c_el = azimuth_elevation(commanded_normal)
        size = err["angle_mrad"]
        ex, ey = err["azimuth_mrad"], err["elevation_mrad"]
        # U of the error's size along its own direction
        along = (math.sqrt(ex * ex * big_u[0] ** 2 + ey * ey * big_u[1] ** 2) / size) if size > 0 else float(max(big_u))
        out["commanded"] = {"normal": np.asarray(commanded_normal, float).tolist(), "azimuth_deg": math.degrees(c_az),
                            "elevation_deg": math.degrees(c_el)}
        out["tracking_error_mrad"] = {"azimuth": ex, "elevation": ey, "angle": size}
        out["tracking_error_mrad_U"] = {"azimuth": float(big_u[0]), "elevation": float(big_u[1]), "angle": along,
                                        "k": K_COVERAGE}
    return out
