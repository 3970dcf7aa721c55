"""The shape figures' Monte Carlo over the corner pose's draws (measure/uncertainty/shape_pose.py): its mean square
changes against the same draws applied by brute force, and when it runs."""

import numpy as np
import pytest

from sofast_station.measure.uncertainty.corner_pose import _rotations
from sofast_station.measure.uncertainty.shape_pose import PoseFields, beyond_linear, shape_monte_carlo


def _frames(rng, n, turn_mrad, shift_mm):
    w = 1e-3 * rng.normal(size=(n, 3)) * turn_mrad
    return {"rotation": _rotations(w), "translation": 1e-3 * rng.normal(size=(n, 3)) * shift_mm,
            "camera_z": rng.normal(size=(n, 9))}, w


def test_the_residual_fields_rms_is_recomputed_per_draw_and_the_figures_moved_to_second_order():
    """Synthetic fields (2 x 500 points, 15 parameters) and 400 draws: each draw's residual is r0 + sum_k d_k F_k
    with d the draw's turn (mrad), shift (mm) and the analysis's camera error (-z), its RMS taken directly with
    numpy; a figure moves by c . d + q . d^2. The Monte Carlo's mean square changes must equal the brute force's
    to rounding (1e-9 relative): its expansion of the mean square is exact, and the only approximation allowed
    is the rotation vector's, which is exact below pi."""
    rng = np.random.default_rng(5)
    m = 500
    r0 = {k: rng.normal(0.0, 0.05, (2, m)) + 0.02 for k in ("design", "parabola")}
    fields = {k: rng.normal(0.0, 0.004, (15, 2, m)) for k in r0}
    c, q = rng.normal(size=15), rng.normal(size=15) * 0.1
    pf = PoseFields(r0, fields, {("twist_mrad_per_m",): c}, {("twist_mrad_per_m",): q})
    frames, w = _frames(rng, 400, 10.0, 5.0)
    corners, w_c = _frames(rng, 400, 3.0, 1.0)
    frames["corners"] = corners
    out = shape_monte_carlo(pf, frames)

    def brute(fr, rot):
        d = np.column_stack([1e3 * rot, 1e3 * fr["translation"], -fr["camera_z"]])
        res = {}
        for k in r0:
            moved = r0[k][None] + np.einsum("dk,kam->dam", d, fields[k])
            for j, a in enumerate(("x", "y")):
                rms = np.sqrt(np.mean(moved[:, j] ** 2, axis=1))
                res[("slope_rms_mrad", k, a)] = np.mean((rms - np.sqrt(np.mean(r0[k][j] ** 2))) ** 2)
            mag = np.sqrt(np.mean(moved[:, 0] ** 2 + moved[:, 1] ** 2, axis=1))
            mag0 = np.sqrt(np.mean(r0[k][0] ** 2 + r0[k][1] ** 2))
            res[("slope_rms_mrad", k, "magnitude")] = np.mean((mag - mag0) ** 2)
        res[("twist_mrad_per_m",)] = np.mean((d @ c + (d * d) @ q) ** 2)
        return res

    full, alone = brute(frames, w), brute(corners, w_c)
    assert set(out) == set(full)
    for p in full:
        assert out[p][0] == pytest.approx(full[p], rel=1e-9, abs=1e-15), p
        assert out[p][1] == pytest.approx(alone[p], rel=1e-9, abs=1e-15), p
        assert out[p][1] < out[p][0], p                      # the corners alone move the frame less


def test_it_runs_only_where_the_draws_move_the_frame_beyond_the_fields_step():
    """The fields are taken at +-2 mrad and +-2 mm: draws of 1 mrad and 0.8 mm RMS (the shipped dish station's)
    stay within, 3 mrad (about y) or 3 mm (along any axis) do not; no draws, no Monte Carlo."""
    rng = np.random.default_rng(2)
    inside, _ = _frames(rng, 2000, 1.0, 0.8)
    assert not beyond_linear(inside)
    turned = dict(inside, rotation=_rotations(1e-3 * rng.normal(size=(2000, 3)) * [0.5, 3.0, 0.5]))
    shifted = dict(inside, translation=1e-3 * rng.normal(size=(2000, 3)) * [0.5, 0.5, 3.0])
    assert beyond_linear(turned) and beyond_linear(shifted)
    assert not beyond_linear({"rotation": None}) and shape_monte_carlo(None, inside) == {}
