"""Optical figures in the station: [optics] settings, inspect against the twin's truth, optical limits."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from sofast_station.config import load_config
from sofast_station.errors import ConfigError
from sofast_station.result.verdict import judge


@pytest.fixture(scope="module")
def inspections(tmp_path_factory):
    """Three inspections (three noisy captures) of the small simulated dish station, with an aperture near
    the spot's size; and the optical sensitivities the station kept."""
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import inspect
    from tests.conftest import ROOT, SMALL_STATION

    d = tmp_path_factory.mktemp("optics-station")
    path = d / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=d / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json")
                    + '\n[optics]\naperture = { shape = "circle", radius_m = 0.028 }\ndesign_points = 40000\n')
    config = dataclasses.replace(load_config(path), data_dir=d / "data")
    station = open_station(config, seed=5)
    try:
        records = [inspect(station, f"OPT-{k}") for k in (1, 2, 3)]
        return config, records, dict(station.design_traces.sensitivities)
    finally:
        station.close()


@pytest.fixture(scope="module")
def inspected(inspections):
    config, records, _ = inspections
    return config, records[0]


def test_inspection_reports_optical_figures_that_match_the_twins_truth(inspected):
    """The measured facet's trace agrees with the twin's own trace of its true surface (twin/sunlight.py, which
    shares nothing with optics/)."""
    _, rec = inspected
    opt, truth = rec["optics"], rec["truth"]["optics"]
    assert opt["conditions"]["aperture"] == {"shape": "circle", "radius_m": 0.028}
    assert opt["conditions"]["slant_range_m"] == pytest.approx(5.33)
    # The twin's facet (f 5.42 / 5.35 m, 0.5 mrad slope error) spills past a 28 mm aperture; the design does not.
    assert 0.7 < opt["intercept"] < 0.99 and opt["design"]["intercept"] == 1.0
    assert opt["intercept"] == pytest.approx(truth["intercept"], abs=0.02)
    assert opt["spot_radius_m"] == pytest.approx(truth["spot_radius_m"], rel=0.03)
    assert opt["power_ratio_vs_design"] == pytest.approx(truth["power_ratio_vs_design"], abs=0.02)
    assert abs(opt["centroid_offset_mrad"]["magnitude"] - truth["centroid_offset_mrad"]["magnitude"]) < 0.05
    assert opt["spot_radius_m"] > opt["design"]["spot_radius_m"]
    assert rec["timings_s"]["analysis_optics"] > 0


def test_optical_limits_judge_the_optical_figures(inspected):
    config, rec = inspected
    f = rec["optics"]
    ok = dataclasses.replace(config.limits, min_intercept=f["intercept"] - 0.01,
                             max_spot_radius_mrad=f["spot_radius_mrad"] + 0.1)
    strict = dataclasses.replace(config.limits, min_intercept=min(1.0, f["intercept"] + 0.01),
                                 max_centroid_offset_mrad=0.0, min_power_ratio=1.0)
    assert not [r for r in judge(rec, config.design, ok, config.quality)["reasons"] if "intercept" in r]
    reasons = judge(rec, config.design, strict, config.quality)["reasons"]
    assert any(r.startswith("intercept factor") and "minimum" in r for r in reasons)
    assert any(r.startswith("beam centroid offset") for r in reasons)
    assert any(r.startswith("intercepted power / design's") for r in reasons)


@pytest.mark.parametrize("table, message", [
    ('[optics]\nsunshape = "buie"\n', "unknown key(s) sunshape"),
    ('[optics]\nsun = "square"\n', "[optics] sun must be one of 'pillbox', 'gaussian', 'buie'"),
    ('[optics]\naperture = { shape = "circle", width_m = 1.0 }\n', "a circle aperture takes exactly shape, radius_m"),
    ('[optics]\nreflectivity = 1.5\n', "[optics] reflectivity must be a number above 0 and at most 1"),
    ('[optics]\nrays_per_pixel = "many"\n', "rays_per_pixel must be a number"),
    ('[optics]\nenabled = false\n[limits]\nmin_intercept = 0.9\n', "sets min_intercept but [optics] enabled = false"),
    ('[limits]\nmin_intercept = 1.5\n', "[limits] min_intercept must be a number of at least 0 and at most 1"),
    ('[recipes.a]\noptics = { sun = "buie", csr = 2.0 }\n', "[recipes.a.optics] csr must be"),
])
def test_optics_configuration_errors_name_the_file_section_and_key(small_station_toml, table, message):
    text = small_station_toml.read_text()
    small_station_toml.write_text(text + "\n" + table)
    with pytest.raises(ConfigError) as err:
        load_config(small_station_toml)
    assert message in str(err.value)
    assert str(small_station_toml) in str(err.value)


def test_recipe_overrides_the_aperture(small_station_toml):
    from sofast_station.recipes import recipes_from_config

    small_station_toml.write_text(small_station_toml.read_text() + '\n[optics]\nsun = "buie"\ncsr = 0.1\n'
                                  '\n[recipes.wide]\noptics = { aperture = { shape = "rectangle", width_m = 0.1, '
                                  'height_m = 0.08 } }\n')
    recipes = recipes_from_config(load_config(small_station_toml))
    assert recipes["default"].optics.aperture is None
    wide = recipes["wide"].optics
    assert (wide.aperture.shape, wide.aperture.width_m, wide.aperture.height_m) == ("rectangle", 0.1, 0.08)
    assert (wide.sun.kind, wide.sun.csr) == ("buie", 0.1)


def test_optical_figures_reach_the_journal_and_the_workbook_row(inspected, tmp_path):
    from sofast_station.archive import Journal
    from sofast_station.archive.workbook import flatten_record

    _, rec = inspected
    row = flatten_record("cycle-1", rec)
    assert row["optics.intercept"] == rec["optics"]["intercept"]
    assert row["optics.spot_radius_mrad"] == rec["optics"]["spot_radius_mrad"]
    assert row["optics.centroid_offset_mrad.magnitude"] == rec["optics"]["centroid_offset_mrad"]["magnitude"]
    assert row["optics.intercept_U"] == rec["optics"]["intercept_U"] > 0            # the U columns too
    assert row["optics.centroid_offset_mrad_U.x"] == rec["optics"]["centroid_offset_mrad_U"]["x"] > 0
    journal = Journal(tmp_path / "journal.sqlite3")
    try:
        journal.append("cycle-1", {k: v for k, v in rec.items() if k != "truth"})
        journaled = journal.get("cycle-1").record["optics"]
        assert journaled["power_ratio_vs_design"] == rec["optics"]["power_ratio_vs_design"]
    finally:
        journal.close()


def test_optical_figures_carry_an_uncertainty_that_covers_the_twins_truth(inspections):
    """Each noisy capture's optical figures lie within their stated U (k = 2) of the twin's own trace of its true
    surface (twin/sunlight.py: its own standard deviation, 1e-4 to 2e-4 of each figure, is a tenth of U or less),
    and U is not absurd: at most 10 x the figures' spread over the three captures plus their difference from
    truth, and within stated bounds."""
    _, records, sensitivities = inspections
    assert len(sensitivities) == 1          # computed on the first facet, kept for the next two
    errors = {"intercept": [], "spot_radius_m": []}
    for rec in records:
        opt, truth = rec["optics"], rec["truth"]["optics"]
        assert rec["coverage_factor"] == 2
        for key in ("intercept", "spot_radius_m", "power_ratio_vs_design"):
            u = opt[f"{key}_U"]
            assert math.isfinite(u) and u > 0, (key, u)
            assert 0 < opt[f"{key}_U_random"] <= u
            assert abs(opt[key] - truth[key]) <= u, (key, opt[key], truth[key], u)
        for axis in ("x", "y"):
            u = opt["centroid_offset_mrad_U"][axis]
            assert math.isfinite(u) and u > 0
            assert abs(opt["centroid_offset_mrad"][axis] - truth["centroid_offset_mrad"][axis]) <= u
        assert opt["spot_radius_mrad_U"] == pytest.approx(opt["spot_radius_m_U"] * 1000 / 5.33)
        for key in errors:
            errors[key].append(opt[key] - truth[key])
    for key in errors:
        values = [rec["optics"][key] for rec in records]
        observed = np.std(values, ddof=1) + np.max(np.abs(errors[key]))
        assert max(rec["optics"][f"{key}_U"] for rec in records) < 10 * observed, (key, observed)
    # Stated bounds: a 200,000-ray trace of this dish knows its intercept to better than 0.005 and its
    # 90 % spot radius (27.5 mm) to better than 1 %.
    assert all(rec["optics"]["intercept_U"] < 0.005 for rec in records)
    assert all(rec["optics"]["spot_radius_m_U"] < 0.01 * rec["optics"]["spot_radius_m"] for rec in records)
