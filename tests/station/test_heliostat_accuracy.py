"""Issue 30, item 3: a heliostat's facets found in one capture, each measured as a facet of its own, and each
facet's canting error, against the twin's truth over drawn populations of heliostats.

Every case draws a heliostat (each facet's focal lengths 5 % apart, twist, random slope errors of 0.1-0.4 mrad
RMS, its own canting error of 1 mrad RMS per axis and spin, its position on the frame to 0.5 mm) placed in
the fixture within +-3 mm and +-2 mrad, and photographs it at one of three noise levels (none, the twin's
default of 0.8 DN read noise and shot noise, twice that read noise). Cameras at a quarter of the station's
resolution (400 x 300: each facet about 110 px across) keep the tests lean; there the noise reaches a canting
about 4 times as much as on the full camera (a sixteenth of the pixels). benchmarks/heliostat.py runs the
full resolution.

Tolerances:

* **canting within 0.05 mrad of truth** (the issue's figure) when the analysis knows the station exactly and
  the facets sit on the frame at their design height to 0.2 mm (one standard deviation; a jig): what is left
  is the method (corners, noise, the facets' own shapes), 0.035 mrad at most here. A facet's height on the
  frame is not measured (its distance comes from the frame's pose and its design position, as OpenCSP does
  it): each millimetre of it turns its measured canting by 0.02 to 0.07 mrad on this station, by facet and
  axis (its U carries it, ``HeliostatSettings.facet_height_mm``);
* **canting covered by its U (k = 2)** when the twin's station (camera, screen, fixture, pitch, distance) is
  drawn from ``[uncertainty]``, the analysis believes the nominal one, and the facets' heights are drawn to
  0.5 mm: the quarter-resolution camera's 1 px focal-length uncertainty is 4 times the full camera's in
  relative terms, so these errors reach 0.3 mrad. 9 heliostats, 72 canting errors, of which at least 90 %
  within U: k = 2 covers 95 %, but a heliostat's four facets move together with its drawn camera, so the
  72 are about 18 independent draws, and 90 % is near their 5th percentile (this seed: 94.4 %); and U at
  most 3 times the errors' RMS (not overstated);
* the facets' own figures as a single facet's: curvature within 1e-3 /m (U of the noisiest is 1.4e-3 /m
  here) and slope RMS against the parabola within 0.05 mrad of truth when noise-free.
"""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.calibrate.records import load_radiometric
from sofast_station.ensemble import load_ensemble
from sofast_station.errors import FacetNotFoundError
from sofast_station.fringes import FringeSet
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.layout import layout_station
from sofast_station.measure.heliostat import analyse_heliostat
from sofast_station.measure.pipeline import AnalysisSettings
from sofast_station.measure.uncertainty import InputUncertainties
from sofast_station.station.heliostat_study import HeliostatRig, scaled_camera
from sofast_station.twin.parameters import TrueFacet, TwinOptics
from sofast_station.twin.heliostat import TrueHeliostat, draw_heliostat
from tests.conftest import ROOT

ENSEMBLE = load_ensemble(ROOT / "fixtures/facets/heliostat_2x2.toml")
NOISE = (TwinOptics.noise_free(), TwinOptics(), TwinOptics(read_noise_dn=1.6))


@pytest.fixture(scope="module")
def rig():
    cam = scaled_camera(CameraIntrinsics(1600, 1200, [[3000, 0, 799.5], [0, 3000, 599.5], [0, 0, 1]],
                                         [-0.03, 0.02, 0, 0, 0]), 4)
    geometry = layout_station(ENSEMBLE.layout_design(), cam, ScreenSpec(2600, 2600, 0.0011), separation_m=1.6)
    return HeliostatRig(geometry, ENSEMBLE, FringeSet(),
                        load_radiometric(ROOT / "calibration/simulated_radiometric.json"),
                        AnalysisSettings(edge_window_px=3), uncertainty=InputUncertainties())


def test_canting_within_0_05_mrad_of_truth_over_a_population(rig):
    rng = np.random.default_rng(30)
    worst = 0.0
    n = 0
    for k in range(6):                       # 6 heliostats, 24 facets, 48 canting errors
        r = rig.case(draw_heliostat(ENSEMBLE, rng, canting_mrad=1.0, position_mm=0.2), NOISE[k % 3], rng)
        assert set(r.status.values()) == {"measured"}
        for label in r.canting:
            err = np.subtract(r.canting[label], r.truth[label])
            worst = max(worst, float(np.abs(err).max()))
            n += 2
            assert np.all(np.abs(err) < 0.05), f"case {k}, facet {label}: canting {r.canting[label]} vs truth " \
                                              f"{r.truth[label]} mrad"
            assert np.all(np.abs(r.curvature_error_per_m[label]) < 1e-3)
            if k % 3 == 0:
                assert abs(r.slope_rms_error_mrad[label]) < 0.05
        # the truth really differs from the design: canting errors of ~1 mrad were drawn and are found
        assert max(abs(v) for t in r.truth.values() for v in t) > 0.3
    print(f"{n} canting errors, the largest {worst:.4f} mrad from truth")


def test_canting_is_covered_by_its_u_when_the_station_is_not_known_exactly(rig):
    rng = np.random.default_rng(31)
    errors, us = [], []
    for k in range(9):                       # 9 heliostats, 36 facets, 72 canting errors
        r = rig.case(draw_heliostat(ENSEMBLE, rng, canting_mrad=1.0), NOISE[k % 3], rng, perturb=True)
        for label in r.canting:
            errors.append(np.subtract(r.canting[label], r.truth[label]))
            us.append(r.u[label])
    errors, us = np.array(errors), np.array(us)
    covered = float(np.mean(np.abs(errors) <= us))
    ratio = np.median(us) / float(np.sqrt(np.mean(errors ** 2)))
    print(f"{errors.size} canting errors: {100 * covered:.1f} % within U, largest {np.abs(errors).max():.3f} mrad, "
          f"median U {np.median(us):.3f} mrad, U / RMS error {ratio:.2f}")
    assert covered >= 0.9
    assert ratio < 3.0
    assert np.abs(errors).max() > 0.1         # the drawn station inputs did reach the canting


def test_a_missing_and_a_hidden_facet_are_named_and_the_others_measured(rig):
    facets = tuple(TrueFacet(placement_mrad=(0.4 * k, -0.3 * k, 0.0)) for k in range(4))
    twin = rig.twin(TrueHeliostat(facets=facets, missing=("R1C2",), obstructed={"R2C1": 0.6}), TwinOptics.noise_free())
    res = analyse_heliostat(rig.capture(twin, None), rig.fringes, rig.geometry, ENSEMBLE, twin.measured_distance_m(),
                            rig.analysis, rays_cam=rig.rays)
    by = {f["label"]: f for f in res.figures["facets"]}
    assert by["R1C2"]["status"] == "missing" and "R1C2 is missing" in by["R1C2"]["reason"]
    assert by["R2C1"]["status"] == "hidden" and "partly hidden" in by["R2C1"]["reason"]
    assert by["R1C1"]["status"] == by["R2C2"]["status"] == "measured"
    assert "canting_mrad" in by["R1C1"] and "canting_mrad" not in by["R1C2"]
    assert res.figures["heliostat"]["n_measured"] == 2 and res.figures["heliostat"]["n_missing"] == 1
    # two facets measured: each one's canting is half their difference, the mean being the reference
    a, b = by["R1C1"]["canting_mrad"], by["R2C2"]["canting_mrad"]
    assert a["x"] == pytest.approx(-b["x"], abs=1e-9)


def test_without_the_range_finders_facet_the_capture_is_refused_naming_it(rig):
    twin = rig.twin(TrueHeliostat(facets=(TrueFacet(),) * 4, missing=("R2C2",)), TwinOptics.noise_free())
    frames = rig.capture(twin, None)
    with pytest.raises(FacetNotFoundError, match="range finder's facet R2C2"):
        analyse_heliostat(frames, rig.fringes, rig.geometry, ENSEMBLE, 4.2, rig.analysis, rays_cam=rig.rays)
    with pytest.raises(FacetNotFoundError, match="nothing in the image responds"):
        dark = np.repeat(frames[:1], len(frames), axis=0)
        analyse_heliostat(dark, rig.fringes, rig.geometry, ENSEMBLE, 4.2, rig.analysis, rays_cam=rig.rays)
