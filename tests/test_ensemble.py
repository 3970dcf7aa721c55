"""Issue 30, item 1: the heliostat (facet ensemble) design file, the shipped 2x2 and 5x5 heliostats, and
OpenCSP's ensemble definition JSON.

The canting rule's angles are recomputed here from the paraboloid's normal with scipy's rotations (not the
module's own helpers), and OpenCSP's JSON is written here the way OpenCSP's ``DefinitionEnsemble.save_to_json``
lays it out.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from sofast_station.ensemble import (EnsembleDesign, angles_mrad, ensemble_from_opencsp, ensemble_to_opencsp,
                                     is_ensemble_file, load_ensemble, rotation_mrad)
from sofast_station.errors import ConfigError
from tests.conftest import ROOT

FACETS = ROOT / "fixtures" / "facets"


def normal_of_paraboloid(x, y, f):
    n = np.array([-x / (2 * f), -y / (2 * f), 1.0])
    return n / np.linalg.norm(n)


def test_the_shipped_2x2_heliostat():
    e = load_ensemble(FACETS / "heliostat_2x2.toml")
    assert e.labels == ["R1C1", "R1C2", "R2C1", "R2C2"] and e.n_facets == 4
    assert e.facets[e.measure_facet].label == "R2C2"
    assert e.adjusters is not None and e.adjusters.thread_pitch_mm == 1.25 and len(e.adjusters.names) == 3
    for f in e.facets:
        x, y, z = f.position_m
        assert abs(abs(x) - 0.325) < 1e-12 and abs(abs(y) - 0.325) < 1e-12
        assert z == pytest.approx((x * x + y * y) / 400.0, abs=1e-15)
        # the canting rule: the facet's z axis is the paraboloid's normal, no turn about z
        assert f.rotation[:, 2] == pytest.approx(normal_of_paraboloid(x, y, 100.0), abs=1e-12)
        rx, ry, rz = f.canting_mrad
        assert rz == pytest.approx(0.0, abs=1e-9)
        expected = Rotation.from_euler("YX", [ry * 1e-3, rx * 1e-3]).as_matrix()      # R_y(ry) R_x(rx)
        assert f.rotation == pytest.approx(expected, abs=1e-12)
        # x right, y up seen from the mirrors: the top-left facet turns its normal down and to the right
        if f.label == "R1C1":
            assert x < 0 < y and f.rotation[0, 2] > 0 > f.rotation[1, 2]
    # the facets' corners on the frame, 5 cm apart, 0.6 m each
    xy = e.corners_m()[:, :2]
    assert xy[:, 0].max() - xy[:, 0].min() == pytest.approx(1.25, abs=1e-5)


def test_the_shipped_5x5_heliostat_from_its_grid():
    e = load_ensemble(FACETS / "heliostat_5x5.toml")
    assert e.n_facets == 25 and e.labels[0] == "R1C1" and e.labels[-1] == "R5C5"
    first = e.facets[0]       # top left, seen from the mirrors
    assert first.position_m[:2] == pytest.approx([-0.86, 0.86], abs=1e-12)
    assert e.facets[e.measure_facet].label == "R3C3"
    assert e.facets[e.measure_facet].canting_mrad == pytest.approx((0.0, 0.0, 0.0), abs=1e-12)
    for f in e.facets:
        assert f.rotation[:, 2] == pytest.approx(normal_of_paraboloid(*f.position_m[:2], 100.0), abs=1e-12)
    layout = e.layout_design()
    assert layout.kind == "heliostat" and layout.layout["distance_m"] == 4.0
    assert layout.outline_m.max(axis=0) == pytest.approx([1.06, 1.06], abs=1e-5)


def test_design_poses_round_trip_through_plain_data():
    e = load_ensemble(FACETS / "heliostat_2x2.toml")
    back = EnsembleDesign.from_dict(json.loads(json.dumps(e.to_dict())))
    assert back.labels == e.labels and back.measure_facet == e.measure_facet
    for a, b in zip(e.facets, back.facets):
        assert np.array_equal(a.rotation, b.rotation) and np.array_equal(a.position_m, b.position_m)
        assert a.design.to_dict() == b.design.to_dict()
    assert back.adjusters.to_dict() == e.adjusters.to_dict()


def test_rotation_helpers_follow_the_placement_convention():
    angles = (1.3, -0.7, 2.1)
    r = rotation_mrad(*angles)
    expected = Rotation.from_euler("ZYX", [a * 1e-3 for a in angles[::-1]]).as_matrix()
    assert r == pytest.approx(expected, abs=1e-15)
    assert angles_mrad(r) == pytest.approx(angles, abs=1e-9)


def write(tmp_path, text: str, name: str = "h.toml"):
    (tmp_path / "f.toml").write_text((FACETS / "heliostat_0m6_100m.toml").read_text())
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("text, words", [
    ('[heliostat]\nfacet = "f.toml"\n', ["grid", "heliostat.facets"]),
    ('[heliostat]\nfacet = "f.toml"\ngrid = { rows = 2, columns = 2, pitch_m = 0.5 }\n', ["overlap"]),
    ('[heliostat]\nfacet = "f.toml"\ngrid = { rows = 1, columns = 2, pitch_m = 0.7 }\nmeasure_facet = "R9C9"\n',
     ["R9C9", "R1C1"]),
    ('[heliostat]\nfacet = "f.toml"\ngrid = { rows = 1, columns = 2, pitch_m = 0.7 }\nspin = 3\n', ["spin"]),
    ('[heliostat]\ngrid = { rows = 1, columns = 2, pitch_m = 0.7 }\n', ["no design"]),
    ('[heliostat]\nfacet = "f.toml"\n[[heliostat.facets]]\nlabel = "A"\nposition_m = [0, 0]\n'
     '[[heliostat.facets]]\nlabel = "A"\nposition_m = [1, 0]\n', ["A", "more than once"]),
    ('[heliostat]\nfacet = "f.toml"\n[[heliostat.facets]]\nlabel = "A"\nposition_m = [0, 0]\n', ["at least 2"]),
    ('[heliostat]\nfacet = "f.toml"\ngrid = { rows = 1, columns = 2, pitch_m = 0.7 }\n'
     '[heliostat.adjusters]\npoints_m = [[0, 0], [0.1, 0], [0.2, 0]]\nthread_pitch_mm = 1.0\n', ["one line"]),
    ('[heliostat]\nfacet = "f.toml"\ngrid = { rows = 1, columns = 2, pitch_m = 0.7 }\n'
     '[heliostat.adjusters]\npoints_m = [[0, 0], [0.1, 0], [0, 0.2]]\nthread_pitch_mm = -1\n', ["thread_pitch_mm"]),
    ('[heliostat]\nfacet = "missing.toml"\ngrid = { rows = 1, columns = 2, pitch_m = 0.7 }\n', ["missing.toml"]),
])
def test_a_bad_heliostat_file_is_named_with_what_is_wrong(tmp_path, text, words):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_ensemble(p)
    for w in words:
        assert w in str(err.value), str(err.value)


def test_explicit_canting_and_position_override_the_rule(tmp_path):
    p = write(tmp_path, '[heliostat]\nfacet = "f.toml"\ncanting_focal_length_m = 50\n'
                        '[[heliostat.facets]]\nlabel = "L"\nposition_m = [-0.35, 0, 0.01]\ncanting_mrad = [0.5, 2.0]\n'
                        '[[heliostat.facets]]\nlabel = "R"\nposition_m = [0.35, 0]\n')
    e = load_ensemble(p)
    assert e.facets[0].position_m[2] == 0.01 and e.facets[0].canting_mrad[:2] == pytest.approx((0.5, 2.0))
    assert e.facets[1].position_m[2] == pytest.approx(0.35 ** 2 / 200.0)
    assert e.facets[1].canting_mrad[1] == pytest.approx(-1e3 * math.atan(0.35 / 100.0), abs=1e-9)
    assert is_ensemble_file(p) and not is_ensemble_file(FACETS / "heliostat_0m6_100m.toml")


def opencsp_ensemble_json(positions, rotvecs) -> dict:
    """The layout of OpenCSP's DefinitionEnsemble.save_to_json (rotation vectors keyed "0", "1", ...)."""
    loc = np.asarray(positions, float)
    return {"v_facet_locations": {"x": loc[:, 0].tolist(), "y": loc[:, 1].tolist(), "z": loc[:, 2].tolist()},
            "r_facet_ensemble": {str(i): list(v) for i, v in enumerate(rotvecs)},
            "ensemble_perimeter": {"facet_indices": [0, 1, 1, 0], "corner_indices": [0, 1, 2, 3]},
            "v_centroid_ensemble": {"x": [0.0], "y": [0.0], "z": [0.0]}}


def test_opencsp_ensemble_definition_is_read(tmp_path):
    positions = [[-0.65, 0.0, 0.001], [0.65, 0.0, 0.001]]
    rotvecs = [[0.0, 0.003, 0.0], [0.0, -0.003, 0.0]]
    (tmp_path / "ensemble.json").write_text(json.dumps(opencsp_ensemble_json(positions, rotvecs)))
    e = ensemble_from_opencsp(tmp_path / "ensemble.json",
                              ROOT / "fixtures/opencsp/test_data/sofast_common/Facet_NSTTF.json", focal_length_m=100.0)
    assert e.n_facets == 2
    for f, p, v in zip(e.facets, positions, rotvecs):
        assert f.position_m == pytest.approx(p)
        assert f.rotation == pytest.approx(Rotation.from_rotvec(v).as_matrix(), abs=1e-15)
        # OpenCSP's corners are clockwise seen from the mirror; ours run counter-clockwise
        o = f.design.outline_m
        assert np.sum(o[:, 0] * np.roll(o[:, 1], -1) - np.roll(o[:, 0], -1) * o[:, 1]) > 0
        assert o.max(axis=0) == pytest.approx([0.606, 0.606])


def test_our_heliostat_written_as_opencsp_reads_back(tmp_path):
    e = load_ensemble(FACETS / "heliostat_5x5.toml")
    (tmp_path / "ensemble.json").write_text(json.dumps(ensemble_to_opencsp(e)))
    facet = {"v_facet_corners": {"x": [0.2, -0.2, -0.2, 0.2], "y": [-0.2, -0.2, 0.2, 0.2], "z": [0.0] * 4},
             "v_centroid_facet": {"x": [0.0], "y": [0.0], "z": [0.0]}}
    (tmp_path / "facet.json").write_text(json.dumps(facet))
    back = ensemble_from_opencsp(tmp_path / "ensemble.json", tmp_path / "facet.json", 100.0)
    for a, b in zip(e.facets, back.facets):
        assert b.position_m == pytest.approx(a.position_m, abs=1e-15)
        assert b.rotation == pytest.approx(a.rotation, abs=1e-14)
    assert back.facets[back.measure_facet].label == "F13"        # the middle facet, nearest the centroid


def test_an_opencsp_file_that_is_not_an_ensemble_is_named(tmp_path):
    (tmp_path / "x.json").write_text('{"v_facet_corners": {}}')
    with pytest.raises(ConfigError, match="v_facet_locations"):
        ensemble_from_opencsp(tmp_path / "x.json", tmp_path / "x.json", 100.0)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        ensemble_from_opencsp(tmp_path / "bad.json", tmp_path / "x.json", 100.0)
