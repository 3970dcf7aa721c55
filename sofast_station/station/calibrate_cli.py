"""``sofast-station calibrate ...``: the calibration routines (:mod:`sofast_station.calibrate`) on the command
line. The commands open the station (its devices, its configuration) and run a routine on it, so they live
with the station's other commands; the routines themselves see only the device protocols.

``register(subparsers)`` adds the ``calibrate`` command and its subcommands to the main parser::

    sofast-station calibrate radiometric [--config station.toml] [--ramp-step 5] [--frames 2] [--no-plot]
    sofast-station calibrate camera IMAGES... --board chessboard --squares 10x7 --square-mm 30
    sofast-station calibrate geometry [--reference reference.toml]
    sofast-station calibrate screen [--views 8] [--model auto]
    sofast-station calibrate pose [--target reference_mirror.toml] [--placements 4]
    sofast-station calibrate commission
    sofast-station calibrate marks
    sofast-station calibrate confirm-geometry [--reference reference.toml]
    sofast-station calibrate status
    sofast-station calibrate camera-position PHOTO --markers CSV [--camera station|record|handheld|FILE]
    sofast-station calibrate dots PHOTO... --origin COLUMN,ROW... --camera CAMERA --markers CSV
    sofast-station calibrate screen-data DISTORTION.h5 --markers CSV --point-pairs CSV --projection FILE.h5

Every command ends its summary with a ``verdict:`` line.

Progress goes to the log (stderr); the summary to stdout (``--json``: one JSON object instead).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys

from .. import __version__
from ..commands import add_command, add_config_option, positive_int
from ..errors import ConfigError
from ..files import json_ready

log = logging.getLogger(__name__)


def _squares(text: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--squares must look like 10x7 (squares across, down), got {text!r}") \
            from None
    return a, b


def _line_stopped(fn):
    """Run the calibration command *fn* only while no line runs on the station's data folder, and keep the line
    from starting until it is done (the data folder's lock, as ``run`` takes it): a record written while the line
    runs would be named by the page while the line still measured with the one it had loaded."""
    import functools

    @functools.wraps(fn)
    def guarded(args) -> int:
        from ..files import station_data_dir
        from .service import DataDirLock, StationLocked

        data_dir = station_data_dir(args.config)
        if data_dir is None:
            return fn(args)                     # the station file cannot be read: load_config says why
        try:
            lock = DataDirLock(data_dir, what="calibration")
        except StationLocked as exc:
            if exc.holder_what in (None, "station"):
                raise StationLocked(
                    f"the line is running on {data_dir} (process {exc.holder or '?'}): a calibration now would change "
                    "the records it measures with while it goes on with the old ones. Stop the line (Ctrl-C in its "
                    "window, or stop its service), calibrate, then start it again: it takes the newest records at its "
                    "start", exc.holder, exc.holder_what) from None
            raise
        try:
            return fn(args)
        finally:
            lock.release()
    return guarded


def _emit(args, data: dict, text: str) -> None:
    if getattr(args, "json", False):
        json.dump(json_ready(data), sys.stdout, indent=1, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(text)


def cmd_radiometric(args) -> int:
    from ..config import load_config
    from .commissioning import run_radiometric

    config = load_config(args.config)
    overrides = {k: v for k, v in (("ramp_step", args.ramp_step), ("frames_per_level", args.frames),
                                   ("max_exposure_periods", args.max_exposure_periods),
                                   ("max_frames_per_level", args.max_frames), ("gain_max", args.gain_max))
                 if v is not None}
    step = run_radiometric(config, seed=args.seed, noise=not args.noise_free, plot=not args.no_plot,
                           overrides=overrides)
    _emit(args, {k: v for k, v in step.data.items() if k != "headline"} | {"verdict": step.verdict}, step.summary)
    return 0


def cmd_camera(args) -> int:
    from ..config import load_config
    from pathlib import Path

    from ..calibrate.camera import BoardSpec, calibrate_camera_images, save_camera, summary_text

    config = load_config(args.config, use_camera_record=False)     # the record may not exist yet: we make it
    if args.board == "charuco" and args.marker_mm is None:
        raise ConfigError("a ChArUco board needs --marker-mm (the marker side)")
    board = BoardSpec(args.board, args.squares[0], args.squares[1], args.square_mm / 1000.0,
                      (args.marker_mm or 0.0) / 1000.0, args.dictionary, args.legacy)
    if args.fix_k2 and args.k3:
        raise ConfigError("--fix-k2 holds k3 at 0 too: give --fix-k2 or --k3, not both")
    # the files are read in the threads that search them (one progress line per image on the log)
    cal = calibrate_camera_images([(str(p), Path(p)) for p in args.images], board, fix_k3=not args.k3,
                                  min_images=args.min_images, max_edge_width_px=args.max_edge_width, fix_k2=args.fix_k2)
    source = f"sofast-station {__version__} calibrate camera, {len(args.images)} image(s)"
    path = save_camera(config.data_dir, cal, source, "handheld" if args.handheld else "camera",
                       station=config.identity)
    cam = config.geometry.camera
    if args.handheld:
        use = "calibrate screen uses this record for the second camera (the newest handheld record)."
        _emit(args, {"path": str(path), "rms_px": cal.rms_px, "camera": cal.intrinsics.to_dict(),
                     "std_intrinsics": cal.std_intrinsics, "verdict": cal.verdict, "quality": cal.quality,
                     "images": [r.to_dict() for r in cal.images], "use": use},
              summary_text(cal, path) + "\n" + use + f"\nverdict: {cal.verdict.upper()}")
        return 0
    if cal.intrinsics.shape != cam.shape:
        log.warning("the images are %d x %d, the station's camera [camera] is %d x %d", cal.intrinsics.width_px,
                    cal.intrinsics.height_px, cam.width_px, cam.height_px)
    if config.raw.get("camera", {}).get("intrinsics") == "record":
        use = "The station uses this record from its next start ([camera] intrinsics = \"record\")."
    else:
        use = ("The station still uses the [camera] table of station.toml; set [camera] intrinsics = \"record\" "
               "to use the newest camera record instead.")
    _emit(args, {"path": str(path), "rms_px": cal.rms_px, "camera": cal.intrinsics.to_dict(),
                 "std_intrinsics": cal.std_intrinsics, "verdict": cal.verdict, "quality": cal.quality,
                 "images": [r.to_dict() for r in cal.images], "use": use},
          summary_text(cal, path) + "\n" + use + f"\nverdict: {cal.verdict.upper()}")
    return 0


def cmd_geometry(args) -> int:
    from ..config import load_config
    from .commissioning import run_geometry

    step = run_geometry(load_config(args.config), reference=args.reference, seed=args.seed, noise=not args.noise_free)
    _emit(args, {k: v for k, v in step.data.items() if k != "headline"} | {"verdict": step.verdict}, step.summary)
    return 0 if step.verdict == "pass" else 1


def _emit_step(args, step) -> int:
    """Print a commissioning step (its summary ends with its verdict; --json: its data, verdict and summary);
    the exit status: 1 when it was refused (no record), else 0."""
    _emit(args, {k: v for k, v in step.data.items() if k != "headline"} | {"verdict": step.verdict,
                                                                        "summary": step.summary}, step.summary)
    return 1 if step.verdict == "refused" else 0


def cmd_screen(args) -> int:
    from ..config import load_config
    from .commissioning import run_screen

    return _emit_step(args, run_screen(load_config(args.config), views=args.views, model=args.model, seed=args.seed,
                                       noise=not args.noise_free))


def cmd_pose(args) -> int:
    from ..config import load_config
    from .commissioning import run_pose

    return _emit_step(args, run_pose(load_config(args.config), placements=args.placements, target=args.target,
                                     seed=args.seed, noise=not args.noise_free))


def cmd_commission(args) -> int:
    from ..config import load_config
    from .commissioning import commission, commission_steps, commission_summary

    config = load_config(args.config)
    steps, verdict = commission(args.config, seed=args.seed, noise=not args.noise_free, reference=args.reference,
                                target=args.target)
    text = "\n\n".join(s.summary for s in steps) + "\n\n" + commission_summary(
        config.name, steps, verdict, total=len(commission_steps(config)))
    _emit(args, {"verdict": verdict, "steps": [{"name": s.name, "verdict": s.verdict, "path": s.path,
                                                "summary": s.summary} for s in steps]}, text)
    return 0 if verdict in ("pass", "warn") else 1


def cmd_marks(args) -> int:
    from ..config import load_config
    from .commissioning import run_marks

    return _emit_step(args, run_marks(load_config(args.config), seed=args.seed, noise=not args.noise_free))


def cmd_confirm_geometry(args) -> int:
    from ..config import load_config
    from .commissioning import confirm_geometry

    steps = confirm_geometry(load_config(args.config), reference=args.reference, seed=args.seed,
                             noise=not args.noise_free)
    verdict = "pass" if steps[-1].name == "marks" and steps[-1].verdict == "pass" else "fail"
    text = "\n\n".join(s.summary for s in steps) + f"\n\nGeometry confirmation: {verdict.upper()}\nverdict: " \
        f"{verdict.upper()}"
    _emit(args, {"verdict": verdict, "steps": [{"name": s.name, "verdict": s.verdict, "path": s.path,
                                                "summary": s.summary} for s in steps]}, text)
    return 0 if verdict == "pass" else 1


def cmd_status(args) -> int:
    from ..config import camera_from_record, load_config
    from ..calibrate.settings import calibration_settings
    from ..calibrate.store import KINDS, check_age, list_records, select_radiometric

    config = load_config(args.config, use_camera_record=False)  # reports on records
    policy, _ = calibration_settings(config)
    status = select_radiometric(config)
    lines = [f"Calibration of {config.name} (data in {config.data_dir})", f"  in force: {status.describe}"]
    try:
        check_age(status, dataclasses.replace(policy, stale="warn"))
    except ConfigError as exc:
        status.warnings.append(str(exc))
    if status.age_h is not None:
        lines.append(f"  age {status.age_h:.1f} h (stale after {policy.max_age_h:g} h; stale records "
                     f"{'refused' if policy.stale == 'refuse' else 'warned about'})")
    camera_source = config.raw.get("camera", {}).get("intrinsics", "station.toml")
    if camera_source == "record":
        try:
            camera_in_force = camera_from_record(config.data_dir, config.geometry.camera,
                                                 f"{config.path} [camera]", config.identity)[1]["path"].name
        except ConfigError as exc:
            camera_in_force = None
            status.warnings.append(str(exc))
        lines.append(f"  camera intrinsics: from the newest camera record ({camera_in_force or 'none usable'})")
    else:
        camera_in_force = "station.toml [camera]"
        lines.append("  camera intrinsics: station.toml [camera] (set intrinsics = \"record\" to use a camera record)")
    commissioned = config.commissioned or {}
    if commissioned:
        lines.append("  geometry: " + ", ".join(f"{k} record {commissioned[k]['record_id']}" for k in ("screen", "pose")
                                                if k in commissioned) + " ([calibration] geometry = \"records\")")
        status.warnings.extend(commissioned.get("warnings", []))
    elif config.raw.get("calibration", {}).get("geometry") == "station.toml":
        lines.append("  geometry: station.toml [screen] and [layout] ([calibration] geometry = \"station.toml\")")
    else:
        lines.append("  geometry: station.toml [screen] and [layout] "
                     "(no screen or pose record: run calibrate commission)")
    lines += [f"  ! {w}" for w in status.warnings]
    data = {"in_force": status.describe, "age_h": status.age_h, "warnings": status.warnings,
            "camera_intrinsics": camera_in_force, "records": {},
            "geometry": {k: v for k, v in commissioned.items() if k != "warnings"}}
    for kind in KINDS:
        records = list_records(config.data_dir, kind)
        data["records"][kind] = [str(p) for p in records]
        lines.append(f"  {kind}: {len(records)} record(s)" + (f", newest {records[-1].name}" if records else ""))
    lines.append(f"verdict: {'WARN (see the warnings above)' if status.warnings else 'OK'}")
    data["verdict"] = "warn" if status.warnings else "ok"
    _emit(args, data, "\n".join(lines))
    return 0


def _pair(option: str):
    def parse(text: str) -> tuple[float, float]:
        try:
            a, b = (float(v) for v in text.replace(":", ",").split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"{option} must be two numbers, e.g. 1201,828; got {text!r}") from None
        return a, b
    return parse


def _photo_camera(spec: str, config) -> tuple:
    """The camera of the photographs: ``station`` (the station's camera in force), ``record`` (the newest
    camera record), ``handheld`` (the newest handheld record), or a file: a camera record (JSON) or OpenCSP's
    Camera (HDF5). Returns (intrinsics, name, standard deviations (9,) or None, note or None)."""
    import numpy as np

    from ..calibrate.camera import load_camera_record
    from ..calibrate.store import newest_record_path, record_dir

    def from_record(path):
        camera, record = load_camera_record(path)
        std = record.get("std_intrinsics")
        vector = None
        if isinstance(std, dict):
            try:
                vector = np.array([std["fx"], std["fy"], std["cx"], std["cy"], *std["distortion"]], np.float64)
            except (KeyError, TypeError, ValueError):
                vector = None
        return camera, str(path), vector, None

    if spec in ("record", "handheld"):
        path = newest_record_path(config.data_dir, "camera" if spec == "record" else "handheld", config.identity)
        if path is None:
            raise ConfigError(f"--camera {spec}: there is no {spec if spec == 'handheld' else 'camera'} record in "
                              f"{record_dir(config.data_dir, 'camera' if spec == 'record' else 'handheld')}: run "
                              f"'sofast-station calibrate camera{' --handheld' if spec == 'handheld' else ''} "
                              "IMAGES...' first, or give the camera's file")
        return from_record(path)
    if spec == "station":
        if config.raw.get("camera", {}).get("intrinsics") == "record":
            path = newest_record_path(config.data_dir, "camera", config.identity)
            if path is not None:
                return from_record(path)
        return config.geometry.camera, f"{config.path} [camera]", None, None
    from pathlib import Path

    path = Path(spec)
    if path.suffix.lower() in (".h5", ".hdf5"):
        from ..interop.opencsp_calibration import opencsp_camera

        camera, note = opencsp_camera(path)
        return camera, str(path), None, note
    if path.suffix.lower() == ".json":
        return from_record(path)
    raise ConfigError(f"--camera {spec}: give station, record, handheld, a camera record (.json) or OpenCSP's Camera "
                      "file (.h5)")


def _photo_inputs(args) -> tuple:
    """What both photogrammetric calibrations read first: the station file, the photographs' camera (with its
    standard deviations and a note on OpenCSP's matrix, logged) and the marker table."""
    from ..config import load_config
    from ..calibrate.photo_inputs import read_marker_table

    config = load_config(args.config, use_camera_record=False)
    camera, camera_name, std, note = _photo_camera(args.camera, config)
    if note:
        log.info("%s", note)
    return config, camera, camera_name, std, note, read_marker_table(args.markers)


def cmd_camera_position(args) -> int:
    from ..calibrate.camera_position import calibrate_camera_position, save_camera_position, summary_text
    from ..calibrate.photo_inputs import read_photo

    config, camera, camera_name, std, note, table = _photo_inputs(args)
    image = read_photo(args.photo)
    log.info("camera position from %s: camera %s, %d marker(s) in %s", args.photo, camera_name, len(table.ids),
             args.markers)
    result = calibrate_camera_position(image, args.photo, camera, camera_name, table, intrinsics_std=std,
                                       dictionary=args.dictionary, refine=args.corners, min_markers=args.min_markers)
    source = f"sofast-station {__version__} calibrate camera-position {args.photo}"
    inputs = {"photo": str(args.photo), "camera": camera_name, "camera_note": note, "markers": str(args.markers)}
    path = save_camera_position(config.data_dir, result, source, inputs, station=config.identity)
    _emit(args, {"path": str(path), **result.to_dict(), "inputs": inputs}, summary_text(result, path))
    return 0


def cmd_dots(args) -> int:
    from ..calibrate.dot_locations import calibrate_dots, save_dots, summary_text
    from ..calibrate.photo_inputs import read_photo

    config, camera, camera_name, _, note, table = _photo_inputs(args)
    if len(args.origin) != len(args.photos):
        raise ConfigError(f"give one --origin COLUMN,ROW per photograph, in their order: {len(args.photos)} "
                          f"photograph(s), {len(args.origin)} origin(s)")
    photos = [(str(p), read_photo(p)) for p in args.photos]
    cal = calibrate_dots(photos, args.origin, camera, camera_name, table, dictionary=args.dictionary,
                         refine=args.corners, dark=not args.light_dots, dot_area_px=args.dot_area,
                         min_circularity=args.min_circularity, min_views=args.min_views,
                         progress=lambda text: log.info("%s", text))
    source = f"sofast-station {__version__} calibrate dots, {len(photos)} photograph(s)"
    inputs = {"photos": [str(p) for p in args.photos], "origins_px": [list(o) for o in args.origin],
              "camera": camera_name, "camera_note": note, "markers": str(args.markers)}
    path = save_dots(config.data_dir, cal, source, inputs, station=config.identity)
    text = summary_text(cal, path)
    data = {"path": str(path), "verdict": cal.verdict, "reasons": cal.reasons, "dots_located":
            int(cal.locations.located.sum()), "sigma_px": cal.solution.sigma_px, "rms_px": cal.solution.rms_px,
            "photos": [p.to_dict() for p in cal.photos], "inputs": inputs}
    if args.opencsp_out:
        from ..interop.opencsp_calibration import write_dot_locations

        write_dot_locations(args.opencsp_out, cal.locations)
        text += f"\nOpenCSP's DotLocationsFixedPattern file: {args.opencsp_out}"
        data["opencsp_out"] = str(args.opencsp_out)
    if args.compare:
        data["compare"], lines = _compare_dots(cal.locations, args.compare)
        text = text.replace("\nverdict:", "\n" + lines + "\nverdict:")
    _emit(args, data, text)
    return 0


def _compare_dots(ours, path) -> tuple[dict, str]:
    """Our dots against OpenCSP's file *path*, dot by dot where both located one: per-axis RMS and largest
    difference, and how many lie within our U."""
    import numpy as np

    from ..interop.opencsp_calibration import read_dot_locations

    theirs = read_dot_locations(path)
    xs = np.intersect1d(ours.x_index, theirs.x_index)
    ys = np.intersect1d(ours.y_index, theirs.y_index)
    a = ours.xyz_m[np.ix_(ys - ours.y_index[0], xs - ours.x_index[0])]
    u = ours.xyz_U_m[np.ix_(ys - ours.y_index[0], xs - ours.x_index[0])]
    b = theirs.xyz_m[np.ix_(ys - theirs.y_index[0], xs - theirs.x_index[0])]
    both = np.all(np.isfinite(a), axis=2) & np.all(np.isfinite(b), axis=2)
    d, u = (a - b)[both], u[both]
    if d.size == 0:
        raise ConfigError(f"{path} locates none of the dots this calibration located: another target, or other "
                          "indices?")
    rms, big = np.sqrt(np.mean(d ** 2, axis=0)), np.max(np.abs(d), axis=0)
    within = np.mean(np.abs(d) <= u, axis=0)
    data = {"file": str(path), "dots": int(both.sum()), "rms_m": rms.tolist(), "max_m": big.tolist(),
            "within_U": within.tolist(), "median_U_m": np.median(u, axis=0).tolist()}
    line = (f"  against {path}: {int(both.sum())} dots; difference RMS x {1000 * rms[0]:.3f}, y {1000 * rms[1]:.3f}, "
            f"z {1000 * rms[2]:.3f} mm (largest {1000 * big[0]:.3f}, {1000 * big[1]:.3f}, {1000 * big[2]:.3f} mm); "
            f"within our U: {100 * within[0]:.0f} %, {100 * within[1]:.0f} %, {100 * within[2]:.0f} % (that file's own "
            "uncertainty is not in U)")
    return data, line


def cmd_screen_data(args) -> int:
    import numpy as np

    from ..calibrate.photo_inputs import read_marker_table
    from ..interop.opencsp import screen_nodes
    from ..interop.opencsp_calibration import (check_screen_data, read_image_projection, read_point_pairs,
                                               read_screen_distortion)

    fractions, xyz = read_screen_distortion(args.data)
    table = read_marker_table(args.markers)
    pairs = read_point_pairs(args.point_pairs)
    projection = read_image_projection(args.projection)
    display = screen_nodes(args.display) if args.display else None
    log.info("checking %s (%d points) against %d fiducial marker(s)", args.data, len(fractions), len(pairs))
    out = check_screen_data(fractions, xyz, table, pairs, projection, display)
    mm = lambda v: ", ".join(f"{1000 * x:.3f}" for x in v)   # noqa: E731
    fid = out["fiducials"]
    lines = [f"Screen distortion data {args.data}: {out['nodes']} points",
             f"  our screen model on the points returns them to {max(out['reproduction']['max_m']) * 1e9:.2g} nm",
             f"  built on every other node ({out['holdout']['nodes_used']}), at the {out['holdout']['count']} others: "
             f"RMS (x, y, z) {mm(out['holdout']['rms_m'])} mm, largest {mm(out['holdout']['max_m'])} mm",
             f"  at the {len(fid['pairs'])} calibration fiducials, the data against the surveyed marker corners: RMS "
             f"{mm(fid['rms_m'])} mm, largest {mm(fid['max_m'])} mm"]
    lines += [f"    fiducial {r['fiducial']} / marker {r['marker']}: {mm(r['difference_m'])} mm" for r in fid["pairs"]]
    verdict = "pass"
    if max(fid["max_m"][:2]) > args.tolerance_mm / 1000.0:
        verdict = "warn"
        lines.append(f"    - a fiducial is more than {args.tolerance_mm:g} mm (in x or y) from its marker: is the "
                     "point pairs file for this data, and the marker table the one the calibration used?")
    if "display" in out:
        d = out["display"]
        m = np.asarray(d["map"])
        lines.append(f"  against {args.display} over the active area: directly RMS (x, y) "
                     f"{mm(d['direct']['rms_m'])} mm, "
                     f"largest {mm(d['direct']['max_m'])} mm; after the best affine map (scale x {m[0, 0]:.5f}, y "
                     f"{m[1, 1]:.5f}) RMS {mm(d['affine']['rms_m'])} mm, largest {mm(d['affine']['max_m'])} mm")
    lines.append(f"verdict: {verdict.upper()}")
    _emit(args, {**out, "verdict": verdict, "file": str(args.data)}, "\n".join(lines))
    return 0


def register(subparsers, default_config_path: str | None = None) -> argparse.ArgumentParser:
    """Add ``calibrate`` and its subcommands to the main parser's *subparsers*.

    Each subcommand sets ``func`` (called with the parsed arguments; returns the exit status; raises
    :class:`~sofast_station.errors.StationError` for the main program to report).
    """
    cal = add_command(
        subparsers, "calibrate",
        help="calibration routines: radiometric (daily), camera, geometry, screen, pose, commission, marks, "
             "confirm-geometry, status, camera-position, dots, screen-data",
        description="""
            The station's calibrations (docs/calibration.md). Each writes a dated record (JSON, never
            overwritten) under data_dir/calibration/; inspection uses the newest and warns or refuses when
            it is stale, as [calibration] in the station file says. Run 'radiometric' every morning after
            the camera's warm-up; 'camera' and 'geometry' when the optics or the assembly change;
            'commission' (radiometric, screen, pose, geometry) when the station is built or its screen or
            camera was moved.""")
    sub = cal.add_subparsers(dest="calibrate_command", required=True, metavar="SUBCOMMAND", title="subcommands")

    def common(p, simulated=True):
        add_config_option(p, default_config_path)
        p.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")
        if simulated:
            p.add_argument("--seed", type=int, default=None,
                           help="simulated station: noise seed (default: the [simulation] seed of the station file)")
            p.add_argument("--noise-free", action="store_true", help="simulated station: no sensor noise")

    rad = add_command(
        sub, "radiometric", help="the daily radiometric calibration: exposure, gain, floor, response, lookup table, "
                                 "display latency",
        description="""
            The morning routine, after the camera's warm-up: find the display latency and a flicker-safe
            exposure, set the gain so a full-white screen reads about 250 of 255 at its brightest, ramp the
            display 0..255, find the floor, fit the end-to-end response polynomial and its linearising
            lookup table, and store them as a dated record (with a PNG of the response curve). Settings not
            given here come from the [calibration] routine table of the station file.""")
    common(rad)
    rad.add_argument("--ramp-step", type=int, default=None, metavar="N",
                     help="command step of the 0..255 ramp (default: the station file's, else 5)")
    rad.add_argument("--frames", type=int, default=None, metavar="N",
                     help="fewest frames averaged per ramp level; more are taken, up to the station file's "
                          "max_frames_per_level, when the room light flickers (default: the station file's, else 2)")
    rad.add_argument("--max-exposure-periods", type=int, default=None, metavar="N",
                     help="longest exposure in display refresh periods (default: the station file's, else 2)")
    rad.add_argument("--max-frames", type=int, default=None, metavar="N",
                     help="most frames averaged per ramp level when the room light flickers (default: the "
                          "station file's max_frames_per_level, else 8)")
    rad.add_argument("--gain-max", type=float, default=None, metavar="G",
                     help="highest camera gain the gain search may use (default: the station file's gain_max)")
    rad.add_argument("--no-plot", action="store_true", help="do not write the PNG plot of the response")
    rad.set_defaults(func=_line_stopped(cmd_radiometric))

    cam = add_command(
        sub, "camera", help="camera intrinsics and distortion from chessboard or ChArUco images",
        description="""
            Calibrate the camera's intrinsics (focal length, principal point) and distortion from images of
            a chessboard or ChArUco board, and store them as a dated camera record. Each image is judged
            as it is searched (one line of progress per image); a chessboard partly out of view is used
            for the part in view; blurred images and images where the board is not found are reported
            and skipped. The calibration judges itself
            (pass / warn / refused) from the reprojection RMS, the parameters' standard deviations and how
            the views cover the image; a refused calibration (parameters not determined) writes no record
            and says what to do (docs/calibration.md). The station uses the record when
            [camera] intrinsics = "record" in the station file.""")
    common(cam, simulated=False)
    cam.add_argument("images", nargs="+", metavar="IMAGE", help="board images (any format OpenCV reads)")
    cam.add_argument("--board", choices=("chessboard", "charuco"), default="chessboard", help="the board's kind")
    cam.add_argument("--squares", type=_squares, required=True, metavar="NxM",
                     help="squares (not inner corners) across x down, e.g. 10x7 for a board of 9 x 6 inner "
                          "corners (required)")
    cam.add_argument("--square-mm", type=float, required=True, metavar="MM", help="side of a square, mm (required)")
    cam.add_argument("--marker-mm", type=float, default=None, metavar="MM",
                     help="ChArUco: side of a marker, mm (required for ChArUco)")
    cam.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco: OpenCV marker dictionary")
    cam.add_argument("--legacy", action="store_true", help="ChArUco: a board made by OpenCV before 4.6")
    cam.add_argument("--k3", action="store_true", help="also fit k3 (held at 0 otherwise)")
    cam.add_argument("--fix-k2", action="store_true",
                     help="hold k2 (and k3) at 0: for a long lens whose small distortion the views cannot determine")
    cam.add_argument("--min-images", type=int, default=5, metavar="N", help="fewest usable images")
    cam.add_argument("--max-edge-width", type=float, default=4.0, metavar="PX",
                     help="reject images whose edges are wider than this many pixels (blurred)")
    cam.add_argument("--handheld", action="store_true",
                     help="the images are of the second camera of 'calibrate screen': its record goes to "
                          "data_dir/calibration/handheld/ and is never taken for the station's camera")
    cam.set_defaults(func=_line_stopped(cmd_camera))

    geo = add_command(
        sub, "geometry", help="measure a reference facet of known shape and report the geometry error",
        description="""
            Check the station's geometry (camera pose, screen pose, distance): measure a reference facet of
            known shape and compare the measured focal lengths and placement with the reference's CERTIFIED
            figures (its certificate, not its design). Writes a dated geometry record stating the fixture
            pose and distance it determines, with their uncertainties (the budget uses them); exits with 1
            when the error is beyond the reference's tolerance.""")
    common(geo)
    geo.add_argument("--reference", default=None, metavar="FILE",
                     help="the reference facet's certificate ([reference] table: certified focal lengths, "
                          "placement and their uncertainties); the simulated station's twin truth by default")
    geo.set_defaults(func=_line_stopped(cmd_geometry))

    scr = add_command(
        sub, "screen", help="the screen's shape and pitch, from views of a second camera (commissioning)",
        description="""
            Measure the screen's shape and pixel pitch (docs/calibration.md#commissioning-the-geometry): a
            calibrated second camera, held or on a tripod about a metre from the screen, takes views from
            around it while the screen shows fiducials and fringes, a certified scale board fixed beside the
            screen. Fits a flat, a distorted 2-D and a distorted 3-D model and keeps the simplest the
            residuals allow; judges itself (pass / warn / refused: no record when the parameters are not
            determined, with what to do) and writes a dated screen record, which the analysis then uses.
            On a real station the technician is asked for each view; the camera is [devices]
            handheld_camera, its calibration the newest 'calibrate camera --handheld' record or
            [calibration.screen] camera.""")
    common(scr)
    scr.add_argument("--views", type=positive_int, default=None, metavar="N",
                     help="views to take (default: [calibration.screen] views, else 8)")
    scr.add_argument("--model", choices=("auto", "flat", "distorted2d", "distorted3d"), default=None,
                     help="the shape model (default: [calibration.screen] model, else auto: the simplest the "
                          "residuals allow)")
    scr.set_defaults(func=_line_stopped(cmd_screen))

    pose = add_command(
        sub, "pose", help="the camera's pose against the screen, and the fixture's, from a reference mirror",
        description="""
            Measure the camera's pose against the screen (6 degrees of freedom) and the fixture's pose
            (docs/calibration.md#the-cameras-pose): the reference mirror, a flat front-surface mirror in a
            certified printed ChArUco frame, is seated in the fixture and then tilted by shims; at each
            placement the station captures its fringes and reads the range finder. Uses the screen record
            in force (run 'calibrate screen' first). Judges itself (pass / warn / refused) and writes a
            dated pose record, which the analysis then uses with its stated uncertainties.""")
    common(pose)
    pose.add_argument("--target", default=None, metavar="FILE",
                      help="the reference mirror's certificate ([mirror] table; default: [calibration.pose] target)")
    pose.add_argument("--placements", type=positive_int, default=None, metavar="N",
                      help="placements to take (default: [calibration.pose] placements, else 4)")
    pose.set_defaults(func=_line_stopped(cmd_pose))

    com = add_command(
        sub, "commission", help="the whole commissioning: radiometric, screen, pose and geometry, one summary",
        description="""
            Commission the station: the radiometric calibration (with its display-latency self-test),
            then 'calibrate screen', 'calibrate pose' and 'calibrate geometry' (the reference facet checks
            the whole chain), in order, each with the records the earlier ones wrote. Stops at a step that
            is refused or fails, and prints every step's summary and one commissioning summary ending with
            the verdict.""")
    common(com)
    com.add_argument("--reference", default=None, metavar="FILE",
                     help="the reference facet's certificate for the geometry check (the twin's truth by default "
                          "on the simulated station)")
    com.add_argument("--target", default=None, metavar="FILE", help="the reference mirror's certificate")
    com.set_defaults(func=_line_stopped(cmd_commission))

    mk = add_command(
        sub, "marks", help="the fixture's marks: their places now become the commissioned ones",
        description="""
            Show white, grab a few frames and find every fixture mark ([marks] in the station file) near where
            the geometry in force puts it; their mean places become the commissioned ones (a dated marks
            record), which every cycle then checks its white frame against: a camera that moved stops the
            line from judging facets (docs/reliability.md#the-station-checks-itself). A new record also ends
            such a hold. After a moved camera, prefer 'confirm-geometry', which checks a reference first.""")
    common(mk)
    mk.set_defaults(func=_line_stopped(cmd_marks))

    cg = add_command(
        sub, "confirm-geometry", help="after a moved camera: check a reference facet, then take the marks' new places",
        description="""
            The line holds (judges no facet) when the fixture's marks show that the camera has moved. Put the
            reference facet in the fixture and run this: it measures the reference against its certificate
            ('calibrate geometry'); within tolerance, the geometry is confirmed and the marks' new places
            become the commissioned ones ('calibrate marks'), which ends the hold at the line's next start.
            Outside tolerance nothing is taken: recommission with 'calibrate commission'.""")
    common(cg)
    cg.add_argument("--reference", default=None, metavar="FILE",
                    help="the reference facet's certificate (the twin's truth by default on the simulated station)")
    cg.set_defaults(func=_line_stopped(cmd_confirm_geometry))

    st = add_command(
        sub, "status", help="the calibration in force, its age, and the records kept",
        description="""
            Show the radiometric calibration in force (or the shipped default), its age against the station
            file's limits, where the camera intrinsics come from, and the records of each kind kept under
            data_dir/calibration/. Nothing is measured.""")
    common(st, simulated=False)
    st.set_defaults(func=cmd_status)

    def photo_options(p):
        p.add_argument("--markers", required=True, metavar="CSV",
                       help="the markers' surveyed corners: OpenCSP's CSV of marker id, corner id (4 x marker id + "
                            "0..3, OpenCV's corner order), x, y, z in metres (required)")
        p.add_argument("--dictionary", default="DICT_4X4_1000", help="the markers' ArUco dictionary (OpenCSP's)")
        p.add_argument("--corners", choices=("edges", "contour", "subpix", "apriltag", "none"), default="edges",
                       help="how marker corners are refined: edges (ours: each side located and the sides "
                            "intersected), OpenCV's methods, or none (whole pixels, as OpenCSP)")

    cpos = add_command(
        sub, "camera-position", help="the camera's position from a photograph of surveyed ArUco markers",
        description="""
            The camera's pose in the markers' frame (docs/calibration.md#the-cameras-position-from-markers):
            the camera photographs ArUco markers whose corners were surveyed (the screen frame's markers);
            their corners are found to a fraction of a pixel, the pose is solved by least squares, and its
            uncertainty (k = 2) comes from the corners' residuals (and the camera record's standard deviations,
            when the camera is a record). Writes a dated cameraposition record with the pose in OpenCV's and in
            OpenCSP's form (rvec, tvec).""")
    common(cpos, simulated=False)
    cpos.add_argument("photo", metavar="PHOTO", help="the camera's photograph of the markers")
    cpos.add_argument("--camera", default="station", metavar="CAMERA",
                      help="the camera: station (the station's camera in force), record (the newest camera record), "
                           "handheld, a camera record .json or OpenCSP's Camera .h5")
    photo_options(cpos)
    cpos.add_argument("--min-markers", type=int, default=3, metavar="N", help="fewest markers of the table to be seen")
    cpos.set_defaults(func=_line_stopped(cmd_camera_position))

    dots = add_command(
        sub, "dots", help="a dot target's 3-D dot locations from photographs with surveyed ArUco markers",
        description="""
            Locate every dot of a fixed-pattern dot target (docs/calibration.md#a-dot-targets-dot-locations):
            photograph the target and the surveyed markers from a few places (3 to 5, spread left and right)
            with one calibrated camera, and give for every photograph the pixel of the same dot, the origin
            (index 0, 0). Dots are found to a few hundredths of a pixel, indexed from the origin, and located
            by a bundle adjustment of the camera poses and the dots (the markers fix the frame), each with
            its U (k = 2). Writes a dated dots record (the grid of x and y indices and xyz); --opencsp-out
            also writes OpenCSP's DotLocationsFixedPattern file.""")
    common(dots, simulated=False)
    dots.add_argument("photos", nargs="+", metavar="PHOTO", help="the photographs (two or more)")
    dots.add_argument("--origin", action="append", type=_pair("--origin"), required=True, metavar="COLUMN,ROW",
                      help="per photograph, in their order: a pixel on the origin dot (required, once per photograph)")
    dots.add_argument("--camera", required=True, metavar="CAMERA",
                      help="the camera of the photographs: handheld, record, station, a camera record .json or "
                           "OpenCSP's Camera .h5 (required)")
    photo_options(dots)
    dots.add_argument("--dot-area", type=_pair("--dot-area"), default=(3.0, 2000.0), metavar="MIN,MAX",
                      help="accepted dot areas in the photographs, square pixels")
    dots.add_argument("--min-circularity", type=float, default=0.8, metavar="C",
                      help="least circularity of a dot (a disc is 1, a square 0.785)")
    dots.add_argument("--light-dots", action="store_true", help="the dots are light on a dark target")
    dots.add_argument("--min-views", type=int, default=2, metavar="N", help="photographs that must show a dot")
    dots.add_argument("--opencsp-out", default=None, metavar="FILE.h5",
                      help="also write OpenCSP's DotLocationsFixedPattern HDF5 file")
    dots.add_argument("--compare", default=None, metavar="FILE.h5",
                      help="compare, dot by dot, with an OpenCSP DotLocationsFixedPattern file")
    dots.set_defaults(func=_line_stopped(cmd_dots))

    scd = add_command(
        sub, "screen-data", help="check OpenCSP's screen distortion data against its fiducial markers",
        description="""
            Check a screen shape measured by OpenCSP's display-shape calibration (its screen distortion
            data: screen fractions and 3-D points, docs/calibration.md#opencsps-screen-shape-data): our screen
            model built on it, its interpolation between nodes, and the shape at the calibration fiducials
            against the surveyed markers paired with them; with --display, against an OpenCSP display model
            of the same screen. Nothing is measured and no record is written.""")
    common(scd, simulated=False)
    scd.add_argument("data", metavar="DISTORTION.h5", help="OpenCSP's screen distortion data")
    scd.add_argument("--markers", required=True, metavar="CSV", help="the marker table the calibration used (required)")
    scd.add_argument("--point-pairs", required=True, metavar="CSV",
                     help="OpenCSP's screen calibration point pairs: fiducial index, marker id (required)")
    scd.add_argument("--projection", required=True, metavar="FILE.h5",
                     help="OpenCSP's ImageProjection file: the active area the fiducials were shown in (required)")
    scd.add_argument("--display", default=None, metavar="FILE.h5", help="an OpenCSP display model to compare with")
    scd.add_argument("--tolerance-mm", type=float, default=5.0, metavar="MM",
                     help="a fiducial further than this from its marker (in x or y) is a warning")
    scd.set_defaults(func=cmd_screen_data)
    return cal
