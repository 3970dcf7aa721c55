"""Assemble the simulated station from station.toml's ``[simulation]`` table."""

from __future__ import annotations

import copy
import dataclasses
import logging
import threading
from dataclasses import dataclass, field

import numpy as np

from ..calibrate.marks import mark_settings
from ..calibrate.records import RadiometricRecord
from ..config import StationConfig
from ..config_schema import SIMULATED_FAULTS
from ..devices.renderer import FringeRenderer
from ..devices.simulated import SimulatedCamera, SimulatedDisplay, SimulatedRangeFinder
from ..errors import ConfigError
from ..twin.assembly import TrueAssembly, TrueScreen, true_geometry
from ..twin.heliostat import TwinHeliostat, heliostat_from_simulation, heliostat_truth
from ..twin.parameters import TrueFacet, TwinOptics
from ..twin.population import FacetPopulation
from ..twin.station import TwinStation
from ..twin.sunlight import Sunlight, facet_in_sunlight, sunlit_plan
from ..twin.trace import rotation_zyx
from ..twin.truth import ground_truth
from .opened import Station
from .simulated_commission import SimulatedHandheld, SimulatedMirror
from .simulated_faults import faulty_job

_SIM_KEYS = {"seed", "facet", "optics", "population", "distance_error_m", "faults", "hang_s", "slow_s",
             "assembly", "heliostat", "temperature"}

#: Faults the simulated station can inject for a given serial ([simulation.faults] SERIAL = KIND).
FAULT_KINDS = SIMULATED_FAULTS

log = logging.getLogger(__name__)


def build_twin(config: StationConfig, noise: bool = True):
    """The digital twin described by ``[simulation]`` (true facet and optics) in the station's geometry.

    The twin's geometry is the one station.toml states (never one measured by a calibration: those are
    estimates of the twin's truth), changed by ``[simulation.assembly]`` (a bowed screen of another pitch, a
    misplaced camera: :class:`~sofast_station.twin.assembly.TrueAssembly`).
    """
    sim = config.simulation
    unknown = sorted(set(sim) - _SIM_KEYS)
    if unknown:
        raise ConfigError(f"{config.path} [simulation] has unknown key(s) {', '.join(unknown)}")
    try:
        facet = TrueFacet.from_dict(sim.get("facet", {}))
        optics = TwinOptics.from_dict(sim.get("optics", {}))
        assembly = TrueAssembly.from_dict(sim.get("assembly", {}))
    except ConfigError as exc:
        raise ConfigError(f"{config.path} [simulation]: {exc}") from None
    if not noise:
        optics = optics.noise_free()
    geometry = getattr(config, "stated_geometry", None) or config.geometry
    if config.camera_record is not None:
        # The analysis uses the camera record (an estimate); the twin's camera is the physical one, which
        # the [camera] table describes.
        geometry = dataclasses.replace(geometry, camera=config.camera_record["stated"])
    screen = None if assembly.screen_is_ideal else TrueScreen(geometry.screen, assembly)
    if not assembly.ideal:
        geometry = true_geometry(geometry, assembly)
    if config.ensemble is not None:
        if screen is not None:
            raise ConfigError(f"{config.path} [simulation.assembly] bends or rescales the screen, which the "
                              "heliostat twin does not trace: leave its screen terms out for a heliostat station")
        heliostat = heliostat_from_simulation(sim, config.ensemble, f"{config.path} [simulation]")
        return TwinHeliostat(geometry, config.ensemble, heliostat, optics)
    if "heliostat" in sim:
        raise ConfigError(f"{config.path} [simulation.heliostat] describes a heliostat, but [station] facet is a "
                          "single facet's file")

    marks = mark_settings(config)
    return TwinStation(geometry, config.design, facet, optics, screen_shape=screen,
                       marks=None if marks is None else marks.design)


def build_population(config: StationConfig):
    """``[simulation.population]`` (:class:`~sofast_station.twin.population.FacetPopulation`), or None when the
    station measures the same facet every time."""
    table = config.simulation.get("population")
    if not table:
        return None
    try:
        return FacetPopulation.from_dict(table)
    except ConfigError as exc:
        raise ConfigError(f"{config.path} [simulation.population]: {exc}") from None


@dataclass
class SimulatedStation(Station):
    """The simulated station, with faults injected per serial for tests of the production loop, and with
    ``[simulation.population]`` a line whose facets differ, each one placed by the simulated robot (:meth:`place`)."""

    population: object | None = None
    #: The twin of ``[simulation.facet]`` (what ``inspect`` measures), every drawn facet's starting point.
    nominal_twin: object | None = None
    #: The facets placed so far in this run, and the serial in the fixture.
    placed: int = 0
    serial_in_fixture: str | None = None
    _next: dict = field(default_factory=dict, repr=False)
    #: The twin's sunlight plans (:func:`truth_optics`), one per design and optics settings.
    _sunlit_plans: dict = field(default_factory=dict, repr=False)

    def place(self, request) -> None:
        """The simulated robot puts the facet of *request* in the fixture (called before its trigger).

        With a population, a serial not in the fixture is the line's next facet: facet k of the run, drawn
        by :meth:`~sofast_station.twin.population.FacetPopulation.draw`; the same serial again (the robot
        placing it once more) is the same facet. The next facet's twin is prepared in the background while
        this one is measured, so a cycle does not wait for it.
        """
        if self.population is None or request.serial == self.serial_in_fixture:
            return
        twin = self._twin_of(self.placed)
        self.twin = self.camera.twin = self.range_finder.twin = twin
        self.serial_in_fixture = request.serial
        self.placed += 1
        self._prepare(self.placed)

    def _twin_of(self, index: int):
        job = self._next.pop(index, None)
        if job is not None:
            job["thread"].join()
            if "twin" in job:
                return job["twin"]
            log.warning("the simulated facet %d could not be prepared in the background (%s); preparing it now",
                        index, job.get("error"))
        return self.nominal_twin.with_facet(self.population.draw(self.nominal_twin.facet, index,
                                                                 self.config.design))

    def _prepare(self, index: int) -> None:
        job: dict = {}

        def run():
            try:
                job["twin"] = self.nominal_twin.with_facet(self.population.draw(self.nominal_twin.facet, index,
                                                                                self.config.design))
            except Exception as exc:          # said when the facet is placed, and made again then
                job["error"] = exc
        job["thread"] = threading.Thread(target=run, name=f"twin-facet-{index}", daemon=True)
        self._next = {index: job}
        job["thread"].start()

    def job_for(self, recipe, serial: str | None = None):
        """The recipe's job, with this cycle's fault armed when ``[simulation.faults]`` names *serial*: a fault of
        the camera ("dark", "camera-timeout", ...) is armed in the simulated camera, one of the analysis
        ("hung-analysis", "hung-facet", "slow-analysis", "worker-dies") wraps the job
        (:class:`~sofast_station.station.simulated_faults.FaultyJob`), which misbehaves in the analysis worker
        as the fault says; with no serial (the warm-up) nothing is armed."""
        job = super().job_for(recipe, serial)
        if serial is None:
            return job
        sim = self.config.simulation
        kind = sim.get("faults", {}).get(serial)
        self.camera.fault = kind if kind in ("dark", "camera-timeout", "misplaced", "hung-capture",
                                             "camera-disconnect", "lights-off") else None
        return faulty_job(job, kind, hang_s=sim.get("hang_s", 3600.0), slow_s=sim.get("slow_s", 15.0))

    def move_camera(self, turn_mrad=(0.0, 0.0, 0.0), shift_mm=(0.0, 0.0, 0.0)) -> None:
        """Bump the twin's camera (tests and benchmarks of the fixture marks' check): turned by *turn_mrad* about
        and shifted by *shift_mm* along its own axes, on top of ``[simulation.assembly]``; the screen and the
        fixture stay. The next facet placed, and the one in the fixture, are seen from there."""
        sim = copy.deepcopy(self.config.simulation)
        assembly = TrueAssembly.from_dict(sim.get("assembly", {}))
        sim["assembly"] = {**assembly.to_dict(),
                           "camera_turn_mrad": [a + float(b) for a, b in zip(assembly.camera_turn_mrad, turn_mrad)],
                           "camera_shift_mm": [a + float(b) for a, b in zip(assembly.camera_shift_mm, shift_mm)]}
        nominal = build_twin(dataclasses.replace(self.config, simulation=sim), noise=True)
        nominal = nominal.with_optics(self.nominal_twin.optics)          # the station's own optics (noise or none)
        in_fixture = self.twin.facet if self.twin is not None else nominal.facet
        self._next = {}
        self.nominal_twin = nominal
        self.twin = self.camera.twin = self.range_finder.twin = nominal.with_facet(in_fixture)

    def change_display(self, **optics) -> None:
        """Change the twin's display (tests of its self-test, station/display.py): e.g. ``display_gamma=2.5``, a
        picture mode changed behind the radiometric table's back. The facet in the fixture and the next are seen
        through it."""
        changed = dataclasses.replace(self.nominal_twin.optics, **optics)
        self._next = {}
        self.nominal_twin = self.nominal_twin.with_optics(changed)
        self.twin = self.camera.twin = self.range_finder.twin = self.twin.with_optics(
            dataclasses.replace(self.twin.optics, **optics))

    def reopen_camera(self) -> None:
        self.camera.fault = None
        self.camera.release_hang()

    def truth(self, valid: np.ndarray, job=None) -> dict:
        """The twin's ground truth at the pixels *valid* (:func:`~sofast_station.twin.truth.ground_truth`),
        with the optical figures of its exact surface (:func:`truth_optics`) when *job* (a facet's) traces its
        optical figures: the same truth whoever measured the facet (``inspect`` or the line)."""
        if isinstance(self.twin, TwinHeliostat):     # every facet's figures and canting, and the heliostat's
            return heliostat_truth(self.twin, valid)
        truth = ground_truth(self.twin, valid)
        self._last_valid = np.asarray(valid, dtype=bool)
        design, optics = getattr(job, "design", None), getattr(job, "optics", None)
        if optics is not None and design is not None:
            truth["optics"] = truth_optics(self.twin, valid, design, optics, self._sunlit_plans,
                                           boresight_mrad=truth["boresight_mrad"])
        return truth

    def handheld_camera(self, settings, seed: int | None = None):
        """The second camera of ``calibrate screen``, with the twin's views of the screen
        (:class:`~sofast_station.station.simulated_commission.SimulatedHandheld`: a Camera with ``place``)."""
        return SimulatedHandheld(self, settings, seed)

    def mirror_placer(self, target, seed: int | None = None):
        """The reference mirror of ``calibrate pose`` in the twin's fixture
        (:class:`~sofast_station.station.simulated_commission.SimulatedMirror`: ``place`` and ``restore``)."""
        return SimulatedMirror(self, target, seed)

    def reference_certificate(self) -> dict:
        """The facet in the fixture as a reference's certificate (``calibrate geometry``): the twin's truth,
        the conventions' figures of its exact surface over the pixels the last inspection kept (as every
        truth of the twin is stated: the analysis leaves out the pixels within the edge's blur, and over a
        1-pixel ring a facet's best-fit f differs by a few hundredths of a percent), else over every pixel
        that sees the facet, and its placement; exact (zero uncertainty)."""
        kept = getattr(self, "_last_valid", None)
        truth = ground_truth(self.twin, kept if kept is not None else np.asarray(self.twin.coverage) > 0.5)
        return {"name": f"twin's true facet ({self.config.design.name})",
                "source": "the digital twin's exact surface ([simulation.facet]), as certified figures",
                "focal_length_x_m": truth["focal_length_x_m"], "focal_length_y_m": truth["focal_length_y_m"],
                "placement_mm": tuple(truth["placement"]["mm"]), "placement_mrad": tuple(truth["placement"]["mrad"])}


def open_simulated(config: StationConfig, radiometric: RadiometricRecord, seed: int | None = None,
                   noise: bool = True) -> Station:
    """Simulated display (offscreen renderer), twin camera and twin range finder."""
    twin = build_twin(config, noise=noise)
    # docs/conventions.md#station-layout: the facet's reflection, widened for its largest slope error,
    # must lie on the screen, or the edge of the facet would be measured against the bezel.
    margin = twin.footprint_check(float(config.design.layout.get("max_slope_error_mrad", 3.0)))
    log.debug("reflected footprint fits the screen with %.0f mm to spare", 1e3 * margin["min_margin_m"])
    scr = config.geometry.screen
    renderer = FringeRenderer(scr.width_px, scr.height_px, lut=radiometric.lut,
                              floor_level=radiometric.floor_level, max_level=radiometric.max_level)
    # The display's settle time: the latency calibration's, else [devices] display_options.settle_s, else 0.
    settle_s = getattr(radiometric, "settle_s", None)
    if settle_s is None:
        settle_s = float(config.raw.get("devices", {}).get("display_options", {}).get("settle_s", 0.0))
    display = SimulatedDisplay(renderer, latency_s=twin.optics.display_latency_s, settle_s=settle_s)
    seed = config.simulation.get("seed", 0) if seed is None else seed
    # The refresh phase of each grab is not noise (it is there in noise-free runs too): its own stream.
    camera = SimulatedCamera(twin, display, np.random.default_rng(seed) if noise else None,
                             flicker_rng=np.random.default_rng([int(seed) % 2**32, 0xF11C]))
    camera.set_exposure(radiometric.exposure_s)
    camera.set_gain(radiometric.gain)
    rangefinder = SimulatedRangeFinder(twin, float(config.simulation.get("distance_error_m", 0.0)))
    faults = config.simulation.get("faults", {})
    bad = {k: v for k, v in faults.items() if v not in FAULT_KINDS}
    if bad:
        raise ConfigError(f"{config.path} [simulation.faults]: unknown fault kind(s) {bad}; use {FAULT_KINDS}")
    return SimulatedStation(config=config, display=display, camera=camera, range_finder=rangefinder,
                            radiometric=radiometric, twin=twin, nominal_twin=twin, population=build_population(config))


def sunlight_of(settings):
    """The twin's record (:class:`~sofast_station.twin.sunlight.Sunlight`) of a recipe's optics settings (an
    :class:`~sofast_station.optics.OpticsSettings`, read attribute by attribute: the twin's truth shares no code
    with the optics it checks)."""
    sun, ap = settings.sun, settings.aperture
    aperture = None if ap is None else (("circle", ap.radius_m) if ap.shape == "circle"
                                        else ("rectangle", ap.width_m, ap.height_m))
    return Sunlight(sun=sun.kind, half_angle_mrad=sun.half_angle_mrad, sigma_mrad=sun.sigma_mrad, csr=sun.csr,
                    dni_w_m2=settings.dni_w_m2, reflectivity=settings.reflectivity,
                    incidence_angle_deg=settings.incidence_angle_deg, slant_range_m=settings.slant_range_m,
                    aperture=aperture)


def truth_optics(twin, kept: np.ndarray, design, settings, plans: dict | None = None,
                 boresight_mrad: dict | None = None) -> dict:
    """The optical figures of the twin's true facet in the sunlight of *settings*: what the measured figures
    should be.

    The twin traces its own true surface over the whole outline (:func:`~sofast_station.twin.sunlight.
    facet_in_sunlight`; nothing of ``optics/``), in the boresight frame its ground truth defines at the kept
    pixels (*boresight_mrad*, ``ground_truth(twin, kept)["boresight_mrad"]``; computed when not given).
    *plans* keeps the sunlight's samples and the design's figures per design and settings (they do not
    depend on the facet)."""
    if boresight_mrad is None:
        boresight_mrad = ground_truth(twin, kept)["boresight_mrad"]
    sunlight = sunlight_of(settings)
    key = (id(design), sunlight)
    plan = None if plans is None else plans.get(key)
    if plan is None or plan[0] is not design:
        plan = (design, sunlit_plan(design, sunlight))
        if plans is not None:
            plans[key] = plan
    x_a, y_a = (float(c) for c in design.alignment_point_m)
    pivot = np.array([x_a, y_a, float(design.z(x_a, y_a))])
    rotation = rotation_zyx(1e-3 * boresight_mrad["x"], 1e-3 * boresight_mrad["y"], 0.0)
    return facet_in_sunlight(twin.surface, plan[1], sunlight, rotation, pivot)
