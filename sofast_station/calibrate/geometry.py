"""Station geometry: the camera-to-screen pose and the screen's size and pitch as records with their
provenance, checked by measuring a reference facet of known shape.

The geometry the analysis uses comes from station.toml (``[camera]``, ``[screen]``, ``[layout]``: the
designed assembly). ``sofast-station calibrate geometry`` measures a reference facet whose focal lengths
and placement in the fixture are known, reports how far the measured figures are from them, and writes
a geometry record (``data_dir/calibration/geometry/``) holding the screen (size in pixels, pitch), the
screen-to-camera pose, where each came from, and the reference check. A geometry error (a wrong
separation, pitch or pose) shows as focal lengths or a placement that disagree with the reference.

The reference facet is described by its certificate, a TOML file::

    [reference]
    name = "reference dish R-01"
    focal_length_x_m = 5.42          # certified (measured on a coordinate measuring machine, say): the
    focal_length_y_m = 5.35          # best-fit parabola's, as docs/conventions.md defines the figure
    focal_length_u_relative = 0.0    # the certificate's standard uncertainty (k = 1), relative
    placement_mm = [0.0, 0.0, 0.0]   # its known placement in the fixture (as the facet's placement figure)
    placement_mrad = [0.0, 0.0, 0.0]
    placement_u_mm = 0.0             # standard uncertainty of that placement (k = 1)
    placement_u_mrad = 0.0
    focal_length_tolerance = 0.005   # relative; defaults shown
    placement_tolerance_mm = 2.0
    placement_tolerance_mrad = 2.0
    screen_scale_tolerance = 0.005   # relative: the screen's pitch flagged beyond this (and its U)

The comparison is with the certified figures, never with the facet's design: a facet's best-fit
parabola differs from its nominal focal lengths (on the twin's default facet, whose paraboloid has f_y
5.35 m, the random slope error and twist make it 5.3444 m: a perfect station compared with the nominal
value reported f_y -0.105 %). On the simulated station the certificate is the twin's truth
(``station.reference_certificate()``: the conventions' figures of its exact surface over the facet).

The check also estimates the screen's scale (:func:`screen_scale`): the screen pitch that would make the
measured focal lengths the certified ones, through their sensitivity to the pitch (the uncertainty
budget's, signed). A station laid out about the facet's centre of curvature sees the pitch only through
how far the reference's focal lengths are from the layout's design focal length: the farther, the finer
(on the 400 x 300 dish station, +-0.8 % (k = 2) with the design's 5.42 / 5.35 m facet; +-0.12 % with a
reference of 5.9 / 5.8 m); the record says how finely, and when that is too coarse to check the pitch.
``screen_scale_tolerance = 0.005`` in the reference file sets what is flagged.

The record also states what the check determines, with standard uncertainties (``determined``): the
fixture's pose (the reference's measured placement minus its certified one; the inspection's U of the
placement and the certificate's) and how well the measured distance is confirmed (the focal lengths'
agreement through their sensitivity to the distance). The budget uses them
(:func:`~sofast_station.calibrate.geometry_record.budget_std`); the record itself is written and read by
:mod:`sofast_station.calibrate.geometry_record`.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..files import read_toml
from ..gum import with_u

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GeometryReference:
    """A reference facet's known figures.

    Attributes
    ----------
    name : str
    focal_length_x_m, focal_length_y_m : float
        Known focal lengths, metres (``math.inf`` for a flat direction).
    placement_mm, placement_mrad : tuple of 3 floats
        Known placement in the fixture (the facet's ``placement`` figure: translation of its middle, mm;
        rotation R_z R_y R_x about it, mrad).
    focal_length_tolerance : float
        Relative tolerance on the focal lengths (on the curvature 1/f for long focal lengths).
    placement_tolerance_mm, placement_tolerance_mrad : float
    source : str
        Where the known values come from.
    """

    name: str
    focal_length_x_m: float
    focal_length_y_m: float
    placement_mm: tuple = (0.0, 0.0, 0.0)
    placement_mrad: tuple = (0.0, 0.0, 0.0)
    focal_length_tolerance: float = 0.005
    placement_tolerance_mm: float = 2.0
    placement_tolerance_mrad: float = 2.0
    source: str = ""
    focal_length_u_relative: float = 0.0
    placement_u_mm: float = 0.0
    placement_u_mrad: float = 0.0
    screen_scale_tolerance: float = 0.005

    def __post_init__(self):
        for key in ("focal_length_x_m", "focal_length_y_m"):
            f = float(getattr(self, key))
            if f == 0 or math.isnan(f):
                raise ConfigError(f"reference {key} must be a non-zero length in metres (inf for flat)")
            object.__setattr__(self, key, f)
        for key in ("placement_mm", "placement_mrad"):
            v = tuple(float(x) for x in getattr(self, key))
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                raise ConfigError(f"reference {key} must be 3 finite numbers")
            object.__setattr__(self, key, v)
        for key in ("focal_length_tolerance", "placement_tolerance_mm", "placement_tolerance_mrad",
                    "screen_scale_tolerance"):
            if not float(getattr(self, key)) > 0:
                raise ConfigError(f"reference {key} must be positive")
        for key in ("focal_length_u_relative", "placement_u_mm", "placement_u_mrad"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ConfigError(f"reference {key} must be a non-negative number (a standard uncertainty), got {v!r}")
            object.__setattr__(self, key, float(v))


_REF_KEYS = {"name", "focal_length_x_m", "focal_length_y_m", "placement_mm", "placement_mrad",
             "focal_length_tolerance", "placement_tolerance_mm", "placement_tolerance_mrad",
             "focal_length_u_relative", "placement_u_mm", "placement_u_mrad", "screen_scale_tolerance"}


def load_reference(path: str | Path) -> GeometryReference:
    """Read a reference facet file (module docstring); ConfigError naming the file and key otherwise."""
    path = Path(path)
    table = read_toml(path, "reference facet file").get("reference")
    if not isinstance(table, dict):
        raise ConfigError(f"reference facet file {path} has no [reference] table")
    unknown = sorted(set(table) - _REF_KEYS)
    if unknown:
        raise ConfigError(f"{path} [reference] has unknown key(s) {', '.join(unknown)}")
    for key in ("focal_length_x_m", "focal_length_y_m"):
        if key not in table:
            raise ConfigError(f"{path} [reference] is missing {key}")
    try:
        return GeometryReference(name=str(table.get("name", path.stem)), source=str(path),
                                 **{k: v for k, v in table.items() if k != "name"})
    except (ConfigError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path} [reference]: {exc}") from None


def reference_from_certificate(certificate: dict) -> GeometryReference:
    """A reference from a certificate dict (the keys of the ``[reference]`` table, plus ``name`` and
    ``source``), e.g. the simulated station's ``reference_certificate()``; None focal lengths are flat."""
    d = dict(certificate)
    for key in ("focal_length_x_m", "focal_length_y_m"):
        if d.get(key) is None:
            d[key] = math.inf
    unknown = sorted(set(d) - _REF_KEYS - {"source"})
    if unknown:
        raise ConfigError(f"certificate has unknown key(s) {', '.join(unknown)}")
    return GeometryReference(**d)


def station_reference(station, path: str | Path | None = None) -> GeometryReference:
    """The reference facet's certificate: the file *path* ([reference] table), else the station's own
    (``station.reference_certificate()``: the simulated station's twin truth); a hardware station needs
    the file."""
    if path:
        return load_reference(path)
    certify = getattr(station, "reference_certificate", None)
    if certify is None:
        raise ConfigError(f"{station.config.path}: a hardware station needs the reference facet's certificate "
                          "(--reference FILE with a [reference] table: its certified focal lengths and placement)")
    return reference_from_certificate(certify())


def reference_from_simulation(config) -> GeometryReference:
    """The twin's true facet as ``[simulation.facet]`` states its *design* (its paraboloid's focal lengths).

    Not a certificate: the facet's best-fit parabola differs from these by its slope error and twist (about
    0.1 % on the default facet); :func:`station_reference` gives the certified (true) figures. Reads the
    configuration's plain data only (the calibration code does not use the twin).
    """
    if config.backend != "simulated":
        raise ConfigError(f"{config.path}: a hardware station needs a reference facet file (--reference)")
    facet = config.simulation.get("facet", {})

    def f(key):
        value = facet.get(key)
        if value is None:
            return config.design.focal_length_m
        if isinstance(value, str) and value.strip().lower() in ("inf", "+inf", "infinity"):
            return math.inf
        return float(value)

    return GeometryReference(name=f"simulated true facet ({config.design.name})",
                             focal_length_x_m=f("focal_length_x_m"), focal_length_y_m=f("focal_length_y_m"),
                             placement_mm=tuple(facet.get("placement_mm", (0.0, 0.0, 0.0))),
                             placement_mrad=tuple(facet.get("placement_mrad", (0.0, 0.0, 0.0))),
                             source=f"{config.path} [simulation.facet]")


def compare_to_reference(figures: dict, reference: GeometryReference) -> dict:
    """How far measured figures are from the reference's known values.

    Parameters
    ----------
    figures : dict
        An inspection's result (``focal_length_x_m``, ``curvature_x_per_m``, ..., ``placement``).
    reference : GeometryReference

    Returns
    -------
    dict
        Per focal length: measured, known, relative error (and the curvature difference, 1/m); the
        placement difference (mm, mrad); ``within_tolerance`` and the reasons when not.
    """
    out = {"reference": reference.name, "reference_source": reference.source, "focal_lengths": {}, "reasons": []}
    for axis in ("x", "y"):
        known = getattr(reference, f"focal_length_{axis}_m")
        kappa_known = 0.0 if math.isinf(known) else 1.0 / known
        kappa = figures.get(f"curvature_{axis}_per_m")
        measured = figures.get(f"focal_length_{axis}_m")
        if kappa is None:
            kappa = 0.0 if measured is None else 1.0 / measured
        # f_measured / f_known - 1 = kappa_known / kappa - 1 (undefined for a flat direction)
        rel = (kappa_known / kappa - 1.0) if kappa != 0 and kappa_known != 0 else None
        entry = {"measured_m": measured, "known_m": None if math.isinf(known) else known, "relative_error": rel,
                 "curvature_error_per_m": float(kappa - kappa_known)}
        out["focal_lengths"][axis] = entry
        # long focal lengths: the tolerance applies to the curvature (docs/conventions.md#focal-power)
        limit = reference.focal_length_tolerance * max(abs(kappa_known), 1 / 20.0)
        if abs(kappa - kappa_known) > limit:
            out["reasons"].append(f"f_{axis} {measured if measured is not None else 'inf'} m differs from the known "
                                  f"{known:g} m by more than {100 * reference.focal_length_tolerance:g} %")
    placement = figures.get("placement") or {}
    d_mm = np.subtract(placement.get("mm", [np.nan] * 3), reference.placement_mm)
    d_mrad = np.subtract(placement.get("mrad", [np.nan] * 3), reference.placement_mrad)
    out["placement_error_mm"] = [float(v) for v in d_mm]
    out["placement_error_mrad"] = [float(v) for v in d_mrad]
    if not np.all(np.abs(d_mm) <= reference.placement_tolerance_mm):
        out["reasons"].append(f"placement differs by {np.round(d_mm, 2).tolist()} mm (tolerance "
                              f"{reference.placement_tolerance_mm:g} mm)")
    if not np.all(np.abs(d_mrad) <= reference.placement_tolerance_mrad):
        out["reasons"].append(f"rotation differs by {np.round(d_mrad, 2).tolist()} mrad (tolerance "
                              f"{reference.placement_tolerance_mrad:g} mrad)")
    out["within_tolerance"] = not out["reasons"]
    out["tolerances"] = {"focal_length": reference.focal_length_tolerance, "mm": reference.placement_tolerance_mm,
                         "mrad": reference.placement_tolerance_mrad}
    return out


def check_geometry(rec: dict, reference: GeometryReference, inputs=None, pitch_sensitivity: dict | None = None) -> dict:
    """Compare the inspection *rec* of the reference facet in the fixture with its certificate
    (:func:`compare_to_reference`), say what that determines (:func:`determined`; *inputs*: the station's
    InputUncertainties) and estimate the screen's scale (:func:`screen_scale`; *pitch_sensitivity*: the
    inspection's, :func:`pitch_sensitivities`). ``sofast-station calibrate geometry`` inspects the
    reference and calls this.

    Returns
    -------
    dict
        The comparison, plus the inspection's serial, time, record id of the radiometric calibration
        and verdict.
    """
    check = compare_to_reference(rec, reference)
    check.update({"serial": rec["serial"], "time": rec["time"], "radiometric": rec["calibration"]["radiometric"],
                  "verdict": rec.get("verdict"), "n_points": rec.get("n_points")})
    check["determined"] = determined(rec, reference, inputs)
    scale = screen_scale(rec, reference, pitch_sensitivity)
    check["screen_scale"] = scale
    if scale.get("flagged"):
        check["reasons"].append(
            f"the screen's scale: the certified focal lengths are met with the screen pitch "
            f"{with_u(scale['value'], scale['U'], ' %', 2, scale=100.0, sign=True)} (k = 2) off the configured "
            "[screen] pitch_m "
            f"(tolerance {100 * reference.screen_scale_tolerance:g} %): measure the screen's active width and "
            "correct pitch_m (a wrong pitch scales every slope deviation the station measures)")
        check["within_tolerance"] = False
    return check


def pitch_sensitivities(sensitivities) -> dict | None:
    """``{figure name: d figure / d (relative pitch)}``, signed, from the uncertainty's sensitivities of the
    inspection (:class:`~sofast_station.measure.uncertainty.Sensitivities`: finite differences at +-1
    standard uncertainty of each axis's pitch, summed: a scale of the whole screen); None without them."""
    if sensitivities is None:
        return None
    rows = [i for i, inp in enumerate(sensitivities.inputs) if inp.name in ("screen pitch x", "screen pitch y")]
    if len(rows) != 2:
        return None
    names = [".".join(str(q) for q in p) for p in sensitivities.paths]
    return {name: float(sum(sensitivities.linear[i, j] / sensitivities.inputs[i].u for i in rows))
            for j, name in enumerate(names)}


def screen_scale(figures: dict, reference: GeometryReference, sensitivity: dict | None) -> dict:
    """The screen's scale the reference check finds: s = true pitch / configured pitch - 1, with its U.

    The measured curvatures differ from the certified ones by d_i = -c_i s to first order (c_i: each
    curvature's sensitivity to a stretch of the configured pitch, :func:`pitch_sensitivities`); s is the
    weighted least-squares solution over kappa_x and kappa_y, each weighted by its standard uncertainty
    without the pitch's own row (the budget's) and the certificate's, in quadrature (the two figures'
    errors taken as independent). ``resolves`` says whether U (k = 2) is below the reference's
    ``screen_scale_tolerance`` (a reference too close to the layout's centre of curvature cannot check the
    pitch: any small disagreement of its focal lengths, the certificate's own included, would read as a
    large scale); flagged when it resolves and |s| exceeds both U and that tolerance.
    """
    budget = figures.get("uncertainty_budget")
    if not sensitivity or not budget:
        return {"value": None, "U": None, "k": 2, "flagged": False,
                "note": "not checked: the inspection has no uncertainty budget or no sensitivity to the screen pitch"}
    num = den = 0.0
    for axis in ("x", "y"):
        name = f"curvature_{axis}_per_m"
        known = getattr(reference, f"focal_length_{axis}_m")
        kappa_known = 0.0 if math.isinf(known) else 1.0 / known
        c = sensitivity.get(name)
        u = _u_without(budget, "screen pitch", name)
        if c is None or u is None or figures.get(name) is None:
            continue
        u = math.hypot(u, reference.focal_length_u_relative * abs(kappa_known))
        if u <= 0:
            continue
        d = float(figures[name]) - kappa_known
        num += -c * d / u ** 2
        den += c * c / u ** 2
    if den <= 0:
        return {"value": None, "U": None, "k": 2, "flagged": False,
                "note": "not checked: the focal lengths do not depend on the screen pitch here"}
    value, big_u = num / den, 2.0 / math.sqrt(den)
    tol = reference.screen_scale_tolerance
    out = {"value": value, "U": big_u, "k": 2, "tolerance": tol, "resolves": big_u < tol,
           "flagged": big_u < tol and abs(value) > max(big_u, tol)}
    if not out["resolves"]:
        out["note"] = (f"this reference resolves the screen's scale to +-{100 * big_u:.2f} % (k = 2) only, coarser "
                       f"than the {100 * tol:g} % to check: its focal lengths are too close to the layout's design "
                       "focal length (the screen near the centre of curvature); a reference whose focal lengths "
                       "differ from it by 10 % resolves about 0.1 %")
    return out


def _u_without(budget: dict, group: str, name: str) -> float | None:
    """The figure's combined standard uncertainty without *group*'s contribution (from the budget)."""
    if not budget or name not in budget["figures"]:
        return None
    j = budget["figures"].index(name)
    if budget["combined_standard"][j] is None:
        return None
    return math.sqrt(sum((r["contributions"][j] or 0.0) ** 2 for r in budget["rows"] if r["group"] != group))


def determined(figures: dict, reference: GeometryReference, inputs=None) -> dict:
    """What the reference check determines, with standard uncertainties (k = 1).

    * ``fixture_translation_mm``, ``fixture_rotation_mrad``: the fixture's pose offset (measured minus
      certified placement) and its standard uncertainty, from the inspection's placement U (k = 2, halved)
      and the certificate's placement uncertainty, in quadrature;
    * ``distance_mm``: how well the measured distance is confirmed: the focal lengths' standard uncertainty
      other than the distance's own (and the certificate's) over their sensitivity to the distance (from
      the inspection's budget); the better of x and y. None without a budget.
    """
    out: dict = {}
    placement = figures.get("placement") or {}
    budget = figures.get("uncertainty_budget")

    def other_than(group: str, name: str) -> float | None:
        return _u_without(budget, group, name)

    for key, unit, cert_u in (("mm", "translation_mm", reference.placement_u_mm),
                              ("mrad", "rotation_mrad", reference.placement_u_mrad)):
        value = placement.get(key)
        known = reference.placement_mm if key == "mm" else reference.placement_mrad
        # the placement's uncertainty without the fixture pose's own (which is what is being determined)
        u = [other_than("fixture pose", f"placement.{key}.{i}") for i in range(3)]
        if value is None or any(v is None for v in u):
            continue
        out[f"fixture_{unit}"] = {"offset": [float(a - b) for a, b in zip(value, known)],
                                  "std": [float(math.hypot(ui, cert_u)) for ui in u]}
    u_distance = getattr(inputs, "distance_mm", None) if inputs is not None else None
    if budget and u_distance:
        best = None
        for axis in ("x", "y"):
            name = f"focal_length_{axis}_m"
            f = figures.get(name)
            if name not in budget["figures"] or f is None:
                continue
            j = budget["figures"].index(name)
            row = next((r for r in budget["rows"] if r["group"] == "measured distance"), None)
            c = None if row is None else row["contributions"][j]
            rest = other_than("measured distance", name)
            if not c or rest is None:
                continue
            other = math.hypot(rest, reference.focal_length_u_relative * f)
            std = other / (c / u_distance)             # metres of f over metres of f per mm of distance
            best = std if best is None else min(best, std)
        if best is not None:
            out["distance_mm"] = {"std": float(best)}
    return out


def summary_text(check: dict, path: Path | None = None) -> str:
    """A readable summary of a reference check."""
    lines = [f"Geometry check against {check['reference']} ({check['reference_source']})"
             + (f"; record {path}" if path else "")]
    for axis, e in check["focal_lengths"].items():
        rel = e["relative_error"]
        lines.append(f"  f_{axis}: measured {e['measured_m'] if e['measured_m'] is not None else float('inf'):.4f} m, "
                     f"known {e['known_m'] if e['known_m'] is not None else float('inf'):.4f} m"
                     + (f", {100 * rel:+.3f} %" if rel is not None else "")
                     + f" (curvature {e['curvature_error_per_m']:+.2e} /m)")
    lines.append("  placement - known: " + ", ".join(f"{v:+.2f}" for v in check["placement_error_mm"]) + " mm; "
                 + ", ".join(f"{v:+.2f}" for v in check["placement_error_mrad"]) + " mrad")
    det = check.get("determined") or {}
    for key, unit in (("fixture_translation_mm", "mm"), ("fixture_rotation_mrad", "mrad")):
        if key in det:
            lines.append(f"  fixture {key.split('_')[1]}: " + ", ".join(
                f"{o:+.2f} +- {s:.2f}" for o, s in zip(det[key]["offset"], det[key]["std"])) + f" {unit} (k=1)")
    if "distance_mm" in det:
        lines.append(f"  measured distance confirmed to +- {det['distance_mm']['std']:.2f} mm (k=1)")
    scale = check.get("screen_scale") or {}
    if scale.get("value") is not None:
        lines.append(f"  screen scale: true pitch / configured - 1 = {100 * scale['value']:+.2f} +- "
                     f"{100 * scale['U']:.2f} % (k=2)")
    if scale.get("note"):
        lines.append(f"  screen scale {scale['note']}")
    t = check["tolerances"]
    verdict = "WITHIN" if check["within_tolerance"] else "OUTSIDE"
    lines.append(f"  {verdict} tolerance (f {100 * t['focal_length']:g} %, "
                 f"{t['mm']:g} mm, {t['mrad']:g} mrad)" + "".join(f"\n    - {r}" for r in check["reasons"]))
    return "\n".join(lines)

