"""Least-squares shape fits in slope space (docs/conventions.md#twist, #data-reduction).

Every sum here is an ``np.sum`` of an element-wise product (pairwise summation on one thread), never a
BLAS call, so a fit gives the same bits whatever the number of threads (docs/conventions.md#determinism).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import AnalysisError


def solve_normal_equations(columns: list[np.ndarray], target: np.ndarray,
                           weights: np.ndarray | None = None) -> np.ndarray:
    """Coefficients k minimising sum_i w_i (sum_j k_j columns[j]_i - target_i)^2, deterministically.

    Columns are scaled to unit RMS before the Gram matrix is formed, which keeps it well conditioned
    for any sensible choice of units. Without *weights* every point weighs 1.
    """
    scale = np.array([np.sqrt(np.sum(c * c) / c.size) for c in columns])
    if np.any(scale == 0) or not np.all(np.isfinite(scale)):
        raise AnalysisError("the fit's points do not span the facet (a design column is zero or not finite); "
                            "too few valid points")
    cols = [c / s for c, s in zip(columns, scale)]
    wcols = cols if weights is None else [c * weights for c in cols]
    k = len(cols)
    gram = np.empty((k, k))
    rhs = np.empty(k)
    for i in range(k):
        rhs[i] = np.sum(wcols[i] * target)
        for j in range(i, k):
            gram[i, j] = gram[j, i] = np.sum(wcols[i] * cols[j])
    try:
        sol = np.linalg.solve(gram, rhs)
    except np.linalg.LinAlgError:
        raise AnalysisError("the slope fit is singular: the valid points do not cover enough of the facet")
    if np.linalg.cond(gram) > 1e12:
        raise AnalysisError("the slope fit is ill-conditioned: the valid points cover too little of the facet")
    return sol / scale


@dataclass(frozen=True)
class ParabolaFit:
    """The paper's two separate slope fits, s_x = 2A x + C + E1 y and s_y = 2B y + D + E2 x.

    The assembled surface z = A x^2 + B y^2 + C x + D y + E xy + F uses E = (E1 + E2)/2; F is not a slope
    quantity and is set by the caller.
    """

    a: float
    b: float
    c: float
    d: float
    e1: float
    e2: float

    @property
    def e(self) -> float:
        return 0.5 * (self.e1 + self.e2)

    def coefficients(self, f: float = 0.0) -> np.ndarray:
        """(A, B, C, D, E, F) of the assembled surface."""
        return np.array([self.a, self.b, self.c, self.d, self.e, f])


#: Tukey bisquare tuning constant (95 % efficiency for normal errors) and the MAD-to-sigma factor.
BISQUARE_C = 4.685
MAD_TO_SIGMA = 0.6745


def robust_weights(columns: list[np.ndarray], target: np.ndarray, max_iterations: int = 50,
                   tolerance: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Iteratively reweighted least squares with Tukey's bisquare (as in robust regression texts).

    Residuals are adjusted for leverage (r / sqrt(1 - h)), scaled by their median absolute deviation,
    and weighted (1 - u^2)^2 for |u| < 1, else 0, with u = r_adj / (4.685 sigma). Stops when the mean
    squared residual changes by less than *tolerance* (relative) or after *max_iterations*.

    Returns
    -------
    (coefficients, weights)
    """
    w = np.ones_like(target)
    prev = None
    k = None
    for _ in range(max_iterations):
        k = solve_normal_equations(columns, target, w)
        model = sum(c * kk for c, kk in zip(columns, k))
        r = target - model
        ms = float(np.sum(w * r * r) / max(np.sum(w), 1.0))
        if prev is not None and abs(ms - prev) <= tolerance * max(prev, 1e-30):
            break
        prev = ms
        # leverage of each point under the current weights: h_i = w_i x_i^T (X^T W X)^-1 x_i
        gram = np.array([[np.sum(w * a * b) for b in columns] for a in columns])
        inv = np.linalg.inv(gram)
        h = w * sum(columns[i] * columns[j] * inv[i, j] for i in range(len(columns)) for j in range(len(columns)))
        r_adj = r / np.sqrt(np.clip(1.0 - h, 1e-12, None))
        mad = float(np.median(np.abs(r_adj - np.median(r_adj))))
        if mad == 0.0:
            break
        u = r_adj / (BISQUARE_C * mad / MAD_TO_SIGMA)
        w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    return k, w


def fit_parabola(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray,
                 robust: bool = False) -> ParabolaFit:
    """Fit the two slope equations separately (metres in, slopes dimensionless).

    Positions are centred on their mean before fitting (the constant terms are restored exactly), so a
    gore facet far from its frame's origin fits as well as a centred one. With *robust*, each equation
    is fitted by bisquare-weighted least squares (:func:`robust_weights`), which keeps outliers (edge
    pixels seeing past the screen, dust) from pulling the shape.
    """
    if x.size < 10:
        raise AnalysisError(f"only {x.size} valid points: too few to fit a shape")
    xm = float(np.sum(x) / x.size)
    ym = float(np.sum(y) / y.size)
    xc, yc = x - xm, y - ym
    one = np.ones_like(xc)
    if robust:
        kx = robust_weights([xc, one, yc], s_x)[0]
        ky = robust_weights([yc, one, xc], s_y)[0]
    else:
        kx = solve_normal_equations([xc, one, yc], s_x)      # 2A, C', E1
        ky = solve_normal_equations([yc, one, xc], s_y)      # 2B, D', E2
    a, e1 = 0.5 * kx[0], kx[2]
    b, e2 = 0.5 * ky[0], ky[2]
    c = kx[1] - 2.0 * a * xm - e1 * ym
    d = ky[1] - 2.0 * b * ym - e2 * xm
    return ParabolaFit(float(a), float(b), float(c), float(d), float(e1), float(e2))


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
        base = _monomials(u, v)
        sx = np.zeros_like(u)
        sy = np.zeros_like(u)
        for c, (i, j) in zip(self.coefficients, CUBIC_TERMS):
            if i:
                sx = sx + (c * i / self.h) * base[_BASE.index((i - 1, j))]
            if j:
                sy = sy + (c * j / self.h) * base[_BASE.index((i, j - 1))]
        return sx, sy

    def to_dict(self) -> dict:
        return {"terms": [f"u^{i} v^{j}" for i, j in CUBIC_TERMS], "coefficients": self.coefficients.tolist(),
                "u": f"(x - {self.x0!r}) / {self.h!r}", "v": f"(y - {self.y0!r}) / {self.h!r}"}


def _monomials(u: np.ndarray, v: np.ndarray) -> list[np.ndarray]:
    one = np.ones_like(u)
    return [one, u, v, u * u, u * v, v * v]


def fit_cubic(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray) -> CubicFit:
    """Fit the higher-order model: both slope equations stacked, with shared coefficients.

    The slopes of every term are multiples of the six monomials of degree <= 2, so the normal equations
    are assembled from their 21 pairwise sums instead of a (2N x 9) design matrix.
    """
    if x.size < 30:
        raise AnalysisError(f"only {x.size} valid points: too few to fit the higher-order model")
    x0 = float(np.sum(x) / x.size)
    y0 = float(np.sum(y) / y.size)
    h = float(max(np.max(np.abs(x - x0)), np.max(np.abs(y - y0)), 1e-9))
    u, v = (x - x0) / h, (y - y0) / h
    base = _monomials(u, v)
    nb = len(_BASE)
    gram_b = np.empty((nb, nb))
    for a in range(nb):
        for b in range(a, nb):
            gram_b[a, b] = gram_b[b, a] = np.sum(base[a] * base[b])
    rhs_x = np.array([np.sum(m * s_x) for m in base])
    rhs_y = np.array([np.sum(m * s_y) for m in base])
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
        for l, (il, jl) in enumerate(CUBIC_TERMS):
            bx = _BASE.index((il - 1, jl)) if il else None
            by = _BASE.index((il, jl - 1)) if jl else None
            if ax is not None and bx is not None:
                gram[k, l] += ik * il / h**2 * gram_b[ax, bx]
            if ay is not None and by is not None:
                gram[k, l] += jk * jl / h**2 * gram_b[ay, by]
    scale = np.sqrt(np.diag(gram))
    g = gram / np.outer(scale, scale)
    if np.linalg.cond(g) > 1e12:
        raise AnalysisError("the higher-order fit is ill-conditioned: the valid points cover too little of the facet")
    coef = np.linalg.solve(g, rhs / scale) / scale
    return CubicFit(coef, x0, y0, h)
