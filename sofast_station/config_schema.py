"""What station.toml may hold: every section, every key, its type, its range, and the rules between keys.

:func:`validate` checks a whole file at load, before any device opens, so that a typo stops the station
at the door with one message naming the file, the section, the key, the value and what is allowed,
instead of a traceback in the middle of a facet.

The schema is data. To add a section or a key, add a :class:`Key` to :data:`SECTIONS` (and a function to
:data:`CROSS_RULES` for a rule between keys), then document the key in the shipped ``station.toml``::

    SECTIONS["opcua"] = {
        "endpoint": Key("str", doc="opc.tcp://host:port of the server"),
        "publish_s": Key("float", low=0.0, low_open=True, doc="publishing interval"),
    }

Sections whose contents another module checks in depth are declared with ``Key("any")`` / ``Key("table")``
and their reader is listed in :data:`READERS` (run at load), e.g. ``[web]``, ``[opcua]``, ``[drift]``.
A library such as pydantic was considered; a table of
plain rules is enough here, keeps messages in the station's words (file, section, key, value, allowed),
and adds no dependency to the measuring loop.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable

from .errors import ConfigError
from .qc.acceptance import contract_from_config


@dataclass(frozen=True)
class Key:
    """One key of a section.

    Parameters
    ----------
    kind : str
        ``"int"`` (a whole number), ``"float"`` (any finite number), ``"bool"``, ``"str"``, ``"table"``
        (a TOML table, not looked into), ``"floats"`` (a list of numbers), ``"ints"`` (a list of whole
        numbers), ``"float|floats"`` (a number or a list of numbers), or ``"section:NAME"`` (a table checked
        against the section NAME of :data:`SECTIONS`), ``"any"``.
    low, high : float, optional
        Inclusive bounds of a number (of every element of a list); *low_open* / *high_open* make them
        exclusive.
    choices : tuple, optional
        The values allowed.
    length : tuple of int, optional
        The lengths a list may have.
    doc : str
        What the key means (for messages and for the reader of this table).
    """

    kind: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple = ()
    length: tuple = ()
    doc: str = ""

    def allowed(self) -> str:
        """What is allowed, in words."""
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        base = {"int": "a whole number", "float": "a number", "bool": "true or false", "str": "a string",
                "table": "a table", "floats": "a list of numbers", "ints": "a list of whole numbers",
                "float|floats": "a number or a list of numbers", "any": "anything"}.get(self.kind, "a table")
        if self.length:
            base += " of length " + " or ".join(str(n) for n in self.length)
        bounds = []
        if self.low is not None:
            bounds.append(f"{'above' if self.low_open else 'at least'} {self.low:g}")
        if self.high is not None:
            bounds.append(f"{'below' if self.high_open else 'at most'} {self.high:g}")
        if bounds:
            text = " and ".join(bounds)
            if self.kind in ("floats", "ints", "float|floats"):
                base += f" (each {text})"
            else:
                base += (" of " if text.startswith("at") else " ") + text
        return base


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _in_range(key: Key, v: float) -> bool:
    if key.low is not None and (v <= key.low if key.low_open else v < key.low):
        return False
    if key.high is not None and (v >= key.high if key.high_open else v > key.high):
        return False
    return True


def _pos(doc: str) -> Key:
    return Key("float", low=0.0, low_open=True, doc=doc)


def _nonneg(doc: str) -> Key:
    return Key("float", low=0.0, doc=doc)


def _fraction(doc: str) -> Key:
    return Key("float", low=0.0, high=1.0, doc=doc)


#: Faults the simulated station can inject for a serial ([simulation.faults] SERIAL = KIND).
SIMULATED_FAULTS = ("dark", "camera-timeout", "misplaced", "hung-analysis", "hung-facet", "hung-capture",
                    "camera-disconnect", "lights-off", "slow-analysis", "worker-dies")

#: The longest [run] late_grace_s, s: an abandoned analysis keeps a worker (and a core) busy at low priority
#: while the standby measures; ten minutes is thirty cycles of a 20 s line, far more than any analysis that is
#: merely slow takes (1e12 s was accepted: an analysis that never ends was never killed).
LATE_GRACE_MAX_S = 600.0

#: Every section of station.toml and its keys.
SECTIONS: dict[str, dict[str, Key]] = {
    "station": {
        "name": Key("str", doc="shown in every record"),
        "id": Key("str", doc="the station's identity, carried by every calibration record it makes (default: name)"),
        "data_dir": Key("str", doc="where everything the station writes goes"),
        "backend": Key("str", choices=("simulated", "hardware"), doc="the twin or real devices"),
        "facet": Key("str", doc="facet design file, relative to station.toml"),
    },
    "camera": {
        "width_px": Key("int", low=1), "height_px": Key("int", low=1),
        "focal_length_px": Key("float|floats", low=0.0, low_open=True, length=(2,), doc="f or [fx, fy], px"),
        "principal_point_px": Key("floats", length=(2,), doc="[cx, cy], px"),
        "distortion": Key("floats", length=(4, 5), doc="OpenCV's k1, k2, p1, p2[, k3]: the 5-term model the "
                          "analysis and the twin use (4 terms: k3 = 0); OpenCV's 8-term rational model is not "
                          "supported, calibrate the camera with the 5-term model ('calibrate camera')"),
        "intrinsics": Key("str", doc="\"station.toml\" or \"record\" (checked with its own message)"),
    },
    "screen": {
        "width_px": Key("int", low=1), "height_px": Key("int", low=1),
        "pitch_m": _pos("pixel pitch of a square-pixel display, m"),
        "pitch_x_m": _pos("pixel pitch along x (display columns), m"),
        "pitch_y_m": _pos("pixel pitch along y (display rows), m"),
    },
    "layout": {
        "separation_m": _nonneg("camera to screen centre, m"),
        "separation_axis": Key("str", choices=("x", "y")),
        "screen_offset_m": Key("floats", length=(2,)),
    },
    "fringes": {
        "periods_x": Key("ints", low=1), "periods_y": Key("ints", low=1),
        "phase_steps": Key("int", low=3),
    },
    "analysis": {
        "mask_threshold_dn": _nonneg("DN"), "min_modulation_dn": _nonneg("DN"),
        "consistency_sigmas": _pos("noise sigmas"), "guard_sigmas": _nonneg("position-noise units"),
        "subsample_step": Key("int", low=1), "max_iterations": Key("int", low=1),
        "max_range_shift_m": _pos("m"), "corner_tolerance_px": _pos("px"), "max_hole_px": Key("int", low=0),
        "max_saturated_fraction": _fraction("fraction of the facet's pixels"), "max_corner_rms_px": _pos("px"),
        "robust_fit": Key("bool"), "edge_window_px": Key("int", low=1), "threads": Key("int", low=1),
    },
    "limits": {
        "focal_length_tolerance": Key("float", low=0.0, high=1.0, low_open=True, doc="relative, |f/f_design - 1|"),
        "curvature_tolerance_per_m": _pos("1/m"),
        "max_twist_mrad_per_m": _pos("mrad/m"),
        "max_slope_rms_mrad": Key("section:slope_limits", doc="per model, mrad"),
        "min_intercept": _fraction("intercept factor for the [optics] aperture"),
        "max_spot_radius_mrad": _pos("radius holding 90 % of the power, seen from the facet, mrad"),
        "max_centroid_offset_mrad": _nonneg("beam centroid from the aim point, mrad"),
        "min_power_ratio": _nonneg("intercepted power / the design facet's"),
        "max_canting_mrad": _nonneg("a heliostat's facets: largest canting error, mrad (docs/heliostats.md)"),
        "slope_rms_value": Key("str", choices=("measured", "corrected"),
                               doc="the slope RMS the limits apply to (docs/uncertainty.md)"),
        "decision_rule": Key("str", choices=("simple", "guarded"), doc="guarded: ISO 14253-1, with U"),
    },
    "uncertainty": {
        "distance_mm": _nonneg("mm, standard uncertainty"), "camera_focal_px": _nonneg("px"),
        "camera_principal_px": _nonneg("px"),
        "camera_distortion": Key("floats", low=0.0, length=(5,), doc="k1, k2, p1, p2, k3"),
        "screen_rotation_mrad": Key("floats", low=0.0, length=(3,), doc="mrad about the screen's x, y, z"),
        "screen_translation_mm": Key("floats", low=0.0, length=(3,), doc="mm along the screen's x, y, z"),
        "screen_pitch_relative": _nonneg("relative"), "response_phase_rad": _nonneg("rad"),
        "fixture_rotation_mrad": Key("floats", low=0.0, length=(3,), doc="mrad"),
        "fixture_translation_mm": Key("floats", low=0.0, length=(3,), doc="mm"),
        "corner_px": _nonneg("px"),
    },
    "slope_limits": {
        "design": _pos("mrad"), "parabola": _pos("mrad"), "higher_order": _pos("mrad"),
    },
    "quality": {
        "min_valid_fraction": _fraction(""), "min_median_modulation_dn": _nonneg("DN"),
        "max_unwrap_disagreement_fraction": _fraction(""), "min_outline_agreement": _fraction(""),
        "max_corner_reprojection_px": _pos("px"),
        "max_display_harmonic_ratio": _nonneg("second harmonic / fringe amplitude"),
        "warn_display_harmonic_ratio": _nonneg("second harmonic / fringe amplitude"),
        "max_slope_curl_ratio": _nonneg("turning / stretching part of the slope gradient"),
        "min_slope_curl_per_m": _nonneg("1/m"),
        "slope_curl_sigmas": _pos("standard deviations of the turning part's noise"),
        "slope_curl_noise_tolerance": _nonneg("relative, of the predicted noise's mean square"),
        "max_placement_mm": _pos("mm, beyond the placement's U"), "max_placement_mrad": _pos("mrad, beyond its U"),
        "max_design_slope_factor": _pos("times the layout's largest slope error (design RMS)"),
    },
    "calibration": {
        "radiometric": Key("str"), "stale": Key("str", choices=("warn", "refuse")),
        "max_age_h": _pos("h"), "max_dark_shift_dn": _nonneg("DN"), "warmup": Key("bool"),
        "warmup_min": _nonneg("min"), "routine": Key("table", doc="checked by calibrate.settings"),
        "geometry": Key("str", choices=("records", "station.toml"),
                        doc="measure with the newest screen and pose records, or [screen] and [layout] as entered"),
        "screen": Key("table", doc="[calibration.screen]: calibrate screen, checked by calibrate.commission_settings"),
        "pose": Key("table", doc="[calibration.pose]: calibrate pose, checked by calibrate.commission_settings"),
    },
    "optics": {
        "enabled": Key("bool", doc="compute the optical figures (docs/optics.md)"),
        "sun": Key("str", choices=("pillbox", "gaussian", "buie"), doc="sun shape"),
        "sigma_mrad": _pos("Gaussian sun, per direction, mrad"),
        "csr": Key("float", low=0.0, high=1.0, low_open=True, high_open=True, doc="Buie sun's circumsolar ratio"),
        "dni_w_m2": _pos("direct normal irradiance, W/m^2"),
        "reflectivity": Key("float", low=0.0, high=1.0, low_open=True, doc="specular reflectivity"),
        "incidence_angle_deg": Key("float", low=0.0, high=90.0, high_open=True, doc="sun from the facet's axis"),
        "slant_range_m": _pos("facet centre to target plane, m"),
        "aperture": Key("table", doc="{shape = \"circle\", radius_m} or {shape = \"rectangle\", width_m, height_m}, "
                                     "checked by result.optical_figures"),
        "rays_per_pixel": _pos("rays per measured point"),
        "min_rays": Key("int", low=0, doc="at least this many rays per facet"),
        "grid_cells": Key("int", low=2, high=4001, doc="flux map cells per side"),
        "grid_half_width_m": _pos("flux map half-width, m"),
        "design_points": Key("int", low=100, doc="samples of the design surface"),
        "seed": Key("int", low=0, doc="seed of the sun-shape samples"),
    },
    "simulation": {
        "seed": Key("int", low=0, doc="sensor noise seed"),
        "facet": Key("table", doc="[simulation.facet]: the twin's true facet (twin.parameters.TrueFacet, a rule "
                                  "below)"),
        "optics": Key("table", doc="[simulation.optics]: display, camera and noise (twin.parameters.TwinOptics)"),
        "population": Key("table", doc="[simulation.population]: how the line's facets differ "
                                       "(twin.population.FacetPopulation)"),
        "distance_error_m": Key("float", low=-1.0, high=1.0, doc="the simulated range finder's error, m"),
        "faults": Key("section:simulation_faults", doc="SERIAL = fault kind, injected (tests, benchmarks)"),
        "heliostat": Key("table", doc="[simulation.heliostat]: the twin's true heliostat (twin.heliostat, a rule "
                                      "below)"),
        "hang_s": _pos("how long a 'hung-analysis' or 'hung-facet' fault hangs, s"),
        "slow_s": _pos("how long a 'slow-analysis' fault delays the analysis, s"),
        "assembly": Key("table", doc="[simulation.assembly]: the twin's true screen and camera (twin.assembly."
                                     "TrueAssembly, a rule below)"),
        "temperature": Key("table", doc="[simulation.temperature]: the simulated hall's start_c, k_per_100 (its "
                                        "warming per hundred facets) and screen_above_k ([temperature] source = "
                                        "\"simulated\"; devices/thermometer.py)"),
    },
    "simulation_faults": {"*": Key("str", choices=SIMULATED_FAULTS, doc="fault injected for this serial")},
    "run": {
        "deadline_s": _pos("trigger to answer, s"), "dump_every_n": Key("int", low=0),
        "dump_failed": Key("bool"), "heartbeat_s": _pos("s"), "poll_s": _pos("s"),
        "camera_timeout_s": _pos("s"), "min_free_gb": _nonneg("GB"), "dump_keep_days": _pos("days"),
        "dump_max_gb": _pos("GB"), "late_grace_s": Key("float", low=0.0, high=LATE_GRACE_MAX_S,
                                                    doc="s after the deadline a late analysis may take"),
        "warmup": Key("bool", doc="analyse one capture before reporting ready"),
        "standby_worker": Key("bool", doc="keep a warm second analysis worker that takes over after a timeout or "
                                          "a crash"),
        "alarm_faults_in_row": Key("int", low=1, high=1000, doc="the line alarm after this many faults in a row"),
        "reference_every_h": Key("float", low=0.0, high=8760.0,
                                 doc="warn when no reference was measured for this long, h (0: never)"),
        "display_level_tolerance": Key("float", low=0.0, high=0.5,
                                       doc="the display's self-test: alarm when the fringes' mean level departs "
                                           "from the radiometric table's by more (0: no check)"),
        "alarm_yield_window": Key("int", low=5, high=1000,
                                  doc="the line alarm's yield rule: the newest facets of a recipe it judges"),
    },
    "archive": {
        "workbook_period": Key("str", choices=("day", "shift")), "workbook_interval_s": _pos("s"),
        "workbook_cpu_share": Key("float", low=0.0, low_open=True, high=1.0,
                                  doc="largest share of one core the workbook saves take on average"),
        "workbook_max_rows": Key("int", low=1, high=1048575, doc="data rows per workbook part (-part2.xlsx, ...)"),
        "dump_keep_days": _pos("days"), "dump_max_gb": _pos("GB"), "min_free_gb": _nonneg("GB"),
    },
    "devices": {
        "trigger": Key("str", choices=("simulated", "modbus", "usb")), "trigger_options": Key("table"),
        "display_options": Key("table"), "camera": Key("str", choices=("basler", "aravis", "replay")),
        "camera_options": Key("table"), "range_finder_options": Key("table"),
        "handheld_camera": Key("str", choices=("basler", "aravis"), doc="calibrate screen's second camera"),
        "handheld_camera_options": Key("table", doc="its options, as camera_options"),
    },
    "recipes": {"*": Key("section:recipe", doc="[recipes.NAME]")},
    "heliostat": {
        "window_margin": _nonneg("each facet's window: its nominal image widened by this fraction of its size"),
        "window_margin_px": Key("int", low=0, doc="... and this many pixels"),
        "min_area_fraction": _fraction("a facet covering less of its nominal image is hidden"),
        "blank_dilation_px": Key("int", low=0, doc="neighbours blanked this far beyond their regions, px"),
        "min_region_px": Key("int", low=1, doc="smaller responsive regions are specks, not facets"),
        "facet_height_mm": _nonneg("standard uncertainty of a facet's height on the frame, mm"),
    },
    "web": {"*": Key("any", doc="checked by its reader (READERS below)")},
    "opcua": {"*": Key("any", doc="checked by its reader (READERS below)")},
    "drift": {"*": Key("any", doc="checked by its reader (READERS below)")},
    "marks": {"*": Key("any", doc="the fixture's marks; checked by its reader (READERS below)")},
    "temperature": {"*": Key("any", doc="the temperature readings; checked by its reader (READERS below)")},
    "acceptance": {"*": Key("table", doc="[acceptance.RECIPE], checked by report.acceptance (a rule below)")},
    "certificate": {
        "issuer": Key("str", doc="who issues the facet certificates (report certificate): the organisation"),
        "address": Key("str", doc="the issuer's address, one line under its name"),
        "signatory": Key("str", doc="name and role printed under the certificate's signature line"),
    },
    "recipe": {
        "facet": Key("str"), "serial_pattern": Key("str"),
        "alignment_point_m": Key("floats", length=(2,)), "measure_point_m": Key("floats", length=(2,)),
        "limits": Key("section:limits"), "quality": Key("section:quality"), "analysis": Key("section:analysis"),
        "optics": Key("section:optics", doc="over [optics] for this recipe"),
        "reference": Key("str", doc="a reference recipe: its facet's certificate file ([reference] table), or "
                                    "\"twin\" (the simulated station's truth)"),
        "prescriptions": Key("str", doc="a heliostat recipe's folder of SERIAL.toml canting prescriptions "
                                        "(field prescription; docs/field.md)"),
        "method": Key("str", choices=("fringe", "fixed"),
                      doc="the fringes' 18 frames (default) or one frame of a dot grid (docs/method.md)"),
        "fixed": Key("section:fixed", doc="the dot grid of method = \"fixed\""),
    },
    "fixed": {
        "pitch_px": Key("int", low=6, doc="dot spacing on the display, pixels (default: from spacing_px)"),
        "spacing_px": Key("float", low=7, doc="the dots' spacing in the camera's picture of the nominal facet, "
                          "pixels, when pitch_px is not given (default 12)"),
        "diameter": Key("float", low=0.1, high=0.6, doc="dot diameter, share of the pitch (default 0.4)"),
        "white_frame": Key("bool", doc="a dark and a white frame before the dots (3 frames; default false: one)"),
        "min_dots": Key("int", low=9, doc="fewer dots used: too few dots (default 100)"),
        "index_tolerance": Key("float", low=0.1, high=0.5, doc="of a lattice step (default 0.45)"),
    },
}

#: The sections that may appear at the top of station.toml (the others are nested tables).
TOP_LEVEL = ["station", "camera", "screen", "layout", "fringes", "analysis", "limits", "quality", "calibration",
             "optics", "simulation", "run", "archive", "devices", "recipes", "web", "opcua", "acceptance", "drift",
             "uncertainty", "certificate", "heliostat", "marks", "temperature"]


def _check_value(key: Key, value, file: str, label: str, name: str) -> None:
    def bad() -> ConfigError:
        what = f" ({key.doc})" if key.length and isinstance(value, list) and len(value) not in key.length else ""
        return ConfigError(f"{file} [{label}] {name} must be {key.allowed()}, got {value!r}{what}")

    kind = key.kind
    if kind == "any":
        return
    if kind.startswith("section:"):
        if not isinstance(value, dict):
            raise bad()
        check_section(kind.split(":", 1)[1], value, file, f"{label}.{name}")
        return
    if kind == "table":
        if not isinstance(value, dict):
            raise bad()
        return
    if kind == "bool":
        if not isinstance(value, bool):
            raise bad()
        return
    if kind == "str":
        if not isinstance(value, str):
            raise bad()
    elif kind == "int":
        if not _is_int(value) or not _in_range(key, value):
            raise bad()
    elif kind == "float" or (kind == "float|floats" and not isinstance(value, list)):
        if not _is_number(value) or not _in_range(key, value):
            raise bad()
    elif kind in ("floats", "ints", "float|floats"):
        ok = _is_int if kind == "ints" else _is_number
        if (not isinstance(value, list) or not value or (key.length and len(value) not in key.length)
                or not all(ok(v) and _in_range(key, v) for v in value)):
            raise bad()
    if key.choices and value not in key.choices:
        raise bad()


def check_section(section: str, table: dict, file: str, label: str | None = None) -> None:
    """Check one table against ``SECTIONS[section]``.

    Parameters
    ----------
    section : str
        The schema's section name.
    table : dict
        The table as read from TOML.
    file : str
        The station file, for messages.
    label : str, optional
        The table's name in the file (``"recipes.gore.limits"``); default *section*.

    Raises
    ------
    ConfigError
        Naming the file, the table, the key, the value and what is allowed.
    """
    label = label or section
    keys = SECTIONS[section]
    if not isinstance(table, dict):
        raise ConfigError(f"{file} [{label}] must be a table, got {table!r}")
    if "*" in keys:
        for name, value in table.items():
            _check_value(keys["*"], value, file, label, name)
        return
    unknown = sorted(set(table) - set(keys))
    if unknown:
        raise ConfigError(f"{file} [{label}] has unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(keys))}")
    for name, value in table.items():
        _check_value(keys[name], value, file, label, name)


def _rule_camera(raw: dict, where: str) -> None:
    cam = raw.get("camera", {})
    if "principal_point_px" in cam and "width_px" in cam and "height_px" in cam:
        cx, cy = cam["principal_point_px"]
        if not (0 <= cx <= cam["width_px"] - 1 and 0 <= cy <= cam["height_px"] - 1):
            raise ConfigError(f"{where} [camera] principal_point_px = {cam['principal_point_px']!r}: must lie "
                              f"inside the {cam['width_px']} x {cam['height_px']} image")


def _rule_screen(raw: dict, where: str) -> None:
    scr = raw.get("screen", {})
    square, per_axis = "pitch_m" in scr, [k for k in ("pitch_x_m", "pitch_y_m") if k in scr]
    if square and per_axis:
        raise ConfigError(f"{where} [screen] has pitch_m and {', '.join(per_axis)}: give pitch_m for square pixels "
                          "or pitch_x_m and pitch_y_m, not both")
    if len(per_axis) == 1:
        raise ConfigError(f"{where} [screen] has {per_axis[0]} alone: give both pitch_x_m and pitch_y_m "
                          "(or pitch_m for square pixels)")


def _rule_fringes(raw: dict, where: str) -> None:
    fr = raw.get("fringes", {})
    for name in ("periods_x", "periods_y"):
        p = fr.get(name)
        if p and any(b <= a for a, b in zip(p, p[1:])):
            raise ConfigError(f"{where} [fringes] {name} = {p!r}: the periods must increase (coarse to fine)")
        if p and p[0] != 1:
            raise ConfigError(f"{where} [fringes] {name} = {p!r}: the first (coarse) set must have 1 period, "
                              "so that its phase is unambiguous")


def _rule_run(raw: dict, where: str) -> None:
    run = raw.get("run", {})
    deadline = run.get("deadline_s", 10.0)
    for name in ("camera_timeout_s", "poll_s"):
        if name in run and run[name] >= deadline:
            raise ConfigError(f"{where} [run] {name} = {run[name]!r}: must be shorter than deadline_s "
                              f"({deadline:g} s)")


#: Sections whose own reader checks them in depth: section -> "module:function", called at load with an
#: object carrying ``path`` and ``raw`` (the reader raises ConfigError naming file, section and key).
READERS = {
    "web": "sofast_station.web.settings:web_settings",
    "opcua": "sofast_station.web.settings:opcua_settings",
    "drift": "sofast_station.station.drift:drift_settings",
    "marks": "sofast_station.calibrate.marks:mark_settings",
    "temperature": "sofast_station.devices.thermometer:temperature_settings",
}


def _rule_readers(raw: dict, where: str) -> None:
    """Run the reader of every section in :data:`READERS` that the file has."""
    config = SimpleNamespace(path=where, raw=raw)
    for section, target in READERS.items():
        if section in raw:
            module, func = target.split(":")
            getattr(importlib.import_module(module), func)(config)


def _rule_simulation(raw: dict, where: str) -> None:
    """[simulation.facet], [simulation.optics] and [simulation.population] through the twin's own records
    (types, ranges, keys)."""
    sim = raw.get("simulation")
    if not sim:
        return
    # lazy: the twin's package, ~770 ms CPU (+536 modules, scipy); config.py loads this at every start
    from .twin.assembly import TrueAssembly
    from .twin.parameters import TrueFacet, TwinOptics
    from .twin.population import FacetPopulation

    for key, cls in (("facet", TrueFacet), ("optics", TwinOptics), ("population", FacetPopulation),
                     ("assembly", TrueAssembly)):
        try:
            cls.from_dict(sim.get(key, {}))
        except ConfigError as exc:
            msg = str(exc).replace(f"{cls.__name__}.", "").replace(f"{cls.__name__}: ", "")
            raise ConfigError(f"{where} [simulation.{key}] {msg}") from None


def _rule_acceptance(raw: dict, where: str) -> None:
    """[acceptance.RECIPE] contracts are checked by their reader (sofast_station/qc/acceptance.py)."""
    if not raw.get("acceptance"):
        return
    for recipe in raw["acceptance"]:
        contract_from_config(SimpleNamespace(path=where, raw=raw), recipe)


#: Rules between keys: ``rule(raw, file)`` raises ConfigError naming the file, the section and the key.
CROSS_RULES: list[Callable[[dict, str], None]] = [_rule_camera, _rule_screen, _rule_fringes, _rule_run, _rule_readers,
                                                  _rule_simulation, _rule_acceptance]


def add_dataclass_keys(section: str, cls) -> None:
    """Declare every field of the dataclass *cls* read from [*section*] that the schema does not list yet,
    typed by its default (a safety net: a field added to e.g. ``Quality`` is accepted, and type-checked,
    before someone writes its range here)."""
    keys = SECTIONS.setdefault(section, {})
    for f in dataclasses.fields(cls):
        if f.name in keys:
            continue
        default = f.default
        kind = ("bool" if isinstance(default, bool) else "int" if isinstance(default, int)
                else "float" if isinstance(default, float) else "str" if isinstance(default, str) else "any")
        keys[f.name] = Key(kind, doc="declared from its dataclass")


def validate(raw: dict, where: str) -> None:
    """Check a whole station file (*raw*, as read from TOML; *where*: its path) against the schema.

    Raises
    ------
    ConfigError
        At the first problem, naming the file, the section, the key, the value and what is allowed.
    """
    unknown = sorted(set(raw) - set(TOP_LEVEL))
    if unknown:
        raise ConfigError(f"{where} has unknown section(s) {', '.join(unknown)}; allowed: {', '.join(TOP_LEVEL)}")
    for section in TOP_LEVEL:
        if section in raw:
            check_section(section, raw[section], where)
    for rule in CROSS_RULES:
        rule(raw, where)
