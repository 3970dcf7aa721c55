"""The uncertainty's sensitivities as a JSON-ready record, so a data dump can carry the station's own.

The sensitivities depend on the station's geometry, the recipe and the input uncertainties
(:func:`~sofast_station.measure.uncertainty.systematic.sensitivity_key`), and cost seconds to compute. The
station computes them once (on its warm-up capture) and keeps them; a dump written with them lets
``reprocess`` and ``batch`` reuse them when the dump is redone with the same inputs, instead of
recomputing them from the dump's capture. Each dump then uses its own record: the result does not
depend on which dumps were processed before it, or on which worker (docs/reanalysis.md).

Floats go through JSON as their shortest round-tripping text, so a record read back gives the same
bits. Pure functions: records in, records out.
"""

from __future__ import annotations

import numpy as np

from .uncertainty.inputs import Input
from .uncertainty.systematic import Sensitivities

#: Version of the record's layout (a reader refuses a layout it does not know and recomputes).
RECORD_VERSION = 1


def to_record(key: str, sens: Sensitivities) -> dict:
    """*sens* (computed for the inputs hashed as *key*) as a JSON-ready dict."""
    return {"version": RECORD_VERSION, "key": str(key),
            "inputs": [[i.name, i.group, float(i.u), i.unit, i.kind] for i in sens.inputs],
            "paths": [list(p) for p in sens.paths],
            "linear": np.asarray(sens.linear, dtype=np.float64).tolist(),
            "curvature": np.asarray(sens.curvature, dtype=np.float64).tolist(),
            "n_points": int(sens.n_points)}


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
