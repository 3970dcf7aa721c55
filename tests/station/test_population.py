"""Issue 26, items 1 and 2 (and issue 27, item 5): a small population of stations and captures drawn at
random (station/population.py), the CI version of benchmarks/population.py.

Eight stations (the four facet kinds twice, each with an edge model, noise and optics drawn at random, 400 x
300 cameras), three good captures each and one of each planted fault: no good capture refused or invalid,
every planted fault caught, and the stated uncertainty's coverage of the twin's truth within what a right
95 % claim shows on this many captures (the full population's numbers: docs/uncertainty.md, docs/method.md).
And eight stations whose lens blurs the facet's edge (Gaussian or defocus disk), two captures each: the fit
figures and slope RMS values covered as claimed there too.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from sofast_station.station.population import (EDGE_MODELS, FAULTS, KINDS, MIN_OBSTRUCTED_FRACTION, draw_station,
                                               obstruct, outside, run_population, summarise, swap_sets)

CAPTURES, PER_STATION, SEED = 24, 3, 0


@pytest.fixture(scope="module")
def population():
    cases = run_population(CAPTURES, seed=SEED, per_station=PER_STATION)
    return cases, summarise(cases)


def test_stations_are_drawn_reproducibly_from_their_seed():
    assert draw_station(3, 7) == draw_station(3, 7) != draw_station(3, 8)
    kinds = [draw_station(i, 0)["kind"] for i in range(8)]
    assert kinds == list(KINDS) * 2                                  # every kind in turn
    spec = draw_station(5, 0)
    assert spec["edge"] in EDGE_MODELS and 0.3 <= spec["optics"]["read_noise_dn"] <= 5.0 and abs(spec["k1"]) <= 0.3


def test_no_good_capture_is_refused_or_invalid(population):
    cases, summary = population
    good = summary["good"]
    print(json.dumps({k: good[k] for k in ("n", "false_alarms", "by_check", "outcomes")}, indent=1))
    assert good["n"] == CAPTURES
    assert good["false_alarms"]["k"] == 0, good["alarms"]
    # the population is not one station: every kind, several edge models, noise over a wide range
    assert {c["kind"] for c in cases} == set(KINDS)
    assert len({c["edge"] for c in cases}) >= 4
    noise = [c["read_noise_dn"] for c in cases if c["case"] == "good"]
    assert min(noise) < 1.0 and max(noise) > 3.0


def test_every_planted_fault_is_caught(population):
    _, summary = population
    for fault in FAULTS:
        r = summary["faults"][fault]
        print(fault, r["how"])
        assert r["n"] == CAPTURES // PER_STATION and r["k"] == r["n"], (fault, r["missed"])
    # and named: the swapped sets and the display by their own checks (the others by whichever part of
    # the outline or the region they spoil)
    assert set(summary["faults"]["gamma"]["how"]) == {"display not linearised"}
    assert set(summary["faults"]["swapped"]["how"]) <= {"swapped sets", "not the facet type (shape)"}


#: The family's false-alarm probability: each cell (a figure over all captures, over one facet kind or over
#: one edge model) is judged at this over the number of cells (Bonferroni), both sides.
FAMILY_FALSE_ALARM = 0.01


def claim_cells(summary: dict) -> dict:
    """The coverage cells the claim is judged on: ``{group: rows}`` for all captures, each facet kind and
    each edge model (:func:`~sofast_station.station.population.coverage_rows`)."""
    cells = {"all": summary["coverage"]}
    for k, t in summary["coverage_by_kind"].items():
        cells[f"kind {k}"] = [dict(r, figure=f) for f, r in t.items()]
    for e, rows in summary["coverage_by_edge"].items():
        cells[f"edge {e}"] = rows
    return cells


def judge_claim(summary: dict, label: str) -> list[str]:
    """Every cell outside the band the claim (95 +- 3 % coverage, RMS of error / (U / 2) 0.7-1.3) leaves for
    its count, at the family's false-alarm probability split over the cells."""
    cells = claim_cells(summary)
    n_cells = sum(len(rows) for rows in cells.values())
    alarm = FAMILY_FALSE_ALARM / n_cells
    bad = []
    for group, rows in cells.items():
        for r in rows:
            print(f"{label} {group:<16} {r['figure']:<44} {100 * r['coverage']:5.1f} % of {r['n']:2d}, "
                  f"rms e/u {r['z_rms']:.2f}")
        bad += [f"{group}: {line}" for line in outside(rows, alarm)]
    return bad


def test_stated_uncertainty_covers_the_truth_as_claimed(population):
    """The claim of U (k = 2), from both sides: each figure's coverage of |error| <= U within 95 +- 3 % and
    its RMS of error / (U / 2) within 0.7-1.3 (1 for a right U; a U twice too large gives 0.5, half as large
    2), over the 24 captures, over each facet kind (6) and each edge model (3-9): a cell outside the band
    that claim leaves for its count fails, whichever side.

    The bands, derived for n cases: coverage, the binomial quantiles of n draws at a true coverage of 92 %
    (low end) and 98 % (high end); RMS, for normal errors whose standard deviation is s times U / 2,
    n RMS^2 / s^2 is chi-square with n degrees of freedom, so the band is 0.7 sqrt(chi2_a(n) / n) ..
    1.3 sqrt(chi2_1-a(n) / n). Each at a false-alarm probability of a = 0.01 over the number of cells, both
    sides (Bonferroni: the family of some 370 cells falsely fails with probability at most 0.01). For 24
    captures: coverage at least 62.5 %, RMS 0.32-2.13 (a U stated three times too large or too small leaves
    that: issue 47 found some twice too large on another renderer, which a 500-capture run resolves);
    for 6: at least 17 %, RMS 0.08-3.0. Every figure is judged on both but the axis angle, whose claim is its
    coverage (:data:`~sofast_station.station.population.COVERAGE_ONLY`: a bounded, heavy-tailed error); until
    issue 47 the focal lengths were judged on coverage only too; they are now judged as the station states them,
    by their power 1/f (:data:`~sofast_station.station.population.FOCAL_PREFIXES`)."""
    _, summary = population
    assert summary["coverage"] and all(r["n"] == CAPTURES for r in summary["coverage"])
    bad = judge_claim(summary, "seed 0")
    assert not bad, "\n".join(bad)


def test_corners_within_a_tenth_of_a_pixel_where_the_image_holds_them(population):
    """Issue 26, item 3: the corners against the twin's true corner pixels on the sample's exactly
    area-sampled, vignetted and bevelled edges (the bevels declared dark, as their maker would: before
    that declaration a bevel's corners were half its width off, 0.24 px median over the population). The
    point-sampled edges are left out: square to the pixel grid their image holds a side only to within its
    pixel interval, and the corners' U says so (test_stated_uncertainty_covers_the_truth_as_claimed)."""
    _, summary = population
    corners = summary["corners_by_edge"]
    print(json.dumps(corners, indent=1))
    checked = [e for e in ("area", "bevel", "vignetting") if e in corners]
    assert "bevel" in checked and len(checked) >= 2
    for e in checked:
        assert corners[e]["max"] <= 0.1, (e, corners[e])


def test_a_planted_obstruction_hides_part_of_the_facet_not_only_the_background_beside_it():
    """A facet that fills little of its bounding box (a thin diagonal band, as a turned gore's trapezoid at
    its worst): a bar reaching in from the box's side often lands beside it. Over 200 draws every planted
    bar hides at least MIN_OBSTRUCTED_FRACTION of the facet's pixels (before: as few as 23 of 28,121)."""
    rows, cols = np.mgrid[0:120, 0:160]
    coverage = np.abs(rows - 0.75 * cols) < 6                # a band 12 px wide across the box's diagonal
    frames = np.full((3, 120, 160), 200, np.uint8)
    frames[0] = 10                                           # the dark frame
    fractions = []
    for seed in range(200):
        out = obstruct(frames, coverage, np.random.default_rng(seed), 1.0)
        hidden = np.any(out != frames, axis=0)
        assert np.all(out[0][hidden] < 30)                   # dark where hidden
        fractions.append(np.count_nonzero(hidden & coverage) / np.count_nonzero(coverage))
    assert min(fractions) >= MIN_OBSTRUCTED_FRACTION


def test_swapped_sets_on_the_same_frames_only_reorder_them():
    """The swapped-sets fault is the good capture's own frames, y sets where the x sets were."""
    from sofast_station.fringes import FringeSet

    frames = np.arange(18)[:, None, None] * np.ones((18, 2, 2), dtype=np.uint8)
    out = swap_sets(frames, FringeSet())
    assert out[:, 0, 0].tolist() == [0, 1, *range(10, 18), *range(2, 10)]


def test_study_population_command(tmp_path, capsys, small_station_toml):
    """Two captures on one station through the CLI: the table, its JSON and a PNG, exit status 0."""
    import argparse

    from sofast_station.station.study_cli import register

    parser = argparse.ArgumentParser(prog="sofast-station")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["study", "population", "--config", str(small_station_toml), "--captures", "2",
                              "--per-station", "2", "--kinds", "dish", "--edges", "area", "--no-faults",
                              "--out", str(tmp_path / "out")])
    assert args.func(args) == 0
    out = capsys.readouterr().out
    assert "false INVALID / refusal on good captures: 0 of 2" in out and "coverage and RMS of error / (U / 2)" in out
    saved = json.loads((tmp_path / "out" / "population-0-2.json").read_text())
    assert saved["summary"]["good"]["n"] == 2 and len(saved["cases"]) == 2
    assert "sofast-station study population --captures 2" in saved["command"]
    assert (tmp_path / "out" / "population-0-2.png").stat().st_size > 10_000
    bad = parser.parse_args(["study", "population", "--config", str(small_station_toml), "--kinds", "dish,moon"])
    from sofast_station.errors import StationError
    with pytest.raises(StationError, match="--kinds: unknown moon"):
        bad.func(bad)


#: The fit figures and slope RMS values the pixels within an edge's blur spoiled.
BLUR_FIGURES = ("curvature_x_per_m", "curvature_y_per_m", "twist_mrad_per_m", "twist_e1_mrad_per_m",
                "twist_e2_mrad_per_m", "principal_focal_lengths_m", "axis_angle_rad", "slope_rms_mrad",
                "slope_rms_corrected_mrad")
BLURRED_CAPTURES, BLURRED_SEED = 16, 3


def test_blurred_and_defocused_edges_leave_the_fit_figures_and_slope_rms_covered():
    """Issue 26: on stations whose lens blurs the facet's edge (a Gaussian of 0.3-1.2 px, a defocus disk of
    radius 0.5-2 px) the pixels within the blur see light from both sides of the edge, and the blur
    averages the slopes it covers: over 110 such captures the fit figures and slope RMS values were
    covered only 57-85 % (twist 6 U off on a defocused dish). The edge's blur is now measured on the
    facet's own edge profiles (no model of the lens), the pixels it reaches left out, and the slope RMS's
    U holds what the blur smooths away.

    Eight stations (the four kinds twice; blur or defocus drawn, 400 x 300 cameras), two captures each:
    16 captures. Each figure's coverage and RMS of error / (U / 2) within the band the claim leaves for its
    count, both sides, over all 16, per kind and per edge model, as
    :func:`test_stated_uncertainty_covers_the_truth_as_claimed` derives it (the code before this change gave
    2.7 for the twist and 3-11 for the slope RMS values; the noise-corrected values left the blur's loss out
    of their U until 2026-12-05: RMS 18-36 on defocused dishes). The measured blur within 0.3 px of
    the twin's point-spread function's standard deviation (its noise is a few hundredths; the disk's
    second moment r / 2 is what it measures)."""
    cases = run_population(BLURRED_CAPTURES, seed=BLURRED_SEED, per_station=2, edges=("blur", "defocus"),
                           faults=())
    summary = summarise(cases)
    assert summary["good"]["n"] == BLURRED_CAPTURES and summary["good"]["false_alarms"]["k"] == 0, summary["good"]
    assert {c["edge"] for c in cases} == {"blur", "defocus"} and {c["kind"] for c in cases} == set(KINDS)
    for c in cases:
        print(f"{c['kind']:<10}{c['edge']:<8} psf {c['psf_sigma_px']:.2f} px, measured {c['edge_blur_px']:.2f} px")
        assert abs(c["edge_blur_px"] - c["psf_sigma_px"]) < 0.3, c
    rows = [r for r in summary["coverage"] if r["figure"].split(".")[0] in BLUR_FIGURES]
    assert len(rows) == 2 + 3 + 2 + 1 + 9 + 9 and all(r["n"] == BLURRED_CAPTURES for r in rows)
    blurred = {**summary, "coverage": rows,
               "coverage_by_kind": {k: {f: r for f, r in t.items() if f.split(".")[0] in BLUR_FIGURES}
                                    for k, t in summary["coverage_by_kind"].items()},
               "coverage_by_edge": {e: [r for r in t if r["figure"].split(".")[0] in BLUR_FIGURES]
                                    for e, t in summary["coverage_by_edge"].items()}}
    bad = judge_claim(blurred, "blurred")
    assert not bad, "\n".join(bad)
