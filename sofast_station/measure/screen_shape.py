"""Screen shape models: where, in the screen frame, each display position really is.

A model maps a display position (u_x, u_y), metres counted in the *stated* pitch from the active area's
left and bottom edges (what the fringes encode), to a screen-frame point. With the normalised coordinates
xi = (u_x - W/2) / (W/2), eta = (u_y - H/2) / (H/2) in [-1, 1] (W, H the stated active extents) ::

    x = (W/2) xi (1 + a_x) + sum_k cx_k m_k(xi, eta)
    y = (H/2) eta (1 + a_y) + sum_k cy_k m_k(xi, eta)
    z =                      sum_k cz_k m_k(xi, eta)          coefficients in metres

The terms m_k are polynomials in xi and eta. Those of x and y that are odd in the same coordinate as the
scale term (x's in eta, as its shear) use Legendre's polynomials, P2(t) = (3 t^2 - 1) / 2 and
P3(t) = (5 t^3 - 3 t) / 2, instead of monomials: over the screen they are orthogonal to the linear terms,
so a_x and a_y stay the screen's mean scale (its pitch) and do not trade with a distortion (with
monomials, xi^3 and xi did, and the pitch's uncertainty in the distorted models was 2.4 times the flat
model's on the twin's views).

Three models, after OpenCSP's display models (``CalibrateDisplayShape``: rectangular, distorted 2-D,
distorted 3-D):

``flat``
    a rectangle of unknown pitch: a_x, a_y only (the pitch is the stated one times 1 + a).
``distorted2d``
    a flat screen whose image is distorted in its plane (a projection screen): x and y gain the terms of
    degree 2 and 3, and x a shear (eta).
``distorted3d``
    and out of its plane: z gains the terms of degree 2 to 4 (a bow is ``xi^2``, ``eta^2``, ``xi^2 eta^2``;
    a twist ``xi eta``).

The screen frame is fixed by the model (no parameter moves it): its origin is the display's centre point
(no constant terms), +z the normal there (no terms of z linear in xi, eta), +x along the display row
through the centre (no term of y linear in xi). So a model's parameters are the shape alone, and the
camera poses that see it carry the rest.

Pure functions of arrays; the fit is :mod:`sofast_station.measure.commission`'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: The models, simplest first.
MODELS = ("flat", "distorted2d", "distorted3d")

def _p2(t):
    return 1.5 * t * t - 0.5


def _p3(t):
    return 2.5 * t ** 3 - 1.5 * t


#: One term: its name and its value at (xi, eta).
_TERMS = {
    "1,0": lambda u, v: u, "0,1": lambda u, v: v,
    "2,0": lambda u, v: u * u, "1,1": lambda u, v: u * v, "0,2": lambda u, v: v * v,
    "3,0": lambda u, v: u ** 3, "2,1": lambda u, v: u * u * v,
    "1,2": lambda u, v: u * v * v, "0,3": lambda u, v: v ** 3,
    "P3,0": lambda u, v: _p3(u), "1,P2": lambda u, v: u * _p2(v), "P2,1": lambda u, v: _p2(u) * v,
    "0,P3": lambda u, v: _p3(v),
    "4,0": lambda u, v: u ** 4, "3,1": lambda u, v: u ** 3 * v, "2,2": lambda u, v: u * u * v * v,
    "1,3": lambda u, v: u * v ** 3, "0,4": lambda u, v: v ** 4,
}
# x: its shear (eta), and of degree 2 and 3 (odd in xi or eta: Legendre's, orthogonal to xi and eta)
_X_TERMS = ("0,1", "2,0", "1,1", "0,2", "P3,0", "1,P2", "P2,1", "0,P3")
# y: no xi term (the frame's x axis lies along the centre row); odd in eta: Legendre's (orthogonal to eta);
# odd in xi: monomials (their slope along xi vanishes at the centre, as the frame's axis needs)
_Y_TERMS = ("2,0", "1,1", "0,2", "3,0", "P2,1", "1,2", "0,P3")
# z: degree 2 to 4, no constant or linear term (the frame's origin and normal)
_Z_TERMS = ("2,0", "1,1", "0,2", "3,0", "2,1", "1,2", "0,3", "4,0", "3,1", "2,2", "1,3", "0,4")


def model_terms(model: str) -> tuple[tuple, tuple, tuple]:
    """The terms (names, ``i,j`` for xi^i eta^j, ``P2``/``P3`` for Legendre's) of x, y and z of *model* (the
    pitch terms a_x, a_y come first, always)."""
    if model == "flat":
        return (), (), ()
    if model == "distorted2d":
        return _X_TERMS, _Y_TERMS, ()
    if model == "distorted3d":
        return _X_TERMS, _Y_TERMS, _Z_TERMS
    raise ValueError(f"unknown screen model {model!r}; use one of {', '.join(MODELS)}")


def parameter_names(model: str) -> list[str]:
    """Names of the parameters of *model*, in order: ``a_x``, ``a_y``, then ``x:<term>``, ``y:<term>``,
    ``z:<term>``."""
    tx, ty, tz = model_terms(model)
    return ["a_x", "a_y"] + [f"x:{t}" for t in tx] + [f"y:{t}" for t in ty] + [f"z:{t}" for t in tz]


@dataclass(frozen=True)
class ScreenShape:
    """A screen shape model with its parameters (module docstring).

    Attributes
    ----------
    model : str
        ``"flat"``, ``"distorted2d"`` or ``"distorted3d"``.
    width_m, height_m : float
        The stated active extents W and H, metres: the units of the positions.
    params : (n,) array
        ``a_x``, ``a_y`` (dimensionless), then the coefficients (metres) in :func:`parameter_names`' order.
    """

    model: str
    width_m: float
    height_m: float
    params: np.ndarray = field(default=None)

    def __post_init__(self):
        names = parameter_names(self.model)
        params = np.zeros(len(names)) if self.params is None else np.asarray(self.params, dtype=np.float64)
        if params.shape != (len(names),):
            raise ValueError(f"a {self.model} screen has {len(names)} parameters, got {params.shape}")
        if not np.all(np.isfinite(params)):
            raise ValueError("screen shape parameters must be finite")
        if not (self.width_m > 0 and self.height_m > 0):
            raise ValueError(f"screen extents must be positive metres, got {self.width_m} x {self.height_m}")
        params = params.copy()
        params.setflags(write=False)
        object.__setattr__(self, "params", params)

    @property
    def names(self) -> list[str]:
        return parameter_names(self.model)

    @property
    def pitch_scale(self) -> tuple[float, float]:
        """The true pitch over the stated one, along x and y: (1 + a_x, 1 + a_y)."""
        return 1.0 + float(self.params[0]), 1.0 + float(self.params[1])

    def with_params(self, params: np.ndarray) -> "ScreenShape":
        return ScreenShape(self.model, self.width_m, self.height_m, params)

    def normalised(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(xi, eta) of display positions (stated metres)."""
        hw, hh = 0.5 * self.width_m, 0.5 * self.height_m
        return (np.asarray(u_x_m, dtype=np.float64) - hw) / hw, (np.asarray(u_y_m, dtype=np.float64) - hh) / hh

    def basis(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model is linear in its parameters: ``points = base + design @ params``.

        Returns
        -------
        base : (N, 3) array
            The stated flat screen's points, metres.
        design : (N, 3, n) array
            d(point)/d(parameter).
        """
        xi, eta = self.normalised(u_x_m, u_y_m)
        xi, eta = np.ravel(xi), np.ravel(eta)
        hw, hh = 0.5 * self.width_m, 0.5 * self.height_m
        base = np.stack([hw * xi, hh * eta, np.zeros_like(xi)], axis=-1)
        tx, ty, tz = model_terms(self.model)
        design = np.zeros((xi.size, 3, 2 + len(tx) + len(ty) + len(tz)))
        design[:, 0, 0] = hw * xi
        design[:, 1, 1] = hh * eta
        k = 2
        for axis, terms in ((0, tx), (1, ty), (2, tz)):
            for t in terms:
                design[:, axis, k] = _TERMS[t](xi, eta)
                k += 1
        return base, design

    def points(self, u_x_m: np.ndarray, u_y_m: np.ndarray) -> np.ndarray:
        """Screen-frame points (N, 3), metres, of display positions (stated metres from left and bottom)."""
        base, design = self.basis(u_x_m, u_y_m)
        return base + design @ self.params

    def height_summary(self, n: int = 41) -> dict:
        """The out-of-plane shape in two numbers, metres: ``sag``, the centre's height above the mean of the
        active area's border, and ``twist``, the coefficient of xi eta (the corners' turn out of the plane);
        ``peak_to_valley`` of z over the active area."""
        u = np.linspace(0.0, self.width_m, n)
        v = np.linspace(0.0, self.height_m, n)
        gu, gv = np.meshgrid(u, v)
        z = self.points(gu.ravel(), gv.ravel())[:, 2].reshape(gu.shape)
        border = np.concatenate([z[0], z[-1], z[1:-1, 0], z[1:-1, -1]])
        twist = 0.0
        if "z:1,1" in self.names:
            twist = float(self.params[self.names.index("z:1,1")])
        return {"sag_m": float(-border.mean()), "twist_m": twist, "peak_to_valley_m": float(np.ptp(z))}

    def grid(self, nodes_x: int = 65, nodes_y: int = 37) -> tuple[np.ndarray, np.ndarray]:
        """Nodes covering the whole active area: positions (M, 2), stated metres, and points (M, 3)."""
        u = np.linspace(0.0, self.width_m, int(nodes_x))
        v = np.linspace(0.0, self.height_m, int(nodes_y))
        gu, gv = np.meshgrid(u, v)
        uv = np.column_stack([gu.ravel(), gv.ravel()])
        return uv, self.points(uv[:, 0], uv[:, 1])

    def to_dict(self) -> dict:
        return {"model": self.model, "width_m": self.width_m, "height_m": self.height_m,
                "names": self.names, "params": [float(v) for v in self.params]}

    @classmethod
    def from_dict(cls, d: dict) -> "ScreenShape":
        shape = cls(str(d["model"]), float(d["width_m"]), float(d["height_m"]), np.asarray(d["params"], float))
        if list(d.get("names", shape.names)) != shape.names:
            raise ValueError(f"screen shape parameters are named {d.get('names')}, expected {shape.names}")
        return shape


def shape_modes(shape: ScreenShape, covariance: np.ndarray, nodes_uv: np.ndarray, max_modes: int = 4,
                keep: float = 0.99) -> tuple[np.ndarray, np.ndarray]:
    """The shape's uncertainty as independent displacement fields of the grid nodes.

    The covariance of the shape coefficients (without the pitch terms a_x, a_y, which the budget carries
    as the pitch) is split into its principal directions; each, at one standard deviation, moves every
    node by a field. The strongest *max_modes* fields that together carry *keep* of the displacement
    variance (summed over the nodes) are returned.

    Parameters
    ----------
    shape : ScreenShape
    covariance : (n, n) array
        Covariance of all of *shape*'s parameters (a_x, a_y first).
    nodes_uv : (M, 2) array
        Node positions, stated metres.

    Returns
    -------
    modes : (K, M, 3) array
        Node displacements of each mode at one standard deviation, metres.
    node_std : (M, 3) array
        Standard deviation of every node's x, y, z from all coefficients but the pitch, metres.
    """
    cov = np.asarray(covariance, dtype=np.float64)[2:, 2:]
    _, design = shape.basis(nodes_uv[:, 0], nodes_uv[:, 1])
    design = design[:, :, 2:]
    m = nodes_uv.shape[0]
    if cov.size == 0:
        return np.zeros((0, m, 3)), np.zeros((m, 3))
    # node covariance's principal fields: B C B^T = (B L)(B L)^T with C = L L^T (eigen form, semidefinite)
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.clip(w, 0.0, None)
    factor = v * np.sqrt(w)                                  # (n, n): C = factor factor^T
    fields = np.einsum("mdn,nk->kmd", design, factor)        # (n, M, 3)
    node_std = np.sqrt(np.einsum("kmd,kmd->md", fields, fields))
    # the fields of B L are not orthogonal over the nodes; their own principal components are
    flat = fields.reshape(fields.shape[0], -1)
    u, s, vt = np.linalg.svd(flat, full_matrices=False)
    energy = s ** 2
    total = energy.sum()
    if total <= 0:
        return np.zeros((0, m, 3)), node_std
    count = int(np.searchsorted(np.cumsum(energy) / total, keep) + 1)
    count = min(count, int(max_modes), s.size)
    modes = (s[:count, None] * vt[:count]).reshape(count, m, 3)
    return modes, node_std
