"""HDF5 data dumps: bit-exact round trip, re-analysis, self-description, bad files, size, retention."""

from __future__ import annotations

import dataclasses
import errno
import os
import time

import h5py
import numpy as np
import pytest

from sofast_station.files import json_ready
from sofast_station.archive.dumps import (SCHEMA_V1, SCHEMA_V2, SCHEMA_V3, SCHEMA_VERSION, crop_to_facet, disk_ok,
                                          prune_dumps, read_dump, restore_frames, write_dump)
from sofast_station.archive.dumps import writer as dump_writer
from sofast_station.archive.spool import spool_get, spool_list, spool_put
from sofast_station.errors import ArchiveError, DumpError

from tests import bad_dumps
from tests.bad_dumps import BAD_FILES

from .conftest import ROOT, make_record, synthetic_content


def assert_same_content(a, b):
    for f in dataclasses.fields(a):
        if f.name in ("created", "path"):
            continue
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f.name
        else:
            assert x == y, f.name
            assert type(x) is type(y) or isinstance(x, (tuple, list)), f.name


@pytest.fixture
def dump_file(small_config, tmp_path):
    content = synthetic_content(small_config)
    path = tmp_path / "dumps" / "d.h5"
    write_dump(path, content)
    return path, content


def test_round_trip_is_bit_exact(dump_file, small_config):
    path, content = dump_file
    back = read_dump(path)
    assert_same_content(content, back)
    assert back.path == path and back.created and back.schema_version == 2 and SCHEMA_VERSION == 3
    # the typed records come back equal to the configuration's
    assert back.station_geometry().to_dict() == small_config.geometry.to_dict()
    assert back.fringe_set() == small_config.fringes
    assert back.facet_design().to_dict() == small_config.design.to_dict()
    assert back.analysis_settings() == small_config.analysis
    rad = back.radiometric_record()
    assert rad.record_id == "simulated-default" and rad.lut.dtype == np.float64
    assert back.station_toml == small_config.path.read_text()
    assert back.facet_toml == small_config.facet_path.read_text()
    assert back.config_hash == small_config.config_hash and back.software_version == make_record()["software_version"]
    assert back.record == json_ready(make_record())
    meta_only = read_dump(path, load_frames=False)
    assert meta_only.frames_cropped is None and meta_only.cycle_id == content.cycle_id
    with h5py.File(path) as f:
        res = f["result"].attrs
        assert res["verdict"] == "pass" and res["n_points"] == make_record()["n_points"]
        assert res["slope_rms_mrad.design.magnitude"] == make_record()["slope_rms_mrad"]["design"]["magnitude"]
        ds = f["capture/frames"]
        assert ds.chunks == (1, 120, 160) and ds.compression == "gzip" and ds.compression_opts == 4
        assert ds.shuffle
        assert np.array_equal(ds[()], content.frames_cropped)          # plain HDF5 decoding


def test_every_group_and_dataset_is_described(dump_file):
    path, _ = dump_file
    seen = []

    def check(name, obj):
        seen.append(name)
        desc = obj.attrs.get("description")
        assert isinstance(desc, str) and desc and "not described" not in desc, name
        assert "units" in obj.attrs, name

    with h5py.File(path) as f:
        assert f.attrs["schema"] == "sofast-station-dump" and f.attrs["schema_version"] == 2
        f.visititems(check)
        for p, kind, *_ in SCHEMA_V2:
            if kind == "attribute" and p != "/@station" and p != "/@facet":
                assert p[2:] in f.attrs, p
    assert "capture/frames" in seen and "geometry/camera/matrix" in seen
    doc = (ROOT / "docs" / "dump-schema.md").read_text()
    for p, *_ in SCHEMA_V1 + SCHEMA_V2 + SCHEMA_V3:
        name = p[2:] if p.startswith("/@") else p
        assert f"`{name}`" in doc, f"docs/dump-schema.md does not describe {p}"


def test_restore_frames_and_crop():
    rng = np.random.default_rng(1)
    full = rng.integers(0, 10, size=(18, 60, 80), dtype=np.uint8)       # ambient light everywhere
    full[1, 20:30, 30:50] += 200                                          # the facet lights up in white
    crop, box, shape = crop_to_facet(full, threshold_dn=20, margin_px=3)
    assert box == (17, 27) and shape == (60, 80) and crop.shape == (18, 16, 26)
    back = restore_frames(crop, box, shape)
    assert np.array_equal(back[:, 17:33, 27:53], full[:, 17:33, 27:53])
    outside = np.ones(shape, bool)
    outside[17:33, 27:53] = False
    assert not back[:, outside].any()                                     # zero outside the crop, by definition
    assert np.array_equal(restore_frames(crop, (17, 27, 33, 53), shape), back)    # (row0, col0, row1, col1)
    with pytest.raises(DumpError, match="does not fit"):
        restore_frames(crop, (50, 0), shape)
    with pytest.raises(ArchiveError, match="does not match"):
        restore_frames(crop, (17, 27, 33, 54), shape)
    dark = np.zeros((18, 60, 80), np.uint8)
    crop, box, shape = crop_to_facet(dark)
    assert box == (0, 0) and crop.shape == dark.shape                     # nothing responds: keep everything


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    """One noisy capture of the small simulated station, its analysis and result record."""
    from sofast_station.config import load_config
    from sofast_station.measure.analysis import analyse
    from sofast_station.station.factory import open_station
    from sofast_station.result.record import build_record
    from sofast_station.station.inspection import capture
    from tests.conftest import SMALL_STATION

    d = tmp_path_factory.mktemp("small")
    path = d / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=d / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    station = open_station(load_config(path), seed=4)
    try:
        frames, distance = capture(station)
    finally:
        station.close()
    cfg = station.config
    analysis = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis)
    record = build_record(station.record_head("SIM-RE"), figures=analysis.figures, timings={"total": 1.0})
    return station, frames, distance, analysis, record


def test_reanalysing_a_dump_gives_the_archived_figures_exactly(small_capture, tmp_path):
    from sofast_station.archive.dumps import DumpContent

    station, frames, distance, analysis, record = small_capture
    crop, box, shape = crop_to_facet(frames, station.config.analysis.mask_threshold_dn)
    assert crop.size < frames.size
    content = DumpContent.from_station(station, cycle_id="re-1", record=record, frames_cropped=crop, crop_box=box,
                                       full_shape=shape, measured_distance_m=distance)
    write_dump(tmp_path / "re.h5", content)
    back = read_dump(tmp_path / "re.h5")
    again = back.analyse()
    figures = {k: v for k, v in again.figures.items() if k != "timings_s"}
    archived = {k: back.record[k] for k in figures}
    assert json_ready(figures) == archived                                # every measured figure, exactly
    assert np.array_equal(again.slopes, analysis.slopes)


def test_full_resolution_dump_of_twin_frames_is_small_and_fast(tmp_path):
    from sofast_station.archive.dumps import DumpContent
    from sofast_station.config import load_config
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture

    config = load_config(ROOT / "station.toml")
    station = open_station(config, seed=1)
    try:
        frames, distance = capture(station)
    finally:
        station.close()
    assert frames.shape == (18, 1200, 1600)
    crop, box, shape = crop_to_facet(frames, config.analysis.mask_threshold_dn)
    content = DumpContent.from_station(station, cycle_id="full-1", record=make_record(), frames_cropped=crop,
                                       crop_box=box, full_shape=shape, measured_distance_m=distance)
    stats = write_dump(tmp_path / "full.h5", content)
    t0 = time.perf_counter()
    back = read_dump(tmp_path / "full.h5")
    t_read = time.perf_counter() - t0
    print(f"\nfull-resolution dump: crop {crop.shape[1]} x {crop.shape[2]} of {shape[0]} x {shape[1]}, "
          f"{stats.size_bytes / 1e6:.2f} MB (frames {stats.raw_bytes / 1e6:.1f} MB raw, full stack "
          f"{frames.nbytes / 1e6:.1f} MB), write {stats.seconds:.2f} s, read {t_read:.2f} s")
    assert np.array_equal(back.frames()[:, box[0]:box[0] + crop.shape[1], box[1]:box[1] + crop.shape[2]], crop)
    assert stats.size_bytes < 10e6
    assert stats.seconds > 0                          # its time (0.4 s on a quiet 2-core machine) is a benchmark
                                                      # figure: a wall-clock bound fails on a loaded machine


# -- bad files ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make, problem", [(make, problem) for _, make, problem in BAD_FILES] + [
    (bad_dumps.tampered, "is corrupt: frame 3 does not match its SHA-256 digest")],
    ids=[name for name, _, _ in BAD_FILES] + ["tampered"])
def test_bad_files_raise_dump_errors_naming_file_and_problem(dump_file, tmp_path, make, problem):
    good, _ = dump_file
    bad = tmp_path / f"bad-{make.__name__}.h5"
    make(bad, good)
    with pytest.raises(DumpError) as info:
        read_dump(bad)
    msg = str(info.value)
    assert str(bad) in msg and problem in msg, msg
    if make is bad_dumps.newer:
        assert "upgrade" in msg


def test_a_failed_write_leaves_neither_dump_nor_temp_file(small_config, tmp_path, monkeypatch):
    content = synthetic_content(small_config)

    def full(record):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(dump_writer, "_flat_figures", full)
    with pytest.raises(ArchiveError, match="No space left"):
        write_dump(tmp_path / "out" / "d.h5", content)
    assert list((tmp_path / "out").iterdir()) == []


def test_spool_round_trip(small_config, tmp_path):
    from sofast_station.archive.dumps import DumpContent

    content = synthetic_content(small_config, cycle_id="20260302T101500-abc")
    t0 = time.perf_counter()
    path = spool_put(tmp_path / "spool", content.cycle_id, *content.to_spool())
    dt = time.perf_counter() - t0
    assert path.name == "20260302T101500-abc.npz" and dt < 1.0
    assert spool_list(tmp_path / "spool") == [path]
    back = DumpContent.from_spool(*spool_get(path))
    assert_same_content(content, back)
    assert back.cycle_id == content.cycle_id
    with pytest.raises(ArchiveError, match="does not exist"):
        spool_get(tmp_path / "spool" / "nope.npz")


# -- retention and disk ---------------------------------------------------------------------------------
def test_prune_removes_the_oldest_first(tmp_path):
    now = time.time()
    files = []
    for i in range(6):                                  # day folders, 1 MB each, 0..5 days old, oldest first
        p = tmp_path / f"2026-03-0{i + 1}" / f"d{i}.h5"
        p.parent.mkdir()
        p.write_bytes(b"\0" * 1_000_000)
        age_days = 5 - i
        os.utime(p, (now - age_days * 86400 - 60, now - age_days * 86400 - 60))
        files.append(p)
    temp = tmp_path / "2026-03-01" / ".d9.h5.123.abcdef01.tmp"
    temp.write_bytes(b"x")
    assert prune_dumps(tmp_path, keep_days=3.5, max_total_gb=None) == files[:2]     # 5 and 4 days old
    assert not files[0].exists() and files[2].exists()
    assert temp.exists() and (tmp_path / "2026-03-01").exists()                     # not a dump; folder kept
    assert not (tmp_path / "2026-03-02").exists()                                   # emptied folder removed
    assert prune_dumps(tmp_path, keep_days=None, max_total_gb=0.0025) == files[2:4]  # 4 MB -> 2 MB
    assert [p.exists() for p in files] == [False] * 4 + [True] * 2
    assert prune_dumps(tmp_path, keep_days=30, max_total_gb=1) == []


def test_disk_watch(tmp_path, monkeypatch):
    ok, free = disk_ok(tmp_path / "not" / "yet" / "made", 0.0)
    assert ok and free > 0
    ok, free2 = disk_ok(tmp_path, 1e9)                   # an exabyte: never
    assert not ok and free2 == pytest.approx(free, rel=0.1)


def test_schema_1_dumps_are_still_read(dump_file, small_config):
    """Schema 2 only added non-square display pixels: a version 1 file (square pixels) reads as before."""
    path, content = dump_file
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = np.int64(1)
    back = read_dump(path)
    assert back.schema_version == 1
    assert back.station_geometry().to_dict() == small_config.geometry.to_dict()


def test_non_square_display_pixels_round_trip(small_config, tmp_path):
    import dataclasses

    from sofast_station.geometry import ScreenSpec

    screen = ScreenSpec(1920, 1080, 0.00027, 0.0002703)
    content = dataclasses.replace(synthetic_content(small_config), geometry=dataclasses.replace(
        small_config.geometry, screen=screen).to_dict())
    path = tmp_path / "n.h5"
    write_dump(path, content)
    with h5py.File(path) as f:
        assert "pitch_m" not in f["geometry/screen"] and f["geometry/screen/pitch_y_m"][()] == 0.0002703
    back = read_dump(path).station_geometry().screen
    assert back == screen and back.height_m == 1080 * 0.0002703 and back.width_m == 1920 * 0.00027


def test_a_dump_whose_fringe_definition_names_no_patterns_says_so(small_config, tmp_path, monkeypatch, caplog):
    """The frames are dumped whatever the fringe definition (it may be what is wrong), and the log says that
    their pattern names were replaced."""
    import logging

    from sofast_station.archive.dumps.content import DumpContent

    content = synthetic_content(small_config)

    def unusable(self):
        raise ValueError("periods_x must increase")

    monkeypatch.setattr(DumpContent, "patterns", property(unusable))
    path = tmp_path / "d.h5"
    with caplog.at_level(logging.WARNING, logger="sofast_station.archive.dumps"):
        write_dump(path, content)
    n = content.frames_cropped.shape[0]
    assert f"gives no pattern names (ValueError: periods_x must increase); its frames are named frame 0..{n - 1}" \
        in caplog.text
    import h5py
    with h5py.File(path, "r") as f:
        names = [v.decode() if isinstance(v, bytes) else str(v) for v in f["capture/patterns"][()]]
    assert names == [f"frame {i}" for i in range(n)]


def test_a_measured_screen_travels_in_the_dump_and_reanalyses_exactly(small_capture, tmp_path):
    """A capture measured with a screen record in force (a bowed, twisted panel, its uncertainty fields): the
    dump keeps the measured shape (geometry/measured_screen), and reanalysing it gives every figure exactly
    as archived; the same frames with the flat screen give others (the shape was used)."""
    import copy
    import dataclasses

    from sofast_station.archive.dumps import DumpContent
    from sofast_station.geometry import MeasuredScreen
    from sofast_station.measure.analysis import analyse
    from sofast_station.measure.screen_shape import ScreenShape, parameter_names, shape_modes
    from sofast_station.result.record import build_record

    station, frames, distance, flat_analysis, _ = small_capture
    cfg = station.config
    scr = cfg.geometry.screen
    names = parameter_names("distorted3d")
    p = np.zeros(len(names))
    p[0] = 2e-3
    p[names.index("z:2,0")], p[names.index("z:1,1")] = -8e-4, 3e-4
    shape = ScreenShape("distorted3d", scr.width_m, scr.height_m, p)
    uv, pts = shape.grid(33, 19)
    modes, _ = shape_modes(shape, np.diag(np.full(len(names), 1e-10)), uv, max_modes=2)
    measured = MeasuredScreen(uv / [scr.pitch_x_m, scr.pitch_y_m], pts, modes, "screen-test-001")
    geometry = dataclasses.replace(cfg.geometry, measured_screen=measured)
    analysis = analyse(frames, cfg.fringes, geometry, cfg.design, distance, cfg.analysis)
    assert analysis.figures["focal_length_x_m"] != flat_analysis.figures["focal_length_x_m"]
    measured_station = copy.copy(station)
    measured_station.config = dataclasses.replace(cfg, geometry=geometry)
    record = build_record(measured_station.record_head("SIM-MS"), figures=analysis.figures, timings={"total": 1.0})
    crop, box, full = crop_to_facet(frames, cfg.analysis.mask_threshold_dn)
    content = DumpContent.from_station(measured_station, cycle_id="ms-1", record=record, frames_cropped=crop,
                                       crop_box=box, full_shape=full, measured_distance_m=distance)
    write_dump(tmp_path / "ms.h5", content)
    with h5py.File(tmp_path / "ms.h5") as f:
        assert f["geometry/measured_screen/modes_m"].shape == (2, uv.shape[0], 3)
    back = read_dump(tmp_path / "ms.h5")
    assert back.station_geometry().measured_screen == measured
    again = back.analyse()
    figures = {k: v for k, v in again.figures.items() if k != "timings_s"}
    assert json_ready(figures) == {k: back.record[k] for k in figures}


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_frames_inflated_on_two_threads_are_what_hdf5_reads(tmp_path, dtype):
    """reader._read_frames reads each frame's chunk as stored and inflates it itself (issue 32: half the
    read of a full-resolution dump): the same bits as HDF5's own read for the writer's layout (one frame
    per chunk, shuffled and deflated) with and without the shuffle; other layouts go to HDF5; a damaged
    chunk is a DumpError naming the frame."""
    import h5py

    from sofast_station.archive.dumps.reader import _read_frames

    rng = np.random.default_rng(7)
    frames = rng.integers(0, np.iinfo(dtype).max, size=(4, 37, 53), endpoint=True).astype(dtype)
    path = tmp_path / "frames.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("written", data=frames, chunks=(1, 37, 53), compression="gzip", compression_opts=4,
                         shuffle=True)
        f.create_dataset("no_shuffle", data=frames, chunks=(1, 37, 53), compression="gzip")
        f.create_dataset("other_chunks", data=frames, chunks=(2, 37, 53), compression="gzip", shuffle=True)
        f.create_dataset("plain", data=frames)
    with h5py.File(path, "r") as f:
        for name in ("written", "no_shuffle", "other_chunks", "plain"):
            got = _read_frames(f[name], path)
            assert got.dtype == dtype and np.array_equal(got, f[name][()]) and np.array_equal(got, frames), name
        offset = f["written"].id.get_chunk_info(2).byte_offset
    raw = bytearray(path.read_bytes())
    raw[offset + 10:offset + 30] = bytes(20)
    path.write_bytes(bytes(raw))
    with h5py.File(path, "r") as f, pytest.raises(DumpError, match="frame 2"):
        _read_frames(f["written"], path)
