"""Screen models: fractional screen coordinates -> 3-D points in the camera frame.

A screen model answers one question: where, in the camera's frame, is the screen point at position
(u_x, u_y) metres from the active area's left and bottom edges? The flat model uses the screen's size
and its pose (the camera/screen assembly); a measured distortion map (projection screens) plugs in
behind the same method.

Every model can be perturbed as itself (the uncertainty's finite differences,
:mod:`sofast_station.measure.uncertainty`): :meth:`~ScreenModel.moved` turns and shifts it about and
along its own axes through its centre, :meth:`~ScreenModel.stretched` scales one axis about its centre
(a pitch error of a flat screen, a scale error of a measured screen's shape).
"""

from __future__ import annotations

import copy
import hashlib
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from ..geometry import Pose
from .kernels import grid_screen_points


class ScreenModel(Protocol):
    """Screen positions -> camera-frame points.

    ``width_m`` and ``height_m`` are the extents L the fringe periods are counted over (positions run
    over [0, L)); ``points_camera`` returns NaN for positions the model does not cover.
    """

    width_m: float
    height_m: float
    screen_to_camera: Pose

    def points_camera(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        """(3, N) camera-frame points, metres, of screen positions u_x (from left), u_y (from bottom)."""

    def centre_camera(self) -> np.ndarray:
        """The point the range finder measures from (the screen centre), camera frame, metres."""

    def moved(self, delta: Pose) -> "ScreenModel":
        """The same screen moved by the small motion *delta* about and along its own axes through its
        centre (the screen's pose in the camera frame composed with *delta*)."""

    def stretched(self, axis: str, factor: float) -> "ScreenModel":
        """The same screen with its *axis* ("x" or "y") scaled by *factor* about its centre: every
        position of that axis lies *factor* times as far from the centre."""


def _check_stretch(axis: str, factor: float) -> int:
    if axis not in ("x", "y"):
        raise ValueError(f"axis must be 'x' or 'y', got {axis!r}")
    if not (np.isfinite(factor) and factor > 0):
        raise ValueError(f"factor must be a positive finite number, got {factor!r}")
    return "xy".index(axis)


@dataclass(frozen=True)
class FlatScreen:
    """A flat screen of known size at a known pose.

    Attributes
    ----------
    width_m, height_m : float
        Active area W and H, metres.
    screen_to_camera : Pose
        Maps screen-frame points (origin at the active area's centre) into the camera frame.
    pitch_scale : (float, float)
        The pixel pitch over the nominal one, per axis (1, 1 unless :meth:`stretched`): a position u,
        counted over the nominal ``width_m``, lies ``u * scale`` from the left edge of an active area
        ``width_m * scale`` wide.
    """

    width_m: float
    height_m: float
    screen_to_camera: Pose
    pitch_scale: tuple = (1.0, 1.0)

    def points_camera(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        u_x_m = np.asarray(u_x_m, dtype=np.float64)
        u_y_m = np.asarray(u_y_m, dtype=np.float64)
        r = self.screen_to_camera.rotation
        t = self.screen_to_camera.translation
        sx, sy = self.pitch_scale
        # (u s) - (w s) / 2, not (u - w / 2) s: the stretched screen's points are then bit for bit those
        # of the positions and width scaled first (the uncertainty's screen-pitch rows before stretched()).
        # At scale 1 both products are exact, so the nominal screen's points are unchanged.
        x = (u_x_m * sx if sx != 1.0 else u_x_m) - 0.5 * (self.width_m * sx)
        y = (u_y_m * sy if sy != 1.0 else u_y_m) - 0.5 * (self.height_m * sy)
        return np.stack([r[i, 0] * x + r[i, 1] * y + t[i] for i in range(3)])

    def centre_camera(self) -> np.ndarray:
        """The screen centre in the camera frame, metres."""
        return self.screen_to_camera.translation.copy()

    def moved(self, delta: Pose) -> "FlatScreen":
        """The screen moved by *delta* about and along its own axes through its centre (its frame's origin)."""
        return replace(self, screen_to_camera=self.screen_to_camera.compose(delta))

    def stretched(self, axis: str, factor: float) -> "FlatScreen":
        """The screen with the pitch of *axis* ("x" or "y") scaled by *factor* about its centre; positions
        are still counted over the nominal width and height (they come from the fringes)."""
        i = _check_stretch(axis, factor)
        scale = list(self.pitch_scale)
        scale[i] = scale[i] * factor
        return replace(self, pitch_scale=(float(scale[0]), float(scale[1])))


class InterpolatedScreen:
    """A measured screen shape: a grid of screen positions with the 3-D point each one lies at.

    For projection screens and other displays that are not a flat rectangle of known pitch (OpenCSP's
    "distorted" display models). Positions between grid nodes are interpolated linearly over the grid's
    triangulation; positions outside it give NaN (those pixels are dropped and counted).

    Parameters
    ----------
    width_m, height_m : float
        Extents the fringe periods span (the unit of the positions; 1.0 for fractional screens).
    nodes_uv : (M, 2) array
        Grid positions (u_x, u_y), in the units of width_m/height_m.
    nodes_screen_m : (M, 3) array
        The screen-frame points of the nodes, metres (z = 0 for a flat but distorted image).
    screen_to_camera : Pose
    centre_screen_m : (3,) array
        The range finder's origin in the screen frame, metres.
    v_from_top : bool
        The grid's second coordinate counts from the top edge (height - u_y), as in OpenCSP's display
        models. The grid is triangulated in its own coordinates, so where a grid cell's two diagonals are
        equally good the interpolation matches the program that measured it.
    modes_m : (K, M, 3) array, optional
        The measured shape's independent uncertainty fields (every node's displacement at one standard
        deviation of each, screen frame, metres): :meth:`displaced` moves the shape along one.
    split : (rows, columns) bool array, optional
        :attr:`split` of a screen on the same grid positions (e.g. kept in the station's cache): the
        triangulation is then not built (nor scipy's interpolation loaded).
    """

    def __init__(self, width_m: float, height_m: float, nodes_uv: np.ndarray, nodes_screen_m: np.ndarray,
                 screen_to_camera: Pose, centre_screen_m=(0.0, 0.0, 0.0), v_from_top: bool = False,
                 modes_m: np.ndarray | None = None, split: np.ndarray | None = None):
        nodes_uv = np.asarray(nodes_uv, np.float64)
        nodes_screen_m = np.asarray(nodes_screen_m, np.float64)
        if nodes_uv.ndim != 2 or nodes_uv.shape[1] != 2 or nodes_screen_m.shape != (nodes_uv.shape[0], 3):
            raise ValueError(f"need (M, 2) grid positions and (M, 3) points, got {nodes_uv.shape} and "
                             f"{nodes_screen_m.shape}")
        if nodes_uv.shape[0] < 3 or not (np.all(np.isfinite(nodes_uv)) and np.all(np.isfinite(nodes_screen_m))):
            raise ValueError("the screen model needs at least 3 finite grid nodes")
        self.width_m, self.height_m = float(width_m), float(height_m)
        self.screen_to_camera = screen_to_camera
        self._nodes_uv, self._nodes_screen = nodes_uv, nodes_screen_m
        self._interp_built = None
        self._centre = np.asarray(centre_screen_m, np.float64)
        self._v_from_top = bool(v_from_top)
        self._modes = (np.zeros((0,) + nodes_screen_m.shape) if modes_m is None
                       else np.asarray(modes_m, np.float64).reshape(-1, *nodes_screen_m.shape))
        self._grid = self._as_grid(nodes_uv, nodes_screen_m, split)

    @property
    def _interp(self):
        """scipy's linear interpolation over the grid's triangulation, built when first needed (a screen
        whose grid split is known, :attr:`split`, never needs it)."""
        if self._interp_built is None:
            # lazy: scipy.interpolate, ~620 ms CPU; config.py loads this at every start
            from scipy.interpolate import LinearNDInterpolator

            self._interp_built = LinearNDInterpolator(self._nodes_uv, self._nodes_screen)
        return self._interp_built

    @property
    def split(self) -> np.ndarray | None:
        """Per grid cell (rows by columns of the grid), whether the triangulation splits it along its main
        diagonal (None when the nodes are not a full rectangular grid): it depends on the grid positions
        alone, so a screen of the same positions (another shape, or this one stretched or displaced)
        built with it skips the triangulation."""
        return None if self._grid is None else self._grid[3]

    def _as_grid(self, nodes_uv: np.ndarray, nodes_screen_m: np.ndarray, split: np.ndarray | None = None):
        """For nodes on a full rectangular grid (OpenCSP's display models): the grid and, per cell, which
        diagonal the triangulation split it along, so that :meth:`points_camera` finds a position's cell
        directly (a compiled kernel) instead of walking the triangulation (a tenth of the time), with the
        same triangles. None when the nodes are not such a grid, or the two disagree (then scipy's). With
        *split* (:attr:`split` of a screen on the same grid positions) the triangulation is not built."""
        xs, ys = np.unique(nodes_uv[:, 0]), np.unique(nodes_uv[:, 1])
        if xs.size < 2 or ys.size < 2 or xs.size * ys.size != nodes_uv.shape[0]:
            return None
        row, col = np.searchsorted(ys, nodes_uv[:, 1]), np.searchsorted(xs, nodes_uv[:, 0])
        grid = np.full((ys.size, xs.size, 3), np.nan)
        grid[row, col] = nodes_screen_m
        if not np.all(np.isfinite(grid)):
            return None
        if split is not None:
            split = np.asarray(split, dtype=bool)
            if split.shape != (ys.size - 1, xs.size - 1):
                raise ValueError(f"a grid split of shape {split.shape} for a grid of {ys.size - 1} x "
                                 f"{xs.size - 1} cells")
            return xs, ys, grid, split
        # the triangle holding a point at (0.2, 0.6) of each cell has both ends of the main diagonal or not
        gx, gy = np.meshgrid(xs[:-1] + 0.2 * np.diff(xs), ys[:-1] + 0.6 * np.diff(ys))
        tri = self._interp.tri
        simplex = tri.find_simplex(np.column_stack([gx.ravel(), gy.ravel()]))
        if np.any(simplex < 0):
            return None
        jj, ii = np.meshgrid(np.arange(ys.size - 1), np.arange(xs.size - 1), indexing="ij")
        node = np.full((ys.size, xs.size), -1)
        node[row, col] = np.arange(nodes_uv.shape[0])
        verts = tri.simplices[simplex]
        first, last = node[jj, ii].ravel(), node[jj + 1, ii + 1].ravel()
        main = (np.any(verts == first[:, None], axis=1) & np.any(verts == last[:, None], axis=1)).reshape(jj.shape)
        out = (xs, ys, grid, main)
        # check against the triangulation at points all over the grid
        rng = np.random.default_rng(0)
        probe = np.column_stack([rng.uniform(xs[0], xs[-1], 4000), rng.uniform(ys[0], ys[-1], 4000)])
        mine = grid_screen_points(probe[:, 0], probe[:, 1], *out, np.eye(3), np.zeros(3))
        if not np.allclose(mine.T, self._interp(probe), rtol=0.0, atol=1e-12):
            return None
        return out

    def points_camera(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        v = np.asarray(u_y_m, np.float64)
        if self._v_from_top:
            v = self.height_m - v
        r, t = self.screen_to_camera.rotation, self.screen_to_camera.translation
        if self._grid is not None:
            return grid_screen_points(np.asarray(u_x_m, np.float64), v, *self._grid, r, t)
        pts = self._interp(np.column_stack([np.asarray(u_x_m, np.float64), v]))
        return np.stack([r[i, 0] * pts[:, 0] + r[i, 1] * pts[:, 1] + r[i, 2] * pts[:, 2] + t[i] for i in range(3)])

    def centre_camera(self) -> np.ndarray:
        return self.screen_to_camera.apply(self._centre)

    def moved(self, delta: Pose) -> "InterpolatedScreen":
        """The screen moved by *delta* about and along its own axes through its centre (``centre_screen_m``):
        its pose composed with the motion conjugated to the centre. The grid is shared, not rebuilt."""
        c = self._centre
        if np.any(c != 0.0):
            to_centre, back = Pose(np.eye(3), c), Pose(np.eye(3), -c)
            delta = to_centre.compose(delta).compose(back)
        out = copy.copy(self)
        out.screen_to_camera = self.screen_to_camera.compose(delta)
        return out

    def stretched(self, axis: str, factor: float) -> "InterpolatedScreen":
        """The screen with its measured shape scaled by *factor* along *axis* ("x" or "y" of the screen
        frame) about its centre: every node's coordinate on that axis *factor* times as far from the
        centre. For a measured grid the screen positions are fractions of the displayed image and exact
        by construction; what a pitch uncertainty stands for is the scale of the shape measurement (its
        photogrammetry) along that axis. On a flat screen's own grid this is the flat screen's
        :meth:`FlatScreen.stretched`."""
        i = _check_stretch(axis, factor)
        nodes = self._nodes_screen.copy()
        nodes[:, i] = self._centre[i] + (nodes[:, i] - self._centre[i]) * factor
        return InterpolatedScreen(self.width_m, self.height_m, self._nodes_uv, nodes, self.screen_to_camera,
                                  self._centre, self._v_from_top, self._modes, split=self.split)

    @property
    def n_modes(self) -> int:
        """How many independent uncertainty fields the measured shape carries."""
        return int(self._modes.shape[0])

    def displaced(self, mode: int, factor: float) -> "InterpolatedScreen":
        """The shape moved along its uncertainty field *mode* by *factor* standard deviations (the nodes
        displaced; the pose kept)."""
        nodes = self._nodes_screen + float(factor) * self._modes[int(mode)]
        return InterpolatedScreen(self.width_m, self.height_m, self._nodes_uv, nodes, self.screen_to_camera,
                                  self._centre, self._v_from_top, self._modes, split=self.split)

    def fingerprint(self) -> str:
        """A short hash of the measured shape (grid, points, centre, extents): what cached sensitivities
        computed with this screen depend on besides the pose."""
        h = hashlib.sha256()
        for a in (self._nodes_uv, self._nodes_screen, self._centre, self._modes,
                  np.array([self.width_m, self.height_m, float(self._v_from_top)])):
            h.update(np.ascontiguousarray(a, np.float64).tobytes())
        return h.hexdigest()[:16]
