"""``sofast-station field orientation``, ``canting``, ``prescription`` and ``spot``: the heliostat in the field,
from the tower's camera, its place in the layout and its spot on the tower's target (docs/field.md).
Registered in :data:`sofast_station.commands.COMMAND_MODULES`.
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


def _photo_scale(notes: dict, photo: Path):
    import numpy as np

    from ..errors import ConfigError
    from .spot import PhotoScale

    try:
        pixel_m = float(notes["pixel_m"])
        aim = np.array([float(v) for v in notes["aim_px"]], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"BCS photo {photo}: its notes ({photo.with_suffix('.json').name}) need pixel_m (metres of "
                          "the target per pixel) and aim_px [column, row] (the aim point's pixel); "
                          "docs/field.md#spot") from None
    if not (pixel_m > 0 and aim.shape == (2,) and np.all(np.isfinite(aim))):
        raise ConfigError(f"BCS photo {photo}: pixel_m must be positive and aim_px two pixel coordinates")
    return PhotoScale(pixel_m, aim, float(notes.get("pixel_m_rel_u", 0.005)), float(notes.get("aim_px_u", 0.5)))


def _print_json(doc: dict) -> int:
    """*doc* as JSON on stdout (``--json``); the command's exit status 0."""
    json.dump(json_ready(doc), sys.stdout, indent=1)
    sys.stdout.write("\n")
    return 0


def _figure_line(name: str, f: dict, ascii_only: bool = False) -> str:
    """A spot's figures in one line, each value with its U (GUM's two digits; ``+-`` for the picture's font)."""
    c, u = f["centroid_m"], f["centroid_m_U"]
    text = (f"{name}: centroid x {with_u(c['x'], u['x'], ' m', sign=True)}, y {with_u(c['y'], u['y'], ' m', sign=True)}"
            f"; 90 % radius {with_u(f['spot_radius_m'], f['spot_radius_m_U'], ' m')}")
    return text.replace("±", "+-") if ascii_only else text


def cmd_spot(args) -> int:
    single_thread_blas()
    import numpy as np

    from ..errors import ConfigError
    from ..files import safe_name
    from .geometry import azimuth_elevation
    from .inputs import heliostat_place, load_site, read_notes, read_photo, read_record
    from .picture import spot_png
    from .spot import (SpotScene, compare_spots, facet_models, facing_target, photo_extent, photo_figures,
                       predict_spot)
    from .sun import sun_direction

    site = load_site(args.site)
    record = read_record(args.factory, args.heliostat)
    serial = args.heliostat or record.get("serial")
    if not serial:
        raise ConfigError("the factory record names no serial: give --heliostat SERIAL")
    place = heliostat_place(site, serial, _triple(args.position))
    models = facet_models(record)
    photo = Path(args.photo) if args.photo else None
    notes = read_notes(photo) if photo is not None else {}
    times = list(args.time or []) or ([notes["time"]] if "time" in notes else [])
    if not times:
        raise ConfigError("no moment for the spot: give --time ISO (with its time zone), or a --photo whose notes "
                          "(PHOTO.json) hold its time")
    azimuth = args.target_azimuth if args.target_azimuth is not None else notes.get("target_azimuth_deg")
    plane = facing_target(site.aim_point_m, place.position_m, azimuth)
    dni = args.dni or float(notes.get("dni_w_m2", 900.0))
    out_dir = Path(args.out) if args.out else (photo.parent if photo is not None else Path(args.factory).parent)
    stem = safe_name(str(serial), 64)
    doc = {"serial": serial, "site": site.name, "position_m": place.position_m.tolist(),
           "target": {"centre_m": plane.centre_m.tolist(), "normal": plane.normal.tolist(),
                      "axes": "x level to the right seen from the field, y up the target; metres from the aim point"},
           "factory_record": {"time": record.get("time"), "canting_reference": record.get("canting_reference")},
           "facets_traced": [m.label for m in models], "dni_w_m2": dni, "spots": []}
    first = None
    for k, when in enumerate(times):
        sun = sun_direction(when, site.latitude_deg, site.longitude_deg, site.altitude_m)
        scene = SpotScene(place.position_m, place.pivot_offset_m, plane, sun)
        pred = predict_spot(models, place.ensemble, scene, dni_w_m2=dni, reflectivity=args.reflectivity)
        az, el = azimuth_elevation(sun)
        entry = {"time": str(when), "sun": {"azimuth_deg": math.degrees(az), "elevation_deg": math.degrees(el)},
                 "predicted": pred["figures"]}
        shown = None
        if photo is not None and k == 0:
            scale = _photo_scale(notes, photo)
            image = read_photo(photo)
            dark = read_photo(photo.parent / notes["dark"]) if notes.get("dark") else None
            fig = photo_figures(image, scale, dark)
            entry["photo"] = {"file": str(photo), **fig}
            entry["comparison"] = compare_spots(pred["figures"], fig)
            grey = image.mean(axis=2) if image.ndim == 3 else image.astype(np.float64)
            shown = {"image": grey - fig["background"], "extent_m": photo_extent(image.shape, scale), "figures": fig}
        doc["spots"].append(entry)
        if first is None:
            first = (pred, shown, entry)
    json_path = out_dir / f"{stem}-spot.json"
    write_json_atomic(json_path, json_ready(doc))
    pred, shown, entry = first
    lines = [_figure_line("predicted", pred["figures"], ascii_only=True)]
    if shown is not None:
        lines.append(_figure_line("photographed", shown["figures"], ascii_only=True))
        comp = entry["comparison"]
        lines.append("field check of the factory record: " + (f"FLAGGED {', '.join(comp['flagged'])}"
                                                              if comp["flagged"] else "within the combined U"))
    title = (f"{serial} on the target at {entry['time']} (sun az {entry['sun']['azimuth_deg']:.1f}, el "
             f"{entry['sun']['elevation_deg']:.1f} deg; slant range {pred['figures']['slant_range_m']:.1f} m)")
    png = spot_png(out_dir / f"{stem}-spot.png", pred, shown, title, lines)
    doc["json"], doc["png"] = str(json_path), str(png)
    if args.json:
        return _print_json(doc)
    print(f"Spot of heliostat {serial} at {place.position_m.tolist()} m on the target at {site.aim_point_m.tolist()} m "
          f"(U, k=2; {len(models)} facets from the factory record):")
    for e in doc["spots"]:
        f = e["predicted"]
        print(f"  {e['time']} (sun azimuth {e['sun']['azimuth_deg']:.1f}, elevation {e['sun']['elevation_deg']:.1f} "
              f"deg; slant range {f['slant_range_m']:.1f} m, incidence {f['incidence_angle_deg']:.1f} deg)")
        print("    " + _figure_line("predicted", f))
        if "photo" in e:
            print("    " + _figure_line("photographed", e["photo"]))
            for key in ("centroid_x_m", "centroid_y_m", "spot_radius_m"):
                c = e["comparison"][key]
                print(f"    {key}: difference {with_u(c['difference'], c['U'], ' m', sign=True)} (the combined U)"
                      + ("  FLAGGED" if c["flagged"] else ""))
            print("    (the centroid's difference holds the heliostat's tracking error on the day as well as its "
                  "facets')")
    print(f"  wrote {json_path} and {png}")
    return 0


def read_observers(path) -> list:
    """Observer points from a CSV (``name, x, y, z`` metres, field frame; a header names the columns loosely) or
    a TOML file (``[[observer]]`` tables with ``name`` and ``position_m``)."""
    import csv

    from ..errors import ConfigError
    from ..files import read_toml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"observers file {path} does not exist")
    out = []
    if path.suffix.lower() == ".toml":
        for k, t in enumerate(read_toml(path, "observers file").get("observer", [])):
            try:
                pos = [float(v) for v in t["position_m"]]
            except (KeyError, TypeError, ValueError):
                pos = []
            if len(pos) != 3:
                raise ConfigError(f"observers file {path}: [[observer]] {k + 1} needs position_m = [x, y, z] metres")
            out.append((str(t.get("name", f"observer {k + 1}")), pos))
    else:
        rows = list(csv.reader(path.read_text().splitlines()))
        head = [h.strip().lower() for h in rows[0]] if rows else []
        cols = {}
        for key, names in (("name", ("name", "id", "observer", "point")), ("x", ("x", "x_m", "east")),
                           ("y", ("y", "y_m", "north")), ("z", ("z", "z_m", "height", "height_m"))):
            cols[key] = next((i for i, h in enumerate(head) if h in names), None)
        if None in (cols["x"], cols["y"], cols["z"]):
            raise ConfigError(f"observers file {path}: its header must name x, y and z (metres, field frame), got "
                              f"{', '.join(head) or 'nothing'}")
        for k, row in enumerate(rows[1:]):
            if not any(c.strip() for c in row):
                continue
            try:
                pos = [float(row[cols[a]]) for a in "xyz"]
            except (IndexError, ValueError):
                raise ConfigError(f"observers file {path}, line {k + 2}: x, y, z must be numbers, got {row}") from None
            name = row[cols["name"]].strip() if cols["name"] is not None else f"observer {k + 1}"
            out.append((name, pos))
    if not out:
        raise ConfigError(f"observers file {path} lists no observer")
    return out


def _glare_value(p: dict, key: str, unit: str, scale: float) -> str:
    """A glare figure with its U from the canting; a U under 0.01 % of the value (the retinal irradiance of a
    uniform sun does not depend on the source's size) is said in words, not as digits."""
    value, u = p[key], p.get(f"{key}_U")
    if u is not None and u < 1e-4 * abs(value):
        return f"{with_u(value, None, unit, 4, scale=scale)} (U from the canting under 0.01 %)"
    return with_u(value, u, unit, 4, scale=scale)


def cmd_glare(args) -> int:
    single_thread_blas()
    import numpy as np

    from ..errors import ConfigError
    from ..files import safe_name
    from .geometry import azimuth_elevation, direction, heliostat_rotation
    from .glare import (EYE_FOCAL_M, OCULAR_TRANSMISSION, PUPIL_M, Sunlight, camera_glare, observers_glare,
                        sun_seen_directly)
    from .inputs import heliostat_place, load_site, read_notes, read_photo, read_record
    from .picture import hazard_chart
    from .spot import facet_models
    from .sun import commanded_normal, sun_direction

    eye = {"eye_focal_m": EYE_FOCAL_M, "pupil_m": PUPIL_M, "ocular_transmission": OCULAR_TRANSMISSION,
           "source": "the patent's Eqs. (47), (48) (Ho, Ghanbari and Diver 2011)"}
    note = ("E_r = E_c (d_p / (f omega))^2 tau, f 17 mm, d_p 2 mm, tau 0.5 (the patent's Eqs. 47-48).\n"
            "The hazard thresholds are not drawn: no quotable source in this build (docs/field.md#glare).")
    if args.sun_image or args.glare_image:
        if not (args.sun_image and args.glare_image):
            raise ConfigError("the camera route needs both --sun-image and --glare-image (same lens and zoom)")
        sun_img, glare_img = Path(args.sun_image), Path(args.glare_image)
        sn, gn = read_notes(sun_img), read_notes(glare_img)
        dni = args.dni if args.dni is not None else sn.get("dni_w_m2")
        factor = {}
        for name, n in (("sun", sn), ("glare", gn)):
            factor[name] = float(n.get("exposure_s", 1.0)) * float(n.get("filter_transmission", 1.0))
        res = camera_glare(read_photo(sun_img), read_photo(glare_img), None if dni is None else float(dni),
                           sun_factor=factor["sun"], glare_factor=factor["glare"])
        ref = sun_seen_directly(float(dni))
        doc = {"route": "camera", "sun_image": str(sun_img), "glare_image": str(glare_img), "dni_w_m2": float(dni),
               "eye": eye, "glare": res, "sun_seen_directly": ref}
        out = Path(args.out) if args.out else glare_img.parent
        stem = safe_name(glare_img.stem, 64)
        points = [{"name": glare_img.stem, **res}]
    else:
        if not (args.factory and args.site and args.observers):
            raise ConfigError("give a factory record with --site and --observers (the measured route), or "
                              "--sun-image and --glare-image with --dni (the camera route)")
        if not args.time:
            raise ConfigError("give --time ISO (with its time zone): the sun's position at that moment (pvlib)")
        site = load_site(args.site)
        record = read_record(args.factory, args.heliostat)
        serial = args.heliostat or record.get("serial")
        place = heliostat_place(site, serial, _triple(args.position))
        models = facet_models(record)
        if args.facet:
            models = [m for m in models if m.label == args.facet]
            if not models:
                raise ConfigError(f"facet {args.facet!r} is not a measured facet of the record")
        sun = sun_direction(args.time, site.latitude_deg, site.longitude_deg, site.altitude_m)
        if args.commanded:
            az, el = _pair(args.commanded, "--commanded")
            normal = direction(math.radians(az), math.radians(el))
        else:
            normal = commanded_normal(sun, place.position_m, site.aim_point_m)
        rot = heliostat_rotation(*azimuth_elevation(normal))
        origin = np.asarray(place.position_m, float) + place.pivot_offset_m * rot[:, 2]
        dni = float(args.dni if args.dni is not None else 900.0)
        light = Sunlight(sun, dni, args.sun)
        points = observers_glare(models, place.ensemble, rot, origin, read_observers(args.observers), light,
                                 args.reflectivity, per_facet=args.samples)
        for g in points:
            if g["glare"] and g["source_samples"] < 50:
                g["warning"] = (f"the source covers only {g['source_samples']} samples: raise --samples for a finer "
                                "estimate")
        ref = sun_seen_directly(dni)
        az_n, el_n = azimuth_elevation(normal)
        doc = {"route": "measured", "serial": serial, "time": args.time, "dni_w_m2": dni, "sun_shape": args.sun,
               "reflectivity": args.reflectivity, "facets": [m.label for m in models],
               "heliostat_normal": {"azimuth_deg": math.degrees(az_n), "elevation_deg": math.degrees(el_n),
                                    "how": "commanded" if args.commanded else "tracking the aim point"},
               "eye": eye, "observers": points, "sun_seen_directly": ref}
        out = Path(args.out) if args.out else Path(args.factory).parent
        stem = f"{safe_name(str(serial), 64)}-glare"
    json_path = out / f"{stem}.json"
    write_json_atomic(json_path, json_ready(doc))
    png = hazard_chart(out / f"{stem}.png", points, ref, f"glare: {stem}", note)
    doc["json"], doc["png"] = str(json_path), str(png)
    if args.json:
        return _print_json(doc)
    print(f"Glare ({doc['route']} route; the sun seen directly: {1e-4 * ref['retinal_w_m2']:.3g} W/cm^2 on the retina "
          f"at {1e3 * ref['omega_rad']:.2f} mrad):")
    for p in points:
        if p.get("omega_rad"):
            print(f"  {p['name']}: retinal irradiance {_glare_value(p, 'retinal_w_m2', ' W/cm^2', 1e-4)}, "
                  f"subtended angle {_glare_value(p, 'omega_rad', ' mrad', 1e3)}, corneal irradiance "
                  f"{_glare_value(p, 'corneal_w_m2', ' W/m^2', 1.0)}"
                  + (f" ({p['warning']})" if p.get("warning") else ""))
        else:
            print(f"  {p['name']}: no glare (the sun's disc is seen in no mirror from there)")
    print("  the hazard class is not given: the thresholds' source is missing (docs/field.md#glare)")
    print(f"  wrote {json_path} and {png}")
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
    spot = add_command(sub, "spot", help="the heliostat's spot on the tower's target from its factory record",
                       description="""
            The flux the heliostat will throw on the tower's calibration target (or receiver) where it stands,
            from the factory's record of its facets (canting, curvature, slope errors) and the sun at --time
            (pvlib), with U (k=2); with --photo, the spot photographed on that target (a BCS image, its scale in
            its notes) beside it: centroid and 90 % radius differences against the combined U, flagged beyond
            it. Writes SERIAL-spot.json and SERIAL-spot.png (docs/field.md#spot).""")
    spot.add_argument("factory", metavar="FACTORY",
                      help="the factory's record: the JSON of 'sofast-station inspect --json', or the station's "
                           "journal")
    spot.add_argument("--site", metavar="FILE", required=True, help="the site file (its latitude, aim point, layout)")
    spot.add_argument("--heliostat", metavar="SERIAL", default=None,
                      help="the heliostat's serial in the layout (default: the record's)")
    spot.add_argument("--position", metavar="X,Y,Z", default=None, help="its pivot instead of the layout's, metres")
    spot.add_argument("--time", metavar="ISO", action="append", default=None,
                      help="a moment for the spot, with its time zone (repeat for several; default: the photo's)")
    spot.add_argument("--photo", metavar="BCS", default=None,
                      help="a photo of the lit target; its notes (BCS.json): pixel_m, aim_px, time, and optionally "
                           "pixel_m_rel_u, aim_px_u, dark, target_azimuth_deg, dni_w_m2")
    spot.add_argument("--target-azimuth", type=float, default=None,
                      help="the way the target faces, degrees clockwise from north (default: towards the heliostat)")
    spot.add_argument("--dni", type=float, default=None, help="direct normal irradiance, W/m^2 (default 900)")
    spot.add_argument("--reflectivity", type=float, default=0.94, help="the mirrors' reflectivity (default 0.94)")
    spot.add_argument("--out", metavar="DIR", default=None, help="folder for the JSON and PNG (default: the photo's)")
    spot.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    spot.set_defaults(func=cmd_spot)
    gl = add_command(sub, "glare", help="glint and glare: retinal irradiance and subtended angle for observers",
                     description="""
            The glint or glare an observer sees in the heliostat: the retinal irradiance and the subtended
            source angle (the patent's Eqs. 47-48), from the factory's measured facets at the heliostat's field
            position (tracking the aim point at --time, or --commanded) for each observer of --observers (a CSV
            of name, x, y, z or a TOML of [[observer]]); or by the camera route, from an image of the sun and one
            of the glare source (same lens and zoom) with the DNI. Writes the JSON and the chart PNG (retinal
            irradiance against subtended angle). The hazard class is not given (docs/field.md#glare).""")
    gl.add_argument("factory", metavar="FACTORY", nargs="?", default=None,
                    help="the factory's record (inspect --json, or the station's journal) for the measured route")
    gl.add_argument("--site", metavar="FILE", default=None, help="the site file")
    gl.add_argument("--observers", metavar="FILE", default=None, help="observer points: CSV or TOML, metres")
    gl.add_argument("--heliostat", metavar="SERIAL", default=None, help="the serial (default: the record's)")
    gl.add_argument("--position", metavar="X,Y,Z", default=None, help="its pivot instead of the layout's, metres")
    gl.add_argument("--facet", metavar="LABEL", default=None, help="one facet only (default: every measured facet)")
    gl.add_argument("--time", metavar="ISO", default=None, help="the moment (with its time zone): the sun by pvlib")
    gl.add_argument("--commanded", metavar="AZ,EL", default=None,
                    help="the heliostat's orientation, degrees (stow, standby), instead of tracking the aim point")
    gl.add_argument("--sun", choices=("pillbox", "buie"), default="pillbox", help="the sun's shape (default pillbox)")
    gl.add_argument("--dni", type=float, default=None,
                    help="direct normal irradiance, W/m^2 (measured route: default 900; camera route: required, or "
                         "dni_w_m2 in the sun image's notes)")
    gl.add_argument("--reflectivity", type=float, default=0.94, help="the mirrors' reflectivity (default 0.94)")
    gl.add_argument("--samples", type=int, default=6000, help="samples per facet (default 6000)")
    gl.add_argument("--sun-image", metavar="IMAGE", default=None,
                    help="camera route: the sun through a neutral density filter (notes: exposure_s, "
                         "filter_transmission, dni_w_m2)")
    gl.add_argument("--glare-image", metavar="IMAGE", default=None,
                    help="camera route: the glare source, same lens and zoom (notes: exposure_s, filter_transmission)")
    gl.add_argument("--out", metavar="DIR", default=None, help="folder for the JSON and the chart")
    gl.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    gl.set_defaults(func=cmd_glare)
