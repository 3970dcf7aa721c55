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
    for w in ("R1C1\n0.224 ± 0.050 mrad\nleave it", "R1C2\nmissing", "R2C1\n1.552 ± 0.051 mrad\nOVER: ADJUST",
              "largest 1.550 mrad", "seen from behind"):
        assert w in words, w
    path = save_facet_map(record(), ENSEMBLE, tmp_path / "map.png", limit_mrad=1.0)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 20_000


def test_the_facet_map_is_seen_from_behind_and_shows_the_sheets_turns():
    """Issue 43: the map's arrows and signs agree with the sheet. Drawn from behind (the sheet's one
    viewpoint), the facets at +x (R1C2, R2C2) are on the left; each screw of a facet to adjust carries the
    sheet's turn for it, its curved arrow the way the sheet says (seen from behind), next to the screw's label
    where the screw is."""
    from sofast_station.report.canting import canting_instructions

    fig = draw_facet_map(record(), ENSEMBLE, limit_mrad=1.0, title="H-1")
    ax = fig.axes[0]
    at = {t.get_text().split("\n")[0]: t.get_position() for t in ax.texts}
    assert at["R2C2"][0] < 0 < at["R2C1"][0] and at["R1C2"][0] < 0 < at["R1C1"][0]
    assert at["R1C1"][1] > 0 > at["R2C1"][1]
    ins = {f["label"]: f for f in canting_instructions(record(), ENSEMBLE, 1.0)["facets"]}
    glyph = {"clockwise": "\u21bb", "counterclockwise": "\u21ba"}
    drawn = [t for t in ax.texts if t.get_text()[:1] in glyph.values() or t.get_text() == "leave"]
    expected = [("leave" if s["direction"] == "leave"
                 else f"{glyph[s['direction']]} {s['turns_text'].split(' turn')[0]}")
                for f in ins.values() if f["action"] == "turn" for s in f["screws"]]
    assert sorted(t.get_text() for t in drawn) == sorted(expected) and len(expected) == 6      # R2C1, R2C2
    # each turn is drawn beside its own screw's label: R2C1's screws A, B, C, from behind (x mirrored)
    labels = [t for t in ax.texts if t.get_text() in ("A", "B", "C")]
    r2c1 = ENSEMBLE.facets[2]
    for s in ins["R2C1"]["screws"]:
        point = ENSEMBLE.adjusters.points_m[ENSEMBLE.adjusters.names.index(s["name"])]
        where = np.array([-(r2c1.position_m[0] + point[0]), r2c1.position_m[1] + point[1]])
        assert [t for t in labels if t.get_text() == s["name"] and np.allclose(t.get_position(), where, atol=0.02)]
        said = min(drawn, key=lambda t: np.hypot(*(np.array(t.get_position()) - where)))
        assert said.get_text().startswith("leave" if s["direction"] == "leave" else glyph[s["direction"]]), s


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
