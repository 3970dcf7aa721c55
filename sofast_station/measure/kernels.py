"""Compiled per-point kernels (numba) for the analysis' hot loops: arctangents and the four-step phase.

numpy's ``arctan`` and ``arctan2`` call the C library once per element on a machine without AVX-512
(12 to 25 ns each here): the phase of 590,000 pixels in four sets and the slope residuals' eight
arctangents per point were a quarter of an analysis' CPU time. The kernels here evaluate the arctangent
as a polynomial the compiler vectorises (about 1 ns per element), loop once over the points, and release
the GIL, so two threads of the analysis' pool run them at once.

Accuracy (tested in tests/measure/test_kernels.py against numpy over the whole range):

* :func:`atan` (float64): within 3 units in the last place of numpy's ``arctan`` (the same value on
  85 % of arguments); the slope residuals atan(s) - atan(s_model) move by at most 1e-15 mrad per point;
* :func:`phase_counts`: the four-step phase from whole counts computed in float64 and rounded once to
  float32, so within one float32 step (4.8e-7 rad) of ``pi - atan2(s, -c)`` in float32 arithmetic, which
  it replaces (a thousandth of the phase noise of 1 DN on 50 DN of modulation); modulation and
  consistency are the same values.

Range reduction of atan(x): |x| > 1 uses pi/2 - atan(1/|x|); t > tan(pi/8) uses
pi/4 + atan((t - 1)/(t + 1)); on |u| <= tan(pi/8), atan(u) = u + u^3 Q(u^2) with Q the degree-10
Chebyshev interpolant (converted to powers of z = u^2) of the arctangent series' (atan(u) - u)/u^3 on
z in [0, tan^2(pi/8)], computed with numpy.polynomial (error below 1e-15 on Q, 4e-17 rad on atan).

Every kernel is element-wise: a point's result does not depend on how the points are split between
calls or threads (so the analysis is the same bits on one thread or two).
"""

from __future__ import annotations

import math

import numpy as np

from .compiled import kernel

#: (atan(u) - u)/u^3 as a polynomial in z = u^2 on [0, tan^2(pi/8)], lowest power first.
_Q = (-0.3333333333333327, 0.19999999999954654, -0.14285714278306827, 0.11111110596745237,
      -0.0909088993853778, 0.0769188120783656, -0.06660656571035933, 0.05827357429554711,
      -0.049356523858863424, 0.03517335366632264, -0.014482933736871916)
_TAN_PI_8 = math.tan(math.pi / 8.0)
_PI = math.pi
_PI_2 = math.pi / 2.0
_PI_4 = math.pi / 4.0

#: Compile options: no GIL (two pool threads run kernels at once), cached on disk, numpy's float semantics.
_JIT = {"nogil": True, "cache": True, "error_model": "numpy", "boundscheck": False}
#: The arctangent's polynomial with fused multiply-adds (a third faster); the kernels that must give numpy's
#: bits (:func:`reflect`) are compiled without them.
_FMA = {**_JIT, "fastmath": {"contract"}}
#: Sums the compiler may regroup into vector lanes (the same bits on every run on a machine; one call sums
#: all its points, so the grouping does not depend on threads).
_VECTOR_SUMS = {**_JIT, "fastmath": {"contract", "reassoc"}}


@kernel(inline="always", **_FMA)
def _atan_reduced(u):
    """atan(u) for |u| <= tan(pi/8)."""
    z = u * u
    q = _Q[10]
    q = q * z + _Q[9]
    q = q * z + _Q[8]
    q = q * z + _Q[7]
    q = q * z + _Q[6]
    q = q * z + _Q[5]
    q = q * z + _Q[4]
    q = q * z + _Q[3]
    q = q * z + _Q[2]
    q = q * z + _Q[1]
    q = q * z + _Q[0]
    return u + u * z * q


@kernel(inline="always", **_FMA)
def _atan_unit(t):
    """atan(t) for 0 <= t <= 1 (both reductions computed and one selected: no branch to mispredict)."""
    big = t > _TAN_PI_8
    reduced = (t - 1.0) / (t + 1.0)
    u = reduced if big else t
    r = _atan_reduced(u)
    offset = _PI_4 if big else 0.0
    return r + offset


@kernel(inline="always", **_FMA)
def _atan_scalar(x):
    """atan(x), radians, for any float64 x (nan stays nan; +-inf gives +-pi/2)."""
    a = abs(x)
    inv = a > 1.0
    recip = 1.0 / a
    t = recip if inv else a
    r = _atan_unit(t)
    flipped = _PI_2 - r
    r = flipped if inv else r
    return math.copysign(r, x)


@kernel(**_FMA)
def _atan_into(x, out):
    for i in range(x.size):
        out[i] = _atan_scalar(x[i])


def atan(x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Element-wise arctangent of a 1-D float64 array, radians (numpy's ``arctan`` to 3 units in the last
    place); *out* may be *x* itself."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    if x.ndim != 1:
        raise ValueError(f"atan takes a 1-D array, got shape {x.shape}")
    if out is None:
        out = np.empty_like(x)
    _atan_into(x, out)
    return out


@kernel(**_FMA)
def _phase_counts_into(frames, phase, modulation, consistency):
    for j in range(frames.shape[1]):
        i0 = np.int32(frames[0, j])
        i1 = np.int32(frames[1, j])
        i2 = np.int32(frames[2, j])
        i3 = np.int32(frames[3, j])
        s = np.float64(i1 - i3)
        c = np.float64(i0 - i2)
        # pi - atan2(s, -c): atan2(s, c) already in [0, 2 pi); s = 0 gives 0 (c >= 0) or pi (c < 0)
        a_s = abs(s)
        a_c = abs(c)
        if a_s == 0.0:
            phi = 0.0 if c >= 0.0 else _PI
        else:
            swap = a_s > a_c
            t = a_c / a_s if swap else a_s / a_c
            r = _atan_unit(t)                      # atan of the smaller over the larger
            r = _PI_2 - r if swap else r           # atan2(|s|, |c|)
            r = _PI - r if c < 0.0 else r          # atan2(|s|, c)
            phi = r if s > 0.0 else 2.0 * _PI - r
        phase[j] = np.float32(phi)
        # s^2 + c^2 is exact in float64 and its square root rounded once to float32 is the correctly
        # rounded float32 square root (float32's own for 8-bit counts, whose sum is exact there too)
        modulation[j] = np.float32(math.sqrt(s * s + c * c)) * np.float32(0.5)
        consistency[j] = np.float32((i0 + i2) - (i1 + i3))


def phase_counts(frames: np.ndarray, phase: np.ndarray, modulation: np.ndarray, consistency: np.ndarray) -> None:
    """Phase (rad, [0, 2 pi)), modulation (DN) and consistency residual (DN) of a (4, n) block of 8- or
    16-bit counts with shifts 0, pi/2, pi, 3 pi/2, into the float32 arrays of length n given."""
    _phase_counts_into(frames, phase, modulation, consistency)


@kernel(inline="always", **_JIT)
def _rotate_shift(rot, a, b, c, s0, s1, s2):
    """rot @ (a, b, c) + (s0, s1, s2), each row summed left to right as :func:`~.camera.to_frame` does."""
    return (((rot[0, 0] * a + rot[0, 1] * b) + rot[0, 2] * c) + s0,
            ((rot[1, 0] * a + rot[1, 1] * b) + rot[1, 2] * c) + s1,
            ((rot[2, 0] * a + rot[2, 1] * b) + rot[2, 2] * c) + s2)


@kernel(inline="always", **_JIT)
def _law_of_reflection(px, py, pz, cx, cy, cz, tx, ty, tz):
    """The slopes (s_x, s_y) at the point p seen from the camera centre c showing the screen point t, in the
    order of :func:`~.surface.normal_slopes` (n = a |b| + b |a| with a = c - p, b = t - p)."""
    ax, ay, az = cx - px, cy - py, cz - pz
    bx, by, bz = tx - px, ty - py, tz - pz
    la = math.sqrt((ax * ax + ay * ay) + az * az)
    lb = math.sqrt((bx * bx + by * by) + bz * bz)
    nx = ax * lb + bx * la
    ny = ay * lb + by * la
    nz = az * lb + bz * la
    return -(nx / nz), -(ny / nz)


@kernel(inline="always", **_JIT)
def _reflect_one(rot, t0, t1_, t2_, ox, oy, oz, k_x, k_y, qc, a_, b_, e_, r0, r1, r2, w0, w1, w2):
    """One ray's point on the quadratic and the law of reflection's slopes there (:func:`reflect`)."""
    ux, uy, uz = _rotate_shift(rot, r0, r1, r2, 0.0, 0.0, 0.0)
    tx, ty, tz = _rotate_shift(rot, w0, w1, w2, t0, t1_, t2_)
    # intersect_quadratic
    qa = (ux * a_ * ux + uy * b_ * uy) + ux * e_ * uy
    qb = (ux * k_x + uy * k_y) - uz
    disc = qb * qb - qa * 4.0 * qc
    miss = disc < 0.0
    root = math.sqrt(disc if (disc >= 0.0 or disc != disc) else 0.0)
    q = (math.copysign(root, qb) + qb) * -0.5
    t1 = qc / q
    t2 = q / qa
    t1 = t1 if t1 > 0.0 else np.inf
    t2 = t2 if t2 > 0.0 else np.inf
    t = t2 if (t2 < t1 or t2 != t2) else t1
    if miss or not np.isfinite(t):
        t = np.nan
    px = t * ux + ox
    py = t * uy + oy
    pz = t * uz + oz
    s_x, s_y = _law_of_reflection(px, py, pz, ox, oy, oz, tx, ty, tz)
    return px, py, pz, s_x, s_y


@kernel(**_JIT)
def _reflect_into(r0, r1, r2, w0_, w1_, w2_, rot, trans, origin, qk, coeffs, p0, p1, p2, s0, s1):
    a_, b_, e_ = coeffs[0], coeffs[1], coeffs[4]
    ox, oy, oz = origin[0], origin[1], origin[2]
    t0, t1_, t2_ = trans[0], trans[1], trans[2]
    k_x, k_y, qc = qk[0], qk[1], qk[2]
    for j in range(r0.size):
        p0[j], p1[j], p2[j], s0[j], s1[j] = _reflect_one(rot, t0, t1_, t2_, ox, oy, oz, k_x, k_y, qc, a_, b_, e_,
                                                         r0[j], r1[j], r2[j], w0_[j], w1_[j], w2_[j])


@kernel(**_JIT)
def _reflect_blend_into(r0, r1, r2, w0_, w1_, w2_, rot, trans, origin, qk, coeffs, scale, p0, p1, p2, s0, s1):
    a_, b_, e_ = coeffs[0], coeffs[1], coeffs[4]
    ox, oy, oz = origin[0], origin[1], origin[2]
    t0, t1_, t2_ = trans[0], trans[1], trans[2]
    k_x, k_y, qc = qk[0], qk[1], qk[2]
    missed = 0
    for j in range(r0.size):
        px, py, pz, sx, sy = _reflect_one(rot, t0, t1_, t2_, ox, oy, oz, k_x, k_y, qc, a_, b_, e_,
                                          r0[j], r1[j], r2[j], w0_[j], w1_[j], w2_[j])
        if not (np.isfinite(sx) and np.isfinite(sy)):
            missed += 1
        # base + (moved - base) * scale, numpy's order
        c = scale[j]
        p0[j] = p0[j] + (px - p0[j]) * c
        p1[j] = p1[j] + (py - p1[j]) * c
        p2[j] = p2[j] + (pz - p2[j]) * c
        s0[j] = s0[j] + (sx - s0[j]) * c
        s1[j] = s1[j] + (sy - s1[j]) * c
    return missed


def _reflect_args(rays_cam, screen_cam_m, rotation, translation, coeffs, origin, lo, hi) -> list:
    """:func:`reflect`'s kernel arguments before the outputs: the columns lo:hi, the frame, the quadratic's
    coefficients of the ray parameter."""
    a_, b_, c_, d_, e_, f_ = (float(v) for v in coeffs)
    origin = translation if origin is None else origin
    ox, oy, oz = (float(v) for v in origin)
    qk = np.array([2.0 * a_ * ox + c_ + e_ * oy, 2.0 * b_ * oy + d_ + e_ * ox,
                   a_ * ox * ox + b_ * oy * oy + c_ * ox + d_ * oy + e_ * ox * oy + f_ - oz])
    sl = slice(lo, hi)        # (slices: a loop over 0..n-1 vectorises, one over lo..hi does not)
    return [*(c[sl] for c in rays_cam), *(c[sl] for c in screen_cam_m),
            np.array(rotation, dtype=np.float64), np.array(translation, dtype=np.float64),   # (writable
            np.array([ox, oy, oz]), qk,                                                       # copies)
            np.asarray(coeffs, dtype=np.float64)]


def reflect(rays_cam: np.ndarray, screen_cam_m: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
            coeffs: np.ndarray, points: np.ndarray, slopes: np.ndarray, lo: int, hi: int,
            origin: np.ndarray | None = None) -> None:
    """Points of the quadratic model surface *coeffs* seen along camera-frame unit rays *rays_cam* (3, N),
    and the slopes the law of reflection gives with the camera-frame screen points *screen_cam_m* (3, N),
    both taken into the frame (*rotation*, *translation*) leads to, for the columns lo:hi, into *points*
    (3, N, metres) and *slopes* (2, N). The rays start at *origin* in that frame (the camera centre; by
    default *translation*, where the camera frame's origin goes).

    The arithmetic of :func:`~.camera.to_frame`, :func:`~.surface.intersect_quadratic` and
    :func:`~.surface.normal_slopes` in the same order, in one pass: the same bits (tested). With the
    identity rotation and a zero translation, those of the last two alone."""
    sl = slice(lo, hi)
    _reflect_into(*_reflect_args(rays_cam, screen_cam_m, rotation, translation, coeffs, origin, lo, hi),
                  *(c[sl] for c in points), *(c[sl] for c in slopes))


def reflect_blend(rays_cam: np.ndarray, screen_cam_m: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                  coeffs: np.ndarray, scale: np.ndarray, points: np.ndarray, slopes: np.ndarray, lo: int, hi: int,
                  origin: np.ndarray | None = None) -> int:
    """:func:`reflect` with the model *coeffs*, each of the columns lo:hi of *points* (3, N) and *slopes*
    (2, N) moved toward it in place: ``base + (reflected - base) * scale`` (*scale* (N,)), numpy's
    arithmetic in one pass, the same bits (tested); the intersection with a model raised a little, and
    each pixel moved to its own height above the model to first order (:func:`~.boresight.close_on_all_points`).
    Returns how many of those columns' reflected slopes are not finite (rays that miss)."""
    sl = slice(lo, hi)
    return int(_reflect_blend_into(*_reflect_args(rays_cam, screen_cam_m, rotation, translation, coeffs, origin,
                                                  lo, hi), scale[sl], *(c[sl] for c in points),
                                   *(c[sl] for c in slopes)))


@kernel(**_JIT)
def _to_frame_every_into(v0, v1, v2, rot, shift, step, out):
    for i in range(out.shape[1]):
        j = i * step
        out[0, i], out[1, i], out[2, i] = _rotate_shift(rot, v0[j], v1[j], v2[j], shift[0], shift[1], shift[2])


def to_frame_every(v: np.ndarray, rotation: np.ndarray, translation: np.ndarray, step: int,
                   translate: bool = True) -> np.ndarray:
    """:func:`~.camera.to_frame` of every *step*-th column of the (3, N) *v* (points, or directions with
    ``translate=False``), gathered and transformed in one pass (the same bits): (3, ceil(N / step))."""
    shift = np.array(translation, dtype=np.float64) if translate else np.zeros(3)
    out = np.empty((3, len(range(0, v.shape[1], step))))
    _to_frame_every_into(v[0], v[1], v[2], np.array(rotation, dtype=np.float64), shift, int(step), out)
    return out


@kernel(**_JIT)
def _normal_slopes_into(px, py, pz, camera, tx_, ty_, tz_, s0, s1):
    cx, cy, cz = camera[0], camera[1], camera[2]
    for j in range(px.size):
        s0[j], s1[j] = _law_of_reflection(px[j], py[j], pz[j], cx, cy, cz, tx_[j], ty_[j], tz_[j])


def normal_slopes(points: np.ndarray, camera_m: np.ndarray, screen_points_m: np.ndarray) -> np.ndarray:
    """:func:`~.surface.normal_slopes` (the law of reflection's slopes at *points* (3, N) seen from *camera_m*
    and showing *screen_points_m* (3, N)) in one compiled pass, the same bits: (2, N)."""
    n = points.shape[1]
    out = np.empty((2, n))
    p = [np.ascontiguousarray(points[k], dtype=np.float64) for k in range(3)]
    t = [np.ascontiguousarray(screen_points_m[k], dtype=np.float64) for k in range(3)]
    _normal_slopes_into(*p, np.array(camera_m, dtype=np.float64), *t, out[0], out[1])
    return out


@kernel(**_FMA)
def _residuals_into(x, y, s_x, s_y, lin, cubic, o0, o1, o2, o3, o4, o5):
    # lin: per linear model (design, parabola) 2A, C, E, 2B, D; cubic: x0, y0, h, then the x and y slopes'
    # coefficients of 1, u, v, u^2, uv, v^2 (every coefficient a local: the loop reads only the points)
    a0, c0, e0, b0, d0 = lin[0], lin[1], lin[2], lin[3], lin[4]
    a1, c1, e1, b1, d1 = lin[5], lin[6], lin[7], lin[8], lin[9]
    x0, y0, h = cubic[0], cubic[1], cubic[2]
    p0, p1, p2, p3, p4, p5 = cubic[3], cubic[4], cubic[5], cubic[6], cubic[7], cubic[8]
    q0, q1, q2, q3, q4, q5 = cubic[9], cubic[10], cubic[11], cubic[12], cubic[13], cubic[14]
    for j in range(x.size):
        xj = x[j]
        yj = y[j]
        ax = _atan_scalar(s_x[j])
        ay = _atan_scalar(s_y[j])
        o0[j] = (ax - _atan_scalar((a0 * xj + c0) + e0 * yj)) * 1000.0
        o1[j] = (ay - _atan_scalar((b0 * yj + d0) + e0 * xj)) * 1000.0
        o2[j] = (ax - _atan_scalar((a1 * xj + c1) + e1 * yj)) * 1000.0
        o3[j] = (ay - _atan_scalar((b1 * yj + d1) + e1 * xj)) * 1000.0
        u = (xj - x0) / h
        v = (yj - y0) / h
        uu = u * u
        uv = u * v
        vv = v * v
        cx = ((((u * p1 + p0) + v * p2) + uu * p3) + uv * p4) + vv * p5
        cy = ((((u * q1 + q0) + v * q2) + uu * q3) + uv * q4) + vv * q5
        o4[j] = (ax - _atan_scalar(cx)) * 1000.0
        o5[j] = (ay - _atan_scalar(cy)) * 1000.0


def model_residuals(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray, linear: list, cubic: np.ndarray,
                    out: np.ndarray, lo: int, hi: int) -> None:
    """Slope residuals e = atan(s_measured) - atan(s_model), mrad, of the points lo:hi against two quadratic
    models and a cubic, into *out* (6, N): e_x, e_y of each model in turn.

    *linear*: per quadratic model its coefficients (A, B, C, D, E, F); *cubic*: (x0, y0, h, the x slope's
    coefficients of 1, u, v, u^2, uv, v^2, then the y slope's), u = (x - x0)/h, v = (y - y0)/h. The model
    slopes are formed in the order of :func:`~.surface.surface_slopes_of_points` and
    :meth:`~.fit.CubicFit.slopes` (the same bits); the arctangents are :func:`atan`'s."""
    lin = np.array([v for a, b, c, d, e, _ in linear for v in (2.0 * a, c, e, 2.0 * b, d)], dtype=np.float64)
    sl = slice(lo, hi)        # (slices: a loop over 0..n-1 vectorises, one over lo..hi does not)
    _residuals_into(x[sl], y[sl], s_x[sl], s_y[sl], lin, np.asarray(cubic, dtype=np.float64), *(o[sl] for o in out))


# ------------------------------------------------------------------------- the four-step residuals' harmonics
_PIO2_HI = 1.5707963267341256          # pi/2 split in two (Cody-Waite): k * _PIO2_HI is exact for k < 2^20
_PIO2_LO = 6.077100506506192e-11
_TWO_OVER_PI = 2.0 / math.pi


@kernel(inline="always", **_FMA)
def _sincos(x):
    """(sin x, cos x) of a float64 |x| < 1e5: quadrant reduction, then Taylor polynomials on |r| <= pi/4
    (truncation below 3e-14), the quadrant chosen by selects."""
    k = np.rint(x * _TWO_OVER_PI)
    r = (x - k * _PIO2_HI) - k * _PIO2_LO
    z = r * r
    sr = r + r * z * (-1.0 / 6.0 + z * (1.0 / 120.0 + z * (-1.0 / 5040.0 + z * (1.0 / 362880.0 + z * (
        -1.0 / 39916800.0 + z * (1.0 / 6227020800.0))))))
    cr = 1.0 - 0.5 * z + z * z * (1.0 / 24.0 + z * (-1.0 / 720.0 + z * (1.0 / 40320.0 + z * (
        -1.0 / 3628800.0 + z * (1.0 / 479001600.0 + z * (-1.0 / 87178291200.0))))))
    q = np.int64(k) & 3
    odd = (q & 1) == 1
    sin_x = cr if odd else sr
    cos_x = sr if odd else cr
    sin_x = -sin_x if q >= 2 else sin_x
    cos_x = -cos_x if (q == 1 or q == 2) else cos_x
    return sin_x, cos_x


@kernel(**_FMA)
def _cleaned_into(residual, phase, modulation, level, has_level, h2m, h3m, own0, own1, out):
    # float32 throughout; cos and sin of 2 phi from :func:`_sincos`
    two = np.float32(2.0)
    four_h2 = h2m[0]
    h0m = h2m[1]
    minus_four_h3 = h3m[0]
    h1p = h3m[1]
    for j in range(residual.size):
        phi2 = phase[j] * two
        s2d, c2d = _sincos(np.float64(phi2))
        c2 = np.float32(c2d)
        s2 = np.float32(s2d)
        t = c2 * c2
        t = t * four_h2
        t = t + h0m
        t = t * c2
        u = s2 * s2
        u = u * minus_four_h3
        u = u + h1p
        u = u * s2
        t = t + u
        t = t * modulation[j]
        t = t + own0
        if has_level:
            t = t + level[j] * own1
        out[j] = residual[j] - t


def cleaned_residuals(residual: np.ndarray, phase: np.ndarray, modulation: np.ndarray, level: np.ndarray | None,
                      harmonic, own) -> np.ndarray:
    """A four-step set's residual (float32, DN) with its fitted offset (and level term) and harmonics removed:
    r - (b (h0 cos 2phi + h1 sin 2phi + h2 cos 6phi + h3 sin 6phi) + own_0 [+ own_1 level]), in float32 as
    b (cos 2phi (h0 - 3 h2 + 4 h2 cos^2 2phi) + sin 2phi (h1 + 3 h3 - 4 h3 sin^2 2phi)) (cos 6phi = cos 2phi
    (4 cos^2 2phi - 3), sin 6phi = sin 2phi (3 - 4 sin^2 2phi)), one pass over the pixels: within a few float32
    steps of the model in double precision (tested; numpy's float32 cosine and sine gave the same to their
    last bits)."""
    h0, h1, h2, h3 = (np.float32(v) for v in harmonic)
    four_h2 = np.float32(4.0) * h2
    h0m = h0 - np.float32(3.0) * h2
    minus_four_h3 = np.float32(-4.0) * h3
    h1p = h1 + np.float32(3.0) * h3
    residual, phase, modulation = (np.ascontiguousarray(np.asarray(a).ravel(), dtype=np.float32)
                                   for a in (residual, phase, modulation))
    has_level = level is not None
    level = (np.ascontiguousarray(np.asarray(level).ravel(), dtype=np.float32) if has_level
             else np.zeros(1, dtype=np.float32))
    out = np.empty(residual.size, dtype=np.float32)
    _cleaned_into(residual, phase, modulation, level, has_level, np.array([four_h2, h0m]),
                  np.array([minus_four_h3, h1p]), np.float32(own[0]),
                  np.float32(own[1]) if has_level else np.float32(0.0), out)
    return out


@kernel(**_FMA)
def _noise_rows_into(phase, modulation, residual, level, has_level, stride, own, shared, r):
    for i in range(r.size):
        j = i * stride
        phi = np.float64(phase[j])
        b = np.float64(modulation[j])
        s2, c2 = _sincos(2.0 * phi)
        shared[0, i] = b * c2
        shared[1, i] = b * s2
        shared[2, i] = b * c2 * (4.0 * c2 * c2 - 3.0)
        shared[3, i] = b * s2 * (3.0 - 4.0 * s2 * s2)
        own[0, i] = 1.0
        if has_level:
            own[1, i] = np.float64(level[j])
        r[i] = np.float64(residual[j])


def noise_rows(phase: np.ndarray, modulation: np.ndarray, residual: np.ndarray, level: np.ndarray | None,
               stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The noise fit's samples of one four-step set on every *stride*-th pixel, in double precision: its own
    regressors (1, and the pixel's level when given) (1 or 2, m), the shared harmonics b cos 2phi, b sin 2phi,
    b cos 6phi, b sin 6phi (4, m; the sixth by the triple-angle formulas) and the residuals (m,)."""
    phase, modulation, residual = (np.ascontiguousarray(np.asarray(a).ravel()) for a in (phase, modulation,
                                                                                          residual))
    m = len(range(0, residual.size, stride))
    has_level = level is not None
    level = np.ascontiguousarray(np.asarray(level).ravel()) if has_level else np.zeros(1, dtype=phase.dtype)
    own = np.empty((2 if has_level else 1, m))
    shared = np.empty((4, m))
    r = np.empty(m)
    _noise_rows_into(phase, modulation, residual, level, has_level, int(stride), own, shared, r)
    return own, shared, r


@kernel(**_JIT)
def _consistency_into(modulation, cleaned, raw, limit, min_mod, inconsistent):
    bad_n = 0
    good_sum = 0.0
    for j in range(cleaned.size):
        b = np.float64(modulation[j])
        if b < min_mod[j]:
            min_mod[j] = b
        r = cleaned[j]
        if r > limit or r < -limit:
            bad_n += 1
            inconsistent[j] = True
        else:
            good_sum += np.float64(raw[j])
    return bad_n, good_sum


def consistency_set(modulation: np.ndarray, cleaned: np.ndarray, raw: np.ndarray, limit: float,
                    min_modulation: np.ndarray, inconsistent: np.ndarray) -> tuple[int, float]:
    """One four-step set's pass of the consistency check: *min_modulation* (float64) lowered to the set's
    modulation, *inconsistent* set where the cleaned residual lies beyond +-*limit* (DN); returns how many
    pixels that is and the sum of the raw residuals of the others (whole counts: exact in float64)."""
    # (compared in the residuals' float32, as numpy compares a float32 array with a Python float)
    bad, good_sum = _consistency_into(modulation, cleaned, raw, cleaned.dtype.type(limit), min_modulation,
                                      inconsistent)
    return int(bad), float(good_sum)


@kernel(**_VECTOR_SUMS)
def trim_rounds(r, a, c, s, shrink, rounds, about):
    """The iteration of :func:`~sofast_station.measure.phase.trimmed_std` from the scale *s*: keep the values
    of *r* whose |deviation| *a* (from *about*, their median) is at most c s, take their standard deviation
    over *shrink*, until the kept set stops changing (the sets of successive thresholds are nested, so the
    same count is the same set).

    One pass per round: the kept values' count, and the sums of their deviations d = r - about and of d^2
    (the variance sum d^2 / n - (sum d / n)^2, exact to rounding as the mean lies within a small fraction of
    the spread of *about*); without branches and summed in vector lanes (the order of a machine's vector
    width: the same bits on one machine, docs/conventions.md#determinism). Two passes a round, with a
    branch per value, took five times as long."""
    previous = -1
    for _ in range(rounds):
        limit = c * s
        count = 0
        total = 0.0
        squares = 0.0
        for j in range(r.size):
            keep = a[j] <= limit
            d = r[j] - about
            count += keep
            total += d if keep else 0.0
            squares += d * d if keep else 0.0
        if count == previous or count < 2:
            break
        previous = count
        mean = total / count
        s = math.sqrt(max(squares / count - mean * mean, 0.0) / shrink)
        if s == 0.0:
            break
    return s


@kernel(**_JIT)
def _minus_models_into(r, rows_a, coef_a, rows_b, coef_b, out):
    ka = rows_a.shape[0]
    kb = rows_b.shape[0]
    for j in range(r.size):
        acc = coef_a[0] * rows_a[0, j]
        for i in range(1, ka):
            acc = acc + coef_a[i] * rows_a[i, j]
        v = r[j] - acc
        if kb:
            acc = coef_b[0] * rows_b[0, j]
            for i in range(1, kb):
                acc = acc + coef_b[i] * rows_b[i, j]
            v = v - acc
        out[j] = v


def minus_models(r: np.ndarray, rows_a: np.ndarray, coef_a: np.ndarray, rows_b: np.ndarray | None = None,
                 coef_b: np.ndarray | None = None) -> np.ndarray:
    """(r - sum_i coef_a[i] rows_a[i]) - sum_i coef_b[i] rows_b[i], each sum formed left to right (the same
    bits as numpy's expression of it), in one pass; rows are (k, n) float64 arrays."""
    if rows_b is None:
        rows_b, coef_b = np.zeros((0, 1)), np.zeros(1)
    out = np.empty(r.size)
    _minus_models_into(r, np.ascontiguousarray(rows_a), np.asarray(coef_a, dtype=np.float64),
                       np.ascontiguousarray(rows_b), np.asarray(coef_b, dtype=np.float64), out)
    return out


@kernel(**_JIT)
def _count_labels_into(labels, counts):
    for v in labels:
        counts[v] += 1


def label_areas(labels: np.ndarray, n_labels: int) -> np.ndarray:
    """How many pixels carry each label 0 .. n_labels - 1 of an OpenCV labelling (int32): one pass, a
    quarter of np.bincount's time (which widens every label to 64 bits first)."""
    counts = np.zeros(n_labels, dtype=np.int64)
    _count_labels_into(np.ascontiguousarray(labels).ravel(), counts)
    return counts


@kernel(**_JIT)
def _label_moments_into(labels, sums):
    h, w = labels.shape
    for r in range(h):
        for c in range(w):
            k = labels[r, c]
            if k != 0:
                sums[0, k] += 1.0
                sums[1, k] += r
                sums[2, k] += c
                sums[3, k] += r * r
                sums[4, k] += c * c
                sums[5, k] += r * c


def label_moments(labels: np.ndarray, n_labels: int) -> np.ndarray:
    """Per label 1 .. n_labels - 1 of an OpenCV labelling (int32, 2-D), its pixels' count and the sums of
    their row, column, row^2, column^2 and row x column (pixels; label 0's all 0): (6, n_labels), each sum
    taken in raster order, so the same bits as np.bincount of the labelled pixels (tested), in one pass."""
    sums = np.zeros((6, n_labels))
    _label_moments_into(np.ascontiguousarray(labels, dtype=np.int32), sums)
    return sums


@kernel(**_JIT)
def _fill_holes_into(labels, max_area, area, edge, region):
    h, w = labels.shape
    for r in range(h):
        for c in range(w):
            k = labels[r, c]
            area[k] += 1
            if r == 0 or c == 0 or r == h - 1 or c == w - 1:
                edge[k] = True
    for r in range(h):
        for c in range(w):
            k = labels[r, c]
            if k != 0 and not edge[k] and area[k] <= max_area:
                region[r, c] = True


def fill_holes(labels: np.ndarray, n_labels: int, max_area_px: int, region: np.ndarray) -> None:
    """Set in *region* (bool, the labelling's shape) the pixels of every label 1 .. n_labels - 1 of *labels*
    (an OpenCV labelling, int32) that touches none of the box's four edges and has at most *max_area_px*
    pixels: a region's holes, from the labelling of its box's complement, in one pass without OpenCV's
    statistics."""
    area = np.zeros(n_labels, dtype=np.int64)
    edge = np.zeros(n_labels, dtype=np.bool_)
    _fill_holes_into(np.ascontiguousarray(labels, dtype=np.int32), int(max_area_px), area, edge, region)

@kernel(**_JIT)
def _laplacian_counts_into(img, mask, hist):
    rows = (img.shape[0] - 1) // 2
    cols = (img.shape[1] - 1) // 2
    n = 0
    for i in range(rows):
        r = 1 + 2 * i
        for j in range(cols):
            c = 1 + 2 * j
            if mask[r, c]:
                v = np.int64(img[r, c])
                lap = (((4 * v - np.int64(img[r - 1, c])) - np.int64(img[r + 1, c])) - np.int64(img[r, c - 1])) \
                    - np.int64(img[r, c + 1])
                hist[abs(lap)] += 1
                n += 1
    return n


def laplacian_median(image: np.ndarray, mask: np.ndarray) -> float:
    """The median of the absolute 4-neighbour Laplacian of a whole-count image (uint8 or uint16, 2-D) at every
    other row and column (rows and columns 1, 3, ..., inside the border) where *mask* (bool, the image's
    shape) is set; 0.0 when none is. Whole counts give whole Laplacians, so they are counted in a histogram
    (one pass, no copy) and the median is read from it: the same value as numpy's median of them in float32
    (the two middle values' mean, exact below 2^23; tested)."""
    img = np.asarray(image)
    hist = np.zeros(4 * int(np.iinfo(img.dtype).max) + 1, dtype=np.int64)
    n = _laplacian_counts_into(img, np.asarray(mask, dtype=np.bool_), hist)
    if n == 0:
        return 0.0
    cum = np.cumsum(hist)
    high = int(np.searchsorted(cum, n // 2 + 1))            # the (n // 2)-th value (from 0)
    low = high if n % 2 else int(np.searchsorted(cum, n // 2))
    return 0.5 * (low + high)

#: Histogram bins for a dot's ring of whole counts (:func:`_dot_centroids_into`): a ring spanning more counts
#: (a 16-bit frame's bright edge) takes numpy's median instead.
_RING_BINS = 1024


@kernel(inline="always", **_JIT)
def _kth_pair(hist, span, k):
    """The offsets of the k-th and (k+1)-th smallest (0-based) of the values counted by ``hist[:span]``."""
    seen = 0
    a = -1
    for i in range(span):
        seen += hist[i]
        if a < 0 and seen > k:
            a = i
        if seen > k + 1:
            return a, i
    return a, span - 1


@kernel(inline="always", **_JIT)
def _counted_median(hist, span, base, n):
    """The median of the *n* whole values ``base + i`` counted by ``hist[:span]``: numpy's (the middle value,
    or the mean of the middle two as ``(a + b) / 2``), so the same bits as ``np.median`` of the values."""
    half = n >> 1
    if n & 1 == 0:
        a, b = _kth_pair(hist, span, half - 1)
        return ((base + a) + (base + b)) / 2
    a, b = _kth_pair(hist, span, half)
    return base + a


@kernel(inline="always", **_JIT)
def _counted_mad(hist, span, base, n, centre):
    """The median of ``|v - centre|`` over the *n* values ``v = base + i`` counted by ``hist[:span]`` (the same
    bits as ``np.median(np.abs(v - centre))``): the distances in increasing order, walking out from *centre*
    on both sides."""
    half = n >> 1
    k1 = half - 1 if n & 1 == 0 else half
    left = int(math.floor(centre - base))          # offsets at or below centre, walked down
    right = left + 1                               # offsets above it, walked up
    seen = 0
    a = b = -1.0
    while True:
        dl = (centre - (base + left)) if left >= 0 else np.inf
        dr = ((base + right) - centre) if right < span else np.inf
        if dl <= dr:
            c = hist[left]
            d = dl
            left -= 1
        else:
            c = hist[right]
            d = dr
            right += 1
        if c == 0:
            continue
        if a < 0.0 and seen + c > k1:
            a = d
        if seen + c > half:
            b = d
            break
        seen += c
    if n & 1 == 0:
        return (a + b) / 2
    return b


@kernel(**_JIT)
def _dot_centroids_into(image, starts, radius, dark, iterations, centres, ok, cov, background, ring_sigma, depth):
    h, w = image.shape
    reach = 1.5 * radius + 1.0
    reach2 = reach * reach
    outer = reach + 0.5 * radius + 2.0
    ring_lo, ring_hi = (outer - 2.0) ** 2, outer * outer
    half = int(math.ceil(outer + 2.0))
    win = int(math.ceil(reach + 3.0))             # the centroid's window: its disc may move 2 px
    # the ring's offsets, once for every dot
    n_ring = 0
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            r2 = dx * dx + dy * dy
            if ring_lo < r2 <= ring_hi:
                n_ring += 1
    ring_dx = np.empty(n_ring, np.int64)
    ring_dy = np.empty(n_ring, np.int64)
    m = 0
    for dy in range(-half, half + 1):
        for dx in range(-half, half + 1):
            r2 = dx * dx + dy * dy
            if ring_lo < r2 <= ring_hi:
                ring_dx[m] = dx
                ring_dy[m] = dy
                m += 1
    ring = np.empty(n_ring)
    hist = np.zeros(_RING_BINS, np.int64)
    for k in range(starts.shape[0]):
        cu = int(round(starts[k, 0]))
        cv = int(round(starts[k, 1]))
        ok[k] = False
        if cu < half or cv < half or cu + half >= w or cv + half >= h:
            continue
        lo_v, hi_v, whole = np.inf, -np.inf, True
        for m in range(n_ring):
            ring[m] = image[cv + ring_dy[m], cu + ring_dx[m]]
            lo_v = min(lo_v, ring[m])
            hi_v = max(hi_v, ring[m])
            whole &= ring[m] == math.floor(ring[m])
        # the ring's median and its median absolute deviation: from the counts of its whole values when it has
        # a few hundred (a camera's counts: numba's np.median, a selection on a copy, was most of the kernel's
        # time), numpy's otherwise; the same values either way
        if whole and n_ring > 0 and hi_v - lo_v < _RING_BINS:
            base = lo_v
            span = int(hi_v - lo_v) + 1
            for m in range(n_ring):
                hist[int(ring[m] - base)] += 1
            bg = _counted_median(hist, span, base, n_ring)
            spread = _counted_mad(hist, span, base, n_ring, bg)
            hist[:span] = 0
        else:
            bg = np.median(ring)
            spread = np.median(np.abs(ring - bg))
        cx, cy = starts[k, 0], starts[k, 1]
        live = True
        tot = suu = svv = suv = top = 0.0
        for _ in range(iterations):
            # the weights over the disc about (cx, cy): the next centre, and the moments about this one (the
            # covariance's, from the last pass: the centre has moved by under a thousandth of a pixel)
            tot = sx = sy = suu = svv = suv = top = 0.0
            for dy in range(-win, win + 1):
                v = cv + dy
                rest = reach2 - (v - cy) * (v - cy)
                if rest < 0.0:
                    continue
                # the disc's chord on this row, a pixel wider each side than its rounded ends: the test below
                # decides as over the whole window (the same pixels in the same order), on a third of them
                chord = math.sqrt(rest)
                for dx in range(max(-win, int(math.floor(cx - chord)) - 1 - cu),
                                min(win, int(math.ceil(cx + chord)) + 1 - cu) + 1):
                    u = cu + dx
                    if (u - cx) * (u - cx) + (v - cy) * (v - cy) <= reach2:
                        s = (bg - image[v, u]) if dark else (image[v, u] - bg)
                        if s > 0.0:
                            tot += s
                            sx += s * u
                            sy += s * v
                            suu += (u - cx) * (u - cx)
                            svv += (v - cy) * (v - cy)
                            suv += (u - cx) * (v - cy)
                            top = max(top, s)
            if tot <= 0.0:
                live = False
                break
            nx, ny = sx / tot, sy / tot
            shift = math.hypot(nx - cx, ny - cy)
            cx, cy = nx, ny
            if shift < 1e-3:
                break
        if not live or abs(cx - cu) >= 2.0 or abs(cy - cv) >= 2.0:
            continue
        ok[k] = True
        centres[k, 0] = cx
        centres[k, 1] = cy
        cov[k, 0, 0] = suu / (tot * tot)
        cov[k, 1, 1] = svv / (tot * tot)
        cov[k, 0, 1] = suv / (tot * tot)
        cov[k, 1, 0] = suv / (tot * tot)
        background[k] = bg
        ring_sigma[k] = 1.4826 * spread
        depth[k] = top


def dot_centroids(image: np.ndarray, starts: np.ndarray, radius_px: float, dark: bool, iterations: int = 10):
    """Background-subtracted intensity centroids of dots (:func:`~.dots._centroids`, which documents them), in
    one compiled pass over the dots: (centres (N, 2), found (N,), covariance per unit noise variance (N, 2, 2),
    background, ring scatter, depth (N,)), NaN where a dot was not found."""
    img = np.ascontiguousarray(image)
    if img.dtype not in (np.uint8, np.uint16):
        img = img.astype(np.float64)
    n = len(starts)
    centres, cov = np.full((n, 2), np.nan), np.full((n, 2, 2), np.nan)
    background, ring_sigma, depth = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    ok = np.zeros(n, dtype=np.bool_)
    if n:
        _dot_centroids_into(img, np.ascontiguousarray(starts, dtype=np.float64), float(radius_px), bool(dark),
                            int(iterations), centres, ok, cov, background, ring_sigma, depth)
    return centres, ok, cov, background, ring_sigma, depth


@kernel(**_JIT)
def _lattice_walk_into(pts, first, basis, tolerance, cell, grid, who):
    n = pts.shape[0]
    size = grid.shape[0]
    # the dots in square buckets of *cell* pixels (a lattice step): the nearest dot to a prediction is looked
    # for in the buckets its tolerance reaches
    x0, y0, x1, y1 = np.inf, np.inf, -np.inf, -np.inf
    for p in range(n):
        x0, x1 = min(x0, pts[p, 0]), max(x1, pts[p, 0])
        y0, y1 = min(y0, pts[p, 1]), max(y1, pts[p, 1])
    nx = int(math.floor((x1 - x0) / cell)) + 1
    ny = int(math.floor((y1 - y0) / cell)) + 1
    start = np.zeros(nx * ny + 1, np.int64)
    bucket = np.empty(n, np.int64)
    for p in range(n):
        b = int(math.floor((pts[p, 1] - y0) / cell)) * nx + int(math.floor((pts[p, 0] - x0) / cell))
        bucket[p] = b
        start[b + 1] += 1
    for b in range(nx * ny):
        start[b + 1] += start[b]
    members = np.empty(n, np.int64)
    fill = start[:-1].copy()
    for p in range(n):
        members[fill[bucket[p]]] = p
        fill[bucket[p]] += 1
    taken = np.zeros(n, np.bool_)
    best = np.full(n, np.inf)                     # this wave's nearest claim on each dot ...
    claim = np.full(n, -1, np.int64)              # ... and the candidate making it
    seen = np.full((size, size), -1, np.int64)    # the wave that last made a place a candidate
    span = size // 2
    grid[span, span, 0], grid[span, span, 1] = pts[first, 0], pts[first, 1]
    who[span, span] = first
    taken[first] = True
    dirs = ((1, 0), (-1, 0), (0, 1), (0, -1))
    frontier = np.empty((n, 2), np.int64)
    frontier[0, 0], frontier[0, 1] = span, span
    n_front = 1
    cand = np.empty((4 * n, 2), np.int64)
    cand_xy = np.empty((4 * n, 2))
    cand_hit = np.empty(4 * n, np.int64)
    hits = np.empty(n, np.int64)
    wave = 0
    while n_front > 0:
        # every free place next to the frontier, from the first direction (in the order of *dirs*) that
        # reaches it, its dot predicted from the grid as it stood before this wave
        n_cand = 0
        for d in range(4):
            dr, dc = dirs[d]
            for f in range(n_front):
                fr, fc = frontier[f, 0], frontier[f, 1]
                r, c = fr + dr, fc + dc
                if r < 1 or c < 1 or r >= size - 1 or c >= size - 1:
                    continue
                if grid[r, c, 0] == grid[r, c, 0] or seen[r, c] == wave:
                    continue
                seen[r, c] = wave
                # from the last two on the line; at its start a neighbouring line's step, else the origin's
                ex = grid[fr, fc, 0] - grid[fr - dr, fc - dc, 0]
                ey = grid[fr, fc, 1] - grid[fr - dr, fc - dc, 1]
                for sgn in (1, -1):
                    if ex != ex:
                        sr, sc = sgn * dc, sgn * dr
                        ax, bx = grid[fr + sr, fc + sc, 0], grid[r + sr, c + sc, 0]
                        if ax == ax and bx == bx:
                            ex = bx - ax
                            ey = grid[r + sr, c + sc, 1] - grid[fr + sr, fc + sc, 1]
                if ex != ex:
                    ex, ey = basis[d, 0], basis[d, 1]
                cand[n_cand, 0], cand[n_cand, 1] = r, c
                cand_xy[n_cand, 0] = grid[fr, fc, 0] + ex
                cand_xy[n_cand, 1] = grid[fr, fc, 1] + ey
                # the nearest dot, when within tolerance of the step (and so within the buckets searched)
                reach = tolerance * math.sqrt(ex * ex + ey * ey)
                qx, qy = cand_xy[n_cand, 0], cand_xy[n_cand, 1]
                wide = reach * 1.000001 + 1e-9
                bx0 = max(int(math.floor((qx - wide - x0) / cell)), 0)
                bx1 = min(int(math.floor((qx + wide - x0) / cell)), nx - 1)
                by0 = max(int(math.floor((qy - wide - y0) / cell)), 0)
                by1 = min(int(math.floor((qy + wide - y0) / cell)), ny - 1)
                near, near_d2 = -1, np.inf
                for by in range(by0, by1 + 1):
                    for bx in range(bx0, bx1 + 1):
                        b = by * nx + bx
                        for m in range(start[b], start[b + 1]):
                            p = members[m]
                            dx, dy = pts[p, 0] - qx, pts[p, 1] - qy
                            d2 = dx * dx + dy * dy
                            if d2 < near_d2 or (d2 == near_d2 and p < near):
                                near, near_d2 = p, d2
                cand_hit[n_cand] = -1
                if near >= 0 and not taken[near]:
                    dist = math.sqrt(near_d2)
                    if dist <= reach:
                        cand_hit[n_cand] = near
                        # a dot two places claim goes to the nearer prediction
                        if dist < best[near]:
                            best[near] = dist
                            claim[near] = n_cand
                n_cand += 1
        wave += 1
        n_hits = 0
        for k in range(n_cand):
            p = cand_hit[k]
            if p >= 0 and claim[p] == k:
                hits[n_hits] = p
                n_hits += 1
        hits_sorted = np.sort(hits[:n_hits])
        n_front = 0
        for h in range(n_hits):
            p = hits_sorted[h]
            k = claim[p]
            r, c = cand[k, 0], cand[k, 1]
            grid[r, c, 0], grid[r, c, 1] = pts[p, 0], pts[p, 1]
            who[r, c] = p
            taken[p] = True
            best[p] = np.inf
            claim[p] = -1
            frontier[n_front, 0], frontier[n_front, 1] = r, c
            n_front += 1
        for k in range(n_cand):
            p = cand_hit[k]
            if p >= 0:
                best[p] = np.inf
                claim[p] = -1


def lattice_walk(pts: np.ndarray, first: int, basis: np.ndarray, tolerance: float, cell_px: float, span: int):
    """The breadth-first walk of :func:`~.dots.index_dots` (which documents it) in one compiled pass: (positions
    by index (2 span + 1, 2 span + 1, 2), NaN where no dot; the dot at each place, -1 where none), the origin's
    dot at [span, span]. *basis* (4, 2): the origin's steps along +i, -i, +j, -j; *cell_px*: the buckets' size
    for the nearest-dot look-ups (a lattice step)."""
    size = 2 * int(span) + 1
    grid = np.full((size, size, 2), np.nan)
    who = np.full((size, size), -1, np.int64)
    _lattice_walk_into(np.ascontiguousarray(pts, dtype=np.float64), int(first),
                       np.ascontiguousarray(basis, dtype=np.float64), float(tolerance), float(cell_px), grid, who)
    return grid, who


@kernel(**_JIT)
def _grid_screen_into(u, v, xs, ys, grid, main_diagonal, tol, rot, trans, out):
    nx = xs.size
    ny = ys.size
    lo_x = xs[0] - tol * (xs[1] - xs[0])
    hi_x = xs[nx - 1] + tol * (xs[nx - 1] - xs[nx - 2])
    lo_y = ys[0] - tol * (ys[1] - ys[0])
    hi_y = ys[ny - 1] + tol * (ys[ny - 1] - ys[ny - 2])
    for k in range(u.size):
        x = u[k]
        y = v[k]
        if not (x >= lo_x and x <= hi_x and y >= lo_y and y <= hi_y):
            out[0, k] = np.nan
            out[1, k] = np.nan
            out[2, k] = np.nan
            continue
        i = min(max(np.searchsorted(xs, x, side="right") - 1, 0), nx - 2)
        j = min(max(np.searchsorted(ys, y, side="right") - 1, 0), ny - 2)
        s = (x - xs[i]) / (xs[i + 1] - xs[i])
        t = (y - ys[j]) / (ys[j + 1] - ys[j])
        # the triangle's three nodes (a, b, c) and their weights
        if main_diagonal[j, i]:
            if t >= s:
                a, b, c, wa, wb, wc = (j, i), (j + 1, i + 1), (j + 1, i), 1.0 - t, s, t - s
            else:
                a, b, c, wa, wb, wc = (j, i), (j, i + 1), (j + 1, i + 1), 1.0 - s, s - t, t
        elif s + t <= 1.0:
            a, b, c, wa, wb, wc = (j, i), (j, i + 1), (j + 1, i), (1.0 - s) - t, s, t
        else:
            a, b, c, wa, wb, wc = (j, i + 1), (j + 1, i), (j + 1, i + 1), 1.0 - t, 1.0 - s, (s + t) - 1.0
        p0 = grid[a[0], a[1], 0] * wa + grid[b[0], b[1], 0] * wb + grid[c[0], c[1], 0] * wc
        p1 = grid[a[0], a[1], 1] * wa + grid[b[0], b[1], 1] * wb + grid[c[0], c[1], 1] * wc
        p2 = grid[a[0], a[1], 2] * wa + grid[b[0], b[1], 2] * wb + grid[c[0], c[1], 2] * wc
        for r in range(3):
            out[r, k] = rot[r, 0] * p0 + rot[r, 1] * p1 + rot[r, 2] * p2 + trans[r]


def grid_screen_points(u: np.ndarray, v: np.ndarray, xs: np.ndarray, ys: np.ndarray, grid: np.ndarray,
                       main_diagonal: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
                       tol: float = 100 * np.finfo(float).eps) -> np.ndarray:
    """Piecewise-linear interpolation of a measured screen on a rectangular grid of positions *xs* (nx,) by
    *ys* (ny,), node points *grid* (ny, nx, 3), each cell split into two triangles along its main diagonal
    ((x0, y0)-(x1, y1)) where *main_diagonal* (ny - 1, nx - 1) says so, else along the other; the points
    then taken into the camera frame by (*rotation*, *translation*): (3, N), NaN outside the grid (beyond
    *tol* of a cell, as scipy's triangulation accepts)."""
    out = np.empty((3, np.size(u)))
    _grid_screen_into(np.ascontiguousarray(u, dtype=np.float64), np.ascontiguousarray(v, dtype=np.float64), xs, ys,
                      grid, main_diagonal, float(tol), np.array(rotation, dtype=np.float64),
                      np.array(translation, dtype=np.float64), out)
    return out


@kernel(**_JIT)
def _gather_runs_into(flat, src, dst, length, out):
    for f in range(flat.shape[0]):
        row = flat[f]
        target = out[f]
        for r in range(src.size):
            a = src[r]
            b = dst[r]
            target[b:b + length[r]] = row[a:a + length[r]]


def gather_runs(flat: np.ndarray, idx: np.ndarray, runs: tuple[list, list], out: np.ndarray) -> None:
    """``out[:] = flat[:, idx]`` for sorted flat indices *idx* that run on in *runs* ((starts, ends) in *idx*):
    each run copied as a row segment, in one compiled pass without the GIL (frames (F, N), out (F, len(idx)))."""
    starts = np.asarray(runs[0], dtype=np.int64)
    ends = np.asarray(runs[1], dtype=np.int64)
    _gather_runs_into(flat, idx[starts].astype(np.int64), starts, ends - starts, out)


# ---------------------------------------------------------------------------------------------- unwrapping
@kernel(**_JIT)
def _unwrap_into(phases, periods, big_l, whole, guard_sigmas, sigma, per_pixel, u_out, valid):
    n_sets = phases.shape[0]
    two_pi = 2.0 * math.pi
    coarse_bad_n = 0
    disagree_n = 0
    edge_n = 0
    first = two_pi * periods[0]
    for j in range(phases.shape[1]):
        u = (big_l * np.float64(phases[0, j])) / first
        coarse_bad = not (u >= 0.0 and u < big_l)
        disagree = False
        for m in range(1, n_sets):
            p = periods[m]
            phi = np.float64(phases[m, j])
            k = np.rint((((two_pi * p) * u) / big_l - phi) / two_pi)
            u_fine = ((phi + k * two_pi) * big_l) / (two_pi * p)
            if abs(u_fine - u) > big_l / (4.0 * p):
                disagree = True
            u = u_fine
        near_edge = False
        if whole:
            if u < 0.0 or u >= big_l:
                u = np.mod(u, big_l)
            if u >= big_l:
                u = 0.0
            coarse_bad = False
            guard = guard_sigmas * (sigma[j] if per_pixel else sigma[0])
            near_edge = u < guard or u > big_l - guard
        else:
            coarse_bad = coarse_bad or not (u >= 0.0 and u < big_l)
        disagree = disagree and not coarse_bad
        near_edge = near_edge and not (coarse_bad or disagree)
        coarse_bad_n += coarse_bad
        disagree_n += disagree
        edge_n += near_edge
        ok = not (coarse_bad or disagree or near_edge)
        valid[j] = ok
        u_out[j] = u if ok else np.nan
    return coarse_bad_n, disagree_n, edge_n


def unwrap(phases: list, periods: list, big_l: float, whole: bool, guard_sigmas: float, sigma
           ) -> tuple[np.ndarray, np.ndarray, int, int, int]:
    """Temporal unwrapping of every pixel in one pass without the GIL (so the two axes unwrap at once on
    two threads; see :func:`~sofast_station.measure.phase.unwrap_positions`, which checks the arguments):
    positions (metres, NaN where invalid), valid, and the counts of coarse-out-of-range, disagreeing and
    edge-guard pixels. *sigma*: the finest phase's position noise per pixel (an array) or for all (a
    float), metres. Each pixel's operations in the order of u = L phi / (2 pi p);
    k = round((2 pi p u / L - phi) / 2 pi); u' = L (phi + 2 pi k) / (2 pi p) (numpy's values)."""
    stack = np.stack([np.asarray(ph).ravel() for ph in phases])
    per_pixel = np.ndim(sigma) > 0
    sig = np.ascontiguousarray(np.ravel(sigma), dtype=np.float64) if per_pixel else np.array([float(sigma)])
    n = stack.shape[1]
    u = np.empty(n)
    valid = np.empty(n, dtype=np.bool_)
    counts = _unwrap_into(stack, np.asarray(periods, dtype=np.float64), float(big_l), bool(whole),
                          float(guard_sigmas), sig, per_pixel, u, valid)
    return u, valid, int(counts[0]), int(counts[1]), int(counts[2])


# ----------------------------------------------------------------------------- sums over the points, by blocks
#: Points per block of the sums below: each block is summed on its own (in the compiler's vector lanes) and
#: the blocks' sums are added in block order, so a sum is the same bits whichever thread formed which blocks.
SUM_BLOCK = 16384


@kernel(**_VECTOR_SUMS)
def _cubic_sums_into(x, y, s_x, s_y, x0, y0, h, block, parts):
    # per block: the 21 products m_a m_b (a <= b, row-major over a) of m = (1, u, v, u^2, uv, v^2), then the
    # six m_k s_x and the six m_k s_y; each sum a local (a register), so the compiler runs it in vector lanes
    n = x.size
    for b in range(parts.shape[0]):
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = 0.0
        a11 = a12 = a13 = a14 = a15 = a16 = a17 = a18 = a19 = a20 = a21 = 0.0
        a22 = a23 = a24 = a25 = a26 = a27 = a28 = a29 = a30 = a31 = a32 = 0.0
        for j in range(b * block, min(n, (b + 1) * block)):
            u = (x[j] - x0) / h
            v = (y[j] - y0) / h
            uu = u * u
            uv = u * v
            vv = v * v
            sx = s_x[j]
            sy = s_y[j]
            a0 += 1.0
            a1 += u
            a2 += v
            a3 += uu
            a4 += uv
            a5 += vv
            a6 += u * u
            a7 += u * v
            a8 += u * uu
            a9 += u * uv
            a10 += u * vv
            a11 += v * v
            a12 += v * uu
            a13 += v * uv
            a14 += v * vv
            a15 += uu * uu
            a16 += uu * uv
            a17 += uu * vv
            a18 += uv * uv
            a19 += uv * vv
            a20 += vv * vv
            a21 += sx
            a22 += u * sx
            a23 += v * sx
            a24 += uu * sx
            a25 += uv * sx
            a26 += vv * sx
            a27 += sy
            a28 += u * sy
            a29 += v * sy
            a30 += uu * sy
            a31 += uv * sy
            a32 += vv * sy
        acc = parts[b]
        acc[0] = a0
        acc[1] = a1
        acc[2] = a2
        acc[3] = a3
        acc[4] = a4
        acc[5] = a5
        acc[6] = a6
        acc[7] = a7
        acc[8] = a8
        acc[9] = a9
        acc[10] = a10
        acc[11] = a11
        acc[12] = a12
        acc[13] = a13
        acc[14] = a14
        acc[15] = a15
        acc[16] = a16
        acc[17] = a17
        acc[18] = a18
        acc[19] = a19
        acc[20] = a20
        acc[21] = a21
        acc[22] = a22
        acc[23] = a23
        acc[24] = a24
        acc[25] = a25
        acc[26] = a26
        acc[27] = a27
        acc[28] = a28
        acc[29] = a29
        acc[30] = a30
        acc[31] = a31
        acc[32] = a32


#: The position of the product m_a m_b (a <= b) among the 21 that :func:`_cubic_sums_into` forms.
_PAIR_INDEX = {(a, b): k for k, (a, b) in enumerate((a, b) for a in range(6) for b in range(a, 6))}


@kernel(**_VECTOR_SUMS)
def _parabola_sums_into(x, y, s_x, s_y, xm, ym, block, parts):
    n = x.size
    for b in range(parts.shape[0]):
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = a10 = 0.0
        for j in range(b * block, min(n, (b + 1) * block)):
            xc = x[j] - xm
            yc = y[j] - ym
            sx = s_x[j]
            sy = s_y[j]
            a0 += xc * xc
            a1 += xc
            a2 += xc * yc
            a3 += yc * yc
            a4 += yc
            a5 += xc * sx
            a6 += sx
            a7 += yc * sx
            a8 += yc * sy
            a9 += sy
            a10 += xc * sy
        acc = parts[b]
        acc[0], acc[1], acc[2], acc[3], acc[4], acc[5] = a0, a1, a2, a3, a4, a5
        acc[6], acc[7], acc[8], acc[9], acc[10] = a6, a7, a8, a9, a10


@kernel(inline="always", **_VECTOR_SUMS)
def _newton_terms(c0, c2, s, k0, k1, k2, inv):
    """A point's nine terms of the bisquare Newton step (:func:`reweight_sums`)."""
    r = s - ((k0 * c0 + k1) + k2 * c2)
    q = r * inv
    q = min(q * q, 1.0)
    one_q = 1.0 - q
    wr = one_q * one_q * r
    dpsi = (1.0 - 5.0 * q) * one_q
    d0 = c0 * dpsi
    return c0 * wr, wr, c2 * wr, d0 * c0, d0, d0 * c2, dpsi, c2 * dpsi, c2 * dpsi * c2


@kernel(**_VECTOR_SUMS)
def _reweight_sums_into(x, y, s_x, s_y, xm, ym, kx, ky, inv_x, inv_y, block, parts):
    n = x.size
    kx0, kx1, kx2, ky0, ky1, ky2 = kx[0], kx[1], kx[2], ky[0], ky[1], ky[2]
    for b in range(parts.shape[0]):
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = a8 = a9 = 0.0
        a10 = a11 = a12 = a13 = a14 = a15 = a16 = a17 = a18 = a19 = 0.0
        for j in range(b * block, min(n, (b + 1) * block)):
            xc = x[j] - xm
            yc = y[j] - ym
            a0 += xc * xc
            a1 += yc * yc
            t0, t1, t2, t3, t4, t5, t6, t7, t8 = _newton_terms(xc, yc, s_x[j], kx0, kx1, kx2, inv_x)
            a2 += t0
            a3 += t1
            a4 += t2
            a5 += t3
            a6 += t4
            a7 += t5
            a8 += t6
            a9 += t7
            a10 += t8
            t0, t1, t2, t3, t4, t5, t6, t7, t8 = _newton_terms(yc, xc, s_y[j], ky0, ky1, ky2, inv_y)
            a11 += t0
            a12 += t1
            a13 += t2
            a14 += t3
            a15 += t4
            a16 += t5
            a17 += t6
            a18 += t7
            a19 += t8
        acc = parts[b]
        acc[0], acc[1], acc[2], acc[3], acc[4], acc[5], acc[6] = a0, a1, a2, a3, a4, a5, a6
        acc[7], acc[8], acc[9], acc[10], acc[11], acc[12], acc[13] = a7, a8, a9, a10, a11, a12, a13
        acc[14], acc[15], acc[16], acc[17], acc[18], acc[19] = a14, a15, a16, a17, a18, a19


def _block_sums(kernel, n_sums: int, columns: tuple, args: tuple, pool=None) -> np.ndarray:
    """``kernel(*columns, *args, SUM_BLOCK, parts)``'s per-block sums over every point, added in block order
    (the second half of the blocks on *pool* when given)."""
    n = columns[0].size
    n_blocks = max(1, -(-n // SUM_BLOCK))
    parts = np.zeros((n_blocks, n_sums))
    half = n_blocks // 2 if pool is not None else 0
    if half:
        cut = half * SUM_BLOCK
        second = pool.submit(kernel, *(c[cut:] for c in columns), *args, SUM_BLOCK, parts[half:])
        kernel(*(c[:cut] for c in columns), *args, SUM_BLOCK, parts[:half])
        second.result()
    else:
        kernel(*columns, *args, SUM_BLOCK, parts)
    total = parts[0].copy()
    for row in parts[1:]:
        total += row
    return total


def cubic_sums(x, y, s_x, s_y, x0: float, y0: float, h: float, pairs, pool=None) -> np.ndarray:
    """With u = (x - x0)/h, v = (y - y0)/h and the monomials m = (1, u, v, u^2, uv, v^2) of every point: the
    sums of m_a m_b for each (a, b) of *pairs*, then of each m_k s_x, then of each m_k s_y."""
    sums = _block_sums(_cubic_sums_into, 33, (x, y, s_x, s_y), (float(x0), float(y0), float(h)), pool)
    return np.concatenate([sums[[_PAIR_INDEX[min(a, b), max(a, b)] for a, b in pairs]], sums[21:]])


def parabola_sums(x, y, s_x, s_y, xm: float, ym: float, pool=None) -> np.ndarray:
    """With xc = x - xm, yc = y - ym: the sums of xc^2, xc, xc yc, yc^2, yc, xc s_x, s_x, yc s_x, yc s_y,
    s_y, xc s_y over every point."""
    return _block_sums(_parabola_sums_into, 11, (x, y, s_x, s_y), (float(xm), float(ym)), pool)


def reweight_sums(x, y, s_x, s_y, xm: float, ym: float, k0x, k0y, sigma: tuple, bisquare_c: float,
                  pool=None) -> np.ndarray:
    """Sums of xc^2 and yc^2, then the bisquare Newton step's nine sums of the x equation (columns xc, 1, yc,
    start *k0x*, scale sigma[0]) and of the y equation (yc, 1, xc; *k0y*, sigma[1]); see
    :func:`~sofast_station.measure.fit.reweight_parabola`."""
    inv = [1.0 / (bisquare_c * float(sg)) for sg in sigma]
    return _block_sums(_reweight_sums_into, 20, (x, y, s_x, s_y),
                       (float(xm), float(ym), np.asarray(k0x, dtype=np.float64), np.asarray(k0y, dtype=np.float64),
                        inv[0], inv[1]), pool)


# --------------------------------------------------------------- the robust fit's reweighting (small subsamples)
@kernel(**_VECTOR_SUMS)
def weighted_sums(c0, c1, c2, target, w, out):
    """Over the points, for three columns: sum w c_a c_b for (a, b) = (0, 0), (0, 1), (0, 2), (1, 1), (1, 2),
    (2, 2), then sum w c_i target for i = 0, 1, 2, into *out* (9,)."""
    s00 = s01 = s02 = s11 = s12 = s22 = t0 = t1 = t2 = 0.0
    for j in range(c0.size):
        a, b, c, wj = c0[j], c1[j], c2[j], w[j]
        s00 += a * a * wj
        s01 += a * b * wj
        s02 += a * c * wj
        s11 += b * b * wj
        s12 += b * c * wj
        s22 += c * c * wj
        tj = target[j]
        t0 += a * tj * wj
        t1 += b * tj * wj
        t2 += c * tj * wj
    out[0], out[1], out[2], out[3], out[4] = s00, s01, s02, s11, s12
    out[5], out[6], out[7], out[8] = s22, t0, t1, t2


@kernel(**_VECTOR_SUMS)
def residuals_and_leverage(c0, c1, c2, target, w, coef, quad, r, r_adj):
    """Residuals r = target - sum_i coef_i c_i (subtracted in column order), and r_adj = r / sqrt(1 - h) with
    the leverage h = w sum_p quad_p c_a c_b over the pairs of :func:`weighted_sums` (1 - h at least 1e-12
    under the root); returns (sum w r^2, sum w)."""
    k0, k1, k2 = coef[0], coef[1], coef[2]
    q0, q1, q2, q3, q4, q5 = quad[0], quad[1], quad[2], quad[3], quad[4], quad[5]
    wrr = 0.0
    sw = 0.0
    for j in range(c0.size):
        a, b, c = c0[j], c1[j], c2[j]
        rj = ((target[j] - k0 * a) - k1 * b) - k2 * c
        r[j] = rj
        wj = w[j]
        wrr += wj * rj * rj
        sw += wj
        h = ((((q0 * (a * a) + q1 * (a * b)) + q2 * (a * c)) + q3 * (b * b)) + q4 * (b * c)) + q5 * (c * c)
        h = 1.0 - h * wj
        r_adj[j] = rj / math.sqrt(max(h, 1e-12))
    return wrr, sw


@kernel(**_JIT)
def bisquare_into(r, scale, w):
    """Tukey's bisquare weights (1 - u^2)^2 for |u| < 1, else 0, u = r * *scale* (1 / (c sigma)), into *w*."""
    for j in range(r.size):
        u = r[j] * scale
        q = max(1.0 - u * u, 0.0)
        w[j] = q * q


@kernel(**_JIT)
def _moved_into(v0, v1, v2, r, pivot, t_z, points, out):
    for j in range(v0.size):
        a, b, c = v0[j], v1[j], v2[j]
        if points:
            a, b, c = a - pivot[0], b - pivot[1], c - pivot[2]
        q0 = (r[0, 0] * a + r[0, 1] * b) + r[0, 2] * c
        q1 = (r[1, 0] * a + r[1, 1] * b) + r[1, 2] * c
        q2 = (r[2, 0] * a + r[2, 1] * b) + r[2, 2] * c
        if points:
            q0, q1, q2 = q0 + pivot[0], q1 + pivot[1], (q2 + pivot[2]) + t_z
        out[0, j], out[1, j], out[2, j] = q0, q1, q2


def moved(v: np.ndarray, rotation: np.ndarray, pivot_m: np.ndarray, t_z_m: float, points: bool) -> np.ndarray:
    """The (3, N) directions *v* rotated by *rotation*, or with *points* the points rotated about *pivot_m*
    and shifted by *t_z_m* along z (:class:`~.boresight.Motion`), in one pass: numpy's arithmetic in its
    order, the same bits."""
    out = np.empty((3, v.shape[1]))
    _moved_into(v[0], v[1], v[2], np.ascontiguousarray(rotation, dtype=np.float64),
                np.ascontiguousarray(pivot_m, dtype=np.float64), float(t_z_m), bool(points), out)
    return out


@kernel(**_JIT)
def sum_squares(c0, c1, c2):
    """(sum c0^2, sum c1^2, sum c2^2) in one pass (the robust fit's column scales)."""
    s0 = s1 = s2 = 0.0
    for j in range(c0.size):
        s0 += c0[j] * c0[j]
        s1 += c1[j] * c1[j]
        s2 += c2[j] * c2[j]
    return s0, s1, s2


@kernel(**_JIT)
def _select_in_place(a, m, k):
    """The k-th smallest (0-based) of a[:m], by quickselect (median-of-three pivots) in place: afterwards
    a[k] holds it and a[:k] holds values no larger."""
    lo, hi = 0, m - 1
    while hi > lo:
        mid = (lo + hi) >> 1
        if a[mid] < a[lo]:
            a[mid], a[lo] = a[lo], a[mid]
        if a[hi] < a[lo]:
            a[hi], a[lo] = a[lo], a[hi]
        if a[hi] < a[mid]:
            a[hi], a[mid] = a[mid], a[hi]
        pivot = a[mid]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            break
    return a[k]


@kernel(**_JIT)
def median_in_window(a, about, absolute, lo, hi, scratch):
    """The median of the values v (a, or |a - about| when *absolute*; float64) when its order statistics
    lie in [lo, hi]: one pass counts the values below lo and gathers those in [lo, hi] into *scratch*
    (at least as long as a), then a selection among those few. Returns (median, found); found is False
    when the median's order statistics are not in the window or a value is NaN (the caller then selects
    over every value). The median of an even count is (lower + upper) / 2, numpy's arithmetic for
    float64, so a found median is the same bits as ``np.median``."""
    n = a.size
    below = 0
    m = 0
    nans = 0
    # No branches: every value is stored and the count of kept ones advances for those in the window.
    # (A branch per value, even one rarely taken, made the pass seven times slower on residuals fresh
    # from their own pass, 170 us against 24 for 38,000 values.)
    for j in range(n):
        v = abs(a[j] - about) if absolute else a[j]
        scratch[m] = v
        below += v < lo
        m += (v >= lo) & (v <= hi)
        nans += v != v
    k = n // 2 - below
    if nans or n == 0 or k < 0 or k >= m or (n % 2 == 0 and k == 0):
        return math.nan, False      # (an even count's lower order statistic below the window: k == 0)
    upper = _select_in_place(scratch, m, k)
    if n % 2:
        return upper, True
    lower = scratch[0]              # the next smaller order statistic: the largest value left of k
    for j in range(1, k):
        if scratch[j] > lower:
            lower = scratch[j]
    return (lower + upper) / 2.0, True


@kernel(**_JIT)
def _median_of(a, about, absolute, lo, hi, scratch):
    """:func:`median_in_window`, then (when the window misses) the selection over every value: the
    median of a (or of |a - about|), the same bits as ``np.median``; NaN when a value is NaN.

    Without a window (lo, hi not finite) or when it and one 8 and one 64 times as wide miss, the window is
    taken from a sample (Floyd and Rivest's selection): every (n / 1024)-th value, sorted; the window
    spans the sample's order statistics 3.5 standard deviations of a sample median's rank either side
    of its middle, so the median lies outside it about once in 2,000 times (then the window doubles)."""
    if lo < hi:                     # a finite window: it, then one 8 and one 64 times as wide
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        for widen in (1.0, 8.0, 64.0):
            m, found = median_in_window(a, about, absolute, centre - widen * half, centre + widen * half,
                                        scratch)
            if found:
                return m
    n = a.size
    step = max(n // 1024, 1)
    sample = np.empty(len(range(0, n, step)))
    for i in range(sample.size):
        v = a[i * step]
        sample[i] = abs(v - about) if absolute else v
    if np.isnan(sample).any():
        return math.nan
    sample.sort()
    ns = sample.size
    spread = max(int(3.5 * 0.5 * math.sqrt(ns)) + 1, 1)
    while spread < ns:
        m, found = median_in_window(a, about, absolute, sample[max(ns // 2 - spread, 0)],
                                    sample[min(ns // 2 + spread, ns - 1)], scratch)
        if found:
            return m
        spread *= 2
    m, _ = median_in_window(a, about, absolute, -math.inf, math.inf, scratch)   # every value
    return m


@kernel(**_JIT)
def _lu(a, piv):
    """LU factors of the square *a* (3 x 3, 6 x 6) in place, with partial pivoting (LAPACK's getrf order); False
    when a pivot is exactly zero (singular)."""
    n = a.shape[0]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        piv[k] = p
        if a[p, k] == 0.0:
            return False
        if p != k:
            for j in range(n):
                a[k, j], a[p, j] = a[p, j], a[k, j]
        for i in range(k + 1, n):
            a[i, k] /= a[k, k]
            for j in range(k + 1, n):
                a[i, j] -= a[i, k] * a[k, j]
    return True


@kernel(**_JIT)
def _lu_solve(lu, piv, b, x):
    """x = a^-1 b from :func:`_lu`'s factors *lu* and pivots *piv* of a."""
    n = lu.shape[0]
    for i in range(n):
        x[i] = b[i]
    for k in range(n):
        p = piv[k]
        if p != k:
            x[k], x[p] = x[p], x[k]
    for i in range(n):
        for j in range(i):
            x[i] -= lu[i, j] * x[j]
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, n):
            x[i] -= lu[i, j] * x[j]
        x[i] /= lu[i, i]


#: :func:`irls_bisquare`'s outcomes besides success.
SINGULAR, ILL_CONDITIONED = 1, 2


@kernel(**_JIT)
def irls_bisquare(c0, c1, c2, target, w, scale, tolerance, max_iterations, sigma_guess, bisquare_c, mad_to_sigma,
                  window_sigmas, coef):
    """Iteratively reweighted least squares with Tukey's bisquare for three columns, the whole iteration
    in one compiled call (:func:`~.fit.robust_weights` says what it computes); *w* holds the starting
    weights and receives the last ones, *coef* (3,) the coefficients. Returns (status, sigma): status 0,
    :data:`SINGULAR` or :data:`ILL_CONDITIONED`; sigma NaN when no reweighting was done.

    Each iteration: the weighted sums of the column products (one pass), the 3 x 3 normal equations
    (columns scaled to unit RMS by *scale*) solved by LU with partial pivoting, residuals and leverage
    (one pass), their median and MAD looked for near the last ones first (:func:`median_in_window`,
    *window_sigmas* wide), the bisquare weights (one pass). Without the GIL, so the two slope
    equations run at once on two threads."""
    n = target.size
    sums = np.empty(9)
    gram = np.empty((3, 3))
    g = np.empty((3, 3))
    lu = np.empty((3, 3))
    piv = np.empty(3, dtype=np.int64)
    rhs = np.empty(3)
    sol = np.empty(3)
    unit = np.zeros(3)
    col = np.empty(3)
    inv = np.empty((3, 3))
    quad = np.empty(6)
    r = np.empty(n)
    r_adj = np.empty(n)
    scratch = np.empty(n)
    prev = math.nan
    sigma = math.nan
    med_guess, mad_guess = 0.0, mad_to_sigma * sigma_guess
    med_step = mad_step = 0.0
    for _ in range(max_iterations):
        weighted_sums(c0, c1, c2, target, w, sums)
        gram[0, 0], gram[0, 1], gram[0, 2] = sums[0], sums[1], sums[2]
        gram[1, 0], gram[1, 1], gram[1, 2] = sums[1], sums[3], sums[4]
        gram[2, 0], gram[2, 1], gram[2, 2] = sums[2], sums[4], sums[5]
        for i in range(3):
            rhs[i] = sums[6 + i] / scale[i]
            for j in range(3):
                g[i, j] = gram[i, j] / (scale[i] * scale[j])
                lu[i, j] = g[i, j]
        if not np.isfinite(g).all():
            return ILL_CONDITIONED, sigma
        if not _lu(lu, piv):
            return SINGULAR, sigma
        _lu_solve(lu, piv, rhs, sol)
        lam = np.abs(np.linalg.eigvalsh(g))
        if not lam.min() > 0.0 or lam.max() > 1e12 * lam.min():
            return ILL_CONDITIONED, sigma
        for i in range(3):
            coef[i] = sol[i] / scale[i]
        # leverage of each point under the current weights: h_i = w_i x_i^T (X^T W X)^-1 x_i
        for i in range(3):
            for j in range(3):
                lu[i, j] = gram[i, j]
        if not _lu(lu, piv):
            return SINGULAR, sigma
        for j in range(3):
            unit[:] = 0.0
            unit[j] = 1.0
            _lu_solve(lu, piv, unit, col)
            for i in range(3):
                inv[i, j] = col[i]
        quad[0], quad[1], quad[2] = inv[0, 0], 2.0 * inv[0, 1], 2.0 * inv[0, 2]
        quad[3], quad[4], quad[5] = inv[1, 1], 2.0 * inv[1, 2], inv[2, 2]
        wrr, sw = residuals_and_leverage(c0, c1, c2, target, w, coef, quad, r, r_adj)
        ms = wrr / max(sw, 1.0)
        if prev == prev and abs(ms - prev) <= tolerance * max(prev, 1e-30):
            break
        prev = ms
        # The median and the MAD move little from one reweighting to the next: each is looked for near
        # its last value first.
        width = window_sigmas * sigma_guess
        hw = width + 2.0 * abs(med_step)
        med = _median_of(r_adj, 0.0, False, med_guess - hw, med_guess + hw, scratch)
        hw = width + 2.0 * abs(mad_step)
        mad = _median_of(r_adj, med, True, mad_guess - hw, mad_guess + hw, scratch)
        med_step, mad_step = med - med_guess, mad - mad_guess
        med_guess, mad_guess = med, mad
        if mad == 0.0:
            break
        sigma = mad / mad_to_sigma
        sigma_guess = sigma
        bisquare_into(r_adj, 1.0 / (bisquare_c * sigma), w)
    return 0, sigma


@kernel(**_JIT)
def _grid_sums_into(x, y, g_x, g_y, model, x0, y0, cell, count, s_x, s_y, o_x, o_y):
    ny, nx = count.shape
    m0, m1, m2, m3, m4 = model[0], model[1], model[2], model[3], model[4]
    # grid_slopes' binning: each finite point's slopes (less the model's, surface_slopes' arithmetic) and its
    # offset from its cell's centre summed into its cell in the points' order (bincount's)
    for k in range(x.size):
        xk, yk = x[k], y[k]
        a = g_x[k] - ((m0 * xk + m1) + m2 * yk)
        b = g_y[k] - ((m3 * yk + m4) + m2 * xk)
        if not (np.isfinite(xk) and np.isfinite(yk) and np.isfinite(a) and np.isfinite(b)):
            continue
        fx = math.floor((xk - x0) / cell)
        fy = math.floor((yk - y0) / cell)
        if fx >= 0.0 and fx < nx and fy >= 0.0 and fy < ny:
            i, j = int(fy), int(fx)
            count[i, j] += 1.0
            s_x[i, j] += a
            s_y[i, j] += b
            o_x[i, j] += xk - (x0 + (j + 0.5) * cell)
            o_y[i, j] += yk - (y0 + (i + 0.5) * cell)


def grid_sums(x: np.ndarray, y: np.ndarray, g_x: np.ndarray, g_y: np.ndarray, x0: float, y0: float,
              cell: float, shape: tuple, model=None) -> tuple[np.ndarray, ...]:
    """:func:`~.heights.grid_slopes`' binning of the points (x, y) (metres; slopes *g_x*, *g_y*, less those of
    the quadratic *model* (A, B, C, D, E, F) when given, :func:`~.surface.surface_slopes`' arithmetic) on the
    grid of *shape* (ny, nx) cells of side *cell* from (*x0*, *y0*), in one compiled pass: per cell the count
    of its points and the sums of their slopes and of their offsets from its centre (metres), each (ny, nx),
    the same bits as numpy's bincounts (tested)."""
    args = [np.ascontiguousarray(v, dtype=np.float64) for v in (x, y, g_x, g_y)]
    # 2A, C, E, 2B, D: a zero model subtracts exactly 0 (s - (+0.0) is s)
    a, b, c, d, e = (0.0,) * 5 if model is None else (float(v) for v in tuple(model)[:5])
    terms = np.array([2.0 * a, c, e, 2.0 * b, d])
    sums = tuple(np.zeros(shape) for _ in range(5))
    _grid_sums_into(*args, terms, float(x0), float(y0), float(cell), *sums)
    return sums


@kernel(**_JIT)
def _bilinear_into(h, x0, y0, cell, x, y, out):
    ny, nx = h.shape
    top_u, top_v = nx - 1.0, ny - 1.0
    last_j, last_i = max(nx - 2, 0), max(ny - 2, 0)
    dj, di = min(nx - 1, 1), min(ny - 1, 1)
    for k in range(x.size):
        u = (x[k] - x0) / cell - 0.5
        v = (y[k] - y0) / cell - 0.5
        if not (np.isfinite(u) and np.isfinite(v)):
            out[k] = np.nan
            continue
        # numpy's clip: the larger of (u, 0), then the smaller of (that, top)
        u = u if u > 0.0 else 0.0
        u = u if u < top_u else top_u
        v = v if v > 0.0 else 0.0
        v = v if v < top_v else top_v
        j = min(int(u), last_j)
        i = min(int(v), last_i)
        tu, tv = u - j, v - i
        su = 1.0 - tu
        out[k] = ((1.0 - tv) * (su * h[i, j] + tu * h[i, j + dj])
                  + tv * (su * h[i + di, j] + tu * h[i + di, j + dj]))


def bilinear(heights_m: np.ndarray, x0: float, y0: float, cell: float, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """:class:`~.heights.HeightGrid`'s bilinear reading of the (ny, nx) *heights_m* on the cell centres
    (x0 + (j + 1/2) cell, y0 + (i + 1/2) cell), clamped at the outer ones, at the 1-D points (*x*, *y*),
    metres, in one compiled pass: the same bits as its numpy expression (tested); NaN at a point not finite
    (where numpy's indexing would fail)."""
    h = np.ascontiguousarray(heights_m, dtype=np.float64)
    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    if h.ndim != 2 or 0 in h.shape or x.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"bilinear takes a non-empty 2-D grid and two 1-D arrays of one length, got shapes "
                         f"{h.shape}, {x.shape} and {y.shape}")
    out = np.empty(x.size)
    _bilinear_into(h, float(x0), float(y0), float(cell), x, y, out)
    return out


@kernel(inline="always", **_JIT)
def _skew_series_into(v0, v1, v2, a, b, out):
    """*out* (3, 3) = I + a V + b V V, V the cross-product matrix of (v0, v1, v2): a rotation by Rodrigues'
    formula (:func:`_rodrigues_into`) and the left Jacobian of SO(3) (:func:`_left_jacobian_into`) alike."""
    out[0, 0] = 1.0 + b * (-v2 * v2 - v1 * v1)
    out[0, 1] = -a * v2 + b * (v1 * v0)
    out[0, 2] = a * v1 + b * (v2 * v0)
    out[1, 0] = a * v2 + b * (v0 * v1)
    out[1, 1] = 1.0 + b * (-v2 * v2 - v0 * v0)
    out[1, 2] = -a * v0 + b * (v2 * v1)
    out[2, 0] = -a * v1 + b * (v0 * v2)
    out[2, 1] = a * v0 + b * (v1 * v2)
    out[2, 2] = 1.0 + b * (-v1 * v1 - v0 * v0)


@kernel(inline="always", **_JIT)
def _rodrigues_into(w0, w1, w2, r):
    """*r* (3, 3): the rotation of the rotation vector (w0, w1, w2), radians, by Rodrigues' formula
    (:func:`~.uncertainty.corner_pose._rotations`' arithmetic: I + sin(theta) K + (1 - cos(theta)) K K, K the
    cross-product matrix of the unit axis)."""
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    d = theta if theta >= 1e-300 else 1.0
    _skew_series_into(w0 / d, w1 / d, w2 / d, math.sin(theta), 1.0 - math.cos(theta), r)


@kernel(inline="always", **_JIT)
def _left_jacobian_into(w0, w1, w2, j):
    """*j* (3, 3): the left Jacobian of SO(3) at the rotation vector (w0, w1, w2), exp(w + d) = exp(J d) exp(w)
    (:func:`~.uncertainty.corner_pose._left_jacobian`: I + a W + b W W, W the cross-product matrix of w)."""
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    if theta < 1e-8:
        a, b = 0.5, 1.0 / 6.0
    else:
        a, b = (1.0 - math.cos(theta)) / theta ** 2, (theta - math.sin(theta)) / theta ** 3
    _skew_series_into(w0, w1, w2, a, b, j)


@kernel(inline="always", **_JIT)
def _pose_normal_equations(p, obs, points, k, dist, rot, jl, jac, err, jtj, jte):
    """The reprojection error's norm (pixels) of the pose *p* (Rodrigues vector, translation) for the *points*
    (m, 3) seen at *obs* (m, 2) by the camera *k* (3, 3), *dist* (k1, k2, p1, p2, k3); *jtj* (6, 6) and *jte* (6,)
    receive the normal equations J^T J and J^T e of the error e (projected minus seen, *err* (2 m,)) with its
    Jacobian J (*jac* (2 m, 6): :func:`~.uncertainty.corner_pose._project_batch`'s, the rotation's columns
    through the left Jacobian of SO(3)); *rot*, *jl* (3, 3) are scratch."""
    _rodrigues_into(p[0], p[1], p[2], rot)
    _left_jacobian_into(p[0], p[1], p[2], jl)
    fx, s, cx, fy, cy = k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for q in range(points.shape[0]):
        a0, a1, a2 = points[q, 0], points[q, 1], points[q, 2]
        rp0 = rot[0, 0] * a0 + rot[0, 1] * a1 + rot[0, 2] * a2         # R X
        rp1 = rot[1, 0] * a0 + rot[1, 1] * a1 + rot[1, 2] * a2
        rp2 = rot[2, 0] * a0 + rot[2, 1] * a1 + rot[2, 2] * a2
        iz = 1.0 / (rp2 + p[5])
        x, y = (rp0 + p[3]) * iz, (rp1 + p[4]) * iz
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        err[2 * q] = fx * xd + s * yd + cx - obs[q, 0]
        err[2 * q + 1] = fy * yd + cy - obs[q, 1]
        d_rad = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2))
        dxd_dx = radial + d_rad * x * x + 2.0 * p1 * y + 6.0 * p2 * x
        dxd_dy = d_rad * x * y + 2.0 * p1 * x + 2.0 * p2 * y
        dyd_dy = radial + d_rad * y * y + 6.0 * p1 * y + 2.0 * p2 * x
        for row in range(2):
            if row == 0:
                dx, dy = fx * dxd_dx + s * dxd_dy, fx * dxd_dy + s * dyd_dy
            else:
                dx, dy = fy * dxd_dy, fy * dyd_dy
            # d/dXc of (X/Z, Y/Z); a rotation w on the left moves R X by w x R X, so d/dw = (R X) x d/dXc
            g0, g1, g2 = dx * iz, dy * iz, -(dx * x + dy * y) * iz
            c0, c1, c2 = rp1 * g2 - rp2 * g1, rp2 * g0 - rp0 * g2, rp0 * g1 - rp1 * g0
            e = 2 * q + row
            for col in range(3):
                jac[e, col] = c0 * jl[0, col] + c1 * jl[1, col] + c2 * jl[2, col]
            jac[e, 3], jac[e, 4], jac[e, 5] = g0, g1, g2
    sq = 0.0
    for e in range(err.size):
        sq += err[e] * err[e]
    for a in range(6):
        v = 0.0
        for e in range(err.size):
            v += jac[e, a] * err[e]
        jte[a] = v
        for b in range(a, 6):
            v = 0.0
            for e in range(err.size):
                v += jac[e, a] * jac[e, b]
            jtj[a, b] = v
            jtj[b, a] = v
    return math.sqrt(sq)


@kernel(**_JIT)
def _solve_poses_into(obs, points, matrix, distortion, start, max_iter, epsilon, rotation, translation, converged):
    """:func:`solve_poses`' Levenberg-Marquardt, one draw after another (its docstring says what it does)."""
    m = points.shape[0]
    jac = np.empty((2 * m, 6))
    err = np.empty(2 * m)
    jtj, jtj_new, a = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
    jte, jte_new, step = np.empty(6), np.empty(6), np.empty(6)
    prev, new = np.empty(6), np.empty(6)
    piv = np.empty(6, np.int64)
    rot, jl = np.empty((3, 3)), np.empty((3, 3))
    for i in range(obs.shape[0]):
        k, dist, seen = matrix[i], distortion[i], obs[i]
        prev[:] = start
        prev_norm = _pose_normal_equations(prev, seen, points, k, dist, rot, jl, jac, err, jtj, jte)
        lam = -3
        iters = 0
        done = False
        solved = True
        while True:
            damp = 1.0 + 10.0 ** float(lam)
            for r in range(6):
                for c in range(6):
                    a[r, c] = jtj[r, c] * damp if r == c else jtj[r, c]
            if not _lu(a, piv):
                solved = False              # the draw's corners leave its pose undetermined
                break
            _lu_solve(a, piv, jte, step)
            for r in range(6):
                new[r] = prev[r] - step[r]
            norm = _pose_normal_equations(new, seen, points, k, dist, rot, jl, jac, err, jtj_new, jte_new)
            if not norm <= prev_norm:
                lam += 1
                if lam <= 16:
                    continue                # redone from the same point with more damping
            lam = max(lam - 1, -16)
            iters += 1
            moved = size = 0.0
            for r in range(6):
                moved += (new[r] - prev[r]) * (new[r] - prev[r])
                size += prev[r] * prev[r]
            if math.sqrt(moved) / max(math.sqrt(size), 1e-300) < epsilon:
                done = True
                break
            if iters >= max_iter:
                break
            prev_norm = norm
            prev, new = new, prev
            jtj, jtj_new = jtj_new, jtj
            jte, jte_new = jte_new, jte
        converged[i] = done
        if not solved:
            rotation[i] = math.nan
            translation[i] = math.nan
            continue
        _rodrigues_into(new[0], new[1], new[2], rotation[i])
        translation[i, 0], translation[i, 1], translation[i, 2] = new[3], new[4], new[5]


def solve_poses(corners_px: np.ndarray, points: np.ndarray, matrix: np.ndarray, distortion: np.ndarray,
                start: np.ndarray, max_iter: int, epsilon: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n camera-from-object poses, each refined from the pose *start* (6,) (Rodrigues vector, radians, then
    translation) so that *points* (m, 3) project through the camera *matrix* (n, 3, 3), *distortion* (n, 5)
    onto the *corners_px* (n, m, 2) with the least squared reprojection error, pixels: the Levenberg-Marquardt of
    :func:`~.uncertainty.corner_pose.solve_poses_batch`, its numpy version (the reference), one compiled pass
    over the draws (that one's cost is numpy's per-call overhead on arrays of a few hundred small matrices).

    Per draw the same algorithm: the parameters, the analytic Jacobian (the rotation's through the left Jacobian
    of SO(3)), Marquardt's damping (J^T J's diagonal times 1 + 10^l, l from -3, up by one and the step redone from
    the same point while the error grows, accepted anyway above 16, down by one after each accepted step, not
    below -16), stopping at a relative parameter change below *epsilon* or after *max_iter* accepted steps. The
    6 x 6 step is solved by LU with partial pivoting (:func:`_lu`); where a pivot is exactly zero (the draw's
    corners leave its pose undetermined) the draw is marked, its rotation and translation NaN and not converged,
    instead of the numpy version's pseudo-inverse step: the Monte Carlo drops such a draw.

    Returns
    -------
    (rotation (n, 3, 3), translation (n, 3), converged (n,) bool: stopped by *epsilon* within *max_iter*)
    """
    # copies, C-ordered and writeable, whatever the caller's (the build's one entry; a few kB)
    obs, points, matrix, distortion, start = (np.array(a, dtype=np.float64, order="C")
                                              for a in (corners_px, points, matrix, distortion, start))
    n = obs.shape[0]
    rotation, translation = np.empty((n, 3, 3)), np.empty((n, 3))
    converged = np.zeros(n, dtype=np.bool_)
    _solve_poses_into(obs, points, matrix, distortion, start.ravel(), int(max_iter), float(epsilon), rotation,
                      translation, converged)
    return rotation, translation, converged


def halves(pool, fn, n: int, *args) -> list:
    """``fn(*args, lo, hi)`` over 0:n, the first half on *pool* (an executor, or None) beside the second:
    for the element-wise kernels here, the same values on one thread or two. Returns the calls' results, one
    per half run (a count such a kernel returns is their sum)."""
    mid = n // 2 if pool is not None and n >= 2048 else 0
    first = pool.submit(fn, *args, 0, mid) if mid else None
    second = fn(*args, mid, n)
    return [second] if first is None else [first.result(), second]


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel, so the first analysis does not pay for it."""
    x = np.zeros(2)
    atan(x, out=x)
    for dtype in (np.uint8, np.uint16):
        out = [np.empty(1, np.float32) for _ in range(3)]
        phase_counts(np.zeros((4, 1), dtype=dtype), *out)
    one = np.ones((3, 1))
    reflect(one, one, np.eye(3), np.zeros(3), np.zeros(6), np.empty((3, 1)), np.empty((2, 1)), 0, 1)
    reflect_blend(one, one, np.eye(3), np.zeros(3), np.zeros(6), np.ones(1), np.zeros((3, 1)), np.zeros((2, 1)), 0, 1)
    model_residuals(x, x, x, x, [np.zeros(6)] * 2, np.ones(15), np.empty((6, 2)), 0, 2)
    cubic_sums(x, x, x, x, 0.0, 0.0, 1.0, [(0, 0)])
    parabola_sums(x, x, x, x, 0.0, 0.0)
    reweight_sums(x, x, x, x, 0.0, 0.0, np.zeros(3), np.zeros(3), (1.0, 1.0), 4.685)
    median_in_window(x, 0.0, True, -1.0, 1.0, np.empty(2))
    irls_bisquare(x, x, x, x, np.ones(2), np.ones(3), 1e-9, 1, math.nan, 4.685, 0.6745, 0.05, np.empty(3))
    for points in (False, True):
        moved(np.zeros((3, 2)), np.eye(3), np.zeros(3), 0.0, points)
    weighted_sums(x, x, x, x, x, np.empty(9))
    residuals_and_leverage(x, x, x, x, x, np.zeros(3), np.zeros(6), np.empty(2), np.empty(2))
    bisquare_into(x, 1.0, np.empty(2))
    f = np.zeros(2, dtype=np.float32)
    cleaned_residuals(f, f, f, None, np.zeros(4), np.zeros(2))
    cleaned_residuals(f, f, f, f, np.zeros(4), np.zeros(2))
    noise_rows(f, f, f, None, 1)
    noise_rows(f, f, f, f, 1)
    consistency_set(f, f, f, 1.0, np.zeros(2), np.zeros(2, dtype=np.bool_))
    to_frame_every(np.zeros((3, 2)), np.eye(3), np.zeros(3), 1)
    trim_rounds(x, x, 1.0, 1.0, 1.0, 1, 0.0)
    label_areas(np.zeros((2, 2), dtype=np.int32), 1)
    label_moments(np.zeros((2, 2), dtype=np.int32), 1)
    for dtype in (np.uint8, np.uint16):
        laplacian_median(np.zeros((5, 5), dtype=dtype)[:4, :4], np.ones((5, 5), dtype=np.bool_)[:4, :4])
    fill_holes(np.zeros((2, 2), dtype=np.int32), 1, 1, np.zeros((3, 3), dtype=np.bool_)[:2, :2])
    for dtype in (np.uint8, np.uint16):
        dot_centroids(np.zeros((4, 4), dtype=dtype), np.zeros((1, 2)), 1.0, True)
    lattice_walk(np.zeros((1, 2)), 0, np.eye(4, 2), 0.3, 1.0, 1)
    normal_slopes(np.ones((3, 2)), np.zeros(3), np.ones((3, 2)))
    for phase_dtype in (np.float32, np.float64):
        for sigma in (np.zeros(1), 0.0):
            unwrap([np.zeros(1, dtype=phase_dtype)] * 2, [1.0, 2.0], 1.0, True, 4.0, sigma)
    for dtype in (np.uint8, np.uint16):
        gather_runs(np.zeros((2, 4), dtype=dtype), np.arange(2), ([0], [2]), np.empty((2, 2), dtype=dtype))
    grid_screen_points(x, x, np.arange(2.0), np.arange(2.0), np.zeros((2, 2, 3)), np.ones((1, 1), dtype=np.bool_),
                       np.eye(3), np.zeros(3))
    minus_models(x, np.ones((1, 2)), np.ones(1))
    minus_models(x, np.ones((1, 2)), np.ones(1), np.ones((4, 2)), np.ones(4))
    grid_sums(x, x, x, x, 0.0, 0.0, 1.0, (2, 2))
    bilinear(np.zeros((2, 2)), 0.0, 0.0, 1.0, x, x)
    solve_poses(np.zeros((1, 4, 2)), np.eye(4, 3) + [0.0, 0.0, 1.0], np.eye(3)[None], np.zeros((1, 5)), np.zeros(6), 1,
                1e-7)
