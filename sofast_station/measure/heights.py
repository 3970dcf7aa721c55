"""Slopes on a regular facet grid, integrated to heights by least squares, and local curvature.

All functions are pure (numpy in, numpy out). Lengths in metres, slopes dimensionless (dz/dx, dz/dy).

Gridding: the measured points (scattered in facet x, y, one per camera pixel) are averaged into square
cells of side ``cell_m``; a cell holds the mean slope of the points that fall in it (or NaN), which is the
slope at those points' centroid, not at the cell's centre. For the heights a facet is intersected at
(:func:`height_grid`), each cell's mean is first moved to its centre (:func:`centred_slopes`).

Integration: the heights h on the cell centres minimise

    sum over x-neighbours (h[i, j+1] - h[i, j] - cell * (s_x[i, j] + s_x[i, j+1]) / 2)^2
  + sum over y-neighbours (h[i+1, j] - h[i, j] - cell * (s_y[i, j] + s_y[i+1, j]) / 2)^2

(the trapezoid rule on every pair of neighbouring valid cells; Southwell's geometry), with the mean of h
fixed at zero. Each connected region of valid cells is solved on its own (its own zero mean).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .kernels import bilinear, grid_sums


def grid_slopes(x_m, y_m, s_x, s_y, cell_m: float, extent_m=None, min_points: int = 1,
                centred: bool = False) -> dict:
    """Average scattered slopes into square cells.

    Parameters
    ----------
    x_m, y_m : (N,) arrays
        Facet-frame positions of the points, metres.
    s_x, s_y : (N,) arrays
        Slopes (or slope differences) at the points, dimensionless.
    cell_m : float
        Cell side, metres.
    extent_m : (x_min, x_max, y_min, y_max), optional
        Grid edges; the points' bounding box (padded by one cell) by default.
    min_points : int
        A cell with fewer points is left empty (NaN).
    centred : bool
        Each cell's mean slope moved from its points' centroid to its centre (:func:`centred_slopes`): for
        what takes differences between cells (heights, curvature, two measurements' difference).

    Returns
    -------
    dict
        ``s_x``, ``s_y`` (ny, nx) mean slopes (at the cells' centres with *centred*), NaN where empty;
        ``offset_x_m``, ``offset_y_m`` (ny, nx) the mean offset of the cell's points from its centre, metres,
        NaN where empty; ``count`` (ny, nx) points per cell; ``x_m`` (nx,), ``y_m`` (ny,) cell centres;
        ``extent_m`` grid edges; ``cell_m``.
    """
    x = np.asarray(x_m, dtype=np.float64).ravel()
    y = np.asarray(y_m, dtype=np.float64).ravel()
    sx = np.asarray(s_x, dtype=np.float64).ravel()
    sy = np.asarray(s_y, dtype=np.float64).ravel()
    if not (x.size == y.size == sx.size == sy.size):
        raise ValueError(f"x_m, y_m, s_x, s_y must have one value per point, got sizes "
                         f"{x.size}, {y.size}, {sx.size}, {sy.size}")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"cell_m must be a positive length in metres, got {cell_m}")
    keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(sx) & np.isfinite(sy)
    if not keep.all():                    # (no copies when every point is finite, as a facet's are)
        x, y, sx, sy = x[keep], y[keep], sx[keep], sy[keep]
    if extent_m is None:
        if x.size == 0:
            raise ValueError("no finite points to grid")
        extent_m = (float(x.min()) - cell_m, float(x.max()) + cell_m, float(y.min()) - cell_m, float(y.max()) + cell_m)
    x0, x1, y0, y1 = (float(v) for v in extent_m)
    nx = max(1, int(math.ceil((x1 - x0) / cell_m - 1e-9)))
    ny = max(1, int(math.ceil((y1 - y0) / cell_m - 1e-9)))
    ix = np.floor((x - x0) / cell_m).astype(np.int64)
    iy = np.floor((y - y0) / cell_m).astype(np.int64)
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    if not ok.all():
        x, y, ix, iy, sx, sy = x[ok], y[ok], ix[ok], iy[ok], sx[ok], sy[ok]
    flat = iy * nx + ix
    count = np.bincount(flat, minlength=nx * ny).astype(np.float64)
    full = count >= max(1, int(min_points))
    with np.errstate(invalid="ignore", divide="ignore"):
        gx, gy, ox, oy = (np.where(full, np.bincount(flat, v, minlength=nx * ny) / count, np.nan).reshape(ny, nx)
                          for v in (sx, sy, x - (x0 + (ix + 0.5) * cell_m), y - (y0 + (iy + 0.5) * cell_m)))
    if centred:
        gx, gy = centred_slopes(gx, gy, ox, oy, cell_m)
    return {"s_x": gx, "s_y": gy, "offset_x_m": ox, "offset_y_m": oy, "count": count.reshape(ny, nx).astype(np.int64),
            "x_m": x0 + (np.arange(nx) + 0.5) * cell_m, "y_m": y0 + (np.arange(ny) + 0.5) * cell_m,
            "extent_m": (x0, x0 + nx * cell_m, y0, y0 + ny * cell_m), "cell_m": float(cell_m)}


def _difference(s: np.ndarray, cell_m: float, axis: int) -> np.ndarray:
    """ds/d(axis) per metre of the gridded *s* (NaN where empty): the central difference where both neighbours
    along *axis* are finite, one-sided where one is, NaN where neither is."""
    fwd = (np.roll(s, -1, axis) - s) / cell_m
    bwd = (s - np.roll(s, 1, axis)) / cell_m
    edge_lo = [slice(None)] * 2
    edge_lo[axis] = 0
    edge_hi = [slice(None)] * 2
    edge_hi[axis] = s.shape[axis] - 1
    bwd[tuple(edge_lo)] = np.nan
    fwd[tuple(edge_hi)] = np.nan
    central = 0.5 * (fwd + bwd)
    return np.where(np.isfinite(central), central, np.where(np.isfinite(fwd), fwd, bwd))


def centred_slopes(s_x, s_y, offset_x_m, offset_y_m, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Gridded mean slopes (:func:`grid_slopes`) moved from their points' centroid to the cell's centre, to
    first order: s(centre) = s(mean) - grad s . offset, the gradient by differences of the neighbouring
    cells' means (:func:`_difference`; none where a cell has no neighbour along an axis). NaN where a cell is
    empty.

    A cell's mean slope is the slope at its points' centroid, which on a camera's pixel lattice sits up to
    half a cell off the centre in a pattern that beats with the grid (a moire), and at a facet's rim always
    toward the inside. Taken as the centre's, it integrates to height errors with a large-scale part: on a
    1.2 m facet of 0.6 mrad slope error of 2.8 cm correlation seen by a 5.5 mm pixel lattice, a tilt and a
    curvature of 0.27 / 0.31 um at the rim at 96 cells and 0.95 / 0.57 um at 112 (RMS over 12 drawn fields);
    moved to the centres 0.11 / 0.11 and 0.10 / 0.11 um, under 0.25 up to 144 cells
    (``tests/measure/test_heights.py``). A nearly flat facet far from its screen reads that part as
    focal power (:func:`~.boresight.close_on_all_points`).
    """
    sx = np.asarray(s_x, dtype=np.float64)
    sy = np.asarray(s_y, dtype=np.float64)
    ox = np.asarray(offset_x_m, dtype=np.float64)
    oy = np.asarray(offset_y_m, dtype=np.float64)
    if not (sx.shape == sy.shape == ox.shape == oy.shape) or sx.ndim != 2:
        raise ValueError(f"s_x, s_y and the offsets must be 2-D arrays of one shape, got {sx.shape}, {sy.shape}, "
                         f"{ox.shape} and {oy.shape}")
    filled = np.isfinite(sx) & np.isfinite(sy) & np.isfinite(ox) & np.isfinite(oy)
    out = []
    for s in (sx, sy):
        s = np.where(filled, s, np.nan)
        move = np.nan_to_num(_difference(s, cell_m, 1)) * ox + np.nan_to_num(_difference(s, cell_m, 0)) * oy
        out.append(np.where(filled, s - move, np.nan))
    return out[0], out[1]


def integrate_slopes(s_x, s_y, cell_m: float) -> np.ndarray:
    """Heights from gridded slopes by least squares (see the module's docstring).

    Parameters
    ----------
    s_x, s_y : (ny, nx) arrays
        dz/dx (along columns, +x) and dz/dy (along rows, +y: row index increasing with y) per cell;
        NaN outside the measured region.
    cell_m : float
        Cell side, metres.

    Returns
    -------
    (ny, nx) array
        Heights, metres, zero mean over each connected measured region; NaN outside it and on
        isolated cells (no neighbour to integrate from).
    """
    # lazy: scipy.sparse, ~260 ms CPU; config.py loads this (via pipeline.py) at every start
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    sx = np.asarray(s_x, dtype=np.float64)
    sy = np.asarray(s_y, dtype=np.float64)
    if sx.shape != sy.shape or sx.ndim != 2:
        raise ValueError(f"s_x and s_y must be 2-D arrays of one shape, got {sx.shape} and {sy.shape}")
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise ValueError(f"cell_m must be a positive length in metres, got {cell_m}")
    valid = np.isfinite(sx) & np.isfinite(sy)
    ny, nx = sx.shape
    index = np.full(sx.shape, -1, dtype=np.int64)
    index[valid] = np.arange(int(valid.sum()))
    n = int(valid.sum())
    out = np.full(sx.shape, np.nan)
    if n == 0:
        return out
    # neighbour pairs (a -> b) with the height difference the slopes predict
    pa, pb, d = [], [], []
    both = valid[:, :-1] & valid[:, 1:]
    pa.append(index[:, :-1][both])
    pb.append(index[:, 1:][both])
    d.append(cell_m * 0.5 * (sx[:, :-1][both] + sx[:, 1:][both]))
    both = valid[:-1, :] & valid[1:, :]
    pa.append(index[:-1, :][both])
    pb.append(index[1:, :][both])
    d.append(cell_m * 0.5 * (sy[:-1, :][both] + sy[1:, :][both]))
    a, b, dh = np.concatenate(pa), np.concatenate(pb), np.concatenate(d)
    m = a.size
    if m == 0:
        return out
    rows = np.r_[np.arange(m), np.arange(m)]
    g = coo_matrix((np.r_[-np.ones(m), np.ones(m)], (rows, np.r_[a, b])), shape=(m, n)).tocsr()
    adjacency = coo_matrix((np.ones(m), (a, b)), shape=(n, n))
    n_comp, label = connected_components(adjacency, directed=False)
    sizes = np.bincount(label, minlength=n_comp)
    # normal equations G^T G h = G^T dh, singular by one constant per region: pin the first cell of each
    # region (one more equation h = 0 there), then shift each region to zero mean
    first = np.full(n_comp, -1, dtype=np.int64)
    first[label[::-1]] = np.arange(n)[::-1]
    pin = coo_matrix((np.ones(n_comp), (first, first)), shape=(n, n))
    system = ((g.T @ g) + pin).tocsc()
    h = np.asarray(spsolve(system, g.T @ dh), dtype=np.float64)
    h -= (np.bincount(label, h, minlength=n_comp) / sizes)[label]
    h[sizes[label] < 2] = np.nan
    out[valid] = h
    return out


def curvature_map(s_x, s_y, cell_m: float) -> dict:
    """Local focal power along x and y from gridded slopes: kappa_x = 2 ds_x/dx, kappa_y = 2 ds_y/dy, 1/m.

    (For z = A x^2 the slope is 2 A x and kappa_x = 4 A = 1/f_x, the convention of the reported figures.)
    Central differences inside the region, one-sided at its edge; NaN where a cell has no neighbour.

    Returns
    -------
    dict
        ``kappa_x``, ``kappa_y`` (ny, nx) in 1/m; ``mean`` their average.
    """
    sx = np.asarray(s_x, dtype=np.float64)
    sy = np.asarray(s_y, dtype=np.float64)

    kx = 2.0 * _difference(sx, cell_m, 1)
    ky = 2.0 * _difference(sy, cell_m, 0)
    return {"kappa_x": kx, "kappa_y": ky, "mean": 0.5 * (kx + ky)}


def slope_differences(slopes, residuals_mrad) -> tuple[np.ndarray, np.ndarray]:
    """Measured minus model slope, in slope units, from measured slopes and angle residuals.

    The residuals are angles e = atan(s_measured) - atan(s_model) in mrad (docs/conventions.md), so the
    model slope is tan(atan(s) - e) and the difference s - tan(atan(s) - e): on a steep gore facet it is
    up to 15 % larger than e itself.

    Parameters
    ----------
    slopes : (2, N) array
        Measured slopes s_x, s_y.
    residuals_mrad : (e_x, e_y)
        Angle residuals, mrad.
    """
    s = np.asarray(slopes, dtype=np.float64)
    ex, ey = (np.asarray(e, dtype=np.float64) * 1e-3 for e in residuals_mrad)
    return s[0] - np.tan(np.arctan(s[0]) - ex), s[1] - np.tan(np.arctan(s[1]) - ey)


@dataclass(frozen=True)
class HeightGrid:
    """Heights on a regular grid of cell centres (x0 + (j + 1/2) cell, y0 + (i + 1/2) cell), metres, read
    anywhere by bilinear interpolation (:meth:`at`; clamped at the grid's outer cell centres)."""

    x0_m: float
    y0_m: float
    cell_m: float
    heights_m: np.ndarray

    def at(self, x_m, y_m) -> np.ndarray:
        """The heights at the points (*x_m*, *y_m*) (metres, arrays of one shape or scalars; NaN at a point
        not finite), metres, an array of their shape."""
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        if x.shape != y.shape:
            raise ValueError(f"x_m and y_m must have one shape, got {x.shape} and {y.shape}")
        # one compiled pass (the same bits as numpy's clip, take and bilinear expression): the uncertainty's
        # reruns read the grid twice a step, 120 times per capture, on a few thousand points
        return bilinear(self.heights_m, self.x0_m, self.y0_m, self.cell_m, x.ravel(), y.ravel()).reshape(x.shape)


@lru_cache(maxsize=16)
def _laplacian_eigenvalues(ny: int, nx: int) -> np.ndarray:
    """The Neumann grid Laplacian's eigenvalues, 2 - 2 cos(pi k / n) per axis summed, with the mean's (0, 0)
    set to 1 (:func:`integrate_full_grid` divides by them; read-only, kept per grid size)."""
    lam = (2.0 - 2.0 * np.cos(np.pi * np.arange(ny) / ny))[:, None] + (2.0 - 2.0 * np.cos(np.pi * np.arange(nx) / nx))
    lam[0, 0] = 1.0
    lam.setflags(write=False)
    return lam


def integrate_full_grid(s_x, s_y, cell_m: float) -> np.ndarray:
    """:func:`integrate_slopes` on a grid with no empty cell, solved by the discrete cosine transform.

    On a full rectangular grid the least-squares normal equations of the trapezoid differences are the
    grid's Laplacian with reflecting (Neumann) edges, which the type-II DCT diagonalises (eigenvalues
    2 - 2 cos(pi k / n) per axis): a few milliseconds for 128 x 128 cells where the sparse solve takes a
    second. Heights have zero mean.
    """
    sx = np.asarray(s_x, dtype=np.float64)
    sy = np.asarray(s_y, dtype=np.float64)
    if sx.shape != sy.shape or sx.ndim != 2 or not (np.all(np.isfinite(sx)) and np.all(np.isfinite(sy))):
        raise ValueError(f"s_x and s_y must be finite 2-D arrays of one shape, got {sx.shape} and {sy.shape}")
    ny, nx = sx.shape
    dx = cell_m * 0.5 * (sx[:, :-1] + sx[:, 1:])          # h[i, j+1] - h[i, j]
    dy = cell_m * 0.5 * (sy[:-1, :] + sy[1:, :])          # h[i+1, j] - h[i, j]
    rhs = np.zeros((ny, nx))                              # G^T d: the differences' divergence
    rhs[:, :-1] -= dx
    rhs[:, 1:] += dx
    rhs[:-1, :] -= dy
    rhs[1:, :] += dy
    return _solve_divergence(rhs)


def _solve_divergence(rhs: np.ndarray) -> np.ndarray:
    """The zero-mean heights whose Neumann Laplacian is *rhs* (:func:`integrate_full_grid`'s solve), metres."""
    # lazy: scipy.fft, ~320 ms CPU; config.py loads this (via pipeline.py) at every start
    from scipy.fft import dctn, idctn

    coef = dctn(rhs, type=2, norm="ortho", workers=1)
    coef /= _laplacian_eigenvalues(*rhs.shape)
    coef[0, 0] = 0.0                                      # the mean: free, set to zero
    return idctn(coef, type=2, norm="ortho", workers=1)


def height_grid(x_m, y_m, g_x, g_y, cells: int = 96, model=None) -> HeightGrid:
    """The heights whose slopes are *g_x*, *g_y* at scattered points (x_m, y_m), on a grid of about *cells*
    square cells along the points' longer extent (:func:`grid_slopes`, each cell's mean moved to its centre
    by :func:`centred_slopes`, then :func:`integrate_full_grid`).

    Cells no point falls in take slopes 0: beyond a facet's outline in its bounding box (a gore's corners)
    the heights are carried on flat, which leaves those inside as the masked least-squares would within
    the grid's resolution. Meant for slopes that are small departures from a model (a facet's slope
    residuals), whose heights are what the model misses: *g_x*, *g_y* less the slopes of the quadratic *model*
    (A, B, C, D, E, F; :func:`~.surface.surface_slopes`) when given.
    """
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    x0, x1, y0, y1 = float(x.min()), float(x.max()), float(y.min()), float(y.max())
    span = max(x1 - x0, y1 - y0, 1e-9)                    # (np.ptp's, from the same extremes)
    cell = span / max(int(cells), 4)
    extent = (x0 - 0.5 * cell, x1 + 0.5 * cell, y0 - 0.5 * cell, y1 + 0.5 * cell)
    # grid_slopes' cells on that extent from one compiled pass over the points (the same bits; the uncertainty's
    # reruns grid a few thousand points 60 times), the empty cells' slopes 0 once centred
    x0, x1, y0, y1 = extent
    shape = (max(1, int(math.ceil((y1 - y0) / cell - 1e-9))), max(1, int(math.ceil((x1 - x0) / cell - 1e-9))))
    count, s_x, s_y, o_x, o_y = grid_sums(x, y, g_x, g_y, x0, y0, cell, shape, model)
    full = count >= 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        means = [np.where(full, v / count, np.nan) for v in (s_x, s_y, o_x, o_y)]
    c_x, c_y = centred_slopes(*means, cell)
    return HeightGrid(x0, y0, cell, integrate_full_grid(np.where(np.isfinite(c_x), c_x, 0.0),
                                                        np.where(np.isfinite(c_y), c_y, 0.0), cell))
