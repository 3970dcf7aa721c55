"""The canting a heliostat's place asks for: on axis it is the design file's own rule at the slant range
(ensemble.py's, written independently), off axis each facet reflects the sun's central ray onto the aim
point (the law of reflection, traced here), and the heliostat files the command writes load as designs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sofast_station.cli import main
from sofast_station.ensemble import ensemble_from_dict, load_ensemble
from sofast_station.field.geometry import azimuth_elevation, direction, heliostat_rotation
from sofast_station.field.prescription import facet_normals, prescribed_ensemble
from sofast_station.field.sun import sun_direction

ROOT = Path(__file__).resolve().parents[2]
FACETS = ROOT / "fixtures" / "facets"


def test_on_axis_is_the_design_rule_at_the_slant_range():
    """A 5 x 5 at 120 m from the aim point: every facet's prescribed canting equals the heliostat file's
    on-axis rule with canting_focal_length_m = 120 m, to 1e-9 rad."""
    base = load_ensemble(FACETS / "heliostat_5x5.toml")
    position, aim = np.array([30.0, 110.0, 1.6]), np.array([0.0, 0.0, 45.0])
    slant = float(np.linalg.norm(aim - position))
    got = prescribed_ensemble(base, facet_normals(base, position, aim))
    rule = ensemble_from_dict({"facet": "heliostat_0m4_100m.toml", "canting_focal_length_m": slant,
                               "grid": {"rows": 5, "columns": 5, "pitch_m": [0.43, 0.43]}}, FACETS, "test")
    for a, b in zip(got.facets, rule.facets):
        assert np.allclose(a.rotation, b.rotation, atol=1e-9), a.label


def test_off_axis_facets_send_the_sun_onto_the_aim_point():
    """For the sun at 40 deg elevation in the south-east and a heliostat 100 m north-west of the tower: each
    facet's prescribed normal, with the heliostat tracking (its normal the bisector at its origin), mirrors the
    sun's ray at the facet's middle into a line through the aim point to 1e-9 rad."""
    base = load_ensemble(FACETS / "heliostat_5x5.toml")
    position, aim = np.array([-60.0, 80.0, 1.6]), np.array([0.0, 0.0, 45.0])
    sun = direction(math.radians(135.0), math.radians(40.0))
    normals = facet_normals(base, position, aim, sun)
    n_h = sun + (aim - position) / np.linalg.norm(aim - position)
    r_h = heliostat_rotation(*azimuth_elevation(n_h))
    for f in base.facets:
        middle = position + r_h @ f.point_m(f.design.centroid_m)
        n = r_h @ normals[f.label]
        out = 2 * (sun @ n) * n - sun
        to_aim = (aim - middle) / np.linalg.norm(aim - middle)
        assert np.linalg.norm(np.cross(out, to_aim)) < 1e-9 and out @ to_aim > 0, f.label


def test_the_command_writes_a_design_per_heliostat(tmp_path, capsys):
    (tmp_path / "layout.csv").write_text("Heliostat ID;X [m];Y [m];Z [m]\nA1;10;60;1.5\nA2;-40;120;1.5\n")
    (tmp_path / "site.toml").write_text(f"""[site]
latitude_deg = 37.1
longitude_deg = -2.36
layout = "layout.csv"
heliostat = "{(FACETS / 'heliostat_5x5.toml').as_posix()}"
aim_point_m = [0.0, 0.0, 45.0]
[camera]
position_m = [0.0, 0.0, 50.0]
width_px = 100
height_px = 100
matrix = [[1000.0, 0.0, 49.5], [0.0, 1000.0, 49.5], [0.0, 0.0, 1.0]]
""")
    assert main(["field", "prescription", "--site", str(tmp_path / "site.toml"), "--time",
                 "2027-06-21T11:00:00+02:00"]) == 0
    text = capsys.readouterr().out
    assert "A1" in text and "A2" in text
    design = load_ensemble(tmp_path / "prescriptions" / "A2.toml")
    assert design.n_facets == 25 and design.adjusters is not None
    sun = sun_direction("2027-06-21T11:00:00+02:00", 37.1, -2.36)
    normals = facet_normals(load_ensemble(FACETS / "heliostat_5x5.toml"), [-40.0, 120.0, 1.5], [0, 0, 45.0], sun)
    for f in design.facets:        # the file keeps the canting to its printed digits
        assert np.allclose(f.rotation[:, 2], normals[f.label], atol=1e-9)
