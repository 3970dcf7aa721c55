"""The facet in the station: which screen point every camera pixel sees in the true facet, traced once.

Frames (see :mod:`sofast_station.geometry`): camera (OpenCV), screen (metres, origin at the active area's
centre, +z toward the facet), fixture (the design's nominal facet frame) and the *true facet frame*, where
the facet really is: ``x_fixture = R (x_facet - P_mid) + P_mid + t`` (:class:`TrueFacet`). The trace works
in the true facet frame.

Screen coordinates (docs/conventions.md#screen-positions): ``u_x`` in [0, W) metres from the left
edge, ``u_y`` in [0, H) from the bottom edge; display column c is centred at ``u_x = (c + 1/2) pitch``, row r (0 = top)
at ``u_y = H - (r + 1/2) pitch``; screen-frame ``x = u_x - W/2``, ``y = u_y - H/2``.

:class:`FacetTrace` is the geometry of one facet in the station and nothing else: no display, no light, no
sensor (:mod:`sofast_station.twin.render` and :mod:`sofast_station.twin.sensor` form the frames from it).
"""

from __future__ import annotations

import copy
import math
import time

import numpy as np

from ..errors import GeometryError
from ..facet import FacetDesign
from ..geometry import Pose, StationGeometry
from . import edges
from .camera import TwinCamera
from .outline import signed_distance_to_outline
from .parameters import TrueFacet, TwinOptics
from .surface import TrueSurface

#: What a trace leaves per seen pixel (in the order of :attr:`FacetTrace.seen_idx`): what a merged trace must
#: give (:meth:`FacetTrace.merged`). ``hit_range_m`` is the distance from the camera centre to the hit.
TRACE_ARRAYS = ("x_facet_m", "hit_range_m", "slope", "u_scr_m", "path_m", "on_screen", "footprint_u_scr_m")

#: :meth:`FacetTrace.with_facet` keeps the traced outline while the new shape moves its image by less than
#: this, pixels: a fifth of the corner location's standard uncertainty ([uncertainty] corner_px = 0.1 px).
MAX_KEPT_EDGE_SHIFT_PX = 0.02


def rotation_zyx(rx_rad: float, ry_rad: float, rz_rad: float) -> np.ndarray:
    """Rotation matrix R = R_z(rz) R_y(ry) R_x(rx), angles in radians."""
    cx, sx = math.cos(rx_rad), math.sin(rx_rad)
    cy, sy = math.cos(ry_rad), math.sin(ry_rad)
    cz, sz = math.cos(rz_rad), math.sin(rz_rad)
    r_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    r_y = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    r_z = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    return r_z @ r_y @ r_x


def facet_to_fixture_pose(facet: TrueFacet, design: FacetDesign) -> Pose:
    """The true facet frame's placement in the fixture frame (:class:`TrueFacet` placement rule)."""
    cx, cy = (float(c) for c in design.centroid_m)
    p_mid_facet = np.array([cx, cy, float(design.z(cx, cy))])
    r_facet_fix = rotation_zyx(*(1e-3 * np.array(facet.placement_mrad)))
    t_fix_m = 1e-3 * np.array(facet.placement_mm)
    return Pose(r_facet_fix, p_mid_facet - r_facet_fix @ p_mid_facet + t_fix_m)


def _unit_normals(zx: np.ndarray, zy: np.ndarray) -> np.ndarray:
    """Unit normals (n, 3) of a surface of slopes (zx, zy): (-zx, -zy, 1) normalised."""
    normal = np.column_stack([-zx, -zy, np.ones_like(zx)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return normal


class FacetTrace:
    """The true facet seen by the station's camera: every camera pixel centre traced to the screen.

    Construction traces the pixel centres of the facet's window: intersection with the true surface (first
    hit from the camera), the outline test (true facet frame), reflection about the exact true normal, and
    the screen point. The optics' edge model (:mod:`sofast_station.twin.edges`: exact area, centre-ray point
    or sub-ray grid sampling, a bevelled rim) gives each pixel its facet coverage; edge pixels keep their
    centre ray's screen point (the analytic surface continues past the outline), and a pixel on a bevelled
    rim also sees the screen point its rim reflects.

    Parameters
    ----------
    geometry : StationGeometry
        Camera intrinsics, screen, and the true camera/screen/fixture poses.
    design : FacetDesign
        The facet design (outline, centroid, measure point).
    facet : TrueFacet
        The true shape and placement.
    optics : TwinOptics
        Only its edge model is read (``edge_sampling``, ``edge_grid``, ``bevel_*``; see
        :mod:`sofast_station.twin.edges`).
    edge_band_px : float
        Half-width of the band around the outline's image whose pixels ``edge_sampling = "grid"``
        supersamples, pixels (at least 1).
    screen_shape : TrueScreen, optional
        The panel as it really is (:mod:`sofast_station.twin.assembly`); a flat screen of the stated pitch by
        default.

    Attributes
    ----------
    camera : TwinCamera
    surface : TrueSurface
    facet_to_fixture, facet_to_camera, facet_to_screen, camera_to_facet, screen_to_facet : Pose
        Where the true facet frame lies relative to the others.
    coverage : (H, W) array
        Fraction of each pixel's area the facet covers (the rim included).
    rim_coverage : (H, W) array
        Fraction of each pixel's area on the bevelled rim (zero without one).
    seen_idx : (n,) int array
        Flat image indices of the pixels that see the facet (coverage > 0), increasing.
    x_facet_m, hit_range_m, slope, u_scr_m, path_m, on_screen : arrays of n rows
        Per seen pixel (:data:`TRACE_ARRAYS`): the centre ray's hit on the true surface (true facet frame,
        metres), its distance from the camera centre (m), the exact slopes (dz/dx, dz/dy) there, the screen
        point (u_x, u_y) metres it reflects to, the path from the hit to the screen (m, NaN when the
        reflected ray misses the screen plane), and whether it lands on the active area.
    footprint_u_scr_m : (n, m, 2) array
        The screen points (u_x, u_y) metres of each seen pixel's m = n x n sub-rays (n ``optics.screen_grid``,
        a regular grid over the pixel, reflected about the true surface's exact normals; NaN where one misses
        the screen plane, :meth:`_footprint`): the pixel's footprint on the screen, whose display light the
        renderer averages. With ``screen_grid = 1`` it is :attr:`u_scr_m` (m = 1, a view).
    d_in_facet : (n, 3) array
        The centre rays' unit directions, true facet frame.
    rim_pos, rim_fraction, rim_u_scr_m : arrays
        The seen pixels (positions in ``seen_idx``) on a bevelled rim, the share of their facet area on it,
        and the screen point the rim reflects.
    trace_seconds : float
        Wall time of the trace, seconds.
    """

    def __init__(self, geometry: StationGeometry, design: FacetDesign, facet: TrueFacet = TrueFacet(),
                 optics: TwinOptics = TwinOptics(), edge_band_px: float = 2.0, screen_shape=None):
        if not edge_band_px >= 1.0:
            raise GeometryError(f"edge_band_px must be at least 1 pixel, got {edge_band_px}")
        self.geometry = geometry
        self.screen_shape = screen_shape
        self.design = design
        self.facet = facet
        self.optics = optics
        self.edge_band_px = float(edge_band_px)
        self.camera = TwinCamera(geometry.camera)
        self.surface = TrueSurface(facet, design)
        self._place(facet)
        start = time.perf_counter()
        self._trace()
        self.trace_seconds = time.perf_counter() - start

    def _place(self, facet: TrueFacet) -> None:
        self.facet_to_fixture = facet_to_fixture_pose(facet, self.design)
        self.facet_to_camera = self.geometry.fixture_to_camera.compose(self.facet_to_fixture)
        self.camera_to_facet = self.facet_to_camera.inverse()
        self.screen_to_facet = self.camera_to_facet.compose(self.geometry.screen_to_camera)
        self.facet_to_screen = self.screen_to_facet.inverse()

    @classmethod
    def merged(cls, geometry: StationGeometry, coverage: np.ndarray, seen_idx: np.ndarray, arrays: dict,
               optics: TwinOptics = TwinOptics()) -> "FacetTrace":
        """The picture several traces make together (:mod:`sofast_station.twin.heliostat`): *coverage* (H, W),
        the seen pixels' flat indices *seen_idx*, and each of :data:`TRACE_ARRAYS` for them, in that order.

        It has no facet of its own (``design``, ``facet``, ``surface`` and the poses are None) and no bevelled
        rim (a heliostat's twin refuses optics with one)."""
        trace = cls.__new__(cls)
        trace.geometry, trace.screen_shape, trace.optics = geometry, None, optics
        trace.design = trace.facet = trace.surface = None
        trace.facet_to_fixture = trace.facet_to_camera = trace.camera_to_facet = None
        trace.screen_to_facet = trace.facet_to_screen = None
        trace.camera = TwinCamera(geometry.camera)
        trace.edge_band_px = 2.0
        trace.coverage = coverage
        trace.seen_idx = seen_idx
        for name in TRACE_ARRAYS:
            setattr(trace, name, arrays[name])
        trace.d_in_facet = None
        trace.rim_pos = np.zeros(0, dtype=np.int64)
        trace.rim_fraction = np.zeros(0)
        trace.rim_u_scr_m = np.empty((0, 2))
        trace.rim_coverage = np.zeros(coverage.shape, dtype=np.float64)
        trace.trace_seconds = 0.0
        return trace

    # ------------------------------------------------------------------ trace
    def _facet_window(self) -> tuple[int, int, int, int]:
        """Image window (u0, u1, v0, v1), inclusive, that holds the facet's image and its edge band.

        The bounding box of the projected outline (densely sampled on the true surface), widened by the
        edge band plus a few pixels; the whole image if the outline does not project (behind the camera).
        """
        height, width = self.geometry.camera.shape
        corners = self.design.outline_m
        steps = np.linspace(0.0, 1.0, 512, endpoint=False)[:, None]
        xy = np.concatenate([c0 + steps * (c1 - c0) for c0, c1 in zip(corners, np.roll(corners, -1, axis=0))])
        boundary_facet = np.column_stack([xy, self.surface.height(xy[:, 0], xy[:, 1])])
        uv = self.camera.project(self.facet_to_camera.apply(boundary_facet))
        if not np.all(np.isfinite(uv)):
            return 0, width - 1, 0, height - 1
        pad = self.edge_band_px + 4.0
        u0 = int(np.clip(np.floor(uv[:, 0].min() - pad), 0, width - 1))
        u1 = int(np.clip(np.ceil(uv[:, 0].max() + pad), 0, width - 1))
        v0 = int(np.clip(np.floor(uv[:, 1].min() - pad), 0, height - 1))
        v1 = int(np.clip(np.ceil(uv[:, 1].max() + pad), 0, height - 1))
        return u0, u1, v0, v1

    def _trace(self) -> None:
        """Trace the pixel centres of the facet's window; fill the coverage and per-seen-pixel arrays."""
        height, width = self.geometry.camera.shape
        n_px = height * width
        v_cam_facet = self.camera_to_facet.translation
        u0, u1, v0, v1 = self._facet_window()
        win_h, win_w = v1 - v0 + 1, u1 - u0 + 1
        u_px, v_px = np.meshgrid(np.arange(u0, u1 + 1, dtype=np.float64), np.arange(v0, v1 + 1, dtype=np.float64))
        pixel_idx = (v_px.astype(np.int64) * width + u_px.astype(np.int64)).ravel()     # full-image flat index
        rays_facet = self.camera_to_facet.apply_vector(self.camera.pixel_rays(u_px.ravel(), v_px.ravel()))

        # Quadratic part first: where does each ray land, and how big is a pixel there (metres)?
        t0 = self.surface.paraboloid_hits(v_cam_facet, rays_facet)
        x0 = (v_cam_facet[0] + t0 * rays_facet[:, 0]).reshape(win_h, win_w)
        y0 = (v_cam_facet[1] + t0 * rays_facet[:, 1]).reshape(win_h, win_w)
        footprint_m = np.full((win_h, win_w), np.nan)
        if win_h > 1 and win_w > 1:
            dx_du, dx_dv = np.gradient(x0, axis=1), np.gradient(x0, axis=0)
            dy_du, dy_dv = np.gradient(y0, axis=1), np.gradient(y0, axis=0)
            footprint_m = np.maximum(np.hypot(dx_du, dy_du), np.hypot(dx_dv, dy_dv))
        footprint_m = footprint_m.ravel()
        x0, y0 = x0.ravel(), y0.ravel()

        # Candidates: inside the outline or within the edge band (+1 px for the shape terms' shift).
        reach_m = (self.edge_band_px + 1.0) * footprint_m
        lo = self.design.outline_m.min(axis=0)
        hi = self.design.outline_m.max(axis=0)
        with np.errstate(invalid="ignore"):
            near = np.isfinite(t0) & np.isfinite(footprint_m) \
                & (x0 > lo[0] - reach_m) & (x0 < hi[0] + reach_m) & (y0 > lo[1] - reach_m) & (y0 < hi[1] + reach_m)
        near_idx = np.flatnonzero(near)
        sd0 = signed_distance_to_outline(x0[near_idx], y0[near_idx], self.design.outline_m)
        rel_pos = near_idx[sd0 < reach_m[near_idx]]          # positions in the window
        rel_idx = pixel_idx[rel_pos]                          # full-image flat indices

        # Full surface for the candidates.
        d_rel = rays_facet[rel_pos]
        t_rel = self.surface.intersect(v_cam_facet, d_rel)
        x_rel = v_cam_facet + t_rel[:, None] * d_rel
        # The edge model (twin/edges.py): each pixel's facet coverage, and the part of it on a bevelled rim.
        coverage_rel, rim_rel = edges.pixel_coverage(self, rel_idx, x_rel, footprint_m[rel_pos], self.edge_band_px)

        coverage = np.zeros(n_px)
        coverage[rel_idx] = coverage_rel
        self.coverage = coverage.reshape(height, width)
        seen = coverage_rel > 0
        self.seen_idx = rel_idx[seen]
        x_facet = x_rel[seen]
        d_in_facet = d_rel[seen]
        self.hit_range_m = t_rel[seen]        # (a heliostat's traces are merged by the nearest hit)

        # Reflection about the exact true normal, then the screen plane.
        _, zx, zy = self.surface.height_and_slopes(x_facet[:, 0], x_facet[:, 1])
        normal = _unit_normals(zx, zy)
        self.x_facet_m = x_facet
        self.d_in_facet = d_in_facet
        self.slope = np.column_stack([zx, zy])
        self.u_scr_m, self.path_m, self.on_screen = self.reflect_to_screen(x_facet, d_in_facet, normal)
        self.footprint_u_scr_m = self._footprint(self.surface, self.u_scr_m)

        # A bevelled rim: its part of a pixel reflects about the rim's tilted normal, elsewhere on the screen.
        rim = rim_rel[seen] / coverage_rel[seen]
        self.rim_pos = np.flatnonzero(rim > 0)
        self.rim_fraction = rim[self.rim_pos]
        self.rim_u_scr_m = np.empty((0, 2))
        if self.rim_pos.size:
            at = self.rim_pos
            outward = edges.rim_distance_and_direction(x_facet[at, 0], x_facet[at, 1], self.design.outline_m)[1]
            tilted = edges.tilt_normals(normal[at], outward, 1e-3 * self.optics.bevel_tilt_mrad)
            self.rim_u_scr_m = self.reflect_to_screen(x_facet[at], d_in_facet[at], tilted)[0]
        rim_image = np.zeros(n_px)
        rim_image[self.seen_idx[self.rim_pos]] = coverage_rel[seen][self.rim_pos] * self.rim_fraction
        self.rim_coverage = rim_image.reshape(height, width)

    def _footprint(self, surface: TrueSurface, u_scr_m: np.ndarray) -> np.ndarray:
        """The seen pixels' footprints on the screen (:attr:`footprint_u_scr_m`) on *surface*: the screen
        points of ``screen_grid`` x ``screen_grid`` sub-rays per pixel, or the centre rays' *u_scr_m* when 1.

        A camera pixel integrates the display over its footprint: at 4 m from a 1.1 mm pitch screen, a pixel
        of the population's 400 x 300 camera covers about ten display pixels, and sampling the display at the
        centre ray's point alone sees the display's pixel steps and the fringes' rounding at full depth.

        The rays through a half-pixel lattice (each pixel's corners, the middles of its sides and its centre:
        neighbours share all but the centre) are traced to the true surface, reflected about its exact normal
        there and followed to the screen; a sub-ray's screen point is their biquadratic (Lagrange)
        interpolation, exact for a screen map that is quadratic over the pixel. Tracing every sub-ray cost
        1.8 s for a station of 49,000 seen pixels at 4 x 4, the lattice 0.4 s; the pixel's own corners alone
        (bilinear) put the footprint's centroid three times as far from its centre as it is (the map's
        curvature), 56 instead of 21 um of position error on a drawn heliostat station."""
        n = self.optics.screen_grid
        if n <= 1:
            return u_scr_m[:, None, :]
        width = self.geometry.camera.width_px
        v_px, u_px = np.divmod(self.seen_idx, width)
        # node (i, j) of the lattice is the image point (i / 2 - 1/2, j / 2 - 1/2): pixel (u, v)'s nine are
        # i = 2u + (0, 1, 2), j = 2v + (0, 1, 2)
        lattice_w = 2 * width + 1
        steps = np.arange(3)
        node_ids = ((2 * v_px[None, None, :] + steps[:, None, None]) * lattice_w
                    + 2 * u_px[None, None, :] + steps[None, :, None]).reshape(9, -1)     # (j, i) -> 3 j + i
        rim = np.arange(9) != 4                   # the centre (node 4) is the centre ray, traced already
        unique, which = np.unique(node_ids[rim], return_inverse=True)
        n_v, n_u = np.divmod(unique, lattice_w)
        v_cam_facet = self.camera_to_facet.translation
        d_in = self.camera_to_facet.apply_vector(self.camera.pixel_rays(0.5 * n_u - 0.5, 0.5 * n_v - 0.5))
        t = surface.intersect(v_cam_facet, d_in)
        x_facet = v_cam_facet + t[:, None] * d_in
        _, zx, zy = surface.height_and_slopes(x_facet[:, 0], x_facet[:, 1])
        node_scr = np.empty((9, self.seen_idx.size, 2))                                       # (9, n, 2)
        node_scr[rim] = self.reflect_to_screen(x_facet, d_in, _unit_normals(zx, zy))[0][which.reshape(8, -1)]
        node_scr[4] = u_scr_m
        out = np.empty((self.seen_idx.size, n * n, 2))
        for k, (du, dv) in enumerate(edges.grid_offsets(n)):
            # quadratic Lagrange weights on the nodes -1/2, 0, +1/2 of each axis
            wu = np.array([2 * du * (du - 0.5), 1 - 4 * du * du, 2 * du * (du + 0.5)])
            wv = np.array([2 * dv * (dv - 0.5), 1 - 4 * dv * dv, 2 * dv * (dv + 0.5)])
            out[:, k] = np.tensordot(np.outer(wv, wu).ravel(), node_scr, axes=1)
        return out

    def reflect_to_screen(self, x_facet: np.ndarray, d_in_facet: np.ndarray, normal: np.ndarray):
        """Screen coordinates (u_x, u_y) metres, path length (m, NaN when the plane is missed) and whether
        it lands on the active area, of rays *d_in_facet* reflected at *x_facet* about unit *normal*."""
        d_out_facet = d_in_facet - 2.0 * np.sum(d_in_facet * normal, axis=1, keepdims=True) * normal
        x_scr = self.facet_to_screen.apply(x_facet)
        d_out_scr = self.facet_to_screen.apply_vector(d_out_facet)
        screen = self.geometry.screen
        if self.screen_shape is None:
            with np.errstate(invalid="ignore", divide="ignore"):
                path_m = -x_scr[:, 2] / d_out_scr[:, 2]
            hits_plane = np.isfinite(path_m) & (path_m > 0)
            path_m = np.where(hits_plane, path_m, np.nan)
            t_scr = x_scr + path_m[:, None] * d_out_scr
            u_scr_m = np.column_stack([t_scr[:, 0] + 0.5 * screen.width_m, t_scr[:, 1] + 0.5 * screen.height_m])
        else:
            # the panel as it really is: positions in the stated pitch's metres, as the fringes encode them
            path_m, u_scr_m = self.screen_shape.trace(x_scr, d_out_scr)
            hits_plane = np.isfinite(path_m)
        with np.errstate(invalid="ignore"):
            on_screen = hits_plane & (u_scr_m[:, 0] >= 0) & (u_scr_m[:, 0] < screen.width_m) \
                & (u_scr_m[:, 1] >= 0) & (u_scr_m[:, 1] < screen.height_m)
        return u_scr_m, path_m, on_screen

    # ------------------------------------------------------------- the next facet
    def with_facet(self, facet: TrueFacet) -> "FacetTrace":
        """The trace of another facet in the fixture (a production line's next facet).

        With the placement unchanged, only the shape differs by micrometres: every pixel that saw the
        facet is intersected again with the new surface (Newton from its old hit, to 1e-12 m), reflected
        about the new exact normal and followed to the screen; the facet's outline in the image, and so
        each edge pixel's coverage, is kept (the returned trace shares :attr:`coverage`, :meth:`keeps_outline`).
        A new trace would move the outline's image by less than :data:`MAX_KEPT_EDGE_SHIFT_PX` (bounded
        here: the largest height change along the outline times the steepest ray there, over the pixel's
        footprint); beyond that, with another placement, or with a bevelled rim (whose pixels reflect
        twice), the facet is traced anew. Shares the unchanged read-only arrays.
        """
        if facet.placement_mm != self.facet.placement_mm or facet.placement_mrad != self.facet.placement_mrad \
                or self.rim_pos.size:
            return self._traced_anew(facet)
        surface = TrueSurface(facet, self.design)
        if self._edge_shift_px(surface) > MAX_KEPT_EDGE_SHIFT_PX:
            return self._traced_anew(facet)
        trace = copy.copy(self)
        trace.facet, trace.surface = facet, surface
        start = time.perf_counter()
        d_in = self.d_in_facet
        v_cam = self.camera_to_facet.translation
        t_old = np.einsum("ij,ij->i", self.x_facet_m - v_cam, d_in)
        t_new = surface.intersect(v_cam, d_in, start_m=t_old)
        x_facet = v_cam + t_new[:, None] * d_in
        _, zx, zy = surface.height_and_slopes(x_facet[:, 0], x_facet[:, 1])
        normal = _unit_normals(zx, zy)
        trace.x_facet_m = x_facet
        trace.slope = np.column_stack([zx, zy])
        trace.u_scr_m, trace.path_m, trace.on_screen = trace.reflect_to_screen(x_facet, d_in, normal)
        trace.footprint_u_scr_m = trace._footprint(surface, trace.u_scr_m)
        trace.trace_seconds = time.perf_counter() - start
        return trace

    def keeps_outline(self, other: "FacetTrace") -> bool:
        """Whether *other* (from :meth:`with_facet`) kept this trace's outline: the same pixels, the same
        coverage (so the same light off the facet, only other screen points)."""
        return other.coverage is self.coverage

    def _traced_anew(self, facet: TrueFacet) -> "FacetTrace":
        return FacetTrace(self.geometry, self.design, facet, self.optics, edge_band_px=self.edge_band_px,
                          screen_shape=self.screen_shape)

    def _edge_shift_px(self, surface: TrueSurface) -> float:
        """How far, in pixels, the facet's outline would move in the image if this trace's surface became
        *surface* (first order: height change along the outline times the ray's tilt, over the footprint)."""
        corners = self.design.outline_m
        steps = np.linspace(0.0, 1.0, 256, endpoint=False)[:, None]
        xy = np.concatenate([c0 + steps * (c1 - c0) for c0, c1 in zip(corners, np.roll(corners, -1, axis=0))])
        z_old = self.surface.height(xy[:, 0], xy[:, 1])
        dz = np.abs(surface.height(xy[:, 0], xy[:, 1]) - z_old)
        ray = np.column_stack([xy, z_old]) - self.camera_to_facet.translation
        distance = np.linalg.norm(ray, axis=1)
        tilt = np.hypot(ray[:, 0], ray[:, 1]) / np.abs(ray[:, 2])
        footprint_m = distance / float(np.max(np.diag(self.geometry.camera.matrix)[:2]))
        return float(np.max(dz * tilt / footprint_m))

    # ------------------------------------------------------------- geometry
    def measured_distance_m(self) -> float:
        """Distance (m) from the true screen centre to the true surface point at ``design.measure_point_m``."""
        x, y = (float(c) for c in self.design.measure_point_m)
        point_facet = np.array([x, y, float(self.surface.height(x, y))])
        return float(np.linalg.norm(point_facet - self.screen_to_facet.translation))

    def corner_pixels(self) -> np.ndarray:
        """Image positions (N, 2) = (u, v) pixels of the true outline corners on the true surface."""
        xy = self.design.outline_m
        corners_facet = np.column_stack([xy, self.surface.height(xy[:, 0], xy[:, 1])])
        return self.camera.project(self.facet_to_camera.apply(corners_facet))

    def footprint_check(self, max_slope_error_mrad: float) -> dict:
        """Check that the facet's reflected footprint, widened for slope errors, lies on the screen.

        Each facet pixel's screen point is widened by ``2 * max_slope_error * path length`` (a slope error
        turns the reflected ray by twice its angle).

        Parameters
        ----------
        max_slope_error_mrad : float
            Largest slope error to allow for, mrad.

        Returns
        -------
        dict
            ``min_margin_m`` (smallest distance from a widened point to the screen edge, metres),
            ``max_widening_m`` and ``n_pixels``.

        Raises
        ------
        GeometryError
            If the facet is not in view, a reflected ray misses the screen plane, or the widened
            footprint leaves the screen.
        """
        if self.seen_idx.size == 0:
            raise GeometryError("the facet is not in the camera's view: check the layout and the facet placement")
        if not np.all(np.isfinite(self.path_m)):
            raise GeometryError(f"{int(np.sum(~np.isfinite(self.path_m)))} facet pixels reflect rays that never "
                                "reach the screen plane: the screen does not face the facet; check the layout")
        screen = self.geometry.screen
        widening_m = 2.0 * 1e-3 * float(max_slope_error_mrad) * self.path_m
        u_x, u_y = self.u_scr_m[:, 0], self.u_scr_m[:, 1]
        margins = {"left": u_x - widening_m, "right": screen.width_m - u_x - widening_m,
                   "bottom": u_y - widening_m, "top": screen.height_m - u_y - widening_m}
        worst_side = min(margins, key=lambda side: float(margins[side].min()))
        worst_m = float(margins[worst_side].min())
        if worst_m < 0:
            raise GeometryError(
                f"the facet's reflected footprint, widened by 2 x {max_slope_error_mrad} mrad x distance "
                f"(up to {1e3 * float(widening_m.max()):.1f} mm), leaves the screen by {1e3 * -worst_m:.1f} mm "
                f"at its {worst_side} edge: use a larger screen, move camera and screen closer together, "
                "or correct the layout distance")
        return {"min_margin_m": worst_m, "max_widening_m": float(widening_m.max()),
                "n_pixels": int(self.seen_idx.size)}

    def image(self, values: np.ndarray, fill, at: np.ndarray | None = None) -> np.ndarray:
        """Scatter per-seen-pixel *values* (or per pixel of ``seen_idx[at]``) into a read-only image-shaped
        array filled with *fill* elsewhere."""
        height, width = self.geometry.camera.shape
        extra = values.shape[1:]
        out = np.full((height * width,) + extra, fill, dtype=values.dtype)
        out[self.seen_idx if at is None else self.seen_idx[at]] = values
        out = out.reshape((height, width) + extra)
        out.setflags(write=False)
        return out
