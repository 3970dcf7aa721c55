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
    assert verdict["verdict"] == "pass" and not verdict["warnings"], verdict


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
    assert len(verdict["warnings"]) == 1 and "phase error up to" in verdict["warnings"][0]
