"""Issue 30, item 4: a heliostat's flux, intercept and spot from its facets' measured surfaces, beside the
design's and beside the same with the canting errors corrected.

The "measured" surfaces here are the design surfaces themselves (design_samples), placed on the frame by
rotations built with scipy, some turned by a known canting error: a facet turned by d mrad sends its beam
2 d mrad away (the law of reflection), the heliostat's figures follow, and correcting the canting gives the
design's figures back.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sofast_station.ensemble import load_ensemble
from sofast_station.optics import Aperture, OpticsSettings, design_samples
from sofast_station.optics.heliostat import FacetSurface, heliostat_optics
from tests.conftest import ROOT

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")
SETTINGS = OpticsSettings(aperture=Aperture("circle", radius_m=0.5), min_rays=60_000, grid_cells=81)


def turn(rx_mrad, ry_mrad):
    return Rotation.from_euler("YX", [1e-3 * ry_mrad, 1e-3 * rx_mrad]).as_matrix()


def surfaces(turns: dict, u=None) -> list[FacetSurface]:
    out = []
    for f in ENSEMBLE.facets:
        pts, slopes, _ = design_samples(f.design, 15_000)
        r = f.rotation @ turn(*turns.get(f.label, (0.0, 0.0)))
        out.append(FacetSurface(f.label, pts, slopes, np.array([0.0, 0.0, 4.0]), 0.36, r, f.position_m, f.rotation,
                                None if u is None else np.array(u)))
    return out


def test_a_perfect_heliostat_measures_as_its_design():
    o = heliostat_optics(surfaces({}), ENSEMBLE, SETTINGS).figures
    for name in ("measured", "corrected"):
        assert o[name]["intercept"] == pytest.approx(o["design"]["intercept"], abs=0.003)
        assert o[name]["spot_radius_mrad"] == pytest.approx(o["design"]["spot_radius_mrad"], rel=0.01)
    # on-axis canting at the slant range: the sun's image, 4.65 mrad x sqrt(0.9) for 90 %, from every facet
    assert o["design"]["spot_radius_mrad"] == pytest.approx(4.65 * np.sqrt(0.9), rel=0.02)
    assert o["recanting_gain"]["intercept"] == pytest.approx(0.0, abs=1e-12)


def test_a_canted_facet_sends_its_beam_twice_its_error_away_and_recanting_brings_it_back():
    o = heliostat_optics(surfaces({"R1C2": (0.0, 3.0), "R2C1": (-2.0, 0.0)}), ENSEMBLE, SETTINGS).figures
    m = o["measured"]["facet_centroids_mrad"]
    # turned +3 mrad about its y axis: its normal leans +x, its beam 6 mrad towards +x on the target
    assert m["R1C2"]["x"] == pytest.approx(6.0, abs=0.05) and abs(m["R1C2"]["y"]) < 0.05
    # turned -2 mrad about x: its normal leans +y (R_x(a) e_z = (0, -sin a, cos a)), its beam 4 mrad towards +y
    assert m["R2C1"]["y"] == pytest.approx(4.0, abs=0.05) and abs(m["R2C1"]["x"]) < 0.05
    assert abs(m["R1C1"]["x"]) < 0.05 and abs(m["R2C2"]["y"]) < 0.05
    # the heliostat's beam is wider and loses power outside the 0.5 m aperture; re-canting recovers it
    assert o["measured"]["spot_radius_mrad"] > o["design"]["spot_radius_mrad"] + 0.5
    assert o["measured"]["intercept"] < o["design"]["intercept"] - 0.05
    assert o["corrected"]["intercept"] == pytest.approx(o["design"]["intercept"], abs=0.003)
    assert o["recanting_gain"]["intercept"] > 0.05


def test_the_cantings_u_spreads_the_measured_figures():
    """Each facet's beam moves by twice its canting (the law of reflection): a canting U of 0.4 mrad (k = 2)
    is a standard turn of 0.2 mrad per axis, the facet's beam 0.4 mrad; the centroid is the mean of the four
    facets' beams, weighted by the power they reflect (equal here: the turned facet's beam moves the
    centroid by 6 / 4 mrad), so it moves by 0.4 / sqrt(4) = 0.2 mrad per axis, and the magnitude of an
    offset along x (1.5 mrad, far beyond that spread) by its x part: U (k = 2) = 0.4 mrad. U is the standard
    deviation of ``u_draws`` draws (ddof 1), so U / 0.4 lies within sqrt(chi2(d) / d), d = draws - 1, at
    probability 0.999 (two-sided)."""
    from scipy.stats import chi2

    u = [0.4, 0.4]
    o = heliostat_optics(surfaces({"R1C2": (0.0, 3.0)}, u=u), ENSEMBLE, SETTINGS).figures
    m = o["measured"]
    d = m["u_draws"] - 1
    assert m["u_draws"] >= 10
    assert m["centroid_offset_mrad"]["x"] == pytest.approx(6.0 / 4, abs=0.05)      # equal weights
    expected = 2.0 * (2.0 * 0.5 * u[0]) / np.sqrt(4)
    low, high = (expected * np.sqrt(chi2.ppf(q, d) / d) for q in (0.0005, 0.9995))
    print(f"centroid U {m['centroid_offset_mrad_U']['magnitude']:.3f} mrad, expected {expected:.2f} "
          f"({low:.2f}-{high:.2f} for {m['u_draws']} draws)")
    assert low < m["centroid_offset_mrad_U"]["magnitude"] < high
    assert o["measured"]["spot_radius_mrad_U"] > 0.0
    none = heliostat_optics(surfaces({"R1C2": (0.0, 3.0)}, u=[0.0, 0.0]), ENSEMBLE, SETTINGS).figures
    assert none["measured"]["spot_radius_mrad_U"] == 0.0


def test_the_same_surfaces_give_the_same_bits():
    a = heliostat_optics(surfaces({"R1C1": (1.0, 1.0)}), ENSEMBLE, SETTINGS)
    b = heliostat_optics(surfaces({"R1C1": (1.0, 1.0)}), ENSEMBLE, SETTINGS)
    assert a.figures == b.figures
    assert all(np.array_equal(a.flux_w_m2[k], b.flux_w_m2[k]) for k in a.flux_w_m2)
