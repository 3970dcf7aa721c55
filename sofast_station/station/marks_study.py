"""The fixture marks' check on drawn stations: its false alarms on good cycles, and the camera moves it catches
(``benchmarks/marks.py``; ``tests/station/test_fixture_marks.py``).

Each station is one of the population's dish stations (:mod:`sofast_station.station.population`: the camera at
a quarter of its resolution, 400 x 300, or at full resolution with ``full=True``; the lens's distortion k1, the
twin's optics and its noise drawn as the population draws them: read noise 0.3-5 DN, shot noise, room light and
its jitter, flicker, vignetting), with the marks of the shipped station file's ``[marks]``. Its marks are
commissioned by the routine the station runs (:func:`~sofast_station.calibrate.marks.commission_marks`, through
a display and a camera over the twin); then

* good cycles: the camera where it was, the facet placed anew in the fixture (within the fixture's tolerance,
  :class:`~sofast_station.station.study.Placement`), each white frame with its own noise, exposure phase and room
  light: every withheld facet is a false alarm;
* moves (:data:`MOVES`): the twin's camera turned or shifted (:class:`~sofast_station.twin.assembly.TrueAssembly`,
  about and along the camera's own axes) and one white frame checked: caught when the facet is withheld.

The truth is the twin's: where it draws the marks (:mod:`sofast_station.twin.marks`), from its own camera model
and the true poses; nothing of the check's code.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
from scipy.stats import beta

from ..calibrate.marks import clear_hold, commission_marks, mark_settings
from ..calibrate.records import load_radiometric
from ..config import load_config
from ..fringes import Pattern
from ..twin.assembly import TrueAssembly, true_geometry
from ..twin.marks import mark_image_centres_px
from ..twin.parameters import TrueFacet, TwinOptics
from ..twin.station import TwinStation
from .marks import MarkCheck
from .population import DEFAULT_STATION, KINDS, _records_from, draw_station, kind_config
from .study import Placement

#: The camera moves the check is asked to catch (the issue's: a turn of 0.2 mrad, a shift of 1 mm), about and
#: along the camera's own axes (x along the image's columns, y down its rows, z the optical axis), and the two
#: it is not expected to see (a roll and a slide along the line of sight: module docstring of
#: :mod:`sofast_station.measure.fixture_marks`).
MOVES = {"turn 0.2 mrad about x": {"turn_mrad": (0.2, 0.0, 0.0)},
         "turn 0.2 mrad about y": {"turn_mrad": (0.0, 0.2, 0.0)},
         "turn 0.2 mrad about x and y": {"turn_mrad": (0.1414, -0.1414, 0.0)},
         "shift 1 mm along x": {"shift_mm": (1.0, 0.0, 0.0)},
         "shift 1 mm along y": {"shift_mm": (0.0, 1.0, 0.0)},
         "shift 1 mm along x and y": {"shift_mm": (-0.7071, 0.7071, 0.0)},
         "roll 0.2 mrad about z": {"turn_mrad": (0.0, 0.0, 0.2)},
         "shift 1 mm along z": {"shift_mm": (0.0, 0.0, 1.0)}}
#: The moves that must be caught.
MUST_CATCH = tuple(k for k in MOVES if "about z" not in k and "along z" not in k)


class _Display:
    """A display over the twin for the commissioning routine: it shows a uniform pattern (white)."""

    def __init__(self, shape):
        self.shape = shape
        self.image = np.zeros(shape, dtype=np.uint8)

    def show(self, pattern: Pattern) -> None:
        if pattern.kind != "uniform":
            raise ValueError("the marks' study shows uniform patterns only")
        self.image = np.full(self.shape, pattern.command, dtype=np.uint8)
        self.image.setflags(write=False)


class _Camera:
    """The twin's camera for the commissioning routine: each grab a new noisy frame of what the display shows."""

    def __init__(self, station: "MarkStation", display: _Display, rng: np.random.Generator):
        self.station, self.display, self.rng = station, display, rng

    def grab(self, timeout_s: float = 2.0) -> np.ndarray:
        return self.station.frame(self.station.twin0, self.rng, self.display.image)


class MarkStation:
    """One drawn station with marks (module docstring).

    Parameters
    ----------
    index, seed : int
        Station *index* of the population of *seed* (:func:`~sofast_station.station.population.draw_station`,
        dish stations only).
    data_dir : Path
        Where its hold file may go (a temporary folder).
    full : bool
        The station's camera at its own resolution (1600 x 1200), not a quarter of it.
    """

    def __init__(self, index: int, seed: int, data_dir: Path, full: bool = False):
        self.spec = draw_station(index, seed, kinds=("dish",))
        if full:
            with _records_from(data_dir):
                cfg = dataclasses.replace(load_config(DEFAULT_STATION), data_dir=data_dir)
        else:
            cfg = kind_config("dish", data_dir)
        cam = cfg.geometry.camera
        dist = cam.distortion.copy()
        dist[0] = self.spec["k1"]
        self.config = dataclasses.replace(cfg, geometry=dataclasses.replace(
            cfg.geometry, camera=dataclasses.replace(cam, distortion=dist)))
        self.settings = mark_settings(self.config)
        if self.settings is None:
            raise ValueError(f"{self.config.path} has no [marks]: the study needs them")
        design = self.config.design
        focal = [design.focal_length_m * (1.0 + KINDS["dish"].focal_spread * u) for u in self.spec["focal"]]
        self.facet = TrueFacet.from_dict({**self.spec["facet"], "focal_length_x_m": focal[0],
                                          "focal_length_y_m": focal[1]})
        self.optics = TwinOptics.from_dict(self.spec["optics"])
        self.data_dir = data_dir
        self.radiometric = load_radiometric(self.config.radiometric_path)
        scr = self.config.geometry.screen
        self.white = np.full((scr.height_px, scr.width_px), 255, dtype=np.uint8)
        self.white.setflags(write=False)
        self.twin0 = self.twin()

    def twin(self, placement=((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), turn_mrad=(0.0, 0.0, 0.0),
             shift_mm=(0.0, 0.0, 0.0)):
        """The station's twin with the facet at *placement* (mm, mrad) and the camera turned and shifted."""
        geometry = self.config.geometry
        if any(turn_mrad) or any(shift_mm):
            geometry = true_geometry(geometry, TrueAssembly(camera_turn_mrad=tuple(turn_mrad),
                                                            camera_shift_mm=tuple(shift_mm)))
        facet = dataclasses.replace(self.facet, placement_mm=tuple(placement[0]), placement_mrad=tuple(placement[1]))
        return TwinStation(geometry, self.config.design, facet, self.optics, marks=self.settings.design)

    def frame(self, twin, rng: np.random.Generator, image: np.ndarray | None = None) -> np.ndarray:
        """A white frame (or *image*'s) with its own noise, room light and refresh phase, at the station's
        radiometric exposure and gain."""
        return twin.capture(self.white if image is None else image, rng, exposure_s=self.radiometric.exposure_s,
                            gain=self.radiometric.gain, flicker_phase=float(rng.random()))

    def commission(self, rng: np.random.Generator):
        """``calibrate marks`` on this station: the commissioned record (as the line loads it) and its check."""
        display = _Display(self.white.shape)
        found = commission_marks(display, _Camera(self, display, rng), self.settings, self.config.geometry)
        record = {"record_id": "marks-study", "positions_px": found.positions_px}
        return found, MarkCheck(self.settings, record, self.config.geometry, self.data_dir)


def check_once(check, frame: np.ndarray) -> dict:
    """One check of *frame*, forgetting any hold it leaves (each capture judged on its own)."""
    entry = check.check(frame)
    if check.hold is not None:
        check.hold = None
        clear_hold(check.data_dir)
    return entry


def good_cycles(station: MarkStation, check, n: int, rng: np.random.Generator, place_every: int = 1) -> list[dict]:
    """*n* good cycles: the facet placed anew every *place_every* cycles, each frame checked. Each outcome:
    ``withheld`` (a false alarm), the apparent turn and roll against their limits, the shift against its own
    noise, the residual RMS, the marks found, the check's time."""
    s = station.settings
    out = []
    twin = station.twin0
    for i in range(n):
        if place_every and i % place_every == 0:
            twin = station.twin(Placement().draw(rng))
        entry = check_once(check, station.frame(twin, rng))
        turn = entry.get("turn_mrad") or [math.nan] * 3
        sigma = entry.get("shift_sigma_px") or math.nan
        out.append({"withheld": bool(entry.get("withhold")), "reason": entry.get("withhold"),
                    "found": entry["found"], "turn_fraction": math.hypot(turn[0], turn[1]) / s.max_turn_mrad,
                    "roll_fraction": abs(turn[2]) / s.max_roll_mrad,
                    "shift_sigmas": math.hypot(*(entry.get("shift_px") or [math.nan, math.nan])) / max(sigma, 1e-12),
                    "residual_rms_px": entry.get("residual_rms_px"), "seconds": entry["seconds"]})
    return out


def moves(station: MarkStation, check, rng: np.random.Generator, which=tuple(MOVES)) -> dict:
    """Each move of :data:`MOVES` in *which*: the camera moved, one white frame checked. Name -> ``caught``,
    the apparent turn (mrad) and the reason."""
    out = {}
    for name in which:
        twin = station.twin(**MOVES[name])
        entry = check_once(check, station.frame(twin, rng))
        out[name] = {"caught": bool(entry.get("withhold")), "turn_mrad": entry.get("turn_mrad"),
                     "shift_px": entry.get("shift_px"), "reason": entry.get("withhold")}
    return out


def binomial_upper(n: int, failures: int = 0, confidence: float = 0.95) -> float:
    """The one-sided upper confidence bound on a rate after *failures* in *n* trials (exact, Clopper-Pearson);
    with none, ``1 - (1 - confidence)^(1/n)`` (3/n for large n, the rule of three)."""
    if n <= 0:
        return 1.0
    if failures == 0:
        return 1.0 - (1.0 - confidence) ** (1.0 / n)

    return float(beta.ppf(confidence, failures + 1, n - failures))


def run_study(stations: int, cycles: int, seed: int, data_dir: Path, full: bool = False, place_every: int = 1,
              which=tuple(MOVES), progress=None) -> dict:
    """The whole study: *stations* drawn stations, *cycles* good cycles each, every move of *which* on each."""
    t0 = time.perf_counter()
    good, caught, found_off = [], {name: [] for name in which}, []
    for i in range(stations):
        station = MarkStation(i, seed, data_dir, full=full)
        rng = np.random.default_rng([seed, i, 0x3A2C])
        found, check = station.commission(rng)
        truth = _truth_px(station)
        found_off.append(float(np.max(np.hypot(*(found.positions_px - truth).T))))
        good += good_cycles(station, check, cycles, rng, place_every)
        for name, m in moves(station, check, rng, which).items():
            caught[name].append(m)
        if progress:
            progress(i + 1, stations, station)
    false = sum(g["withheld"] for g in good)
    return {"stations": stations, "cycles": len(good), "false_alarms": false,
            "false_alarm_upper_95": binomial_upper(len(good), false), "good": good, "moves": caught,
            "commissioned_vs_truth_px": found_off, "seconds": time.perf_counter() - t0}


def _truth_px(station: MarkStation) -> np.ndarray:
    """Where the twin draws the marks' centres, pixels (its own camera model and the true fixture pose)."""
    twin = station.twin0
    return mark_image_centres_px(station.settings.design, twin.geometry.fixture_to_camera, twin.trace.camera)
