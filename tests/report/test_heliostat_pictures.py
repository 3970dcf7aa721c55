"""Issue 30, items 4 and 6: the heliostat's pictures (flux maps; the map of its facets) are drawn and written.

What they show is checked where it is computed (tests/optics/test_heliostat_optics.py,
tests/station/test_heliostat_accuracy.py); here: that they are drawn from real results, say what they must
(every facet named, a missing one marked, the values with their U), and are written whole.
"""

from __future__ import annotations

import numpy as np

from sofast_station.ensemble import load_ensemble
from sofast_station.optics import Aperture, OpticsSettings
from sofast_station.report.heliostat import draw_facet_map, save_facet_map, save_heliostat_flux
from tests.conftest import ROOT
from tests.optics.test_heliostat_optics import surfaces

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")


def texts(fig) -> str:
    return "\n".join(t.get_text() for ax in fig.axes for t in ax.texts + [ax.title]) + fig.get_suptitle()


def record():
    facets = [{"label": "R1C1", "status": "measured", "canting_mrad": {"x": 0.2, "y": -0.1},
               "canting_mrad_U": {"x": 0.05, "y": 0.05}},
              {"label": "R1C2", "status": "missing", "reason": "facet R1C2 is missing"},
              {"label": "R2C1", "status": "measured", "canting_mrad": {"x": -1.5, "y": 0.4},
               "canting_mrad_U": {"x": 0.05, "y": 0.06}},
              {"label": "R2C2", "status": "measured", "canting_mrad": {"x": 1.3, "y": -0.3},
               "canting_mrad_U": {"x": 0.05, "y": 0.05}}]
    return {"facets": facets, "heliostat": {"canting_rms_mrad": 1.2, "canting_max_mrad": 1.55,
                                            "canting_max_facet": "R2C1"}}


def test_the_facet_map_names_every_facet_with_its_canting_and_marks_the_missing(tmp_path):
    fig = draw_facet_map(record(), ENSEMBLE, limit_mrad=1.0, title="H-1")
    words = texts(fig)
    for w in ("R1C1", "x +0.200 ± 0.050", "R1C2\nmissing", "R2C1  OVER", "y +0.400 ± 0.060", "largest 1.550 mrad"):
        assert w in words, w
    path = save_facet_map(record(), ENSEMBLE, tmp_path / "map.png", limit_mrad=1.0)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000


def test_the_flux_maps_are_written_with_their_figures(tmp_path):
    from sofast_station.optics.heliostat import heliostat_optics
    from sofast_station.report.heliostat import draw_heliostat_flux

    settings = OpticsSettings(aperture=Aperture("circle", radius_m=0.5), min_rays=20_000, grid_cells=41)
    o = heliostat_optics(surfaces({"R1C2": (0.0, 3.0)}, u=[0.1, 0.1]), ENSEMBLE, settings)
    words = texts(draw_heliostat_flux(o, "H-1"))
    assert "as measured\nintercept" in words and "canting errors corrected" in words and " ± " in words
    path = save_heliostat_flux(o, tmp_path / "flux.png", "H-1")
    assert path.stat().st_size > 20_000
    assert np.isfinite(o.flux_w_m2["measured"]).all()
