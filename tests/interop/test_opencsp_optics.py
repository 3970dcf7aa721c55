"""The optical figures of OpenCSP's real NSTTF facet (fixtures/opencsp), against OpenCSP's own ray trace.

OpenCSP's standard facet output (its example ``example_single_facet`` and ``test_StandardPlotOutput``)
traces this measurement with a top-hat sun of 9.308 mrad diameter straight down the facet's axis onto a
target 100 m away, normal to the axis, and plots the *ensquared energy*: the share of the reflected power
inside a square of a given semi-width about the target centre. Its reference plot
(``opencsp/common/lib/csp/test/data/input/StandardPlotOutput/facet/Ensquared_Energy_xy.png``) reads, for
the measured facet, about 0.23 at 0.2 m, 0.50 at 0.3 m, 0.73 at 0.4 m, 0.91 at 0.5 m, 0.96 at 0.6 m and
0.99 at 0.8 m, and for the ideal 100 m paraboloid about 0.52 at 0.3 m and 1.0 from 0.43 m. Our intercept
factor for a square aperture of that semi-width is the same quantity; OpenCSP's values are read from its
plot (about +-0.02) and its measured slopes come from its own reduction, so agreement within 0.05 is what
one can expect.
"""

from __future__ import annotations

import dataclasses

import pytest

from sofast_station.interop.opencsp import opencsp_test_data_paths, read_opencsp
from sofast_station.optics import Aperture, OpticsSettings
from sofast_station.result.optical_figures import DesignTraces, analysis_optics

OPENCSP_MEASURED = {0.2: 0.23, 0.3: 0.50, 0.4: 0.73, 0.5: 0.91, 0.6: 0.96, 0.8: 0.99}
OPENCSP_REFERENCE = {0.3: 0.52, 0.5: 1.0}


@pytest.fixture(scope="module")
def analysis(repo_root):
    m = read_opencsp(**opencsp_test_data_paths(repo_root / "fixtures/opencsp/test_data"), focal_length_m=100.0)
    return m, m.analyse(robust=True)


def test_ensquared_energy_agrees_with_opencsps_ray_trace(analysis):
    m, a = analysis
    base = OpticsSettings(design_points=40_000)
    for semi_width, expected in OPENCSP_MEASURED.items():
        settings = dataclasses.replace(base, aperture=Aperture("rectangle", width_m=2 * semi_width,
                                                               height_m=2 * semi_width))
        res = analysis_optics(a, m.design, settings)
        assert res.figures["intercept"] == pytest.approx(expected, abs=0.05), semi_width
        if semi_width in OPENCSP_REFERENCE:
            assert res.figures["design"]["intercept"] == pytest.approx(OPENCSP_REFERENCE[semi_width], abs=0.03)


def test_opencsp_facet_intercept_and_spot_size_are_reported(analysis):
    """The station's default figures for this facet: the 90 % radius of its beam at 100 m against the ideal
    facet's sun image (100 m x 4.65 mrad x sqrt(0.9) = 0.441 m), and the intercept of a 0.5 m circle."""
    m, a = analysis
    res = analysis_optics(a, m.design, OpticsSettings(aperture=Aperture("circle", radius_m=0.5), design_points=40_000),
                          DesignTraces())
    f = res.figures
    assert f["design"]["spot_radius_m"] == pytest.approx(0.441, rel=0.01)
    assert 0.46 < f["spot_radius_m"] < 0.56           # wider than the sun's image: the facet's slope errors
    assert 0.85 < f["intercept"] < 0.95 and f["design"]["intercept"] == 1.0
    assert f["centroid_offset_mrad"]["magnitude"] < 0.3
