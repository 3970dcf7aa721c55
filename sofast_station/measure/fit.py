"""Least-squares shape fits in slope space (SPEC.md, "Twist" and "Data reduction").

Every sum here is an ``np.sum`` of an element-wise product (pairwise summation on one thread), never a
BLAS call, so a fit gives the same bits whatever the number of threads (SPEC.md, "Determinism").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import AnalysisError


def solve_normal_equations(columns: list[np.ndarray], target: np.ndarray) -> np.ndarray:
    """Coefficients k minimising |sum_j k_j columns[j] - target|^2, deterministically.

    Columns are scaled to unit RMS before the Gram matrix is formed, which keeps it well conditioned
    for any sensible choice of units.
    """
    scale = np.array([np.sqrt(np.sum(c * c) / c.size) for c in columns])
    if np.any(scale == 0) or not np.all(np.isfinite(scale)):
        raise AnalysisError("the fit's points do not span the facet (a design column is zero or not finite); "
                            "too few valid points")
    cols = [c / s for c, s in zip(columns, scale)]
    k = len(cols)
    gram = np.empty((k, k))
    rhs = np.empty(k)
    for i in range(k):
        rhs[i] = np.sum(cols[i] * target)
        for j in range(i, k):
            gram[i, j] = gram[j, i] = np.sum(cols[i] * cols[j])
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


def fit_parabola(x: np.ndarray, y: np.ndarray, s_x: np.ndarray, s_y: np.ndarray) -> ParabolaFit:
    """Fit the two slope equations separately (metres in, slopes dimensionless).

    Positions are centred on their mean before fitting (the constant terms are restored exactly), so a
    gore facet far from its frame's origin fits as well as a centred one.
    """
    if x.size < 10:
        raise AnalysisError(f"only {x.size} valid points: too few to fit a shape")
    xm = float(np.sum(x) / x.size)
    ym = float(np.sum(y) / y.size)
    xc, yc = x - xm, y - ym
    one = np.ones_like(xc)
    kx = solve_normal_equations([xc, one, yc], s_x)      # 2A, C', E1
    ky = solve_normal_equations([yc, one, xc], s_y)      # 2B, D', E2
    a, e1 = 0.5 * kx[0], kx[2]
    b, e2 = 0.5 * ky[0], ky[2]
    c = kx[1] - 2.0 * a * xm - e1 * ym
    d = ky[1] - 2.0 * b * ym - e2 * xm
    return ParabolaFit(float(a), float(b), float(c), float(d), float(e1), float(e2))
