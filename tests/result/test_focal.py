"""A nearly flat facet's focal length: its exact interval from the focal power's U, and where it is written.

The truth here is computed by the test itself (f = 1 / kappa of a drawn facet), never by the code under test.
"""

from __future__ import annotations

import numpy as np

from sofast_station.result.focal import LINEAR_FRACTION, focal_length_interval, is_linear
from sofast_station.result.formatting import figure_parts, figure_text
from sofast_station.result.record import RecordHead, build_record
from sofast_station.station import console


def _inside(f_true: float, interval: list) -> bool:
    """Whether *f_true* lies in *interval*, written out here from its definition (lo <= hi: between them;
    lo > 0 > hi or an end None: through infinity)."""
    lo, hi = interval
    if lo is not None and hi is not None and lo <= hi:
        return lo <= f_true <= hi
    return (lo is not None and f_true >= lo) or (hi is not None and f_true <= hi)


def test_the_interval_holds_the_true_focal_length_exactly_when_the_focal_power_is_within_its_u():
    """2000 drawn facets from f 5 m to flat (and convex), each measured with a drawn U: the true f inside the
    interval on exactly the captures whose true kappa is within kappa's U, so f covers as kappa covers (a claim
    of 95 % shows 93.8-96.2 % on 2000 with probability 0.99; the drawn errors are Gaussian with sigma U / 2)."""
    rng = np.random.default_rng(47)
    n, agree, covered, through_infinity = 2000, 0, 0, 0
    for _ in range(n):
        f_true = rng.choice([-1.0, 1.0], p=[0.1, 0.9]) * 10 ** rng.uniform(0.7, 3.5)     # 5 m to 3 km
        kappa_true = 1.0 / f_true
        u = abs(kappa_true) * 10 ** rng.uniform(-3, 0.5)          # a U of 0.1 % to 3 times the power
        kappa = kappa_true + rng.normal(0.0, u / 2)
        interval = focal_length_interval(kappa, u)
        within = abs(kappa - kappa_true) <= u
        agree += _inside(f_true, interval) == within
        covered += within
        through_infinity += interval[0] is None or interval[1] is None or interval[0] > interval[1]
    assert agree == n
    assert 0.938 <= covered / n <= 0.962
    assert through_infinity > 100                                 # the flat-within-U case was drawn often


def _record(kappa_x: float, u_x: float, kappa_y: float, u_y: float) -> dict:
    head = RecordHead(serial="F-1", time="2026-12-06T12:00:00+00:00", station="flat", config_hash="0",
                      calibration={}, camera={})
    figures = {"focal_length_x_m": 1 / kappa_x, "focal_length_y_m": 1 / kappa_y,
               "focal_length_x_m_U": u_x / kappa_x ** 2, "focal_length_y_m_U": u_y / kappa_y ** 2,
               "curvature_x_per_m": kappa_x, "curvature_y_per_m": kappa_y,
               "curvature_x_per_m_U": u_x, "curvature_y_per_m_U": u_y,
               "twist_mrad_per_m": 0.0, "twist_e1_mrad_per_m": 0.0, "twist_e2_mrad_per_m": 0.0,
               "principal_focal_lengths_m": [1 / kappa_x, 1 / kappa_y], "axis_angle_rad": 0.0,
               "slope_rms_mrad": {"design": {"x": 0.3, "y": 0.3, "magnitude": 0.42}}, "n_points": 1000,
               "boresight_mrad": {"x": 0.0, "y": 0.0}, "optical_tilt_mrad": {"x": 0.0, "y": 0.0}}
    return build_record(head, figures=figures, verdict={"verdict": "pass", "reasons": []})


def test_f_is_written_with_its_u_where_linear_and_as_its_interval_where_not():
    """The simulated flat station's capture (kappa x 0.00196 +- 0.00045 /m: 510 +- 120 m by the linear U)
    reads 415 to 662 m; y flat within its U; a dish's f (U a thousandth of kappa) keeps value +- U."""
    rec = _record(0.001956, 0.00045, 0.0002, 0.00045)
    lo, hi = rec["focal_length_x_m_interval"]
    assert abs(lo - 1 / 0.002406) < 1e-9 and abs(hi - 1 / 0.001506) < 1e-9
    assert not is_linear(0.001956, 0.00045)
    assert figure_text(rec, "focal_length_x_m", " m") == "416 to 664 m"
    assert figure_text(rec, "focal_length_y_m", " m") == ">= 1538 or <= -4000 m (flat within U)"
    assert figure_parts(rec, "focal_length_x_m") == ("416..664", None)
    dish = _record(1 / 5.4183, 7e-5, 1 / 5.35, 7e-5)              # U(f) = 7e-5 * f^2 = 0.0021 m
    assert figure_text(dish, "focal_length_x_m", " m") == "5.4183 ± 0.0021 m"
    edge = 1 / 600
    assert is_linear(edge, LINEAR_FRACTION * edge) and not is_linear(edge, 1.01 * LINEAR_FRACTION * edge)
    # the console's line keeps its columns with an interval in the f cells
    line, head = console.facet_line(rec, "pass", 1.0, n=1, total=20), console.header(total=20)
    assert line.index("PASS") == head.index("verdict") and "416..664" in line
    c_end = head.index("cycle") + len("cycle")
    assert line[c_end - 1] == "s", (head, line)
