"""Bundle adjustment: weighted least squares over blocks of parameters, with the covariance and the
residuals judged.

A problem is a list of parameter blocks (a camera pose, a screen shape, a scale...) and of residual groups,
each a function of some blocks returning its residuals and their derivatives with respect to those
blocks (analytic: the problems are projections of points through rigid motions, whose derivatives are
short formulas, and finite differences over a hundred parameters cost a hundred evaluations per step).
The solver, Levenberg-Marquardt on the normal equations (a few hundred parameters at most), also

* estimates the noise of every kind of observation from the residuals themselves (variance component
  estimation: each kind's standard deviation is rescaled until its normalised residuals have unit
  variance, the redundancy shared in proportion), so that a covariance does not rest on a guessed noise;
* drops observations beyond ``outlier_sigmas`` (a misdetected corner, a pixel at an occluding edge) and
  says how many;
* returns the parameters' covariance (Gauss-Newton, at the solution) and the singular values of the
  weighted Jacobian with its columns scaled to unit length: parameters the observations cannot tell apart
  are *not determined*, which the calling routine must refuse.

A pose block is a rigid motion, moved by small motions on the right: ``P <- P o M(omega, tau)``, omega a
rotation vector (radians) and tau a translation (metres) in the pose's own (source) frame. After each step
the pose absorbs the motion, so derivatives are taken at omega = tau = 0 and the final covariance is that
of small motions "about and along its own axes", as the uncertainty budget moves things.

Pure numpy/scipy; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..geometry import CameraIntrinsics, Pose


# -- rigid motions --------------------------------------------------------------------------------
def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices: (..., 3) -> (..., 3, 3) with ``skew(a) @ b = a x b``."""
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_from_vector(omega: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector *omega* (radians; Rodrigues' formula)."""
    omega = np.asarray(omega, dtype=np.float64)
    theta = float(np.linalg.norm(omega))
    k = skew(omega)
    if theta < 1e-12:
        return np.eye(3) + k + 0.5 * k @ k
    r = np.eye(3) + np.sin(theta) / theta * k + (1.0 - np.cos(theta)) / theta ** 2 * k @ k
    u, _, vt = np.linalg.svd(r)            # exactly orthonormal, whatever the rounding
    return u @ vt


def vector_from_rotation(r: np.ndarray) -> np.ndarray:
    """Rotation vector (radians) of the rotation matrix *r*."""
    r = np.asarray(r, dtype=np.float64)
    c = np.clip(0.5 * (np.trace(r) - 1.0), -1.0, 1.0)
    theta = float(np.arccos(c))
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if theta < 1e-8:
        return 0.5 * w
    return theta / (2.0 * np.sin(theta)) * w


def moved(pose: Pose, params: np.ndarray) -> Pose:
    """``pose o M(omega, tau)`` for ``params = (omega (rad), tau (m))``."""
    params = np.asarray(params, dtype=np.float64)
    return pose.compose(Pose(rotation_from_vector(params[:3]), params[3:6]))


def motion_between(start: Pose, end: Pose) -> np.ndarray:
    """The small-motion parameters (omega, tau) with ``end = start o M(omega, tau)``."""
    rel = start.inverse().compose(end)
    return np.concatenate([vector_from_rotation(rel.rotation), rel.translation])


def pose_derivative(pose: Pose, points: np.ndarray) -> np.ndarray:
    """d(pose.apply(points)) / d(omega, tau) at the right motion 0: (N, 3, 6)."""
    r = pose.rotation
    out = np.empty((points.shape[0], 3, 6))
    out[:, :, :3] = -np.einsum("ij,njk->nik", r, skew(points))
    out[:, :, 3:] = r
    return out


# -- cameras ---------------------------------------------------------------------------------------
def camera_vector(camera: CameraIntrinsics) -> np.ndarray:
    """(fx, fy, cx, cy, k1, k2, p1, p2, k3) of *camera*."""
    k = camera.matrix
    return np.concatenate([[k[0, 0], k[1, 1], k[0, 2], k[1, 2]], camera.distortion])


def camera_from_vector(c: np.ndarray, width_px: int, height_px: int) -> CameraIntrinsics:
    return CameraIntrinsics(width_px, height_px, [[c[0], 0.0, c[2]], [0.0, c[1], c[3]], [0.0, 0.0, 1.0]], c[4:9])


def project(camera: np.ndarray, points_cam: np.ndarray, derivatives: bool = False):
    """Image positions (N, 2), pixels, of camera-frame points (N, 3): OpenCV's pinhole and 5-term model,
    *camera* a :func:`camera_vector`.

    With *derivatives*, also d(pixel)/d(point) (N, 2, 3) and d(pixel)/d(camera) (N, 2, 9).
    """
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = (float(v) for v in camera)
    p = np.asarray(points_cam, dtype=np.float64)
    iz = 1.0 / p[:, 2]
    x, y = p[:, 0] * iz, p[:, 1] * iz
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    pix = np.column_stack([fx * xd + cx, fy * yd + cy])
    if not derivatives:
        return pix
    n = p.shape[0]
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)          # d(radial)/d(r2)
    dxd_dx = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    dxd_dy = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dx = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    dyd_dy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    # (x, y) = (X/Z, Y/Z)
    d_pt = np.zeros((n, 2, 3))
    d_pt[:, 0, 0] = fx * dxd_dx * iz
    d_pt[:, 0, 1] = fx * dxd_dy * iz
    d_pt[:, 0, 2] = -fx * (dxd_dx * x + dxd_dy * y) * iz
    d_pt[:, 1, 0] = fy * dyd_dx * iz
    d_pt[:, 1, 1] = fy * dyd_dy * iz
    d_pt[:, 1, 2] = -fy * (dyd_dx * x + dyd_dy * y) * iz
    d_cam = np.zeros((n, 2, 9))
    d_cam[:, 0, 0] = xd
    d_cam[:, 1, 1] = yd
    d_cam[:, 0, 2] = 1.0
    d_cam[:, 1, 3] = 1.0
    d_cam[:, 0, 4], d_cam[:, 1, 4] = fx * x * r2, fy * y * r2
    d_cam[:, 0, 5], d_cam[:, 1, 5] = fx * x * r2 * r2, fy * y * r2 * r2
    d_cam[:, 0, 6], d_cam[:, 1, 6] = fx * 2.0 * x * y, fy * (r2 + 2.0 * y * y)
    d_cam[:, 0, 7], d_cam[:, 1, 7] = fx * (r2 + 2.0 * x * x), fy * 2.0 * x * y
    d_cam[:, 0, 8], d_cam[:, 1, 8] = fx * x * r2 ** 3, fy * y * r2 ** 3
    return pix, d_pt, d_cam


def reflect(points: np.ndarray, plane_point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Mirror images (N, 3) of *points* in the plane through *plane_point* with unit *normal*."""
    n = np.asarray(normal, dtype=np.float64)
    d = (np.asarray(points) - plane_point) @ n
    return points - 2.0 * d[:, None] * n


# -- the least-squares problem ---------------------------------------------------------------------
@dataclass
class Block:
    """A block of parameters.

    Attributes
    ----------
    name : str
    x0 : (n,) array or Pose
        Starting values; a :class:`~sofast_station.geometry.Pose` makes a pose block (6 parameters: the
        small motion on its right).
    prior : (n,) array, optional
        Known values of the parameters (a calibrated camera, a certified scale) ...
    prior_std : (n,) array, optional
        ... and their standard deviations: pseudo-observations ``(x - prior) / prior_std``; a zero or
        infinite entry means no prior for that parameter.
    fixed : bool
        Held at *x0* (not estimated).
    names : list of str, optional
        One name per parameter (for messages).
    """

    name: str
    x0: object
    prior: np.ndarray | None = None
    prior_std: np.ndarray | None = None
    fixed: bool = False
    names: list | None = None

    def __post_init__(self):
        self.is_pose = isinstance(self.x0, Pose)
        if not self.is_pose:
            self.x0 = np.asarray(self.x0, dtype=np.float64).ravel()
        if self.names is None:
            self.names = ([f"{self.name} {a}" for a in ("rx", "ry", "rz", "tx", "ty", "tz")] if self.is_pose
                          else [f"{self.name}[{i}]" for i in range(self.size)])

    @property
    def size(self) -> int:
        return 6 if self.is_pose else self.x0.size


@dataclass
class Group:
    """A group of residuals of one kind.

    Attributes
    ----------
    kind : str
        What the observations are (their noise is estimated per kind), e.g. ``"screen corners"``.
    blocks : list of str
        The blocks the residuals depend on.
    function : callable
        ``function(values, derivatives) -> residuals`` or, with *derivatives* true,
        ``(residuals, {block name: (m, n_block) derivative})``: residuals in the observations' units
        (pixels, metres); ``values`` maps block names to their current values (a Pose for a pose block).
        A pose block's derivative is with respect to a small motion on its right.
    sigma : float or (m,) array
        Standard deviation of each observation, in the same units (the starting guess when the kind's
        noise is estimated).
    label : str
        Where the observations come from (a view, a placement), for the per-group summary.
    """

    kind: str
    blocks: list
    function: Callable
    sigma: float | np.ndarray
    label: str = ""


@dataclass
class Solution:
    """A solved problem.

    Attributes
    ----------
    values : dict
        Block name -> estimated parameters (a Pose for a pose block).
    covariance : dict
        Block name -> its covariance (free blocks); ``joint`` holds the full matrix over the free
        parameters in :attr:`order`.
    order : list of (str, slice)
        Where each free block sits in the joint covariance.
    sigma : dict
        Kind -> estimated standard deviation of one observation (units of the observations).
    rms : dict
        Kind -> RMS of the residuals (units of the observations).
    count, dropped : dict
        Kind -> observations used, and outliers left out.
    groups : list of dict
        Per group: label, kind, count, RMS (units of the observations).
    chi2 : float
        Sum of the squared normalised residuals, priors included, at the final noise estimates.
    dof : int
        Observations (priors included) minus free parameters.
    singular_values : (n,) array
        Of the weighted Jacobian with unit columns, largest first.
    undetermined : list of str
        Parameters the observations cannot determine (the weakest direction's largest components) when
        the Jacobian is rank-deficient; empty otherwise.
    iterations : int
    keep : list of bool arrays
        Per group, the observations used (outliers left out).
    scales : dict
        Per kind, the factor its groups' sigmas were scaled by.
    """

    values: dict
    covariance: dict
    order: list
    sigma: dict
    rms: dict
    count: dict
    dropped: dict
    groups: list
    chi2: float
    dof: int
    singular_values: np.ndarray
    undetermined: list = field(default_factory=list)
    iterations: int = 0
    keep: list = field(default_factory=list)
    scales: dict = field(default_factory=dict)
    names: list = field(default_factory=list)

    def std(self, name: str) -> np.ndarray:
        """Standard deviations of block *name*'s parameters."""
        return np.sqrt(np.clip(np.diag(self.covariance[name]), 0.0, None))


#: Relative size of the smallest scaled singular value below which the problem is rank-deficient.
RANK_TOLERANCE = 1e-8


class _Problem:
    def __init__(self, blocks, groups):
        self.blocks = blocks
        self.groups = groups
        self.by_name = {b.name: b for b in blocks}
        for g in groups:
            unknown = [name for name in g.blocks if name not in self.by_name]
            if unknown:
                raise ValueError(f"residual group {g.label or g.kind!r} depends on unknown block(s) {unknown}")
        self.free = [b for b in blocks if not b.fixed]
        if not self.free:
            raise ValueError("no free parameters")
        self.order, start = [], 0
        for b in self.free:
            self.order.append((b.name, slice(start, start + b.size)))
            start += b.size
        self.slices = dict(self.order)
        self.n = start
        self.names = [nm for b in self.free for nm in b.names]
        self.priors = []
        for b in self.free:
            if b.is_pose or b.prior is None or b.prior_std is None:
                continue
            ps = np.broadcast_to(np.asarray(b.prior_std, dtype=np.float64), b.x0.shape)
            use = np.isfinite(ps) & (ps > 0)
            if np.any(use):
                value = np.broadcast_to(np.asarray(b.prior, float), b.x0.shape)
                self.priors.append((b.name, np.flatnonzero(use), value[use], ps[use]))

    def initial(self) -> dict:
        return {b.name: b.x0 for b in self.blocks}

    def step(self, values: dict, delta: np.ndarray) -> dict:
        out = dict(values)
        for name, sl in self.order:
            out[name] = moved(values[name], delta[sl]) if self.by_name[name].is_pose else values[name] + delta[sl]
        return out

    def residuals(self, values):
        return [np.asarray(g.function(values, False), dtype=np.float64) for g in self.groups]

    def normal_equations(self, values, weights, keep):
        """Cost, gradient and Gauss-Newton matrix of the weighted problem at *values*."""
        h = np.zeros((self.n, self.n))
        grad = np.zeros(self.n)
        cost = 0.0
        for g, w, k in zip(self.groups, weights, keep):
            r, jac = g.function(values, True)
            r = np.asarray(r, dtype=np.float64)[k] * w[k]
            cost += float(r @ r)
            parts = [(self.slices[name], np.asarray(jac[name])[k] * w[k, None]) for name in g.blocks
                     if name in self.slices and name in jac]
            for sa, ja in parts:
                grad[sa] += ja.T @ r
                for sb, jb in parts:
                    h[sa, sb] += ja.T @ jb
        for name, idx, value, std in self.priors:
            x = values[name][idx]
            r = (x - value) / std
            cost += float(r @ r)
            cols = self.slices[name].start + idx
            grad[cols] += r / std
            h[cols, cols] += 1.0 / std ** 2
        return cost, grad, h


def _levenberg_marquardt(problem, values, weights, keep, max_iterations=100):
    cost, grad, h = problem.normal_equations(values, weights, keep)
    lam = 1e-6
    it = 0
    for it in range(1, max_iterations + 1):
        d = np.sqrt(np.clip(np.diag(h), 1e-300, None))
        hs = h / np.outer(d, d)
        gs = grad / d
        while True:
            try:
                step = -np.linalg.solve(hs + lam * np.eye(problem.n), gs) / d
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            trial = problem.step(values, step)
            t_cost, t_grad, t_h = problem.normal_equations(trial, weights, keep)
            if np.isfinite(t_cost) and t_cost <= cost:
                break
            lam *= 10.0
            if lam > 1e12:
                return values, cost, grad, h, it
        converged = (cost - t_cost) <= 1e-12 * max(cost, 1e-300) or np.max(np.abs(step * d)) < 1e-10
        values, cost, grad, h = trial, t_cost, t_grad, t_h
        lam = max(lam / 10.0, 1e-12)
        if converged:
            break
    return values, cost, grad, h, it


def solve(blocks: list[Block], groups: list[Group], *, estimate_noise: bool = True, outlier_sigmas: float = 5.0,
          rounds: int = 4, scales: dict | None = None, keep: list | None = None,
          known_noise: tuple = ()) -> Solution:
    """Solve the problem (module docstring).

    Parameters
    ----------
    blocks, groups
        The parameters and the observations.
    estimate_noise : bool
        Estimate each kind's noise from its residuals (and rescale its weights), up to *rounds* rounds;
        otherwise the groups' sigmas (times *scales*) are taken as they are.
    outlier_sigmas : float
        Observations whose residual exceeds this many of their kind's standard deviations are left out
        after the first round (0: keep everything).
    scales, keep : optional
        A :class:`Solution`'s noise scales and kept observations to start from (with
        ``estimate_noise=False, outlier_sigmas=0``: judge a model on another's observations and noise).
    known_noise : tuple of str
        Kinds whose sigmas are known (an instrument's stated accuracy) and not estimated: too few of them
        to estimate, or what they are is the point.

    Raises
    ------
    ValueError
        If there are no free parameters or fewer observations than parameters.
    """
    problem = _Problem(blocks, groups)
    values = problem.initial()
    raw0 = problem.residuals(values)
    sigmas = [np.broadcast_to(np.asarray(g.sigma, dtype=np.float64), r.shape) for g, r in zip(groups, raw0)]
    kinds = sorted({g.kind for g in groups})
    scale = {k: float((scales or {}).get(k, 1.0)) for k in kinds}
    keep = [np.ones(r.shape, dtype=bool) for r in raw0] if keep is None else [np.asarray(k, bool).copy() for k in keep]
    n_prior = sum(p[1].size for p in problem.priors)
    iterations = 0
    for round_ in range(max(1, int(rounds))):
        m = sum(int(k.sum()) for k in keep) + n_prior
        if m < problem.n:
            raise ValueError(f"{m} observations cannot determine {problem.n} parameters")
        weights = [1.0 / (s * scale[g.kind]) for g, s in zip(groups, sigmas)]
        values, cost, grad, h, it = _levenberg_marquardt(problem, values, weights, keep)
        iterations += it
        if not estimate_noise and outlier_sigmas <= 0:
            break
        raw = [r / s for r, s in zip(problem.residuals(values), sigmas)]
        redundancy = max(m - problem.n, 1) / m
        changed = False
        if estimate_noise:
            for kind in kinds:
                if kind in known_noise:
                    continue
                sq = sum(float(np.sum(r[k] ** 2)) for g, r, k in zip(groups, raw, keep) if g.kind == kind)
                cnt = sum(int(k.sum()) for g, k in zip(groups, keep) if g.kind == kind)
                if cnt and sq > 0:
                    new = float(np.sqrt(sq / (cnt * redundancy)))
                    changed |= abs(new / scale[kind] - 1.0) > 1e-3
                    scale[kind] = new
        if outlier_sigmas > 0:
            for i, (g, r) in enumerate(zip(groups, raw)):
                k = np.abs(r) <= outlier_sigmas * scale[g.kind]
                changed |= bool(np.any(k != keep[i]))
                keep[i] = k
        if not changed:
            break
    weights = [1.0 / (s * scale[g.kind]) for g, s in zip(groups, sigmas)]
    values, cost, grad, h, it = _levenberg_marquardt(problem, values, weights, keep)
    iterations += it
    # covariance and determinedness, on the columns scaled to unit length
    d = np.sqrt(np.clip(np.diag(h), 0.0, None))
    d_safe = np.where(d > 0, d, 1.0)
    hs = h / np.outer(d_safe, d_safe)
    w, v = np.linalg.eigh(0.5 * (hs + hs.T))
    w = np.clip(w[::-1], 0.0, None)
    v = v[:, ::-1]
    sv = np.sqrt(w)
    undetermined = []
    if sv.size == 0 or sv[-1] <= RANK_TOLERANCE * sv[0] or np.any(d == 0):
        weakest = np.abs(v[:, -1])
        weakest = np.where(d == 0, np.inf, weakest)
        idx = np.argsort(-weakest)[:4]
        floor = 0.3 * np.max(weakest[np.isfinite(weakest)])
        undetermined = [problem.names[i] for i in idx if d[i] == 0 or weakest[i] > floor]
    inv = np.where(sv > RANK_TOLERANCE * (sv[0] if sv.size else 1.0), 1.0 / np.where(w > 0, w, 1.0), 0.0)
    joint = (v * inv) @ v.T / np.outer(d_safe, d_safe)
    covariance = {"joint": joint}
    for name, sl in problem.order:
        covariance[name] = joint[sl, sl]
    raw = problem.residuals(values)
    sigma, rms, count, dropped, per_group = {}, {}, {}, {}, []
    for kind in kinds:
        members = [(r, k, s) for g, r, k, s in zip(groups, raw, keep, sigmas) if g.kind == kind]
        used = np.concatenate([r[k] for r, k, _ in members])
        count[kind] = int(used.size)
        dropped[kind] = int(sum((~k).sum() for _, k, _ in members))
        rms[kind] = float(np.sqrt(np.mean(used ** 2))) if used.size else float("nan")
        sig = np.concatenate([s[k] for _, k, s in members])
        sigma[kind] = float(np.sqrt(np.mean(sig ** 2)) * scale[kind]) if sig.size else float("nan")
    for g, r, k in zip(groups, raw, keep):
        per_group.append({"label": g.label, "kind": g.kind, "count": int(k.sum()),
                          "rms": float(np.sqrt(np.mean(r[k] ** 2))) if k.any() else float("nan")})
    m = sum(int(k.sum()) for k in keep) + n_prior
    return Solution(values=values, covariance=covariance, order=problem.order, sigma=sigma, rms=rms, count=count,
                    dropped=dropped, groups=per_group, chi2=float(cost), dof=int(m - problem.n), singular_values=sv,
                    undetermined=undetermined, iterations=iterations, keep=keep, scales=dict(scale),
                    names=problem.names)


def nested_model_test(chi2_simple: float, chi2_rich: float, extra_params: int, dof_rich: int,
                      confidence: float = 0.99) -> dict:
    """Is the richer of two nested models needed? The F test on their residual sums of squares.

    Both sums must be normalised with the same noise (the richer model's estimate).

    Returns
    -------
    dict
        ``F``, the critical value at *confidence*, and ``needed`` (the simpler model leaves significantly
        more than noise).
    """
    # lazy: scipy.stats, ~1 s CPU; recipes.py loads this (via fixed.py) at every station start
    from scipy.stats import f as f_dist

    if extra_params <= 0 or dof_rich <= 0:
        return {"F": float("nan"), "critical": float("nan"), "needed": False}
    f_value = ((chi2_simple - chi2_rich) / extra_params) / (chi2_rich / dof_rich)
    critical = float(f_dist.ppf(confidence, extra_params, dof_rich))
    return {"F": float(f_value), "critical": critical, "needed": bool(f_value > critical)}
