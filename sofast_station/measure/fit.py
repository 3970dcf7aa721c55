"""Least-squares shape fits in slope space (docs/conventions.md#twist, #data-reduction).

Every sum over the points is formed by the compiled kernels (measure/kernels.py: blocks of 16,384 points
summed on their own, then added in block order) or by einsum's own loops, never a BLAS call, so a fit
gives the same bits whatever the number of threads (docs/conventions.md#determinism).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import AnalysisError
from .kernels import ILL_CONDITIONED, SINGULAR, cubic_sums, irls_bisquare, parabola_sums, reweight_sums, sum_squares


def _solve_scaled(gram: np.ndarray, rhs: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The normal equations from the sums of the unscaled column products *gram* and column-target
    products *rhs*, the columns scaled to unit RMS (*scale*, their RMS values) before solving."""
    gram = gram / np.outer(scale, scale)
    rhs = rhs / scale
    try:
        sol = np.linalg.solve(gram, rhs)
    except np.linalg.LinAlgError:
        raise AnalysisError("the slope fit is singular: the valid points do not cover enough of the facet")
    if np.linalg.cond(gram) > 1e12:
        raise AnalysisError("the slope fit is ill-conditioned: the valid points cover too little of the facet")
    return sol / scale


def monomial_powers(degree: int) -> list[tuple[int, int]]:
    """The exponents (i, j) of the monomials u^i v^j of total degree at most *degree*, i outer, j inner."""
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def monomials(u: np.ndarray, v: np.ndarray, degree: int) -> np.ndarray:
    """The design matrix (N, K) of those monomials at the points (*u*, *v*) ((N,) each), in that order."""
    return np.stack([u ** i * v ** j for i, j in monomial_powers(degree)], axis=1)


@dataclass(frozen=True)
class ParabolaFit:
    """The paper's two separate slope fits, s_x = 2A x + C + E1 y and s_y = 2B y + D + E2 x.

    The assembled surface z = A x^2 + B y^2 + C x + D y + E xy + F uses E = (E1 + E2)/2; F is not a slope
    quantity and is set by the caller.

    A robust fit also keeps, per equation, the bisquare weights of its points and the residual scale
    (sigma, slope units) of its last iteration: a later fit on the same points starts from those weights,
    and :func:`reweight_parabola` finishes on other points with that scale. They take no part in equality.
    """

    a: float
    b: float
    c: float
    d: float
    e1: float
    e2: float
    weights: tuple | None = field(default=None, compare=False, repr=False)
    sigma: tuple | None = field(default=None, compare=False, repr=False)

    @property
    def e(self) -> float:
        return 0.5 * (self.e1 + self.e2)

    def coefficients(self, f: float = 0.0) -> np.ndarray:
        """(A, B, C, D, E, F) of the assembled surface."""
        return np.array([self.a, self.b, self.c, self.d, self.e, f])


#: Tukey bisquare tuning constant (95 % efficiency for normal errors) and the MAD-to-sigma factor.
BISQUARE_C = 4.685
MAD_TO_SIGMA = 0.6745
#: Half-width of the window, in residual sigmas (plus twice the last step), in which the robust fit looks
#: for the residuals' median and MAD first: about 4 % of normal residuals lie within +-0.05 sigma of the
#: median. Only the time depends on it.
WINDOW_SIGMAS = 0.01


def robust_weights(columns: list[np.ndarray], target: np.ndarray, max_iterations: int = 50,
                   tolerance: float = 1e-9, weights: np.ndarray | None = None,
                   start_sigma: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Iteratively reweighted least squares with Tukey's bisquare (as in robust regression texts).

    Residuals are adjusted for leverage (r / sqrt(1 - h)), scaled by their median absolute deviation,
    and weighted (1 - u^2)^2 for |u| < 1, else 0, with u = r_adj / (4.685 sigma), sigma = MAD / 0.6745.
    Stops when the mean squared residual changes by less than *tolerance* (relative) or after
    *max_iterations*.

    Each iteration solves the small (k x k) normal equations from weighted sums of the column products,
    which are formed once: a handful of passes over the points instead of a least-squares solve.

    Parameters
    ----------
    weights : array, optional
        Starting weights (a previous fit's on the same points, when the data have moved only a little):
        the iteration then needs a few steps instead of some twenty from equal weights.
    start_sigma : float, optional
        That fit's residual scale: where the first reweighting looks for the residuals' MAD first
        (the result does not depend on it).

    Returns
    -------
    (coefficients, weights, sigma)
        sigma is the residual scale of the last reweighting (slope units; NaN when none was done).
    """
    if len(columns) != 3:
        raise ValueError(f"robust_weights fits three columns (a slope equation), got {len(columns)}")
    n = target.size
    cols = [np.ascontiguousarray(c, dtype=np.float64) for c in columns]
    target = np.ascontiguousarray(target, dtype=np.float64)
    scale = np.sqrt(np.array(sum_squares(*cols)) / n)
    if np.any(scale == 0) or not np.all(np.isfinite(scale)):
        raise AnalysisError("the fit's points do not span the facet (a design column is zero or not finite); "
                            "too few valid points")
    w = np.ones(n) if weights is None else np.array(weights, dtype=np.float64)
    coef = np.empty(3)
    # The whole iteration in one compiled call that releases the GIL: the two slope equations' fits run
    # at once on two threads (as Python loops they took turns for the GIL: 0.2 ms a reweighting instead
    # of 0.05).
    status, sigma = irls_bisquare(*cols, target, w, scale, float(tolerance), int(max_iterations),
                                  float(start_sigma) if start_sigma is not None else float("nan"), BISQUARE_C,
                                  MAD_TO_SIGMA, WINDOW_SIGMAS, coef)
    if status == SINGULAR:
        raise AnalysisError("the slope fit is singular: the valid points do not cover enough of the facet")
    if status == ILL_CONDITIONED:
        raise AnalysisError("the slope fit is ill-conditioned: the valid points cover too little of the facet")
    return coef, w, float(sigma)


def _centred(x: np.ndarray, y: np.ndarray):
    xm = float(np.sum(x) / x.size)
    ym = float(np.sum(y) / y.size)
    return xm, ym, x - xm, y - ym


def _assemble(kx, ky, xm: float, ym: float, **extra) -> ParabolaFit:
    a, e1 = 0.5 * kx[0], kx[2]
    b, e2 = 0.5 * ky[0], ky[2]
    c = kx[1] - 2.0 * a * xm - e1 * ym
    d = ky[1] - 2.0 * b * ym - e2 * xm
    return ParabolaFit(float(a), float(b), float(c), float(d), float(e1), float(e2), **extra)


def fit_parabola(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray,
                 robust: bool = False, start: ParabolaFit | None = None, pool=None,
                 robust_tolerance: float = 1e-9) -> ParabolaFit:
    """Fit the two slope equations separately (metres in, slopes dimensionless).

    Positions are centred on their mean before fitting (the constant terms are restored exactly), so a
    gore facet far from its frame's origin fits as well as a centred one. With *robust*, each equation
    is fitted by bisquare-weighted least squares (:func:`robust_weights`), which keeps outliers (edge
    pixels seeing past the screen, dust) from pulling the shape; *start*, a robust fit of the same points
    in an earlier iteration, supplies the starting weights, and *pool* (an executor) runs the second
    equation's iteration beside the first (each does the same arithmetic on any thread);
    *robust_tolerance* is the reweighting's stopping tolerance (see :func:`robust_weights`).
    """
    if x.size < 10:
        raise AnalysisError(f"only {x.size} valid points: too few to fit a shape")
    if not robust:
        return _plain_parabola(x, y, s_x, s_y)
    xm, ym, xc, yc = _centred(x, y)
    one = np.ones_like(xc)
    wx, wy = start.weights if start is not None and start.weights is not None else (None, None)
    sx0, sy0 = start.sigma if start is not None and start.sigma is not None else (None, None)
    tol = float(robust_tolerance)
    second = None if pool is None else pool.submit(robust_weights, [yc, one, xc], s_y, tolerance=tol, weights=wy,
                                                   start_sigma=sy0)
    kx, wx, sig_x = robust_weights([xc, one, yc], s_x, tolerance=tol, weights=wx, start_sigma=sx0)
    ky, wy, sig_y = (robust_weights([yc, one, xc], s_y, tolerance=tol, weights=wy, start_sigma=sy0)
                     if second is None else second.result())
    return _assemble(kx, ky, xm, ym, weights=(wx, wy), sigma=(sig_x, sig_y))


def _plain_parabola(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray) -> ParabolaFit:
    """:func:`fit_parabola` without weights: both equations' columns are xc, 1, yc, so every sum they need
    comes from one compiled pass over the points (the centred columns are never formed)."""
    xm = float(np.sum(x) / x.size)
    ym = float(np.sum(y) / y.size)
    xx, x1, xy, yy, y1, xsx, sx1, ysx, ysy, sy1, xsy = parabola_sums(x, y, s_x, s_y, xm, ym)
    n = float(x.size)
    rms_x, rms_y = np.sqrt(xx / n), np.sqrt(yy / n)
    if not (rms_x > 0 and rms_y > 0 and np.isfinite(rms_x) and np.isfinite(rms_y)):
        raise AnalysisError("the fit's points do not span the facet (a design column is zero or not finite); "
                            "too few valid points")
    grams = np.array([[[xx, x1, xy], [x1, n, y1], [xy, y1, yy]], [[yy, y1, xy], [y1, n, x1], [xy, x1, xx]]])
    rhs = np.array([[xsx, sx1, ysx], [ysy, sy1, xsy]])
    scales = np.array([[rms_x, 1.0, rms_y], [rms_y, 1.0, rms_x]])
    kx, ky = _solve_scaled_pair(grams, rhs, scales)        # (2A, C', E1), (2B, D', E2)
    return _assemble(kx, ky, xm, ym)


def _solve_scaled_pair(grams: np.ndarray, rhs: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """:func:`_solve_scaled` of two systems (*grams* (2, 3, 3), *rhs* and *scales* (2, 3)) by one call of each
    of numpy's stacked solve and condition number (LAPACK's same routine per system: the same bits, for half
    the calls' overhead; the all-point fit runs 60 times per capture in the uncertainty's shape reruns). A
    system that cannot be solved goes through :func:`_solve_scaled` one by one, which says which way."""
    g = grams / (scales[:, :, None] * scales[:, None, :])
    try:
        sol = np.linalg.solve(g, (rhs / scales)[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.array([_solve_scaled(grams[k], rhs[k], scales[k]) for k in range(2)])
    if np.any(np.linalg.cond(g) > 1e12):
        return np.array([_solve_scaled(grams[k], rhs[k], scales[k]) for k in range(2)])
    return sol / scales


def _newton_solve(sums: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The Newton step (X^T diag(psi') X)^-1 X^T (w r) from :func:`~.kernels.reweight_sums`, the columns scaled to unit
    RMS (*scale*, their RMS values) as in :func:`_solve_scaled`."""
    rhs = sums[:3] / scale
    g = sums[3:]                      # (0,0) (0,1) (0,2) (1,1) (1,2) (2,2)
    gram = np.array([[g[0], g[1], g[2]], [g[1], g[3], g[4]], [g[2], g[4], g[5]]]) / np.outer(scale, scale)
    if not np.all(np.linalg.eigvalsh(gram) > 1e-12 * np.abs(gram).max()):
        raise AnalysisError("the robust fit's last step is not a minimum: too many points lie far from the "
                            "subsample's fit; check the capture (or use the plain fit)")
    return np.linalg.solve(gram, rhs) / scale


def reweight_parabola(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray,
                      start: ParabolaFit, pool=None) -> ParabolaFit:
    """The robust fit on all points: one Newton step of the bisquare M-estimate from a converged robust fit.

    The bisquare iteration converges on the subsample (every n-th point, :func:`fit_parabola` with
    ``robust=True``); here the residuals of every point from that fit, scaled by that fit's sigma, give
    one Newton-Raphson step of the M-estimate on all points: a one-step M-estimate (Bickel, "One-step
    Huber estimates in the linear model", JASA 1975), which agrees with iterating to convergence on all
    points to within a small fraction of its own statistical uncertainty, at the cost of one plain fit.
    (Leverage is left out here: it is ~k/N, below 1e-5 for a full capture.)

    Both equations' terms and sums are formed in one pass, block by block in cache
    (:func:`~sofast_station.measure.kernels.reweight_sums`; *pool*, an executor, takes half of the blocks):
    the same bits on any number of threads, and the same fit as one sum over all points but for the
    sums' last bits.
    """
    if x.size < 10:
        raise AnalysisError(f"only {x.size} valid points: too few to fit a shape")
    if start.sigma is None or not all(np.isfinite(start.sigma)):
        return fit_parabola(x, y, s_x, s_y, robust=True)
    xm = float(np.sum(x) / x.size)
    ym = float(np.sum(y) / y.size)
    # The start in centred coordinates: s_x = 2A xc + (C + 2A xm + E1 ym) + E1 yc, and alike for s_y.
    k0x = np.array([2.0 * start.a, start.c + 2.0 * start.a * xm + start.e1 * ym, start.e1])
    k0y = np.array([2.0 * start.b, start.d + 2.0 * start.b * ym + start.e2 * xm, start.e2])
    sums = reweight_sums(x, y, s_x, s_y, xm, ym, k0x, k0y, start.sigma, BISQUARE_C, pool=pool)
    rms_x, rms_y = np.sqrt(sums[0] / x.size), np.sqrt(sums[1] / x.size)
    kx = k0x + _newton_solve(sums[2:11], np.array([rms_x, 1.0, rms_y]))
    ky = k0y + _newton_solve(sums[11:20], np.array([rms_y, 1.0, rms_x]))
    return _assemble(kx, ky, xm, ym, sigma=start.sigma)


#: Terms (i, j) of the higher-order model z = sum c_ij x^i y^j, 1 <= i + j <= 3 (the constant is free).
CUBIC_TERMS = ((1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3))
# Monomials u^a v^b of degree <= 2 that the slopes of those terms are made of.
_BASE = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))


@dataclass(frozen=True)
class CubicFit:
    """Higher-order model (3rd order in z, 2nd order in slope) in centred, scaled coordinates.

    z = sum_k c_k u^i_k v^j_k with u = (x - x0)/h, v = (y - y0)/h and (i_k, j_k) = CUBIC_TERMS[k].
    """

    coefficients: np.ndarray
    x0: float
    y0: float
    h: float

    def slopes(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Model slopes dz/dx, dz/dy at facet-frame (x, y), metres."""
        u, v = (x - self.x0) / self.h, (y - self.y0) / self.h
        return self._slopes([None, u, v, u * u, u * v, v * v])

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Model height z at facet-frame (x, y), metres, up to the model's free constant (taken as 0)."""
        u, v = (np.asarray(x, np.float64) - self.x0) / self.h, (np.asarray(y, np.float64) - self.y0) / self.h
        return sum(c * u ** i * v ** j for c, (i, j) in zip(self.coefficients, CUBIC_TERMS))

    def slope_coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """Each slope (dz/dx, dz/dy) as a quadratic in (u, v): its coefficients of 1, u, v, u^2, uv, v^2."""
        cx, cy = np.zeros(len(_BASE)), np.zeros(len(_BASE))
        for c, (i, j) in zip(self.coefficients, CUBIC_TERMS):
            if i:
                cx[_BASE.index((i - 1, j))] += c * i / self.h
            if j:
                cy[_BASE.index((i, j - 1))] += c * j / self.h
        return cx, cy

    def _slopes(self, base: list) -> tuple[np.ndarray, np.ndarray]:
        """The slopes from the monomials (1), u, v, u^2, uv, v^2 of the points (``base[0]`` unused)."""
        # Each slope is a quadratic in (u, v): its six coefficients first, then one pass per monomial.
        cx, cy = self.slope_coefficients()
        u = base[1]
        out = []
        for coef in (cx, cy):
            acc = np.multiply(u, coef[1])
            acc += coef[0]
            tmp = np.empty_like(acc)
            for m in range(2, len(_BASE)):
                acc += np.multiply(base[m], coef[m], out=tmp)
            out.append(acc)
        return out[0], out[1]

    def to_dict(self) -> dict:
        return {"terms": [f"u^{i} v^{j}" for i, j in CUBIC_TERMS], "coefficients": self.coefficients.tolist(),
                "u": f"(x - {self.x0!r}) / {self.h!r}", "v": f"(y - {self.y0!r}) / {self.h!r}"}


#: The distinct sums of the monomials' pairwise products (a <= b, rows last to first, as assembled):
#: 1 x u^2, 1 x uv, 1 x v^2 are the products u x u, u x v, v x v, so they are taken from those.
_GRAM_PAIRS = [(a, b) for a in reversed(range(len(_BASE))) for b in range(a, len(_BASE))
               if (a, b) not in ((0, 3), (0, 4), (0, 5))]
_SAME = {(0, 3): (1, 1), (0, 4): (1, 2), (0, 5): (2, 2)}


def fit_cubic(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray) -> CubicFit:
    """Fit the higher-order model: both slope equations stacked, with shared coefficients.

    The slopes of every term are multiples of the six monomials of degree <= 2, so the normal equations
    are assembled from their 21 pairwise sums instead of a (2N x 9) design matrix.
    """
    if x.size < 30:
        raise AnalysisError(f"only {x.size} valid points: too few to fit the higher-order model")
    x0 = float(np.sum(x) / x.size)
    y0 = float(np.sum(y) / y.size)
    # max |x - x0| without the temporary: rounding is monotonic, so these are the same numbers.
    h = float(max(np.max(x) - x0, x0 - np.min(x), np.max(y) - y0, y0 - np.min(y), 1e-9))
    # The monomials and their sums block by block in cache (the blocks' sums added in order: one sum
    # over all points but for the last bits).
    sums = cubic_sums(x, y, s_x, s_y, x0, y0, h, _GRAM_PAIRS)
    nb = len(_BASE)
    gram_b = np.empty((nb, nb))
    for (a, b), value in zip(_GRAM_PAIRS, sums):
        gram_b[a, b] = gram_b[b, a] = value
    for (a, b), same in _SAME.items():
        gram_b[a, b] = gram_b[b, a] = gram_b[same]
    rhs_x = sums[len(_GRAM_PAIRS):len(_GRAM_PAIRS) + nb]
    rhs_y = sums[len(_GRAM_PAIRS) + nb:]
    n = len(CUBIC_TERMS)
    gram = np.zeros((n, n))
    rhs = np.zeros(n)
    for k, (ik, jk) in enumerate(CUBIC_TERMS):
        ax = _BASE.index((ik - 1, jk)) if ik else None
        ay = _BASE.index((ik, jk - 1)) if jk else None
        if ax is not None:
            rhs[k] += ik / h * rhs_x[ax]
        if ay is not None:
            rhs[k] += jk / h * rhs_y[ay]
        for m, (il, jl) in enumerate(CUBIC_TERMS):
            bx = _BASE.index((il - 1, jl)) if il else None
            by = _BASE.index((il, jl - 1)) if jl else None
            if ax is not None and bx is not None:
                gram[k, m] += ik * il / h**2 * gram_b[ax, bx]
            if ay is not None and by is not None:
                gram[k, m] += jk * jl / h**2 * gram_b[ay, by]
    scale = np.sqrt(np.diag(gram))
    g = gram / np.outer(scale, scale)
    if np.linalg.cond(g) > 1e12:
        raise AnalysisError("the higher-order fit is ill-conditioned: the valid points cover too little of the facet")
    coef = np.linalg.solve(g, rhs / scale) / scale
    return CubicFit(coef, x0, y0, h)


#: The shape models a facet may be fitted with (``[analysis] surface``): the paper's parabola, or a plane
#: (OpenCSP's plano surface: constant slopes, for a flat mirror, or to measure only where a mirror points).
SURFACES = ("parabolic", "plano")


def bisquare_location(values: np.ndarray, tolerance: float = 1e-9, max_iterations: int = 50) -> float:
    """The bisquare M-estimate of location of *values* (Tukey's weights, c = :data:`BISQUARE_C`, the scale
    the median absolute deviation / :data:`MAD_TO_SIGMA`), from the median: the robust plane's slope."""
    v = np.asarray(values, np.float64)
    mu = float(np.median(v))
    for _ in range(max_iterations):
        r = v - mu
        sigma = float(np.median(np.abs(r))) / MAD_TO_SIGMA
        if not sigma > 0:
            return mu
        u = r / (BISQUARE_C * sigma)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
        total = float(np.sum(w))
        if total <= 0:
            raise AnalysisError("the robust plane fit has no point within its weights: too few valid points")
        new = float(np.sum(w * v) / total)
        if abs(new - mu) <= tolerance * max(sigma, 1e-300):
            return new
        mu = new
    return mu


def fit_plane(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray, robust: bool = False) -> ParabolaFit:
    """The plano model: constant slopes s_x = C, s_y = D (A = B = E1 = E2 = 0), their mean, or with *robust*
    their bisquare location (:func:`bisquare_location`). Returned as a :class:`ParabolaFit` so that the
    boresight, the intersections and the residuals treat it as the parabola they already know."""
    if x.size < 10:
        raise AnalysisError(f"only {x.size} valid points: too few to fit a shape")
    if robust:
        c, d = bisquare_location(s_x), bisquare_location(s_y)
    else:
        c, d = float(np.sum(s_x) / s_x.size), float(np.sum(s_y) / s_y.size)
    return ParabolaFit(0.0, 0.0, c, d, 0.0, 0.0)


def fit_surface(surface: str, x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray, robust: bool = False,
                start: ParabolaFit | None = None, pool=None, robust_tolerance: float = 1e-9) -> ParabolaFit:
    """The slope fit of the shape model *surface* (:data:`SURFACES`): :func:`fit_parabola` or :func:`fit_plane`."""
    if surface == "plano":
        return fit_plane(x, y, s_x, s_y, robust=robust)
    if surface != "parabolic":
        raise ValueError(f"surface must be one of {SURFACES}, got {surface!r}")
    return fit_parabola(x, y, s_x, s_y, robust=robust, start=start, pool=pool, robust_tolerance=robust_tolerance)
