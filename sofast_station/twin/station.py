"""The ray-traced station: which screen point every camera pixel sees in the facet, and the frames it takes.

Frames (see :mod:`sofast_station.geometry`): camera (OpenCV), screen (metres, origin at the active area's
centre, +z toward the facet), fixture (the design's nominal facet frame) and the *true facet frame*, where
the facet really is: ``x_fixture = R (x_facet - P_mid) + P_mid + t`` (:class:`TrueFacet`). The trace works
in the true facet frame.

Screen coordinates (docs/conventions.md#screen-positions): ``u_x`` in [0, W) metres from the left
edge, ``u_y`` in [0, H) from the bottom edge; display column c is centred at ``u_x = (c + 1/2) pitch``, row r (0 = top)
at ``u_y = H - (r + 1/2) pitch``; screen-frame ``x = u_x - W/2``, ``y = u_y - H/2``.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import weakref
from concurrent.futures import ThreadPoolExecutor
from functools import cached_property

import numpy as np

from ..errors import DisplayError, GeometryError
from ..facet import FacetDesign
from ..geometry import Pose, StationGeometry
from . import edges
from .camera import TwinCamera
from .noise import scratch_f32, standard_normal_f32
from .parameters import TrueFacet, TwinOptics
from .outline import signed_distance_to_outline
from .surface import TrueSurface

#: A captured frame is drawn and finished in blocks of rows of about this many pixels: a block's float32
#: working arrays (a few hundred kB each) stay in the core's cache between passes.
_BLOCK_PX = 96_000

#: What a trace leaves per seen pixel (in the order of ``_seen_idx``): what a merged trace must give
#: (:meth:`TwinStation.adopt_trace`). ``_hit_range_m`` is the distance from the camera centre to the hit.
TRACE_ARRAYS = ("_x_facet_m", "_hit_range_m", "_slope", "_u_scr_m", "_path_m", "_on_screen")

#: :meth:`TwinStation.with_facet` keeps the traced outline while the new shape moves its image by less than
#: this, pixels: a fifth of the corner location's standard uncertainty ([uncertainty] corner_px = 0.1 px).
MAX_KEPT_EDGE_SHIFT_PX = 0.02

#: The thread that finishes half of every captured frame (shared by all twins of the process).
_FINISHER: ThreadPoolExecutor | None = None
_FINISHER_LOCK = threading.Lock()


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


def rook_lattice(n: int) -> np.ndarray:
    """``n*n`` sub-pixel sample offsets in (-1/2, 1/2)^2, one per row and per column of an n^2 x n^2 grid.

    A rank-1 lattice ``((j + 1/2) / N, ((g j) mod N + 1/2) / N)``, N = n^2, with the generator g that
    maximises the smallest toroidal distance between samples. Every sample has its own column and row, so
    a nearly axis-aligned edge is located to 1/(2N) pixel (a plain n x n grid: 1/(2n)).

    Returns
    -------
    (N, 2) array of (du, dv) offsets, pixels.
    """
    count = n * n
    j = np.arange(count)
    best_g, best_d = 1, -1.0
    for g in range(1, count):
        if math.gcd(g, count) != 1:
            continue
        pts = np.column_stack([j, (g * j) % count]) / count
        diff = np.abs(pts[:, None, :] - pts[None, :, :])
        diff = np.minimum(diff, 1.0 - diff)
        dist = np.hypot(diff[..., 0], diff[..., 1])
        np.fill_diagonal(dist, np.inf)
        if dist.min() > best_d + 1e-12:
            best_g, best_d = g, float(dist.min())
    return np.column_stack([(j + 0.5) / count - 0.5, ((best_g * j) % count + 0.5) / count - 0.5])


class TwinStation:
    """Digital twin of the station: camera, LCD and the true facet, ray traced once, captured many times.

    Construction traces every camera pixel centre: intersection with the true surface (first hit from the
    camera), the outline test (true facet frame), reflection about the exact true normal, and the screen
    point. The optics' edge model (:mod:`sofast_station.twin.edges`: exact area, centre-ray point or
    sub-ray grid sampling, a bevelled rim) gives each pixel its facet coverage; edge pixels keep their
    centre ray's screen point (the analytic surface continues past the outline), and a pixel on a
    bevelled rim also sees the screen point its rim reflects. Display sampling indices and weights are
    precomputed, so :meth:`capture` is a few vector operations.

    Parameters
    ----------
    geometry : StationGeometry
        Camera intrinsics, screen, and the true camera/screen/fixture poses.
    design : FacetDesign
        The facet design (outline, centroid, measure point).
    facet : TrueFacet
        The true shape and placement.
    optics : TwinOptics
        Display, reflection, ambient, camera response, noise, vignetting, and the edge model
        (``edge_sampling``, ``edge_grid``, ``blur_px``, ``defocus_px``, ``bevel_*``; see
        :mod:`sofast_station.twin.edges`).
    edge_band_px : float
        Half-width of the band around the outline's image whose pixels ``edge_sampling = "grid"``
        supersamples, pixels (at least 1).
    trace_only : bool
        Only trace (no display sampling, no photometry): one facet of a picture that several traces make
        together (:class:`~sofast_station.twin.heliostat.TwinHeliostat`); it cannot capture.
    screen_shape : TrueScreen, optional
        The panel as it really is (bowed, twisted, another pitch: :mod:`sofast_station.twin.assembly`);
        a flat screen of the stated pitch by default. *geometry* then holds the stated screen (the units
        the fringes encode positions in) and the true poses.

    Attributes
    ----------
    camera : TwinCamera
    surface : TrueSurface
    facet_to_fixture, facet_to_camera, facet_to_screen, camera_to_facet, screen_to_facet : Pose
        Where the true facet frame lies relative to the others.
    gain_dn : float
        DN per unit radiance (fraction of white) at vignetting factor 1, at the reference exposure and gain 1.
    trace_seconds : float
        Wall time of the trace, seconds.
    """

    def __init__(self, geometry: StationGeometry, design: FacetDesign, facet: TrueFacet = TrueFacet(),
                 optics: TwinOptics = TwinOptics(), edge_band_px: float = 2.0, trace_only: bool = False,
                 screen_shape=None):
        if not edge_band_px >= 1.0:
            raise GeometryError(f"edge_band_px must be at least 1 pixel, got {edge_band_px}")
        self.geometry = geometry
        self.screen_shape = screen_shape
        self.design = design
        self.facet = facet
        self.optics = optics
        self.camera = TwinCamera(geometry.camera)
        self.surface = TrueSurface(facet, design)
        self.facet_to_fixture = facet_to_fixture_pose(facet, design)
        self.facet_to_camera = geometry.fixture_to_camera.compose(self.facet_to_fixture)
        self.camera_to_facet = self.facet_to_camera.inverse()
        self.screen_to_facet = self.camera_to_facet.compose(geometry.screen_to_camera)
        self.facet_to_screen = self.screen_to_facet.inverse()
        self._edge_band_px = float(edge_band_px)
        #: Display samples of the read-only images captured so far (id -> (weak reference, sample)).
        self._samples: dict = {}
        start = time.perf_counter()
        self._trace()
        if not trace_only:
            self._prepare_sampling()
            self._prepare_photometry()
        self.trace_seconds = time.perf_counter() - start

    def adopt_trace(self, coverage: np.ndarray, seen_idx: np.ndarray, arrays: dict) -> None:
        """Take the trace of another picture (several traces merged: :mod:`sofast_station.twin.heliostat`)
        and prepare the captures from it: *coverage* (H, W), the seen pixels' flat indices *seen_idx*, and
        each of :data:`TRACE_ARRAYS` for them, in that order."""
        self._coverage = coverage
        self._seen_idx = seen_idx
        for name in TRACE_ARRAYS:
            setattr(self, name, arrays[name])
        # a merged picture draws no bevelled rim (TwinHeliostat refuses an optics with one)
        self._rim_pos = np.zeros(0, dtype=np.int64)
        self._rim_fraction = np.zeros(0)
        self._rim_u_scr_m = np.empty((0, 2))
        self._rim_coverage = np.zeros(coverage.shape, dtype=np.float64)
        self._samples = {}
        self.__dict__.pop("_seen_box", None)
        for name in ("screen_position_m", "surface_point_facet_m", "slope_true", "on_screen",
                     "rim_screen_position_m"):
            self.__dict__.pop(name, None)
        self._prepare_sampling()
        self._prepare_photometry()

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
        pad = self._edge_band_px + 4.0
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
        reach_m = (self._edge_band_px + 1.0) * footprint_m
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
        coverage_rel, rim_rel = edges.pixel_coverage(self, rel_idx, x_rel, footprint_m[rel_pos], self._edge_band_px)

        coverage = np.zeros(n_px)
        coverage[rel_idx] = coverage_rel
        self._coverage = coverage.reshape(height, width)
        seen = coverage_rel > 0
        self._seen_idx = rel_idx[seen]
        x_facet = x_rel[seen]
        d_in_facet = d_rel[seen]
        self._hit_range_m = t_rel[seen]        # (a heliostat's traces are merged by the nearest hit)

        # Reflection about the exact true normal, then the screen plane.
        _, zx, zy = self.surface.height_and_slopes(x_facet[:, 0], x_facet[:, 1])
        normal = np.column_stack([-zx, -zy, np.ones_like(zx)])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        self._x_facet_m = x_facet
        self._d_in_facet = d_in_facet
        self._slope = np.column_stack([zx, zy])
        self._u_scr_m, self._path_m, self._on_screen = self._reflect_to_screen(x_facet, d_in_facet, normal)

        # A bevelled rim: its part of a pixel reflects about the rim's tilted normal, elsewhere on the screen.
        rim = rim_rel[seen] / coverage_rel[seen]
        self._rim_pos = np.flatnonzero(rim > 0)
        self._rim_fraction = rim[self._rim_pos]
        self._rim_u_scr_m = np.empty((0, 2))
        if self._rim_pos.size:
            at = self._rim_pos
            outward = edges.rim_distance_and_direction(x_facet[at, 0], x_facet[at, 1], self.design.outline_m)[1]
            tilted = edges.tilt_normals(normal[at], outward, 1e-3 * self.optics.bevel_tilt_mrad)
            self._rim_u_scr_m = self._reflect_to_screen(x_facet[at], d_in_facet[at], tilted)[0]
        rim_image = np.zeros(n_px)
        rim_image[self._seen_idx[self._rim_pos]] = coverage_rel[seen][self._rim_pos] * self._rim_fraction
        self._rim_coverage = rim_image.reshape(height, width)

    def _reflect_to_screen(self, x_facet: np.ndarray, d_in_facet: np.ndarray, normal: np.ndarray):
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

    # ------------------------------------------------------------- precompute
    def _prepare_sampling(self) -> None:
        """Bilinear sampling indices/weights into a zero-padded window of the display luminance.

        A pixel on a bevelled rim has a second set (``_rim_idx``, ``_rim_w``) for its rim's screen point;
        each set's weights carry its share of the pixel's facet area (and the rim's relative reflectance).
        """
        screen = self.geometry.screen
        pitch_x, pitch_y = screen.pitch_m, screen.pitch_y_m              # columns, rows (may differ)
        u_scr_m = np.concatenate([self._u_scr_m, self._rim_u_scr_m])
        with np.errstate(invalid="ignore"):
            col = u_scr_m[:, 0] / pitch_x - 0.5                       # continuous display column
            row = (screen.height_m - u_scr_m[:, 1]) / pitch_y - 0.5    # continuous display row
            good = np.isfinite(col) & np.isfinite(row) & (col > -1) & (col < screen.width_px) \
                & (row > -1) & (row < screen.height_px)
        col0 = np.floor(np.where(good, col, 0.0))
        row0 = np.floor(np.where(good, row, 0.0))
        frac_c = np.where(good, col - col0, 0.0)
        frac_r = np.where(good, row - row0, 0.0)
        pad_c = col0.astype(np.int64) + 1          # padded index: display index + 1 (0 = bezel)
        pad_r = row0.astype(np.int64) + 1
        if np.any(good):
            self._win_r0, self._win_r1 = int(pad_r[good].min()), int(pad_r[good].max()) + 1
            self._win_c0, self._win_c1 = int(pad_c[good].min()), int(pad_c[good].max()) + 1
        else:
            self._win_r0 = self._win_r1 = self._win_c0 = self._win_c1 = 0
        win_w = self._win_c1 - self._win_c0 + 1
        base = np.where(good, (pad_r - self._win_r0) * win_w + (pad_c - self._win_c0), 0)
        idx = np.stack([base, base + 1, base + win_w, base + win_w + 1]).astype(np.intp)
        weights = np.stack([(1 - frac_r) * (1 - frac_c), (1 - frac_r) * frac_c,
                            frac_r * (1 - frac_c), frac_r * frac_c])
        weights = np.where(good, weights, 0.0)
        n = self._u_scr_m.shape[0]
        if self._rim_pos.size:
            weights[:, self._rim_pos] *= 1.0 - self._rim_fraction
            weights[:, n:] *= self._rim_fraction * self.optics.bevel_reflectance
        self._sample_idx, self._rim_idx = idx[:, :n], idx[:, n:]
        self._sample_w, self._rim_w = weights[:, :n].astype(np.float32), weights[:, n:].astype(np.float32)

    def _prepare_photometry(self) -> None:
        """Vignetting, gain, and the per-pixel affine terms of the linear response."""
        optics = self.optics
        height, width = self.geometry.camera.shape
        self._vignetting = edges.vignetting_factor((height, width), self.camera.cx, self.camera.cy,
                                                   optics.vignetting, optics.vignetting_exponent)
        full = self._coverage >= 1.0
        some = self._coverage > 0
        vig_max = float(self._vignetting[full].max() if full.any()
                        else self._vignetting[some].max() if some.any() else 1.0)
        self.gain_dn = (optics.white_dn - optics.camera_offset_dn) / ((optics.reflectance + optics.ambient) * vig_max)
        scale = self.gain_dn * self._vignetting
        self._dn_base = (optics.camera_offset_dn
                         + scale * (1.0 - self._coverage) * optics.background).astype(np.float32)
        self._dn_per_ambient = (scale * self._coverage).astype(np.float32)
        self._dn_per_luminance = (self._dn_per_ambient.ravel()[self._seen_idx] * optics.reflectance).astype(np.float32)
        self._dark_sigmas: dict = {}        # gain -> noise deviation at the dark level (_dark_sigma)
        levels = np.arange(256, dtype=np.float64) / 255.0
        self._luminance_lut = (optics.display_floor
                               + (1.0 - optics.display_floor) * levels ** optics.display_gamma).astype(np.float32)

    def with_facet(self, facet: TrueFacet) -> "TwinStation":
        """The same station with another facet in the fixture (a production line's next facet).

        With the placement unchanged, only the shape differs by micrometres: every pixel that saw the
        facet is intersected again with the new surface (Newton from its old hit, to 1e-12 m), reflected
        about the new exact normal and followed to the screen; the facet's outline in the image, and so
        each edge pixel's coverage, is kept. A new trace would move the outline's image by less than
        :data:`MAX_KEPT_EDGE_SHIFT_PX` (bounded here: the largest height change along the outline times the
        steepest ray there, over the pixel's footprint); beyond that, with another placement, or with a
        bevelled rim (whose pixels reflect twice), the station is traced anew. Every figure of the twin's
        truth is the new surface's, exactly. Shares the unchanged read-only arrays.
        """
        if facet.placement_mm != self.facet.placement_mm or facet.placement_mrad != self.facet.placement_mrad \
                or self._rim_pos.size:
            return self._traced_anew(facet)
        surface = TrueSurface(facet, self.design)
        if self._edge_shift_px(surface) > MAX_KEPT_EDGE_SHIFT_PX:
            return self._traced_anew(facet)
        twin = copy.copy(self)
        twin.facet, twin.surface = facet, surface
        twin._samples = {}
        for name in ("screen_position_m", "surface_point_facet_m", "slope_true", "on_screen"):
            twin.__dict__.pop(name, None)
        start = time.perf_counter()
        d_in = self._d_in_facet
        v_cam = self.camera_to_facet.translation
        t_old = np.einsum("ij,ij->i", self._x_facet_m - v_cam, d_in)
        t_new = surface.intersect(v_cam, d_in, start_m=t_old)
        x_facet = v_cam + t_new[:, None] * d_in
        _, zx, zy = surface.height_and_slopes(x_facet[:, 0], x_facet[:, 1])
        normal = np.column_stack([-zx, -zy, np.ones_like(zx)])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        twin._x_facet_m = x_facet
        twin._slope = np.column_stack([zx, zy])
        twin._u_scr_m, twin._path_m, twin._on_screen = twin._reflect_to_screen(x_facet, d_in, normal)
        twin._prepare_sampling()
        twin.trace_seconds = time.perf_counter() - start
        return twin

    def _traced_anew(self, facet: TrueFacet) -> "TwinStation":
        return TwinStation(self.geometry, self.design, facet, self.optics, edge_band_px=self._edge_band_px,
                           screen_shape=self.screen_shape)

    def _edge_shift_px(self, surface: TrueSurface) -> float:
        """How far, in pixels, the facet's outline would move in the image if this station's surface became
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

    def with_optics(self, optics: TwinOptics) -> "TwinStation":
        """The same traced station with other optics (exposure, noise, display, blur, vignetting): no new trace.

        The returned station shares the trace's (read-only) arrays with this one. Optics whose edge model
        changes the trace (:data:`sofast_station.twin.edges.TRACE_FIELDS`: sampling, a bevelled rim) give a
        newly traced station.
        """
        if any(getattr(optics, name) != getattr(self.optics, name) for name in edges.TRACE_FIELDS):
            return TwinStation(self.geometry, self.design, self.facet, optics, edge_band_px=self._edge_band_px,
                               screen_shape=self.screen_shape)
        twin = copy.copy(self)
        twin.optics = optics
        twin._samples = {}                   # the display's response (luminance table) may differ
        twin._prepare_photometry()
        if optics.bevel_reflectance != self.optics.bevel_reflectance:
            twin._prepare_sampling()
        for name in ("screen_position_m", "surface_point_facet_m", "slope_true", "on_screen"):
            twin.__dict__.pop(name, None)
        return twin

    # ---------------------------------------------------------------- capture
    def sensor_scale(self, exposure_s: float | None = None, gain: float | None = None) -> float:
        """Signal multiplier of an exposure and gain relative to the reference (``white_dn`` holds at 1).

        Parameters
        ----------
        exposure_s : float or None
            Exposure time, seconds; None is ``optics.reference_exposure_s``.
        gain : float or None
            Linear gain factor; None is 1.

        Returns
        -------
        float
            ``(exposure_s / reference_exposure_s) * gain``.
        """
        exposure = self.optics.reference_exposure_s if exposure_s is None else float(exposure_s)
        g = 1.0 if gain is None else float(gain)
        if not (math.isfinite(exposure) and exposure > 0):
            raise DisplayError(f"exposure must be a positive time in seconds, got {exposure_s!r}")
        if not (math.isfinite(g) and g > 0):
            raise DisplayError(f"gain must be a positive factor, got {gain!r}")
        return exposure / self.optics.reference_exposure_s * g

    def flicker_factor(self, exposure_s: float | None = None, phase: float | None = None) -> float:
        """Mean backlight factor seen by an exposure starting at *phase* of a refresh period.

        The display's light is ``L (1 + m cos(2 pi (f t + phase)))`` (m ``optics.flicker_depth``, f
        ``optics.refresh_hz``); averaged over an exposure of T seconds it is
        ``1 + m (sin(2 pi (phase + f T)) - sin(2 pi phase)) / (2 pi f T)``: exactly 1 when f T is a whole
        number (within 1e-6 periods), otherwise off by up to ``m / (pi f T)`` depending on the phase.

        Parameters
        ----------
        exposure_s : float or None
            Exposure time, seconds (None: the reference exposure).
        phase : float or None
            Phase of the refresh cycle at the start of the exposure, in periods (0..1); None is 0.
        """
        o = self.optics
        exposure = o.reference_exposure_s if exposure_s is None else float(exposure_s)
        periods = exposure * o.refresh_hz
        if o.flicker_depth == 0 or (round(periods) >= 1 and abs(periods - round(periods)) < 1e-6):
            return 1.0
        p0 = 0.0 if phase is None else float(phase)
        two_pi = 2.0 * math.pi
        return 1.0 + o.flicker_depth * (math.sin(two_pi * (p0 + periods)) - math.sin(two_pi * p0)) / (two_pi * periods)

    def _display_sample(self, display_image: np.ndarray) -> np.ndarray:
        """Display luminance (fraction of white) bilinearly sampled at every seen pixel's screen point."""
        screen = self.geometry.screen
        image = np.asarray(display_image)
        if image.dtype != np.uint8 or image.shape != (screen.height_px, screen.width_px):
            raise DisplayError(f"display image must be uint8 of shape {(screen.height_px, screen.width_px)} "
                               f"(rows, columns of the screen), got {image.dtype} {image.shape}")
        sample = np.zeros(self._seen_idx.size, dtype=np.float32)
        if self._win_r1 > self._win_r0:
            window = np.zeros((self._win_r1 - self._win_r0 + 1, self._win_c1 - self._win_c0 + 1), np.float32)
            r_lo, r_hi = max(self._win_r0, 1), min(self._win_r1, screen.height_px)
            c_lo, c_hi = max(self._win_c0, 1), min(self._win_c1, screen.width_px)
            if r_hi >= r_lo and c_hi >= c_lo:
                window[r_lo - self._win_r0:r_hi - self._win_r0 + 1, c_lo - self._win_c0:c_hi - self._win_c0 + 1] = \
                    self._luminance_lut[image[r_lo - 1:r_hi, c_lo - 1:c_hi]]
            flat = window.ravel()
            for k in range(4):
                sample += self._sample_w[k] * flat[self._sample_idx[k]]
            if self._rim_pos.size:
                rim = np.zeros(self._rim_pos.size, dtype=np.float32)
                for k in range(4):
                    rim += self._rim_w[k] * flat[self._rim_idx[k]]
                sample[self._rim_pos] += rim
        return sample

    def _cached_sample(self, display_image: np.ndarray) -> np.ndarray:
        """:meth:`_display_sample`, kept for read-only images (the display's rendered patterns, which
        never change): the trace fixes where every pixel looks, so only the image formation is redone."""
        image = display_image
        if not (isinstance(image, np.ndarray) and not image.flags.writeable and image.base is None):
            return self._display_sample(image)
        key = id(image)
        hit = self._samples.get(key)
        if hit is not None and hit[0]() is image:
            return hit[1]
        sample = self._display_sample(image)
        sample.setflags(write=False)
        # The entry goes when its image goes. The callback holds the twin weakly: holding its dict would make a
        # reference cycle (dict -> weakref -> callback -> dict) that only the cyclic garbage collector frees,
        # so every twin a simulated line drew (one per facet) kept its samples, a hundred MB at full
        # resolution, until a full collection.
        owner = weakref.ref(self)

        def forget(_, k=key):
            twin = owner()
            if twin is not None:
                twin._samples.pop(k, None)

        # (the third item keeps the image's light term once :meth:`_cached_light` has formed it)
        self._samples[key] = (weakref.ref(image, forget), sample, [])
        return sample

    def _cached_light(self, display_image: np.ndarray) -> np.ndarray | None:
        """The display light of a cached read-only image at the reference exposure, laid out on the box of
        camera pixels that see the screen (zero where a pixel sees none), or None for an image not cached.

        Adding it to that box of the frame gives the same bits as adding the light to the seen pixels one by
        one (x + 0 = x), without an indexed scatter per frame (a fifth of a frame's cost)."""
        hit = self._samples.get(id(display_image))
        if hit is None or hit[0]() is not display_image:
            return None
        if not hit[2]:
            if not hasattr(self, "_seen_box"):
                width = self.geometry.camera.width_px
                rows, cols = np.divmod(self._seen_idx, width)
                r0, c0 = (int(rows.min()), int(cols.min())) if rows.size else (0, 0)
                r1, c1 = (int(rows.max()) + 1, int(cols.max()) + 1) if rows.size else (0, 0)
                self._seen_box = (r0, r1, c0, c1, (rows - r0) * (c1 - c0) + (cols - c0))
            r0, r1, c0, c1, local = self._seen_box
            light = np.zeros((r1 - r0, c1 - c0), dtype=np.float32)
            light.ravel()[local] = self._dn_per_luminance * hit[1]
            light.setflags(write=False)
            hit[2].append(light)
        return hit[2][0]

    def _linear(self, sample: np.ndarray, ambient: float, scale: float, flicker: float,
                light: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """Noise-free DN before the knee, rounding and clipping (float32, camera shape), through the lens's
        point-spread function when it has one. *light*: the sample's :meth:`_cached_light`, when known;
        *out*: where the sharp signal may be formed (a float32 array of the camera's shape)."""
        dn = self._linear_sharp(sample, ambient, scale, flicker, light, out)
        if edges.has_psf(self.optics):
            # The light is spread before the sensor integrates it (twin/edges.py: Gaussian, disk).
            dn = edges.apply_psf(dn, self.optics)
        return dn

    def _linear_sharp(self, sample: np.ndarray, ambient: float, scale: float, flicker: float,
                      light: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
        """:meth:`_linear` without the point-spread function: every pixel its own area's light."""
        if scale == 1.0 and flicker == 1.0:
            # The reference exposure and gain: exactly the arithmetic the twin has always used.
            dn = np.multiply(self._dn_per_ambient, np.float32(ambient), out=out)
            dn += self._dn_base
            if light is not None:
                r0, r1, c0, c1, _ = self._seen_box
                dn[r0:r1, c0:c1] += light
            else:
                flat = dn.ravel()
                flat[self._seen_idx] += self._dn_per_luminance * sample
            return dn
        offset = np.float32(self.optics.camera_offset_dn)
        dn = (self._dn_base - offset) + np.float32(ambient) * self._dn_per_ambient
        dn.ravel()[self._seen_idx] += self._dn_per_luminance * (sample * np.float32(flicker))
        dn *= np.float32(scale)
        dn += offset
        return dn

    def linear_dn(self, display_image: np.ndarray, exposure_s: float | None = None, gain: float | None = None,
                  flicker_phase: float | None = None) -> np.ndarray:
        """The noise-free camera signal before the knee, rounding and clipping, DN (float32).

        The same image formation as :meth:`capture` without its random terms, for tests that need the
        exact forward model (the analytically known optimum exposure and gain).
        """
        return self._linear(self._display_sample(display_image), self.optics.ambient,
                            self.sensor_scale(exposure_s, gain), self.flicker_factor(exposure_s, flicker_phase))

    def capture(self, display_image: np.ndarray, rng: np.random.Generator | None = None, *,
                exposure_s: float | None = None, gain: float | None = None,
                flicker_phase: float | None = None, ambient_z: float | None = None) -> np.ndarray:
        """The camera frame while the display shows *display_image*.

        The sensor: DN = black level + (exposure / reference exposure) x gain x (the light the pixel
        gathers, display light times the flicker factor); read noise x gain and shot noise (variance
        signal x gain / ``electrons_per_dn``) are added, then the knee, rounding and clipping to 0..255.
        At the reference exposure, gain 1 and a whole number of refresh periods the signal is exactly the
        one the twin has always formed (a noise-free frame is the same bits). The noise of each half of
        the image comes from its own generator seeded from *rng*, so the two halves are drawn in parallel;
        a given *rng* state still gives the same frame.

        Parameters
        ----------
        display_image : (screen height_px, screen width_px) uint8 array
            Command values the display shows, row 0 = top row.
        rng : numpy Generator or None
            Source of the ambient jitter and the sensor noise; None gives the noise-free frame.
        exposure_s : float or None
            Exposure time, seconds; None is ``optics.reference_exposure_s``.
        gain : float or None
            Linear gain factor; None is 1.
        flicker_phase : float or None
            Phase of the display's refresh cycle at the start of the exposure, periods (0..1); None is 0.
            Matters only for exposures that are not a whole number of refresh periods.
        ambient_z : float or None
            This frame's ambient jitter as a standard normal value (ambient x (1 + ``ambient_jitter`` z));
            None draws it from *rng* when there is one. Given, it is not drawn, so the sensor noise comes
            from the state *rng* is in: drawing z from *rng* first and passing it gives the same frame as
            passing nothing, and ``0.0`` with a copy of that state gives the same sensor noise at the
            nominal ambient (what the frame-to-frame brightness leaves in a figure, ``benchmarks/uncertainty_coverage.py
            --split-brightness``).

        Returns
        -------
        (camera height_px, camera width_px) uint8 array
        """
        optics = self.optics
        scale = self.sensor_scale(exposure_s, gain)
        g = 1.0 if gain is None else float(gain)
        flicker = self.flicker_factor(exposure_s, flicker_phase)
        sample = self._cached_sample(display_image)
        ambient = optics.ambient
        if ambient_z is None and rng is not None and optics.ambient_jitter > 0:
            ambient_z = float(rng.standard_normal())
        if ambient_z is not None and optics.ambient_jitter > 0:
            ambient = max(0.0, ambient * (1.0 + optics.ambient_jitter * float(ambient_z)))
        light = self._cached_light(display_image) if scale == 1.0 and flicker == 1.0 else None
        height, width = self.geometry.camera.shape
        out = np.empty((height, width), dtype=np.uint8)
        noisy = rng is not None and (optics.read_noise_dn > 0 or optics.electrons_per_dn > 0)
        # The image's two halves are finished side by side, each with its own generator seeded from *rng*
        # (numpy releases the GIL while it draws and computes): the sensor noise dominates the frame's cost.
        seeds = rng.integers(0, 2**63, size=2) if noisy else (None, None)
        if light is not None and noisy and not edges.has_psf(optics):
            # The signal is formed, block by block, on the box of pixels that see the screen only: outside
            # it every pixel has its constant dark level (no light, no ambient) and its noise deviation is
            # kept per gain. The same noise draws, the same arithmetic per pixel: the same frame as below.
            job = (self._finish_boxed, ambient, light)
        else:
            # (the signal is formed in this thread's scratch frame: it is finished into *out* and dropped)
            dn = self._linear(sample, ambient, scale, flicker, light, out=scratch_f32("twin.frame", (height, width)))
            job = (self._finish_rows, dn)
        half = height // 2
        first = self._finisher().submit(self._finish, job, out, 0, half, seeds[0], g)
        self._finish(job, out, half, height, seeds[1], g)
        first.result()
        return out

    def _finisher(self) -> ThreadPoolExecutor:
        """The one extra thread that finishes half of each frame (created on first use)."""
        with _FINISHER_LOCK:
            global _FINISHER
            if _FINISHER is None:
                _FINISHER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="twin-frame")
            return _FINISHER

    def _finish(self, job: tuple, out: np.ndarray, a: int, b: int, seed, g: float) -> None:
        """Rows ``a .. b`` of the frame *out*: sensor noise, knee, rounding and clipping, block by block.

        A block of rows (about ``_BLOCK_PX`` pixels) is drawn and finished before the next: its working
        arrays stay in the core's cache from one pass to the next, where a pass over a whole frame would
        run at the speed of memory. The noise comes from a generator seeded with *seed* (None: no noise),
        drawn block after block. *job* is ``(method, *arguments)``: :meth:`_finish_rows` or
        :meth:`_finish_boxed`, called for each block.
        """
        width = out.shape[1]
        step = max(1, _BLOCK_PX // max(width, 1))
        # SFC64: the cheapest of numpy's bit generators per raw word, of the same statistical quality
        gen = None if seed is None else np.random.Generator(np.random.SFC64(int(seed)))
        method, *args = job
        for start in range(a, b, step):
            stop = min(start + step, b)
            noise = None
            if gen is not None:
                n = (stop - start) * width
                noise = standard_normal_f32(gen, n, out=scratch_f32("twin.noise", n)).reshape(stop - start, width)
            method(*args, out, start, stop, noise, g)

    def _finish_rows(self, dn: np.ndarray, out: np.ndarray, a: int, b: int, noise: np.ndarray | None,
                     g: float) -> None:
        """Rows ``a .. b`` of *out* from the frame's linear signal *dn* (changed in place) and their standard
        normal *noise* (None: no noise)."""
        if noise is None:
            self._round(dn[a:b], out[a:b])
        else:
            self._noisy_round(dn[a:b], noise, out[a:b], g)

    def _finish_boxed(self, ambient: float, light: np.ndarray, out: np.ndarray, a: int, b: int,
                      noise: np.ndarray, g: float) -> None:
        """:meth:`_finish_rows` of the rows ``a .. b`` of a frame whose signal is the cached *light* plus the
        ambient on the seen box and the dark level elsewhere: the same noise draws and per-pixel
        arithmetic, so the same counts."""
        width = out.shape[1]
        r0, r1, c0, c1, _ = self._seen_box
        i0, i1 = min(max(r0, a), b), max(min(r1, b), a)          # the box's rows within these rows
        # Whole rows throughout: numpy's passes over a block of whole rows are contiguous, several times
        # faster per pixel than over the strips beside the box.
        sigma = self._dark_sigma(g)
        for lo, hi in ((a, i0), (i1, b)):
            if hi > lo:
                # rows without the box: dn + noise x sigma with dn the dark level, the sum in the other
                # order (the same bits)
                block = noise[lo - a:hi - a]
                block *= sigma[lo:hi] if sigma.ndim else sigma
                block += self._dn_base[lo:hi]
                self._round(block, out[lo:hi])
        if i1 > i0:
            # the box's rows as :meth:`_linear_sharp` forms them: ambient term (zero off the facet) and dark
            # level, plus the display's light on the box (zero on the pixels that see no screen)
            dn = np.multiply(self._dn_per_ambient[i0:i1], np.float32(ambient),
                             out=scratch_f32("twin.box", (i1 - i0, width)))
            dn += self._dn_base[i0:i1]
            dn[:, c0:c1] += light[i0 - r0:i1 - r0]
            self._noisy_round(dn, noise[i0 - a:i1 - a], out[i0:i1], g)

    def _noisy_round(self, dn: np.ndarray, noise: np.ndarray, out: np.ndarray, g: float) -> None:
        """dn + noise x (the noise deviation at dn), then the knee, rounding and clipping into *out* (*dn*
        and *noise* are overwritten)."""
        noise *= self._sigma(dn, g, scratch_f32("twin.sigma", dn.shape))
        dn += noise
        self._round(dn, out)

    def _sigma(self, dn: np.ndarray, g: float, out: np.ndarray) -> np.ndarray:
        """The noise deviation at the signal *dn*, DN: sqrt(read noise^2 x gain^2 + max(dn - black level, 0)
        x gain / ``electrons_per_dn``) (read and shot noise), into *out*; a float32 scalar when there is no
        shot noise.

        Formed as sqrt(max(dn k + (r - b k), r)) with k = gain / electrons per DN, r the read variance and b
        the black level: four passes (the same value as the formula, to float rounding).
        """
        optics = self.optics
        read_var = np.float32((optics.read_noise_dn * g) ** 2)
        if optics.electrons_per_dn <= 0:
            return np.sqrt(read_var)
        k = np.float32(g / optics.electrons_per_dn)
        sigma = np.multiply(dn, k, out=out)
        sigma += np.float32(read_var - k * np.float32(optics.camera_offset_dn))
        np.maximum(sigma, read_var, out=sigma)
        np.sqrt(sigma, out=sigma)
        return sigma

    def _dark_sigma(self, g: float) -> np.ndarray:
        """The noise deviation of every pixel at its dark level (the signal outside the seen box), DN:
        what :meth:`_sigma` computes there, kept per gain (float32, camera shape; a scalar without shot
        noise)."""
        key = float(g)
        sigma = self._dark_sigmas.get(key)
        if sigma is None:
            sigma = self._sigma(self._dn_base, g, np.empty(self._dn_base.shape, dtype=np.float32))
            if sigma.ndim:
                sigma.setflags(write=False)
            self._dark_sigmas[key] = sigma
        return sigma

    def _round(self, dn: np.ndarray, out: np.ndarray) -> None:
        """The knee, then clipping and rounding of *dn* (in place) into the uint8 *out*."""
        optics = self.optics
        if optics.knee_dn is not None:
            knee = np.float32(optics.knee_dn)
            room = np.float32(255.0 - optics.knee_dn)
            over = dn > knee
            dn[over] = knee + room * -np.expm1(-(dn[over] - knee) / room)
        # Clipping to the whole counts 0 and 255 commutes with rounding: clip, then round straight into
        # the uint8 frame (one pass fewer than rounding, clipping and converting; the same counts).
        np.clip(dn, 0, 255, out=dn)
        np.rint(dn, out=out, casting="unsafe")

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
        if self._seen_idx.size == 0:
            raise GeometryError("the facet is not in the camera's view: check the layout and the facet placement")
        if not np.all(np.isfinite(self._path_m)):
            raise GeometryError(f"{int(np.sum(~np.isfinite(self._path_m)))} facet pixels reflect rays that never "
                                "reach the screen plane: the screen does not face the facet; check the layout")
        screen = self.geometry.screen
        widening_m = 2.0 * 1e-3 * float(max_slope_error_mrad) * self._path_m
        u_x, u_y = self._u_scr_m[:, 0], self._u_scr_m[:, 1]
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
                "n_pixels": int(self._seen_idx.size)}

    # ------------------------------------------------------- test support
    def _image(self, values: np.ndarray, fill) -> np.ndarray:
        """Scatter per-seen-pixel values into a read-only image-shaped array."""
        height, width = self.geometry.camera.shape
        extra = values.shape[1:]
        out = np.full((height * width,) + extra, fill, dtype=values.dtype)
        out[self._seen_idx] = values
        out = out.reshape((height, width) + extra)
        out.setflags(write=False)
        return out

    @property
    def coverage(self) -> np.ndarray:
        """Fraction (H, W) of each pixel's area covered by the facet (0 outside, 1 inside)."""
        out = self._coverage.view()
        out.setflags(write=False)
        return out

    @property
    def rim_coverage(self) -> np.ndarray:
        """Fraction (H, W) of each pixel's area on the facet's bevelled rim (zero without one)."""
        out = self._rim_coverage.view()
        out.setflags(write=False)
        return out

    @cached_property
    def rim_screen_position_m(self) -> np.ndarray:
        """Screen coordinates (H, W, 2) of the screen point each rim pixel's rim reflects; NaN elsewhere."""
        height, width = self.geometry.camera.shape
        out = np.full((height * width, 2), np.nan)
        out[self._seen_idx[self._rim_pos]] = self._rim_u_scr_m
        out = out.reshape(height, width, 2)
        out.setflags(write=False)
        return out

    @cached_property
    def screen_position_m(self) -> np.ndarray:
        """Screen coordinates (H, W, 2) = (u_x, u_y) metres of each facet pixel's centre ray; NaN elsewhere."""
        return self._image(self._u_scr_m, np.nan)

    @cached_property
    def surface_point_facet_m(self) -> np.ndarray:
        """True surface point (H, W, 3), true facet frame, metres, of each facet pixel's centre ray; NaN elsewhere."""
        return self._image(self._x_facet_m, np.nan)

    @cached_property
    def slope_true(self) -> np.ndarray:
        """Exact slopes (H, W, 2) = (dz/dx, dz/dy) of the true surface at :attr:`surface_point_facet_m`."""
        return self._image(self._slope, np.nan)

    @cached_property
    def on_screen(self) -> np.ndarray:
        """Whether (H, W) a facet pixel's centre ray lands on the screen's active area."""
        return self._image(self._on_screen, False)

    @property
    def vignetting_factor(self) -> np.ndarray:
        """Relative irradiance (H, W) after vignetting, 1 at the principal point."""
        out = self._vignetting.view()
        out.setflags(write=False)
        return out
