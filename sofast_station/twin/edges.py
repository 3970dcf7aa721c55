"""How the facet's edge forms its image: pixel sampling, the lens's blur, a bevelled glass rim, vignetting.

The corner finder of the measurement is only as good as the edges it has been tried on. These models
draw the facet's edge in several physically different ways, each written from its own physics (none
looks at how the pipeline finds corners), so that a corner finder tuned on one of them can be tried on
the others. Every model combines with every other and with the camera's lens distortion (the twin's
camera model, any k1 the distortion inverts, e.g. |k1| <= 0.3).

Selecting a model
-----------------
Every model is a field of :class:`~sofast_station.twin.parameters.TwinOptics`, so a station file selects it
in its ``[simulation.optics]`` table, and code passes ``TwinOptics(...)`` to
:class:`~sofast_station.twin.station.TwinStation`::

    [simulation.optics]
    edge_sampling = "point"        # "area" (default), "point" or "grid"
    edge_grid = 2                  # sub-rays per pixel side for "grid"
    blur_px = 0.7                  # Gaussian point-spread function, standard deviation, pixels
    defocus_px = 1.5               # uniform-disk point-spread function, radius, pixels
    bevel_width_mm = 1.5           # a bevelled rim this wide inside the outline (0: none)
    bevel_tilt_mrad = 300.0        # its surface tilted this much outward (reflects the screen elsewhere)
    bevel_reflectance = 0.5        # its specular reflectance relative to the facet's
    vignetting = 0.6               # relative fall-off at the farthest image corner
    vignetting_exponent = 4.0      # ... as 1 - vignetting (r / r_corner)^exponent
    screen_grid = 4                # sub-rays per pixel side whose display light a pixel averages (1: centre ray)

The models
----------
(a) ``edge_sampling = "point"``: centre-ray point sampling. A pixel sees the scene along its centre ray
    only: it is wholly facet or wholly background, and a slightly tilted edge is a staircase.
(b) ``edge_sampling = "area"`` (the default): exact area sampling. A pixel's value is the light falling on
    its square: its facet coverage is the exact area of the pixel square inside the outline's image, the
    outline traced on the true surface and projected through the distorted camera as a polyline of chords
    under 0.2 px (:func:`polygon_pixel_coverage`, a signed-area accumulation that is exact for a polygon;
    the chords' sag is below 1e-5 px for any realistic curvature of the image of an edge).
    ``edge_sampling = "grid"``: a renderer that supersamples, each edge pixel the mean of
    ``edge_grid x edge_grid`` sub-rays on a regular grid (2 x 2 is a coarse one: a staircase of half pixels).
    Either way an edge pixel's light comes from its centre ray's screen point (the analytic surface
    continues past the outline).
(c) ``blur_px`` and ``defocus_px``: the lens's point-spread function, a Gaussian (standard deviation in
    pixels) and/or a uniform disk (a defocused lens's blur circle, radius in pixels), applied to the light
    before the sensor integrates it (:func:`apply_psf`); either conserves the light.
(d) ``bevel_width_mm``, ``bevel_tilt_mrad``, ``bevel_reflectance``: a glass edge ground to a narrow rim
    (a chamfer) inside the outline: the rim's surface normal is the facet's normal turned outward, away
    from the nearest side of the outline, by the tilt (mitred at the corners), so it reflects the screen at
    another angle: a small tilt shows other fringes, a large one looks past the screen and is dark, and
    its reflectance (relative to the facet's) dims it. The rim is thin: its height below the facet surface
    is neglected (a 3 mm rim tilted 0.3 rad drops 0.9 mm), only its normal differs. The outline, and the
    true corners, stay the rim's outer edge. The outline must be convex (every facet design is).
(e) ``vignetting``, ``vignetting_exponent``: radial fall-off of the irradiance,
    ``1 - vignetting (r / r_corner)^exponent`` with r the distance from the principal point and r_corner
    that of the farthest image corner; exponent 2 (the default) is the classic quadratic fall-off, larger
    exponents keep the middle bright and fall off steeply toward the corners.

(f) ``screen_grid``: how a pixel samples the display it sees in the facet. 1 (the default): at its centre
    ray's screen point. n > 1: the mean of the display's light at the screen points of n x n sub-rays on a
    regular grid over the pixel (:meth:`~sofast_station.twin.trace.FacetTrace._footprint`): the pixel
    integrates the display over its footprint on the screen, as a camera does. It matters where a pixel
    covers several display pixels (the population's heliostat and flat stations: 9-10), where the centre
    ray alone sees the display's pixel steps and the fringes' rounding at full depth.

Models (a), (b), (d) and (f) decide the pixels' coverage and screen points, so they are fixed when the station
is traced; (c) and (e) act on the light and can change with :meth:`TwinStation.with_optics`.

This module is pure numpy/scipy (no twin state): :class:`~sofast_station.twin.station.TwinStation` calls it
from a few hooks.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from scipy.ndimage import convolve, gaussian_filter

from ..errors import GeometryError
from .outline import inside_outline, signed_distance_to_outline

#: Edge sampling models (:class:`TwinOptics.edge_sampling`).
EDGE_SAMPLING = ("area", "point", "grid")

#: Longest chord of the projected outline polyline, pixels.
CHORD_PX = 0.2

#: Coverage this close to 0 or 1 is rounding: made exactly 0 or 1.
_SNAP = 1e-9

#: Fields of TwinOptics that change the trace (coverage, screen points), not only the light.
TRACE_FIELDS = ("edge_sampling", "edge_grid", "bevel_width_mm", "bevel_tilt_mrad", "screen_grid")


# ----------------------------------------------------------------- exact area coverage
def _clip_polygon(poly: np.ndarray, lo: tuple[float, float], hi: tuple[float, float]) -> np.ndarray:
    """Sutherland-Hodgman clip of a closed polygon (N, 2) to the box lo <= (x, y) <= hi."""
    for axis, bound, keep_below in ((0, lo[0], False), (0, hi[0], True), (1, lo[1], False), (1, hi[1], True)):
        if len(poly) == 0:
            break
        p = poly
        q = np.roll(poly, -1, axis=0)
        inside_p = p[:, axis] <= bound if keep_below else p[:, axis] >= bound
        inside_q = q[:, axis] <= bound if keep_below else q[:, axis] >= bound
        if inside_p.all():
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (bound - p[:, axis]) / (q[:, axis] - p[:, axis])
            cross = p + t[:, None] * (q - p)           # (used only where the side crosses the bound)
        cross[:, axis] = bound
        out = []
        for i in range(len(p)):
            if inside_p[i]:
                out.append(p[i])
                if not inside_q[i]:
                    out.append(cross[i])
            elif inside_q[i]:
                out.append(cross[i])
        poly = np.array(out).reshape(-1, 2)
    return poly


def polygon_pixel_coverage(polygon_px: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Exact area of every pixel's square inside a polygon.

    Pixel (column u, row v) is the square ``[u - 1/2, u + 1/2] x [v - 1/2, v + 1/2]`` (its centre at image
    coordinates (u, v)). Each side of the polygon is cut where it crosses a pixel boundary; a piece inside
    pixel (u, v) adds its signed trapezoid area to the pixel's right edge to (u, v) and the rest of its
    height to the pixels right of it (a running sum along each row), as a font rasteriser does. The result
    is exact for a polygon (to rounding, about 1e-13; a pixel within 1e-9 of whole or empty is made so).

    Parameters
    ----------
    polygon_px : (N, 2) array
        Closed simple polygon (u, v), pixels, either orientation (the last vertex joins the first).
    shape : (height, width)
        The image's size, pixels; the polygon is clipped to it.

    Returns
    -------
    (height, width) float64 array
        Covered fraction of each pixel's area, in [0, 1].
    """
    height, width = int(shape[0]), int(shape[1])
    poly = np.asarray(polygon_px, dtype=np.float64) + 0.5        # pixel u covers [u, u + 1) here
    if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.all(np.isfinite(poly)):
        raise GeometryError(f"polygon_px must be at least 3 finite (u, v) vertices, got shape {poly.shape}")
    coverage = np.zeros((height, width))
    poly = _clip_polygon(poly, (0.0, 0.0), (float(width), float(height)))
    if len(poly) < 3:
        return coverage
    # a window around the clipped polygon
    c0, r0 = (int(math.floor(v)) for v in poly.min(axis=0))
    c1 = min(int(math.floor(poly[:, 0].max())) + 1, width)
    r1 = min(int(math.floor(poly[:, 1].max())) + 1, height)
    poly = poly - np.array([c0, r0], dtype=np.float64)
    win_w, win_h = c1 - c0, r1 - r0
    p = poly
    q = np.roll(poly, -1, axis=0)
    # Every segment's parameters t in [0, 1] at which it crosses a grid line (plus its ends).
    ts = [np.zeros(len(p)), np.ones(len(p))]
    owners = [np.arange(len(p)), np.arange(len(p))]
    for axis in (0, 1):
        lo = np.floor(np.minimum(p[:, axis], q[:, axis])) + 1.0
        hi = np.floor(np.maximum(p[:, axis], q[:, axis]))
        count = np.maximum(hi - lo + 1.0, 0.0).astype(np.int64)
        seg = np.repeat(np.arange(len(p)), count)
        if seg.size:
            first = np.repeat(np.cumsum(count) - count, count)
            line = lo[seg] + (np.arange(seg.size) - first)
            ts.append((line - p[seg, axis]) / (q[seg, axis] - p[seg, axis]))
            owners.append(seg)
    t = np.concatenate(ts)
    owner = np.concatenate(owners)
    order = np.lexsort((t, owner))
    t, owner = t[order], owner[order]
    same = owner[1:] == owner[:-1]
    seg, ta, tb = owner[1:][same], t[:-1][same], t[1:][same]
    d = q[seg] - p[seg]
    a = p[seg] + ta[:, None] * d
    b = p[seg] + tb[:, None] * d
    mid = 0.5 * (a + b)
    ix = np.clip(np.floor(mid[:, 0]).astype(np.int64), 0, win_w)
    iy = np.clip(np.floor(mid[:, 1]).astype(np.int64), 0, max(win_h - 1, 0))
    dy = b[:, 1] - a[:, 1]
    frac = mid[:, 0] - ix                                         # mean x of the piece within its pixel
    acc = np.zeros((max(win_h, 1), win_w + 2))
    np.add.at(acc, (iy, ix), dy * (1.0 - frac))
    np.add.at(acc, (iy, ix + 1), dy * frac)
    cov = np.abs(np.cumsum(acc, axis=1)[:win_h, :win_w])
    # whole and empty pixels exactly 1 and 0 (the running sum leaves rounding of order 1e-15 on them)
    cov[cov > 1.0 - _SNAP] = 1.0
    cov[cov < _SNAP] = 0.0
    coverage[r0:r1, c0:c1] = cov
    return coverage


def densify_outline(outline_m: np.ndarray, samples_per_side: np.ndarray | int) -> np.ndarray:
    """Points along a closed outline, *samples_per_side* per side (the corners included, each once).

    Returns
    -------
    (M, 2) array, metres; side k's points start at corner k.
    """
    corners = np.asarray(outline_m, dtype=np.float64)
    n = np.broadcast_to(np.asarray(samples_per_side, dtype=np.int64), (len(corners),))
    pieces = []
    for k, (c0, c1) in enumerate(zip(corners, np.roll(corners, -1, axis=0))):
        s = np.arange(int(n[k]))[:, None] / float(n[k])
        pieces.append(c0 + s * (c1 - c0))
    return np.concatenate(pieces)


def projected_outline_px(outline_m: np.ndarray, to_camera, camera, shape: tuple[int, int]) -> np.ndarray:
    """The outline's image as a polyline of chords under :data:`CHORD_PX` (its corners among the vertices).

    Parameters
    ----------
    outline_m : (N, 2) array
        Polygon corners in the facet's (x, y), metres.
    to_camera : callable
        ``to_camera(xy) -> (M, 3)``: camera-frame points, metres, of facet points (x, y) on the surface.
    camera : TwinCamera
        Projects them (``project``) and checks the projection against its inverse (``pixel_rays``).
    shape : (height, width)
        The image's size, pixels: points that project into it (or within 2 px of it) are checked.

    Returns
    -------
    (M, 2) array, pixels.

    Raises
    ------
    GeometryError
        If the outline does not project (behind the camera), or projects where the distortion folds over
        (there its image would be false).
    """
    outline = np.asarray(outline_m, dtype=np.float64)
    coarse = camera.project(to_camera(densify_outline(outline, 64)))
    if not np.all(np.isfinite(coarse)):
        raise GeometryError("the facet's outline does not project into the camera (a point lies behind it): "
                            "check the layout and the facet placement")
    steps = np.hypot(*np.diff(np.vstack([coarse, coarse[:1]]), axis=0).T).reshape(len(outline), 64)
    n = np.maximum(np.ceil(steps.sum(axis=1) * 1.5 / CHORD_PX).astype(np.int64), 64)
    points_cam = to_camera(densify_outline(outline, n))
    uv = camera.project(points_cam)
    chord = np.hypot(*np.diff(np.vstack([uv, uv[:1]]), axis=0).T)
    height, width = shape
    seen = (uv[:, 0] > -2) & (uv[:, 0] < width + 1) & (uv[:, 1] > -2) & (uv[:, 1] < height + 1)
    folded = not (np.all(np.isfinite(uv)) and chord.max() <= 2 * CHORD_PX)
    if not folded and np.any(seen):
        direct = points_cam[seen] / np.linalg.norm(points_cam[seen], axis=1, keepdims=True)
        try:
            folded = float(np.max(np.abs(camera.pixel_rays(uv[seen, 0], uv[seen, 1]) - direct))) > 1e-7
        except GeometryError:
            folded = True
    if folded:
        raise GeometryError("the facet's outline does not project smoothly into the camera (its distortion "
                            "folds over there): check the layout and the camera's distortion, or use "
                            "edge_sampling = 'grid' or 'point'")
    return uv


# ----------------------------------------------------------------- bevelled rim
def _outward_normals(outline_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) outward unit normals of the sides of a convex outline and (N,) offsets c, so that
    ``normal . p - c`` is the signed distance from side k's line (positive outside)."""
    corners = np.asarray(outline_m, dtype=np.float64)
    nxt = np.roll(corners, -1, axis=0)
    edge = nxt - corners
    area2 = float(np.sum(corners[:, 0] * nxt[:, 1] - nxt[:, 0] * corners[:, 1]))
    sign = 1.0 if area2 > 0 else -1.0                             # counter-clockwise: outward is (ey, -ex)
    normal = sign * np.column_stack([edge[:, 1], -edge[:, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    cross = edge[:, 0] * np.roll(edge, -1, axis=0)[:, 1] - edge[:, 1] * np.roll(edge, -1, axis=0)[:, 0]
    if not (np.all(sign * cross > 0)):
        raise GeometryError("a bevelled rim needs a convex facet outline; this outline is not convex")
    return normal, np.sum(normal * corners, axis=1)


def inset_outline(outline_m: np.ndarray, width_m: float) -> np.ndarray:
    """The convex outline moved inward by *width_m* on every side (the rim's inner edge), metres.

    Raises
    ------
    GeometryError
        If the outline is not convex or the rim is too wide for it.
    """
    normal, offset = _outward_normals(outline_m)
    offset = offset - float(width_m)
    n_next, c_next = np.roll(normal, -1, axis=0), np.roll(offset, -1)
    det = normal[:, 0] * n_next[:, 1] - normal[:, 1] * n_next[:, 0]
    # corner k+1 of the inset outline: where side k's and side k+1's moved lines meet
    x = (offset * n_next[:, 1] - c_next * normal[:, 1]) / det
    y = (normal[:, 0] * c_next - n_next[:, 0] * offset) / det
    inner = np.roll(np.column_stack([x, y]), 1, axis=0)
    side_in = np.roll(inner, -1, axis=0) - inner
    side_out = np.roll(np.asarray(outline_m, float), -1, axis=0) - np.asarray(outline_m, float)
    if np.any(np.sum(side_in * side_out, axis=1) <= 0):
        raise GeometryError(f"a bevelled rim {1e3 * width_m:g} mm wide does not fit inside the facet outline")
    return inner


def rim_distance_and_direction(x_m: np.ndarray, y_m: np.ndarray, outline_m: np.ndarray):
    """Distance inside the nearest side of a convex outline, and that side's outward direction.

    Returns
    -------
    depth_m : (M,) array
        Distance from the nearest side's line, metres, positive inside.
    outward : (M, 2) array
        Unit outward normal (x, y) of that side.
    """
    normal, offset = _outward_normals(outline_m)
    signed = np.column_stack([x_m, y_m]) @ normal.T - offset      # (M, N), positive outside
    nearest = np.argmax(signed, axis=1)
    return -signed[np.arange(len(nearest)), nearest], normal[nearest]


def tilt_normals(normal: np.ndarray, outward_xy: np.ndarray, tilt_rad: float) -> np.ndarray:
    """Unit normals (M, 3) turned by *tilt_rad* toward the outward direction (x, y, 0) (a chamfer)."""
    out = np.column_stack([outward_xy, np.zeros(len(outward_xy))])
    out -= np.sum(out * normal, axis=1, keepdims=True) * normal
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return math.cos(tilt_rad) * normal + math.sin(tilt_rad) * out


# ----------------------------------------------------------------- sub-pixel grid
def grid_offsets(n: int) -> np.ndarray:
    """``n * n`` sub-pixel offsets (du, dv) on a regular grid, the centres of the n x n sub-squares, pixels."""
    s = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(s, s)
    return np.column_stack([du.ravel(), dv.ravel()])


# ----------------------------------------------------------------- a station's edge pixels
def _outline_image(twin, outline_m: np.ndarray) -> np.ndarray:
    """The image polyline (M, 2), pixels, of an outline traced on the twin's true surface."""
    def to_camera(xy):
        return twin.facet_to_camera.apply(np.column_stack([xy, twin.surface.height(xy[:, 0], xy[:, 1])]))

    return projected_outline_px(outline_m, to_camera, twin.camera, twin.geometry.camera.shape)


def pixel_coverage(twin, pixel_idx: np.ndarray, hits_facet_m: np.ndarray, footprint_m: np.ndarray,
                   band_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Facet and rim coverage of a twin's pixels under its optics' edge model.

    Parameters
    ----------
    twin : TwinStation
        Uses its camera, true surface, design outline, poses and optics (``edge_sampling``, ``edge_grid``,
        ``bevel_width_mm``).
    pixel_idx : (M,) int array
        Flat image indices (row x width + column) of the pixels, candidates near or inside the outline.
    hits_facet_m : (M, 3) array
        Where each pixel's centre ray meets the true surface, true facet frame, metres.
    footprint_m : (M,) array
        Size of a pixel on the surface there, metres.
    band_px : float
        Half-width, pixels, of the band about the outline in which ``"grid"`` sends sub-rays.

    Returns
    -------
    coverage : (M,) array
        Fraction of each pixel's area inside the outline (the rim included), [0, 1].
    rim : (M,) array
        Fraction of each pixel's area on the bevelled rim (0 without one), [0, coverage].
    """
    optics = twin.optics
    outline = np.asarray(twin.design.outline_m, dtype=np.float64)
    width_m = 1e-3 * optics.bevel_width_mm
    height, width = twin.geometry.camera.shape
    x, y = hits_facet_m[:, 0], hits_facet_m[:, 1]
    inside = inside_outline(x, y, outline)
    depth = rim_distance_and_direction(x, y, outline)[0] if width_m > 0 else None

    if optics.edge_sampling == "point":
        coverage = inside.astype(np.float64)
        rim = (inside & (depth < width_m)).astype(np.float64) if width_m > 0 else np.zeros_like(coverage)
        return coverage, rim

    if optics.edge_sampling == "area":
        full = polygon_pixel_coverage(_outline_image(twin, outline), (height, width)).ravel()
        coverage = full[pixel_idx]
        if width_m <= 0:
            return coverage, np.zeros_like(coverage)
        inner = polygon_pixel_coverage(_outline_image(twin, inset_outline(outline, width_m)), (height, width))
        return coverage, np.clip(coverage - inner.ravel()[pixel_idx], 0.0, None)

    # "grid": sub-rays on a regular grid for the pixels near the outline (or the rim's inner edge)
    sd = signed_distance_to_outline(x, y, outline)
    band_m = band_px * footprint_m
    near = np.abs(sd) < band_m
    if width_m > 0:
        near |= (sd <= 0) & (-sd < width_m + band_m)
    coverage = inside.astype(np.float64)
    rim = (inside & (depth < width_m)).astype(np.float64) if width_m > 0 else np.zeros_like(coverage)
    offsets = grid_offsets(optics.edge_grid)
    v_cam_facet = twin.camera_to_facet.translation
    where = np.flatnonzero(near)
    chunk_px = max(1, 262_144 // len(offsets))
    for start in range(0, where.size, chunk_px):
        pos = where[start:start + chunk_px]
        idx = pixel_idx[pos]
        u = (idx % width).astype(np.float64)[:, None] + offsets[None, :, 0]
        v = (idx // width).astype(np.float64)[:, None] + offsets[None, :, 1]
        rays = twin.camera_to_facet.apply_vector(twin.camera.pixel_rays(u.ravel(), v.ravel()))
        t = twin.surface.intersect(v_cam_facet, rays)
        hit = v_cam_facet + t[:, None] * rays
        sub_in = inside_outline(hit[:, 0], hit[:, 1], outline) & np.isfinite(t)
        coverage[pos] = sub_in.reshape(pos.size, -1).mean(axis=1)
        if width_m > 0:
            sub_depth = rim_distance_and_direction(hit[:, 0], hit[:, 1], outline)[0]
            rim[pos] = (sub_in & (sub_depth < width_m)).reshape(pos.size, -1).mean(axis=1)
    return coverage, rim


# ----------------------------------------------------------------- point-spread function
@functools.lru_cache(maxsize=8)
def disk_kernel(radius_px: float) -> np.ndarray:
    """A uniform disk of *radius_px* integrated over each pixel (64 x 64 sub-samples), summing to 1
    (read-only; kept per radius)."""
    half = int(math.ceil(radius_px - 0.5)) if radius_px > 0.5 else 0
    sub = grid_offsets(64)
    centres = np.arange(-half, half + 1, dtype=np.float64)
    u = centres[None, :, None] + sub[None, None, :, 0]
    v = centres[:, None, None] + sub[None, None, :, 1]
    kernel = np.mean(u * u + v * v <= radius_px * radius_px, axis=2)
    if kernel.sum() == 0:
        kernel[half, half] = 1.0
    kernel = kernel / kernel.sum()
    kernel.setflags(write=False)
    return kernel


def has_psf(optics) -> bool:
    """Whether the optics blur the image (a Gaussian or a disk point-spread function)."""
    return optics.blur_px > 0 or optics.defocus_px > 0


def apply_psf(dn: np.ndarray, optics) -> np.ndarray:
    """A frame's signal spread by the lens's point-spread function(s) (Gaussian, then disk), float32.

    Both filters are normalised and continue the borders by their nearest pixel, so a uniform level (the
    black level, which is not light) passes unchanged and the light of a scene away from the image's
    borders is conserved.
    """
    if optics.blur_px > 0:
        dn = gaussian_filter(dn, float(optics.blur_px), mode="nearest", truncate=4.0)
    if optics.defocus_px > 0:
        dn = convolve(np.asarray(dn, dtype=np.float32), disk_kernel(float(optics.defocus_px)).astype(np.float32),
                      mode="nearest")
    return dn


# ----------------------------------------------------------------- vignetting
def vignetting_factor(shape: tuple[int, int], cx: float, cy: float, strength: float, exponent: float) -> np.ndarray:
    """Relative irradiance (H, W): ``1 - strength (r / r_corner)^exponent``, 1 at the principal point (cx, cy).

    r_corner is the distance from (cx, cy) to the farthest image corner (pixel centres).
    """
    height, width = int(shape[0]), int(shape[1])
    v_px, u_px = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = (u_px - cx) ** 2 + (v_px - cy) ** 2
    r2_corner = max((u - cx) ** 2 + (v - cy) ** 2 for u in (0, width - 1) for v in (0, height - 1))
    if r2_corner <= 0:
        return np.ones_like(r2)
    if exponent == 2.0:
        return 1.0 - strength * r2 / r2_corner
    return 1.0 - strength * (r2 / r2_corner) ** (0.5 * exponent)
