"""Facet recipes: which design, alignment point, analysis settings and limits apply to a facet.

The PLC names the recipe, or the serial number picks it by pattern, or the station's default applies.
In station.toml::

    [recipes.gore-a]
    facet = "fixtures/facets/gore_5m33.toml"
    serial_pattern = "^GA-"                 # regular expression on the serial
    alignment_point_m = [3.8, 0.0]          # overrides the facet file's
    limits = { focal_length_tolerance = 0.01 }
    quality = { min_valid_fraction = 0.85 }
    optics = { aperture = { shape = "circle", radius_m = 0.05 } }   # over [optics] (docs/optics.md)
    method = "fixed"                        # one frame of a dot grid, not the 18 of the fringes
    fixed = { spacing_px = 12, white_frame = false }   # the dot grid (docs/method.md, "On the station")

    [recipes.reference]                     # judges the station (docs/reliability.md#a-reference-every-shift)
    facet = "fixtures/facets/dish_5m33.toml"
    serial_pattern = "^REF-"
    reference = "certificates/REF-1.toml"   # its certificate ([reference] table), or "twin"

    [recipes.field-5x5]                     # a heliostat recipe
    facet = "fixtures/facets/heliostat_5x5.toml"
    prescriptions = "site/prescriptions"    # 'field prescription' output: a heliostat whose serial has its
                                            # SERIAL.toml there is judged against that canting (docs/field.md)
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path

from .calibrate.geometry import load_reference
from .devices.protocols import FacetRequest
from .ensemble import EnsembleDesign, is_ensemble_file, load_ensemble
from .errors import ConfigError, UnknownRecipeError
from .facet import FacetDesign, load_facet
from .measure.fixed import FixedCapture, FixedSettings, LcdDotGrid, check_fixed_layout, pitch_for_spacing
from .measure.pipeline import AnalysisSettings, default_screen
from .result.optical_figures import optics_for
from .result.verdict import Limits, Quality, limits_from_table, quality_from_table

_KEYS = {"facet", "serial_pattern", "alignment_point_m", "measure_point_m", "limits", "quality", "analysis",
         "optics", "reference", "prescriptions", "method", "fixed"}
#: A recipe's fixed-pattern table's keys and defaults (config_schema's section "fixed").
FIXED_DEFAULTS = {"pitch_px": None, "spacing_px": 12.0, "diameter": 0.4, "white_frame": False, "min_dots": 100,
                  "index_tolerance": 0.45}


@dataclass(frozen=True)
class Recipe:
    name: str
    design: FacetDesign
    analysis: AnalysisSettings
    limits: Limits
    quality: Quality
    serial_pattern: re.Pattern | None = None
    #: How the optical figures are computed (``[optics]`` with the recipe's ``optics`` table); None: off.
    optics: object | None = None
    #: A heliostat recipe's heliostat (its facet file is a heliostat file; ``design`` is then its bounding
    #: outline): the loop analyses its facets in one capture (docs/heliostats.md). None: a single facet.
    ensemble: EnsembleDesign | None = None
    #: A reference recipe's certificate (a [reference] file's path, or "twin": the simulated station's truth):
    #: its facet judges the station, not itself (:mod:`sofast_station.station.reference`). None: a facet.
    reference: str | None = None
    #: A heliostat recipe's folder of canting prescriptions (``sofast-station field prescription``'s
    #: ``SERIAL.toml``): a heliostat whose serial has a file there is judged against its own place in the field
    #: (:func:`~sofast_station.job.job_for`). None: every heliostat against the recipe's design.
    prescriptions: Path | None = None
    #: The fixed-pattern method's dot grid and settings (``method = "fixed"``,
    #: :class:`~sofast_station.measure.fixed.FixedCapture`); None: the fringes.
    fixed: object | None = None

    @property
    def method(self) -> str:
        return "fringe" if self.fixed is None else "fixed"


def fixed_capture(table: dict, config, design: FacetDesign, where: str):
    """The :class:`~sofast_station.measure.fixed.FixedCapture` of a recipe's ``fixed`` table on the station of
    *config*: the dot grid on its display (``pitch_px``, or the pitch that pictures the dots ``spacing_px``
    camera pixels apart on the nominal facet), checked against the station's layout
    (:func:`~sofast_station.measure.fixed.check_fixed_layout`: a ConfigError naming what to change when the
    lattice cannot be indexed there)."""
    unknown = sorted(set(table) - set(FIXED_DEFAULTS))
    if unknown:
        raise ConfigError(f"{where}.fixed has unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(FIXED_DEFAULTS))}")
    t = {**FIXED_DEFAULTS, **table}
    geometry, scr = config.geometry, config.geometry.screen
    screen = default_screen(geometry)
    pitch = t["pitch_px"] or pitch_for_spacing(geometry, design, scr.width_px, scr.height_px, screen,
                                               float(t["spacing_px"]))
    grid = LcdDotGrid(int(scr.width_px), int(scr.height_px), int(pitch), max(2.0, float(t["diameter"]) * int(pitch)))
    check_fixed_layout(geometry, design, grid, screen, where)
    settings = FixedSettings(min_dots=int(t["min_dots"]), index_tolerance=float(t["index_tolerance"]),
                             max_dot_diameter_px=max(24.0, 2.0 * float(t["spacing_px"])))
    return FixedCapture(grid, settings, bool(t["white_frame"]))


def default_recipe(config) -> Recipe:
    """The station's own facet (or heliostat), settings and limits, under the name "default"."""
    return Recipe("default", config.design, config.analysis, config.limits, config.quality,
                  optics=getattr(config, "optics", None), ensemble=getattr(config, "ensemble", None))


def recipes_from_config(config) -> dict[str, Recipe]:
    """The station's recipes: "default" plus every ``[recipes.NAME]`` table of station.toml."""
    out = {"default": default_recipe(config)}
    for name, table in config.raw.get("recipes", {}).items():
        where = f"{config.path} [recipes.{name}]"
        if not isinstance(table, dict):
            raise ConfigError(f"{where} must be a table")
        unknown = sorted(set(table) - _KEYS)
        if unknown:
            raise ConfigError(f"{where} has unknown key(s) {', '.join(unknown)}; allowed: {', '.join(sorted(_KEYS))}")
        design, ensemble = config.design, getattr(config, "ensemble", None)
        if "facet" in table:
            path = config.path.parent / table["facet"]
            if is_ensemble_file(path):          # a heliostat recipe
                ensemble = load_ensemble(path)
                design = ensemble.layout_design()
            else:
                design, ensemble = load_facet(path), None
        overrides = {k: table[k] for k in ("alignment_point_m", "measure_point_m") if k in table}
        if overrides and ensemble is not None:
            raise ConfigError(f"{where}: alignment_point_m and measure_point_m are a facet's; a heliostat's are in "
                              "its facets' files (and its measure_facet)")
        if overrides:
            design = FacetDesign.from_dict({**design.to_dict(), **overrides}, source=where)
        analysis = dataclasses.replace(config.analysis, **table.get("analysis", {}))
        limits = limits_from_table({**dataclasses.asdict(config.limits), **table.get("limits", {})}, f"{where}.limits")
        quality = quality_from_table({**dataclasses.asdict(config.quality), **table.get("quality", {})},
                                     f"{where}.quality")
        pattern = None
        if "serial_pattern" in table:
            try:
                pattern = re.compile(table["serial_pattern"])
            except re.error as exc:
                raise ConfigError(f"{where}: serial_pattern is not a valid regular expression: {exc}") from None
        optics = optics_for(config.raw, str(config.path), name)
        reference = table.get("reference")
        if reference is not None:
            reference = _reference(reference, config, where, ensemble)
        method = table.get("method", "fringe")
        if method not in ("fringe", "fixed"):
            raise ConfigError(f"{where}: method must be \"fringe\" or \"fixed\", got {method!r}")
        if "fixed" in table and method != "fixed":
            raise ConfigError(f"{where}: a fixed table is for method = \"fixed\"; this recipe measures with {method}")
        fixed = None
        if method == "fixed":
            if ensemble is not None:
                raise ConfigError(f"{where}: the fixed-pattern method measures one facet; a heliostat recipe "
                                  "measures with the fringes")
            fixed = fixed_capture(table.get("fixed", {}), config, design, where)
        out[name] = Recipe(name, design, analysis, limits, quality, pattern, optics, ensemble, reference,
                           _prescriptions(table, ensemble, config.path.parent, where), fixed=fixed)
    return out


def _reference(value, config, where: str, ensemble) -> str:
    """A recipe's ``reference``: "twin" (the simulated station's truth) or a certificate file, read now so a
    mistake stops the station at its start."""
    if ensemble is not None:
        raise ConfigError(f"{where}: reference is a single facet's certificate; a heliostat recipe cannot be one")
    if value == "twin":
        if config.backend != "simulated":
            raise ConfigError(f"{where}: reference = \"twin\" is the simulated station's truth; a hardware station "
                              "names the reference facet's certificate (a [reference] file)")
        return "twin"
    if not isinstance(value, str) or not value:
        raise ConfigError(f"{where}: reference must name the reference facet's certificate file, got {value!r}")
    path = config.path.parent / value
    try:
        load_reference(path)
    except ConfigError as exc:
        raise ConfigError(f"{where} reference: {exc}") from None
    return str(path)


def _prescriptions(table: dict, ensemble, base: Path, where: str) -> Path | None:
    """A heliostat recipe's ``prescriptions`` folder (relative to station.toml), checked; None without one."""
    if "prescriptions" not in table:
        return None
    if ensemble is None:
        raise ConfigError(f"{where}: prescriptions is a heliostat's (canting per serial); this recipe measures a "
                          "single facet: name a heliostat file as its facet, or remove prescriptions")
    folder = (base / str(table["prescriptions"])).resolve()
    if not folder.is_dir():
        raise ConfigError(f"{where}: prescriptions folder {folder} does not exist; write it with 'sofast-station "
                          "field prescription --site SITE.toml' (docs/field.md) or correct the path")
    return folder


def choose_recipe(recipes: dict[str, Recipe], request: FacetRequest) -> Recipe:
    """The PLC's recipe if it names one, else the first whose serial pattern matches, else "default"."""
    if request.recipe:
        if request.recipe not in recipes:
            raise UnknownRecipeError(f"the PLC asked for recipe {request.recipe!r}, which station.toml does not define "
                              f"(known: {', '.join(sorted(recipes))})")
        return recipes[request.recipe]
    for recipe in recipes.values():
        if recipe.serial_pattern is not None and recipe.serial_pattern.search(request.serial):
            return recipe
    return recipes["default"]
