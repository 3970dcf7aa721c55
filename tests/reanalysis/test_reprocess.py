"""Issue 7, item 1: `sofast-station reprocess` recomputes a dump's figures from its raw frames.

Exactness: the dumps come from the production loop of the small simulated station in this same test
session (same software, same platform), so reprocessing must reproduce every archived figure bit for bit.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest

from sofast_station.archive import read_dump
from sofast_station.errors import DumpError
from sofast_station.reanalysis.cli import main
from sofast_station.reanalysis.reprocess import Overrides, compare_figures, flatten_figures, reprocess_dump
from sofast_station.result.record import FIGURE_KEYS
from tests.archive.conftest import SAMPLE_RECORD
from tests.bad_dumps import make_bad_files
from tests.reanalysis.conftest import copy_dump

#: Figures computed before the corner pose: they depend on the frames, the fringe definition and the
#: analysis thresholds only, never on the facet design or the measured distance.
UPSTREAM_OF_POSE = ("n_points", "valid_fraction", "facet_pixels", "median_modulation_dn", "intensity_noise_dn",
                    "unwrap_disagreements", "measured_distance_m")
#: Figures fixed once the corner pose and the range are: they do not depend on the alignment point.
UPSTREAM_OF_BORESIGHT = UPSTREAM_OF_POSE + ("corner_reprojection_rms_px", "outline_agreement", "range_correction_m",
                                            "placement")


def _flat_subset(record: dict, names) -> dict:
    flat = flatten_figures(record)
    return {k: v for k, v in flat.items() if k.split(".")[0].split("[")[0] in names}


def test_dumps_reprocess_to_exactly_the_archived_figures(station_dumps):
    for dump in station_dumps.good:
        res = reprocess_dump(dump)
        archived = read_dump(dump, load_frames=False).record
        assert res.archived == archived
        assert res.exact is True, res.differences
        assert res.n_compared > 60
        for k in FIGURE_KEYS + ("coefficients", "placement", "valid_fraction", "iterations", "higher_order", "verdict",
                                "reasons"):
            assert res.record[k] == archived[k], k
        assert res.record["reprocess"]["exact"] is True
        assert res.summary().startswith("reproduced exactly: all ")
        # recomputed, not copied: the analysis ran and timed itself
        assert res.analysis is not None and res.record["timings_s"]["analysis"] > 0


def test_a_faulted_capture_reprocesses_to_the_same_fault(station_dumps):
    res = reprocess_dump(station_dumps.fault)
    assert res.analysis is None and res.record["verdict"] == "fault"
    assert res.record["reasons"] == res.archived["reasons"] and "dark" in res.record["reasons"][0]
    assert res.exact is True, res.differences


def test_a_u_that_moved_is_a_difference_the_table_names(station_dumps):
    """Issue 43: reprocess said "0 difference" while report showed another U, because it compared no U. An
    archived U 20 % larger than the one the frames give (every value the same) is now a difference: named in
    ``differences`` with its figure, in the table's U column, and in the summary (same software: NOT
    reproduced); the values' column still says 0."""
    import copy

    from sofast_station.reanalysis.cli import comparison_table
    from sofast_station.reanalysis.reprocess import reprocess_content

    content = read_dump(station_dumps.good[0])
    archived = copy.deepcopy(content.record)
    archived["focal_length_x_m_U"] *= 1.2
    archived["slope_rms_mrad_U"]["design"]["magnitude"] *= 1.2
    res = reprocess_content(content, archived=archived)
    assert set(res.differences) == {"focal_length_x_m_U", "slope_rms_mrad_U.design.magnitude"}
    assert res.differences["focal_length_x_m_U"]["uncertainty_of"] == "focal_length_x_m"
    assert res.exact is False and "2 of" in res.summary() and "(only U)" in res.summary()
    assert "NOT reproduced" in res.summary() and res.record["reprocess"]["uncertainties_different"] == 2
    cells = {row[0]: row for row in (re.split(r"\s{2,}", ln.strip()) for ln in comparison_table(res).splitlines()[1:])}
    for name in ("focal_length_x_m", "slope_rms_mrad.design.magnitude"):
        assert cells[name][3] == "0" and cells[name][4].endswith("(-17 %)"), cells[name]   # (1 - 1.2) / 1.2
    assert cells["focal_length_y_m"][3:] == ["0", "0"]


def test_an_archived_fault_that_now_analyses_is_named_as_such(station_dumps):
    from sofast_station.reanalysis.reprocess import reprocess_content

    content = read_dump(station_dumps.good[0])
    fault = {k: content.record[k] for k in ("cycle_id", "serial", "time", "recipe", "station")}
    fault.update(verdict="fault", fault_code=6, reasons=["timeout: the analysis did not finish within 2.0 s"])
    res = reprocess_content(content, archived=fault)
    assert res.exact is False and res.record["verdict"] == "pass"
    assert "the archive holds verdict 'fault', reprocessing gives 'pass' (timeout:" in res.summary()


def test_without_the_stored_result_group_the_figures_are_still_reproduced(station_dumps, tmp_path):
    original = station_dumps.good[0]
    bare = copy_dump(original, tmp_path / original.name)
    with h5py.File(bare, "r+") as f:
        del f["result"]
    with pytest.raises(DumpError, match="lacks the dataset"):      # the station's reader still insists on it
        read_dump(bare)
    res = reprocess_dump(bare)
    assert res.archived is None and res.exact is None
    assert "no archived result" in res.summary() and "result group is missing" in res.notes[0]
    archived = read_dump(original, load_frames=False).record
    differences, n = compare_figures(archived, res.record)
    assert n > 60 and not [k for k, d in differences.items() if "uncertainty_of" not in d], differences
    # the journal still has the row: with it the comparison is made; every value is the archive's, but what the
    # line's U came from (its input uncertainties, its sensitivities and frame-brightness pool) was in the
    # result group, so U moved, and the summary and notes say why
    res = reprocess_dump(bare, journal=station_dumps.journal)
    assert res.exact is False and res.differences and res.differences == res.uncertainty_differences
    assert str(station_dumps.journal) in res.summary() and "every value reproduced" in res.summary()
    assert res.u_missing == ["its input uncertainties", "its sensitivities"]
    assert any("does not keep the input uncertainties" in n for n in res.notes)


def _set_frame(path, index: int, frame: np.ndarray) -> None:
    """Replace one frame of a dump and its SHA-256 digest (a legitimately different capture)."""
    with h5py.File(path, "r+") as f:
        f["capture/frames"][index] = frame
        f["capture/frames_sha256"][index] = hashlib.sha256(np.ascontiguousarray(frame)).hexdigest()


def test_one_changed_pixel_changes_the_result(station_dumps, tmp_path):
    original = station_dumps.good[0]
    changed = copy_dump(original, tmp_path / original.name)
    content = read_dump(original)
    base = reprocess_dump(original)
    # a pixel in the middle of the facet, in the first frame of the fine x fringes
    index = 2 + content.fringe_set().phase_steps
    rows, cols = np.nonzero(base.analysis.valid)
    r = int(rows[rows.size // 2]) - content.crop_box[0]
    c = int(cols[cols.size // 2]) - content.crop_box[1]
    frame = content.frames_cropped[index].copy()
    frame[r, c] = frame[r, c] + 40 if frame[r, c] < 200 else frame[r, c] - 40
    _set_frame(changed, index, frame)
    res = reprocess_dump(changed)
    assert res.exact is False and res.differences
    flat_new, flat_old = flatten_figures(res.record), flatten_figures(base.record)
    assert (flat_new["n_points"] != flat_old["n_points"]
            or flat_new["slope_rms_mrad.design.magnitude"] != flat_old["slope_rms_mrad.design.magnitude"])
    assert "NOT reproduced" in res.summary()


def test_design_focal_length_changes_exactly_the_figures_that_depend_on_it(station_dumps):
    """On this on-axis dish the alignment and measure points are at the vertex (0, 0). There the design's
    height is 0 and its slopes are 0 for every focal length f, so none of the boresight conditions
    (F, t_z, alpha, beta) involves f. f enters the analysis in exactly three places:

    1. the design residuals: e = atan(s) - atan(x / 2f) changes at every point;
    2. the corner pose: the four corners lie on the design surface at z_c = r_c^2 / 4f (r_c^2 = 0.18 m^2,
       the same for all four), so the pose moves by dz_c along the facet axis, the range correction takes
       it back (the line of sight is within 1 degree of the axis) and the frame's origin ends up a few
       micrometres aside (placement); and the corners themselves move a little, as the design's sides
       bow less (the corner finder draws each side's bow toward the design's): by under 0.005 px, which
       moves the range by up to that move over the facet's width in pixels, relative to the distance, and
       turns the corner pose (the boresight, measured from it, turns back by as much);
    3. the verdict, whose focal-length limit is relative to the design f.

    So: the figures upstream of the pose stay bit-identical; the design residuals equal the baseline's
    measured slopes against the new design; the range correction moves by -dz_c; the fitted figures
    (focal lengths, twist, parabola and higher-order residuals) move only by the iteration's convergence
    tolerance |d kappa| < 1e-6 |kappa| (docs/conventions.md#iteration; in practice 1e-8) and the boresight
    by its 1 microradian tolerance plus the lateral shift delta of the frame, delta / 2f.
    """
    f1 = 5.6
    for dump in station_dumps.good:
        base = reprocess_dump(dump)
        new = reprocess_dump(dump, Overrides(focal_length_m=f1))
        f0 = base.design.focal_length_m
        assert new.design.focal_length_m == f1 and f0 == 5.33
        # upstream of the pose: identical bits
        assert _flat_subset(new.record, UPSTREAM_OF_POSE) == _flat_subset(base.record, UPSTREAM_OF_POSE)
        # 1. design residuals: the baseline's points and slopes against the new design
        a = base.analysis
        x, y = a.points_facet_m[0], a.points_facet_m[1]
        ex = 1000.0 * (np.arctan(a.slopes[0]) - np.arctan(x / (2 * f1)))
        ey = 1000.0 * (np.arctan(a.slopes[1]) - np.arctan(y / (2 * f1)))
        predicted = {"x": math.sqrt(np.mean(ex * ex)), "y": math.sqrt(np.mean(ey * ey))}
        predicted["magnitude"] = math.hypot(predicted["x"], predicted["y"])
        got, old = new.record["slope_rms_mrad"]["design"], base.record["slope_rms_mrad"]["design"]
        for k in ("x", "y", "magnitude"):
            assert abs(got[k] - predicted[k]) < 2e-3, (k, got[k], predicted[k])     # 2 microradians
        assert got["magnitude"] - old["magnitude"] > 0.3                              # a large, real change
        # 2. the corner pose's range: moved by -dz_c, and by the corners' small move with the design's bow
        # (a move of the corners by m px changes the outline's size in the image by up to 2 m over its
        # width w px, and the corner pose's range by as much relative to the distance)
        move_px = np.abs(new.analysis.corners_px - base.analysis.corners_px).max()
        assert move_px < 0.005
        dz = 0.18 / 4.0 * (1.0 / f1 - 1.0 / f0)
        d_range = new.record["range_correction_m"] - base.record["range_correction_m"]
        width_px = np.ptp(base.analysis.corners_px[:, 0])
        assert abs(d_range + dz) < 0.01 * dz + 2 * move_px / width_px * base.record["measured_distance_m"]
        # fitted figures: within the convergence tolerance
        for key in ("curvature_x_per_m", "curvature_y_per_m"):
            assert abs(new.record[key] / base.record[key] - 1) < 1e-6, key
        for key in ("focal_length_x_m", "focal_length_y_m"):
            assert abs(new.record[key] / base.record[key] - 1) < 1e-6, key
        kappa = max(abs(base.record["curvature_x_per_m"]), 1e-3)
        for key in ("twist_mrad_per_m", "twist_e1_mrad_per_m", "twist_e2_mrad_per_m"):
            assert abs(new.record[key] - base.record[key]) < 1000 * 1e-6 * kappa, key
        for model in ("parabola", "higher_order"):
            for k in ("x", "y", "magnitude"):
                assert new.record["slope_rms_mrad"][model][k] == pytest.approx(
                    base.record["slope_rms_mrad"][model][k], rel=1e-6), (model, k)
        shift_mm = np.subtract(new.record["placement"]["mm"][:2], base.record["placement"]["mm"][:2])
        shift_m = math.hypot(*shift_mm) / 1000
        bound_mrad = 1e-3 + 1000 * shift_m / (2 * f0) + 5e-4
        for i, axis in enumerate(("x", "y")):
            # (plus the corner pose's own turn, which the boresight is measured from: the corners' small
            # move turns it, and the boresight turns back by as much)
            turn = abs(new.record["placement"]["mrad"][i] - base.record["placement"]["mrad"][i])
            moved = abs(new.record["boresight_mrad"][axis] - base.record["boresight_mrad"][axis])
            assert moved < bound_mrad + turn, axis
        # 3. the verdict: the measured 5.42 / 5.35 m are now 3 to 4 % short of the design
        assert base.record["verdict"] == "pass" and new.record["verdict"] == "fail"
        assert any("focal length x" in r for r in new.record["reasons"])
        # and the comparison says so, figure by figure
        assert "slope_rms_mrad.design.magnitude" in new.differences
        assert not set(new.differences) & set(_flat_subset(base.record, UPSTREAM_OF_POSE))


def test_alignment_point_changes_exactly_the_figures_that_depend_on_it(station_dumps):
    """Moving the alignment point to P_a = (0.1, 0.05) m changes nothing before the boresight (frames,
    mask, corner pose, range: bit-identical; the placement, stated from the corners on the measured surface,
    at second order only). The boresight then rotates the assembly so that the fitted
    parabola's normal at P_a is the design normal there: to first order it rotates by the difference of
    the baseline fit's slope and the design's slope at P_a, beta: atan(2A x_a + C + E y_a) - atan(x_a / 2f),
    alpha: -(atan(2B y_a + D + E x_a) - atan(y_a / 2f)) (the second-order part: the rotation also moves the
    intersections and the re-fitted A..E, a few percent of the rotation). The tilts C, D, the constant F and
    the design residuals follow. The focal lengths change only at second order in that 0.15 mrad tilt
    (about 1e-8 here; bound: the iteration's 1e-6 tolerance)."""
    xa, ya = 0.1, 0.05
    for dump in station_dumps.good:
        base = reprocess_dump(dump)
        new = reprocess_dump(dump, Overrides(alignment_point_m=(xa, ya)))
        f = base.design.focal_length_m
        upstream = tuple(n for n in UPSTREAM_OF_BORESIGHT if n != "placement")
        assert _flat_subset(new.record, upstream) == _flat_subset(base.record, upstream)
        c = base.record["coefficients"]
        d_beta = 1000 * (math.atan(2 * c["A"] * xa + c["C"] + c["E"] * ya) - math.atan(xa / (2 * f)))
        d_alpha = -1000 * (math.atan(2 * c["B"] * ya + c["D"] + c["E"] * xa) - math.atan(ya / (2 * f)))
        tol = 0.03 * max(abs(d_alpha), abs(d_beta)) + 1e-3
        got_alpha = new.record["boresight_mrad"]["x"] - base.record["boresight_mrad"]["x"]
        got_beta = new.record["boresight_mrad"]["y"] - base.record["boresight_mrad"]["y"]
        assert abs(got_beta - d_beta) < tol and abs(got_alpha - d_alpha) < tol, (got_alpha, d_alpha, got_beta, d_beta)
        assert abs(got_beta) > 0.1                                   # a real rotation
        # The placement is the corner pose on the measured surface (docs/method.md): the corners are lifted by
        # the surface's departure from the design, whose curvature terms the boresight's turn mixes only at
        # second order: within 1 % of the turn (mrad) and 1 um (found: 1.1e-4 mrad, 1e-6 mm)
        for unit, bound in (("mrad", 0.01 * max(abs(d_alpha), abs(d_beta))), ("mm", 1e-3)):
            moved = np.subtract(new.record["placement"][unit], base.record["placement"][unit])
            assert np.max(np.abs(moved)) < bound, (unit, moved)
        for key in ("C", "D", "F"):
            assert new.record["coefficients"][key] != base.record["coefficients"][key], key
        # F puts the fitted surface through the design height at P_a
        z_design = (xa * xa + ya * ya) / (4 * f)
        k = new.record["coefficients"]
        z_fit = k["A"] * xa * xa + k["B"] * ya * ya + k["C"] * xa + k["D"] * ya + k["E"] * xa * ya + k["F"]
        assert z_fit == pytest.approx(z_design, abs=1e-12)
        design_rms = (new.record["slope_rms_mrad"]["design"]["magnitude"],
                      base.record["slope_rms_mrad"]["design"]["magnitude"])
        assert design_rms[0] != design_rms[1]
        for key in ("curvature_x_per_m", "curvature_y_per_m"):
            assert abs(new.record[key] / base.record[key] - 1) < 1e-6, key


def test_measured_distance_and_mask_threshold_overrides(station_dumps):
    dump = station_dumps.good[0]
    base = reprocess_dump(dump)
    d0 = base.record["measured_distance_m"]
    new = reprocess_dump(dump, Overrides(measured_distance_m=d0 + 0.001))
    assert new.record["measured_distance_m"] == d0 + 0.001
    assert _flat_subset(new.record, UPSTREAM_OF_POSE[:-1]) == _flat_subset(base.record, UPSTREAM_OF_POSE[:-1])
    # the range correction slides the facet 1 mm further along the line of sight (within 1 degree of it)
    assert new.record["range_correction_m"] - base.record["range_correction_m"] == pytest.approx(0.001, rel=0.01)
    # a threshold above the dimmest facet pixels' response keeps fewer pixels; the note says what a lower
    # one cannot do
    frames = read_dump(dump).frames().astype(np.int16)
    response = (frames[1] - frames[0])[base.analysis.valid]
    high = reprocess_dump(dump, Overrides(mask_threshold_dn=float(np.percentile(response, 0.5))))
    assert 0 < high.record["facet_pixels"] < base.record["facet_pixels"]
    assert high.differences and "mask threshold" in high.notes[0]
    low = reprocess_dump(dump, Overrides(mask_threshold_dn=5))
    assert any("only inside that box" in n for n in low.notes)


def test_a_facet_file_override(station_dumps, tmp_path):
    from tests.conftest import ROOT

    dump = station_dumps.good[0]
    same = reprocess_dump(dump, Overrides(facet_path=str(ROOT / "fixtures/facets/dish_5m33.toml")))
    assert same.differences == {} and "dish_5m33.toml" in same.notes[0]
    other = tmp_path / "dish.toml"
    other.write_text((ROOT / "fixtures/facets/dish_5m33.toml").read_text().replace(
        'name = "dish-5.33"', 'name = "dish-5.6"').replace("focal_length_m = 5.33", "focal_length_m = 5.6"))
    res = reprocess_dump(dump, Overrides(facet_path=str(other)))
    by_f = reprocess_dump(dump, Overrides(focal_length_m=5.6))
    assert res.record["facet"] == "dish-5.6"
    assert flatten_figures(res.record) == flatten_figures(by_f.record)   # the same design, reached two ways


def test_a_calibration_record_override_changes_no_measured_figure(station_dumps, tmp_path):
    dump = station_dumps.good[0]
    content = read_dump(dump, load_frames=False)
    record = dict(content.radiometric, record_id="calibration-2026-11-26",
                  lut=[float(v) for v in np.linspace(0.0, 1.0, 256) ** (1 / 2.0)])
    path = tmp_path / "radiometric.json"
    path.write_text(json.dumps(record))
    res = reprocess_dump(dump, Overrides(radiometric_path=str(path)))
    assert res.record["calibration"]["radiometric"] == "calibration-2026-11-26"
    assert res.differences == {}                       # every measured figure: the same frames, the same analysis
    note = next(n for n in res.notes if n.startswith("calibration record"))
    assert "cannot change" in note and "reads nothing from the record" in note and "display commands" in note
    assert res.record["camera"] == content.record["camera"]


def _write_v1_by_hand(path, content) -> None:
    """A schema-1 dump written with h5py from the layout table of docs/dump-schema.md (not by write_dump):
    the v1 layout frozen in the tests, so that readers of later versions are checked against it."""
    s = h5py.string_dtype("utf-8")
    with h5py.File(path, "w") as f:
        for k, v in {"schema": "sofast-station-dump", "description": "hand-written schema 1 dump",
                     "software_version": content.software_version, "created": "2026-01-01T00:00:00.000+01:00",
                     "cycle_id": content.cycle_id, "serial": content.serial, "time": content.time,
                     "config_hash": content.config_hash}.items():
            f.attrs[k] = v
        f.attrs["schema_version"] = np.int64(1)
        frames = content.frames_cropped
        cap = f.create_group("capture")
        cap.create_dataset("frames", data=frames, chunks=(1, *frames.shape[1:]), compression="gzip",
                           compression_opts=4, shuffle=True)
        cap.create_dataset("frames_sha256", data=[hashlib.sha256(fr).hexdigest() for fr in frames], dtype=s)
        cap.create_dataset("crop_box", data=np.array(content.crop_box, np.int64))
        cap.create_dataset("full_shape", data=np.array(content.full_shape, np.int64))
        cap.create_dataset("patterns", data=content.patterns, dtype=s)
        cap.create_dataset("measured_distance_m", data=np.float64(content.measured_distance_m))
        fr = f.create_group("fringes")
        fr.create_dataset("periods_x", data=np.array(content.fringes["periods_x"], np.float64))
        fr.create_dataset("periods_y", data=np.array(content.fringes["periods_y"], np.float64))
        fr.create_dataset("phase_steps", data=np.int64(content.fringes["phase_steps"]))
        if "drawn" in content.fringes:      # an optional group (issue 47): how the display drew the fringes
            d = content.fringes["drawn"]
            dr = fr.create_group("drawn")
            dr.create_dataset("lut", data=np.array(d["lut"], np.float64))
            dr.create_dataset("floor_level", data=np.float64(d["floor_level"]))
            dr.create_dataset("max_level", data=np.float64(d["max_level"]))
            dr.create_dataset("display_px", data=np.array(d["display_px"], np.int64))
        rad = f.create_group("calibration/radiometric")
        r = content.radiometric
        rad.create_dataset("schema", data=np.int64(r["schema"]))
        for k in ("kind", "record_id", "created", "source"):
            rad.create_dataset(k, data=r[k], dtype=s)
        rad.create_dataset("lut", data=np.array(r["lut"], np.float64))
        for k in ("floor_level", "max_level", "exposure_s", "gain"):
            rad.create_dataset(k, data=np.float64(r[k]))
        g = content.geometry
        for k in ("width_px", "height_px"):
            f.create_dataset(f"geometry/camera/{k}", data=np.int64(g["camera"][k]))
        f.create_dataset("geometry/camera/matrix", data=np.array(g["camera"]["matrix"], np.float64))
        f.create_dataset("geometry/camera/distortion", data=np.array(g["camera"]["distortion"], np.float64))
        for k in ("width_px", "height_px"):
            f.create_dataset(f"geometry/screen/{k}", data=np.int64(g["screen"][k]))
        f.create_dataset("geometry/screen/pitch_m", data=np.float64(g["screen"]["pitch_m"]))
        for pose in ("screen_to_camera", "fixture_to_camera"):
            for k in ("rotation", "translation"):
                f.create_dataset(f"geometry/{pose}/{k}", data=np.array(g[pose][k], np.float64))
        d = content.design
        for k in ("name", "kind"):
            f.create_dataset(f"design/{k}", data=d[k], dtype=s)
        f.create_dataset("design/focal_length_m", data=np.float64(d["focal_length_m"]))
        for k in ("outline_m", "measure_point_m", "alignment_point_m"):
            f.create_dataset(f"design/{k}", data=np.array(d[k], np.float64))
        f.create_group("design/layout")
        v1_settings = ("mask_threshold_dn", "min_modulation_dn", "consistency_sigmas", "guard_sigmas", "subsample_step",
                       "max_iterations", "max_range_shift_m", "corner_tolerance_px", "max_hole_px",
                       "max_saturated_fraction", "max_corner_rms_px")
        for k in v1_settings:
            f.create_dataset(f"analysis/{k}", data=content.analysis[k])
        for k in ("station_toml", "facet_toml", "station_path", "facet_path", "config_hash", "station_name"):
            value = {"config_hash": content.config_hash, "station_name": content.station_name}.get(k) \
                or getattr(content, k)
            f.create_dataset(f"config/{k}", data=value, dtype=s)
        f.create_dataset("result/record_json", data=json.dumps(content.record), dtype=s)


def test_a_hand_written_schema_1_dump_is_read_and_reproduced(station_dumps, tmp_path):
    content = read_dump(station_dumps.good[1])
    assert content.schema_version == 2          # the station writes schema 2; this test writes 1 by hand
    v1 = tmp_path / "v1.h5"
    _write_v1_by_hand(v1, content)
    back = read_dump(v1)
    assert back.schema_version == 1 and back.cycle_id == content.cycle_id
    assert np.array_equal(back.frames_cropped, content.frames_cropped)
    res = reprocess_dump(v1)
    # every value reproduced; a schema-1 dump keeps neither the input uncertainties nor the sensitivities the
    # line's U came from, so the U that moved are listed, and the notes say why
    assert res.differences == res.uncertainty_differences, res.differences
    assert res.u_missing == ["its input uncertainties", "its sensitivities"]
    assert "every value reproduced" in res.summary()


@pytest.mark.parametrize("json_mode", [False, True], ids=["table", "json"])
def test_bad_files_give_clear_errors_through_reprocess(station_dumps, tmp_path, capsys, caplog, json_mode):
    bad = make_bad_files(tmp_path / "bad", station_dumps.good[0])
    for path, problem in bad.items():
        with pytest.raises(DumpError) as info:
            reprocess_dump(path)
        assert str(path) in str(info.value) and problem in str(info.value), str(info.value)
    # the command goes on past them: the good dump after the bad ones is still reprocessed
    args = ["reprocess", *map(str, bad), str(station_dumps.good[0])] + (["--json"] if json_mode else [])
    assert main(args) == 2
    captured = capsys.readouterr()
    for path, problem in bad.items():
        assert any(str(path) in line and problem in line for line in caplog.text.splitlines()), (path, caplog.text)
    if json_mode:
        objects = [json.loads(line) for line in captured.out.splitlines()]
        assert [o["status"] for o in objects] == ["error"] * len(bad) + ["ok"]
        for o, (path, problem) in zip(objects, bad.items()):
            assert o["dump"] == str(path) and problem in o["error"]
    else:
        assert "reproduced exactly" in captured.out


def test_cli_table_and_json(station_dumps, capsys):
    dump = station_dumps.good[0]
    assert main(["reprocess", str(dump)]) == 0
    out = capsys.readouterr().out
    assert "reproduced exactly: all " in out and "focal_length_x_m" in out and "new - archived" in out
    assert main(["reprocess", str(dump), "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)          # one dump: one JSON object, nothing else
    assert set(SAMPLE_RECORD) <= set(obj)              # the keys of `inspect --json`
    assert {"archived", "differences", "reprocess", "dump", "status"} <= set(obj)
    assert obj["differences"] == {} and obj["reprocess"]["exact"] is True
    assert main(["reprocess", str(dump), "--focal-length", "5.6", "--json", "--check"]) == 3
    obj = json.loads(capsys.readouterr().out)
    d = obj["differences"]["slope_rms_mrad.design.magnitude"]
    assert d["difference"] == pytest.approx(d["new"] - d["archived"]) and d["difference"] > 0.3
    assert obj["reprocess"]["overrides"] == {"focal_length_m": 5.6} and "truth" not in obj


def test_the_command_reports_a_bad_file_without_a_traceback(tmp_path):
    bad = tmp_path / "photo.h5"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 100)
    proc = subprocess.run([sys.executable, "-m", "sofast_station.reanalysis.cli", "reprocess", str(bad)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert str(bad) in proc.stderr and "it looks like a PNG image" in proc.stderr and "Traceback" not in proc.stderr


def test_dumps_carry_the_stations_sensitivities_and_reprocess_reuses_them_in_any_order(station_dumps):
    from sofast_station.reanalysis.reprocess import is_uncertainty_key, reprocess_content

    def u_figures(res):
        return {k: v for k, v in flatten_figures(res.record, uncertainties=True).items() if is_uncertainty_key(k)}

    contents = [read_dump(d) for d in station_dumps.good[:2]]
    for content in contents:
        stored = content.sensitivities
        assert stored is not None and stored["key"] and len(stored["linear"]) == len(stored["inputs"])
        # the station's own sensitivities are used: none computed in the re-analysis
        res = reprocess_content(content)
        assert res.exact is True, res.differences
        assert "analysis_uncertainty_sensitivities" not in res.record["timings_s"]
        assert u_figures(res) and all(v is None or math.isfinite(v) for v in u_figures(res).values())
    # Each dump uses its own record: the order of a batch does not change a dump's uncertainties.
    first = [u_figures(reprocess_content(c)) for c in contents]
    second = [u_figures(reprocess_content(c)) for c in reversed(contents)][::-1]
    assert first == second
    # Without the record (an older dump), they are computed from the capture: a cost, and U of the capture's
    # own (its frame brightness not pooled with the line's earlier captures): every value is the archive's, and
    # the U that moved are named, with why
    bare = read_dump(station_dumps.good[0])
    bare.sensitivities = None
    res = reprocess_content(bare)
    assert res.record["timings_s"]["analysis_uncertainty_sensitivities"] > 0
    assert res.differences == res.uncertainty_differences and res.u_missing == ["its sensitivities"]
    assert set(u_figures(res)) == set(first[0])
