"""``sofast-station field orientation`` and ``sofast-station field canting``: the heliostat in the field,
from the tower's camera (docs/field.md). Registered in :data:`sofast_station.commands.COMMAND_MODULES`.
"""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path

from ..commands import add_command, single_thread_blas
from ..files import json_ready, write_json_atomic
from ..gum import with_u

log = logging.getLogger("sofast_station")


def _pair(text: str, what: str) -> tuple[float, float]:
    from ..errors import ConfigError

    try:
        a, b = (float(v) for v in str(text).split(","))
    except ValueError:
        raise ConfigError(f"{what} must be two numbers A,B (degrees), got {text!r}") from None
    return a, b


def _triple(text: str | None):
    if text is None:
        return None
    from ..errors import ConfigError

    try:
        values = [float(v) for v in str(text).split(",")]
    except ValueError:
        values = []
    if len(values) != 3:
        raise ConfigError(f"--position must be X,Y,Z metres (field frame: x east, y north, z up), got {text!r}")
    return values


def _setup(site, place, photo: Path, args, *, need_command: bool) -> dict:
    """A photo with what belongs to it: its image, the camera at its zoom, the commanded orientation and normal
    (from --commanded, its notes' ``commanded``, or its time and the sun), the predicted corners."""
    import dataclasses

    from ..errors import ConfigError
    from ..geometry import CameraIntrinsics
    from .detect import check_photo
    from .geometry import azimuth_elevation, direction, heliostat_rotation
    from .inputs import read_notes, read_photo
    from .orientation import nominal_pointing, predict_corners
    from .sun import commanded_normal, sun_direction

    notes = read_notes(photo)
    image = read_photo(photo)
    camera = site.camera
    focal = getattr(args, "focal_px", None) or notes.get("focal_px")
    if focal is not None:
        k = camera.intrinsics
        mat = k.matrix.copy()
        mat[0, 0] = mat[1, 1] = float(focal)
        camera = dataclasses.replace(camera, intrinsics=CameraIntrinsics(k.width_px, k.height_px, mat, k.distortion))
    check_photo(image, camera.intrinsics, f"photo {photo}")
    time = getattr(args, "time", None) or notes.get("time")
    commanded = normal = None
    given = getattr(args, "commanded", None)
    if given is not None:
        az, el = _pair(given, "--commanded")
        commanded = (math.radians(az), math.radians(el))
    elif isinstance(notes.get("commanded"), dict):
        c = notes["commanded"]
        commanded = (math.radians(float(c["azimuth_deg"])), math.radians(float(c["elevation_deg"])))
    elif time is not None:
        sun = sun_direction(time, site.latitude_deg, site.longitude_deg, site.altitude_m)
        normal = commanded_normal(sun, place.position_m, site.aim_point_m)
        commanded = azimuth_elevation(normal)
    if commanded is not None and normal is None:
        normal = direction(*commanded)
    if commanded is None:
        if need_command:
            raise ConfigError(f"photo {photo} has no commanded orientation: give its time (the sun's position) or "
                              "commanded {azimuth_deg, elevation_deg} in its notes (PHOTO.json), or --commanded")
        # no command: look for it facing the camera (the layout's map takes up the difference)
        guess = azimuth_elevation(camera.position_m - place.position_m)
    else:
        guess = commanded
    r_fc = nominal_pointing(camera, place)
    rotation = heliostat_rotation(*guess)
    predicted = predict_corners(place, rotation, camera, r_fc)
    return {"photo": photo, "image": image, "camera": camera, "time": time, "commanded": commanded,
            "commanded_normal": normal, "predicted": predicted, "rotation": rotation, "pointing": r_fc,
            "notes": notes}


def _out_dir(args, photo: Path) -> Path:
    return Path(args.out) if args.out else photo.resolve().parent


def cmd_orientation(args) -> int:
    single_thread_blas()
    import numpy as np

    from .detect import detect_facets
    from .inputs import heliostat_place, load_site
    from .orientation import heliostat_origin, orientation_figures, solve_orientation
    from .picture import orientation_png

    photo = Path(args.photo)
    site = load_site(args.site)
    place = heliostat_place(site, _serial(args, photo), _triple(args.position))
    s = _setup(site, place, photo, args, need_command=False)
    detection = detect_facets(s["image"], s["camera"].intrinsics, s["predicted"])
    result = solve_orientation(detection.facets, place, s["camera"], commanded=s["commanded"],
                               uncertainty=site.uncertainty)
    figures = orientation_figures(result, s["commanded_normal"])
    record = {"command": "field orientation", "photo": str(photo), "site": site.name, "heliostat": place.serial,
              "design": place.ensemble.name, "position_m": place.position_m.tolist(), "time": s["time"],
              "orientation": figures, "detection": _detection_dict(detection)}
    out = _out_dir(args, photo)
    json_path = out / f"{photo.stem}-orientation.json"
    write_json_atomic(json_path, json_ready(record))
    # the normals as arrows from the heliostat's middle, the heliostat's size long
    from .geometry import azimuth_elevation, direction, heliostat_rotation, look_at

    size = float(np.max(np.ptp(place.ensemble.corners_m(), axis=0)))
    axis = azimuth_elevation(s["pointing"][2])
    c = s["camera"].position_m
    r_fc = look_at(c, c + direction(axis[0] + 1e-3 * result.camera_correction_mrad[0],
                                    axis[1] + 1e-3 * result.camera_correction_mrad[1]), 1e-3 * s["camera"].roll_mrad)
    middle = heliostat_origin(place, heliostat_rotation(result.azimuth_rad, result.elevation_rad, result.spin_rad))
    arrows = {"measured": _arrow(s["camera"], r_fc, middle, result.normal, size)}
    if s["commanded_normal"] is not None:
        arrows["commanded"] = _arrow(s["camera"], r_fc, middle, s["commanded_normal"], size)
    png = orientation_png(out / f"{photo.stem}-orientation.png", s["image"], detection, figures, arrows,
                          s["predicted"], f"{place.serial} ({place.ensemble.name}) in {photo.name}")
    if args.json:
        json.dump(json_ready(record), sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    u = figures["pointing_U_mrad"]
    print(f"Heliostat {place.serial} ({place.ensemble.name}) at {np.round(place.position_m, 2).tolist()} m, photo "
          f"{photo.name}")
    print(f"  facets found   {len(detection.facets)} of {len(s['predicted'])}"
          + (f"; left out: {'; '.join(f'{k} {v}' for k, v in detection.left_out.items())}" if detection.left_out
             else ""))
    print(f"  normal         azimuth {with_u(figures['azimuth_deg'], figures['azimuth_deg_U'], ' deg')}, elevation "
          f"{with_u(figures['elevation_deg'], figures['elevation_deg_U'], ' deg')} (U, k=2); on the sky "
          f"U {u['azimuth']:.2g} mrad, {u['elevation']:.2g} mrad")
    if "tracking_error_mrad" in figures:
        t, tu = figures["tracking_error_mrad"], figures["tracking_error_mrad_U"]
        print(f"  tracking error {with_u(t['angle'], tu['angle'], ' mrad')} (azimuth "
              f"{with_u(t['azimuth'], tu['azimuth'], sign=True)}, elevation "
              f"{with_u(t['elevation'], tu['elevation'], ' mrad', sign=True)}) against "
              f"commanded {figures['commanded']['azimuth_deg']:.3f}, {figures['commanded']['elevation_deg']:.3f} deg")
    else:
        print("  tracking error not known: no commanded orientation (give the photo's time or --commanded)")
    print(f"  corners        reprojection {figures['reprojection_rms_px']:.3f} px RMS, chi2/dof "
          f"{figures['chi2_per_dof']:.2f}")
    if "alternative" in figures:
        print(f"  WARNING: a second orientation {figures['alternative']['apart_mrad']:.1f} mrad away fits almost as "
              "well (the normal points near the camera): take another photo from another orientation")
    print(f"  json {json_path}\n  png  {png}")
    return 0


def _arrow(camera, r_fc, middle, normal, length):
    import cv2
    import numpy as np

    pts = np.array([middle, middle + length * np.asarray(normal)])
    cam = (pts - camera.position_m) @ r_fc.T
    k = camera.intrinsics
    px, _ = cv2.projectPoints(cam.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k.matrix, k.distortion)
    return px.reshape(-1, 2)


def _serial(args, photo: Path) -> str:
    from ..errors import ConfigError
    from .inputs import read_notes

    if args.heliostat:
        return args.heliostat
    serial = read_notes(photo).get("heliostat")
    if not serial:
        raise ConfigError(f"which heliostat is in {photo}? give --heliostat SERIAL (or a heliostat file with "
                          "--position), or heliostat in the photo's notes")
    return str(serial)


def _detection_dict(detection) -> dict:
    return {"facets_found": list(detection.facets), "left_out": detection.left_out,
            "facet_colour": list(detection.facet_colour), "shift_px": detection.shift_px.tolist(),
            "scale": detection.scale, "saturated_fraction": detection.saturated_fraction,
            "corners_px": {k: f.corners_px.tolist() for k, f in detection.facets.items()},
            "edge_rms_px": {k: f.edge_rms_px.tolist() for k, f in detection.facets.items()}}


def cmd_canting(args) -> int:
    single_thread_blas()
    from ..errors import ConfigError, StationError
    from ..geometry import Pose
    from .canting import PhotoCorners, canting_figures, compare_with_factory, solve_canting
    from .detect import detect_facets
    from .inputs import heliostat_place, load_site, read_record
    from .orientation import heliostat_origin
    from .picture import canting_png

    photos = [Path(p) for p in args.photos]
    if len(photos) < 2:
        raise ConfigError(f"{len(photos)} photo given: the canting needs at least 2 (10 or more, the heliostat "
                          "turned over 30 degrees or more between them)")
    site = load_site(args.site)
    place = heliostat_place(site, _serial(args, photos[0]), _triple(args.position))
    record = read_record(args.factory, place.serial) if args.factory else None
    used, failed, first = [], {}, None
    for i, photo in enumerate(photos, 1):
        s = _setup(site, place, photo, args, need_command=True)
        try:
            detection = detect_facets(s["image"], s["camera"].intrinsics, s["predicted"])
        except StationError as exc:
            failed[str(photo)] = str(exc)
            log.warning("photo %d/%d %s left out: %s", i, len(photos), photo.name, exc)
            continue
        log.info("photo %d/%d %s: %d facets", i, len(photos), photo.name, len(detection.facets))
        r_fc = s["pointing"]
        initial = Pose(r_fc @ s["rotation"], r_fc @ (heliostat_origin(place, s["rotation"]) - s["camera"].position_m))
        used.append(PhotoCorners(photo.name, s["camera"].intrinsics, detection.facets, initial))
        if first is None:
            first = (s, detection)
    if len(used) < 2:
        raise ConfigError(f"only {len(used)} of the {len(photos)} photos show the heliostat's facets: "
                          + "; ".join(f"{Path(k).name}: {v}" for k, v in failed.items()))
    result = solve_canting(used, place.ensemble, facet_size_u_mm=site.uncertainty.facet_size_mm,
                           focal_length_rel=site.uncertainty.focal_length_rel)
    figures = canting_figures(result)
    comparison = compare_with_factory(result, record) if record is not None else None
    out = _out_dir(args, photos[0])
    stem = f"{place.serial}-canting"
    doc = {"command": "field canting", "site": site.name, "heliostat": place.serial, "design": place.ensemble.name,
           "position_m": place.position_m.tolist(), "photos": [str(p) for p in photos], "photos_left_out": failed,
           "canting": figures}
    if comparison is not None:
        doc["factory"] = comparison
    json_path = out / f"{stem}.json"
    write_json_atomic(json_path, json_ready(doc))
    s, detection = first
    png = canting_png(out / f"{stem}.png", s["image"], detection, figures, comparison, s["predicted"],
                      f"{place.serial} ({place.ensemble.name}): canting from {len(used)} photos, shown on "
                      f"{s['photo'].name}")
    if args.json:
        json.dump(json_ready(doc), sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    print(f"Heliostat {place.serial} ({place.ensemble.name}): canting from {len(used)} of {len(photos)} photos")
    print(f"  canting error RMS {figures['canting_rms_mrad']:.2f} mrad, largest {figures['canting_max_mrad']:.2f} "
          f"mrad ({figures['canting_max_facet']}); corners' noise {result.corner_noise_scale:.2f} x their own u")
    rows = {r["label"]: r for r in (comparison or {}).get("facets", [])}
    head = "  facet    canting x (mrad)   canting y (mrad)"
    print(head + ("     factory x, y       diff x, y    U comb. x, y" if comparison else ""))
    for f in figures["facets"]:
        c, u = f["canting_mrad"], f["canting_mrad_U"]
        line = f"  {f['label']:<7} {with_u(c['x'], u['x'], sign=True):>15}   {with_u(c['y'], u['y'], sign=True):>15}"
        r = rows.get(f["label"])
        if r is not None:
            line += (f"   {r['factory_mrad']['x']:+6.2f}, {r['factory_mrad']['y']:+6.2f}   "
                     f"{r['difference_mrad']['x']:+6.2f}, {r['difference_mrad']['y']:+6.2f}   "
                     f"{r['U_combined_mrad']['x']:4.2f}, {r['U_combined_mrad']['y']:4.2f}"
                     + ("   FLAGGED" if r["flagged"] else ""))
        print(line)
    for label, why in figures["not_measured"].items():
        print(f"  {label:<7} not measured: {why}")
    if comparison is not None:
        print("  against the factory record: " + (f"FLAGGED {', '.join(comparison['flagged'])} (the field and the "
                                                   "factory differ beyond their combined U)" if comparison["flagged"]
                                                   else "every facet agrees within the combined U"))
    print(f"  json {json_path}\n  png  {png}")
    return 0


def cmd_prescription(args) -> int:
    single_thread_blas()
    import csv
    import io

    import numpy as np

    from ..ensemble import load_ensemble
    from ..errors import ConfigError
    from .inputs import load_site, read_layout, write_prescribed_heliostat
    from .prescription import facet_normals, prescribed_ensemble, prescription_mrad
    from .sun import sun_direction

    site = load_site(args.site)
    if site.layout_file is None:
        raise ConfigError(f"site file {site.path} names no layout ([site] layout = \"layout.csv\")")
    layout = read_layout(site.layout_file)
    sun = None
    if args.time:
        sun = sun_direction(args.time, site.latitude_deg, site.longitude_deg, site.altitude_m)
    out = Path(args.out) if args.out else site.path.resolve().parent / "prescriptions"
    rule = f"off axis at {args.time}" if args.time else "on axis at the slant range"
    rows, doc = [], {"site": site.name, "rule": rule, "aim_point_m": site.aim_point_m.tolist(), "heliostats": {}}
    for serial, row in layout.items():
        design_file = row["design"] or site.heliostat_file
        if design_file is None:
            raise ConfigError(f"heliostat {serial!r}: its layout row names no design and the site file no "
                              "[site] heliostat")
        ensemble = load_ensemble(design_file)
        normals = facet_normals(ensemble, row["position_m"], site.aim_point_m, sun, site.pivot_offset_m)
        mrad = prescription_mrad(ensemble, normals)
        named = prescribed_ensemble(ensemble, normals, name=f"{ensemble.name} for {serial}")
        slant = float(np.linalg.norm(site.aim_point_m - row["position_m"]))
        path = write_prescribed_heliostat(out / f"{serial}.toml", design_file, named,
                                          {k: {"x": v["x"], "y": v["y"]} for k, v in mrad.items()},
                                          f"The canting heliostat {serial} asks for at {row['position_m'].tolist()} m "
                                          f"(slant range {slant:.1f} m; {doc['rule']}), written by "
                                          "'sofast-station field prescription' (docs/field.md)")
        change = max(math.hypot(v["change"]["x"], v["change"]["y"]) for v in mrad.values())
        doc["heliostats"][serial] = {"file": str(path), "slant_range_m": slant, "facets": mrad,
                                     "largest_change_mrad": change}
        rows.append((serial, f"{slant:.2f}", f"{change:.3f}", str(path)))
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["serial", "slant_range_m", "largest_change_from_design_mrad", "heliostat_file"])
    writer.writerows(rows)
    (out / "prescriptions.csv").write_text(buf.getvalue())
    write_json_atomic(out / "prescriptions.json", json_ready(doc))
    if args.json:
        json.dump(json_ready(doc), sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    print(f"Canting prescriptions for {len(rows)} heliostats of {site.name} ({doc['rule']}):")
    for serial, slant, change, path in rows:
        print(f"  {serial:<10} slant range {slant} m, largest change from the design's canting {change} mrad: {path}")
    print(f"  table {out / 'prescriptions.csv'}")
    return 0


def register(subparsers) -> None:
    """Add ``field orientation`` and ``field canting`` to the ``sofast-station`` *subparsers*."""
    field = add_command(subparsers, "field", help="the heliostat in the field, from the tower's camera",
                        description="""
            The heliostat after the factory: photographs from a camera on the tower give a heliostat's
            orientation (and its tracking error) from one photo, and every facet's canting from several,
            beside the factory's record of the same serial (docs/field.md).""")
    sub = field.add_subparsers(dest="field", metavar="WHAT", required=True)
    common = []
    ori = add_command(sub, "orientation", help="a heliostat's normal and tracking error from one photo",
                      description="""
            The heliostat's facets' corners by edge detection in one photo from the tower's camera, and
            from them its normal (azimuth, elevation) and its tracking error against the commanded normal
            (from the photo's time, the sun's position by pvlib and the site's aim point, or the commanded
            orientation given), each with U (k=2). Prints a summary and writes PHOTO-orientation.json and
            PHOTO-orientation.png (the photo with the corners found and the normals as arrows).""")
    ori.add_argument("photo", metavar="PHOTO", help="the photo (PNG, JPEG, TIFF); its notes in PHOTO.json if any")
    common.append(ori)
    can = add_command(sub, "canting", help="every facet's canting from several photos, beside the factory's",
                      description="""
            Every facet's corners in 3-D by bundle adjustment over several photos of the heliostat (turned
            between them to orientations whose mirrors show the sky), each facet's normal and canting error
            with U (k=2), and with --factory the difference from the factory's record of the same serial,
            flagged where it exceeds both U combined. Each photo needs its commanded orientation (its time,
            or commanded in its notes). Writes SERIAL-canting.json and SERIAL-canting.png.""")
    can.add_argument("photos", metavar="PHOTO", nargs="+", help="the photos, at least 2 (10 or more is better)")
    can.add_argument("--factory", metavar="FILE", default=None,
                     help="the factory's record: the JSON of 'sofast-station inspect --json', or the station's "
                          "journal (its newest record of the serial)")
    common.append(can)
    for p in common:
        p.add_argument("--site", metavar="FILE", required=True,
                       help="the site file: where the tower camera stands and its intrinsics, the site's latitude, "
                            "the aim point, the field layout (docs/field.md)")
        p.add_argument("--heliostat", metavar="SERIAL|FILE", default=None,
                       help="the heliostat: its serial in the site's layout, or a heliostat file with --position "
                            "(default: heliostat in the photo's notes)")
        p.add_argument("--position", metavar="X,Y,Z", default=None,
                       help="the heliostat's pivot, metres, field frame (x east, y north, z up), instead of the "
                            "layout's")
        p.add_argument("--time", metavar="ISO", default=None,
                       help="when the photo was taken, with its time zone (instead of the notes' time)")
        p.add_argument("--focal-px", type=float, default=None,
                       help="the zoom's focal length in pixels (instead of the site's or the notes')")
        p.add_argument("--out", metavar="DIR", default=None, help="folder for the JSON and the PNG (default: the "
                                                                  "photo's folder)")
        p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    ori.add_argument("--commanded", metavar="AZ,EL", default=None,
                     help="the commanded orientation, degrees (azimuth clockwise from north, elevation), instead "
                          "of the one the photo's time gives")
    ori.set_defaults(func=cmd_orientation)
    can.set_defaults(func=cmd_canting)
    pre = add_command(sub, "prescription", help="each heliostat's canting for its place in the field",
                      description="""
            For every heliostat of the site's field layout, the canting its place asks for: on axis at its
            slant range to the aim point (default), or off axis for the sun at --time (pvlib). Writes one
            heliostat file per serial (the design with each facet's prescribed canting: the line measures
            the heliostat against it like any design) and prescriptions.csv / .json with each one's largest
            change from the design's canting.""")
    pre.add_argument("--site", metavar="FILE", required=True, help="the site file (its layout and aim point)")
    pre.add_argument("--time", metavar="ISO", default=None,
                     help="off-axis canting for the sun at this moment (with its time zone); default: on axis")
    pre.add_argument("--out", metavar="DIR", default=None,
                     help="folder for the heliostat files and the table (default: prescriptions/ beside the site "
                          "file)")
    pre.add_argument("--json", action="store_true", help="print the prescriptions as JSON on stdout")
    pre.set_defaults(func=cmd_prescription)
