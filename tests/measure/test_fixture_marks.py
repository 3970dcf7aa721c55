"""The fixture marks' math (measure/fixture_marks.py): marks located against the twin's truth, the similarity of
their motion, and what a small motion adds to the U's it reaches."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sofast_station.geometry import CameraIntrinsics, FixtureMarks, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.facet import load_facet
from sofast_station.measure.fixture_marks import (apparent_turn_rad, implied_pose_u, locate_marks, mark_motion,
                                                  widen_for_pose)

MARKS = FixtureMarks(np.array([[x, y, 0.0] for x in (-0.45, 0.0, 0.45) for y in (-0.38, 0.38)]
                              + [[-0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]), 0.02)


def _similarity(p: np.ndarray, shift, roll, scale) -> np.ndarray:
    centred = p - p.mean(axis=0)
    rot = np.array([[scale, -roll], [roll, scale]])
    return p + np.asarray(shift) + centred @ rot.T


def test_the_motion_of_known_displacements_is_recovered():
    """Displacements made from a known shift, roll and scale are fitted back exactly (to rounding) with no
    residual; with noise of sigma per coordinate over 200 draws, the fitted shift scatters by sigma / sqrt(N)
    as the fit says (shift_sigma_px from its residuals): the spread of the draws within 20 % of sigma / sqrt(N)
    (the standard error of a standard deviation from 400 numbers is 3.5 %) and the median stated sigma within
    15 % of it (each from 2N - 4 = 12 degrees of freedom)."""
    rng = np.random.default_rng(3)
    ref = rng.uniform([50, 40], [350, 260], (8, 2))
    now = _similarity(ref, (0.7, -0.3), 2e-4, -5e-5)
    m = mark_motion(now, ref)
    assert np.allclose(m.shift_px, [0.7, -0.3], atol=1e-10)
    assert m.roll_rad == pytest.approx(2e-4, abs=1e-12) and m.scale == pytest.approx(-5e-5, abs=1e-12)
    assert m.residual_rms_px < 1e-10
    sigma = 0.02
    shifts, stated = [], []
    for _ in range(200):
        fit = mark_motion(now + rng.normal(0.0, sigma, now.shape), ref)
        shifts.append(fit.shift_px - [0.7, -0.3])
        stated.append(fit.shift_sigma_px)
    want = sigma / math.sqrt(len(ref))
    assert np.std(shifts) == pytest.approx(want, rel=0.2)
    assert np.median(stated) == pytest.approx(want, rel=0.15)


def test_too_few_marks_cannot_say_how_they_moved():
    ref = np.array([[10.0, 10.0], [100.0, 10.0], [50.0, 80.0]])
    now = ref.copy()
    now[1:] = np.nan
    with pytest.raises(ValueError, match="at least 3"):
        mark_motion(now, ref)


def test_an_apparent_turn_is_the_fixture_pose_it_leaves_unknown():
    """The camera's apparent turn w (camera axes) is a rotation R^T w of the fixture's frame and a slide of the
    turn times the distance across the line of sight: with the fixture's axes those of the camera turned by a
    half-turn about x (the fixture faces the camera), 0.1 mrad about the camera's y is 0.1 mrad about the
    fixture's y and 1 mm (at 10 m) along its x."""
    motion = mark_motion(np.array([[1.3409, 0.0], [101.3409, 0.0], [0.0 + 1.3409, 100.0]]),
                         np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]]))
    turn = apparent_turn_rad(motion, (13409.0, 13409.0))
    assert turn == pytest.approx([0.0, 1e-4, 0.0], abs=1e-12)
    half_turn_x = np.diag([1.0, -1.0, -1.0])
    u = implied_pose_u(turn, half_turn_x, 10.0)
    assert u["rotation_mrad"] == pytest.approx([0.0, 0.1, 0.0], abs=1e-12)
    assert u["translation_mm"] == pytest.approx([1.0, 0.0, 0.0], abs=1e-9)


def test_a_small_motion_widens_the_placement_and_the_optical_tilt_in_quadrature():
    """The fixture pose a small shift leaves unknown is a budget row of its own: each reached figure's combined
    standard uncertainty and its U (k = 2) grow in quadrature by it; figures it does not reach are untouched."""
    names = ["focal_length_x_m", "optical_tilt_mrad.x", "optical_tilt_mrad.y", "placement.mm.0", "placement.mrad.1"]
    figures = {"placement_U": {"mm": [0.6, 0.6, 0.3], "mrad": [30.0, 40.0, 2.0]},
               "optical_tilt_mrad_U": {"x": 1.0, "y": None}, "focal_length_x_m_U": 0.001,
               "uncertainty_budget": {"figures": names, "rows": [],
                                      "combined_standard": [0.0005, 0.5, None, 0.3, 20.0]}}
    added = widen_for_pose(figures, {"rotation_mrad": [0.05, 0.02, 0.0], "translation_mm": [0.4, 0.0, 0.0]})
    assert figures["optical_tilt_mrad_U"]["x"] == pytest.approx(math.hypot(1.0, 0.1))
    assert figures["optical_tilt_mrad_U"]["y"] is None                      # no U: nothing to widen
    assert figures["placement_U"]["mrad"][1] == pytest.approx(math.hypot(40.0, 0.04))
    assert figures["placement_U"]["mm"][0] == pytest.approx(math.hypot(0.6, 0.8))
    assert figures["focal_length_x_m_U"] == 0.001                            # the fixture pose does not reach f
    assert added["optical_tilt_mrad.x"] == pytest.approx(0.1) and "optical_tilt_mrad.y" not in added
    budget = figures["uncertainty_budget"]
    row = budget["rows"][-1]
    assert row["group"] == "fixture marks: camera shift"
    assert row["contributions"] == [0.0, 0.05, 0.02, 0.4, 0.02]
    combined = budget["combined_standard"]
    assert combined[2] is None                                  # a figure without a stated one stays so
    assert [combined[i] for i in (0, 1, 3, 4)] == pytest.approx([0.0005, math.hypot(0.5, 0.05), 0.5, 20.0], rel=1e-3)


@pytest.fixture(scope="module")
def small_twin(repo_root):
    from sofast_station.twin.parameters import TwinOptics
    from sofast_station.twin.station import TwinStation

    design = load_facet(repo_root / "fixtures/facets/dish_5m33.toml")
    camera = CameraIntrinsics(400, 300, [[3409.0, 0, 199.5], [0, 3409.0, 149.5], [0, 0, 1]],
                              [-0.2, 0.1, 0.0002, -0.0001, 0.0])
    geo = layout_station(design, camera, ScreenSpec(1920, 1080, 0.000275), 0.34, "x", (0.0, 0.0))
    return TwinStation(geo, design, optics=TwinOptics(read_noise_dn=5.0, electrons_per_dn=10.0), marks=MARKS)


def test_marks_are_located_against_the_twins_truth(small_twin):
    """On the quarter-resolution twin (marks of 6.4 px through a lens with k1 = -0.2), noise-free, each mark is
    found within 0.01 px of where the twin draws its centre (the image of a disc's centre is not its image's
    centroid by a few thousandths of a pixel: distortion, perspective, the edge pixels' sampling), the search
    started on its place (the fast path) or 3 px off (the slow one).

    With the population's worst noise (read noise 5 DN, shot noise at 10 e-/DN: about 6 DN on a mark of 117 DN)
    the centroid over its disc of 1.5 radii and a pixel (106 px, their spread of 30 px about the centre) scatters
    by 6 x 30 / (32 px x 117 DN) = 0.05 px per coordinate: over 10 frames every mark within 0.25 px (5 sigma),
    and their mean error within 0.1 px of the truth."""
    from sofast_station.twin.marks import mark_image_centres_px

    twin = small_twin
    truth = mark_image_centres_px(MARKS, twin.geometry.fixture_to_camera, twin.trace.camera)
    scr = twin.geometry.screen
    white = np.full((scr.height_px, scr.width_px), 255, np.uint8)
    rng = np.random.default_rng(11)
    clean = twin.with_optics(twin.optics.noise_free()).capture(white)
    for start in (truth, truth + rng.normal(0.0, 3.0, truth.shape)):
        loc = locate_marks(clean, start, 3.2, 7.0)
        assert loc.found.all()
        assert np.max(np.hypot(*(loc.centres_px - truth).T)) < 0.01
    errors = []
    for k in range(10):
        start = truth + (rng.normal(0.0, 3.0, truth.shape) if k % 2 else 0.0)
        loc = locate_marks(twin.capture(white, rng), start, 3.2, 7.0)
        assert loc.found.all()
        errors.append(loc.centres_px - truth)
    errors = np.array(errors)
    assert np.max(np.abs(errors)) < 0.25
    assert np.max(np.abs(errors.mean(axis=0))) < 0.1


def test_a_bright_facet_in_the_window_is_not_taken_for_a_mark():
    """A window that holds the facet's bright image (larger than the window, touching its border) and the mark
    finds the mark; a window with no mark (or one too faint) finds nothing."""
    img = np.full((120, 160), 10, np.uint8)
    img[:, :60] = 230                                      # the facet's image, beside the mark
    rows, cols = np.mgrid[0:120, 0:160]
    disc = np.hypot(cols - 80.3, rows - 60.6) < 4.0
    img[disc] = 140
    loc = locate_marks(img, np.array([[75.0, 64.0], [130.0, 20.0]]), 4.0, 20.0)
    assert loc.found.tolist() == [True, False]
    # the drawn disc's own centroid: the mean of its pixels' centres (a uniform disc on a flat background)
    assert np.hypot(*(loc.centres_px[0] - [cols[disc].mean(), rows[disc].mean()])) < 1e-9
