"""Rows added to a facet's uncertainty budget after its analysis, by what the line's checks of itself found in
the same cycle: a small shift of the fixture's marks (:mod:`sofast_station.measure.fixture_marks`) and the
temperature against the commissioning's (:mod:`sofast_station.measure.thermal`).

The analysis's budget (``uncertainty_budget``: its ``figures``, ``rows`` of contributions per figure and
``combined_standard``) is computed once per geometry and recipe; these inputs change from cycle to cycle, so they
are added to it here, by the same rule the budget combines its rows (GUM: root sum of squares of standard
uncertainties, U = k u with k = 2): a row of standard-uncertainty contributions per figure, the combined standard
uncertainty grown in quadrature, and every reached figure's expanded uncertainty ``NAME_U`` grown by k times its
contribution in quadrature.

Pure functions of the figures dict (JSON-ready, as the analysis returns it); no I/O.
"""

from __future__ import annotations

import math

COVERAGE_FACTOR = 2.0


def _locate(figures: dict, path: str):
    """The container and key of the expanded uncertainty of the figure at dotted *path*
    (``placement.mm.0`` -> ``figures["placement_U"]["mm"]``, 0), or (None, None)."""
    head, *rest = path.split(".")
    node = figures.get(f"{head}_U")
    if not rest:
        return (figures, f"{head}_U") if f"{head}_U" in figures else (None, None)
    for part in rest[:-1]:
        node = _child(node, part)
    key = rest[-1]
    if isinstance(node, list):
        key = int(key) if key.isdigit() else None
        if key is None or key >= len(node):
            return None, None
        return node, key
    if isinstance(node, dict) and key in node:
        return node, key
    return None, None


def _child(node, part):
    if isinstance(node, dict):
        return node.get(part)
    if isinstance(node, list) and part.isdigit() and int(part) < len(node):
        return node[int(part)]
    return None


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def group_contributions(figures: dict, group: str) -> dict[str, float]:
    """A budget group's standard-uncertainty contribution to each figure (``{path: u}``, figure units; figures
    it does not reach, or not stated, left out)."""
    budget = figures.get("uncertainty_budget") or {}
    names = budget.get("figures") or []
    for row in budget.get("rows") or []:
        if row.get("group") == group:
            return {name: float(c) for name, c in zip(names, row.get("contributions") or []) if _number(c) and c}
    return {}


def add_budget_row(figures: dict, group: str, inputs: list[str], contributions: dict[str, float],
                   coverage_factor: float = COVERAGE_FACTOR) -> dict[str, float]:
    """Add a systematic row to the figures' budget and grow the U's it reaches (module docstring); changes
    *figures* in place.

    Parameters
    ----------
    figures : dict
        The analysis's figures, with their ``NAME_U`` and ``uncertainty_budget``.
    group : str
        The row's name in the budget.
    inputs : list of str
        What the row stands for (the budget's ``inputs`` column).
    contributions : dict
        Dotted figure path -> its standard-uncertainty contribution (figure units, k = 1).

    Returns
    -------
    dict
        Path -> what was added to its expanded uncertainty (k times the contribution), for the figures that
        have one.
    """
    added: dict[str, float] = {}
    for path, u in contributions.items():
        if not (_number(u) and u > 0):
            continue
        node, key = _locate(figures, path)
        if node is None or not _number(node[key]):
            continue
        node[key] = float(math.hypot(node[key], coverage_factor * u))
        added[path] = coverage_factor * u
    budget = figures.get("uncertainty_budget")
    if isinstance(budget, dict) and isinstance(budget.get("figures"), list) and isinstance(budget.get("rows"), list):
        names = budget["figures"]
        row = [float(f"{contributions[n]:.3g}") if _number(contributions.get(n)) else 0.0 for n in names]
        budget["rows"].append({"group": group, "kind": "systematic", "inputs": list(inputs), "contributions": row})
        combined = budget.get("combined_standard")
        if isinstance(combined, list) and len(combined) == len(names):
            budget["combined_standard"] = [float(f"{math.hypot(c, r):.3g}") if _number(c) else c
                                           for c, r in zip(combined, row)]
    return added
