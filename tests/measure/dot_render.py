"""A small ray tracer of a facet reflecting a dot grid into a camera, for the fixed-pattern method's tests
(tests/measure/test_fixed.py). It shares no code with the package: its own camera model (pinhole with one
radial term, undistorted by its own iteration), its own surface intersection (the quadric's quadratic, then
Newton steps for a bump), its own law of reflection, and dots drawn as exact discs on the screen plane, each
camera pixel the mean of n x n rays over its area (so a dot's image is area-sampled), then blurred, noisy and
rounded to 8 bits. Only the package's plain records (CameraIntrinsics, Pose, ...) describe the scene to the
analysis.

Frames: the camera's is the world's (x right, y down, z forward). The facet's frame has its origin at the
facet's centre on the surface, z along the surface normal there; the true surface is
z = A x^2 + B y^2 + E x y + bump. The dot grid lies in its screen's plane z = 0, dot (i, j) at
(i pitch, j pitch, 0) in the screen's frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sofast_station.facet import FacetDesign
from sofast_station.geometry import CameraIntrinsics, Pose, ScreenSpec, StationGeometry
from sofast_station.measure.dots import DotLocations


def _frame(z_axis: np.ndarray, x_hint: np.ndarray) -> np.ndarray:
    """Rotation whose columns are an orthonormal frame with z along *z_axis* and x as near *x_hint* as can be."""
    z = z_axis / np.linalg.norm(z_axis)
    x = x_hint - (x_hint @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


@dataclass
class Scene:
    """Camera, facet and dot grid. Lengths in metres, angles in radians, image values in DN."""

    width: int = 800
    height: int = 600
    focal_px: float = 2000.0
    k1: float = 0.0
    half_size: float = 0.3                    # the facet's half side
    a: float = 1.0 / 80.0                     # z = A x^2 + B y^2 + E xy (+ bump)
    b: float = 1.0 / 76.0
    e: float = 0.002
    bump: tuple = (0.0, 0.1, -0.05, 0.06)     # amplitude, x0, y0, width (a Gaussian dent)
    facet_centre: tuple = (0.25, 0.02, 4.0)
    screen_centre: tuple = (0.5, 0.0, 0.0)
    pitch: float = 0.04
    radius: float = 0.008
    n_dots: int = 30                          # dots from -n to n along each axis
    background: float = 150.0
    dark: float = 25.0
    mark_level: float = 245.0                 # the origin mark's level, a disc beside the origin dot
    mark_radius: float = 0.005
    mark_offset: float = 0.37                 # of a pitch, along the screen's +y from the origin dot
    ambient: float = 6.0
    blur_px: float = 0.6
    samples: int = 3
    missing: list = field(default_factory=list)      # dots (i, j) not drawn
    dot_offset: tuple = (0.0, 0.0)                    # the whole grid shifted on the screen (of a pitch)
    screen_image: object = None                       # (image, pixel pitch) an LCD shows instead of the dots

    # -- geometry ------------------------------------------------------------------------------------
    @property
    def facet_rotation(self) -> np.ndarray:
        """Facet frame -> camera frame: its normal bisects the directions to the camera and the screen centre."""
        p, s = np.array(self.facet_centre), np.array(self.screen_centre)
        n = -p / np.linalg.norm(p) + (s - p) / np.linalg.norm(s - p)
        return _frame(n, np.array([1.0, 0.0, 0.0]))

    @property
    def screen_rotation(self) -> np.ndarray:
        """Screen frame -> camera frame: its z toward the facet, its x as near the camera's -x as can be."""
        return _frame(np.array(self.facet_centre) - np.array(self.screen_centre), np.array([-1.0, 0.0, 0.0]))

    def camera(self) -> CameraIntrinsics:
        k = np.array([[self.focal_px, 0.0, 0.5 * (self.width - 1)], [0.0, self.focal_px, 0.5 * (self.height - 1)],
                      [0.0, 0.0, 1.0]])
        return CameraIntrinsics(self.width, self.height, k, np.array([self.k1, 0.0, 0.0, 0.0, 0.0]))

    def facet_to_camera(self) -> Pose:
        return Pose(self.facet_rotation, np.array(self.facet_centre, float))

    def screen_to_camera(self) -> Pose:
        return Pose(self.screen_rotation, np.array(self.screen_centre, float))

    def geometry(self, nominal: Pose | None = None) -> StationGeometry:
        return StationGeometry(self.camera(), ScreenSpec(1000, 1000, 0.001), self.screen_to_camera(),
                               nominal or self.facet_to_camera())

    def design(self, focal_length_m: float = 20.0) -> FacetDesign:
        h = self.half_size
        return FacetDesign(name="test facet", kind="dish", focal_length_m=focal_length_m,
                           outline_m=np.array([[h, -h], [h, h], [-h, h], [-h, -h]]),
                           measure_point_m=[0.0, 0.0], alignment_point_m=[0.0, 0.0])

    def dots(self) -> DotLocations:
        idx = np.arange(-self.n_dots, self.n_dots + 1)
        i, j = np.meshgrid(idx, idx)
        xyz = np.stack([i * self.pitch, j * self.pitch, np.zeros(i.shape)], axis=2)
        return DotLocations(idx, idx, xyz)

    def measured_distance_m(self) -> float:
        """From the screen centre to the facet's measure point (its centre, on the surface)."""
        return float(np.linalg.norm(np.array(self.facet_centre) - np.array(self.screen_centre)))

    # -- the surface ---------------------------------------------------------------------------------
    def z(self, x, y):
        amp, x0, y0, w = self.bump
        return (self.a * x * x + self.b * y * y + self.e * x * y
                + amp * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * w * w)))

    def slopes(self, x, y):
        """(dz/dx, dz/dy) of the true surface."""
        amp, x0, y0, w = self.bump
        g = amp * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * w * w))
        return (2 * self.a * x + self.e * y - g * (x - x0) / (w * w),
                2 * self.b * y + self.e * x - g * (y - y0) / (w * w))

    def pixel_directions(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Unit rays (3, n) through image positions (u, v), pixel centres at integers."""
        f, cx, cy = self.focal_px, 0.5 * (self.width - 1), 0.5 * (self.height - 1)
        xd, yd = (u - cx) / f, (v - cy) / f
        x, y = xd.copy(), yd.copy()
        for _ in range(20 if self.k1 else 0):  # x (1 + k1 r^2) = xd, by fixed-point iteration
            d = 1.0 + self.k1 * (x * x + y * y)
            x, y = xd / d, yd / d
        ray = np.vstack([x, y, np.ones_like(x)])
        return ray / np.linalg.norm(ray, axis=0)

    def trace(self, rays: np.ndarray):
        """Where camera rays (3, n) meet the facet (facet-frame x, y; NaN off the facet) and the screen point
        (screen-frame x, y) they then see (NaN where they miss the screen's plane)."""
        r_f, p = self.facet_rotation, np.array(self.facet_centre)
        o = -r_f.T @ p                                        # camera centre in the facet frame
        d = r_f.T @ rays
        # the quadric's intersection (the root nearest the camera), then Newton steps for the bump
        qa = self.a * d[0] ** 2 + self.b * d[1] ** 2 + self.e * d[0] * d[1]
        qb = (2 * self.a * o[0] * d[0] + 2 * self.b * o[1] * d[1] + self.e * (o[0] * d[1] + o[1] * d[0]) - d[2])
        qc = self.a * o[0] ** 2 + self.b * o[1] ** 2 + self.e * o[0] * o[1] - o[2]
        disc = np.sqrt(qb * qb - 4 * qa * qc)
        t = 2 * qc / (-qb - np.sign(qb) * disc)              # the stable form of the root nearest the camera
        for _ in range(6 if self.bump[0] else 0):
            x, y = o[0] + t * d[0], o[1] + t * d[1]
            sx, sy = self.slopes(x, y)
            g = self.z(x, y) - (o[2] + t * d[2])
            t = t - g / (sx * d[0] + sy * d[1] - d[2])
        x, y = o[0] + t * d[0], o[1] + t * d[1]
        z = o[2] + t * d[2]
        sx, sy = self.slopes(x, y)
        n = np.vstack([-sx, -sy, np.ones_like(sx)])
        n /= np.linalg.norm(n, axis=0)
        refl = d - 2 * np.sum(d * n, axis=0) * n
        on = (np.abs(x) <= self.half_size) & (np.abs(y) <= self.half_size)
        # into the screen's frame, onto its plane
        r_s, s = self.screen_rotation, np.array(self.screen_centre)
        point_cam = r_f @ np.vstack([x, y, z]) + p[:, None]
        ps = r_s.T @ (point_cam - s[:, None])
        ds = r_s.T @ (r_f @ refl)
        k = -ps[2] / ds[2]
        hit = (ds[2] < 0) & (k > 0)
        sx_, sy_ = ps[0] + k * ds[0], ps[1] + k * ds[1]
        return (np.where(on, x, np.nan), np.where(on, y, np.nan),
                np.where(on & hit, sx_, np.nan), np.where(on & hit, sy_, np.nan))

    def screen_level(self, sx: np.ndarray, sy: np.ndarray) -> np.ndarray:
        """What the screen shows at screen-frame (x, y): the lit background, dark dots, the origin mark."""
        if self.screen_image is not None:
            return self._lcd_level(sx, sy)
        p = self.pitch
        ox, oy = self.dot_offset[0] * p, self.dot_offset[1] * p
        i, j = np.round((sx - ox) / p), np.round((sy - oy) / p)
        level = np.full(sx.shape, self.background)
        within = (np.abs(i) <= self.n_dots) & (np.abs(j) <= self.n_dots)
        dot = within & ((sx - ox - i * p) ** 2 + (sy - oy - j * p) ** 2 <= self.radius ** 2)
        for mi, mj in self.missing:
            dot &= ~((i == mi) & (j == mj))
        level[dot] = self.dark
        mark = (sx ** 2 + (sy - self.mark_offset * p) ** 2) <= self.mark_radius ** 2
        level[mark] = self.mark_level
        extent = (self.n_dots + 0.5) * p
        level[(np.abs(sx) > extent) | (np.abs(sy) > extent) | np.isnan(sx)] = 0.0
        return level

    def _lcd_level(self, sx, sy):
        """An LCD's image: display pixel (row r, column c) covers x in [c p, (c + 1) p] - W / 2 and y in
        [H / 2 - (r + 1) p, H / 2 - r p] (docs/conventions.md, screen frame; +y up), its level the command's
        share of the background level's command."""
        image, pitch = self.screen_image
        h, w = image.shape
        col = np.floor((sx + 0.5 * w * pitch) / pitch)
        row = np.floor((0.5 * h * pitch - sy) / pitch)
        inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
        level = np.zeros(sx.shape)
        cmd = image[row[inside].astype(int), col[inside].astype(int)].astype(float)
        level[inside] = self.background * cmd / 170.0
        return level

    # -- the image -----------------------------------------------------------------------------------
    def render(self, noise_dn: float = 0.0, seed: int = 0) -> np.ndarray:
        """The camera frame (height, width) uint8: :meth:`signal`, Gaussian noise of *noise_dn*, rounded."""
        img = self.signal().copy()
        if noise_dn > 0:
            img += np.random.default_rng(seed).normal(0.0, noise_dn, img.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    def signal(self) -> np.ndarray:
        """The noise-free camera signal (height, width), DN, before rounding (computed once)."""
        if getattr(self, "_signal", None) is None:
            self._signal = self._render_signal()
        return self._signal

    def _render_signal(self) -> np.ndarray:
        from scipy.ndimage import gaussian_filter

        # the facet's box in the image, from its corners (and a margin)
        h = self.half_size
        corners = np.array([[h, h], [h, -h], [-h, h], [-h, -h]])
        pc = self.facet_rotation @ np.column_stack([corners, self.z(corners[:, 0], corners[:, 1])]).T \
            + np.array(self.facet_centre)[:, None]
        xn, yn = pc[0] / pc[2], pc[1] / pc[2]
        r2 = xn * xn + yn * yn
        u = self.focal_px * xn * (1 + self.k1 * r2) + 0.5 * (self.width - 1)
        v = self.focal_px * yn * (1 + self.k1 * r2) + 0.5 * (self.height - 1)
        c0, c1 = int(max(np.floor(u.min()) - 8, 0)), int(min(np.ceil(u.max()) + 8, self.width))
        r0, r1 = int(max(np.floor(v.min()) - 8, 0)), int(min(np.ceil(v.max()) + 8, self.height))
        n = self.samples
        sub = (np.arange(n) + 0.5) / n - 0.5
        cols, rows = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
        su, sv = np.meshgrid(sub, sub)
        uu = (cols[..., None] + su.ravel()).ravel()
        vv = (rows[..., None] + sv.ravel()).ravel()
        x, y, sx, sy = self.trace(self.pixel_directions(uu, vv))
        on = ~np.isnan(x)
        level = np.where(on, self.screen_level(np.nan_to_num(sx), np.nan_to_num(sy)), 0.0)
        level[on & np.isnan(sx)] = 0.0
        box = level.reshape(rows.shape + (n * n,)).mean(axis=2)
        img = np.full((self.height, self.width), 0.0)
        img[r0:r1, c0:c1] = box
        if self.blur_px > 0:
            img = gaussian_filter(img, self.blur_px)
        return img + self.ambient

    def project(self, points_facet: np.ndarray) -> np.ndarray:
        """Image positions (n, 2) of facet-frame points (n, 3)."""
        pc = self.facet_rotation @ points_facet.T + np.array(self.facet_centre)[:, None]
        xn, yn = pc[0] / pc[2], pc[1] / pc[2]
        r2 = xn * xn + yn * yn
        return np.column_stack([self.focal_px * xn * (1 + self.k1 * r2) + 0.5 * (self.width - 1),
                                self.focal_px * yn * (1 + self.k1 * r2) + 0.5 * (self.height - 1)])

    def seen_px(self, sx: float, sy: float) -> np.ndarray | None:
        """The image position where the screen point (sx, sy) is seen (a search over the facet's rays), for
        where to expect a dot or the mark."""
        h = self.half_size
        g = np.linspace(-h, h, 121)
        gx, gy = np.meshgrid(g, g)
        pts = np.column_stack([gx.ravel(), gy.ravel(), self.z(gx.ravel(), gy.ravel())])
        px = self.project(pts)
        _, _, ex, ey = self.trace(self.pixel_directions(px[:, 0], px[:, 1]))
        k = int(np.nanargmin((ex - sx) ** 2 + (ey - sy) ** 2))
        u, v = px[k]
        for _ in range(6):                    # Newton on the image position
            def at(uu, vv):
                _, _, a_, b_ = self.trace(self.pixel_directions(np.array([uu]), np.array([vv])))
                return np.array([a_[0], b_[0]])
            e0 = at(u, v)
            jac = np.column_stack([(at(u + 0.1, v) - e0) / 0.1, (at(u, v + 0.1) - e0) / 0.1])
            step = np.linalg.solve(jac, np.array([sx, sy]) - e0)
            u, v = u + step[0], v + step[1]
        return np.array([u, v])
