"""Phase retrieval and temporal unwrapping: round trips from a forward model."""

import numpy as np
import pytest

from sofast_station.devices.renderer import FringeRenderer
from sofast_station.fringes import FringeSet
from sofast_station.measure.phase import (QUANTISATION_NOISE_DN, frame_noise, intensity_noise_dn, noise_at_level,
                                          noise_by_level, phase_and_modulation, position_sigma_m, unwrap_positions,
                                          wrap_phase)

WIDTH_PX, HEIGHT_PX, PITCH_M = 1920, 1080, 0.000275


def test_phase_convention_quarter_shifts():
    phi = np.linspace(0, 2 * np.pi, 1000, endpoint=False)
    frames = np.stack([100 + 50 * np.cos(phi - k * np.pi / 2) for k in range(4)])
    got, mod, cons = phase_and_modulation(frames)
    assert np.abs(got - phi).max() < 1e-12
    assert np.allclose(mod, 50) and np.abs(cons).max() < 1e-9
    assert got.min() >= 0 and got.max() < 2 * np.pi


def test_wrap_phase_never_returns_two_pi():
    # np.mod(-1e-17, 2 pi) rounds to exactly 2 pi; the convention maps it to 0
    assert np.mod(np.array([-1e-17]), 2 * np.pi)[0] == 2 * np.pi
    assert wrap_phase(np.array([-1e-17]))[0] == 0.0


def test_noise_estimate_from_consistency():
    rng = np.random.default_rng(3)
    r = rng.normal(0, 2 * 1.7, 200_000)          # residual of four frames with sigma 1.7 DN, not rounded
    assert intensity_noise_dn(r, quantised=False) == pytest.approx(1.7, rel=0.02)
    assert intensity_noise_dn(np.zeros(10)) == 0.0


def _quantised_sets(sigma, gamma=1.0, n=100_000, seed=1):
    """Four-step 8-bit frames of pixels with random phase, level and amplitude; a power-law response."""
    rng = np.random.default_rng(seed)
    phi, a, b = rng.uniform(0, 2 * np.pi, n), rng.uniform(60, 160, n), rng.uniform(30, 60, n)
    frames = np.stack([np.rint((a - b) + 2 * b * ((1 + np.cos(phi - k * np.pi / 2)) / 2) ** gamma
                               + rng.normal(0, sigma, n)) for k in range(4)])
    return np.clip(frames, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("sigma", [0.3, 1.0, 2.0, 5.0])
def test_noise_of_rounded_frames(sigma):
    """Regression: the median absolute deviation of integer residuals collapsed to 0.741 DN for 1 DN of
    noise; the trimmed variance less the rounding variance finds the camera's noise."""
    frames = _quantised_sets(sigma)
    phi, b, r = phase_and_modulation(frames)
    got = frame_noise([phi], [b], [r], level=frames.mean(axis=0))
    assert got.noise_dn == pytest.approx(sigma, rel=0.03)
    assert got.frame_noise_dn == pytest.approx(np.hypot(sigma, QUANTISATION_NOISE_DN), rel=0.03)
    assert got.harmonic_ratio < 0.002 and got.phase_error_rad < 1e-3


def _shot_noise_sets(read_dn, electrons_per_dn, n=120_000, seed=2):
    """Four-step 8-bit frames whose noise grows with the signal (variance read^2 + signal / electrons_per_dn,
    as a camera's): 90 % of the pixels evenly lit, 10 % dim (a facet's edge pixels); and each pixel's
    white - dark level and true per-frame noise (rounding included) averaged over its four frames."""
    rng = np.random.default_rng(seed)
    dim = rng.random(n) < 0.1
    mean = np.where(dim, rng.uniform(10, 110, n), rng.uniform(112, 122, n))      # fringe mean, DN
    amp = 0.8 * mean
    phi = rng.uniform(0, 2 * np.pi, n)
    clean = np.stack([mean + amp * np.cos(phi - k * np.pi / 2) for k in range(4)])
    var = read_dn ** 2 + (clean / electrons_per_dn if electrons_per_dn else np.zeros_like(clean))
    frames = np.clip(np.rint(clean + rng.standard_normal(clean.shape) * np.sqrt(var)), 0, 255).astype(np.uint8)
    white_minus_dark = 2.0 * mean
    true_dn = np.sqrt(var.mean(axis=0) + QUANTISATION_NOISE_DN ** 2)
    return frames, white_minus_dark, true_dn, dim


@pytest.mark.parametrize("read_dn, electrons_per_dn", [(0.8, 40.0), (0.5, 10.0)])
def test_noise_grows_with_brightness_as_the_camera_makes_it(read_dn, electrons_per_dn):
    """Shot noise makes dim pixels quieter: the noise-against-brightness line gives each pixel its own
    noise (the facet's dim edge pixels within 5 %, where one figure for all is 30-60 % too high), and its
    mean over the pixels stays the capture's one noise figure."""
    frames, w, true_dn, dim = _shot_noise_sets(read_dn, electrons_per_dn)
    phi, b, r = phase_and_modulation(frames)
    got = frame_noise([phi], [b], [r], level=w)
    per_pixel = noise_at_level(noise_by_level(got.residuals, w, got.frame_noise_dn), w)
    for sel in (dim & (w < 80), dim & (w > 140), ~dim):
        assert np.sqrt(np.mean(per_pixel[sel] ** 2)) == pytest.approx(np.sqrt(np.mean(true_dn[sel] ** 2)), rel=0.05)
    assert np.sqrt(np.mean(true_dn[dim & (w < 80)] ** 2)) < 0.8 * got.frame_noise_dn    # one figure would be wrong
    assert np.mean(per_pixel ** 2) == pytest.approx(got.frame_noise_dn ** 2, rel=1e-6)


def test_noise_that_does_not_grow_with_brightness_stays_one_figure():
    frames, w, true_dn, dim = _shot_noise_sets(1.5, 0.0)
    phi, b, r = phase_and_modulation(frames)
    got = frame_noise([phi], [b], [r], level=w)
    per_pixel = noise_at_level(noise_by_level(got.residuals, w, got.frame_noise_dn), w)
    assert per_pixel == pytest.approx(np.full(w.size, got.frame_noise_dn), rel=0.04)
    assert got.frame_noise_dn == pytest.approx(np.hypot(1.5, QUANTISATION_NOISE_DN), rel=0.03)


def test_noise_by_level_falls_back_to_one_figure():
    rng = np.random.default_rng(0)
    w = rng.uniform(50, 200, 20_000)
    falling = rng.normal(0, 2 * np.sqrt(4.0 - 0.01 * w))              # noise that falls with brightness
    assert noise_by_level([falling], w, 1.7) == (1.7 ** 2, 0.0)
    assert noise_by_level([falling[:100]], w[:100], 1.7) == (1.7 ** 2, 0.0)         # too few residuals
    assert noise_by_level([falling], np.full(w.size, 120.0), 1.7) == (1.7 ** 2, 0.0)  # no spread of brightness
    assert noise_by_level([falling], w[:10], 1.7) == (1.7 ** 2, 0.0)                # not the same pixels


def test_half_drawn_pixels_do_not_inflate_the_noise():
    frames = _quantised_sets(1.0).astype(np.int16)
    frames[2, :3000] += 40                        # 3 % of the pixels saw a wrong frame
    phi, b, r = phase_and_modulation(frames)
    assert frame_noise([phi], [b], [r]).noise_dn == pytest.approx(1.0, rel=0.05)


@pytest.mark.parametrize("gamma, ratio", [(2.2, 0.28), (1.1, 0.033), (0.8, -0.07)])
def test_a_nonlinear_response_is_a_harmonic_not_noise(gamma, ratio):
    """A power-law response puts a second harmonic into the residual; it is measured, and removed
    before the noise (uncorrected gamma 2.2 made the old estimate 18 DN for 1 DN of noise)."""
    frames = _quantised_sets(1.0, gamma=gamma)
    phi, b, r = phase_and_modulation(frames)
    got = frame_noise([phi], [b], [r])
    assert got.signed_harmonic_ratio == pytest.approx(ratio, rel=0.1)
    assert got.harmonic_ratio == pytest.approx(abs(ratio), rel=0.1)
    assert got.noise_dn < 1.25
    # the phase error such a response gives full-depth fringes, found here by brute force
    theta = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    i0, i1, i2, i3 = ((1 + np.cos(theta - k * np.pi / 2)) ** gamma for k in range(4))
    worst = np.abs(np.angle(np.exp(1j * (np.arctan2(i1 - i3, i0 - i2) - theta)))).max()
    assert got.phase_error_rad == pytest.approx(worst, rel=0.25)


def _sample_display(rows_of_frames: np.ndarray, u: np.ndarray, pitch: float) -> np.ndarray:
    """What a camera pixel sees at position u (metres along the axis) of a displayed line of pixels:
    linear interpolation between display pixel centres (a slightly defocused view), clamped at the edge."""
    n = rows_of_frames.shape[1]
    centres = (np.arange(n) + 0.5) * pitch
    return np.stack([np.interp(u, centres, line.astype(float)) for line in rows_of_frames])


@pytest.fixture(scope="module")
def displayed():
    """The real renderer's 8-bit fringe images (identity lookup table)."""
    with FringeRenderer(WIDTH_PX, HEIGHT_PX) as r:
        return FringeSet(), r.render_all(FringeSet().patterns())


@pytest.mark.parametrize("axis", ["x", "y"])
def test_round_trip_through_the_renderer_edges_and_period_boundaries(displayed, axis):
    fringes, imgs = displayed
    length = (WIDTH_PX if axis == "x" else HEIGHT_PX) * PITCH_M
    periods = getattr(fringes, f"periods_{axis}")
    # Positions within 1 % of each edge, and around every period boundary of every pattern.
    near_edges = np.concatenate([np.linspace(0.0005, 0.01, 40), 1 - np.linspace(0.0005, 0.01, 40)]) * length
    boundaries = np.array([k / p for p in periods for k in range(1, int(p))]) * length
    offsets = np.array([-3, -1, -0.25, 0, 0.25, 1, 3]) * PITCH_M
    u_true = np.concatenate([near_edges, (boundaries[:, None] + offsets).ravel()])
    phases, mods = [], []
    for sl in fringes.slices()[axis]:
        frames = imgs[sl]
        # the line of display pixels along the axis, ordered by increasing u
        lines = frames[:, 0, :] if axis == "x" else frames[:, ::-1, 0]
        phi, b, _ = phase_and_modulation(_sample_display(lines, u_true, PITCH_M))
        phases.append(phi)
        mods.append(b)
    sigma = position_sigma_m(mods[-1], QUANTISATION_NOISE_DN, periods[-1], length)
    res = unwrap_positions(phases, periods, length, sigma)
    err = np.abs(res.position_m - u_true)
    # 8-bit display levels move the phase by at most ~0.5/127 rad: 0.08 mm at 4 periods; allow 0.4 pitch
    print(f"{axis}: max position error {np.nanmax(err) * 1e3:.4f} mm, {(~res.valid).sum()} dropped at edges")
    assert np.nanmax(err) < 0.4 * PITCH_M, f"max error {np.nanmax(err) * 1e3:.4f} mm"
    # nothing is ever a screen width off, and only pixels inside the guard band may be dropped
    guard = 4 * sigma
    dropped = ~res.valid
    assert np.all((u_true[dropped] < guard[dropped]) | (u_true[dropped] > length - guard[dropped]))
    assert res.valid.mean() > 0.95
    assert res.disagreements == 0


def test_last_columns_are_not_a_screen_width_off():
    """Regression: a noise-free 8-bit capture must not put the last screen columns at the left edge."""
    length, periods = 0.528, [1.0, 4.0]
    u = length - np.array([0.1, 0.3, 0.6, 1.0, 2.0]) * 1e-3
    phases = []
    for p in periods:
        frames = np.stack([np.round(127.5 + 127.5 * np.cos(2 * np.pi * p * u / length - k * np.pi / 2))
                           for k in range(4)])
        phases.append(phase_and_modulation(frames)[0])
    res = unwrap_positions(phases, periods, length, position_sigma_m(127.5, 0.29, 4.0, length))
    assert np.all(res.position_m[res.valid] > length / 2)
    assert np.nanmax(np.abs(res.position_m - u)) < 1e-4


def test_non_integer_periods_like_opencsp():
    """OpenCSP shows 0.9, 3.9, 15.9, 63.9 periods; positions past the coarse pattern's end are invalid."""
    length, periods = 1.0, [0.9, 3.9, 15.9, 63.9]
    u = np.linspace(0.0005, 0.9995, 5001)
    phases = [wrap_phase(2 * np.pi * p * u / length) for p in periods]
    res = unwrap_positions(phases, periods, length)
    assert np.all(res.valid)
    assert np.abs(res.position_m - u).max() < 1e-12
    # a pixel whose coarse phase says u > L (only possible with p_1 < 1) is dropped and counted
    u_bad = np.array([0.5 / 0.9 * 1.0])          # phase of 0.9 periods at 1.05 L
    phases = [wrap_phase(np.array([2 * np.pi * 0.9 * 1.05])) for _ in periods]
    res = unwrap_positions(phases, periods, length)
    assert res.coarse_out_of_range == 1 and not res.valid[0]
    del u_bad


def test_disagreement_is_dropped_and_counted():
    length, periods = 1.0, [1.0, 4.0]
    u = np.array([0.30, 0.60])
    phases = [wrap_phase(2 * np.pi * p * u / length) for p in periods]
    # coarse phase 0.12 L (half a fine period) off for the second pixel: the fine phase cannot agree
    phases[0] = phases[0] + np.array([0.0, 2 * np.pi * 0.12])
    phases[0] = wrap_phase(phases[0])
    res = unwrap_positions(phases, periods, length)
    assert res.valid.tolist() == [True, False] and res.disagreements == 1
    assert np.isnan(res.position_m[1])


def test_bad_arguments_name_the_problem():
    with pytest.raises(ValueError, match="increasing"):
        unwrap_positions([np.zeros(2)] * 2, [4, 1], 1.0)
    with pytest.raises(ValueError, match="one phase per period"):
        unwrap_positions([np.zeros(2)], [1, 4], 1.0)
    with pytest.raises(ValueError, match="guard_sigmas"):
        unwrap_positions([np.zeros(2)] * 2, [1, 4], 1.0, guard_sigmas=2)


def test_eight_bit_frames_give_the_general_paths_values():
    """The 8-bit path (from the bytes, block by block) on every (s, c) = (I_1 - I_3, I_0 - I_2) that 8-bit
    counts can give, against the general path on the same counts as 16-bit integers: modulation and
    consistency the same values, the phase within one float32 step (4.8e-7 rad) and in [0, 2 pi)."""
    s, c = (g.ravel() for g in np.meshgrid(np.arange(-255, 256), np.arange(-255, 256)))
    level = np.random.default_rng(4).integers(0, 256, s.size)
    frames = np.stack([np.maximum(c, 0), np.maximum(s, 0), np.maximum(-c, 0), np.maximum(-s, 0)])
    frames = np.clip(frames + np.minimum(level, 255 - frames.max(axis=0)), 0, 255)
    fast = phase_and_modulation(frames.astype(np.uint8))
    general = phase_and_modulation(frames.astype(np.int16))
    assert fast[0].size > 16384 * 10                               # many blocks
    assert np.array_equal(fast[1], general[1]) and np.array_equal(fast[2], general[2])
    step = np.abs(fast[0].astype(np.float64) - general[0])
    assert np.minimum(step, 2 * np.pi - step).max() <= 4.8e-7
    assert fast[0].dtype == np.float32 and fast[0].min() >= 0 and fast[0].max() < 2 * np.pi
    # and the shape of the frames is kept
    image = frames[:, :300 * 400].reshape(4, 300, 400).astype(np.uint8)
    assert all(a.shape == (300, 400) for a in phase_and_modulation(image))


def test_sixteen_bit_frames_give_the_general_paths_values():
    """16-bit counts (OpenCSP's scaled images) take the same path, the modulation's sum of squares in float64:
    against the general path's float32 arithmetic on the same counts (as float32, exact), modulation and
    consistency the same values, the phase within one float32 step."""
    rng = np.random.default_rng(6)
    frames = rng.integers(0, 65536, (4, 400_000)).astype(np.uint16)
    frames[:, :500] = frames[0, :500]                       # no fringe: phase 0 as atan2(0, 0)
    fast = phase_and_modulation(frames)
    i0, i1, i2, i3 = frames.astype(np.float32)
    s, c = i1 - i3, i0 - i2
    assert np.array_equal(fast[1], 0.5 * np.hypot(s, c)) and np.array_equal(fast[2], (i0 + i2) - (i1 + i3))
    general = np.arctan2(s, c)
    general[general < 0] += 2 * np.pi                       # the general path's wrap, stored in float32
    step = np.abs(fast[0].astype(np.float64) - general)
    assert np.minimum(step, 2 * np.pi - step).max() <= 4.8e-7 and np.all(fast[0][:500] == 0)
    assert fast[0].dtype == np.float32 and fast[0].min() >= 0 and fast[0].max() < 2 * np.pi


def test_block_wise_unwrapping_gives_the_formulas_values():
    """unwrap_positions runs block by block, in place: the same positions and counts as the formulas
    written as whole-array expressions (docs/conventions.md#unwrapping), on more pixels than a block."""
    rng = np.random.default_rng(8)
    length, periods = 0.53, [1.0, 4.0, 16.0]
    u_true = rng.uniform(-0.002, length + 0.002, 70_000)
    spoiled = rng.random(u_true.size) < 0.02                      # some pixels far off: disagreements
    phases = [wrap_phase(2 * np.pi * p * u_true / length + rng.normal(0, 0.02, u_true.size)
                         + (2.5 * spoiled if p == 4.0 else 0.0)).astype(np.float32) for p in periods]
    sigma = rng.uniform(1e-5, 2e-4, u_true.size)
    res = unwrap_positions(phases, periods, length, sigma)
    two_pi = 2.0 * np.pi
    u = length * phases[0].astype(np.float64) / (two_pi * periods[0])
    disagree = np.zeros(u.size, dtype=bool)
    for phi, p in zip(phases[1:], periods[1:]):
        phi = phi.astype(np.float64)
        k = np.round((two_pi * p * u / length - phi) / two_pi)
        u_fine = length * (phi + two_pi * k) / (two_pi * p)
        disagree |= np.abs(u_fine - u) > length / (4.0 * p)
        u = u_fine
    u = np.mod(u, length)
    u[u >= length] = 0.0
    near_edge = ((u < 4 * sigma) | (u > length - 4 * sigma)) & ~disagree
    valid = ~(disagree | near_edge)
    assert np.array_equal(res.valid, valid)
    assert np.array_equal(res.position_m, np.where(valid, u, np.nan), equal_nan=True)
    assert (res.disagreements, res.edge_guard, res.coarse_out_of_range) == (disagree.sum(), near_edge.sum(), 0)
    assert res.edge_guard > 0 and res.disagreements > 0


def test_noise_fit_on_two_threads_gives_the_same_bits():
    """frame_noise with a pool (half of the sets' samples, scatters and cleaned residuals on the pool's
    thread) gives the serial path's values, bit for bit; the analysis keeps one pool per process."""
    from sofast_station.measure.pipeline import thread_pool

    sets = [_quantised_sets(1.0, gamma=1.3, n=60_000, seed=s) for s in (1, 2, 3)]
    parts = [phase_and_modulation(f) for f in sets]
    args = ([p[0] for p in parts], [p[1] for p in parts], [p[2] for p in parts])
    level = sets[0].mean(axis=0)
    serial = frame_noise(*args, level=level)
    with thread_pool(2) as pool:
        threaded = frame_noise(*args, level=level, pool=pool)
    with thread_pool(2) as again:
        assert again is pool                                   # kept, not shut down
        assert again.submit(lambda: 7).result() == 7
    assert serial.harmonic_ratio > 0.01                         # a harmonic was fitted and removed
    assert (threaded.noise_dn, threaded.signed_harmonic_ratio) == (serial.noise_dn, serial.signed_harmonic_ratio)
    assert all(np.array_equal(a, b) for a, b in zip(serial.residuals, threaded.residuals))


def test_unwrapping_on_two_threads_gives_the_same_positions():
    """The compiled unwrapping of both axes at once (as the analysis runs it): each pixel's arithmetic
    is its own, so the same positions and counts as one after the other."""
    from concurrent.futures import ThreadPoolExecutor

    from sofast_station.measure.phase import unwrap_positions

    rng = np.random.default_rng(32)
    n, big_l, periods = 100_000, 0.52, [1, 8]
    u_true = rng.uniform(0, big_l, n)
    phases = [np.mod(2 * np.pi * p * u_true / big_l + rng.normal(0, 0.02, n), 2 * np.pi).astype(np.float32)
              for p in periods]
    sigma = rng.uniform(1e-5, 4e-5, n)
    alone = unwrap_positions(phases, periods, big_l, sigma, 4.0)
    with ThreadPoolExecutor(2) as pool:
        both = [pool.submit(unwrap_positions, phases, periods, big_l, sigma, 4.0) for _ in range(2)]
        both = [f.result() for f in both]
    for got in both:
        np.testing.assert_array_equal(got.position_m, alone.position_m)
        assert (got.edge_guard, got.disagreements) == (alone.edge_guard, alone.disagreements)
    assert np.nanmedian(np.abs(alone.position_m - u_true)) < 1e-3


@pytest.mark.parametrize("outliers", [0.0, 0.1])
def test_the_period_sets_show_a_known_phase_error_past_spoiled_pixels(outliers):
    """Coarse and fine phases (8 fine periods per coarse) both carrying e(phi) = 10 mrad sin 4 phi, 2 mrad
    of noise, and a share of pixels whose fine phase is spoiled by 0.5-2.5 rad: the fit finds e's largest
    value (10 mrad) and RMS (7.07 mrad) to 2 %, and leaves the spoiled pixels out."""
    from sofast_station.measure.phase import phase_error_between_periods

    rng = np.random.default_rng(7)
    n, r, a = 200_000, 8, 0.01
    u = rng.uniform(0.0, 1.0, n)
    true_c, true_f = 2 * np.pi * u, 2 * np.pi * r * u
    phi_c = (true_c + a * np.sin(4 * true_c) + rng.normal(0.0, 0.002, n)) % (2 * np.pi)
    phi_f = (true_f + a * np.sin(4 * true_f) + rng.normal(0.0, 0.002, n)) % (2 * np.pi)
    bad = rng.random(n) < outliers
    phi_f[bad] = (phi_f[bad] + rng.uniform(0.5, 2.5, bad.sum()) * rng.choice([-1.0, 1.0], bad.sum())) % (2 * np.pi)
    b = np.full(n, 300.0)
    got = phase_error_between_periods([(phi_c, phi_f, b, b, 1, r)], 1.0)
    assert got.max_rad == pytest.approx(a, rel=0.02)
    assert got.rms_rad == pytest.approx(a / np.sqrt(2.0), rel=0.02)
    assert got.n_pixels <= n - 0.9 * bad.sum()


def test_the_power_law_table_written_in_the_source_is_what_it_is_computed_from():
    """phase._RATIOS and _PHASE_ERRORS are constants (computing them cost every command 0.03 s): they must
    be what _power_law_table gives (to rounding: numpy's pow and cos may differ by a unit in the last place
    from one processor to another), and must still say what the model says: a linear response (g = 1)
    has no second harmonic and no phase error, and the ratio grows with the exponent. A phase error is the
    difference of two angles up to 2 pi, so its rounding is absolute, a few units in the last place of 2 pi
    (8.9e-16): on 2026-12-07's machine one of 301 differed by 4.9e-16, 8e-13 of its 6e-4 rad."""
    from sofast_station.measure import phase as ph

    ratios, errors = ph._power_law_table(ph._EXPONENTS)
    assert ph._RATIOS.shape == ph._PHASE_ERRORS.shape == ph._EXPONENTS.shape
    np.testing.assert_allclose(ph._RATIOS, ratios, rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(ph._PHASE_ERRORS, errors, rtol=1e-13, atol=4e-15)
    linear = int(np.argmin(np.abs(ph._EXPONENTS - 1.0)))
    assert abs(ph._RATIOS[linear]) < 1e-12 and ph._PHASE_ERRORS[linear] < 1e-12
    assert np.all(np.diff(ph._RATIOS) > 0)          # the inverse lookup needs a monotonic table


def test_the_period_sets_phase_error_is_the_same_bits_with_its_axes_on_a_pool():
    """phase_error_between_periods forms each axis's regressors on the analysis' pool (issue 32): the same
    figures, to the bit, as formed one after another; and it finds a fourth-harmonic error it is given."""
    from concurrent.futures import ThreadPoolExecutor

    from sofast_station.measure.phase import phase_error_between_periods

    rng = np.random.default_rng(5)
    sets = []
    for p_c, p_f in ((1, 8), (1, 4)):
        theta = rng.uniform(0.0, 2.0 * np.pi, 60_000)           # the coarse set's true phase
        fine = p_f * theta

        def seen(phi):
            return np.angle(np.exp(1j * (phi + 0.004 * np.sin(4.0 * phi))))

        sets.append((seen(theta).astype(np.float32), seen(fine).astype(np.float32),
                     np.full(theta.size, 80.0, np.float32), np.full(theta.size, 80.0, np.float32), p_c, p_f))
    mask = [rng.random(60_000) > 0.1 for _ in sets]
    alone = phase_error_between_periods(sets, 0.5, mask=mask)
    with ThreadPoolExecutor(2) as pool:
        pooled = phase_error_between_periods(sets, 0.5, mask=mask, pool=pool)
    assert alone == pooled
    assert alone.max_rad == pytest.approx(0.004, rel=0.05)


def test_the_drawn_correction_passes_a_phase_error_on_with_its_gain():
    """``drawn_gain``: a phase error d of the finest set moves the corrected position by (1 - e'(phi)) d.

    Checked against the correction itself (``pipeline.corrected_positions``, which interpolates the table's
    values, where the gain takes the table's central-difference slope): a 1920-pixel display drawing 16 periods
    of 120 pixels through a gamma-2.2 table, the position's change for d = 0.01 rad at 400 phases over a
    period. The two differ by the table's interpolation over d (a few 1e-3 of e' for a ripple of at most
    n / 6 = 20 harmonics on 2048 samples); the tolerance is 2 % of e''s largest value, which is itself checked
    to be worth a gain (above 1 %)."""
    from sofast_station.measure.phase import drawn_gain, drawn_table
    from sofast_station.measure.pipeline import corrected_positions

    lut = tuple(float(v) for v in np.linspace(0.0, 1.0, 256) ** (1 / 2.2))
    fringes = FringeSet(periods_x=(1, 4, 16), periods_y=(1, 4, 16)).drawn_through(lut, 0.05, 0.95, 1920, 1080)
    assert drawn_gain(FringeSet(periods_x=(1, 4, 16), periods_y=(1, 4, 16)), "x", np.zeros(3), 1.0) is None
    length_m, periods, d = 0.528, 16, 0.01
    table = drawn_table(fringes, "x", periods)

    class _NoMeasuredError:
        def error_at(self, phase):
            return np.zeros_like(phase)

    phi = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False) + 0.0013
    cycle = 2.0 * np.pi * 7                                   # the 8th period of the screen
    position = length_m * (phi + cycle) / (2.0 * np.pi * periods)
    step = length_m * d / (2.0 * np.pi * periods)
    moved = corrected_positions(position + step, phi + d, _NoMeasuredError(), table, periods, length_m)
    still = corrected_positions(position, phi, _NoMeasuredError(), table, periods, length_m)
    seen = (moved - still) / step
    gain = drawn_gain(fringes, "x", position + 0.5 * step, length_m)
    slope = np.max(np.abs(gain - 1.0))
    assert slope > 0.01
    assert np.max(np.abs(seen - gain)) < 0.02 * slope


def _drawn_and_seen(footprint_px: tuple, n: int = 150, sub: int = 32):
    """The four-step phase error of a fringe set drawn on a display of *n* pixels a period (a gamma-2.2 table,
    every pixel's command rounded) as a camera pixel of footprint *footprint_px* sees it: each pixel's linear
    level, linear between pixel centres, averaged over a box of each footprint edge's width (a parallelogram's
    projection on the fringes' axis is the convolution of its two edges' boxes), at *sub* points a display
    pixel over one period. Returns (phase, error) in rad, and the fringes' (lut, floor, max)."""
    lut = tuple(float(v) for v in np.linspace(0.0, 1.0, 256) ** (1 / 2.2))
    grid = np.linspace(0.0, 1.0, 256)
    floor_level, max_level, periods = 0.05, 0.95, 3
    centres = np.arange(n * periods) + 0.5
    phi = 2.0 * np.pi * centres / n
    x = np.arange(n * periods * sub) / sub
    seen = []
    for k in range(4):
        level = floor_level + (max_level - floor_level) * 0.5 * (1.0 + np.cos(phi - 0.5 * np.pi * k))
        command = np.floor(255.0 * np.interp(level, grid, np.asarray(lut)) + 0.5)
        fine = np.interp(x, centres, np.interp(command / 255.0, np.asarray(lut), grid), period=n * periods)
        for width in footprint_px:
            m = max(int(round(width * sub)), 1)
            fine = np.convolve(np.concatenate([fine[-m:], fine, fine[:m]]), np.ones(m) / m, mode="same")[m:-m]
        seen.append(fine)
    phase = 2.0 * np.pi * x / n
    error = np.angle(np.exp(1j * (np.arctan2(seen[1] - seen[3], seen[0] - seen[2]) - phase)))
    middle = (x >= n) & (x < 2 * n)                 # one period clear of the wrapped ends
    return phase[middle], error[middle], (lut, floor_level, max_level)


@pytest.mark.parametrize("footprint_px", [(9.7, 0.4), (5.0, 2.6)])
def test_the_drawn_fringes_error_as_a_camera_pixel_of_some_footprint_sees_it(footprint_px):
    """``drawn_phase_error(..., footprint_px)`` against the forward model: the drawn fringes' rounded levels
    averaged over the pixel's footprint on the screen (:func:`_drawn_and_seen`), 150 display pixels a period
    (the heliostat station's 16 periods on 2400 pixels). (9.7, 0.4) is a pixel of the population's heliostat
    station (400 x 300 camera at 4 m from a 1.1 mm pitch screen), (5.0, 2.6) a sheared one of its gore's.

    Measured: the footprint's table leaves 0.140 and 0.108 mrad RMS (harmonics above n / 6 the table does not
    keep, which the footprint attenuates); a point's table leaves 1.84 and 1.00 mrad, more than the 0.82 and
    1.20 mrad of ripple the pixels see without any correction. Tolerances: 0.2 mrad (1.4 times the larger
    measured residual), and a point's table must leave at least 0.9 mrad (so the case tells the two apart)."""
    from sofast_station.measure.phase import drawn_error_at, drawn_phase_error

    phase, error, drawn = _drawn_and_seen(footprint_px)
    left = {}
    for name, footprint in (("point", (0.0, 0.0)), ("footprint", footprint_px)):
        r = error - drawn_error_at(drawn_phase_error(*drawn, 150, footprint), phase)
        left[name] = float(np.sqrt(np.mean((r - r.mean()) ** 2)))
    assert left["footprint"] < 0.2e-3
    assert left["point"] > 0.9e-3
    assert left["footprint"] < 0.25 * float(np.std(error))


def test_pixel_footprint_from_the_positions_steps():
    """``pixel_footprint_px``: screen positions that are an affine map of the pixel grid (metres; a 2400-pixel
    display across 2.64 m) give each axis's steps along the image's columns and rows back in display pixels,
    whatever sign they have, with a fifth of the pixels untrusted (NaN where they are)."""
    from sofast_station.measure.phase import pixel_footprint_px

    shape = (30, 40)
    rows, cols = np.divmod(np.arange(shape[0] * shape[1]), shape[1])
    pitch = 2.64 / 2400
    positions = {"x": 0.5 + pitch * (9.7 * cols - 0.4 * rows), "y": 0.7 + pitch * (0.3 * cols + 9.6 * rows)}
    ok = np.random.default_rng(3).random(rows.size) > 0.2
    positions = {a: np.where(ok, p, np.nan) for a, p in positions.items()}
    got = pixel_footprint_px(shape, np.arange(rows.size), ok, positions, {"x": 2400, "y": 2400},
                             {"x": 2.64, "y": 2.64})
    assert got == {"x": (9.7, 0.4), "y": (0.3, 9.6)}
