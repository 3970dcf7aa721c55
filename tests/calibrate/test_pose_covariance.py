"""The pose record's joint covariance of the screen's and the fixture's poses against the scatter of repeated
pose calibrations (issue 47 item 4).

The pose calibration finds the fixture through the reference mirror seated in it, seen through the screen pose
the same fit finds: their errors are correlated, and they largely cancel in what a facet at the same place
reports in the fixture (its optical tilt). Taken as independent rows, the record's twelve standard
uncertainties put the optical tilt's U at about ten times its errors' spread after commissioning
(docs/uncertainty.md#after-commissioning). Here: synthetic placements of the mirror (the target's corners and
the fringe pixels projected exactly from a known truth, then noise drawn), fitted by the calibration's own
least squares (:func:`fit_pose`), :data:`RUNS` times; the tilt a flat facet seated in the fixture would show,
computed from the fitted screen and fixture poses by reflection, independently of the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from sofast_station.calibrate.commission_settings import load_mirror_target
from sofast_station.calibrate.pose import (JOINT_PARAMETERS, joint_covariance_mrad_mm, joint_pose_covariance,
                                          target_layout)
from sofast_station.config import load_config
from sofast_station.geometry import Pose
from sofast_station.layout import mirror_seat
from sofast_station.measure import bundle
from sofast_station.measure.commission import MirrorPlacement, fit_pose
from sofast_station.measure.screen_shape import ScreenShape
from tests.conftest import ROOT, SMALL_STATION

#: Repeated calibrations (each about 0.5 s of CPU).
RUNS = 16
#: Noise drawn: the target's corners (px), the display positions the fringes give (m), the range finder (m).
CORNER_NOISE_PX, UV_NOISE_M, DISTANCE_NOISE_M = 0.07, 5e-5, 5e-4
SHIM_TILT_RAD = 0.003


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    path = tmp_path_factory.mktemp("pose") / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=path.parent / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    cfg = load_config(path)
    target = load_mirror_target(ROOT / "fixtures/targets/reference_mirror.toml")
    return cfg, target


def _placements(cfg, target, screen: Pose, fixture: Pose, seat_error: np.ndarray, rng) -> list[MirrorPlacement]:
    """The seated mirror (its seat moved by *seat_error*, rad and m) and four tilted by a shim: the corners and
    the fringe pixels inside the mirror's window, projected from the truth, with noise."""
    cam = bundle.camera_vector(cfg.geometry.camera)
    width, height = cfg.geometry.screen.width_m, cfg.geometry.screen.height_m
    shape = ScreenShape("flat", width, height)
    seat = mirror_seat(cfg.design, target.window_centre_m)
    xy = target_layout(target).corners()
    x0, y0, x1, y1 = target.window_m
    u, v = np.meshgrid(np.linspace(0.02, width - 0.02, 36), np.linspace(0.02, height - 0.02, 24))
    uv = np.column_stack([u.ravel(), v.ravel()])
    screen_points = screen.apply(shape.points(uv[:, 0], uv[:, 1]))
    out = []
    for k in range(5):
        tilt = np.zeros(3)
        if k:
            axis, sign = [(1, -1.0), (0, 1.0), (1, 1.0), (0, -1.0)][k - 1]
            tilt[axis] = sign * SHIM_TILT_RAD
        c = target.window_centre_m
        r = bundle.rotation_from_vector(tilt)
        placed = seat.compose(Pose(r, c - r @ c))
        if k == 0:
            placed = placed.compose(Pose(bundle.rotation_from_vector(seat_error[:3]), seat_error[3:]))
        t2c = fixture.compose(placed)
        corners = bundle.project(cam, t2c.apply(np.column_stack([xy, np.zeros(len(xy))])))
        virtual = bundle.reflect(screen_points, t2c.translation, t2c.rotation[:, 2])
        px = bundle.project(cam, virtual)
        # where the ray to the virtual point crosses the mirror's plane, target frame: inside its clear window
        n, o = t2c.rotation[:, 2], t2c.translation
        hit = virtual * ((o @ n) / (virtual @ n))[:, None]
        local = (hit - o) @ t2c.rotation
        inside = (local[:, 0] > x0) & (local[:, 0] < x1) & (local[:, 1] > y0) & (local[:, 1] < y1)
        measure = np.array([*target.measure_point, 0.0])
        distance = np.linalg.norm(screen.translation - t2c.apply(measure[None])[0])
        out.append(MirrorPlacement(
            f"placement {k + 1}", corners + rng.normal(0.0, CORNER_NOISE_PX, corners.shape), xy, px[inside],
            uv[inside] + rng.normal(0.0, UV_NOISE_M, (int(inside.sum()), 2)),
            np.full((int(inside.sum()), 2), UV_NOISE_M), float(distance + rng.normal(0.0, DISTANCE_NOISE_M))))
    return out


def _facet_tilt_mrad(cfg, target, screen: Pose, fixture: Pose, true_screen: Pose, true_fixture: Pose) -> np.ndarray:
    """The tilt (about the fixture's x and y, mrad) a flat facet seated exactly in the true fixture shows when
    measured with *screen* and *fixture*: the pixel that sees its middle sees the display position the true
    screen puts on the reflected ray; the station takes that display position where *screen* puts it, the
    normal as the bisector of the two rays there, in *fixture*'s frame; less the truth's."""
    seat = true_fixture.compose(mirror_seat(cfg.design, target.window_centre_m))
    h, n_true = seat.apply(target.window_centre_m[None])[0], -seat.rotation[:, 2]
    d = h / np.linalg.norm(h)
    out = d - 2.0 * (d @ n_true) * n_true
    # the true screen's plane (flat: the screen frame's z = 0) along the reflected ray
    s = ((true_screen.translation - h) @ true_screen.rotation[:, 2]) / (out @ true_screen.rotation[:, 2])
    local = true_screen.inverse().apply((h + s * out)[None])[0]
    seen = screen.apply(local[None])[0]
    n_est = -d + (seen - h) / np.linalg.norm(seen - h)
    n_est /= np.linalg.norm(n_est)
    est, true = fixture.rotation.T @ n_est, true_fixture.rotation.T @ n_true
    return 1e3 * (est[:2] / est[2] - true[:2] / true[2])


def test_joint_covariance_predicts_the_scatter_of_the_seated_facets_tilt(rig):
    """Over RUNS calibrations with drawn noise and seating, the facet's tilt errors (computed by reflection
    from the fitted poses, not by the budget) against the spread the record's joint covariance predicts
    (first order, its gradient by central differences): their sum of squares over that variance is chi-square
    with RUNS degrees of freedom for a right covariance, so RMS(error / predicted sd) lies in
    sqrt(chi2(RUNS) / RUNS) at 0.999 two-sided, 0.47-1.61 for 16 runs, per axis; and taken as independent
    rows (the record's standard uncertainties alone, as the budget did until 2026-12-06) the predicted spread is
    at least twice the scatter (measured: 5-10 times), which that band would refuse."""
    cfg, target = rig
    rng = np.random.default_rng(47)
    stated_screen, true_fixture = cfg.geometry.screen_to_camera, cfg.geometry.fixture_to_camera
    true_screen = bundle.moved(stated_screen, np.array([1e-3, -1.5e-3, 5e-4, 3e-3, -2e-3, 2.5e-3]))
    shape = ScreenShape("flat", cfg.geometry.screen.width_m, cfg.geometry.screen.height_m)
    seat = mirror_seat(cfg.design, target.window_centre_m)
    seating = np.diag([(1e-3 * target.seating_u_mrad) ** 2] * 3 + [(1e-3 * target.seating_u_mm) ** 2] * 3)
    errors, joint_sd, independent_sd = [], [], []
    for _ in range(RUNS):
        seat_error = np.sqrt(np.diag(seating)) * rng.standard_normal(6)
        placements = _placements(cfg, target, true_screen, true_fixture, seat_error, rng)
        fit = fit_pose(placements, cfg.geometry.camera, shape, stated_screen, scale_u=target.scale_u_relative,
                       measure_point_xy=target.measure_point, distance_std_m=DISTANCE_NOISE_M,
                       assembly_std=[3e-3] * 3 + [5e-3] * 3)
        fixture, cov = joint_pose_covariance(fit, seat, seating)
        screen = fit.screen_to_camera
        errors.append(_facet_tilt_mrad(cfg, target, screen, fixture, true_screen, true_fixture))
        # the tilt's gradient in the twelve small motions of the record's poses (rad, m)
        grad = np.zeros((2, 12))
        for i in range(12):
            step = np.zeros(12)
            step[i] = 1e-6
            tilt = [_facet_tilt_mrad(cfg, target, bundle.moved(screen, s * step[:6]),
                                     bundle.moved(fixture, s * step[6:]), true_screen, true_fixture)
                    for s in (1.0, -1.0)]
            grad[:, i] = (tilt[0] - tilt[1]) / 2e-6
        joint_sd.append(np.sqrt(np.diag(grad @ cov @ grad.T)))
        independent_sd.append(np.sqrt(np.diag(grad @ np.diag(np.diag(cov)) @ grad.T)))
    errors, joint_sd, independent_sd = (np.array(v) for v in (errors, joint_sd, independent_sd))
    lo, hi = (np.sqrt(chi2.ppf(q, RUNS) / RUNS) for q in (0.0005, 0.9995))
    z_joint = np.sqrt(np.mean((errors / joint_sd) ** 2, axis=0))
    z_independent = np.sqrt(np.mean((errors / independent_sd) ** 2, axis=0))
    print(f"RMS of error / sd: joint {z_joint}, independent {z_independent}; band {lo:.2f}-{hi:.2f}")
    assert np.all((lo <= z_joint) & (z_joint <= hi)), (z_joint, lo, hi, errors.std(axis=0), joint_sd.mean(axis=0))
    assert np.all(z_independent < 0.5 * lo), (z_independent, independent_sd.mean(axis=0))


def test_the_record_states_the_joint_covariance_and_older_records_load(rig):
    """The record's field in the budget's units (mrad, mm) is the matrix itself scaled by 1e3 on both sides,
    its diagonal the stated standard uncertainties squared; a record without it (made before) gives None (the
    budget then keeps independent rows); a garbled one is refused with the field named."""
    cov = np.diag(np.arange(1.0, 13.0) * 1e-8)
    cov[0, 6] = cov[6, 0] = 0.9 * np.sqrt(cov[0, 0] * cov[6, 6])
    record = {"joint_covariance": {"parameters": list(JOINT_PARAMETERS), "units": "rad, m", "matrix": cov.tolist()}}
    np.testing.assert_allclose(joint_covariance_mrad_mm(record), 1e6 * cov)
    assert joint_covariance_mrad_mm({}) is None
    record["joint_covariance"]["matrix"][0][6] = 1.0              # no longer symmetric
    with pytest.raises(ValueError, match="joint_covariance.matrix"):
        joint_covariance_mrad_mm(record)
