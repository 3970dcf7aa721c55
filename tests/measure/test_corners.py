"""Sub-pixel facet corners from an anti-aliased quadrilateral drawn in the test."""

import numpy as np
import pytest

from sofast_station.errors import FacetNotFoundError
from sofast_station.measure.corners import fit_outline, match_corners


def coverage_image(corners, shape, ss=16):
    """Fraction of each pixel inside the convex polygon *corners* (column, row), by ss x ss supersampling."""
    h, w = shape
    off = (np.arange(ss) + 0.5) / ss - 0.5
    cov = np.zeros(shape)
    rows, cols = np.mgrid[0:h, 0:w].astype(float)
    n = len(corners)
    for dy in off:
        for dx in off:
            x, y = cols + dx, rows + dy
            inside = np.ones(shape, dtype=bool)
            for i in range(n):
                (x0, y0), (x1, y1) = corners[i], corners[(i + 1) % n]
                inside &= (x1 - x0) * (y - y0) - (y1 - y0) * (x - x0) >= 0
            cov += inside
    return cov / ss**2


@pytest.mark.parametrize("angle_deg", [0.0, 0.7, 12.0])
def test_corners_to_a_small_fraction_of_a_pixel(angle_deg):
    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    half = np.array([[-120.3, -100.2], [121.1, -98.7], [119.4, 102.6], [-118.8, 100.9]])   # irregular quad
    true = half @ np.array([[c, s], [-s, c]]) + [160.37, 140.81]
    cov = coverage_image(true, (280, 320))
    rng = np.random.default_rng(0)
    contrast = 180.0 * cov + rng.normal(0, 1.0, cov.shape)
    region = cov > 0.1
    fit = fit_outline(contrast, region, 4)
    got = match_corners(fit.corners_px, true, tolerance_px=5)
    err = np.linalg.norm(got - true, axis=1)
    # the test image's own 16 x 16 supersampling quantises an axis-aligned edge to 1/16 px (error <= 1/32)
    assert err.max() < 0.03, err
    assert np.all(fit.edge_rms_px < 0.2)


def test_a_triangle_is_not_a_four_cornered_facet():
    cov = coverage_image(np.array([[20.0, 20.0], [150.0, 30.0], [80.0, 150.0]]), (180, 200))
    with pytest.raises(FacetNotFoundError, match="4 corners"):
        fit_outline(180.0 * cov, cov > 0.1, 4)


def test_corners_far_from_the_fixture_are_refused():
    found = np.array([[10.0, 10.0], [110.0, 10.0], [110.0, 110.0], [10.0, 110.0]])
    with pytest.raises(FacetNotFoundError, match="misplaced"):
        match_corners(found, found + 200.0, tolerance_px=50)
    assert np.array_equal(match_corners(found[[2, 3, 0, 1]], found, 5), found)


def test_corner_covariance_matches_the_scatter_over_noise():
    """The corners' covariance from the sides' fits (issue 12: corner noise is not isotropic and corners on
    one side move together) against the scatter of 40 noise draws of a blurred, tilted quadrilateral: each
    coordinate's standard deviation, and the combinations a pose sees (a side's tilt, the outline's size),
    within a factor 1.6."""
    from scipy.ndimage import gaussian_filter

    c, s = np.cos(np.radians(12.0)), np.sin(np.radians(12.0))
    half = np.array([[-120.3, -100.2], [121.1, -98.7], [119.4, 102.6], [-118.8, 100.9]])
    true = half @ np.array([[c, s], [-s, c]]) + [160.37, 140.81]
    cov = gaussian_filter(coverage_image(true, (280, 320), ss=8), 1.5)
    rng = np.random.default_rng(4)
    errors, predicted = [], []
    for _ in range(40):
        fit = fit_outline(180.0 * cov + rng.normal(0, 3.0, cov.shape), cov > 0.1, 4)
        order = [int(np.argmin(np.linalg.norm(fit.corners_px - t, axis=1))) for t in true]
        idx = np.array([[2 * j, 2 * j + 1] for j in order]).ravel()
        errors.append((fit.corners_px[order] - true).ravel())
        # the noise's part: the covariance less the corner finder's own model error
        predicted.append((fit.corner_cov_px2 - fit.corner_model_cov_px2)[np.ix_(idx, idx)])
    seen = np.cov(np.array(errors).T)
    stated = np.mean(predicted, axis=0)
    combos = {f"corner {i} {'uv'[k]}": np.eye(8)[2 * i + k] for i in range(4) for k in range(2)}
    combos["top side's tilt (v1 - v0)"] = np.array([0, -1, 0, 1, 0, 0, 0, 0], float)
    combos["left side's tilt (u3 - u0)"] = np.array([-1, 0, 0, 0, 0, 0, 1, 0], float)
    combos["width (u1 + u2 - u0 - u3)"] = np.array([-1, 0, 1, 0, 1, 0, -1, 0], float)
    for name, w in combos.items():
        ratio = np.sqrt(w @ stated @ w / (w @ seen @ w))
        print(f"{name}: stated / seen {ratio:.2f}")
        assert 1 / 1.6 < ratio < 1.6, name


@pytest.mark.parametrize("angle_deg", [0.0, 3.0])
def test_a_point_sampled_side_along_the_pixel_grid_is_named_and_a_turned_one_is_pinned(angle_deg):
    """Each pixel its centre ray (a staircase edge, as a ray tracer draws it). Along the pixel grid a side
    has no step: the image places it only within a pixel at its ends, and staircase_sides names it;
    turned 3 degrees every side steps through a dozen rows and the corners come within 0.05 px."""
    from sofast_station.measure.corners import staircase_sides

    c, s = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    half = np.array([[-120.15, -110.25], [120.15, -110.25], [120.15, 110.25], [-120.15, 110.25]])
    true = half @ np.array([[c, s], [-s, c]]) + [160.37, 140.41]
    cov = coverage_image(true, (280, 320), ss=1)
    assert set(np.unique(cov)) == {0.0, 1.0}                    # point sampled: no partial pixel
    rng = np.random.default_rng(1)
    contrast = 180.0 * cov + rng.normal(0, 0.5, cov.shape)
    fit = fit_outline(contrast, cov > 0.5, 4)
    assert np.all(fit.quantised == 1)
    err = np.linalg.norm(match_corners(fit.corners_px, true, tolerance_px=5) - true, axis=1)
    if angle_deg == 0.0:
        assert staircase_sides(fit) == [1, 2, 3, 4] and np.all(fit.steps == 0)
        # the truth is within the pixel the image allows, and the stated model covariance says so
        assert err.max() < 0.75
        assert np.all(np.sqrt(np.diag(fit.corner_model_cov_px2)) > 0.2)
    else:
        assert staircase_sides(fit) == [] and np.all(fit.steps >= 10)
        assert err.max() < 0.05, err


def test_a_staircase_side_is_numbered_as_the_design_outlines_side():
    """One side exactly along a pixel row, the other three slanted; the design outline listed from another
    corner: the flagged side is named by the design's numbering (its third side here), not the image's."""
    from sofast_station.measure.corners import staircase_sides

    true = np.array([[40.3, 30.5], [280.6, 30.5], [290.2, 250.7], [35.1, 255.4]])
    cov = coverage_image(true, (290, 330), ss=1)
    contrast = 180.0 * cov + np.random.default_rng(2).normal(0, 0.5, cov.shape)
    design = true[[2, 3, 0, 1]]                  # design corners c2, c3, c0, c1: side 3 runs c0 -> c1
    t = np.linspace(0.0, 1.0, 16, endpoint=False)[:, None]
    nominal = np.concatenate([design[i] + t * (design[(i + 1) % 4] - design[i]) for i in range(4)])
    fit = fit_outline(contrast, cov > 0.5, 4, nominal_px=nominal)
    assert sorted(fit.design_sides.tolist()) == [0, 1, 2, 3]
    assert staircase_sides(fit) == [3]


def test_a_grid_sampled_side_along_the_pixel_grid_is_known_to_its_sub_ray_interval():
    """A 2 x 2 sub-ray renderer's image (each pixel the mean of 4 rays): three slanted sides step through the
    sub-ray lines, the fourth runs exactly along a pixel column, 0.12 px right of the pixel centres, so every
    row's pixel there sees 2 of its 4 rays, coverage 0.5: one coverage sum in every row, no evidence of a grid
    of its own. The image says only that the side lies between the two sub-ray lines 0.5 px apart; fitted
    as an area-sampled side it was put on the pixel centre, its corners 0.12 px off and stated to 0.01-0.03 px
    (chi-square of the 8 coordinates above 100). Taken as the image's grid (the other sides') its corners are
    stated to about 0.5 / sqrt(12) = 0.14 px: the chi-square is below 20 (8 degrees of freedom: 1.4 % above)."""
    true = np.array([[40.12, 30.3], [280.6, 36.5], [290.2, 250.7], [40.12, 255.4]])
    cov = coverage_image(true, (290, 330), ss=2)
    assert set(np.unique(cov)) <= {0.0, 0.25, 0.5, 0.75, 1.0}
    contrast = 180.0 * cov + np.random.default_rng(3).normal(0, 0.5, cov.shape)
    fit = fit_outline(contrast, cov > 0.5, 4)
    found = match_corners(fit.corners_px, true, tolerance_px=5)
    order = [int(np.flatnonzero(np.all(fit.corners_px == f, axis=1))[0]) for f in found]
    idx = np.array([[2 * j, 2 * j + 1] for j in order]).ravel()
    c = fit.corner_cov_px2[np.ix_(idx, idx)]
    e = (found - true).ravel()
    chi2 = float(e @ np.linalg.solve(c, e))
    print(f"grids {fit.quantised.tolist()}, steps {fit.steps.tolist()}, corner errors {np.round(e, 3).tolist()}, "
          f"sigma {np.round(np.sqrt(np.diag(c)), 3).tolist()}, chi-square {chi2:.1f}")
    assert np.all(fit.quantised == 2)
    assert chi2 < 20.0
