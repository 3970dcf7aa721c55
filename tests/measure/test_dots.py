"""A dot target's 3-D dot locations (measure/dots.py): finding and indexing dots, and the bundle adjustment with
its uncertainty, on photographs rendered from a known truth (tests/calibrate/photographs.py: nothing from the
package)."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.geometry import CameraIntrinsics
from sofast_station.measure.dots import (DotLocations, DotView, dot_grid, find_dots, index_dots, locate_dots,
                                         orient_indices)
from sofast_station.measure.markers import MarkerTable, detect_markers, marker_correspondences
from tests.calibrate.photographs import DOWN, RIGHT, DotBoard, Lens, camera_in_front, render, wall_markers

LENS = Lens(960, 640, 700.0, 699.0, 481.0, 322.0, (-0.06, 0.04, 0.0003, -0.0002, 0.0))
CAMERA = CameraIntrinsics(LENS.width, LENS.height, LENS.matrix, np.array(LENS.distortion))
CENTRES = [(-0.8, -0.6), (0.0, -0.65), (0.8, -0.6), (-0.85, 0.05), (0.8, 0.0), (-0.8, 0.65), (0.05, 0.7), (0.8, 0.65)]
IDS = [3, 7, 11, 15, 21, 30, 41, 52]


def board() -> DotBoard:
    """13 x 11 dots, 40 mm apart, 9 mm radius (about 2.4 px in the photographs, 10.7 px apart: OpenCSP's
    pegboard as its photographs show it), tilted a few milliradians off the wall and bowed 4 mm at the
    corners, its (0, 0) dot 15 mm in front of the wall. Lattice i runs along the camera's right (world -x),
    j down (world +y)."""
    a = RIGHT + np.array([0.0, 0.01, 0.02])
    return DotBoard(origin=np.array([0.03, 0.02, 0.015]), a=a, b=DOWN + np.array([0.0, 0.0, 0.01]), pitch=0.04,
                    radius=0.009, i_range=(-6, 7), j_range=(-5, 6), bow=0.004)


def photographs(seed: int, views: int = 3):
    """The markers and the board from *views* places 1 m apart, 2.45-2.75 m away; noise 1.5 DN."""
    rng = np.random.default_rng(seed)
    ids, corners, planes = wall_markers(CENTRES, IDS, 0.10, np.random.default_rng(99))
    target = board()
    shots = []
    for x in np.linspace(-1.0, 1.0, views):
        rotation, translation, _ = camera_in_front(rng, x=x, distance=2.6)
        image = render(LENS, rotation, translation, planes, board=target, samples=3, rng=rng)
        origin = LENS.project(rotation, translation, target.origin[None])[0] + rng.normal(0.0, 1.0, 2)
        shots.append((image, origin))
    return MarkerTable(ids, corners), target, shots


def views_of(table, shots) -> list[DotView]:
    out = []
    for n, (image, origin) in enumerate(shots):
        centres, _ = find_dots(image)
        indices, dot_px = index_dots(centres, origin)
        _, marker_px, marker_world, _ = marker_correspondences(detect_markers(image, camera=CAMERA), table)
        out.append(DotView(f"view {n}", marker_world, marker_px, indices, dot_px))
    return out


@pytest.fixture(scope="module")
def scenes():
    """Three drawn scenes of three photographs each, their dots found and indexed: (table, board, views)."""
    out = []
    for seed in range(3):
        table, target, shots = photographs(seed)
        out.append((table, target, views_of(table, shots)))
    return out


def test_dots_are_located_within_their_u_over_three_scenes(scenes):
    """Three drawn scenes of three photographs each: every dot located, with x index along the world's +x
    (the lattice's i runs along -x: x = -i) and y along +y; per scene at least 93 % of the dots' coordinates
    within their U (k = 2) of the truth (95 % expected of a right U; 96.5-100 % per axis were measured), none
    beyond 2.5 U (1.16-1.57 U the largest measured), and the errors in units of their standard uncertainty
    have an RMS between 0.3 and 1.6 per scene and axis (0.46-1.08 measured: U is neither a fraction of the
    error nor over three times it; the dots' errors share their photographs' pose errors, so 143 dots are
    far fewer independent draws, and the bounds are wide). 143 dots, 429 coordinates per scene."""
    for seed, (table, target, views) in enumerate(scenes):
        solution = locate_dots(CAMERA, views)
        loc = solution.locations
        truth = target.dots()
        assert solution.index_map.tolist() == [[-1, 0, 0], [0, 1, 0]]
        assert loc.located.sum() == len(truth) and solution.outliers == 0
        err, u = [], []
        for (i, j), xyz in truth.items():
            err.append(loc.dot(-i, j) - xyz)
            u.append(loc.xyz_U_m[j - loc.y_index[0], -i - loc.x_index[0]])
        err, u = np.array(err), np.array(u)
        assert np.mean(np.abs(err) <= u) >= 0.93, (seed, np.mean(np.abs(err) <= u, axis=0))
        assert np.all(np.abs(err) <= 2.5 * u), seed
        rms = np.sqrt(np.mean((err / (u / 2)) ** 2, axis=0))
        assert np.all((rms > 0.3) & (rms < 1.6)), (seed, rms)
        assert solution.rms_px["dots"] < 0.1 and solution.rms_px["markers"] < 0.3


def test_fixed_poses_carry_the_markers_uncertainty_into_the_dots(scenes):
    """With each pose from its markers alone (OpenCSP's method) the dots' U is larger than when the dots also
    adjust the poses (by 11-19 % per axis here, with eight markers in each of three photographs): the poses'
    uncertainty is carried into the dots either way."""
    views = scenes[0][2]
    joint = locate_dots(CAMERA, views)
    fixed = locate_dots(CAMERA, views, refine_poses=False)
    u_joint = np.nanmedian(joint.locations.xyz_U_m, axis=(0, 1))
    u_fixed = np.nanmedian(fixed.locations.xyz_U_m, axis=(0, 1))
    assert np.all(u_fixed > 1.07 * u_joint), (u_fixed, u_joint)


def test_index_dots_walks_a_perspective_lattice_past_a_gap_and_a_stray_blob():
    """A 21 x 17 lattice seen in perspective (steps changing by 40 % across it), one dot missing, a stray blob
    between two dots, every point moved by 0.05 px noise: every present dot gets its true index relative to
    the origin, the stray blob none."""
    rng = np.random.default_rng(4)
    i, j = np.meshgrid(np.arange(-10, 11), np.arange(-8, 9), indexing="ij")
    i, j = i.ravel(), j.ravel()
    w = 1.0 + 0.015 * i + 0.01 * j                                          # a homography's denominator
    pts = np.column_stack([500 + (12.0 * i + 1.5 * j) / w, 400 + (12.0 * j - 1.0 * i) / w])
    pts += rng.normal(0.0, 0.05, pts.shape)
    missing = (i == 3) & (j == -2)
    stray = (pts[(i == -4) & (j == 5)] + pts[(i == -3) & (j == 5)]) / 2 + [0.0, 3.0]
    pts_in = np.vstack([pts[~missing], stray])
    indices, found = index_dots(pts_in, pts[(i == 0) & (j == 0)][0] + [1.0, -1.0])
    assert len(indices) == (~missing).sum()
    lookup = {(a, b): p for a, b, p in zip(i, j, pts)}
    for (a, b), p in zip(indices.tolist(), found):
        np.testing.assert_allclose(p, lookup[(a, b)])


def test_bad_dots_inputs_are_named():
    pts = np.array([[x, y] for x in range(0, 50, 10) for y in range(0, 50, 10)], float)
    with pytest.raises(ValueError, match="no dot within half a lattice step"):
        index_dots(pts, (5.0, 5.0))
    with pytest.raises(ValueError, match="at least a 3 x 3 block"):
        index_dots(pts[:5], (0.0, 0.0))
    with pytest.raises(ValueError, match="grey uint8"):
        find_dots(np.zeros((10, 10)))
    with pytest.raises(ValueError, match="at least 2 places"):
        locate_dots(CAMERA, [])


def test_dot_grid_holds_scattered_dots_like_opencsps_file():
    """Scattered dots into the (rows, columns, 3) grid of OpenCSP's DotLocationsFixedPattern: row = y index,
    column = x index, NaN where no dot; U = 2 sqrt(diag(covariance))."""
    idx = np.array([[-1, 0], [0, 0], [2, 1]])
    xyz = np.arange(9.0).reshape(3, 3)
    cov = np.stack([np.diag([1e-8, 4e-8, 9e-8])] * 3)
    grid = dot_grid(idx, xyz, cov)
    assert grid.x_index.tolist() == [-1, 0, 1, 2] and grid.y_index.tolist() == [0, 1]
    np.testing.assert_array_equal(grid.dot(2, 1), xyz[2])
    np.testing.assert_array_equal(grid.xyz_m[0, 1], xyz[1])
    assert np.isnan(grid.dot(1, 0)).all() and grid.located.sum() == 3
    np.testing.assert_allclose(grid.xyz_U_m[1, 3], [2e-4, 4e-4, 6e-4])
    with pytest.raises(IndexError, match="outside the grid"):
        grid.dot(5, 0)
    with pytest.raises(ValueError, match="given once"):
        dot_grid(np.array([[0, 0], [0, 0]]), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="consecutive"):
        DotLocations(np.array([0, 2]), np.array([0]), np.zeros((1, 2, 3)))


def test_orient_indices_follows_the_world_axes():
    """A lattice whose i runs along world -y and j along world +x: x index = j, y index = -i."""
    i, j = np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), indexing="ij")
    ij = np.column_stack([i.ravel(), j.ravel()])
    xyz = np.column_stack([0.04 * ij[:, 1], -0.04 * ij[:, 0], np.zeros(len(ij))])
    m = orient_indices(ij, xyz)
    assert m.tolist() == [[0, 1, 0], [-1, 0, 0]]


def _numpy_walk(pts, first, basis, tolerance, span):
    """The lattice walk as :func:`index_dots` did it in numpy, wave by wave with a k-d tree (the compiled walk's
    definition): positions by index and the dot at each place."""
    from scipy.spatial import cKDTree

    tree = cKDTree(pts)
    grid = np.full((2 * span + 1, 2 * span + 1, 2), np.nan)
    grid[span, span] = pts[first]
    who = np.full(grid.shape[:2], -1, np.int64)
    who[span, span] = first
    taken = np.zeros(len(pts), bool)
    taken[first] = True
    dirs = np.array([(1, 0), (-1, 0), (0, 1), (0, -1)])
    frontier = np.array([[span, span]])
    while frontier.size:
        f, d = np.tile(frontier, (4, 1)), np.repeat(dirs, len(frontier), axis=0)
        guess, nxt = np.repeat(basis, len(frontier), axis=0), f + d
        keep = np.all((nxt >= 1) & (nxt < 2 * span), axis=1)
        f, nxt, d, guess = f[keep], nxt[keep], d[keep], guess[keep]
        keep = np.isnan(grid[nxt[:, 0], nxt[:, 1], 0])
        f, nxt, d, guess = f[keep], nxt[keep], d[keep], guess[keep]
        here = grid[f[:, 0], f[:, 1]]
        delta = here - grid[f[:, 0] - d[:, 0], f[:, 1] - d[:, 1]]
        for side in (d[:, ::-1], -d[:, ::-1]):
            a = grid[f[:, 0] + side[:, 0], f[:, 1] + side[:, 1]]
            b = grid[nxt[:, 0] + side[:, 0], nxt[:, 1] + side[:, 1]]
            fill = np.isnan(delta[:, 0]) & ~np.isnan(a[:, 0]) & ~np.isnan(b[:, 0])
            delta[fill] = (b - a)[fill]
        unset = np.isnan(delta[:, 0])
        delta[unset] = guess[unset]
        if nxt.size == 0:
            break
        _, first_of = np.unique(nxt[:, 0] * (2 * span + 1) + nxt[:, 1], return_index=True)
        cand, pred, step = nxt[first_of], (here + delta)[first_of], np.linalg.norm(delta, axis=1)[first_of]
        dist, hit = tree.query(pred)
        ok = (dist <= tolerance * step) & ~taken[hit]
        order = np.argsort(dist[ok])
        hit_ok, cand_ok = hit[ok][order], cand[ok][order]
        _, once = np.unique(hit_ok, return_index=True)
        hit_ok, cand_ok = hit_ok[once], cand_ok[once]
        grid[cand_ok[:, 0], cand_ok[:, 1]] = pts[hit_ok]
        who[cand_ok[:, 0], cand_ok[:, 1]] = hit_ok
        taken[hit_ok] = True
        frontier = cand_ok
    return grid, who


def test_the_compiled_lattice_walk_is_the_numpy_walk():
    """24 lattices (turned, sheared, bent, jittered by up to a fifth of a step, a third of the dots missing,
    stray blobs among them, four tolerances): the compiled walk places the same dot at every index as the numpy
    walk it replaced (:func:`_numpy_walk`), bit for bit; together they index thousands of dots."""
    from sofast_station.measure.kernels import lattice_walk

    rng = np.random.default_rng(7)
    indexed = 0
    for case in range(24):
        nx, ny = rng.integers(8, 40, 2)
        pitch, turn, shear = rng.uniform(5, 25), rng.normal(0, 0.2), rng.normal(0, 0.1)
        i, j = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"))
        u, v = i + shear * j + 0.003 * j ** 2, j.astype(float)
        pts = pitch * np.column_stack([np.cos(turn) * u - np.sin(turn) * v, np.sin(turn) * u + np.cos(turn) * v])
        pts += rng.normal(0, [0.0, 0.05, 0.2][case % 3] * pitch, pts.shape)
        pts = pts[rng.random(len(pts)) > [0.0, 0.1, 0.33][case % 3 if case % 2 else 0]]
        if case % 4 == 1:
            pts = np.vstack([pts, rng.uniform(pts.min(0), pts.max(0), (rng.integers(5, 40), 2))])
        pts = pts[rng.permutation(len(pts))] + 200.0
        first = int(rng.integers(len(pts)))
        basis = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]) * pitch
        tolerance = [0.1, 0.3, 0.45, 0.5][case % 4]
        span = int(np.ceil(4 * np.sqrt(len(pts)))) + 8
        grid, who = lattice_walk(pts, first, basis, tolerance, pitch, span)
        ref_grid, ref_who = _numpy_walk(pts, first, basis, tolerance, span)
        np.testing.assert_array_equal(who, ref_who, err_msg=f"case {case}")
        np.testing.assert_array_equal(grid, ref_grid, err_msg=f"case {case}")
        indexed += int((who >= 0).sum())
    assert indexed > 5000, indexed
