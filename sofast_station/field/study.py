"""The field's methods on the twin (``sofast_station.twin.field``): populations of heliostat positions and
photo campaigns, each measured by the same code as the commands and judged against the twin's truth.

A drawn field (:class:`TwinSite`): a tower whose camera stands ``camera_above_aim_m`` above the aim point
(the receiver), heliostats on a radial stagger north of it; the sun from pvlib at a drawn day and hour;
each heliostat commanded to the bisector of the sun and the aim point and off it by a drawn tracking error.
What the measurement is told differs from the truth by what a survey and a calibration leave: the camera's
and the heliostat's positions (the uncertainty's standard deviations, per axis), the camera's roll, its
focal length; the camera points at the heliostat within ``pointing_mrad``. Every photo has the lens's blur,
shot and read noise, neighbours beside and behind, and the sky's light as the mirrors show it.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..ensemble import EnsembleDesign, load_ensemble
from ..geometry import CameraIntrinsics, Pose
from ..twin.field import Exposure, FieldHeliostat, Sky, camera_rotation, canting_truth, render
from ..twin.field import TowerCamera as TwinTowerCamera
from ..twin.field_spot import bcs_photo, map_centroid_radius, spot_flux, tracking
from .canting import PhotoCorners, canting_figures, canting_orientations, compare_with_factory, solve_canting
from .detect import detect_facets
from .geometry import azimuth_elevation, direction, heliostat_rotation, pointing_error_mrad
from .orientation import (
    HeliostatPlace,
    InputUncertainty,
    TowerCamera,
    heliostat_origin,
    nominal_pointing,
    orientation_figures,
    predict_corners,
    solve_orientation,
)
from .spot import FacetModel, SpotScene, facing_target, predict_spot
from .sun import commanded_normal, sun_direction, sun_position

#: The published figures this is measured against (the DLR paper): the orientation within 4 mrad in 80 % of
#: positions, a facet's normal to 1.6 mrad.
DLR_ORIENTATION_MRAD = 4.0
DLR_ORIENTATION_SHARE = 0.8
DLR_FACET_NORMAL_MRAD = 1.6
#: The canting photos are zoomed in by this against the orientation photos' (the heliostat spans two thirds of
#: the photo: its gaps 5 px or more, which the canting needs to beat a milliradian; it turns by 30 degrees).
CANTING_ZOOM = 1.1


@dataclass(frozen=True)
class TwinSite:
    """A drawn field: where it is, the tower, the camera and how the heliostats stand (metres, field frame)."""

    latitude_deg: float = 37.094
    longitude_deg: float = -2.359
    altitude_m: float = 500.0
    tower_height_m: float = 45.0
    camera_above_aim_m: float = 5.0
    radii_m: tuple = (35.0, 160.0)
    pivot_height_m: float = 1.6
    width_px: int = 800
    height_px: int = 600
    fill: float = 0.6                       # the zoom makes the heliostat this share of the photo's width
    pointing_mrad: float = 3.0
    tracking_error_mrad: float = 3.0
    uncertainty: InputUncertainty = field(default_factory=InputUncertainty)

    @property
    def aim_m(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.tower_height_m])

    @property
    def camera_m(self) -> np.ndarray:
        return np.array([0.0, -1.0, self.tower_height_m + self.camera_above_aim_m])

    def intrinsics(self, ensemble: EnsembleDesign, distance_m: float) -> CameraIntrinsics:
        """The camera at the zoom that makes the heliostat *fill* of the photo's width."""
        size = float(np.max(np.ptp(ensemble.corners_m()[:, :2], axis=0)))
        f = self.fill * self.width_px * distance_m / size
        return CameraIntrinsics(self.width_px, self.height_px,
                                [[f, 0.0, 0.5 * (self.width_px - 1)], [0.0, f, 0.5 * (self.height_px - 1)],
                                 [0.0, 0.0, 1.0]], [0.0, 0.0, 0.0, 0.0, 0.0])


def draw_position(site: TwinSite, rng: np.random.Generator) -> np.ndarray:
    """A heliostat's pivot in the field north of the tower (uniform in area between the radii, +-70 deg)."""
    r = math.sqrt(rng.uniform(site.radii_m[0] ** 2, site.radii_m[1] ** 2))
    a = math.radians(rng.uniform(-70.0, 70.0))
    return np.array([r * math.sin(a), r * math.cos(a), site.pivot_height_m])


def draw_time(site: TwinSite, rng: np.random.Generator, min_elevation_deg: float = 20.0) -> tuple:
    """A moment of a drawn day (2027) with the sun at least *min_elevation_deg* high: (ISO text, sun vector)."""
    for _ in range(200):
        day = dt.datetime(2027, 1, 1, tzinfo=dt.timezone.utc) + dt.timedelta(days=int(rng.integers(0, 365)))
        moment = day + dt.timedelta(hours=float(rng.uniform(6.0, 18.0)) - site.longitude_deg / 15.0)
        text = moment.isoformat(timespec="seconds")
        az, el = sun_position([text], site.latitude_deg, site.longitude_deg, site.altitude_m)[0]
        if math.degrees(el) >= min_elevation_deg:
            return text, direction(az, el)
    raise RuntimeError("no daylight drawn")                 # pragma: no cover


def _tilted(normal: np.ndarray, rng: np.random.Generator, sigma_mrad: float) -> tuple:
    """(azimuth, elevation) of *normal* turned by a drawn error of *sigma_mrad* per direction on the sky."""
    az, el = azimuth_elevation(normal)
    e_az, e_el = 1e-3 * sigma_mrad * rng.standard_normal(2)
    return az + e_az / max(math.cos(el), 1e-3), el + e_el


@dataclass
class Shot:
    """One drawn photo and what the measurement is told about it."""

    image: np.ndarray
    truth: dict
    camera_known: TowerCamera
    place_known: HeliostatPlace
    commanded: tuple
    commanded_normal: np.ndarray
    true_normal: np.ndarray
    time: str
    twin_heliostat: object = None


def orientation_shot(site: TwinSite, ensemble: EnsembleDesign, rng: np.random.Generator, *,
                     position=None, neighbours: bool = True, canting_mrad: float = 0.5) -> Shot:
    """A heliostat tracking with a drawn error, photographed (module docstring)."""
    pos = draw_position(site, rng) if position is None else np.asarray(position, float)
    moment, sun = draw_time(site, rng)
    cmd_n = commanded_normal(sun, pos, site.aim_m)
    cmd = azimuth_elevation(cmd_n)
    az, el = _tilted(cmd_n, rng, site.tracking_error_mrad)
    errors = canting_mrad * rng.standard_normal((ensemble.n_facets, 3))
    target = FieldHeliostat(ensemble, pos, az, el, 0.0, 0.0, errors)
    heliostats = [target]
    if neighbours:                       # the stagger's neighbours beside and behind it, tracking too
        r = float(np.hypot(*pos[:2]))
        u = pos[:2] / r
        side = np.array([u[1], -u[0]])
        size = float(np.max(np.ptp(ensemble.corners_m()[:, :2], axis=0)))
        for ds, dr in ((1.9, 0.0), (-1.9, 0.0), (0.95, 1.7), (-0.95, 1.7)):
            p = pos.copy()
            p[:2] += size * (ds * side + dr * u)
            n = commanded_normal(sun, p, site.aim_m)
            heliostats.append(FieldHeliostat(ensemble, p, *_tilted(n, rng, site.tracking_error_mrad)))
    distance = float(np.linalg.norm(pos - site.camera_m))
    intr = site.intrinsics(ensemble, distance)
    uc = site.uncertainty
    roll = 1e-3 * uc.camera_roll_mrad * float(rng.standard_normal())
    look = pos + 1e-3 * site.pointing_mrad * distance * rng.standard_normal(3)
    camera = TwinTowerCamera(intr, site.camera_m, camera_rotation(site.camera_m, look, roll))
    exposure = Exposure(blur_px=float(rng.uniform(0.6, 1.3)), read_noise_dn=float(rng.uniform(0.5, 2.0)))
    photo = render(camera, heliostats, Sky(sun), rng, exposure)
    k = intr.matrix.copy()
    k[0, 0] *= 1.0 + uc.focal_length_rel * float(rng.standard_normal())
    k[1, 1] = k[0, 0]
    known_cam = TowerCamera(CameraIntrinsics(intr.width_px, intr.height_px, k, intr.distortion),
                            site.camera_m + uc.camera_position_m * rng.standard_normal(3), 0.0)
    known_place = HeliostatPlace(ensemble, pos + uc.heliostat_position_m * rng.standard_normal(3), 0.0, "TWIN")
    return Shot(photo.image, photo.truth, known_cam, known_place, cmd, cmd_n, target.normal, moment, target)


def measure_orientation(shot: Shot, uncertainty: InputUncertainty) -> dict:
    """The command's path on a shot: detection, the fit and its U; against the truth."""
    t0 = time.process_time()
    predicted = predict_corners(shot.place_known, heliostat_rotation(*shot.commanded), shot.camera_known,
                                nominal_pointing(shot.camera_known, shot.place_known))
    detection = detect_facets(shot.image, shot.camera_known.intrinsics, predicted)
    result = solve_orientation(detection.facets, shot.place_known, shot.camera_known, commanded=shot.commanded,
                               uncertainty=uncertainty)
    figures = orientation_figures(result, shot.commanded_normal)
    err = pointing_error_mrad(result.normal, shot.true_normal)
    true_tracking = pointing_error_mrad(shot.true_normal, shot.commanded_normal)
    u = figures["pointing_U_mrad"]
    return {"error_mrad": err, "U_mrad": u, "U_azimuth_angle_mrad": 2.0 * result.u_azimuth_mrad,
            "facets": len(detection.facets), "left_out": detection.left_out,
            "distance_m": float(np.linalg.norm(shot.place_known.position_m - shot.camera_known.position_m)),
            "tracking_error_mrad": figures["tracking_error_mrad"], "true_tracking_error_mrad": true_tracking,
            "within_U": bool(abs(err["azimuth_mrad"]) <= u["azimuth"] and abs(err["elevation_mrad"]) <= u["elevation"]),
            "cpu_s": time.process_time() - t0}


def orientation_population(n: int, seed: int, ensemble: EnsembleDesign, site: TwinSite = TwinSite(),
                           progress=None) -> dict:
    """*n* drawn positions (seed *seed*): each one's error and U, and the shares the DLR paper states."""
    rng = np.random.default_rng(seed)
    cases, failures = [], []
    for i in range(n):
        shot = orientation_shot(site, ensemble, rng)
        try:
            case = measure_orientation(shot, site.uncertainty)
        except Exception as exc:                       # a refused photo is counted, not hidden
            failures.append({"case": i, "error": f"{type(exc).__name__}: {exc}"})
            continue
        cases.append(case)
        if progress is not None:
            progress(i + 1, n, case)
    return summarise_orientation(cases, failures, n, seed)


def summarise_orientation(cases: list, failures: list, n: int, seed) -> dict:
    angle = np.array([c["error_mrad"]["angle_mrad"] for c in cases]) if cases else np.zeros(0)
    dlr_u = np.array([max(c["U_azimuth_angle_mrad"], c["U_mrad"]["elevation"]) for c in cases]) if cases else angle
    largest = np.array([c["U_mrad"]["largest"] for c in cases]) if cases else angle
    within = [c["within_U"] for c in cases]

    def share(a, limit):
        return float(np.mean(a <= limit)) if a.size else float("nan")

    return {"seed": seed, "positions": n, "measured": len(cases), "refused": failures,
            "error_angle_mrad": {"median": float(np.median(angle)) if angle.size else None,
                                 "p80": float(np.percentile(angle, 80)) if angle.size else None,
                                 "max": float(angle.max()) if angle.size else None},
            "share_error_within_4_mrad": share(angle, DLR_ORIENTATION_MRAD),
            "share_U_within_4_mrad": share(dlr_u, DLR_ORIENTATION_MRAD),
            "U_dlr_mrad": {"median": float(np.median(dlr_u)) if dlr_u.size else None,
                           "p80": float(np.percentile(dlr_u, 80)) if dlr_u.size else None},
            "U_largest_mrad_p80": float(np.percentile(largest, 80)) if largest.size else None,
            "share_within_U": float(np.mean(within)) if within else None, "cases": cases}


def canting_campaign(site: TwinSite, ensemble: EnsembleDesign, rng: np.random.Generator, *, photos: int = 12,
                     position=None, canting_mrad: float = 1.0, damaged: dict | None = None,
                     neighbours: bool = False) -> dict:
    """A heliostat with drawn canting errors (and *damaged* {label: (rx, ry) mrad} on top), turned to
    ``photos`` orientations whose mirrors show the sky and photographed at each: the shots, and its truth."""
    pos = draw_position(site, rng) if position is None else np.asarray(position, float)
    moment, sun = draw_time(site, rng)
    errors = canting_mrad * rng.standard_normal((ensemble.n_facets, 3))
    for label, (rx, ry) in (damaged or {}).items():
        errors[ensemble.index(label), :2] += (rx, ry)
    distance = float(np.linalg.norm(pos - site.camera_m))
    intr = site.intrinsics(ensemble, distance / CANTING_ZOOM)          # zoomed in: gaps of 5 px or more
    uc = site.uncertainty
    known_cam = TowerCamera(intr, site.camera_m + uc.camera_position_m * rng.standard_normal(3), 0.0)
    known_place = HeliostatPlace(ensemble, pos + uc.heliostat_position_m * rng.standard_normal(3), 0.0, "TWIN")
    shots = []
    for az, el in canting_orientations(site.camera_m, pos, count=photos, sun=sun):
        true = FieldHeliostat(ensemble, pos, *_tilted(direction(az, el), rng, site.tracking_error_mrad), 0.0, 0.0,
                              errors)
        others = []
        if neighbours:
            for dx in (-2.5, 2.5):
                others.append(FieldHeliostat(ensemble, pos + [dx, 1.0, 0.0], az, el))
        look = pos + 1e-3 * site.pointing_mrad * distance * rng.standard_normal(3)
        camera = TwinTowerCamera(intr, site.camera_m, camera_rotation(site.camera_m, look, 0.0))
        photo = render(camera, [true] + others, Sky(sun), rng,
                       Exposure(blur_px=float(rng.uniform(0.6, 1.2)), read_noise_dn=1.0))
        shots.append(Shot(photo.image, photo.truth, known_cam, known_place, (az, el), direction(az, el),
                          true.normal, moment, true))
    return {"shots": shots, "errors_mrad": errors, "position_m": pos, "time": moment, "sun": sun}


def measure_canting(shots: list, uncertainty: InputUncertainty, factory: dict | None = None) -> dict:
    """The command's path on a campaign: every photo's detection, the bundle, the canting with U (and the
    comparison with a factory record), against the truth (the twin's canting of the facets measured)."""
    t0 = time.process_time()
    photos, refused = [], []
    for k, shot in enumerate(shots):
        r_fc = nominal_pointing(shot.camera_known, shot.place_known)
        rot = heliostat_rotation(*shot.commanded)
        predicted = predict_corners(shot.place_known, rot, shot.camera_known, r_fc)
        try:
            det = detect_facets(shot.image, shot.camera_known.intrinsics, predicted)
        except Exception as exc:
            refused.append(f"photo {k}: {exc}")
            continue
        initial = Pose(r_fc @ rot, r_fc @ (heliostat_origin(shot.place_known, rot) - shot.camera_known.position_m))
        photos.append(PhotoCorners(f"photo {k}", shot.camera_known.intrinsics, det.facets, initial))
    ensemble = shots[0].place_known.ensemble
    result = solve_canting(photos, ensemble, facet_size_u_mm=uncertainty.facet_size_mm,
                           focal_length_rel=uncertainty.focal_length_rel)
    truth = canting_truth(shots[0].twin_heliostat, list(result.canting_mrad))
    rows = []
    for lab, c in result.canting_mrad.items():
        u = result.canting_mrad_U[lab]
        e = (c["x"] - truth[lab]["x"], c["y"] - truth[lab]["y"])
        rows.append({"label": lab, "error_mrad": {"x": e[0], "y": e[1]}, "normal_error_mrad": math.hypot(*e),
                     "U_mrad": u, "within_U": abs(e[0]) <= u["x"] and abs(e[1]) <= u["y"]})
    out = {"photos": len(photos), "refused": refused, "facets": rows, "figures": canting_figures(result),
           "truth": truth, "cpu_s": time.process_time() - t0}
    if factory is not None:
        out["factory"] = compare_with_factory(result, factory)
    return out


def factory_record(truth: dict, serial: str, rng: np.random.Generator, u_mrad: float = 0.12,
                   changed: dict | None = None) -> dict:
    """A factory record (the line's heliostat record's facets: ``label``, ``canting_mrad``, ``canting_mrad_U``)
    made from the twin's truth as the line would have measured it (within its U of *u_mrad*), with *changed*
    {label: (dx, dy) mrad}: facets that moved since (transport, mounting) so the factory saw them elsewhere."""
    facets = []
    for lab, c in truth.items():
        dx, dy = (changed or {}).get(lab, (0.0, 0.0))
        noise = 0.5 * u_mrad * rng.standard_normal(2)
        facets.append({"label": lab, "status": "measured",
                       "canting_mrad": {"x": c["x"] - dx + float(noise[0]), "y": c["y"] - dy + float(noise[1])},
                       "canting_mrad_U": {"x": u_mrad, "y": u_mrad}})
    return {"serial": serial, "facet": "twin", "facets": facets,
            "note": "made from the field twin's truth for trying the field commands: not a measurement"}


def _site_text(site: TwinSite, heliostat_file: Path, width_px: int, height_px: int, matrix: list, made_by: str) -> str:
    """A site file (docs/field.md#the-site-file) of the twin's field: its place, layout.csv beside it, the
    heliostat file, the aim point and the tower camera."""
    return f"""# A field on the twin (sofast_station.field.study.{made_by})
[site]
name = "twin field"
latitude_deg = {site.latitude_deg}
longitude_deg = {site.longitude_deg}
altitude_m = {site.altitude_m}
layout = "layout.csv"
heliostat = "{Path(heliostat_file).as_posix()}"
aim_point_m = {site.aim_m.tolist()}
pivot_offset_m = 0.0

[camera]
position_m = {site.camera_m.tolist()}
roll_mrad = 0.0
width_px = {width_px}
height_px = {height_px}
matrix = {matrix}
distortion = [0.0, 0.0, 0.0, 0.0, 0.0]
"""


def write_campaign(out_dir, seed: int = 0, photos: int = 10, ensemble_file=None, site: TwinSite | None = None) -> dict:
    """A campaign on the twin written as files the commands read: a site file, its layout, one photo for
    ``field orientation`` and *photos* for ``field canting`` (each with its notes), and a factory record in
    which facet R2C2 sat 3 mrad elsewhere (a facet knocked in transport). Returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ensemble_file = Path(ensemble_file or Path(__file__).resolve().parents[2] / "fixtures" / "facets" /
                         "heliostat_5x5.toml").resolve()
    ensemble = load_ensemble(ensemble_file)
    site = site or TwinSite()
    rng = np.random.default_rng(seed)
    position = np.array([25.0, 80.0, site.pivot_height_m])
    serial = "H-0042"
    (out / "layout.csv").write_text(f"id,x,y,z\n{serial},{position[0]},{position[1]},{position[2]}\n"
                                    "H-0043,27.2,80.0,1.6\n")
    shot = orientation_shot(site, ensemble, rng, position=position)
    intr = site.intrinsics(ensemble, float(np.linalg.norm(position - site.camera_m)))
    k = intr.matrix
    (out / "site.toml").write_text(_site_text(site, ensemble_file, intr.width_px, intr.height_px, k.tolist(),
                                              f"write_campaign, seed {seed}"))
    paths = {"site": out / "site.toml", "layout": out / "layout.csv"}
    cv2.imwrite(str(out / "orientation.png"), shot.image[..., ::-1])
    (out / "orientation.json").write_text(json.dumps({"heliostat": serial, "time": shot.time,
                                                      "focal_px": float(k[0, 0]),
                                                      "truth": {"normal": shot.true_normal.tolist()}}, indent=1))
    paths["orientation"] = out / "orientation.png"
    campaign = canting_campaign(site, ensemble, rng, photos=photos, position=position,
                                damaged={"R2C2": (3.0, -2.0)})
    names = []
    intr_canting = campaign["shots"][0].camera_known.intrinsics
    for i, s in enumerate(campaign["shots"]):
        name = out / f"canting-{i:02d}.png"
        cv2.imwrite(str(name), s.image[..., ::-1])
        notes = {"heliostat": serial, "commanded": {"azimuth_deg": math.degrees(s.commanded[0]),
                                                    "elevation_deg": math.degrees(s.commanded[1])},
                 "focal_px": float(intr_canting.matrix[0, 0])}
        name.with_suffix(".json").write_text(json.dumps(notes, indent=1))
        names.append(name)
    paths["canting"] = names
    truth = canting_truth(campaign["shots"][0].twin_heliostat)
    record = factory_record(truth, serial, rng, changed={"R2C2": (3.0, -2.0)})
    (out / "factory.json").write_text(json.dumps(record, indent=1))
    (out / "truth.json").write_text(json.dumps({"canting_mrad": truth, "damaged": {"R2C2": [3.0, -2.0]}}, indent=1))
    paths["factory"] = out / "factory.json"
    return paths


def write_spot_campaign(out_dir, seed: int = 0, knocked: dict | None = None, time: str = "2026-06-21T10:00:00+00:00",
                        position=(30.0, 95.0, 1.6), peak: float = 0.7) -> dict:
    """Files for ``field spot`` on the twin: a site file and layout, a factory record of heliostat H-0042 (the
    2x2 heliostat of fixtures/facets with drawn canting errors of 0.8 mrad per axis, U 0.2 mrad; its facets'
    curvature the design's, no slope scatter) and a BCS photo of its spot on a target facing it at *time*, taken
    by the twin (:mod:`sofast_station.twin.field_spot`) of the true heliostat: the factory's, with *knocked*
    {label: (dx, dy) mrad} facets turned since. Returns their paths and the truth (the twin's spot's centroid
    and 90 % radius on the target)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    design = Path(__file__).resolve().parents[2] / "fixtures" / "facets" / "heliostat_2x2.toml"
    ensemble = load_ensemble(design)
    site = TwinSite()
    rng = np.random.default_rng(seed)
    cant = 0.8 * rng.standard_normal((ensemble.n_facets, 2))
    cant -= cant.mean(axis=0)
    serial, pos = "H-0042", np.asarray(position, dtype=np.float64)
    (out / "layout.csv").write_text(f"id,x,y,z\n{serial},{pos[0]},{pos[1]},{pos[2]}\n")
    (out / "site.toml").write_text(_site_text(site, design, 800, 600, [[8000.0, 0.0, 399.5], [0.0, 8000.0, 299.5],
                                                                      [0.0, 0.0, 1.0]],
                                              f"write_spot_campaign, seed {seed}"))
    facets = [{"label": f.label, "status": "measured", "canting_mrad": {"x": float(c[0]), "y": float(c[1])},
               "canting_mrad_U": {"x": 0.2, "y": 0.2}, "curvature_x_per_m": f.design.curvature_per_m,
               "curvature_y_per_m": f.design.curvature_per_m}
              for f, c in zip(ensemble.facets, cant)]
    (out / "factory.json").write_text(json.dumps({"serial": serial, "facet": ensemble.name, "facets": facets,
                                                  "note": "made by the field twin: not a measurement"}, indent=1))
    true = cant.copy()
    for k, f in enumerate(ensemble.facets):
        true[k] += np.asarray((knocked or {}).get(f.label, (0.0, 0.0)))
    sun = sun_direction(time, site.latitude_deg, site.longitude_deg, site.altitude_m)
    az, el = tracking(pos, site.aim_m, sun)
    heliostat = FieldHeliostat(ensemble, pos, az, el, canting_errors_mrad=np.column_stack([true, np.zeros(4)]))
    d = site.aim_m - pos
    normal = np.array([d[0], d[1], 0.0])
    normal = -normal / np.linalg.norm(normal)
    half = 2.5
    flux = spot_flux(heliostat, site.aim_m, normal, sun, half_width_m=half, cells=161, seed=seed)
    cx, cy, r90 = map_centroid_radius(flux, half)
    pixel_m, aim_px = 0.01, (230.4, 210.6)
    photo = bcs_photo(flux, half, (420, 460), pixel_m, aim_px, rng, peak=peak)
    cv2.imwrite(str(out / "bcs.png"), photo)
    (out / "bcs.json").write_text(json.dumps({"time": time, "pixel_m": pixel_m, "aim_px": list(aim_px),
                                              "heliostat": serial}, indent=1))
    return {"site": out / "site.toml", "factory": out / "factory.json", "photo": out / "bcs.png",
            "truth": {"centroid_m": {"x": cx, "y": cy}, "spot_radius_m": r90}}


def spot_population(n: int, seed: int, ensemble_file=None, site: TwinSite | None = None) -> dict:
    """The spot's prediction against the twin's own trace over *n* drawn cases: heliostats 40 to 160 m from the
    tower within +-70 deg, the sun 20 deg or more above the horizon on a drawn day and hour, canting errors of
    1 mrad per axis (U 0.1 mrad), every second case with flat facets. Returns each case's differences and the
    prediction's U (centroid x, y; 90 % radius), metres."""
    site = site or TwinSite()
    ensemble = load_ensemble(ensemble_file or Path(__file__).resolve().parents[2] / "fixtures" / "facets" /
                             "heliostat_2x2.toml")
    labels = [f.label for f in ensemble.facets]
    size = float(np.max(np.abs([f.position_m[:2] for f in ensemble.facets])))
    rng = np.random.default_rng(seed)
    cases = []
    while len(cases) < n:
        r, a = rng.uniform(40.0, 160.0), math.radians(rng.uniform(-70.0, 70.0))
        pos = np.array([r * math.sin(a), r * math.cos(a), site.pivot_height_m])
        hour = rng.uniform(7.0, 17.0)
        when = f"2026-{int(rng.integers(1, 13)):02d}-15T{int(hour):02d}:{int(60 * (hour % 1)):02d}:00+00:00"
        sun = sun_direction(when, site.latitude_deg, site.longitude_deg, site.altitude_m) \
            if _sun_up(when, site) else None
        if sun is None or math.degrees(math.asin(sun[2])) < 20.0:
            continue
        cant = rng.normal(0.0, 1.0, (len(labels), 2))
        cant -= cant.mean(axis=0)
        flat = len(cases) % 2 == 1
        plane = facing_target(site.aim_m, pos)
        twin = FieldHeliostat(ensemble, pos, *tracking(pos, site.aim_m, sun),
                              canting_errors_mrad=np.column_stack([cant, np.zeros(len(labels))]))
        slant = float(np.linalg.norm(site.aim_m - pos))
        half = 3.0 * slant * 4.65e-3 + 2.0 * size + 0.5
        flux = spot_flux(twin, site.aim_m, plane.normal, sun, half_width_m=half, cells=161, seed=len(cases),
                         curvature_per_m={k: (0.0, 0.0) for k in labels} if flat else None)
        tx, ty, tr = map_centroid_radius(flux, half)
        models = [FacetModel(k, cant[i], np.full(2, 0.1), np.zeros(2) if flat else None)
                  for i, k in enumerate(labels)]
        f = predict_spot(models, ensemble, SpotScene(pos, 0.0, plane, sun), half_width_m=half,
                         seed=len(cases) + 1)["figures"]
        cases.append({"time": when, "position_m": pos.tolist(), "slant_range_m": slant, "flat": flat,
                      "twin_radius_m": tr,
                      "difference_m": [f["centroid_m"]["x"] - tx, f["centroid_m"]["y"] - ty, f["spot_radius_m"] - tr],
                      "U_m": [f["centroid_m_U"]["x"], f["centroid_m_U"]["y"], f["spot_radius_m_U"]]})
    d = np.abs(np.array([c["difference_m"] for c in cases]))
    u = np.array([c["U_m"] for c in cases])
    return {"seed": seed, "cases": cases, "largest_m": d.max(axis=0).tolist(),
            "rms_m": np.sqrt(np.mean(d ** 2, axis=0)).tolist(), "median_U_m": np.median(u, axis=0).tolist(),
            "share_within_U": np.mean(d <= u, axis=0).tolist()}


def _sun_up(when: str, site: TwinSite) -> bool:
    return bool(sun_position([when], site.latitude_deg, site.longitude_deg, site.altitude_m)[0][1] > 0)


__all__ = ["TwinSite", "orientation_shot", "measure_orientation", "orientation_population", "canting_campaign",
           "measure_canting", "factory_record", "write_campaign", "write_spot_campaign",
           "spot_population"]
