"""``calibrate screen``: the screen's shape and pitch, measured from views of a second camera.

The technician holds (or sets on a tripod) a calibrated second camera about a metre from the screen and
takes several views from different sides, the certified scale board fixed beside the screen in each. For
every view the station shows ChArUco fiducials (corners at exactly known display positions) and then its
fringe sequence (every pixel's display position); :func:`~sofast_station.measure.commission.fit_screen`
fits the three shape models to all views at once and picks the simplest the residuals allow.

The routine sees the hardware only through the Display and Camera protocols and a ``place(k, n, hint)``
callback that asks for view k (on the simulated station it moves the twin's handheld camera). It judges
its result (:func:`judge_screen`): ``pass``, ``warn`` (recorded, with the warnings) or ``refused`` (no
record: the parameters are not determined, or the views do not allow it; the message says what to do).
The record (``data_dir/calibration/screen/``) holds the shape model and its parameters' covariance, the
pitch with its standard uncertainty, the shape on a grid of nodes with every node's standard uncertainty
and the shape's principal uncertainty fields (what the analysis and its budget use), the residuals, the
model tests and every view's verdict.
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
from ..fringes import DisplayImage, FringeSet, Pattern
from ..geometry import CameraIntrinsics, ScreenSpec
from ..measure.fiducials import CharucoLayout, detect_charuco, screen_fiducials
from ..measure.screen_shape import ScreenShape, shape_modes
from .commission_settings import ScreenSettings
from .errors import CalibrationError
from .store import write_record

log = logging.getLogger(__name__)

SCHEMA = 1

#: Reprojection RMS of the fiducial and board corners, pixels: (warn above, refuse above). A sharp view
#: gives 0.05-0.15 px (0.07 on the twin); a pixel means a view that moved, a screen or board that moved
#: between views, or misdetected corners.
CORNER_RMS_PX = (0.3, 1.0)
#: Standard uncertainty of the pitch, relative: (warn, refuse). 1e-3 of pitch moves a focal length by
#: 0.0017 % and a slope RMS by 6e-4 mrad on the default station; 3e-3, 0.005 %: no longer a measurement of
#: it. (The pose calibration refines the pitch again, with the range finder: docs/calibration.md.)
PITCH_STD = (1e-3, 3e-3)
#: Largest standard uncertainty of a node of the shape (x, y or z), metres: (warn, refuse). In-plane 0.2
#: mm at 10 m is 10 urad of slope; out of the plane a hundred times less.
SHAPE_STD_M = (2e-4, 1e-3)
#: Fraction of the active area (an 8 x 5 grid of cells) seen with fringes in at least two views: warn below
#: the first, refuse below the second.
COVERAGE = (0.8, 0.5)
COVERAGE_GRID = (8, 5)
#: The largest angle between two views' directions from the screen centre must reach this, degrees: views
#: from one side cannot tell the screen's depth from its size.
MIN_SPREAD_DEG = 20.0


@dataclass
class ViewReport:
    """What became of one view."""

    label: str
    used: bool = False
    reason: str = ""
    corners: int = 0
    markers: int = 0
    board_corners: int = 0
    fringe_pixels: int = 0
    noise_dn: float = float("nan")

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class ScreenCalibration:
    """The screen calibration: the fit, every view's verdict and the judgement.

    Attributes
    ----------
    fit : ScreenFit or None
    views : list of ViewReport
    stated : ScreenSpec
        The screen as station.toml states it.
    camera : CameraIntrinsics
        The handheld camera's calibration used; ``camera_std`` its parameters' standard deviations.
    quality : dict
        :func:`judge_screen`'s verdict, reasons, warnings, advice and measures.
    record : dict
        What the record holds (:func:`screen_record_content`).
    """

    fit: object
    views: list
    stated: ScreenSpec
    camera: CameraIntrinsics
    camera_std: tuple
    settings: ScreenSettings
    quality: dict = field(default_factory=dict)

    @property
    def verdict(self) -> str:
        return self.quality.get("verdict", "refused")


def view_hints(n: int) -> list[str]:
    """What to ask of the technician for each of *n* views: from around the screen, 15-35 degrees off its
    normal, about a metre away, the whole screen and the scale board in the image."""
    sides = ["the right", "the upper right", "above", "the upper left", "the left", "the lower left", "below",
             "the lower right"]
    out = []
    for k in range(n):
        side = sides[int(round(k * len(sides) / n)) % len(sides)]
        tilt = 20 if k % 2 == 0 else 30
        out.append(f"from {side}, about {tilt} degrees off the screen's normal, 0.8-1 m from it, with the whole "
                   "screen and the scale board in the image")
    return out


def screen_fiducials_for(stated: ScreenSpec, settings: ScreenSettings):
    """The fiducials shown on the screen."""
    return screen_fiducials(stated.width_px, stated.height_px, settings.fiducial_squares,
                            dictionary=settings.fiducial_dictionary)


def board_layout(settings: ScreenSettings):
    """The scale board's ChArUco layout (metres)."""
    b = settings.board
    return CharucoLayout(b.squares[0], b.squares[1], b.square_m, b.marker_m, b.dictionary, b.first_id)


def analyse_view(label: str, frames: np.ndarray, stated: ScreenSpec, fringes: FringeSet, settings: ScreenSettings,
                 fiducials=None, board=None):
    """One view's observations: (ScreenView or None, ViewReport).

    *frames*: the fiducial frame, then the fringe sequence (dark, white, fringes). A view is left out, with
    the reason, when too few fiducial corners are found or its fringes decode nowhere.
    """
    # lazy: measure/commission.py costs ~300 ms CPU (scipy.optimize); config loads this module's record reader
    from ..measure.commission import ScreenView, decode_positions, fringe_samples

    fiducials = fiducials if fiducials is not None else screen_fiducials_for(stated, settings)
    board = board if board is not None else board_layout(settings)
    report = ViewReport(label)
    ids, px, markers = detect_charuco(frames[0], fiducials.layout)
    report.corners, report.markers = int(len(ids)), int(markers)
    if len(ids) < settings.min_corners:
        report.reason = (f"fiducials not found: {len(ids)} corners ({markers} markers) of "
                         f"{fiducials.layout.n_corners}, at least {settings.min_corners} needed; the whole screen "
                         "must be in the image, in focus and not saturated")
        return None, report
    uv = fiducials.positions_m(ids, stated.pitch_x_m, stated.pitch_y_m)
    b_ids, b_px, _ = detect_charuco(frames[0], board)
    report.board_corners = int(len(b_ids))
    b_xy = board.corners()[b_ids] if len(b_ids) >= 6 else np.zeros((0, 2))
    b_px = b_px if len(b_ids) >= 6 else np.zeros((0, 2))
    decoded = decode_positions(frames[1:], fringes, (stated.width_m, stated.height_m))
    report.noise_dn = decoded.noise_dn
    report.fringe_pixels = int(decoded.valid.sum())
    if report.fringe_pixels < 100:
        report.reason = ("the fringes decode on too few pixels (under 100): the screen's fringes must fill much of "
                         "the image, in focus")
        return None, report
    f_px, f_uv, f_sigma = fringe_samples(decoded, settings.max_samples)
    report.used = True
    return ScreenView(label, px, uv, b_px, b_xy, f_px, f_uv, f_sigma), report


def capture_view(display, camera, patterns: list[Pattern]) -> np.ndarray:
    """Show every pattern and grab a frame of each."""
    frames = None
    for i, pattern in enumerate(patterns):
        display.show(pattern)
        frame = camera.grab()
        if frames is None:
            frames = np.empty((len(patterns), *frame.shape), dtype=frame.dtype)
        frames[i] = frame
    return frames


def calibrate_screen(display, camera, place: Callable[[int, int, str], None], settings: ScreenSettings,
                     stated: ScreenSpec, fringes: FringeSet, intrinsics: CameraIntrinsics, intrinsics_std,
                     progress: Callable[[str], None] | None = None) -> ScreenCalibration:
    """Run the screen calibration (module docstring).

    Parameters
    ----------
    display : Display
        The station's screen.
    camera : Camera
        The second camera.
    place : callable
        ``place(k, n, hint)``: bring the second camera to view k of n (ask the technician; on the simulated
        station, move the twin's camera).
    settings : ScreenSettings
    stated : ScreenSpec
        The screen as station.toml states it (its pixels; the pitch it states is what is checked).
    fringes : FringeSet
        The fringe sequence to show (the station's).
    intrinsics, intrinsics_std
        The second camera's calibration and its parameters' standard deviations (9, see
        :data:`~sofast_station.measure.commission.CAMERA_NAMES`).
    progress : callable, optional
        Receives one line per step (views, the fit).

    Raises
    ------
    CalibrationError
        Too few usable views, or no view sees the scale board (what to do is in the message).
    """
    # lazy: measure/commission.py costs ~300 ms CPU (scipy.optimize); config loads this module's record reader
    from ..measure.commission import fit_screen

    say = progress or log.info
    if camera.shape != intrinsics.shape:
        raise CalibrationError(f"the second camera gives {camera.shape[1]} x {camera.shape[0]} images but its "
                               f"calibration is for {intrinsics.width_px} x {intrinsics.height_px}: calibrate this "
                               "camera (calibrate camera --handheld) or fix [calibration.screen] camera")
    fiducials = screen_fiducials_for(stated, settings)
    board = board_layout(settings)
    patterns = [Pattern("image", image=DisplayImage(fiducials.image(), "fiducials"))] + fringes.patterns()
    hints = view_hints(settings.views)
    views, reports = [], []
    for k in range(settings.views):
        place(k, settings.views, hints[k])
        frames = capture_view(display, camera, patterns)
        view, report = analyse_view(f"view {k + 1}", frames, stated, fringes, settings, fiducials, board)
        reports.append(report)
        if view is not None:
            views.append(view)
            say(f"view {k + 1}/{settings.views}: {report.corners} fiducial corners, {report.board_corners} scale "
                f"board corners, {report.fringe_pixels} pixels with fringes")
        else:
            say(f"view {k + 1}/{settings.views}: not used: {report.reason}")
    display.show(Pattern("uniform", command=0))
    cal = ScreenCalibration(None, reports, stated, intrinsics, tuple(intrinsics_std), settings)
    if len(views) < settings.min_views:
        lines = "\n".join(f"  {r.label}: {r.reason}" for r in reports if not r.used)
        raise CalibrationError(f"too few views: {len(views)} usable of {len(reports)}, at least {settings.min_views} "
                               f"needed. Take {settings.views} views from around the screen (15-35 degrees off its "
                               f"normal, about 1 m away), each with the whole screen and the scale board in the "
                               f"image.\n{lines}")
    if sum(len(v.board_xy) > 0 for v in views) < 2:
        raise CalibrationError("the scale board was found in fewer than 2 views: it sets the scale (the pitch). Fix "
                               f"the certified board ({board.squares_x} x {board.squares_y} squares of "
                               f"{1e3 * board.square:g} mm, ids from {board.first_id}) beside the screen and keep it "
                               "in the image in every view")
    say(f"fitting the screen's shape to {len(views)} views")
    force = None if settings.model == "auto" else settings.model
    try:
        cal.fit = fit_screen(views, intrinsics, stated.width_m, stated.height_m, camera_std=intrinsics_std,
                             scale_u=settings.board.scale_u_relative, force=force)
    except ValueError as exc:
        raise CalibrationError(f"the screen's shape cannot be fitted ({exc}); take the views again, each with the "
                               "whole screen and the scale board sharp in the image") from None
    cal.quality = judge_screen(cal, views)
    return cal


def _coverage(views, stated: ScreenSpec) -> float:
    nx, ny = COVERAGE_GRID
    counts = np.zeros((ny, nx), dtype=int)
    for v in views:
        if not len(v.fringe_uv):
            continue
        cx = np.clip((v.fringe_uv[:, 0] / stated.width_m * nx).astype(int), 0, nx - 1)
        cy = np.clip((v.fringe_uv[:, 1] / stated.height_m * ny).astype(int), 0, ny - 1)
        seen = np.zeros((ny, nx), dtype=bool)
        seen[cy, cx] = True
        counts += seen
    return float(np.mean(counts >= 2))


def _spread_deg(poses) -> float:
    dirs = []
    for p in poses:
        centre = -p.rotation.T @ p.translation           # camera centre in the screen frame
        dirs.append(centre / np.linalg.norm(centre))
    best = 0.0
    for i in range(len(dirs)):
        for j in range(i + 1, len(dirs)):
            best = max(best, math.degrees(math.acos(float(np.clip(dirs[i] @ dirs[j], -1.0, 1.0)))))
    return best


def judge_screen(cal: ScreenCalibration, views) -> dict:
    """The screen calibration's verdict: ``pass``, ``warn`` or ``refused`` (module docstring; thresholds are
    this module's constants)."""
    best = cal.fit.best
    sol = best.solution
    stated = cal.stated
    warn, refuse, advice = [], [], []
    corner_rms = max(sol.rms.get("screen corners", 0.0), sol.rms.get("board corners", 0.0))
    pitch_std = sol.std("shape")[:2]
    uv, _ = best.shape.grid(17, 9)
    _, node_std = shape_modes(best.shape, best.shape_covariance, uv)
    shape_std = float(np.max(node_std)) if node_std.size else 0.0
    coverage = _coverage(views, stated)
    spread = _spread_deg(best.views)
    measures = {"corner_rms_px": corner_rms, "fringe_rms_px": sol.rms.get("fringes"),
                "pitch_std_relative": [float(v) for v in pitch_std], "shape_std_max_m": shape_std,
                "coverage": coverage, "spread_deg": spread, "views": len(views)}
    if sol.undetermined:
        refuse.append(f"parameters not determined: {', '.join(sol.undetermined)}")
        advice.append("take views from more sides of the screen, tilted 15-35 degrees")
    if corner_rms > CORNER_RMS_PX[1]:
        refuse.append(f"corner reprojection RMS {corner_rms:.2f} px (over {CORNER_RMS_PX[1]} px)")
        advice.append("check that neither the screen nor the scale board moved between views and that the views "
                      "are sharp; check the second camera's calibration")
    elif corner_rms > CORNER_RMS_PX[0]:
        warn.append(f"corner reprojection RMS {corner_rms:.2f} px (over {CORNER_RMS_PX[0]} px)")
    if max(pitch_std) > PITCH_STD[1]:
        refuse.append(f"pitch uncertain by {max(pitch_std):.1e} (over {PITCH_STD[1]:.0e})")
        advice.append("bring the camera closer to the scale board's side, or use a larger certified board")
    elif max(pitch_std) > PITCH_STD[0]:
        warn.append(f"pitch uncertain by {max(pitch_std):.1e} (over {PITCH_STD[0]:.0e})")
    if shape_std > SHAPE_STD_M[1]:
        refuse.append(f"shape uncertain by up to {1e3 * shape_std:.2f} mm (over {1e3 * SHAPE_STD_M[1]:.1f} mm)")
        advice.append("take more views, from every side")
    elif shape_std > SHAPE_STD_M[0]:
        warn.append(f"shape uncertain by up to {1e3 * shape_std:.2f} mm (over {1e3 * SHAPE_STD_M[0]:.1f} mm)")
    if coverage < COVERAGE[1]:
        refuse.append(f"poor coverage: {100 * coverage:.0f} % of the screen seen with fringes in two views or more "
                      f"(at least {100 * COVERAGE[1]:.0f} % needed)")
        advice.append("keep the whole screen in the image in every view")
    elif coverage < COVERAGE[0]:
        warn.append(f"coverage: {100 * coverage:.0f} % of the screen seen in two views or more")
    if spread < MIN_SPREAD_DEG:
        refuse.append(f"the views' directions differ by at most {spread:.0f} degrees (at least {MIN_SPREAD_DEG:.0f} "
                      "needed): their depth is not determined")
        advice.append("take the views from opposite sides of the screen, 15-35 degrees off its normal")
    verdict = "refused" if refuse else ("warn" if warn else "pass")
    return {"verdict": verdict, "reasons": refuse + warn, "refuse_reasons": refuse, "warnings": warn,
            "advice": advice, "measures": measures}


def screen_record_content(cal: ScreenCalibration, nodes: tuple[int, int] = (65, 37), max_modes: int = 4) -> dict:
    """What the screen record holds (besides its id, date and source)."""
    best = cal.fit.best
    sol = best.solution
    stated = cal.stated
    cov = best.shape_covariance
    a_std = np.sqrt(np.clip(np.diag(cov)[:2], 0.0, None))
    pitch = (stated.pitch_x_m * best.shape.pitch_scale[0], stated.pitch_y_m * best.shape.pitch_scale[1])
    uv, pts = best.shape.grid(*nodes)
    modes, node_std = shape_modes(best.shape, cov, uv, max_modes=max_modes)
    heights = best.shape.height_summary()
    # the summary figures' own standard uncertainties, by propagating the covariance through them
    names = best.shape.names
    summary_std = {}
    if "z:1,1" in names:
        summary_std["twist_m"] = float(np.sqrt(cov[names.index("z:1,1"), names.index("z:1,1")]))
    grad = np.zeros(len(names))
    for i in range(2, len(names)):
        e = np.zeros(len(names))
        e[i] = 1e-6
        grad[i] = (best.shape.with_params(best.shape.params + e).height_summary()["sag_m"] - heights["sag_m"]) / 1e-6
    summary_std["sag_m"] = float(np.sqrt(max(grad @ cov @ grad, 0.0)))
    pitch_rel = [pitch[0] / stated.pitch_x_m - 1.0, pitch[1] / stated.pitch_y_m - 1.0]
    return {
        "stated_screen": stated.to_dict(),
        "model": best.shape.model, "shape": best.shape.to_dict(), "covariance": cov.tolist(),
        "pitch_m": {"x": {"value": pitch[0], "std": stated.pitch_x_m * float(a_std[0])},
                    "y": {"value": pitch[1], "std": stated.pitch_y_m * float(a_std[1])}},
        "pitch_vs_stated_relative": pitch_rel,
        "heights": {**heights, "std": summary_std},
        "grid": {"nodes_uv_m": uv.tolist(), "nodes_screen_m": pts.tolist(), "node_std_m": node_std.tolist(),
                 "modes_m": modes.tolist(), "shape": list(nodes)},
        "tests": cal.fit.tests, "models": {m: {"chi2": f.solution.chi2, "dof": f.solution.dof,
                                               "rms_px": f.solution.rms} for m, f in cal.fit.fits.items()},
        "residuals": {"rms_px": sol.rms, "sigma_px": sol.sigma, "count": sol.count, "dropped": sol.dropped,
                      "groups": sol.groups},
        "views": [r.to_dict() for r in cal.views],
        "view_poses": [p.to_dict() for p in best.views],
        "camera": {"stated": cal.camera.to_dict(), "std": list(cal.camera_std),
                   "refined": [float(v) for v in best.camera]},
        "board": {"squares": list(cal.settings.board.squares), "square_m": cal.settings.board.square_m,
                  "scale_u_relative": cal.settings.board.scale_u_relative, "scale": best.scale,
                  "to_screen": None if best.board_to_screen is None else best.board_to_screen.to_dict()},
        "quality": cal.quality,
    }


def save_screen(data_dir: str | Path, cal: ScreenCalibration, source: str, station: dict | None = None) -> Path:
    """Write the screen record (*station*: the identity of the station it is made on). A refused calibration is
    never written: CalibrationError saying why."""
    if cal.verdict == "refused":
        raise CalibrationError(refusal_text(cal))
    content = screen_record_content(cal)

    def build(record_id: str, created: str) -> dict:
        return {"schema": SCHEMA, "kind": "screen", "record_id": record_id, "created": created, "source": source,
                **content}

    path, _ = write_record(data_dir, "screen", build, station=station)
    return path


def refusal_text(cal: ScreenCalibration) -> str:
    q = cal.quality
    return ("screen calibration refused (no record written): " + "; ".join(q.get("refuse_reasons", []))
            + ("\nwhat to do: " + "; ".join(q["advice"]) if q.get("advice") else ""))


def load_screen_record(path: str | Path) -> dict:
    """Read a screen record; ConfigError naming the file and what to do when it is unusable."""
    path = Path(path)
    redo = "rerun 'sofast-station calibrate screen'"
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"screen record {path} does not exist; {redo}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"screen record {path} is corrupt ({exc}); {redo}") from None
    if not isinstance(d, dict) or d.get("kind") != "screen" or d.get("schema") != SCHEMA:
        raise ConfigError(f"{path} is not a screen record of schema {SCHEMA}; {redo}")
    try:
        grid = d["grid"]
        uv = np.asarray(grid["nodes_uv_m"], dtype=np.float64)
        pts = np.asarray(grid["nodes_screen_m"], dtype=np.float64)
        modes = np.asarray(grid.get("modes_m", []), dtype=np.float64).reshape(-1, uv.shape[0], 3)
        ScreenSpec.from_dict(d["stated_screen"])
        ScreenShape.from_dict(d["shape"])
        float(d["pitch_m"]["x"]["std"])
        float(d["pitch_m"]["y"]["std"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"screen record {path} lacks or garbles {exc}; {redo}") from None
    if uv.ndim != 2 or uv.shape[1] != 2 or pts.shape != (uv.shape[0], 3) or not (
            np.all(np.isfinite(uv)) and np.all(np.isfinite(pts)) and np.all(np.isfinite(modes))):
        raise ConfigError(f"screen record {path}: its grid is not finite (M, 2) positions and (M, 3) points; {redo}")
    d["path"] = str(path)
    return d


def summary_text(cal: ScreenCalibration, path: Path | None = None) -> str:
    """A readable summary of a screen calibration, ending with its verdict."""
    lines = [f"Screen calibration from {sum(r.used for r in cal.views)} of {len(cal.views)} views"
             + (f"; record {path}" if path else "")]
    for r in cal.views:
        lines.append(f"  {r.label}: " + (f"{r.corners} fiducial corners, {r.board_corners} board corners, "
                                         f"{r.fringe_pixels} fringe pixels" if r.used else f"not used: {r.reason}"))
    if cal.fit is not None:
        best = cal.fit.best
        sol = best.solution
        stated = cal.stated
        cov = best.shape_covariance
        a_std = np.sqrt(np.clip(np.diag(cov)[:2], 0.0, None))
        for axis, i, p0 in (("x", 0, stated.pitch_x_m), ("y", 1, stated.pitch_y_m)):
            p = p0 * best.shape.pitch_scale[i]
            lines.append(f"  pitch {axis}: {1e6 * p:.3f} +- {2e6 * p0 * a_std[i]:.3f} um (k=2); station.toml says "
                         f"{1e6 * p0:.3f} um ({100 * (p / p0 - 1):+.3f} %)")
        h = best.shape.height_summary()
        lines.append(f"  model: {best.shape.model} (" + ", ".join(
            f"{m}: F {t['F']:.1f} against {t['critical']:.2f}" + ("" if t.get("pitch_agrees") in (None, True)
                                                                 else ", its pitch off the 3-D model's")
            for m, t in cal.fit.tests.items()) + ")")
        lines.append(f"  shape: sag {1e3 * h['sag_m']:+.3f} mm, twist {1e3 * h['twist_m']:+.3f} mm, peak to valley "
                     f"{1e3 * h['peak_to_valley_m']:.3f} mm")
        lines.append("  residuals: " + ", ".join(f"{k} {v:.3f} px" for k, v in sol.rms.items())
                     + (f"; outliers dropped: {sum(sol.dropped.values())}" if sum(sol.dropped.values()) else ""))
    q = cal.quality
    if q:
        m = q["measures"]
        lines.append(f"  coverage {100 * m['coverage']:.0f} % of the screen in two views or more; views spread over "
                     f"{m['spread_deg']:.0f} degrees")
        for w in q["reasons"]:
            lines.append(f"  - {w}")
        if q["advice"] and q["verdict"] != "pass":
            lines.append("  what to do: " + "; ".join(q["advice"]))
    lines.append(f"verdict: {cal.verdict.upper()}")
    return "\n".join(lines)
