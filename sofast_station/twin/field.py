"""The twin of a heliostat field seen from the tower's camera: photographs, and their truth.

A photograph is rendered by painting, far to near, the lit ground, then every heliostat in view (its
pedestal, the beams behind its mirrors, its facets), then the lens's blur, the sensor's noise and its 8-bit
quantisation. Every facet mirrors the sky: a clear sky brightening towards the horizon, the sun's disk and
its aureole (Buie's sun shape, of circumsolar ratio ``csr``), or the ground when its reflected ray points
down; each facet's reflected ray is taken pixel by pixel on its curved surface (its design focal length),
so a facet's brightness runs across it as the aureole's does. A facet seen from behind shows its painted
back. The colours (sky blue, sandy ground, grey steel) give the three channels different contrasts: the
detection has to pick one.

Every pixel's coverage by a facet (or a beam, a pedestal) is its area's share inside the quadrilateral the
facet's corners project to in the ideal (undistorted) image, from each pixel's distance to the four edges;
the lens's distortion enters through each pixel's ideal coordinates (:meth:`TwinCamera.undistort`), so edges
bend as a real lens bends them. Nothing here is shared with ``sofast_station.field`` or ``measure``: the
frames are the documented ones (docs/field.md#frames), written again here.

Frames: the field frame is x east, y north, z up (metres); a heliostat's frame in it turns by its azimuth
(clockwise from north), elevation and spin about its normal (docs/field.md#frames); each facet's true pose
is its design pose on that frame, then its own canting error (rx, ry, rz in mrad, R = R_z R_y R_x, about its
middle, in its design frame). The camera's ``rotation`` maps field vectors into OpenCV's camera frame.

Truth (:func:`facet_truth`, :func:`canting_truth`): each facet's true corners in the picture (the design
outline's order), the heliostat's true normal, and the facets' canting errors by the definition of
docs/conventions.md#canting applied to the facets' true frames (their corners' planes: the field sees no
slopes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from ..ensemble import EnsembleDesign
from ..errors import ConfigError, GeometryError
from ..geometry import CameraIntrinsics
from .camera import TwinCamera
from .heliostat import TILT_TOLERANCE_RAD, _angles
from .station import rotation_zyx

#: Half-angle of the sun's disk, radians.
SUN_HALF_ANGLE_RAD = 4.65e-3
#: Colours (red, green, blue) of the clear sky, the ground and painted steel; the sun's light is white.
SKY_RGB = (0.42, 0.62, 1.0)
GROUND_RGB = (1.0, 0.82, 0.62)
STEEL_RGB = (0.8, 0.8, 0.82)


# ------------------------------------------------------------------------------------------ the frames
def _direction(az: float, el: float) -> np.ndarray:
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def heliostat_to_field(azimuth_rad: float, elevation_rad: float, spin_rad: float = 0.0) -> np.ndarray:
    """Heliostat frame -> field frame: z the normal at (azimuth, elevation), x level
    (``(-cos az, sin az, 0)``) before the spin about z (docs/field.md#frames)."""
    z = _direction(azimuth_rad, elevation_rad)
    x = np.array([-math.cos(azimuth_rad), math.sin(azimuth_rad), 0.0])
    y = np.cross(z, x)
    c, s = math.cos(spin_rad), math.sin(spin_rad)
    x, y = c * x + s * y, -s * x + c * y
    return np.column_stack([x, y, z])


def camera_rotation(camera_m, target_m, roll_rad: float = 0.0) -> np.ndarray:
    """Field -> camera rotation of a camera at *camera_m* looking at *target_m*: level x axis (east of the
    view direction) turned by *roll_rad* about the optical axis (docs/field.md#frames)."""
    forward = np.asarray(target_m, float) - np.asarray(camera_m, float)
    forward /= np.linalg.norm(forward)
    right = np.array([forward[1], -forward[0], 0.0])          # forward x up
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    return np.vstack([c * right + s * down, -s * right + c * down, forward])


# ------------------------------------------------------------------------------------------ the scene
@dataclass(frozen=True)
class FieldHeliostat:
    """A heliostat as it stands in the field.

    Parameters
    ----------
    ensemble : EnsembleDesign
    position_m : (3,) sequence
        Its pivot (where its axes cross), field frame, metres.
    azimuth_rad, elevation_rad, spin_rad : float
        Its true orientation (docs/field.md#frames).
    pivot_offset_m : float
        The heliostat frame's origin lies this far in front of the pivot, along the normal.
    canting_errors_mrad : (F, 3) array or None
        Each facet's canting error (rx, ry, rz) about its middle, in its design frame; None: none.
    """

    ensemble: EnsembleDesign
    position_m: tuple
    azimuth_rad: float
    elevation_rad: float
    spin_rad: float = 0.0
    pivot_offset_m: float = 0.0
    canting_errors_mrad: np.ndarray | None = None

    def __post_init__(self):
        pos = np.asarray(self.position_m, dtype=np.float64)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise ConfigError(f"FieldHeliostat.position_m must be 3 finite metres, got {self.position_m!r}")
        object.__setattr__(self, "position_m", pos)
        err = np.zeros((self.ensemble.n_facets, 3)) if self.canting_errors_mrad is None else \
            np.asarray(self.canting_errors_mrad, dtype=np.float64)
        if err.shape != (self.ensemble.n_facets, 3):
            raise ConfigError(f"FieldHeliostat.canting_errors_mrad must be ({self.ensemble.n_facets}, 3), got "
                              f"{err.shape}")
        object.__setattr__(self, "canting_errors_mrad", err)

    @property
    def rotation(self) -> np.ndarray:
        """Heliostat frame -> field frame."""
        return heliostat_to_field(self.azimuth_rad, self.elevation_rad, self.spin_rad)

    @property
    def normal(self) -> np.ndarray:
        return self.rotation[:, 2]

    @property
    def origin_m(self) -> np.ndarray:
        """The heliostat frame's origin, field frame."""
        return self.position_m + self.pivot_offset_m * self.normal

    def facet_rotations(self) -> list[np.ndarray]:
        """Each facet's true frame -> heliostat frame: its design canting, then its canting error."""
        return [f.rotation @ rotation_zyx(*(1e-3 * e)) for f, e in zip(self.ensemble.facets, self.canting_errors_mrad)]

    def facet_corners_m(self) -> list[np.ndarray]:
        """Each facet's true corners (the design outline's, on the design surface), field frame, (N, 3)."""
        out = []
        r_h, o_h = self.rotation, self.origin_m
        for f, e in zip(self.ensemble.facets, self.canting_errors_mrad):
            local = f.design.corners_3d()
            mid = _middle(f)
            local = mid + (local - mid) @ rotation_zyx(*(1e-3 * e)).T
            out.append((local @ f.rotation.T + f.position_m) @ r_h.T + o_h)
        return out


def _middle(f) -> np.ndarray:
    cx, cy = (float(v) for v in f.design.centroid_m)
    return np.array([cx, cy, float(f.design.z(cx, cy))])


@dataclass(frozen=True)
class Sky:
    """The light: the sun's direction (unit, field frame), its DNI (W/m^2), its circumsolar ratio, the
    clear sky's radiance at the zenith and at the horizon (W/m^2/sr), the ground's albedo range and the
    mirrors' reflectivity."""

    sun: tuple
    dni_w_m2: float = 900.0
    csr: float = 0.05
    sky_zenith: float = 40.0
    sky_horizon: float = 110.0
    albedo: tuple = (0.18, 0.34)
    reflectivity: float = 0.93

    def __post_init__(self):
        s = np.asarray(self.sun, dtype=np.float64)
        if s.shape != (3,) or s[2] <= 0:
            raise GeometryError(f"the sun must be a direction above the horizon, got {self.sun!r}")
        object.__setattr__(self, "sun", s / np.linalg.norm(s))

    def radiance(self, rays: np.ndarray) -> np.ndarray:
        """Radiance (R, G, B; W/m^2/sr) of the sky in the unit directions *rays* (..., 3): the clear sky, the
        sun's disk and aureole (Buie's shape); rays below the horizon get the ground's mean."""
        rays = np.asarray(rays, dtype=np.float64)
        up = np.clip(rays[..., 2], 0.0, 1.0)
        base = self.sky_zenith + (self.sky_horizon - self.sky_zenith) * (1.0 - up) ** 3
        theta = np.arccos(np.clip(rays @ self.sun, -1.0, 1.0))
        sun = self.dni_w_m2 * _buie(theta, self.csr)
        out = base[..., None] * np.asarray(SKY_RGB) + sun[..., None]
        down = rays[..., 2] < 0
        if np.any(down):
            out[down] = self.ground_radiance(np.mean(self.albedo))
        return out

    def ground_radiance(self, albedo) -> np.ndarray:
        """Radiance (..., 3) of lit ground of *albedo* (Lambertian: the sun's and the sky's light)."""
        irradiance = self.dni_w_m2 * float(self.sun[2]) + math.pi * 0.5 * (self.sky_zenith + self.sky_horizon)
        return (np.asarray(albedo, dtype=np.float64)[..., None] * irradiance / math.pi) * np.asarray(GROUND_RGB)


def _buie(theta: np.ndarray, csr: float) -> np.ndarray:
    """Buie's sun shape per unit DNI (1/sr): the disk's limb darkening within 4.65 mrad, the aureole's
    power law beyond, normalised so that the disk and aureole together hold the DNI."""
    mrad = 1e3 * np.asarray(theta, dtype=np.float64)
    kappa = 0.9 * math.log(13.5 * csr) * csr ** -0.3
    gamma = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1
    with np.errstate(divide="ignore", invalid="ignore"):
        phi = np.where(mrad <= 4.65, np.cos(0.326 * mrad) / np.cos(0.308 * mrad),
                       math.exp(kappa) * np.maximum(mrad, 4.65) ** gamma)
    return phi / _buie_norm(csr)


_NORMS: dict = {}


def _buie_norm(csr: float) -> float:
    """The solid-angle integral of Buie's unnormalised shape (sr), out to 0.2 rad."""
    if csr not in _NORMS:
        kappa = 0.9 * math.log(13.5 * csr) * csr ** -0.3
        gamma = 2.2 * math.log(0.52 * csr) * csr ** 0.43 - 0.1
        t = np.linspace(0.0, 0.2, 200001)
        m = 1e3 * t
        phi = np.where(m <= 4.65, np.cos(0.326 * m) / np.cos(0.308 * m), math.exp(kappa) * np.maximum(m, 4.65) ** gamma)
        f = phi * 2.0 * np.pi * np.sin(t)
        _NORMS[csr] = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(t)))
    return _NORMS[csr]


@dataclass(frozen=True)
class TowerCamera:
    """The tower's camera as it really is: intrinsics, position (field frame, metres) and the rotation
    field -> camera (OpenCV's camera frame)."""

    intrinsics: CameraIntrinsics
    position_m: tuple
    rotation: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "position_m", np.asarray(self.position_m, dtype=np.float64))
        r = np.asarray(self.rotation, dtype=np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-9):
            raise ConfigError("TowerCamera.rotation must be a 3 x 3 rotation")
        object.__setattr__(self, "rotation", r)

    def project(self, points_m: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) of field points (..., 3), through the lens (NaN behind the camera)."""
        return TwinCamera(self.intrinsics).project((np.asarray(points_m) - self.position_m) @ self.rotation.T)


@dataclass(frozen=True)
class Exposure:
    """How the photo is taken: the lens's blur (a Gaussian's standard deviation, pixels, heat shimmer
    included), the sensor's read noise (DN) and full well (electrons at 255 DN), the auto exposure's target
    (the target heliostat's median facet pixel in the blue channel, as a fraction of 255), or a fixed
    *scale* (DN per W/m^2/sr) that overrides it, and the lens's vignetting (fraction lost at the corners)."""

    blur_px: float = 0.8
    read_noise_dn: float = 1.0
    full_well_e: float = 12000.0
    target_level: float = 0.45
    scale: float | None = None
    vignetting: float = 0.1


@dataclass
class Photo:
    """A rendered photo: ``image`` (H, W, 3) uint8 (RGB) and its truth."""

    image: np.ndarray
    truth: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------ painting
class _Canvas:
    """The radiance image being painted, and every pixel's ideal coordinates and ray."""

    def __init__(self, camera: TowerCamera):
        k = camera.intrinsics
        tc = TwinCamera(k)
        h, w = k.height_px, k.width_px
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        x_d, y_d = (u - tc.cx) / tc.fx, (v - tc.cy) / tc.fy
        if np.any(k.distortion != 0):
            x, y = tc.undistort(x_d, y_d)
        else:
            x, y = x_d, y_d
        self.camera, self.tc = camera, tc
        self.ideal_u, self.ideal_v = tc.fx * x + tc.cx, tc.fy * y + tc.cy
        rays = np.stack([x, y, np.ones_like(x)], axis=-1) @ camera.rotation      # camera -> field
        self.rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
        self.radiance = np.zeros((h, w, 3))
        self.shape = (h, w)

    def ideal(self, points_m: np.ndarray) -> np.ndarray | None:
        """Ideal pixel coordinates (N, 2) of field points; None when one is behind the camera."""
        p = (np.asarray(points_m) - self.camera.position_m) @ self.camera.rotation.T
        if np.any(p[:, 2] <= 1e-6):
            return None
        return np.column_stack([self.tc.fx * p[:, 0] / p[:, 2] + self.tc.cx,
                                self.tc.fy * p[:, 1] / p[:, 2] + self.tc.cy])

    def coverage(self, quad_px: np.ndarray):
        """(rows slice, cols slice, coverage) of a convex quadrilateral given in ideal pixels, or None when
        it misses the picture."""
        h, w = self.shape
        lo = np.floor(quad_px.min(axis=0)) - 4
        hi = np.ceil(quad_px.max(axis=0)) + 4
        c0, r0 = int(max(lo[0], 0)), int(max(lo[1], 0))
        c1, r1 = int(min(hi[0], w - 1)), int(min(hi[1], h - 1))
        if c1 < c0 or r1 < r0:
            return None
        rows, cols = slice(r0, r1 + 1), slice(c0, c1 + 1)
        pu, pv = self.ideal_u[rows, cols], self.ideal_v[rows, cols]
        qx, qy = quad_px[:, 0], quad_px[:, 1]
        area = 0.5 * float(np.sum(qx * np.roll(qy, -1) - np.roll(qx, -1) * qy))
        if abs(area) < 1e-9:
            return None
        sign = 1.0 if area > 0 else -1.0
        cov = np.ones(pu.shape)
        for k in range(len(quad_px)):
            a, b = quad_px[k], quad_px[(k + 1) % len(quad_px)]
            t = b - a
            length = float(np.hypot(*t))
            # inward distance (pixels) of each pixel centre from the edge a -> b
            d = sign * (t[0] * (pv - a[1]) - t[1] * (pu - a[0])) / length
            cov *= np.clip(0.5 + d, 0.0, 1.0)
        if not np.any(cov > 0):
            return None
        return rows, cols, cov

    def paint(self, quad_m: np.ndarray, colour) -> None:
        """Paint the field-frame quadrilateral *quad_m* (4, 3) with a radiance (3,) or a function of the
        rows, columns and coverage that returns one per pixel."""
        q = self.ideal(quad_m)
        if q is None:
            return
        got = self.coverage(q)
        if got is None:
            return
        rows, cols, cov = got
        value = colour(rows, cols, cov) if callable(colour) else np.asarray(colour, dtype=np.float64)
        patch = self.radiance[rows, cols]
        self.radiance[rows, cols] = patch * (1.0 - cov[..., None]) + value * cov[..., None]


def _ground(canvas: _Canvas, sky: Sky, rng: np.random.Generator) -> None:
    """Lit ground (a smooth albedo texture) below the horizon, the sky above it."""
    rays = canvas.rays
    c = canvas.camera.position_m
    down = rays[..., 2] < -1e-6
    t = np.where(down, -c[2] / np.where(down, rays[..., 2], -1.0), 0.0)
    x, y = c[0] + t * rays[..., 0], c[1] + t * rays[..., 1]
    lo, hi = sky.albedo
    texture = np.zeros(x.shape)
    for _ in range(6):                     # a few random plane waves of 2 to 20 m
        k = rng.uniform(2.0 * math.pi / 20.0, 2.0 * math.pi / 2.0)
        a = rng.uniform(0.0, 2.0 * math.pi)
        texture += np.sin(k * (x * math.cos(a) + y * math.sin(a)) + rng.uniform(0.0, 2.0 * math.pi))
    albedo = lo + (hi - lo) * (0.5 + texture / 12.0)
    canvas.radiance[:] = np.where(down[..., None], sky.ground_radiance(albedo), sky.radiance(rays))


def _paint_heliostat(canvas: _Canvas, h: FieldHeliostat, sky: Sky, is_target: bool, facet_pixels: list) -> None:
    """Pedestal, the beams behind the mirrors, then the facets (each mirroring the sky pixel by pixel)."""
    r_h, o_h = h.rotation, h.origin_m
    steel_lit = sky.ground_radiance(np.mean(sky.albedo)) * 0.35 / np.asarray(GROUND_RGB) * np.asarray(STEEL_RGB)
    steel_dark = 0.4 * steel_lit
    # pedestal: a post of 0.25 m from the ground up to the pivot, facing the camera
    view = canvas.camera.position_m - h.position_m
    side = np.array([view[1], -view[0], 0.0])
    side = 0.125 * side / max(np.linalg.norm(side), 1e-9)
    base = np.array([h.position_m[0], h.position_m[1], 0.0])
    canvas.paint(np.array([base - side, base + side, h.position_m + side, h.position_m - side]), steel_dark)
    # beams 0.15 m behind the mirrors: one along each gap between rows of facets, and a torque tube
    corners = np.vstack(h.ensemble.corners_m())
    (x0, y0), (x1, y1) = corners[:, :2].min(axis=0), corners[:, :2].max(axis=0)
    ys = sorted({round(float(f.position_m[1]), 6) for f in h.ensemble.facets})
    gaps = [0.5 * (a + b) for a, b in zip(ys[:-1], ys[1:])] or [0.0]
    behind = -0.15
    for y in gaps:
        beam = np.array([[x0, y - 0.04, behind], [x1, y - 0.04, behind], [x1, y + 0.04, behind],
                         [x0, y + 0.04, behind]])
        canvas.paint(beam @ r_h.T + o_h, steel_lit)
    tube = np.array([[-0.06, y0, behind - 0.1], [0.06, y0, behind - 0.1], [0.06, y1, behind - 0.1],
                     [-0.06, y1, behind - 0.1]])
    canvas.paint(tube @ r_h.T + o_h, steel_dark)
    # the facets
    cam = canvas.camera
    for j, (f, corners_m, r_f) in enumerate(zip(h.ensemble.facets, h.facet_corners_m(), h.facet_rotations())):
        r_fw = r_h @ r_f                                   # facet -> field
        n_f = r_fw[:, 2]
        origin = o_h + r_h @ (f.position_m + f.rotation @ (_middle(f) - rotation_zyx(*(1e-3 * h.canting_errors_mrad[j]))
                                                          @ _middle(f)))
        seen_from_front = float(n_f @ (cam.position_m - corners_m.mean(axis=0))) > 0
        focal = float(f.design.focal_length_m)

        def mirror(rows, cols, cov, r_fw=r_fw, origin=origin, n_f=n_f, focal=focal):
            d = canvas.rays[rows, cols]
            t = ((origin - cam.position_m) @ n_f) / np.where(np.abs(d @ n_f) > 1e-12, d @ n_f, 1e-12)
            hit = cam.position_m + t[..., None] * d
            local = (hit - origin) @ r_fw                  # facet frame: x, y on the facet
            slope = local[..., :2] / (2.0 * focal) if math.isfinite(focal) and focal > 0 else 0.0 * local[..., :2]
            normal = n_f - slope[..., 0:1] * r_fw[:, 0] - slope[..., 1:2] * r_fw[:, 1]
            normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
            reflected = d - 2.0 * np.sum(d * normal, axis=-1, keepdims=True) * normal
            return sky.reflectivity * sky.radiance(reflected)

        if seen_from_front:
            canvas.paint(corners_m, mirror)
            if is_target:
                q = canvas.ideal(corners_m)
                got = None if q is None else canvas.coverage(q)
                if got is not None:
                    facet_pixels.append(got)
        else:
            canvas.paint(corners_m, steel_dark)


def render(camera: TowerCamera, heliostats: list, sky: Sky, rng: np.random.Generator,
           exposure: Exposure = Exposure(), target: int = 0) -> Photo:
    """A photograph of *heliostats* (the one at index *target* is the one photographed: the exposure meters
    on it and the truth is its) taken by *camera* under *sky*.

    Returns
    -------
    Photo
        ``image`` (H, W, 3) uint8 RGB; ``truth``: ``corners_px`` {label: (N, 2) true corner pixels in the design
        outline's order} for the target's facets seen from the front, ``normal``, ``azimuth_rad``,
        ``elevation_rad``, ``spin_rad`` of the target, ``camera_rotation``, ``scale`` (DN per W/m^2/sr),
        ``saturated_fraction`` of the target's facet pixels, ``sun_in_mirrors`` (a facet pixel mirrors the
        sun's disk).
    """
    if not 0 <= target < len(heliostats):
        raise ConfigError(f"target {target} is not one of the {len(heliostats)} heliostats")
    canvas = _Canvas(camera)
    _ground(canvas, sky, rng)
    order = sorted(range(len(heliostats)),
                   key=lambda i: -float(np.linalg.norm(heliostats[i].position_m - camera.position_m)))
    facet_pixels: list = []
    for i in order:
        _paint_heliostat(canvas, heliostats[i], sky, i == target, facet_pixels)
    radiance = canvas.radiance
    if exposure.vignetting:
        h, w = canvas.shape
        v, u = np.mgrid[0:h, 0:w]
        r2 = ((u - 0.5 * (w - 1)) / (0.5 * w)) ** 2 + ((v - 0.5 * (h - 1)) / (0.5 * h)) ** 2
        radiance = radiance * (1.0 - 0.5 * exposure.vignetting * r2)[..., None]
    inside = np.zeros(canvas.shape, dtype=bool)
    for rows, cols, cov in facet_pixels:
        inside[rows, cols] |= cov > 0.99
    if exposure.scale is not None:
        scale = float(exposure.scale)
    else:
        if not inside.any():
            raise GeometryError("the photographed heliostat shows no mirror to the camera: nothing to meter on")
        scale = exposure.target_level * 255.0 / float(np.median(radiance[..., 2][inside]))
    signal = radiance * scale
    if exposure.blur_px > 0:
        signal = np.stack([ndimage.gaussian_filter(signal[..., c], exposure.blur_px, mode="nearest")
                           for c in range(3)], axis=-1)
    electrons_per_dn = exposure.full_well_e / 255.0
    noisy = signal + rng.standard_normal(signal.shape) * np.sqrt(np.clip(signal, 0.0, None) / electrons_per_dn
                                                                 + exposure.read_noise_dn ** 2)
    image = np.clip(np.round(noisy), 0, 255).astype(np.uint8)
    t = heliostats[target]
    truth = {"corners_px": facet_truth(camera, t), "normal": t.normal.tolist(), "azimuth_rad": t.azimuth_rad,
             "elevation_rad": t.elevation_rad, "spin_rad": t.spin_rad, "camera_rotation": camera.rotation.tolist(),
             "scale": scale,
             "saturated_fraction": float(np.mean(image[inside].max(axis=-1) == 255)) if inside.any() else 0.0,
             "sun_in_mirrors": bool(np.any(radiance[inside].max(axis=-1) * scale > 50 * 255))}
    return Photo(image=image, truth=truth)


def facet_truth(camera: TowerCamera, heliostat: FieldHeliostat) -> dict:
    """The true corner pixels {label: (N, 2)} of every facet whose mirror faces the camera."""
    out = {}
    for f, corners in zip(heliostat.ensemble.facets, heliostat.facet_corners_m()):
        n = heliostat.rotation @ heliostat.facet_rotations()[heliostat.ensemble.labels.index(f.label)][:, 2]
        if float(n @ (camera.position_m - corners.mean(axis=0))) > 0:
            out[f.label] = camera.project(corners)
    return out


def canting_truth(heliostat: FieldHeliostat, labels=None) -> dict:
    """Each facet's true canting error {label: {"x", "y"} mrad} over the facets *labels* (default all):
    docs/conventions.md#canting with each facet's true frame (its design canting and its error) in the true
    heliostat frame turned by T = R_y(b) R_x(a) until the errors have zero mean."""
    labels = list(heliostat.ensemble.labels if labels is None else labels)
    idx = [heliostat.ensemble.labels.index(lab) for lab in labels]
    design = [heliostat.ensemble.facets[i].rotation for i in idx]
    true = [heliostat.facet_rotations()[i] for i in idx]
    a = b = 0.0
    for _ in range(100):
        t = rotation_zyx(a, b, 0.0)
        angles = np.array([_angles(d.T @ t.T @ r) for d, r in zip(design, true)])
        da, db = angles.mean(axis=0)
        a, b = a + da, b + db
        if abs(da) < TILT_TOLERANCE_RAD and abs(db) < TILT_TOLERANCE_RAD:
            break
    t = rotation_zyx(a, b, 0.0)
    out = {}
    for lab, d, r in zip(labels, design, true):
        rx, ry = _angles(d.T @ t.T @ r)
        out[lab] = {"x": 1e3 * rx, "y": 1e3 * ry}
    return out
