"""Checks of a measured screen shape given as scattered nodes (OpenCSP's screen distortion data: screen
fractions and the 3-D point each lies at), with the station's own screen model.

* :func:`node_reproduction`: the :class:`~sofast_station.measure.screen.InterpolatedScreen` built on the
  nodes returns each node's point at its own position (the model and its conventions, not the data);
* :func:`holdout_interpolation`: the same model built on every other node of the grid, evaluated at the
  nodes left out: how far a linear interpolation between nodes strays, which bounds the model's error
  between the data's nodes (and shows the data's own node-to-node noise);
* :func:`local_quadratic`: the shape at a position near the grid's edge, from a quadratic fitted to the
  nodes around it (the calibration fiducials lie just outside OpenCSP's 1 %..99 % grid);
* :func:`affine_residuals`: two descriptions of one screen compared after the best affine map of one's
  x, y onto the other's (what remains is a difference of shape, not of frame or scale).

Pure functions of arrays; no I/O.
"""

from __future__ import annotations

import numpy as np

from ..geometry import Pose
from .screen import InterpolatedScreen


def screen_model(fractions: np.ndarray, xyz_m: np.ndarray) -> InterpolatedScreen:
    """Our model of the nodes (an :class:`InterpolatedScreen`): positions in fractional screens (u_y counted
    from the bottom, the nodes' second coordinate from the top, as OpenCSP's display models and
    ``import-opencsp`` have it), points in the data's own frame (the pose is the identity)."""
    return InterpolatedScreen(1.0, 1.0, fractions, xyz_m, Pose(np.eye(3), np.zeros(3)), v_from_top=True)


def shape_at(screen: InterpolatedScreen, fractions: np.ndarray) -> np.ndarray:
    """The model's points (N, 3), metres, at positions given as the nodes are (fractions, second from the top)."""
    return screen.points_camera(fractions[:, 0], 1.0 - fractions[:, 1]).T


def _stats(diff_m: np.ndarray) -> dict:
    ok = np.all(np.isfinite(diff_m), axis=1)
    d = diff_m[ok]
    return {"count": int(ok.sum()), "rms_m": np.sqrt(np.mean(d ** 2, axis=0)).tolist(),
            "max_m": np.max(np.abs(d), axis=0).tolist()}


def node_reproduction(fractions: np.ndarray, xyz_m: np.ndarray) -> dict:
    """Per-axis RMS and largest difference (metres) between the model built on the nodes and the nodes."""
    fractions, xyz_m = np.asarray(fractions, np.float64), np.asarray(xyz_m, np.float64)
    return _stats(shape_at(screen_model(fractions, xyz_m), fractions) - xyz_m)


def holdout_interpolation(fractions: np.ndarray, xyz_m: np.ndarray) -> dict:
    """The model built on the nodes whose grid row and column are both even, evaluated at the others inside
    it: per-axis RMS and largest difference (metres) from their own points."""
    fractions, xyz_m = np.asarray(fractions, np.float64), np.asarray(xyz_m, np.float64)
    col = np.searchsorted(np.unique(fractions[:, 0]), fractions[:, 0])
    row = np.searchsorted(np.unique(fractions[:, 1]), fractions[:, 1])
    kept = (col % 2 == 0) & (row % 2 == 0)
    screen = screen_model(fractions[kept], xyz_m[kept])
    out = _stats(shape_at(screen, fractions[~kept]) - xyz_m[~kept])
    out["nodes_used"] = int(kept.sum())
    return out


def local_quadratic(fractions: np.ndarray, xyz_m: np.ndarray, query: np.ndarray, radius: float = 0.05) -> np.ndarray:
    """The shape at each *query* position (fractions, (K, 2)) from a least-squares quadratic in the position
    over the nodes within *radius* of it (NaN with fewer than 12 nodes there): (K, 3) metres."""
    fractions, xyz_m = np.asarray(fractions, np.float64), np.asarray(xyz_m, np.float64)
    out = np.full((len(query), 3), np.nan)
    for k, q in enumerate(np.asarray(query, np.float64).reshape(-1, 2)):
        d = fractions - q
        near = np.hypot(d[:, 0], d[:, 1]) <= radius
        if near.sum() < 12:
            continue
        x, y = d[near, 0], d[near, 1]
        basis = np.column_stack([np.ones(x.size), x, y, x * x, x * y, y * y])
        coef, *_ = np.linalg.lstsq(basis, xyz_m[near], rcond=None)
        out[k] = coef[0]
    return out


def affine_residuals(xy_a: np.ndarray, xy_b: np.ndarray) -> dict:
    """Points b (N, 2) against points a (N, 2) of the same places: the direct difference b - a, and what is
    left after the least-squares affine map of a onto b (per-axis RMS and largest, metres; the map's 2 x 3
    matrix)."""
    a, b = np.asarray(xy_a, np.float64), np.asarray(xy_b, np.float64)
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    a, b = a[ok], b[ok]
    design = np.column_stack([a, np.ones(len(a))])
    coef, *_ = np.linalg.lstsq(design, b, rcond=None)
    left = design @ coef - b
    return {"count": int(ok.sum()), "direct": _stats(b - a), "affine": _stats(left), "map": coef.T.tolist()}
