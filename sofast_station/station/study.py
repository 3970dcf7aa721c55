"""Measurement studies on the digital twin: repeatability (gauge R&R) and the uncertainty's coverage.

Both take the same facet out and put it back many times: a new placement within the fixture tolerance and
new sensor noise each time (the repeatability study); the coverage study also perturbs the station's
geometry within its stated standard uncertainties (``[uncertainty]``) *in the twin only*, while the
analysis keeps the nominal geometry, and checks how often |error against the twin's truth| <= U.

The fringe images are rendered once (offscreen OpenGL, with the station's radiometric lookup table); each
repeat traces a new twin and photographs them. Ground truth comes from :mod:`sofast_station.twin.truth`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np

from ..calibrate.store import open_calibration
from ..config import StationConfig
from ..devices.renderer import FringeRenderer
from ..errors import StationError
from ..measure.analysis import analyse
from ..measure.uncertainty import SCALAR_PATHS, InputUncertainties, get_path, path_name, small_motion
from ..result.specs import figure_name
from ..twin.parameters import TrueFacet, TwinOptics
from ..twin.station import TwinStation
from ..twin.truth import ground_truth

log = logging.getLogger(__name__)

#: Figures the studies report (a readable subset of every scalar with an uncertainty).
STUDY_FIGURES = (("focal_length_x_m",), ("focal_length_y_m",), ("twist_mrad_per_m",), ("twist_e1_mrad_per_m",),
                 ("twist_e2_mrad_per_m",), ("principal_focal_lengths_m", 0), ("principal_focal_lengths_m", 1),
                 ("slope_rms_mrad", "design", "magnitude"), ("slope_rms_mrad", "parabola", "magnitude"),
                 ("slope_rms_mrad", "higher_order", "magnitude"), ("slope_rms_mrad", "design", "x"),
                 ("slope_rms_mrad", "design", "y"), ("optical_tilt_mrad", "x"), ("optical_tilt_mrad", "y"),
                 ("boresight_mrad", "x"), ("boresight_mrad", "y"),
                 *[("placement", "mm", i) for i in range(3)], *[("placement", "mrad", i) for i in range(3)])


@dataclass(frozen=True)
class Placement:
    """The fixture's placement tolerance: each placement coordinate is uniform in +-these."""

    mm: tuple = (1.0, 1.0, 0.5)
    mrad: tuple = (1.0, 1.0, 1.0)

    def draw(self, rng: np.random.Generator) -> tuple[tuple, tuple]:
        return (tuple(float(v) for v in rng.uniform(-1, 1, 3) * np.asarray(self.mm)),
                tuple(float(v) for v in rng.uniform(-1, 1, 3) * np.asarray(self.mrad)))


class TwinRig:
    """The station's twin without the production devices: fringe images rendered once, a twin traced per
    placement (and per perturbed geometry), frames captured with a given noise stream."""

    def __init__(self, config: StationConfig):
        if config.backend != "simulated":
            raise StationError(f"{config.path}: studies run on the simulated station (backend = \"simulated\"), "
                               f"this one is {config.backend!r}")
        self.config = config
        sim = config.simulation
        self.facet = TrueFacet.from_dict(sim.get("facet", {}))
        self.optics = TwinOptics.from_dict(sim.get("optics", {}))
        radiometric = open_calibration(config, checks=False).record
        scr = config.geometry.screen
        with FringeRenderer(scr.width_px, scr.height_px, lut=radiometric.lut, floor_level=radiometric.floor_level,
                            max_level=radiometric.max_level) as renderer:
            self.images = renderer.render_all(config.fringes.patterns())
        self.exposure_s = radiometric.exposure_s
        self.gain = radiometric.gain

    def twin(self, placement_mm, placement_mrad, geometry=None):
        facet = dataclasses.replace(self.facet, placement_mm=tuple(placement_mm), placement_mrad=tuple(placement_mrad))
        return TwinStation(geometry if geometry is not None else self.config.geometry, self.config.design, facet,
                           self.optics)

    def capture(self, twin, rng: np.random.Generator, steady: bool = False):
        """The capture's frames (n, rows, columns) with the noise drawn from *rng*.

        With *steady*, also the same frames with the ambient light at its nominal level in every frame (the
        same sensor noise, no frame-to-frame brightness change): ``(frames, steady frames)``. The noise of
        the first is what it is without *steady* (the same draws from *rng*, in the same order).
        """
        jitter = rng is not None and twin.optics.ambient_jitter > 0
        frames, calm = [], []
        for img in self.images:
            # What TwinStation.capture draws first when it draws the ambient itself: the same stream.
            z = float(rng.standard_normal()) if jitter else None
            if steady:
                twin_rng = np.random.default_rng()
                twin_rng.bit_generator.state = rng.bit_generator.state
                calm.append(twin.capture(img, twin_rng, exposure_s=self.exposure_s, gain=self.gain,
                                         ambient_z=0.0 if jitter else None))
            frames.append(twin.capture(img, rng, exposure_s=self.exposure_s, gain=self.gain, ambient_z=z))
        return (np.stack(frames), np.stack(calm)) if steady else np.stack(frames)


#: Names of the inputs :func:`perturbed_geometry` draws, in its order (``drawn`` values).
DRAWN_INPUTS = ("camera fx", "camera fy", "camera cx", "camera cy", "camera k1", "camera k2", "camera p1",
                "camera p2", "camera k3", "screen rx", "screen ry", "screen rz", "screen tx", "screen ty", "screen tz",
                "fixture rx", "fixture ry", "fixture rz", "fixture tx", "fixture ty", "fixture tz", "screen pitch",
                "distance")


def perturbed_geometry(geometry, inputs: InputUncertainties, rng: np.random.Generator, drawn: dict | None = None):
    """The station geometry with every input of the budget drawn from a normal distribution with its
    standard uncertainty (the "true" station the twin photographs), and the distance error (m).

    *drawn*, a dict, receives each input's draw in its own unit (:data:`DRAWN_INPUTS`: px, 1, mrad, mm,
    relative, mm), so that a study can say which input its errors follow."""
    cam = geometry.camera
    k = cam.matrix.copy()
    d_k = [rng.normal(0, inputs.camera_focal_px), rng.normal(0, inputs.camera_focal_px),
           rng.normal(0, inputs.camera_principal_px), rng.normal(0, inputs.camera_principal_px)]
    k[0, 0] += d_k[0]
    k[1, 1] += d_k[1]
    k[0, 2] += d_k[2]
    k[1, 2] += d_k[3]
    d_dist = rng.normal(0, 1, 5) * np.asarray(inputs.camera_distortion)
    camera = dataclasses.replace(cam, matrix=k, distortion=cam.distortion + d_dist)
    d_screen = (rng.normal(0, 1, 3) * np.asarray(inputs.screen_rotation_mrad),
                rng.normal(0, 1, 3) * np.asarray(inputs.screen_translation_mm))
    d_fixture = (rng.normal(0, 1, 3) * np.asarray(inputs.fixture_rotation_mrad),
                 rng.normal(0, 1, 3) * np.asarray(inputs.fixture_translation_mm))
    screen_delta = small_motion(*d_screen)
    fixture_delta = small_motion(*d_fixture)
    # One pitch for both axes (the twin's display has square pixels).
    d_pitch = rng.normal(0, inputs.screen_pitch_relative)
    pitch = geometry.screen.pitch_m * (1.0 + d_pitch)
    screen = dataclasses.replace(geometry.screen, pitch_m=pitch)
    true = dataclasses.replace(geometry, camera=camera, screen=screen,
                               screen_to_camera=geometry.screen_to_camera.compose(screen_delta),
                               fixture_to_camera=geometry.fixture_to_camera.compose(fixture_delta))
    d_distance = float(rng.normal(0, 1e-3 * inputs.distance_mm))
    if drawn is not None:
        values = [*d_k, *d_dist, *d_screen[0], *d_screen[1], *d_fixture[0], *d_fixture[1], d_pitch, 1e3 * d_distance]
        drawn.update({name: float(v) for name, v in zip(DRAWN_INPUTS, values)})
    return true, d_distance


def _flat(figures: dict, paths) -> dict:
    return {path_name(p): get_path(figures, p) for p in paths}


def capture_record(fig: dict, truth: dict, place, paths=SCALAR_PATHS) -> dict:
    """One capture's figures, their U and U_random, the noise-corrected slope RMS values with theirs, and
    the truth, each flattened to ``{figure name: value}`` over *paths* (what the coverage tables read);
    the true placement is *place* ((mm, mrad), as drawn), which the twin's truth echoes."""
    u_all = {k[:-2]: v for k, v in fig.items() if k.endswith("_U")}
    ur_all = {k[:-9]: v for k, v in fig.items() if k.endswith("_U_random")}
    rms_paths = [p for p in paths if p[0] == "slope_rms_mrad"]
    rec = {"figures": _flat(fig, paths), "U": _flat(u_all, paths), "U_random": _flat(ur_all, paths), "truth": {},
           "corrected": _flat({"slope_rms_mrad": fig["slope_rms_corrected_mrad"]}, rms_paths),
           "U_corrected": _flat({"slope_rms_mrad": fig["slope_rms_corrected_mrad_U"]}, rms_paths),
           "placement": [list(place[0]), list(place[1])]}
    truth_fig = dict(truth)
    truth_fig["placement"] = {"mm": list(place[0]), "mrad": list(place[1])}
    for p in paths:
        try:
            rec["truth"][path_name(p)] = get_path(truth_fig, p)
        except (KeyError, IndexError, TypeError):
            rec["truth"][path_name(p)] = None
    return rec


def run_repeats(config: StationConfig, n: int, seed: int = 0, placement: Placement = Placement(),
                perturb_geometry: bool = False, progress=None, paths=SCALAR_PATHS,
                split_brightness: bool = False) -> list[dict]:
    """*n* repeats of the station's facet on the twin; each returns the figures, their U and U_random,
    and the truth (flattened ``{figure name: value}`` dicts).

    With *split_brightness*, each capture is also analysed with the same sensor noise and no frame-to-frame
    change of the ambient light (:meth:`TwinRig.capture`, its own sensitivity cache and frame-brightness
    pool): ``steady`` holds those figures, so ``figures - steady`` is the part of each error the
    frame-to-frame brightness made, and ``U_brightness`` the budget's frame-brightness rows (k = 2) that
    state it. The repeats themselves are the same as without it."""
    rig = TwinRig(config)
    rng = np.random.default_rng(seed)
    cache: dict = {}
    steady_cache: dict = {}
    out = []
    for i in range(n):
        t0 = time.perf_counter()
        place = placement.draw(rng)
        drawn: dict = {}
        geometry, distance_error = (perturbed_geometry(config.geometry, config.uncertainty, rng, drawn)
                                    if perturb_geometry else (config.geometry, 0.0))
        twin = rig.twin(*place, geometry=geometry)
        frames = rig.capture(twin, np.random.default_rng(rng.integers(2**63)), steady=split_brightness)
        if split_brightness:
            frames, steady_frames = frames
        distance = twin.measured_distance_m() + distance_error
        a = analyse(frames, config.fringes, config.geometry, config.design, distance, config.analysis,
                    uncertainty=config.uncertainty, sensitivity_cache=cache)
        fig = a.figures
        rec = capture_record(fig, ground_truth(twin, a.valid), place, paths)
        rec.update({"drawn": drawn, "seconds": time.perf_counter() - t0, "analysis_seconds": fig["timings_s"]})
        if split_brightness:
            calm = analyse(steady_frames, config.fringes, config.geometry, config.design, distance, config.analysis,
                           uncertainty=config.uncertainty, sensitivity_cache=steady_cache)
            rec["steady"] = _flat(calm.figures, paths)
            budget = fig["uncertainty_budget"]
            row = next((r["contributions"] for r in budget["rows"] if r["group"] == "frame-to-frame brightness"), [])
            stated = dict(zip(budget["figures"], row))
            rec["U_brightness"] = {path_name(p): None if stated.get(path_name(p)) is None
                                   else 2.0 * stated[path_name(p)] for p in paths}
        out.append(rec)
        if progress:
            progress(i + 1, n, rec)
    return out


def repeatability_table(repeats: list[dict], config: StationConfig, paths=STUDY_FIGURES) -> list[dict]:
    """Per figure: mean, standard deviation, the mean stated random U (k = 2), the standard deviation of
    the error against the twin's truth (for placement and optical tilt, whose true value changes with
    every placement, the measurement's own repeatability) and its ratio to U_random, and %GRR = 6 std /
    tolerance width against ``[limits]`` where a limit applies (<= 10 %: acceptable, 10-30 %: marginal,
    above: unacceptable)."""
    lim = config.limits
    f_design = config.design.focal_length_m
    tolerances = {"focal_length_x_m": 2 * lim.focal_length_tolerance * f_design,
                  "focal_length_y_m": 2 * lim.focal_length_tolerance * f_design,
                  "twist_mrad_per_m": 2 * lim.max_twist_mrad_per_m}
    for model, limit in lim.max_slope_rms_mrad.items():
        tolerances[f"slope_rms_mrad.{model}.magnitude"] = float(limit)     # one-sided: 0 .. limit
    rows = []
    for p in paths:
        name = path_name(p)
        v = np.array([r["figures"][name] for r in repeats if r["figures"][name] is not None], float)
        ur = np.array([r["U_random"][name] for r in repeats if r["U_random"].get(name) is not None], float)
        u = np.array([r["U"][name] for r in repeats if r["U"].get(name) is not None], float)
        if v.size < 2:
            continue
        std = float(np.std(v, ddof=1))
        err = np.array([r["figures"][name] - r["truth"][name] for r in repeats
                        if r["figures"][name] is not None and r["truth"].get(name) is not None], float)
        std_err = float(np.std(err, ddof=1)) if err.size > 1 else None
        u_rand = float(np.mean(ur)) if ur.size else None
        tol = tolerances.get(name)
        grr = None if tol is None else 100.0 * 6.0 * std / tol
        rows.append({"figure": name, "n": int(v.size), "mean": float(np.mean(v)), "std": std,
                     "U_random": u_rand, "U": float(np.mean(u)) if u.size else None,
                     "std_error": std_err,
                     "std_over_U_random": None if not u_rand or std_err is None else std_err / u_rand,
                     "tolerance": tol, "grr_percent": grr,
                     "grr_class": None if grr is None else
                     ("acceptable" if grr <= 10 else "marginal" if grr <= 30 else "unacceptable")})
    return rows


def table_text(rows: list[dict]) -> str:
    """The repeatability table, one aligned line per figure with its human name and unit (columns sized to
    their contents, two spaces apart: the old fixed widths ran long names into the numbers)."""
    def g(v, fmt):
        return "-" if v is None else format(v, fmt)
    head = ("figure", "unit", "mean", "std", "std error", "U_random", "U (k=2)", "err/U_rand", "%GRR", "class")
    body = []
    for r in rows:
        name, unit = figure_name(r["figure"])
        body.append((name, unit, g(r["mean"], ".6g"), g(r["std"], ".3g"), g(r["std_error"], ".3g"),
                     g(r["U_random"], ".3g"), g(r["U"], ".3g"), g(r["std_over_U_random"], ".2f"),
                     g(r["grr_percent"], ".1f"), r["grr_class"] or ""))
    widths = [max(len(str(line[i])) for line in (head, *body)) for i in range(len(head))]

    def line(cells):
        text = [str(cells[0]).ljust(widths[0]), str(cells[1]).ljust(widths[1])]
        text += [str(c).rjust(w) for c, w in zip(cells[2:-1], widths[2:-1])]
        return "  ".join(text + [str(cells[-1])]).rstrip()
    return "\n".join([line(head)] + [line(b) for b in body])


def repeatability_png(rows: list[dict], path, title: str) -> None:
    """Bars of std / U_random per figure (the 1.5 line is the study's pass mark), and %GRR where a
    tolerance applies (10 % and 30 % lines)."""
    # Only the chart draws: the other studies import this module and never do.
    # lazy: matplotlib.pyplot costs ~350 ms CPU (+176 modules) after this module; Agg chosen before pyplot loads
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: as matplotlib above

    fig, axes = plt.subplots(1, 2, figsize=(14, 7), gridspec_kw={"width_ratios": [3, 1]})

    names = [figure_name(r["figure"])[0] for r in rows if r["std_over_U_random"] is not None]
    ratios = [r["std_over_U_random"] for r in rows if r["std_over_U_random"] is not None]
    ax = axes[0]
    ax.barh(names, ratios, color=["tab:red" if x > 1.5 else "tab:blue" for x in ratios])
    ax.axvline(1.5, color="tab:red", linestyle="--", label="1.5 (limit of the study)")
    ax.axvline(0.5, color="grey", linestyle=":", label="0.5 (std = u_random, k = 2)")
    ax.set_xlabel("standard deviation of the error against truth over repeats / stated random U (k=2)")
    ax.invert_yaxis()
    ax.legend(loc="lower right")
    ax.set_title("repeatability against the stated random uncertainty")
    graded = [r for r in rows if r["grr_percent"] is not None]
    ax = axes[1]
    ax.bar([figure_name(r["figure"])[0] for r in graded],
           [r["grr_percent"] for r in graded], color="tab:green")
    ax.axhline(10, color="tab:orange", linestyle="--", label="10 % acceptable")
    ax.axhline(30, color="tab:red", linestyle="--", label="30 % marginal")
    ax.set_ylabel("%GRR = 6 std / tolerance")
    ax.tick_params(axis="x", rotation=60)
    ax.legend()
    ax.set_title("%GRR against [limits]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def coverage_table(repeats: list[dict], paths=SCALAR_PATHS) -> list[dict]:
    """Per figure: the fraction of repeats with |error against truth| <= U, the median U, the errors'
    mean, standard deviation and RMS, and the ratio median U / std (errors)."""
    rows = []
    for p in paths:
        name = path_name(p)
        err, u = [], []
        for r in repeats:
            v, t, uu = r["figures"].get(name), r["truth"].get(name), r["U"].get(name)
            if v is None or t is None or uu is None:
                continue
            err.append(v - t)
            u.append(uu)
        if len(err) < 2:
            continue
        err, u = np.array(err), np.array(u)
        std = float(np.std(err, ddof=1))
        rows.append({"figure": name, "n": int(err.size), "coverage": float(np.mean(np.abs(err) <= u)),
                     "median_U": float(np.median(u)), "mean_error": float(np.mean(err)), "std_error": std,
                     "rms_error": float(np.sqrt(np.mean(err ** 2))),
                     "U_over_std": float(np.median(u) / std) if std > 0 else None})
    return rows


def brightness_split_table(repeats: list[dict], paths=SCALAR_PATHS) -> list[dict]:
    """Per figure, from repeats of ``run_repeats(..., split_brightness=True)``: the part of the errors the
    frame-to-frame brightness made (``figures - steady``) against the budget's frame-brightness rows, and
    the rest (``steady - truth``, its RMS: U also covers offsets) against the rest of U, so that a coverage
    run can tell a wrong budget from the spread of its own draws.

    ``brightness_ratio`` is sqrt(mean((part / stated)^2)) over the repeats (1 for a right row, with a
    sampling spread of about 1 / sqrt(2 n)), ``rest_ratio`` the rest's RMS over the median
    of sqrt((U/2)^2 - stated^2), ``U_over_std`` median U / std(error) as in :func:`coverage_table` and
    ``U_over_std_at_stated`` the same with each brightness part divided by ``brightness_ratio`` (the
    brightness draws at the spread the budget states, the rest as drawn).
    """
    rows = []
    for p in paths:
        name = path_name(p)
        part, rest, stated, u = [], [], [], []
        for r in repeats:
            v, t, uu = r["figures"].get(name), r["truth"].get(name), r["U"].get(name)
            calm, ub = (r.get("steady") or {}).get(name), (r.get("U_brightness") or {}).get(name)
            if None in (v, t, uu, calm, ub) or ub <= 0:
                continue
            part.append(v - calm)
            rest.append(calm - t)
            stated.append(ub / 2.0)
            u.append(uu)
        if len(part) < 2:
            continue
        part, rest, stated, u = (np.array(x, float) for x in (part, rest, stated, u))
        ratio = float(np.sqrt(np.mean((part / stated) ** 2)))
        u_rest = np.sqrt(np.clip((u / 2.0) ** 2 - stated ** 2, 0.0, None))
        std = float(np.std(part + rest, ddof=1))
        rest_rms = float(np.sqrt(np.mean(rest ** 2)))       # U also covers the offsets the reported value keeps
        std_at = float(np.std(rest + part / ratio, ddof=1)) if ratio > 0 else std
        rows.append({"figure": name, "n": int(part.size), "brightness_std": float(np.std(part, ddof=1)),
                     "brightness_stated": float(np.median(stated)), "brightness_ratio": ratio,
                     "rest_rms": rest_rms, "rest_stated": float(np.median(u_rest)),
                     "rest_ratio": rest_rms / float(np.median(u_rest)) if np.median(u_rest) > 0 else None,
                     "U_over_std": float(np.median(u) / std) if std > 0 else None,
                     "U_over_std_at_stated": float(np.median(u) / std_at) if std_at > 0 else None})
    return rows
