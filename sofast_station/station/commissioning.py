"""The geometry commissioning run on a station: ``calibrate screen``, ``calibrate pose`` and the whole
``calibrate commission`` (radiometric, screen, pose, geometry in order, one summary).

Each step opens the station from its configuration, runs its routine (:mod:`sofast_station.calibrate`)
through the device protocols, writes its record and returns a :class:`Step`: its verdict (``pass``,
``warn``, ``fail``: a reference check outside tolerance, ``refused``: no record, the parameters were not
determined or the routine could not run), a summary ending with that verdict, and its data. On a real
station the technician is asked, on the console, for every view and placement; on the simulated station
the twin's second camera and reference mirror move instead.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import __version__
from ..calibrate.camera import load_camera_record
from ..calibrate.commission_settings import commission_settings, load_mirror_target
from ..calibrate.errors import CalibrationError
from ..calibrate.geometry import check_geometry, load_reference, pitch_sensitivities, station_reference
from ..calibrate.geometry import summary_text as geometry_summary
from ..calibrate.geometry_record import save_geometry
from ..calibrate.pose import calibrate_pose, pose_std, save_pose
from ..calibrate.pose import summary_text as pose_summary
from ..calibrate.screen import calibrate_screen, load_screen_record, save_screen
from ..calibrate.screen import summary_text as screen_summary
from ..calibrate.settings import calibration_settings
from ..calibrate.store import check_warmup, newest_record_path
from ..config import load_config
from ..devices.cameras import open_camera
from ..errors import ConfigError
from ..measure.screen_shape import ScreenShape
from ..measure.uncertainty import sensitivity_key
from .factory import open_station
from .inspection import inspect
from .temperature import read_temperature

log = logging.getLogger(__name__)


@dataclass
class Step:
    """One calibration step's outcome."""

    name: str
    verdict: str
    summary: str
    data: dict = field(default_factory=dict)
    path: str | None = None

    def line(self) -> str:
        """One line for the commissioning summary."""
        first = self.summary.splitlines()[-1] if self.verdict == "refused" else self.data.get("headline", "")
        return f"  {self.name:12s} {self.verdict.upper():8s} {first}"


def _prompt(what: str):
    """``place(k, n, hint)`` for a real station: ask the technician on the console."""

    def place(k: int, n: int, hint: str) -> None:
        input(f"{what} {k + 1} of {n}: {hint}. Press Enter when ready ")

    return place


def _handheld_intrinsics(config, settings):
    """The second camera's calibration: its newest ``handheld`` record, else [calibration.screen] camera."""
    path = newest_record_path(config.data_dir, "handheld", config.identity)
    if path is not None:
        camera, record = load_camera_record(path)
        std = record.get("std_intrinsics") or {}
        prior = list(settings.camera.std)
        try:
            prior[:4] = [float(std["fx"]), float(std["fy"]), float(std["cx"]), float(std["cy"])]
            if len(std.get("distortion", [])) == 5:
                prior[4:] = [float(v) for v in std["distortion"]]
        except (KeyError, TypeError, ValueError):
            pass
        return camera, tuple(prior), f"handheld camera record {path.name}"
    if settings.camera.intrinsics is None:
        raise ConfigError(f"{config.path} [calibration.screen]: no calibration of the second camera: run "
                          "'sofast-station calibrate camera --handheld IMAGES...' with it, or give "
                          "[calibration.screen] camera")
    return settings.camera.intrinsics, tuple(settings.camera.std), f"{config.path} [calibration.screen] camera"


def _open_handheld(station, config, settings, seed):
    """The second camera and its ``place``: the twin's on the simulated station, else [devices]
    handheld_camera's with the technician asked for every view."""
    if hasattr(station, "handheld_camera"):
        cam = station.handheld_camera(settings, seed)
        return cam, cam.place

    dev = config.raw.get("devices", {})
    kind = dev.get("handheld_camera")
    if kind is None:
        raise ConfigError(f"{config.path} [devices]: name the second camera of calibrate screen (handheld_camera = "
                          "\"aravis\" or \"basler\", handheld_camera_options = {...})")
    return open_camera(kind, **dict(dev.get("handheld_camera_options", {}))), _prompt("Second camera, view")


def _enough(what: str, wanted: int, least: int, from_command_line: bool, config, section: str) -> None:
    """Refuse, before anything is measured, to take fewer *what* (views, placements) than the calibration needs
    to keep a record: the routine would take them all, then refuse."""
    if wanted < least:
        said = f"--{what} {wanted}" if from_command_line else f"{config.path} [calibration.{section}] {what} = {wanted}"
        raise ConfigError(f"{said}: calibrate {section} needs at least {least} usable {what} ([calibration.{section}] "
                          f"min_{what}) and refuses fewer; take at least {least}")


def check_commission(config, *, reference: str | None = None, target: str | None = None) -> None:
    """Every input of ``calibrate commission`` read and checked before its first step runs (the radiometric
    step took minutes before a mistyped ``--target`` stopped the pose step): the steps' settings, the views and
    placements they take, the reference mirror's certificate and the reference facet's.

    Raises
    ------
    ConfigError
        Naming the argument or key and what to do.
    """
    screen, pose = commission_settings(config.raw, config.path.parent, str(config.path))
    _enough("views", screen.views, screen.min_views, False, config, "screen")
    _enough("placements", pose.placements, pose.min_placements, False, config, "pose")
    try:
        load_mirror_target(target or pose.target)
    except ConfigError as exc:
        raise ConfigError(f"{'--target' if target else f'{config.path} [calibration.pose] target'}: {exc}") from None
    if reference:
        try:
            load_reference(reference)
        except ConfigError as exc:
            raise ConfigError(f"--reference: {exc}") from None
    elif config.backend != "simulated":
        raise ConfigError(f"{config.path}: a hardware station needs the reference facet's certificate for the "
                          "geometry step (--reference FILE with a [reference] table)")


def run_screen(config, *, views: int | None = None, model: str | None = None, seed: int | None = None,
               noise: bool = True) -> Step:
    """``calibrate screen`` on the station of *config*."""
    settings, _ = commission_settings(config.raw, config.path.parent, str(config.path))
    if views is not None or model is not None:
        # `views or ...` took --views 0 for "the default" and ran the station file's views without a word
        settings = dataclasses.replace(settings, views=settings.views if views is None else views,
                                       model=model or settings.model)
    _enough("views", settings.views, settings.min_views, views is not None, config, "screen")
    intrinsics, std, source_cam = _handheld_intrinsics(config, settings)
    stated = (config.stated_geometry or config.geometry).screen
    log.info("screen calibration of %s: %d views with the second camera (%s)", config.name, settings.views, source_cam)
    station = open_station(config, seed=seed, noise=noise, calibration_checks=False)
    try:
        camera, place = _open_handheld(station, config, settings, seed)
        try:
            cal = calibrate_screen(station.display, camera, place, settings, stated, config.fringes, intrinsics, std)
        except CalibrationError as exc:
            return Step("screen", "refused", f"{exc}\nverdict: REFUSED")
        finally:
            camera.close()
    finally:
        station.close()
    if cal.verdict == "refused":
        return Step("screen", "refused", screen_summary(cal), {"quality": cal.quality})
    source = f"sofast-station {__version__} calibrate screen on {config.name} ({config.backend}; {source_cam})"
    path = save_screen(config.data_dir, cal, source, station=config.identity)
    best = cal.fit.best
    h = best.shape.height_summary()
    rel = [best.shape.pitch_scale[0] - 1.0, best.shape.pitch_scale[1] - 1.0]
    headline = (f"pitch {100 * rel[0]:+.3f} % / {100 * rel[1]:+.3f} % against station.toml, {best.shape.model}, "
                f"sag {1e3 * h['sag_m']:+.3f} mm, twist {1e3 * h['twist_m']:+.3f} mm; {path.name}")
    return Step("screen", cal.verdict, screen_summary(cal, path),
                {"path": str(path), "headline": headline, "quality": cal.quality, "model": best.shape.model,
                 "pitch_vs_stated_relative": rel, "heights": h}, str(path))


def run_pose(config, *, placements: int | None = None, target: str | None = None, seed: int | None = None,
             noise: bool = True) -> Step:
    """``calibrate pose`` on the station of *config*."""
    _, settings = commission_settings(config.raw, config.path.parent, str(config.path))
    if placements is not None:
        settings = dataclasses.replace(settings, placements=placements)
    _enough("placements", settings.placements, settings.min_placements, placements is not None, config, "pose")
    mirror = load_mirror_target(target or settings.target)
    stated = config.stated_geometry or config.geometry
    screen_path = newest_record_path(config.data_dir, "screen", config.identity)
    if screen_path is not None:
        rec = load_screen_record(screen_path)
        shape = ScreenShape.from_dict(rec["shape"])
        cov = np.asarray(rec["covariance"], dtype=np.float64)
        pitch_std = tuple(float(v) for v in np.sqrt(np.clip(np.diag(cov)[:2], 0.0, None)))
        screen_record = rec["record_id"]
    else:
        shape = ScreenShape("flat", stated.screen.width_m, stated.screen.height_m)
        pitch_std, screen_record = (0.0, 0.0), None
    camera_std = None
    if config.camera_record is not None and isinstance(config.camera_record.get("std"), dict):
        s = config.camera_record["std"]
        try:
            camera_std = [float(s["fx"]), float(s["fy"]), float(s["cx"]), float(s["cy"]),
                          *[float(v) for v in s.get("distortion", [0.0] * 5)]]
        except (KeyError, TypeError, ValueError):
            camera_std = None
    log.info("pose calibration of %s: %d placements of %s", config.name, settings.placements, mirror.name)
    station = open_station(config, seed=seed, noise=noise, calibration_checks=False)
    try:
        if hasattr(station, "mirror_placer"):
            placer = station.mirror_placer(mirror, seed)
            place, restore = placer.place, placer.restore
        else:
            place = _prompt("Reference mirror, placement")

            def restore():
                input("Take the reference mirror out of the fixture. Press Enter when done ")
        try:
            cal = calibrate_pose(station.display, station.camera, station.range_finder, place, settings, mirror,
                                 stated, config.design, config.fringes, shape, pitch_std=pitch_std,
                                 screen_record=screen_record, camera_std=camera_std,
                                 distance_std_mm=config.uncertainty.distance_mm)
        except CalibrationError as exc:
            return Step("pose", "refused", f"{exc}\nverdict: REFUSED")
        finally:
            restore()
    finally:
        station.close()
    if cal.verdict == "refused":
        return Step("pose", "refused", pose_summary(cal), {"quality": cal.quality})
    source = f"sofast-station {__version__} calibrate pose on {config.name} ({config.backend}; {mirror.name})"
    path = save_pose(config.data_dir, cal, source, station=config.identity)
    std = pose_std(cal.fit.screen_covariance)
    headline = (f"screen depth U {2 * std['translation_mm'][2]:.2f} mm, rotation U "
                f"{2 * max(std['rotation_mrad']):.2f} mrad (k=2); {path.name}")
    return Step("pose", cal.verdict, pose_summary(cal, path),
                {"path": str(path), "headline": headline, "quality": cal.quality, "screen_std": std}, str(path))


def sensitivities_in_force(station):
    """The uncertainty's sensitivities the station's analyses used (from its cache; None when it has none):
    the geometry check reads the screen pitch's from them."""
    config = station.config
    if getattr(config, "uncertainty", None) is None:
        return None
    key = sensitivity_key(config.geometry, config.design, config.fringes, config.analysis, config.uncertainty)
    return (getattr(station, "sensitivity_cache", None) or {}).get(key)


def run_geometry(config, *, reference: str | None = None, seed: int | None = None, noise: bool = True) -> Step:
    """``calibrate geometry`` (the reference facet checks the whole chain) on the station of *config*."""
    station = open_station(config, seed=seed, noise=noise)
    try:
        log.info("measuring the reference facet on %s", config.name)
        rec = inspect(station, "GEOMETRY-REFERENCE")
        ref = station_reference(station, reference)        # the twin's: over the pixels the inspection kept
        # the screen pitch's sensitivities the station's analyses used: the check estimates the screen's scale
        check = check_geometry(rec, ref, config.uncertainty, pitch_sensitivities(sensitivities_in_force(station)))
    finally:
        station.close()
    source = f"sofast-station {__version__} calibrate geometry with {ref.name}"
    path = save_geometry(config.data_dir, config, check, source, station=config.identity)
    verdict = "pass" if check["within_tolerance"] else "fail"
    f = check["focal_lengths"]
    rel = [f[a]["relative_error"] for a in ("x", "y")]
    headline = ("f " + ", ".join(f"{a} {100 * r:+.4f} %" for a, r in zip("xy", rel) if r is not None)
                + f" against the certificate; {path.name}")
    return Step("geometry", verdict, geometry_summary(check, path) + f"\nverdict: {verdict.upper()}",
                {"path": str(path), "headline": headline, **check}, str(path))


def run_marks(config, *, seed: int | None = None, noise: bool = True, confirmed_by: str | None = None) -> Step:
    """``calibrate marks`` on the station of *config*: the fixture's marks' places now become the commissioned
    ones (a new ``marks`` record, which also ends a hold the line put itself on; :mod:`sofast_station.calibrate.marks`).
    *confirmed_by*: the geometry record of the reference check that confirmed the geometry first
    (``calibrate confirm-geometry``)."""
    # lazy: calibrate.marks costs ~340 ms CPU (+219 modules, scipy) after this module; only marks need it
    from ..calibrate.marks import clear_hold, commission_marks, focal_px, mark_settings, save_marks_record

    settings = mark_settings(config)
    if settings is None:
        raise ConfigError(f"{config.path} has no [marks] table: describe the fixture's marks (centres_mm, diameter_mm; "
                          "docs/reliability.md#the-station-checks-itself) before commissioning them")
    station = open_station(config, seed=seed, noise=noise, calibration_checks=False)
    try:
        try:
            found = commission_marks(station.display, station.camera, settings, config.geometry)
        except CalibrationError as exc:
            return Step("marks", "refused", f"{exc}\nverdict: REFUSED")
    finally:
        station.close()
    pose = newest_record_path(config.data_dir, "pose", config.identity)
    source = f"sofast-station {__version__} calibrate marks on {config.name} ({config.backend})"

    extra = {"pose_record": pose.stem if pose is not None else None, "confirmed_by": confirmed_by,
             "temperature_c": read_temperature(config)}
    path, record_id = save_marks_record(config.data_dir, found, settings, config.geometry, source,
                                        station=config.identity, extra=extra)
    ended = clear_hold(config.data_dir)
    off = np.hypot(*(found.positions_px - found.predicted_px).T)
    spread = float(np.sqrt(np.mean(found.std_px ** 2))) if found.frames > 1 else float("nan")
    f = focal_px(config.geometry)
    headline = (f"{len(off)} marks, {spread:.3f} px repeatability (RMS over {found.frames} frames), "
                f"{off.max():.1f} px ({1e3 * off.max() / f:.2f} mrad) at most from where the geometry puts them; "
                f"{path.name}")
    lines = [f"Fixture marks of {config.name}: {len(off)} found in {found.frames} white frames; record {path}",
             f"  image radius {found.radius_px:.1f} px, contrast {found.contrast_dn.min():.0f} DN at least",
             f"  repeatability {spread:.4f} px RMS per coordinate (a cycle's check stops the line at "
             f"{settings.max_turn_mrad:g} mrad = {1e-3 * settings.max_turn_mrad * f:.2f} px)",
             f"  found {np.median(off):.2f} px (median), {off.max():.2f} px (worst) from the geometry's prediction"]
    if confirmed_by:
        lines.append(f"  the geometry was confirmed first by the reference check {confirmed_by}")
    if ended:
        lines.append("  the line's hold (a moved camera) is ended: the station judges facets again at its next start")
    lines.append("verdict: PASS")
    return Step("marks", "pass", "\n".join(lines),
                {"path": str(path), "record_id": record_id, "headline": headline, "positions_px": found.positions_px,
                 "std_px": found.std_px, "hold_ended": ended}, str(path))


def confirm_geometry(config, *, reference: str | None = None, seed: int | None = None,
                     noise: bool = True) -> list[Step]:
    """``calibrate confirm-geometry``: after the marks showed a moved camera, a reference facet measured against
    its certificate (``calibrate geometry``) confirms the geometry still measures right; only then the marks'
    new places are taken as the commissioned ones (``calibrate marks``), which ends the line's hold. A check
    outside tolerance takes nothing: recommission (``calibrate commission``)."""
    steps = [run_geometry(config, reference=reference, seed=seed, noise=noise)]
    if steps[0].verdict == "pass":
        steps.append(run_marks(config, seed=seed, noise=noise,
                               confirmed_by=Path(steps[0].path).stem if steps[0].path else None))
    else:
        steps[0].summary += ("\nThe geometry is not confirmed: the marks' places are not taken and the line stays on "
                             "hold. Recommission the station: 'sofast-station calibrate commission'")
    return steps


def commission_steps(config) -> list[str]:
    """The steps ``calibrate commission`` runs on the station of *config*, in order (``marks`` when it has
    ``[marks]``)."""
    # lazy: calibrate.marks costs ~340 ms CPU (+219 modules, scipy); the other steps never need it
    from ..calibrate.marks import mark_settings

    names = ["radiometric", "screen", "pose", "geometry"]
    return names + (["marks"] if mark_settings(config) is not None else [])


def run_radiometric(config, *, seed: int | None = None, noise: bool = True, plot: bool = True,
                    overrides: dict | None = None) -> Step:
    """``calibrate radiometric`` (with its display-latency self-test) on the station of *config*."""
    # lazy: calibrate.radiometric costs ~1 s CPU (+684 modules, scipy) after this module; only it needs it
    from ..calibrate.radiometric import calibrate_radiometric, save_radiometric
    from ..calibrate.radiometric import summary_text as radiometric_summary

    policy, settings = calibration_settings(config)
    if overrides:
        try:
            settings = dataclasses.replace(settings, **overrides)
        except ConfigError as exc:
            raise ConfigError(f"command line: {exc}") from None
    log.info("radiometric calibration of %s (%s); records in %s", config.name, config.backend,
             config.data_dir / "calibration" / "radiometric")
    station = open_station(config, seed=seed, noise=noise, calibration_checks=False)
    try:
        check_warmup(policy, config.data_dir, station.camera)
        result = calibrate_radiometric(station.display, station.camera, settings)
        source = (f"sofast-station {__version__} calibrate radiometric on {config.name} ({config.backend} backend, "
                  f"{type(station.camera).__name__}, {type(station.display).__name__})")
        record = save_radiometric(config.data_dir, result, source, plot=plot, station=config.identity)
    finally:
        station.close()
    headline = (f"exposure {1e3 * record.exposure_s:.2f} ms, gain {record.gain:.3f}, display latency "
                f"{record.latency_frames} frame(s); {record.path.name}")
    data = {k: v for k, v in record.to_dict(curve=True).items() if k != "lut"} | {"path": str(record.path),
                                                                               "headline": headline}
    return Step("radiometric", "pass", radiometric_summary(record, record.path) + "\nverdict: PASS", data,
                str(record.path))


def commission(config_path, *, seed: int | None = None, noise: bool = True, reference: str | None = None,
               target: str | None = None, progress=None) -> tuple[list[Step], str]:
    """The whole commissioning: radiometric, screen, pose, geometry, in order, once every input is checked
    (:func:`check_commission`), then, on a station with fixture marks, their places (``marks``: the geometry
    the reference confirmed is the one the marks keep watch over); the configuration is read again after each
    step (its records change the geometry in force). Stops at a step that is refused or fails. Returns the
    steps and the overall verdict (the worst step's)."""
    say = progress or log.info
    first = load_config(config_path)
    check_commission(first, reference=reference, target=target)
    steps: list[Step] = []
    every = {"radiometric": lambda c: run_radiometric(c, seed=seed, noise=noise),
             "screen": lambda c: run_screen(c, seed=seed, noise=noise),
             "pose": lambda c: run_pose(c, target=target, seed=seed, noise=noise),
             "geometry": lambda c: run_geometry(c, reference=reference, seed=seed, noise=noise),
             "marks": lambda c: run_marks(c, seed=seed, noise=noise)}
    runs = [(name, every[name]) for name in commission_steps(first)]
    for k, (name, run) in enumerate(runs):
        say(f"commissioning step {k + 1} of {len(runs)}: calibrate {name}")
        step = run(load_config(config_path))
        steps.append(step)
        say(f"calibrate {name}: {step.verdict.upper()}")
        if step.verdict in ("refused", "fail"):
            break
    order = ["pass", "warn", "fail", "refused"]
    verdict = max((s.verdict for s in steps), key=order.index)
    if len(steps) < len(runs) and verdict == "pass":
        verdict = "fail"
    return steps, verdict


def commission_summary(config_name: str, steps: list[Step], verdict: str, total: int = 4) -> str:
    lines = [f"Commissioning of {config_name}"]
    lines += [s.line() for s in steps]
    if len(steps) < total:
        lines.append(f"  (stopped after {steps[-1].name}: the later steps need it)")
    lines.append(f"verdict: {verdict.upper()}")
    return "\n".join(lines)
