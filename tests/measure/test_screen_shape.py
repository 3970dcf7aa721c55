"""Screen shape models: the frame they fix, their terms, the uncertainty fields they hand the budget."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.measure.screen_shape import MODELS, ScreenShape, parameter_names, shape_modes

W, H = 0.528, 0.297


@pytest.mark.parametrize("model", MODELS)
def test_no_parameter_moves_the_screen_frame(model):
    """Whatever the parameters, the display's centre is the origin, the normal there is +z and the centre
    row runs along +x (the frame is the model's, the poses carry the rest): else a pose and a shape would
    trade, and neither would be determined."""
    rng = np.random.default_rng(0)
    shape = ScreenShape(model, W, H, rng.normal(0, 1e-3, len(parameter_names(model))))
    c = shape.points(np.array([W / 2]), np.array([H / 2]))[0]
    assert np.allclose(c, 0.0, atol=1e-15)
    e = 1e-6
    dx = (shape.points(np.array([W / 2 + e]), np.array([H / 2])) - shape.points(np.array([W / 2 - e]),
                                                                                 np.array([H / 2])))[0] / (2 * e)
    dy = (shape.points(np.array([W / 2]), np.array([H / 2 + e])) - shape.points(np.array([W / 2]),
                                                                                 np.array([H / 2 - e])))[0] / (2 * e)
    assert abs(dx[2]) < 1e-9 and abs(dy[2]) < 1e-9            # the normal at the centre is z
    assert abs(dx[1]) < 1e-9                                  # the centre row along x


def test_the_pitch_terms_are_orthogonal_to_the_distortions():
    """a_x and a_y are the screen's mean scale: over the screen, every distortion term of x is orthogonal to
    xi and every one of y to eta (Legendre's polynomials where monomials would not be), so a pitch does not
    trade with a distortion (with monomials the distorted models' pitch was 2.4 times as uncertain)."""
    u, v = np.meshgrid(np.linspace(0, W, 201), np.linspace(0, H, 201))
    shape = ScreenShape("distorted3d", W, H)
    _, design = shape.basis(u.ravel(), v.ravel())
    for axis, scale_col in ((0, 0), (1, 1)):
        lin = design[:, axis, scale_col]
        for k in range(2, design.shape[2]):
            term = design[:, axis, k]
            if not np.any(term):
                continue
            corr = abs(lin @ term) / (np.linalg.norm(lin) * np.linalg.norm(term))
            assert corr < 0.05, (shape.names[k], corr)         # (xi^3 against xi: 0.92)


def test_a_pitch_scales_the_screen():
    shape = ScreenShape("flat", W, H, [0.01, -0.005])
    corner = shape.points(np.array([W]), np.array([H]))[0]
    assert np.allclose(corner, [0.5 * W * 1.01, 0.5 * H * 0.995, 0.0])
    assert shape.pitch_scale == pytest.approx((1.01, 0.995))


def test_a_bow_and_a_twist_are_summed_up():
    names = parameter_names("distorted3d")
    p = np.zeros(len(names))
    p[names.index("z:2,0")] = -1e-3               # z = -1 mm xi^2: the centre 1 mm in front of the sides
    p[names.index("z:1,1")] = 2e-4
    h = ScreenShape("distorted3d", W, H, p).height_summary(n=201)
    # the border's mean of -xi^2: the two sides (xi = +-1, all eta) and the top and bottom (mean of xi^2 = 1/3)
    assert h["sag_m"] == pytest.approx(1e-3 * (2 * 1 + 2 * (1 / 3)) / 4, rel=0.01)
    assert h["twist_m"] == 2e-4


def test_the_uncertainty_fields_carry_the_node_covariance():
    """The fields returned are the node covariance's principal components (less the pitch's): together
    they give every node's variance, here to 1 % (keep = 0.99 of the total), and their count is capped."""
    rng = np.random.default_rng(1)
    shape = ScreenShape("distorted3d", W, H)
    n = len(shape.names)
    a = rng.normal(0, 1e-5, (n, n))
    cov = a @ a.T
    uv, _ = shape.grid(9, 5)
    modes, node_std = shape_modes(shape, cov, uv, max_modes=40, keep=0.999999)
    _, design = shape.basis(uv[:, 0], uv[:, 1])
    exact = np.sqrt(np.einsum("mdi,ij,mdj->md", design[:, :, 2:], cov[2:, 2:], design[:, :, 2:]))
    assert np.allclose(node_std, exact, rtol=1e-9)
    assert np.allclose(np.sqrt(np.sum(modes ** 2, axis=0)), exact, rtol=1e-3, atol=1e-12)
    few, _ = shape_modes(shape, cov, uv, max_modes=3)
    assert few.shape[0] == 3


def test_a_record_from_another_model_layout_is_refused():
    d = ScreenShape("flat", W, H, [0.01, 0.0]).to_dict()
    d["names"] = ["a_x", "b"]
    with pytest.raises(ValueError, match="named"):
        ScreenShape.from_dict(d)
