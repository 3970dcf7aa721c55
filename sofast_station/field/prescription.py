"""The canting a heliostat's place in the field asks for (issue 45, item 3).

A heliostat at field position P aiming at the tower's aim point A focuses best when each facet's normal,
where the facet sits, reflects the sun's central ray onto A:

* **on axis** (the usual factory rule): the sun, the heliostat's normal and the aim point in one line, the
  facets on a paraboloid of focal length equal to the slant range |A - P|
  (docs/conventions.md#heliostat-frame: ``canting_focal_length_m``); a facet at (x, y) on the frame is
  turned to that paraboloid's normal;
* **off axis** for a chosen moment: the sun where pvlib puts it then, the heliostat tracking (its normal the
  bisector of the sun and the aim point, seen from its origin), and each facet turned so that the sun's ray
  reflected at the facet's middle meets A (the rule of the DLR paper's "ideal" heliostat for that hour).

Each facet's prescription is its design pose with the canting replaced: the rotation ``R_y(ry) R_x(rx)``
(no turn about z, as the on-axis rule) that takes its z axis to the prescribed normal, in the heliostat frame;
its origin stays where the design puts it on the frame (a millimetre's height from a canting's change is
left to the line's measurement, which finds it). :func:`prescribed_ensemble` gives the heliostat's design
with those cantings (an :class:`~sofast_station.ensemble.EnsembleDesign`, written by the command as a
heliostat file): the line measures a heliostat against it as against any design, so its canting errors are
against its own place in the field.

Pure numpy; the sun comes in as a vector (:mod:`.sun` gives it from pvlib).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..ensemble import EnsembleDesign, EnsembleFacet, angles_mrad
from ..errors import GeometryError
from .geometry import azimuth_elevation, heliostat_rotation


def _canting_rotation(n: np.ndarray) -> np.ndarray:
    """``R_y(ry) R_x(rx)`` taking z to the unit vector *n* (heliostat frame): rx = -asin(n_y), ry =
    atan2(n_x, n_z) (the on-axis rule's parametrisation)."""
    n = np.asarray(n, dtype=np.float64) / np.linalg.norm(n)
    rx, ry = -math.asin(max(-1.0, min(1.0, n[1]))), math.atan2(n[0], n[2])
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    return np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]]) @ np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx],
                                                                                [0.0, sx, cx]])


def facet_normals(ensemble: EnsembleDesign, position_m, aim_m, sun=None, pivot_offset_m: float = 0.0) -> dict:
    """Each facet's prescribed normal in the heliostat frame {label: (3,)}.

    Parameters
    ----------
    ensemble : EnsembleDesign
    position_m, aim_m : (3,) sequences
        The heliostat's pivot and the aim point, field frame, metres.
    sun : (3,) unit vector or None
        Towards the sun (field frame) for the off-axis prescription; None: on axis at the slant range.
    pivot_offset_m : float
    """
    p = np.asarray(position_m, dtype=np.float64)
    a = np.asarray(aim_m, dtype=np.float64)
    slant = float(np.linalg.norm(a - p))
    if slant < 1.0:
        raise GeometryError(f"the aim point is {slant:.2f} m from the heliostat: no canting focuses there")
    out = {}
    if sun is None:
        # on axis: the facets' normals of the paraboloid of focal length = slant range
        for f in ensemble.facets:
            x, y = f.position_m[0], f.position_m[1]
            n = np.array([-x / (2.0 * slant), -y / (2.0 * slant), 1.0])
            out[f.label] = n / np.linalg.norm(n)
        return out
    s = np.asarray(sun, dtype=np.float64)
    s = s / np.linalg.norm(s)
    t = (a - p) / slant
    normal = s + t
    if np.linalg.norm(normal) < 1e-9:
        raise GeometryError("the sun stands behind the aim point as seen from the heliostat")
    r_h = heliostat_rotation(*azimuth_elevation(normal))
    origin = p + pivot_offset_m * r_h[:, 2]
    for f in ensemble.facets:
        middle = origin + r_h @ f.point_m(f.design.centroid_m)
        to_aim = (a - middle) / np.linalg.norm(a - middle)
        n = s + to_aim
        out[f.label] = r_h.T @ (n / np.linalg.norm(n))
    return out


def prescribed_ensemble(ensemble: EnsembleDesign, normals: dict, name: str | None = None) -> EnsembleDesign:
    """The design with each facet's canting replaced by the one that turns its z axis to *normals*[label]."""
    facets = []
    for f in ensemble.facets:
        if f.label not in normals:
            facets.append(f)
            continue
        facets.append(EnsembleFacet(f.label, f.design, f.position_m.copy(), _canting_rotation(normals[f.label])))
    return dataclasses.replace(ensemble, facets=tuple(facets), name=name or ensemble.name,
                               canting_focal_length_m=None)


def prescription_mrad(ensemble: EnsembleDesign, normals: dict) -> dict:
    """Each facet's prescribed canting (rx, ry) mrad {label: {"x", "y"}}, and its change from the design's
    canting (``change``): what the assembler turns it by from the factory's rule."""
    out = {}
    for f in ensemble.facets:
        r = _canting_rotation(normals[f.label])
        rx, ry, _ = angles_mrad(r)
        change = angles_mrad(f.rotation.T @ r)
        out[f.label] = {"x": rx, "y": ry, "change": {"x": change[0], "y": change[1]}}
    return out
