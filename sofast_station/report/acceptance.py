"""Contract acceptance of a recipe's facets over a period (``sofast-station report acceptance``).

The contract is in station.toml, one table per recipe (``default`` is the station's own facet)::

    [acceptance.default]
    population = 14500          # N_pop: facets in the contract
    confidence = 0.95           # two-sided, for the sample size and the confidence intervals
    relative_error = 0.05       # e*: permitted relative error of the mean

    [acceptance.default.figures."slope_rms_mrad.design.magnitude"]
    name = "slope deviation SD_2D,RMS"
    contract = 1.3              # contract value, in the figure's unit
    tolerance = 0.2             # the mean may exceed it by this much ("at_most") or deviate by it ("two_sided")
    expected_std = 0.3          # sigma_e for the sample size (expected_mean defaults to the contract value)
    sense = "at_most"

The contract's reader and the statistics (guideline sample sizes, t intervals, normal and Weibull fits) are
:mod:`sofast_station.qc.acceptance`; this module evaluates a period's records and draws and writes the result.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy.stats import norm, weibull_min

from ..errors import ReportError
from ..qc import acceptance as acc
from ..qc.acceptance import Contract
from ..result.record import figure_value
from ..result.specs import figure_name
from ._common import savefig_atomic


def evaluate(contract: Contract, records: list[dict]) -> list[dict]:
    """Per contract figure: the guideline sample size, what is missing, the observed mean with its
    confidence interval, the verdict, and normal and Weibull fits of the distribution."""
    measured = [r for r in records if r.get("verdict") in ("pass", "fail")]
    out = []
    for f in contract.figures:
        values = np.array([v for v in (figure_value(r, f.key) for r in measured) if v is not None], float)
        rel = f.relative_error or contract.relative_error
        n_req = acc.sample_size(f.expected_mean, f.expected_std, rel, contract.confidence, contract.population)
        ci = acc.mean_interval(values, contract.confidence, contract.population)
        verdict, why = acc.judge_mean(ci, f.contract, f.tolerance, f.sense)
        if values.size < n_req and verdict != "undecided":
            verdict, why = "undecided", f"{values.size} of the {n_req} facets the guideline asks for; " + why
        normal = acc.fit_normal(values) if values.size >= 2 else None
        weibull = acc.fit_weibull(values) if values.size >= 3 else None
        out.append({"figure": f, "values": values, "required": n_req, "measured": int(values.size),
                    "missing": max(0, n_req - int(values.size)), "interval": ci, "verdict": verdict, "why": why,
                    "normal": normal, "weibull": weibull, "relative_error": rel})
    return out


def text(contract: Contract, results: list[dict], period: str) -> str:
    lines = [f"Contract acceptance, recipe {contract.recipe}, {period}: population N_pop = {contract.population}, "
             f"confidence {100 * contract.confidence:g} %"]
    for r in results:
        f, ci = r["figure"], r["interval"]
        unit = figure_name(f.key)[1]
        u = f" {unit}" if unit else ""
        lines.append(f"  {f.name}: contract {f.contract:g}{u} ({'at most +' if f.sense == 'at_most' else '+-'}"
                     f"{f.tolerance:g}{u})")
        lines.append(f"    sample size (guideline Eq. 7, mu_e {f.expected_mean:g}, sigma_e {f.expected_std:g}, "
                     f"e* {100 * r['relative_error']:g} %): {r['required']}; measured {r['measured']}"
                     + (f"; MISSING {r['missing']}" if r["missing"] else ""))
        if ci["low"] is not None:
            lines.append(f"    mean {ci['mean']:.5g}{u}, {100 * contract.confidence:g} % interval "
                         f"[{ci['low']:.5g}, {ci['high']:.5g}]{u}, sample standard deviation {ci['std']:.4g}{u}")
        lines.append(f"    {r['verdict'].upper()}: {r['why']}")
    overall = ("PASS" if all(r["verdict"] == "pass" for r in results) else
               "FAIL" if any(r["verdict"] == "fail" for r in results) else "UNDECIDED")
    lines.append(f"  overall: {overall}")
    return "\n".join(lines)


def draw(contract: Contract, results: list[dict], path: Path, title: str, dpi: int = 100) -> Path:
    """A histogram per contract figure with the fitted normal and Weibull densities, the contract value,
    its tolerance and the mean's confidence interval."""
    if not results:
        raise ReportError("no contract figure to draw")
    fig = Figure(figsize=(7.0 * len(results), 5.2), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(results)))
    for ax, r in zip(axes, results):
        f, v, ci = r["figure"], r["values"], r["interval"]
        if v.size:
            ax.hist(v, bins=max(5, min(40, int(np.sqrt(v.size)) + 1)), density=True, color="0.8", edgecolor="0.5",
                    label=f"{v.size} facets")
            lo, hi = float(v.min()), float(v.max())
            pad = 0.2 * (hi - lo or abs(hi) * 0.05 or 1.0)
            xs = np.linspace(lo - pad, hi + pad, 300)
            if r["normal"]:
                ax.plot(xs, norm.pdf(xs, r["normal"]["mu"], max(r["normal"]["sigma"], 1e-300)), color="tab:blue",
                        label=f"normal mu {r['normal']['mu']:.4g}, sigma {r['normal']['sigma']:.3g}")
            if r["weibull"]:
                w = r["weibull"]
                ax.plot(xs, weibull_min.pdf(xs, w["shape"], scale=w["scale"]), color="tab:orange",
                        label=f"Weibull k {w['shape']:.3g}, lambda {w['scale']:.4g}")
        u = f" {figure_name(f.key)[1]}".rstrip()
        ax.axvline(f.contract, color="tab:green", lw=1.5, label=f"contract {f.contract:g}{u}")
        if f.sense == "two_sided":
            ax.axvline(f.contract - f.tolerance, color="tab:red", lw=1.0, ls="--")
        ax.axvline(f.contract + f.tolerance, color="tab:red", lw=1.0, ls="--",
                   label=f"contract {'+' if f.sense == 'at_most' else '±'} tolerance {f.tolerance:g}{u}")
        if ci["low"] is not None:
            ax.axvspan(ci["low"], ci["high"], color="tab:purple", alpha=0.2,
                       label=f"mean {ci['mean']:.4g}{u}, its {100 * contract.confidence:g} % interval")
        ax.set_title(f"{f.name}: {r['verdict'].upper()}\n{r['measured']} measured, guideline sample {r['required']}"
                     + (f", {r['missing']} missing" if r["missing"] else ""), fontsize=10)
        label, unit = figure_name(f.key)
        ax.set_xlabel(f"{label} ({unit})" if unit else label)
        ax.set_ylabel(f"probability density (1/{unit})" if unit else "probability density")
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=11)
    return savefig_atomic(fig, Path(path), dpi)
