"""The uncertainty's sensitivities as a JSON-ready record, so a data dump can carry the station's own.

The sensitivities depend on the station's geometry, the recipe and the input uncertainties
(:func:`~sofast_station.measure.uncertainty.systematic.sensitivity_key`), and cost seconds to compute. The
station computes them once (on its warm-up capture) and keeps them; a dump written with them lets
``reprocess`` and ``batch`` reuse them when the dump is redone with the same inputs, instead of
recomputing them from the dump's capture. Each dump then uses its own record: the result does not
depend on which dumps were processed before it, or on which worker (docs/reanalysis.md).

A capture's record also keeps the frame-brightness pool its uncertainty found (the earlier captures' frame-
to-frame brightness, pooled under GUM 4.2.4): the re-analysis of the dump pools the capture with the same
earlier captures, and states the same U as the line did (without it, the capture's own few degrees of
freedom widen its U: 0.0012 m against the line's 0.00097 m for f_x of a simulated facet).

Floats go through JSON as their shortest round-tripping text, so a record read back gives the same
bits. Pure functions: records in, records out.
"""

from __future__ import annotations

import numpy as np

from .uncertainty.inputs import Input
from .uncertainty.systematic import Sensitivities

#: Version of the record's layout (a reader refuses a layout it does not know and recomputes).
RECORD_VERSION = 1


def to_record(key: str, sens: Sensitivities, frame_pool: list | None = None) -> dict:
    """*sens* (computed for the inputs hashed as *key*) as a JSON-ready dict; with *frame_pool*, the
    frame-brightness pool one capture's uncertainty found (``[[sum of squares DN^2, dof], ...]``, the earlier
    captures of its geometry and recipe, :func:`~.uncertainty.pooled_frame_brightness`) under ``frame_pool``."""
    out = {"version": RECORD_VERSION, "key": str(key),
           "inputs": [[i.name, i.group, float(i.u), i.unit, i.kind] for i in sens.inputs],
           "paths": [list(p) for p in sens.paths],
           "linear": np.asarray(sens.linear, dtype=np.float64).tolist(),
           "curvature": np.asarray(sens.curvature, dtype=np.float64).tolist(),
           "n_points": int(sens.n_points)}
    if frame_pool is not None:
        out["frame_pool"] = [[float(ss), int(dof)] for ss, dof in frame_pool]
    return out


def frame_pool_of(record) -> list[tuple[float, int]] | None:
    """The frame-brightness pool a record of :func:`to_record` keeps (``(sum of squares, dof)`` per earlier
    capture, oldest first), or None when it keeps none (a record written before the pool was kept, or one
    of sensitivities alone)."""
    try:
        pool = record.get("frame_pool") if isinstance(record, dict) else None
        return None if pool is None else [(float(ss), int(dof)) for ss, dof in pool]
    except (TypeError, ValueError):
        return None


def from_record(record) -> tuple[str, Sensitivities] | None:
    """(key, sensitivities) of a record written by :func:`to_record`; None for anything else (an older or
    damaged record: the caller then computes the sensitivities afresh)."""
    try:
        if not isinstance(record, dict) or record.get("version") != RECORD_VERSION:
            return None
        inputs = [Input(str(n), str(g), float(u), str(unit), str(kind)) for n, g, u, unit, kind in record["inputs"]]
        paths = [tuple(p) for p in record["paths"]]
        linear = np.array(record["linear"], dtype=np.float64).reshape(len(inputs), len(paths))
        curvature = np.array(record["curvature"], dtype=np.float64).reshape(len(inputs), len(paths))
        return str(record["key"]), Sensitivities(inputs, paths, linear, curvature, int(record["n_points"]), 0.0)
    except (KeyError, TypeError, ValueError):
        return None
