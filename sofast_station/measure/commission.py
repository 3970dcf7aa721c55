"""Commissioning the station's geometry: the screen's shape and pitch, and the camera's pose against it.

Two bundle adjustments (:mod:`sofast_station.measure.bundle`) of reprojection errors, in pixels:

**The screen** (:func:`fit_screen`), from views of a second, calibrated camera. Each view sees the screen
showing ChArUco fiducials (corners at exactly known display positions) and phase fringes (every pixel's
display position), and a certified flat scale board fixed beside the screen. Unknowns: every view's pose
(the screen frame in the camera), the board's pose on the screen, the board's scale (prior: its
certificate), the camera's intrinsics (prior: its calibration) and the screen's shape
(:mod:`sofast_station.measure.screen_shape`). The board sets the metric scale, so the pitch is measured,
not assumed. The three shape models are fitted on the same observations; the simplest that leaves no
significantly larger residual than the richest (F test, 99 %) and whose pitch agrees with the richest's
(within two of its standard uncertainties) is chosen.

**The pose** (:func:`fit_pose`), from the station camera looking at a flat reference mirror in the
fixture whose printed frame is a certified ChArUco target, in several placements (tilted by shims). Per
placement the target's corners fix the mirror's plane; through the mirror every pixel sees a display
position (fringes): the screen point there, reflected in the plane, must project onto the pixel. The
range finder's distance from the screen centre to the target's measure point joins them. Unknowns: the
screen's pose in the camera (6), every placement's target pose (6 each), the target's scale and the
screen's pitch (priors: the certificate and the screen calibration).

Every residual is an image position error; the noise of each kind of observation is estimated from the
residuals (variance component estimation), outliers beyond 5 sigma are dropped and counted, and the
covariance comes from the weighted Jacobian at the solution.

Pure numpy/scipy/OpenCV; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.ndimage import binary_erosion

from ..fringes import FringeSet
from ..geometry import CameraIntrinsics, Pose
from . import bundle
from .phase import intensity_noise_dn, phase_and_modulation, position_sigma_m, unwrap_positions
from .screen_shape import MODELS, ScreenShape, parameter_names


# -- fringes: every pixel's display position -------------------------------------------------------
@dataclass(frozen=True)
class DecodedView:
    """Display positions seen by every pixel of one capture.

    Attributes
    ----------
    positions_m : (H, W, 2) array
        (u_x, u_y), stated metres from the active area's left and bottom edges; NaN where invalid.
    sigma_m : (H, W, 2) array
        Their noise (finest phase), metres.
    valid : (H, W) bool array
    noise_dn : float
        The capture's intensity noise per frame, DN.
    """

    positions_m: np.ndarray
    sigma_m: np.ndarray
    valid: np.ndarray
    noise_dn: float


def decode_positions(frames: np.ndarray, fringes: FringeSet, screen_size_m: tuple[float, float], *,
                     min_contrast_dn: float = 20.0, min_modulation_dn: float = 4.0,
                     consistency_sigmas: float = 6.0, erode_px: int = 2) -> DecodedView:
    """Decode a fringe capture (dark, white, then the sets in :meth:`FringeSet.patterns` order).

    A pixel is valid where white - dark exceeds *min_contrast_dn*, every set's modulation exceeds
    *min_modulation_dn*, its four-step residual stays within *consistency_sigmas* x 2 x the noise (+1 DN),
    unwrapping agrees (docs/conventions.md#unwrapping), and so do all its neighbours within *erode_px*
    (a pixel that sees the edge of the screen, of a marker or of an occluding object sees two positions).
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.shape[0] != fringes.n_frames:
        raise ValueError(f"need {fringes.n_frames} frames (dark, white, fringes), got shape {frames.shape}")
    dark = frames[0].astype(np.float32)
    white = frames[1].astype(np.float32)
    mask = (white - dark) > min_contrast_dn
    shape = mask.shape
    slices = fringes.slices()
    raw = {}
    residuals = []
    for axis in ("x", "y"):
        sets = []
        for sl in slices[axis]:
            phase, mod, cons = phase_and_modulation(frames[sl])
            sets.append((phase, mod, cons))
            residuals.append(cons[mask])
        raw[axis] = sets
    noise = intensity_noise_dn(np.concatenate(residuals)) if residuals else 0.0
    limit = consistency_sigmas * 2.0 * max(noise, 0.5) + 1.0
    valid = mask.copy()
    positions = np.full(shape + (2,), np.nan)
    sigma = np.full(shape + (2,), np.nan)
    for a, axis in enumerate(("x", "y")):
        periods = getattr(fringes, f"periods_{axis}")
        length = screen_size_m[a]
        for _, mod, cons in raw[axis]:
            valid &= (mod > min_modulation_dn) & (np.abs(cons) <= limit)
        s = position_sigma_m(raw[axis][-1][1], max(noise, 0.5), periods[-1], length)
        res = unwrap_positions([p for p, _, _ in raw[axis]], periods, length, s, 4.0)
        valid &= res.valid
        positions[..., a] = res.position_m
        sigma[..., a] = s
    if erode_px > 0:
        valid = binary_erosion(valid, structure=np.ones((2 * erode_px + 1, 2 * erode_px + 1), bool))
    positions[~valid] = np.nan
    return DecodedView(positions, sigma, valid, float(noise))


def fringe_samples(decoded: DecodedView, max_samples: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every n-th valid pixel in raster order (at most *max_samples*): pixel positions (K, 2) (column,
    row), display positions (K, 2) and their noise (K, 2), metres."""
    idx = np.flatnonzero(decoded.valid.ravel())
    if idx.size > max_samples > 0:
        idx = idx[:: -(-idx.size // max_samples)]
    rows, cols = np.divmod(idx, decoded.valid.shape[1])
    px = np.column_stack([cols, rows]).astype(np.float64)
    return px, decoded.positions_m.reshape(-1, 2)[idx], decoded.sigma_m.reshape(-1, 2)[idx]


def _uv_sigma_in_pixels(project_uv, uv: np.ndarray, sigma_uv: np.ndarray, step_m: float = 1e-4) -> np.ndarray:
    """Per sample, the standard deviation (K, 2) in image x and y that display-position noise *sigma_uv*
    becomes through ``project_uv`` (display positions -> pixels), by finite differences."""
    p0 = project_uv(uv)
    jx = (project_uv(uv + [step_m, 0.0]) - p0) / step_m
    jy = (project_uv(uv + [0.0, step_m]) - p0) / step_m
    return np.sqrt((jx * sigma_uv[:, :1]) ** 2 + (jy * sigma_uv[:, 1:2]) ** 2)


def _pnp(object_points: np.ndarray, image_points: np.ndarray, camera: CameraIntrinsics,
         initial: Pose | None = None) -> Pose:
    obj = np.ascontiguousarray(object_points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(image_points, dtype=np.float64).reshape(-1, 1, 2)
    if obj.shape[0] != img.shape[0]:
        raise ValueError(f"{obj.shape[0]} object points against {img.shape[0]} image points")
    spread = np.linalg.svd(obj.reshape(-1, 3) - obj.reshape(-1, 3).mean(axis=0), compute_uv=False)
    if obj.shape[0] < 4 or spread[1] <= 1e-6 * spread[0]:
        raise ValueError("the points lie on a line: no pose fits them")
    if initial is None:
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.matrix, camera.distortion, flags=cv2.SOLVEPNP_ITERATIVE)
    else:
        rvec0, _ = cv2.Rodrigues(initial.rotation)
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.matrix, camera.distortion, rvec=rvec0.copy(),
                                      tvec=initial.translation.reshape(3, 1).copy(), useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        raise ValueError("no pose fits the points")
    return Pose(cv2.Rodrigues(rvec)[0], tvec.ravel())


# -- the screen ------------------------------------------------------------------------------------
@dataclass
class ScreenView:
    """What one view of the screen gives.

    Attributes
    ----------
    label : str
    corners_px, corners_uv : (N, 2) arrays
        Screen fiducial corners: image positions (pixels) and display positions (stated metres).
    board_px : (M, 2) array, board_xy : (M, 2) array
        Scale board corners: image positions and certified board-frame positions (metres).
    fringe_px, fringe_uv, fringe_sigma_uv : (K, 2) arrays
        Fringe samples: pixel positions, display positions and their noise (metres).
    """

    label: str
    corners_px: np.ndarray
    corners_uv: np.ndarray
    board_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    board_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fringe_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fringe_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    fringe_sigma_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass
class ModelFit:
    """One shape model fitted to the views.

    Attributes
    ----------
    shape : ScreenShape
    solution : bundle.Solution
    views : list of Pose
        Every view's ``screen_to_camera``.
    board_to_screen : Pose or None
    camera : (9,) array
        The camera's (fx, fy, cx, cy, k1, k2, p1, p2, k3) as refined.
    scale : float
        The board's scale factor (1 = as certified).
    """

    shape: ScreenShape
    solution: bundle.Solution
    views: list
    board_to_screen: Pose | None
    camera: np.ndarray
    scale: float

    @property
    def shape_covariance(self) -> np.ndarray:
        return self.solution.covariance["shape"]


@dataclass
class ScreenFit:
    """The screen calibration's fit: every model, the test between them and the one chosen.

    Attributes
    ----------
    fits : dict
        Model name -> :class:`ModelFit`.
    chosen : str
    tests : dict
        Model name -> the F test against the richest (``F``, ``critical``, ``needed``).
    """

    fits: dict
    chosen: str
    tests: dict

    @property
    def best(self) -> ModelFit:
        return self.fits[self.chosen]


def _flat_points(uv: np.ndarray, width_m: float, height_m: float) -> np.ndarray:
    return np.column_stack([uv[:, 0] - 0.5 * width_m, uv[:, 1] - 0.5 * height_m, np.zeros(len(uv))])


def initial_screen_poses(views: list[ScreenView], camera: CameraIntrinsics, width_m: float,
                         height_m: float) -> list[Pose]:
    """Every view's pose by solvePnP against the stated flat screen (corners, else fringe samples)."""
    poses = []
    for v in views:
        if len(v.corners_uv) >= 6:
            obj, img = _flat_points(v.corners_uv, width_m, height_m), v.corners_px
        elif len(v.fringe_uv) >= 6:
            obj, img = _flat_points(v.fringe_uv, width_m, height_m), v.fringe_px
        else:
            raise ValueError(f"view {v.label}: too few points to place the camera")
        poses.append(_pnp(obj, img, camera))
    return poses


def _points_group(pose_name: str, px: np.ndarray, points_in_pose, extra):
    """A group function: camera-frame points ``values[pose_name].apply(points)`` projected and compared with
    *px*. ``points_in_pose(values, der)`` gives the points in the pose's source frame and, with *der*, a dict
    of their derivatives (N, 3, n_block) with respect to other blocks; *extra* lists those blocks."""

    def f(values, der):
        pose = values[pose_name]
        cam = values["camera"]
        if not der:
            pts = points_in_pose(values, False)
            return (bundle.project(cam, pose.apply(pts)) - px).ravel()
        pts, d_pts = points_in_pose(values, True)
        pix, d_pix, d_cam = bundle.project(cam, pose.apply(pts), True)
        jac = {pose_name: np.einsum("nij,njk->nik", d_pix, bundle.pose_derivative(pose, pts)).reshape(-1, 6),
               "camera": d_cam.reshape(-1, 9)}
        r = pose.rotation
        for name in extra:
            d = np.einsum("ij,njk->nik", r, d_pts[name])
            jac[name] = np.einsum("nij,njk->nik", d_pix, d).reshape(-1, d.shape[-1])
        return (pix - px).ravel(), jac

    return f


def _screen_problem(views: list[ScreenView], camera: CameraIntrinsics, camera_std, model: str, width_m: float,
                    height_m: float, scale_u: float, starts: dict) -> tuple[list, list]:
    """Blocks and residual groups of the screen's bundle adjustment for *model*."""
    shape0 = ScreenShape(model, width_m, height_m)
    names = parameter_names(model)
    shape_x0 = np.zeros(len(names))
    if "shape" in starts:                       # a richer model's parameters, where they apply
        for name, value in starts["shape"].items():
            if name in names:
                shape_x0[names.index(name)] = value
    cam0 = bundle.camera_vector(camera)
    cam_std = None if camera_std is None else np.asarray(camera_std, dtype=np.float64)
    blocks = [bundle.Block("shape", shape_x0, names=names),
              bundle.Block("camera", starts.get("camera", cam0), prior=cam0, prior_std=cam_std, fixed=cam_std is None,
                           names=list(CAMERA_NAMES))]
    has_board = any(len(v.board_xy) for v in views)
    if has_board:
        blocks.append(bundle.Block("board", starts["board_to_screen"],
                                   names=[f"board {n}" for n in ("rx", "ry", "rz", "tx", "ty", "tz")]))
        blocks.append(bundle.Block("scale", [starts.get("scale", 1.0)], prior=[1.0], prior_std=[scale_u],
                                   names=["board scale"]))
    groups = []
    for k, (v, pose0) in enumerate(zip(views, starts["views"])):
        name = f"view {k}"
        blocks.append(bundle.Block(name, pose0, names=[f"{v.label} {n}" for n in ("rx", "ry", "rz", "tx", "ty", "tz")]))
        for kind, px, uv in (("screen corners", v.corners_px, v.corners_uv), ("fringes", v.fringe_px, v.fringe_uv)):
            if len(px) == 0:
                continue
            base, design = shape0.basis(uv[:, 0], uv[:, 1])

            def on_screen(values, der, base=base, design=design):
                pts = base + design @ values["shape"]
                return (pts, {"shape": design}) if der else pts

            if kind == "fringes":
                sigma = starts["fringe_sigma"][k]
            else:
                sigma = 0.1
            groups.append(bundle.Group(kind, [name, "shape", "camera"], _points_group(name, px, on_screen, ["shape"]),
                                       sigma, f"{v.label} {kind}"))
        if has_board and len(v.board_xy):
            xy = np.column_stack([v.board_xy, np.zeros(len(v.board_xy))])

            def on_board(values, der, xy=xy):
                board = values["board"]
                s = values["scale"][0]
                pts = board.apply(xy * s)
                if not der:
                    return pts
                return pts, {"board": bundle.pose_derivative(board, xy * s),
                             "scale": (xy @ board.rotation.T)[:, :, None]}

            groups.append(bundle.Group("board corners", [name, "board", "scale", "camera"],
                                       _points_group(name, v.board_px, on_board, ["board", "scale"]), 0.1,
                                       f"{v.label} board corners"))
    return blocks, groups


def _model_fit(shape_model: str, sol: bundle.Solution, views: list[ScreenView], starts: dict, width_m: float,
               height_m: float) -> ModelFit:
    shape = ScreenShape(shape_model, width_m, height_m, sol.values["shape"])
    poses = [sol.values[f"view {k}"] for k in range(len(views))]
    board = None
    scale = 1.0
    if "board" in sol.values:
        board = sol.values["board"]
        scale = float(sol.values["scale"][0])
    return ModelFit(shape, sol, poses, board, np.asarray(sol.values["camera"]), scale)


#: Names of the camera parameters, in :func:`~sofast_station.measure.bundle.camera_vector`'s order.
CAMERA_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


def _camera_std(camera: CameraIntrinsics, camera_std):
    """Priors' standard deviations for the camera block: None holds it; a zero entry is a stiff prior
    (a millionth of the parameter's natural size)."""
    if camera_std is None:
        return None
    std = np.asarray(camera_std, dtype=np.float64)
    if std.shape != (9,) or np.any(~np.isfinite(std)) or np.any(std < 0):
        raise ValueError(f"camera_std must be 9 non-negative numbers ({', '.join(CAMERA_NAMES)}), got {camera_std}")
    natural = np.array([camera.matrix[0, 0], camera.matrix[1, 1], camera.width_px, camera.height_px,
                        1, 1, 0.01, 0.01, 1])
    return np.where(std > 0, std, 1e-6 * natural)


def _restart(starts: dict, rich: bundle.Solution, shape_start: dict, n_views: int) -> dict:
    """Start another model from the richest's solution (poses, camera, board, scale)."""
    st = dict(starts, shape=shape_start, camera=rich.values["camera"],
              views=[rich.values[f"view {k}"] for k in range(n_views)])
    if "board" in rich.values:
        st.update(board_to_screen=rich.values["board"], scale=float(rich.values["scale"][0]))
    return st


def fit_screen(views: list[ScreenView], camera: CameraIntrinsics, width_m: float, height_m: float, *,
               camera_std=None, scale_u: float = 5e-5, models: tuple = MODELS, confidence: float = 0.99,
               force: str | None = None) -> ScreenFit:
    """Fit the screen's shape to the views (module docstring).

    Parameters
    ----------
    views : list of ScreenView
    camera : CameraIntrinsics
        The second camera's calibration.
    width_m, height_m : float
        The stated active extents (the positions' units).
    camera_std : (9,) array, optional
        Standard deviations of the camera's (fx, fy, cx, cy, k1, k2, p1, p2, k3): the intrinsics are refined
        with these priors (a zero entry holds that parameter at its calibrated value... as a stiff prior);
        None holds them all fixed.
    scale_u : float
        The scale board's relative standard uncertainty (its certificate).
    models : tuple of str
        The models to fit, simplest first; the last is the reference of the F tests.
    force : str, optional
        Take this model whatever the tests say.

    Raises
    ------
    ValueError
        When the views cannot be placed (too few points) or the problem has too few observations.
    """
    if not views:
        raise ValueError("no views")
    models = tuple(models)
    for m in models:
        if m not in MODELS:
            raise ValueError(f"unknown screen model {m!r}; use {', '.join(MODELS)}")
    camera_std = _camera_std(camera, camera_std)
    starts = {"views": initial_screen_poses(views, camera, width_m, height_m)}
    # every fringe sample's noise in pixels, from its display position's through the starting pose; computed
    # once, so that every model is judged on the same weights (the F tests compare their sums of squares)
    cam0 = bundle.camera_vector(camera)
    starts["fringe_sigma"] = []
    for v, pose0 in zip(views, starts["views"]):
        def project_uv(q, pose0=pose0):
            return bundle.project(cam0, pose0.apply(_flat_points(q, width_m, height_m)))
        starts["fringe_sigma"].append(np.maximum(_uv_sigma_in_pixels(project_uv, v.fringe_uv, v.fringe_sigma_uv)
                                                 .ravel(), 1e-3) if len(v.fringe_uv) else np.zeros(0))
    if any(len(v.board_xy) for v in views):
        boards = []
        for v, p in zip(views, starts["views"]):
            if len(v.board_xy) >= 6:
                b = _pnp(np.column_stack([v.board_xy, np.zeros(len(v.board_xy))]), v.board_px, camera)
                boards.append((len(v.board_xy), p.inverse().compose(b)))
        if not boards:
            raise ValueError("the scale board was not seen well enough in any view (6 corners at least)")
        starts["board_to_screen"] = max(boards, key=lambda nb: nb[0])[1]
    richest = models[-1]
    blocks, groups = _screen_problem(views, camera, camera_std, richest, width_m, height_m, scale_u, starts)
    rich = bundle.solve(blocks, groups)
    fits = {richest: _model_fit(richest, rich, views, starts, width_m, height_m)}
    tests = {}
    chosen = richest
    rich_names = parameter_names(richest)
    shape_start = dict(zip(rich_names, rich.values["shape"]))
    for m in models[:-1]:
        st = _restart(starts, rich, shape_start, len(views))
        blocks, groups = _screen_problem(views, camera, camera_std, m, width_m, height_m, scale_u, st)
        judged = bundle.solve(blocks, groups, estimate_noise=False, outlier_sigmas=0.0, scales=rich.scales,
                              keep=rich.keep)
        extra = len(rich_names) - len(parameter_names(m))
        tests[m] = bundle.nested_model_test(judged.chi2, rich.chi2, extra, rich.dof, confidence)
        fits[m] = _model_fit(m, judged, views, starts, width_m, height_m)
    if force is not None:
        if force not in fits:
            raise ValueError(f"model {force!r} was not fitted; fit it with models=(..., {force!r}, ...)")
        chosen = force
    else:
        # the simplest model that leaves no significantly larger residual than the richest AND whose pitch
        # agrees with the richest's within two of the richest's standard uncertainties: a bow too small for
        # the F test at these views can still bias a flat model's pitch (by 0.15 % for a 0.2 mm bow on the
        # twin), and the pitch is what the record is for
        rich_pitch = rich.values["shape"][:2]
        rich_std = rich.std("shape")[:2]
        for m in models[:-1]:
            agree = np.abs(fits[m].solution.values["shape"][:2] - rich_pitch) < 2.0 * rich_std
            tests[m]["pitch_agrees"] = bool(np.all(agree))
            if not tests[m]["needed"] and tests[m]["pitch_agrees"]:
                chosen = m
                break
        for m in models[:-1]:
            tests[m].setdefault("pitch_agrees", None)
    if chosen != richest:
        # the chosen model's own noise estimate and covariance (its residuals are the richest's, within noise)
        st = _restart(starts, rich, shape_start, len(views))
        blocks, groups = _screen_problem(views, camera, camera_std, chosen, width_m, height_m, scale_u, st)
        sol = bundle.solve(blocks, groups, scales=rich.scales, keep=rich.keep, outlier_sigmas=0.0)
        fits[chosen] = _model_fit(chosen, sol, views, starts, width_m, height_m)
    return ScreenFit(fits, chosen, tests)


# -- a printed target's outer border: its size, to a thousandth of a pixel ------------------------
def target_border(image: np.ndarray, camera: CameraIntrinsics, target_to_camera: Pose, width_m: float,
                  height_m: float, border_m: float, half_width_px: int = 4, trim_px: int = 12):
    """Sub-pixel points of a printed target's outer border (its white margin against a darker background).

    The border is the rectangle ``[-border, width + border] x [-border, height + border]`` of the target
    frame. Along every image row (a side that runs down the image) or column (one that runs across) the
    contrast is summed across the edge: the covered fractions of the pixels give the edge's position to a
    hundredth of a pixel (exact for an area-sampled edge), and a few hundred of them give the border's size
    far better than the corners inside it: what the distance to a target 10 m away rests on.

    Parameters
    ----------
    image : (H, W) array
        A frame with the target lit (the room's light) and the background darker.
    camera : CameraIntrinsics
    target_to_camera : Pose
        The target's approximate pose (its corners' solvePnP): where to look.
    width_m, height_m : float
        The pattern's extent, target frame, metres.
    border_m : float
        The white margin's width, metres (at least half_width + 3 pixels in the image).

    Returns
    -------
    points_m : (N, 3) array
        Border points in the target frame (z = 0), one per row or column crossed.
    observed_px : (N, 2) array
        Where the border crosses that row or column in the image.
    normals : (N, 2) array
        The border's unit normal in the image there (the residual's direction).
    """
    img = np.asarray(image, dtype=np.float64)
    h_img, w_img = img.shape
    x0, y0, x1, y1 = -border_m, -border_m, width_m + border_m, height_m + border_m
    corners = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    cam = bundle.camera_vector(camera)
    centre_px = bundle.project(cam, target_to_camera.apply(np.array([[0.5 * width_m, 0.5 * height_m, 0.0]])))[0]
    pts, obs, nrm = [], [], []
    h = int(half_width_px)
    for a, b in zip(corners, np.roll(corners, -1, axis=0)):
        pa, pb = bundle.project(cam, target_to_camera.apply(np.stack([a, b])))
        d = pb - pa
        vertical = abs(d[1]) > abs(d[0])
        along = 1 if vertical else 0              # image axis the side runs along
        across = 1 - along
        lo, hi = sorted((pa[along], pb[along]))
        steps = np.arange(np.ceil(lo + trim_px), np.floor(hi - trim_px) + 1)
        if steps.size < 4:
            continue
        normal = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        inside = 1.0 if (centre_px[across] - (pa[across] + d[across] * (centre_px[along] - pa[along]) / d[along])) > 0 \
            else -1.0                               # the margin lies toward +across or -across
        for t in steps:
            frac = (t - pa[along]) / d[along]
            c0 = pa[across] + frac * d[across]
            lo_c, hi_c = int(np.floor(c0)) - h, int(np.floor(c0)) + h + 1
            across_n, along_n = (w_img, h_img) if vertical else (h_img, w_img)
            if lo_c - 4 < 0 or hi_c + 4 >= across_n or not 0 <= int(t) < along_n:
                continue
            line = img[int(t), :] if vertical else img[:, int(t)]
            if inside > 0:
                out_level = np.median(line[lo_c - 4:lo_c - 1])
                in_level = np.median(line[hi_c + 1:hi_c + 4])
            else:
                out_level = np.median(line[hi_c + 1:hi_c + 4])
                in_level = np.median(line[lo_c - 4:lo_c - 1])
            if in_level - out_level < 20.0:
                continue
            f = np.clip((line[lo_c:hi_c + 1] - out_level) / (in_level - out_level), -0.5, 1.5)
            covered = float(f.sum())
            # pixel c spans [c - 1/2, c + 1/2]: the inside's covered width ends at the window's far edge
            edge = (hi_c + 0.5 - covered) if inside > 0 else (lo_c - 0.5 + covered)
            q = np.empty(2)
            q[across], q[along] = edge, t
            pts.append(a + frac * (b - a))
            obs.append(q)
            nrm.append(normal)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 2))
    return np.array(pts), np.array(obs), np.array(nrm)


def _border_group(target_name: str, points: np.ndarray, observed: np.ndarray, normals: np.ndarray):
    """The target's border points projected, their offset from where the image shows the border, along
    its normal (the border's position along itself is not observed)."""

    def f(values, der):
        target, s, cam = values[target_name], values["scale"][0], values["camera"]
        pts = points * s
        if not der:
            pix = bundle.project(cam, target.apply(pts))
            return np.sum((pix - observed) * normals, axis=1)
        pix, d_pix, d_cam = bundle.project(cam, target.apply(pts), True)
        dn = np.einsum("ni,nij->nj", normals, d_pix)                 # d(residual)/d(camera point)
        jac = {target_name: np.einsum("nj,njk->nk", dn, bundle.pose_derivative(target, pts)),
               "scale": np.einsum("nj,jk,nk->n", dn, target.rotation, points)[:, None],
               "camera": np.einsum("ni,nij->nj", normals, d_cam)}
        return np.sum((pix - observed) * normals, axis=1), jac

    return f


CORNER_SIGMA = 0.1
KNOWN = ()


# -- the pose -------------------------------------------------------------------------------------
@dataclass
class MirrorPlacement:
    """What one placement of the reference mirror gives the station camera.

    Attributes
    ----------
    label : str
    target_px : (N, 2) array, target_xy : (N, 2) array
        The printed frame's corners: image positions and certified target-frame positions (metres).
    fringe_px, fringe_uv, fringe_sigma_uv : (K, 2) arrays
        Pixels that see the screen through the mirror: pixel positions, display positions, their noise.
    distance_m : float or None
        The range finder's distance from the screen centre to the target's measure point.
    border_points, border_px, border_normals : arrays, optional
        The printed frame's outer border (:func:`target_border`): target-frame points, where the image shows
        them, the border's normal there.
    """

    label: str
    target_px: np.ndarray
    target_xy: np.ndarray
    fringe_px: np.ndarray
    fringe_uv: np.ndarray
    fringe_sigma_uv: np.ndarray
    distance_m: float | None = None
    border_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    border_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    border_normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass
class PoseFit:
    """The camera's pose against the screen, and every placement's target pose.

    Attributes
    ----------
    screen_to_camera : Pose
    screen_covariance : (6, 6) array
        Of the screen's small motion (rotation vector, rad; translation, m) about and along its own axes
        through its centre.
    targets : list of Pose
        Every placement's ``target_to_camera``.
    target_covariances : list of (6, 6) arrays
        Their covariances (about and along the target's axes).
    pitch_scale : (float, float)
        The screen's pitch scale as refined with its prior (the screen calibration's).
    solution : bundle.Solution
    """

    screen_to_camera: Pose
    screen_covariance: np.ndarray
    targets: list
    target_covariances: list
    pitch_scale: tuple
    solution: bundle.Solution


def _mirror_group(target_name: str, px: np.ndarray, base: np.ndarray, rest: np.ndarray, pitch_design: np.ndarray):
    """Pixels that see display positions through the mirror: the screen point, reflected in the target's
    plane (its z = 0; normal its z axis), projected."""
    e_z = np.array([0.0, 0.0, 1.0])
    skew_z = bundle.skew(e_z)

    def f(values, der):
        screen, target, cam = values["screen"], values[target_name], values["camera"]
        pts_s = base + rest + pitch_design @ values["pitch"]
        x_c = screen.apply(pts_s)
        n = target.rotation[:, 2]
        o = target.translation
        q = x_c - o
        s = q @ n
        virtual = x_c - 2.0 * s[:, None] * n
        if not der:
            return (bundle.project(cam, virtual) - px).ravel()
        pix, d_pix, d_cam = bundle.project(cam, virtual, True)
        mirror = np.eye(3) - 2.0 * np.outer(n, n)
        d_screen = np.einsum("ij,njk->nik", mirror, bundle.pose_derivative(screen, pts_s))
        d_pitch = np.einsum("ij,jk,nkl->nil", mirror, screen.rotation, pitch_design)
        # dV/dn = -2 (s I + n q^T); dn/d(omega) = -R skew(e_z); dV/do = 2 n n^T; do/d(tau) = R
        dv_dn = -2.0 * (s[:, None, None] * np.eye(3) + n[None, :, None] * q[:, None, :])
        d_target = np.empty((len(px), 3, 6))
        d_target[:, :, :3] = dv_dn @ (-target.rotation @ skew_z)
        d_target[:, :, 3:] = 2.0 * np.outer(n, n) @ target.rotation
        jac = {"screen": np.einsum("nij,njk->nik", d_pix, d_screen).reshape(-1, 6),
               "pitch": np.einsum("nij,njk->nik", d_pix, d_pitch).reshape(-1, 2),
               target_name: np.einsum("nij,njk->nik", d_pix, d_target).reshape(-1, 6),
               "camera": d_cam.reshape(-1, 9)}
        return (pix - px).ravel(), jac

    return f


def _distance_group(target_name: str, point: np.ndarray, distance_m: float):
    """The range finder: distance from the screen centre (its frame's origin) to the target's point."""

    def f(values, der):
        screen, target, s = values["screen"], values[target_name], values["scale"][0]
        w = screen.translation - target.apply(point * s)
        dist = float(np.linalg.norm(w))
        r = np.array([dist - distance_m])
        if not der:
            return r
        e = w / dist
        d_screen = np.zeros((1, 6))
        d_screen[0, 3:] = e @ screen.rotation
        d_target = np.zeros((1, 6))
        d_target[0, :3] = -e @ (-target.rotation @ bundle.skew(point * s))
        d_target[0, 3:] = -e @ target.rotation
        return r, {"screen": d_screen, target_name: d_target,
                   "scale": np.array([[-e @ (target.rotation @ point)]])}

    return f


def _assembly_group(designed: Pose):
    """The designed assembly as a prior on the screen's pose: its small motion from the designed one."""

    def f(values, der):
        r = bundle.motion_between(designed, values["screen"])
        return (r, {"screen": np.eye(6)}) if der else r

    return f


def fit_pose(placements: list[MirrorPlacement], camera: CameraIntrinsics, shape: ScreenShape,
             screen_to_camera0: Pose, *, pitch_std=(0.0, 0.0), camera_std=None, scale_u: float = 5e-5,
             measure_point_xy=None, distance_std_m: float = 5e-4, assembly_std=None) -> PoseFit:
    """Fit the screen's pose in the camera frame to mirror placements (module docstring).

    Parameters
    ----------
    placements : list of MirrorPlacement
    camera : CameraIntrinsics
        The station camera.
    shape : ScreenShape
        The screen's shape (the screen calibration's; a flat one of the stated pitch without it). Its
        pitch terms are refined with the prior *pitch_std*; the rest is held.
    screen_to_camera0 : Pose
        Where to start (the designed assembly).
    pitch_std : (float, float)
        Standard deviations of the shape's a_x, a_y (0: held).
    camera_std : (9,) array, optional
        The station camera's parameters' standard deviations (priors); None holds them.
    scale_u : float
        The target's relative scale uncertainty (its certificate).
    measure_point_xy : (2,) array, optional
        The range finder's point on the target, target frame (metres); needed with distances.
    distance_std_m : float
        The range finder's standard uncertainty, metres: the distances' noise (too few readings to
        estimate it from their residuals).
    assembly_std : (6,) array, optional
        How well the station is assembled to its drawing (*screen_to_camera0*): standard deviations of the
        screen's rotations (rad) and shifts (m) about and along its axes. A prior: the mirror sees the
        screen from about twice the facet's distance, through a plane whose tilt its printed frame gives
        only to milliradians, so one combination (the screen turned about the camera's mirror image and the
        mirror with it) is hardly seen; the drawing holds it. None: no prior.
    """
    if not placements:
        raise ValueError("no placements")
    cam0 = bundle.camera_vector(camera)
    cam_std = _camera_std(camera, camera_std)
    pitch_std = np.asarray(pitch_std, dtype=np.float64)
    blocks = [bundle.Block("screen", screen_to_camera0,
                           names=[f"screen {n}" for n in ("rx", "ry", "rz", "tx", "ty", "tz")]),
              bundle.Block("camera", cam0, prior=cam0, prior_std=cam_std, fixed=cam_std is None,
                           names=list(CAMERA_NAMES)),
              bundle.Block("pitch", shape.params[:2], prior=shape.params[:2], prior_std=pitch_std,
                           fixed=not np.any(pitch_std > 0), names=["a_x", "a_y"]),
              bundle.Block("scale", [1.0], prior=[1.0], prior_std=[scale_u], names=["target scale"])]
    groups = []
    for k, pl in enumerate(placements):
        if len(pl.target_xy) < 6:
            raise ValueError(f"placement {pl.label}: too few target corners ({len(pl.target_xy)}) to place it")
        xy = np.column_stack([pl.target_xy, np.zeros(len(pl.target_xy))])
        name = f"target {k}"
        blocks.append(bundle.Block(name, _pnp(xy, pl.target_px, camera),
                                   names=[f"{pl.label} {n}" for n in ("rx", "ry", "rz", "tx", "ty", "tz")]))

        def on_target(values, der, xy=xy):
            s = values["scale"][0]
            return (xy * s, {"scale": xy[:, :, None]}) if der else xy * s

        groups.append(bundle.Group("target corners", [name, "scale", "camera"],
                                   _points_group(name, pl.target_px, on_target, ["scale"]), CORNER_SIGMA,
                                   f"{pl.label} target"))
        if len(pl.border_points):
            groups.append(bundle.Group("target border", [name, "scale", "camera"],
                                       _border_group(name, pl.border_points, pl.border_px, pl.border_normals), 0.02,
                                       f"{pl.label} border"))
        if len(pl.fringe_px):
            base, design = shape.basis(pl.fringe_uv[:, 0], pl.fringe_uv[:, 1])
            rest = design[:, :, 2:] @ shape.params[2:]
            t0 = blocks[-1].x0

            def project_uv(q, t0=t0):
                pts = screen_to_camera0.apply(shape.points(q[:, 0], q[:, 1]))
                return bundle.project(cam0, bundle.reflect(pts, t0.translation, t0.rotation[:, 2]))

            sigma = np.maximum(_uv_sigma_in_pixels(project_uv, pl.fringe_uv, pl.fringe_sigma_uv).ravel(), 1e-4)
            groups.append(bundle.Group("fringes", ["screen", name, "pitch", "camera"],
                                       _mirror_group(name, pl.fringe_px, base, rest, design[:, :, :2]), sigma,
                                       f"{pl.label} fringes"))
        if pl.distance_m is not None:
            if measure_point_xy is None:
                raise ValueError("a range finder distance needs the target's measure point")
            mp = np.array([measure_point_xy[0], measure_point_xy[1], 0.0])
            groups.append(bundle.Group("distance", ["screen", name, "scale"], _distance_group(name, mp, pl.distance_m),
                                       distance_std_m, f"{pl.label} distance"))
    if assembly_std is not None:
        groups.append(bundle.Group("assembly", ["screen"], _assembly_group(screen_to_camera0),
                                   np.asarray(assembly_std, dtype=np.float64), "designed assembly"))
    # the range finder's noise is its stated accuracy and the assembly's its tolerance: a few values cannot
    # estimate them
    sol = bundle.solve(blocks, groups, known_noise=("distance", "assembly") + KNOWN)
    pitch = sol.values["pitch"]
    return PoseFit(sol.values["screen"], sol.covariance["screen"],
                   [sol.values[f"target {k}"] for k in range(len(placements))],
                   [sol.covariance[f"target {k}"] for k in range(len(placements))],
                   (1.0 + float(pitch[0]), 1.0 + float(pitch[1])), sol)


def motion_jacobian(pose: Pose, to_other) -> tuple[Pose, np.ndarray]:
    """``other = to_other(pose)`` and the (6, 6) derivative of *other*'s small motion (about and along its own
    axes) with respect to *pose*'s (finite differences of the map, first order)."""
    other0 = to_other(pose)
    jac = np.zeros((6, 6))
    step = 1e-7
    for i in range(6):
        d = np.zeros(6)
        d[i] = step
        jac[:, i] = (bundle.motion_between(other0, to_other(bundle.moved(pose, d)))
                     - bundle.motion_between(other0, to_other(bundle.moved(pose, -d)))) / (2 * step)
    return other0, jac

