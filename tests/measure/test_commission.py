"""The commissioning fits on synthetic observations made by their forward model: the shape model the residuals
ask for is chosen, its parameters are recovered within their stated uncertainty; a printed border is located
to a few thousandths of a pixel.

(The end-to-end check, on frames the twin renders from its own truth, is tests/calibrate/test_commission.py.)"""

from __future__ import annotations

import math

import numpy as np

from sofast_station.geometry import CameraIntrinsics, Pose
from sofast_station.measure import bundle
from sofast_station.measure.commission import ScreenView, fit_screen, target_border
from sofast_station.measure.screen_shape import ScreenShape, parameter_names

W, H = 0.528, 0.297
CAM = CameraIntrinsics(640, 480, [[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]], [0.02, -0.05, 0, 0, 0])
BOARD_TO_SCREEN = Pose(np.diag([1.0, -1.0, -1.0]), np.array([0.30, 0.1, 0.004]))


def _looking_at(centre, target=(0.13, 0.0, 0.0)) -> Pose:
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    z = (target - centre) / np.linalg.norm(target - centre)
    y = -(np.array([0, 1.0, 0]) - z[1] * z)
    y /= np.linalg.norm(y)
    rot = np.vstack([np.cross(y, z), y, z])
    return Pose(rot, -rot @ centre)


def _views(shape: ScreenShape, rng, n=6, corner_noise=0.07, uv_noise=1e-4):
    """Views of *shape* from around it (25 degrees off its normal, 0.9 m away): fiducial corners on a grid,
    fringe samples anywhere, the scale board's corners; all projected through the true poses, with noise."""
    cam = bundle.camera_vector(CAM)
    board_xy = np.array([[i * 0.04, j * 0.04] for i in range(1, 7) for j in range(1, 5)])
    views, poses = [], []
    for k in range(n):
        az = 2 * math.pi * k / n
        tilt = math.radians(25)
        pose = _looking_at(np.array([0.13, 0, 0]) + 0.9 * np.array([math.sin(tilt) * math.cos(az),
                                                                    math.sin(tilt) * math.sin(az), math.cos(tilt)]))
        gu, gv = np.meshgrid(np.linspace(0.04, W - 0.04, 11), np.linspace(0.03, H - 0.03, 6))
        c_uv = np.column_stack([gu.ravel(), gv.ravel()])
        c_px = bundle.project(cam, pose.apply(shape.points(c_uv[:, 0], c_uv[:, 1])))
        f_uv = rng.uniform([0.01, 0.01], [W - 0.01, H - 0.01], (400, 2))
        f_px = bundle.project(cam, pose.apply(shape.points(f_uv[:, 0], f_uv[:, 1])))
        b_px = bundle.project(cam, pose.apply(BOARD_TO_SCREEN.apply(np.column_stack([board_xy, np.zeros(24)]))))
        views.append(ScreenView(f"view {k}", c_px + rng.normal(0, corner_noise, c_px.shape), c_uv,
                                b_px + rng.normal(0, corner_noise, b_px.shape), board_xy, f_px,
                                f_uv + rng.normal(0, uv_noise, f_uv.shape), np.full((400, 2), uv_noise)))
        poses.append(pose)
    return views, poses


def test_a_bowed_screen_of_another_pitch_is_recovered_and_the_3d_model_chosen():
    """A screen 0.8 % larger than stated, bowed (0.6 mm) and twisted: the F tests ask for the 3-D model, and
    its pitch, bow and twist come out within 4 of their stated standard uncertainties."""
    rng = np.random.default_rng(5)
    names = parameter_names("distorted3d")
    p = np.zeros(len(names))
    p[0], p[1] = 0.008, 0.008
    p[names.index("z:2,0")], p[names.index("z:0,2")] = -6e-4, -6e-4
    p[names.index("z:2,2")] = 6e-4
    p[names.index("z:1,1")] = 2.5e-4
    truth = ScreenShape("distorted3d", W, H, p)
    views, _ = _views(truth, rng)
    fit = fit_screen(views, CAM, W, H)
    print(f"\ntests: {fit.tests}")
    assert fit.chosen == "distorted3d"
    best = fit.best
    std = best.solution.std("shape")
    err = (best.shape.params - p) / std
    for name in ("a_x", "a_y", "z:2,0", "z:0,2", "z:1,1", "z:2,2"):
        i = names.index(name)
        print(f"{name}: {best.shape.params[i]:+.6f} +- {std[i]:.6f} (true {p[i]:+.6f})")
        assert abs(err[i]) < 4, name


def test_a_flat_screen_is_fitted_flat():
    """A flat screen of the stated pitch: the richer models earn nothing (F below its 99 % value), the flat
    one is kept and its pitch is 1 within its uncertainty."""
    rng = np.random.default_rng(6)
    views, _ = _views(ScreenShape("flat", W, H), rng)
    fit = fit_screen(views, CAM, W, H)
    print(f"\ntests: {fit.tests}")
    assert fit.chosen == "flat"
    std = fit.best.solution.std("shape")
    assert abs(fit.best.shape.params[0]) < 4 * std[0] and abs(fit.best.shape.params[1]) < 4 * std[1]


def test_the_model_can_be_forced():
    rng = np.random.default_rng(7)
    views, _ = _views(ScreenShape("flat", W, H), rng)
    assert fit_screen(views, CAM, W, H, force="distorted2d").chosen == "distorted2d"


def _border_image(camera: CameraIntrinsics, pose: Pose, rect, rng, sub=6, inside=150.0, outside=10.0):
    """The target's white margin against the dark room, each pixel the mean of sub x sub jittered samples
    (an area-integrating sensor to 1/sub^2 of a pixel, with errors that do not line up along an edge)."""
    from sofast_station.measure.camera import pixel_rays

    h, w = camera.shape
    x0, y0, x1, y1 = rect
    out = np.empty((h, w))
    to_target = pose.inverse()
    for r in range(h):
        cols = np.repeat(np.arange(w), sub * sub).astype(float) + rng.uniform(-0.5, 0.5, w * sub * sub)
        rows = np.full(cols.size, float(r)) + rng.uniform(-0.5, 0.5, cols.size)
        rays = pixel_rays(camera, cols, rows).T
        o = to_target.translation
        d = rays @ to_target.rotation.T
        t = -o[2] / d[:, 2]
        px, py = o[0] + t * d[:, 0], o[1] + t * d[:, 1]
        inside_rect = (px >= x0) & (px < x1) & (py >= y0) & (py < y1)
        out[r] = np.where(inside_rect, inside, outside).reshape(w, -1).mean(axis=1)
    return out + rng.normal(0, 1.0, out.shape)


def test_a_printed_border_is_located_to_thousandths_of_a_pixel():
    """The border of a 1.08 x 0.78 m target 10.66 m away (quarter-resolution camera, 1 DN of noise): its
    points' offsets from the true border, per side, average under 0.01 px (about 230-320 points each,
    0.05 px apiece, so the means scatter by 0.003 px): what puts the target's distance to a few hundredths
    of a millimetre per side (its ChArUco corners, good to 0.07 px, to a millimetre)."""
    rng = np.random.default_rng(8)
    cam = CameraIntrinsics(400, 300, [[3409, 0, 199.5], [0, 3409, 149.5], [0, 0, 1]], [-0.05, 0.1, 0, 0, 0])
    pose = Pose(bundle.rotation_from_vector([math.pi + 0.004, 0.003, 0.01]), np.array([-0.5, 0.35, 10.66]))
    border = 0.04
    rect = (-border, -border, 1.0 + border, 0.7 + border)
    image = _border_image(cam, pose, rect, rng)
    rough = bundle.moved(pose, [2e-3, -2e-3, 1e-3, 3e-3, -3e-3, 5e-3])     # solvePnP of the corners' quality
    pts, obs, nrm = target_border(image, cam, rough, 1.0, 0.7, border)
    r = np.sum((bundle.project(bundle.camera_vector(cam), pose.apply(pts)) - obs) * nrm, axis=1)
    sides = np.round(nrm, 1)
    groups = {tuple(s): r[np.all(sides == s, axis=1)] for s in np.unique(sides, axis=0)}
    print({k: (v.size, round(float(v.mean()), 4), round(float(v.std()), 3)) for k, v in groups.items()})
    assert len(groups) == 4 and all(v.size > 150 for v in groups.values())
    assert all(abs(v.mean()) < 0.01 for v in groups.values())
    assert np.std(r) < 0.1
