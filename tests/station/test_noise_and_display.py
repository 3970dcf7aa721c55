"""Issue 12, item 4: the capture's own intensity noise, and a display response left nonlinear, on twin
captures of the small dish station.

The twin's frames carry read noise (shot noise off here, so the read noise is all the camera adds) and
8-bit rounding; the display's own 8-bit commands add a fixed-pattern deviation from the ideal fringe, which
the phases see like noise. The twin's forward model (its noise-free linear signal, before rounding) gives
that part exactly: the expected per-frame noise is the read noise and it in quadrature.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sofast_station.calibrate.records import load_radiometric
from sofast_station.config import load_config
from sofast_station.devices.renderer import FringeRenderer
from sofast_station.measure.analysis import analyse
from sofast_station.measure.phase import phase_and_modulation
from sofast_station.station.simulated import build_twin
from sofast_station.result.verdict import judge
from tests.conftest import ROOT


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    from tests.conftest import SMALL_STATION
    path = tmp_path_factory.mktemp("station") / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=path.parent / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    cfg = load_config(path)
    record = load_radiometric(ROOT / "calibration/simulated_radiometric.json")
    twin = build_twin(cfg, noise=False)
    scr = cfg.geometry.screen
    images = {}
    for name, lut in (("linearised", record.lut), ("uncorrected", None)):
        with FringeRenderer(scr.width_px, scr.height_px, lut=lut, floor_level=record.floor_level,
                            max_level=record.max_level) as renderer:
            images[name] = renderer.render_all(cfg.fringes.patterns())
    return cfg, twin, images


def _analyse(cfg, twin, images, seed):
    rng = np.random.default_rng(seed)
    frames = np.stack([twin.capture(img, rng) for img in images])
    return analyse(frames, cfg.fringes, cfg.geometry, cfg.design, twin.measured_distance_m(), cfg.analysis)


def _display_rounding_dn(cfg, twin, images, valid):
    """Per-frame deviation (DN) of the noise-free, unrounded signal from ideal four-step fringes at the
    analysed pixels: the display's 8-bit commands (the consistency residual of the exact signal)."""
    linear = np.stack([twin.linear_dn(img) for img in images])[:, valid]
    parts = [phase_and_modulation(linear[sl])[2] for sets in cfg.fringes.slices().values() for sl in sets]
    return float(np.sqrt(np.mean(np.concatenate(parts) ** 2)) / 2)


@pytest.mark.parametrize("read_noise_dn", [0.3, 1.0, 2.0, 5.0])
def test_noise_estimate_within_ten_percent(small, read_noise_dn):
    cfg, twin, images = small
    optics = dataclasses.replace(twin.optics, read_noise_dn=read_noise_dn, electrons_per_dn=0.0)
    noisy = twin.with_optics(optics)
    a = _analyse(cfg, noisy, images["linearised"], seed=int(10 * read_noise_dn))
    display_dn = _display_rounding_dn(cfg, noisy, images["linearised"], a.valid)
    expected = float(np.hypot(read_noise_dn, display_dn))
    got = a.figures["intensity_noise_dn"]
    print(f"read noise {read_noise_dn} DN, display rounding {display_dn:.3f} DN: expected {expected:.3f}, "
          f"estimated {got:.3f} DN")
    assert display_dn < 0.4
    assert got == pytest.approx(expected, rel=0.1)
    verdict = judge(a.figures, cfg.design, cfg.limits, cfg.quality)
    assert a.figures["display_response"]["harmonic_ratio"] < cfg.quality.warn_display_harmonic_ratio
    # no warning about the display; the small station's sharp, square facet may have a side exactly along
    # a pixel boundary, which the outline cannot tell from a point-sampled staircase (and warns of)
    assert verdict["verdict"] == "pass", verdict
    assert not [w for w in verdict["warnings"] if "pixel grid" not in w], verdict


def test_uncorrected_gamma_is_invalid(small):
    """Gamma 2.2 with no lookup table: invalid with the message, not a pass with a 56 DN 'noise'."""
    cfg, twin, images = small
    a = _analyse(cfg, twin.with_optics(dataclasses.replace(twin.optics, read_noise_dn=1.0, electrons_per_dn=0.0)),
                 images["uncorrected"], seed=4)
    verdict = judge(a.figures, cfg.design, cfg.limits, cfg.quality)
    print(a.figures["display_response"], verdict)
    assert verdict["verdict"] == "invalid"
    assert verdict["reasons"][0].startswith("display response not linearised: run calibrate radiometric")
    assert a.figures["display_response"]["harmonic_ratio"] == pytest.approx(0.27, abs=0.03)
    assert a.figures["intensity_noise_dn"] < 1.5


def test_slightly_nonlinear_display_warns_with_the_phase_error(small):
    """A display whose lookup table is for gamma 2.0 while it has 2.2: a residual exponent of 1.1."""
    cfg, twin, images = small
    optics = dataclasses.replace(twin.optics, display_gamma=2.2 * 1.1, read_noise_dn=1.0, electrons_per_dn=0.0)
    a = _analyse(cfg, twin.with_optics(optics), images["linearised"], seed=5)
    verdict = judge(a.figures, cfg.design, cfg.limits, cfg.quality)
    print(a.figures["display_response"], verdict)
    assert verdict["verdict"] == "pass"
    display = [w for w in verdict["warnings"] if "pixel grid" not in w]     # (see the test above)
    assert len(display) == 1 and "phase error up to" in display[0]


def _true_phase_error_rad(cfg, images, optics) -> float:
    """The largest four-step phase error the display's response gives, from the twin's own law
    (luminance = floor + (1 - floor) (command / 255)^gamma) applied to the rendered fringes along the
    screen: its part that repeats with a quarter of the phase (4 phi and 8 phi; the rest is the 8-bit
    commands' rounding, stated on its own), the largest over the four sets."""
    worst = 0.0
    patterns = cfg.fringes.patterns()
    for axis, sets in cfg.fringes.slices().items():
        for sl in sets:
            profile = [(images[i][0, :] if axis == "x" else images[i][::-1, 0]).astype(float)
                       for i in range(sl.start, sl.stop)]
            lum = [optics.display_floor + (1 - optics.display_floor) * (v / 255.0) ** optics.display_gamma
                   for v in profile]
            phase = np.arctan2(lum[1] - lum[3], lum[0] - lum[2])
            u = (np.arange(profile[0].size) + 0.5) / profile[0].size
            err = np.angle(np.exp(1j * (phase - 2 * np.pi * patterns[sl.start].periods * u)))
            basis = np.column_stack([f(k * phase) for k in (4, 8) for f in (np.sin, np.cos)])
            coef = np.linalg.lstsq(np.column_stack([basis, np.ones_like(phase)]), err, rcond=None)[0]
            grid = np.linspace(0, 2 * np.pi, 720, endpoint=False)
            worst = max(worst, float(np.abs(np.column_stack([f(k * grid) for k in (4, 8) for f in (np.sin, np.cos)])
                                            @ coef[:4]).max()))
    return worst


@pytest.mark.parametrize("gamma", [1.8, 2.0, 2.4, 2.6])
def test_residual_nonlinearity_phase_error_stated_within_30_percent(small, gamma):
    """A display of gamma 1.8-2.6 behind the lookup table for 2.2: the stated phase error is the true one
    (from the twin's gamma) to 30 %."""
    cfg, twin, images = small
    optics = dataclasses.replace(twin.optics, display_gamma=gamma, read_noise_dn=1.0, electrons_per_dn=0.0)
    a = _analyse(cfg, twin.with_optics(optics), images["linearised"], seed=5)
    stated = a.figures["display_response"]["phase_error_rad"]
    true = _true_phase_error_rad(cfg, images["linearised"], optics)
    print(f"gamma {gamma}: stated {1e3 * stated:.2f} mrad ({a.figures['display_response']['phase_error_from']}), "
          f"true {1e3 * true:.2f} mrad")
    assert true > 0.004
    assert stated == pytest.approx(true, rel=0.3)


@pytest.mark.parametrize("knee_dn", [150.0, 180.0])
def test_phase_error_of_a_response_that_is_no_power_law_is_stated_right(small, knee_dn):
    """A camera whose response bends over toward 255 DN (a knee, with the display's own gamma matched):
    its second harmonic is that of a power law with a phase error 2 to 2.4 times smaller than the true
    one (issue 26: a capture's 7.5 mrad were stated "up to 1.5 mrad"). The true phase error here is the
    knee applied to the twin's noise-free signal at the analysed pixels, against the signal without it
    (its part that repeats with a quarter of the phase)."""
    cfg, twin, images = small
    optics = dataclasses.replace(twin.optics, knee_dn=knee_dn, white_dn=250.0, read_noise_dn=1.0, electrons_per_dn=0.0)
    noisy = twin.with_optics(optics)
    a = _analyse(cfg, noisy, images["linearised"], seed=6)
    linear = np.stack([noisy.linear_dn(img) for img in images["linearised"]]).astype(np.float64)[:, a.valid]
    room = 255.0 - knee_dn
    bent = np.where(linear > knee_dn, knee_dn + room * -np.expm1(-(linear - knee_dn) / room), linear)
    true = 0.0
    grid = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    for sl in [s for sets in cfg.fringes.slices().values() for s in sets]:
        p_lin = np.arctan2(linear[sl][1] - linear[sl][3], linear[sl][0] - linear[sl][2])
        p_bent = np.arctan2(bent[sl][1] - bent[sl][3], bent[sl][0] - bent[sl][2])
        err = np.angle(np.exp(1j * (p_bent - p_lin)))
        # its part that repeats with a quarter of the phase (as the display's above)
        basis = np.column_stack([f(k * p_lin) for k in (4, 8) for f in (np.sin, np.cos)])
        coef = np.linalg.lstsq(np.column_stack([basis, np.ones_like(p_lin)]), err, rcond=None)[0]
        true = max(true, float(np.abs(np.column_stack([f(k * grid) for k in (4, 8) for f in (np.sin, np.cos)])
                                      @ coef[:4]).max()))
    stated = a.figures["display_response"]["phase_error_rad"]
    print(f"knee {knee_dn} DN: stated {1e3 * stated:.2f} mrad, true {1e3 * true:.2f} mrad")
    assert true > 0.02
    assert stated == pytest.approx(true, rel=0.3)
