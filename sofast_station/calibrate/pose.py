"""``calibrate pose``: the station camera's pose against the screen, and the fixture's, from a reference mirror.

The technician seats the reference mirror (a front-surface flat mirror in a certified printed ChArUco frame,
:class:`~sofast_station.calibrate.commission_settings.MirrorTarget`) on the fixture's pins, then again
tilted by shims under each edge in turn. At every placement the station runs its own capture: the frame's
corners place the mirror's plane, the fringes tell which display position every pixel sees through the
mirror, and the range finder measures from the screen centre to the mirror's marked point.
:func:`~sofast_station.measure.commission.fit_pose` fits the screen's pose in the camera frame (6 degrees of
freedom) to all placements at once, with the screen's shape and pitch from the screen record in force
(``calibrate screen``; without one, the flat screen station.toml states). The seated placement gives the
fixture's pose.

Of the pose's six parameters the distance from the camera to the screen along the screen's normal matters
most: 1 mm moves a focal length by 0.0046 % on the default station (docs/calibration.md); the rotations and
the sideways shifts a hundred times less. The thresholds of :func:`judge_pose` follow that.

The routine sees the hardware through the Display, Camera and RangeFinder protocols and a
``place(k, n, hint)`` callback (the technician; on the simulated station, the twin's mirror scene).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import ConfigError
from ..fringes import FringeSet, Pattern
from ..geometry import Pose, StationGeometry
from ..layout import mirror_seat
from ..measure.bundle import motion_between
from ..measure.fiducials import CharucoLayout, detect_charuco
from .commission_settings import MirrorTarget, PoseSettings
from .errors import CalibrationError
from .store import write_record

log = logging.getLogger(__name__)

SCHEMA = 1

#: Standard uncertainties of the screen's pose: (warn above, refuse above), by what they do to a facet's
#: figures on the default station (docs/calibration.md, the sensitivities there): a turn about the screen's
#: x or y axis moves nothing measurable (1e-8 of f per mrad), about its z axis the twist (6e-4 mrad/m per
#: mrad); a shift along x or y moves f by 4e-6 per mm and the twist by 7e-5 mrad/m per mm; along z, the
#: screen's normal, f moves by 0.0046 % per mm. The mirror sees the turns about x and y and the shifts
#: along x and y only as far as its frame's print and the drawing hold them (a few mrad and mm).
TILT_STD_MRAD = (3.0, 10.0)
TURN_STD_MRAD = (0.5, 2.0)
SHIFT_STD_MM = (5.0, 20.0)
DEPTH_STD_MM = (0.3, 1.0)
#: Reprojection RMS of the frame's corners and of the fringe pixels, pixels: (warn, refuse).
RMS_PX = (0.3, 1.0)
#: The placements' mirror normals must differ by at least this, mrad (else warn: the mirror's tilt and
#: the screen's position are told apart by the fit's other observations only).
MIN_TILT_SPREAD_MRAD = 1.0


@dataclass
class PlacementReport:
    label: str
    used: bool = False
    reason: str = ""
    corners: int = 0
    border_points: int = 0
    mirror_pixels: int = 0
    distance_m: float | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class PoseCalibration:
    """The pose calibration: the fit, every placement's verdict, the fixture and the judgement."""

    fit: object
    placements: list
    target: MirrorTarget
    stated: StationGeometry
    screen_record: str | None
    fixture_to_camera: Pose | None = None
    fixture_covariance: np.ndarray | None = None
    #: (12, 12): the screen's small motion (6) then the fixture's (6), rad and m (:func:`joint_pose_covariance`).
    joint_covariance: np.ndarray | None = None
    quality: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return self.quality.get("verdict", "refused")


def placement_hints(n: int) -> list[str]:
    """What to ask for placement k of *n*: seated, then tilted by a shim under each edge in turn."""
    edges = ["left", "top", "right", "bottom"]
    out = ["seated on the fixture's pins, no shims"]
    for k in range(1, n):
        out.append(f"on the fixture's pins with the 1 mm shim under its {edges[(k - 1) % 4]} edge")
    return out


def target_layout(target: MirrorTarget):
    return CharucoLayout(target.squares[0], target.squares[1], target.square_m, target.marker_m, target.dictionary,
                         target.first_id)


def analyse_placement(label: str, frames: np.ndarray, distance_m: float, target: MirrorTarget, stated: StationGeometry,
                      fringes: FringeSet, settings: PoseSettings, layout=None):
    """One placement's observations: (MirrorPlacement or None, PlacementReport)."""
    # lazy: measure/commission.py costs ~300 ms CPU (scipy.optimize); config loads this module's record reader
    from ..measure.commission import MirrorPlacement, _pnp, decode_positions, fringe_samples, target_border

    layout = layout if layout is not None else target_layout(target)
    report = PlacementReport(label, distance_m=float(distance_m))
    ids, px, markers = detect_charuco(frames[0], layout)
    report.corners = int(len(ids))
    if len(ids) < settings.min_corners:
        report.reason = (f"target not found: {len(ids)} corners ({markers} markers) of the mirror's printed frame, at "
                         f"least {settings.min_corners} needed; is the reference mirror in the fixture, facing the "
                         "camera, and lit by the room?")
        return None, report
    decoded = decode_positions(frames, fringes, (stated.screen.width_m, stated.screen.height_m))
    report.mirror_pixels = int(decoded.valid.sum())
    if report.mirror_pixels < settings.min_mirror_pixels:
        report.reason = (f"the mirror shows the screen's fringes on {report.mirror_pixels} pixels (at least "
                         f"{settings.min_mirror_pixels} needed): is it the mirror side up, and the screen on?")
        return None, report
    f_px, f_uv, f_sigma = fringe_samples(decoded, settings.max_samples)
    xy = layout.corners()[ids]
    try:
        rough = _pnp(np.column_stack([xy, np.zeros(len(xy))]), px, stated.camera)
    except ValueError:
        report.reason = "the target's corners fit no pose (misdetected?): seat the mirror again"
        return None, report
    border = target_border(frames[0], stated.camera, rough, target.squares[0] * target.square_m,
                           target.squares[1] * target.square_m, target.border_m)
    report.border_points = int(len(border[0]))
    report.used = True
    return MirrorPlacement(label, px, xy, f_px, f_uv, f_sigma, float(distance_m), *border), report


def calibrate_pose(display, camera, range_finder, place: Callable[[int, int, str], None], settings: PoseSettings,
                   target: MirrorTarget, stated: StationGeometry, design, fringes: FringeSet, shape, *,
                   pitch_std=(0.0, 0.0), screen_record: str | None = None, camera_std=None,
                   distance_std_mm: float = 0.5, progress: Callable[[str], None] | None = None) -> PoseCalibration:
    """Run the pose calibration (module docstring).

    Parameters
    ----------
    display, camera, range_finder
        The station's devices.
    place : callable
        ``place(k, n, hint)``: bring the reference mirror to placement k of n.
    settings : PoseSettings
    target : MirrorTarget
        The reference mirror's certificate.
    stated : StationGeometry
        The geometry station.toml states (the camera, the screen's pixels, the designed poses: the start).
    design : FacetDesign
        The facet design of the fixture (where the mirror seats).
    fringes : FringeSet
    shape : ScreenShape
        The screen's shape (the screen record's, or a flat one).
    pitch_std : (float, float)
        Its pitch terms' standard deviations.
    screen_record : str, optional
        The screen record's id (for the pose record).
    camera_std : (9,) array, optional
        The station camera's parameters' standard deviations (the camera record's), or None to hold them.
    distance_std_mm : float
        The range finder's standard uncertainty.

    Raises
    ------
    CalibrationError
        Too few usable placements (what to do is in the message).
    """
    # lazy: measure/commission.py costs ~300 ms CPU (scipy.optimize); config loads this module's record reader
    from ..measure.commission import fit_pose

    say = progress or log.info
    layout = target_layout(target)
    hints = placement_hints(settings.placements)
    placements, reports = [], []
    for k in range(settings.placements):
        place(k, settings.placements, hints[k])
        frames = None
        for i, pattern in enumerate(fringes.patterns()):
            display.show(pattern)
            frame = camera.grab()
            if frames is None:
                frames = np.empty((fringes.n_frames, *frame.shape), dtype=frame.dtype)
            frames[i] = frame
        distance = float(range_finder.measure())
        pl, report = analyse_placement(f"placement {k + 1}", frames, distance, target, stated, fringes, settings,
                                       layout)
        reports.append(report)
        if pl is None:
            if k == 0:
                raise CalibrationError(f"placement 1 (seated, which gives the fixture's pose): {report.reason}")
            say(f"placement {k + 1}/{settings.placements}: not used: {report.reason}")
            continue
        placements.append(pl)
        say(f"placement {k + 1}/{settings.placements}: {report.corners} target corners, {report.mirror_pixels} "
            f"pixels see the screen through the mirror, distance {distance:.4f} m")
    display.show(Pattern("uniform", command=0))
    if len(placements) < settings.min_placements:
        lines = "\n".join(f"  {r.label}: {r.reason}" for r in reports if not r.used)
        raise CalibrationError(f"too few placements: {len(placements)} usable of {len(reports)}, at least "
                               f"{settings.min_placements} needed: seat the reference mirror, then tilt it with the "
                               f"shims under each edge in turn.\n{lines}")
    say(f"fitting the camera's pose against the screen to {len(placements)} placements")
    try:
        assembly = [1e-3 * settings.assembly_mrad] * 3 + [1e-3 * settings.assembly_mm] * 3
        fit = fit_pose(placements, stated.camera, shape, stated.screen_to_camera, pitch_std=pitch_std,
                       camera_std=camera_std, scale_u=target.scale_u_relative, measure_point_xy=target.measure_point,
                       distance_std_m=1e-3 * distance_std_mm, assembly_std=assembly)
    except ValueError as exc:
        raise CalibrationError(f"the pose cannot be fitted ({exc}); seat the mirror again and repeat") from None
    cal = PoseCalibration(fit, reports, target, stated, screen_record)
    seat = mirror_seat(design, target.window_centre_m)
    seating = np.diag([(1e-3 * target.seating_u_mrad) ** 2] * 3 + [(1e-3 * target.seating_u_mm) ** 2] * 3)
    cal.fixture_to_camera, cal.joint_covariance = joint_pose_covariance(fit, seat, seating)
    cal.fixture_covariance = cal.joint_covariance[6:, 6:]
    cal.quality = judge_pose(cal)
    return cal


#: The joint covariance's parameters, in order (the budget's rows of the screen's and the fixture's pose).
JOINT_PARAMETERS = ("screen rx", "screen ry", "screen rz", "screen tx", "screen ty", "screen tz",
                    "fixture rx", "fixture ry", "fixture rz", "fixture tx", "fixture ty", "fixture tz")


def joint_pose_covariance(fit, seat: Pose, seating: np.ndarray) -> tuple[Pose, np.ndarray]:
    """The fixture's pose and the (12, 12) covariance of the screen's and the fixture's small motions together.

    The fit finds the seated mirror's pose (target 0) and the screen's in one least-squares problem: the
    mirror's tilt is fixed by its printed frame to milliradians only, the fringes then say where the screen is
    as seen through that mirror, so their errors are correlated, and they largely cancel in what a facet
    measured at the same place reports in the fixture (its optical tilt). The covariance is the fit's own
    (Gauss-Newton, its weighted Jacobian at the solution: ``solution.covariance["joint"]``), the mirror's block
    carried to the fixture by the first-order derivative of ``fixture = target o seat^-1``; the seat's
    repeatability (*seating*, rad^2 and m^2) is independent of the fit and adds to the fixture's block only.

    Returns
    -------
    fixture_to_camera : Pose
    covariance : (12, 12) array
        The screen's rotation (rad) and shift (m) about and along its own axes through its centre, then the
        fixture's about and along its own: :data:`JOINT_PARAMETERS`.
    """
    # lazy: measure/commission.py costs ~300 ms CPU (scipy.optimize); config loads this module's record reader
    from ..measure.commission import motion_jacobian

    sol = fit.solution
    slices = dict(sol.order)
    joint = sol.covariance["joint"]
    idx = np.r_[np.arange(slices["screen"].start, slices["screen"].stop),
                np.arange(slices["target 0"].start, slices["target 0"].stop)]
    fixture, jac = motion_jacobian(fit.targets[0], lambda t: t.compose(seat.inverse()))
    carry = np.eye(12)
    carry[6:, 6:] = jac
    cov = carry @ joint[np.ix_(idx, idx)] @ carry.T
    cov[6:, 6:] += seating
    return fixture, 0.5 * (cov + cov.T)


def pose_std(covariance: np.ndarray) -> dict:
    """Standard deviations of a small motion's rotations (mrad) and shifts (mm) from its covariance (rad, m)."""
    s = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return {"rotation_mrad": [float(1e3 * v) for v in s[:3]], "translation_mm": [float(1e3 * v) for v in s[3:]]}


def _tilt_spread_mrad(targets) -> float:
    normals = [t.rotation[:, 2] for t in targets]
    best = 0.0
    for i in range(len(normals)):
        for j in range(i + 1, len(normals)):
            best = max(best, 1e3 * math.acos(float(np.clip(normals[i] @ normals[j], -1.0, 1.0))))
    return best


def judge_pose(cal: PoseCalibration) -> dict:
    """The pose calibration's verdict: ``pass``, ``warn`` or ``refused`` (thresholds: this module's constants)."""
    sol = cal.fit.solution
    std = pose_std(cal.fit.screen_covariance)
    warn, refuse, advice = [], [], []
    measures = {"screen_std": std, "rms_px": sol.rms, "tilt_spread_mrad": _tilt_spread_mrad(cal.fit.targets),
                "placements": len(cal.fit.targets)}
    if sol.undetermined:
        refuse.append(f"parameters not determined: {', '.join(sol.undetermined)}")
        advice.append("tilt the mirror with the shims under each edge in turn")
    for label, values, (w, r), unit in (("tilt (about x, y)", std["rotation_mrad"][:2], TILT_STD_MRAD, "mrad"),
                                        ("turn (about its normal)", std["rotation_mrad"][2:], TURN_STD_MRAD, "mrad"),
                                        ("shift along x, y", std["translation_mm"][:2], SHIFT_STD_MM, "mm"),
                                        ("depth (along the screen's normal)", std["translation_mm"][2:], DEPTH_STD_MM,
                                         "mm")):
        worst = max(values)
        if worst > r:
            refuse.append(f"screen {label} uncertain by {worst:.2f} {unit} (over {r:g} {unit})")
            if "take more placements" not in " ".join(advice):
                advice.append("check the range finder's aim at the mirror's mark, that the mirror's frame is whole "
                              "in the image and lit; take more placements, the shims under each edge in turn")
        elif worst > w:
            warn.append(f"screen {label} uncertain by {worst:.2f} {unit} (over {w:g} {unit})")
    for kind in ("target corners", "fringes"):
        rms = sol.rms.get(kind)
        if rms is None:
            continue
        if rms > RMS_PX[1]:
            refuse.append(f"{kind} reprojection RMS {rms:.2f} px (over {RMS_PX[1]} px)")
            advice.append("check that the mirror is clean and flat and the camera's calibration current; the screen "
                          "record must be this screen's")
        elif rms > RMS_PX[0]:
            warn.append(f"{kind} reprojection RMS {rms:.2f} px (over {RMS_PX[0]} px)")
    if measures["tilt_spread_mrad"] < MIN_TILT_SPREAD_MRAD:
        warn.append(f"the placements tilt the mirror by at most {measures['tilt_spread_mrad']:.1f} mrad: use the shims")
    if cal.screen_record is None:
        warn.append("no screen record: the flat screen of station.toml's pitch was assumed "
                    "(run calibrate screen first)")
    verdict = "refused" if refuse else ("warn" if warn else "pass")
    return {"verdict": verdict, "reasons": refuse + warn, "refuse_reasons": refuse, "warnings": warn,
            "advice": advice, "measures": measures}


def _difference(stated: Pose, measured: Pose) -> dict:
    """How far a measured pose is from the stated one: the small motion of the stated frame (mrad, mm)."""
    d = motion_between(stated, measured)
    return {"rotation_mrad": [float(1e3 * v) for v in d[:3]], "translation_mm": [float(1e3 * v) for v in d[3:]]}


def pose_record_content(cal: PoseCalibration) -> dict:
    fit = cal.fit
    sol = fit.solution
    return {
        "screen_record": cal.screen_record,
        "stated_screen": cal.stated.screen.to_dict(), "camera": cal.stated.camera.to_dict(),
        "screen_to_camera": fit.screen_to_camera.to_dict(), "screen_covariance": fit.screen_covariance.tolist(),
        "screen_std": pose_std(fit.screen_covariance),
        "screen_vs_stated": _difference(cal.stated.screen_to_camera, fit.screen_to_camera),
        "fixture_to_camera": cal.fixture_to_camera.to_dict(), "fixture_covariance": cal.fixture_covariance.tolist(),
        "fixture_std": pose_std(cal.fixture_covariance),
        **({} if cal.joint_covariance is None else
           {"joint_covariance": {"parameters": list(JOINT_PARAMETERS), "units": "rad, m",
                                 "matrix": cal.joint_covariance.tolist()}}),
        "fixture_vs_stated": _difference(cal.stated.fixture_to_camera, cal.fixture_to_camera),
        "pitch_scale": list(fit.pitch_scale),
        "target": cal.target.to_dict(),
        "placements": [r.to_dict() | ({"target_to_camera": fit.targets[i].to_dict()} if i is not None else {})
                       for r, i in zip(cal.placements, _indices(cal.placements))],
        "residuals": {"rms_px": sol.rms, "sigma_px": sol.sigma, "count": sol.count, "dropped": sol.dropped,
                      "groups": sol.groups},
        "quality": cal.quality,
    }


def _indices(reports) -> list:
    out, k = [], 0
    for r in reports:
        out.append(k if r.used else None)
        k += r.used
    return out


def save_pose(data_dir: str | Path, cal: PoseCalibration, source: str, station: dict | None = None) -> Path:
    """Write the pose record (*station*: the identity of the station it is made on). A refused calibration is
    never written: CalibrationError saying why."""
    if cal.verdict == "refused":
        q = cal.quality
        raise CalibrationError("pose calibration refused (no record written): " + "; ".join(q["refuse_reasons"])
                               + ("\nwhat to do: " + "; ".join(q["advice"]) if q["advice"] else ""))
    content = pose_record_content(cal)

    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": "pose", "record_id": record_id, "created": created, "source": source,
                **content}

    path, _ = write_record(data_dir, "pose", build, station=station)
    return path


def load_pose_record(path: str | Path) -> dict:
    """Read a pose record; ConfigError naming the file and what to do when it is unusable."""
    path = Path(path)
    redo = "rerun 'sofast-station calibrate pose'"
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"pose record {path} does not exist; {redo}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"pose record {path} is corrupt ({exc}); {redo}") from None
    if not isinstance(d, dict) or d.get("kind") != "pose" or d.get("schema") != SCHEMA:
        raise ConfigError(f"{path} is not a pose record of schema {SCHEMA}; {redo}")
    try:
        Pose.from_dict(d["screen_to_camera"])
        Pose.from_dict(d["fixture_to_camera"])
        for key in ("screen_std", "fixture_std"):
            for part in ("rotation_mrad", "translation_mm"):
                values = [float(v) for v in d[key][part]]
                if len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values):
                    raise ValueError(f"{key}.{part}")
        if "joint_covariance" in d:
            joint_covariance_mrad_mm(d)
    except (KeyError, TypeError, ValueError, ConfigError) as exc:
        raise ConfigError(f"pose record {path} lacks or garbles {exc}; {redo}") from None
    d["path"] = str(path)
    return d


def joint_covariance_mrad_mm(record: dict) -> np.ndarray | None:
    """The pose record's joint covariance of the screen's and the fixture's poses in the budget's units (mrad
    and mm: :data:`JOINT_PARAMETERS`), or None for a record made before it was kept (schema 1 records until
    2026-12-06: the budget then takes the twelve standard uncertainties as independent rows).

    Raises
    ------
    ValueError
        ``joint_covariance`` is not a finite, symmetric, positive semi-definite (12, 12) matrix of those
        parameters.
    """
    joint = record.get("joint_covariance")
    if joint is None:
        return None
    if not isinstance(joint, dict) or tuple(joint.get("parameters", ())) != JOINT_PARAMETERS:
        raise ValueError("joint_covariance.parameters")
    cov = np.asarray(joint.get("matrix"), dtype=np.float64)
    if cov.shape != (12, 12) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, rtol=1e-9, atol=0.0):
        raise ValueError("joint_covariance.matrix (12 x 12, finite, symmetric)")
    scale = 1e3 * np.ones(12)              # rad -> mrad, m -> mm alike
    cov = cov * np.outer(scale, scale)
    if np.linalg.eigvalsh(cov).min() < -1e-9 * max(np.abs(np.diag(cov)).max(), 1e-300):
        raise ValueError("joint_covariance.matrix (not positive semi-definite)")
    return cov


def summary_text(cal: PoseCalibration, path: Path | None = None) -> str:
    """A readable summary of a pose calibration, ending with its verdict."""
    lines = [f"Pose calibration from {sum(r.used for r in cal.placements)} of {len(cal.placements)} placements of "
             f"{cal.target.name}" + (f"; record {path}" if path else "")]
    for r in cal.placements:
        lines.append(f"  {r.label}: " + (f"{r.corners} target corners, {r.border_points} border points, "
                                         f"{r.mirror_pixels} mirror pixels, distance {r.distance_m:.4f} m"
                                         if r.used else f"not used: {r.reason}"))
    fit = cal.fit
    if fit is not None:
        std = pose_std(fit.screen_covariance)
        diff = _difference(cal.stated.screen_to_camera, fit.screen_to_camera)
        lines.append("  screen against the designed assembly: rotation " + ", ".join(
            f"{v:+.2f}" for v in diff["rotation_mrad"]) + " mrad, shift " + ", ".join(
            f"{v:+.2f}" for v in diff["translation_mm"]) + " mm (screen axes)")
        lines.append("  its expanded uncertainty (k=2): rotation " + ", ".join(
            f"{2 * v:.2f}" for v in std["rotation_mrad"]) + " mrad, shift " + ", ".join(
            f"{2 * v:.2f}" for v in std["translation_mm"]) + " mm")
        fdiff = _difference(cal.stated.fixture_to_camera, cal.fixture_to_camera)
        fstd = pose_std(cal.fixture_covariance)
        lines.append("  fixture against the designed one: rotation " + ", ".join(
            f"{v:+.2f}" for v in fdiff["rotation_mrad"]) + " mrad, shift " + ", ".join(
            f"{v:+.2f}" for v in fdiff["translation_mm"]) + " mm; U (k=2) " + ", ".join(
            f"{2 * v:.2f}" for v in fstd["rotation_mrad"]) + " mrad, " + ", ".join(
            f"{2 * v:.2f}" for v in fstd["translation_mm"]) + " mm")
        lines.append("  residuals: " + ", ".join(f"{k} {v:.3f} {'m' if k == 'distance' else 'px'}"
                                                 for k, v in fit.solution.rms.items()))
        lines.append(f"  screen record: {cal.screen_record or 'none (flat screen of station.toml)'}")
    for w in cal.quality.get("reasons", []):
        lines.append(f"  - {w}")
    if cal.quality.get("advice") and cal.verdict != "pass":
        lines.append("  what to do: " + "; ".join(cal.quality["advice"]))
    lines.append(f"verdict: {cal.verdict.upper()}")
    return "\n".join(lines)
