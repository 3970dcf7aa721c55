"""The twin's real assembly (a bowed, twisted panel of another pitch; a misplaced camera) and its commissioning
scenes: every ray meets the panel where its shape says, the ideal assembly changes nothing, and what the
scenes render agrees with their truth as an independent model computes it."""

from __future__ import annotations

import numpy as np
import pytest

from sofast_station.errors import ConfigError
from sofast_station.geometry import CameraIntrinsics, ScreenSpec
from sofast_station.twin.assembly import TrueAssembly, TrueScreen, camera_error_pose, true_geometry

SPEC = ScreenSpec(1920, 1080, 0.000275)


def test_rays_meet_the_bowed_panel_where_its_shape_is():
    screen = TrueScreen(SPEC, TrueAssembly(screen_sag_mm=0.8, screen_twist_mm=-0.3, screen_pitch_scale=(1.01, 0.99)))
    rng = np.random.default_rng(0)
    origins = np.column_stack([rng.uniform(-0.3, 0.3, 500), rng.uniform(-0.2, 0.2, 500), np.full(500, 10.0)])
    targets = np.column_stack([rng.uniform(-0.25, 0.25, 500), rng.uniform(-0.14, 0.14, 500), np.zeros(500)])
    t, pos = screen.trace(origins, targets - origins)
    hit = origins + t[:, None] * (targets - origins)
    z, _, _ = screen.height_and_slopes(hit[:, 0], hit[:, 1])
    assert np.max(np.abs(hit[:, 2] - z)) < 1e-11
    assert np.allclose(screen.points(pos[:, 0], pos[:, 1]), hit, atol=1e-12)       # positions round-trip
    # the frame: origin the display's centre on the panel, the normal there +z
    centre = screen.points(np.array([SPEC.width_m / 2]), np.array([SPEC.height_m / 2]))[0]
    assert np.allclose(centre, 0.0, atol=1e-15)
    _, zx, zy = screen.height_and_slopes(np.zeros(1), np.zeros(1))
    assert zx[0] == 0.0 and zy[0] == 0.0
    # the sag: the centre stands 0.8 mm in front of every edge
    edge = screen.points(np.array([0.0, SPEC.width_m, SPEC.width_m / 2]), np.array([SPEC.height_m / 2] * 2 + [0.0]))
    assert np.allclose(edge[:, 2], -0.8e-3, atol=1e-12)


def test_a_pitch_error_puts_the_pixels_elsewhere():
    screen = TrueScreen(SPEC, TrueAssembly(screen_pitch_scale=(1.01, 1.01)))
    corner = screen.points(np.array([SPEC.width_m]), np.array([SPEC.height_m]))[0]
    assert corner[:2] == pytest.approx([0.5 * SPEC.width_m * 1.01, 0.5 * SPEC.height_m * 1.01])


@pytest.fixture(scope="module")
def small_dish_station(design):
    """The dish at quarter resolution (400 x 300 px): enough for the trace's bookkeeping."""
    from sofast_station.layout import layout_station
    from sofast_station.twin.parameters import TrueFacet, TwinOptics
    from sofast_station.twin.station import TwinStation

    cam = CameraIntrinsics(400, 300, [[3409, 0, 199.5], [0, 3409, 149.5], [0, 0, 1]], [-0.05, 0.1, 2e-4, -1e-4, 0])
    geometry = layout_station(design, cam, SPEC, separation_m=0.34)
    return TwinStation(geometry, design, TrueFacet(focal_length_x_m=5.42, focal_length_y_m=5.35),
                       TwinOptics.noise_free())


def test_the_ideal_assembly_traces_as_the_flat_screen(small_dish_station):
    """The twin's flat screen of the stated pitch through the hook gives the same screen positions as the
    plane it always traced (to 1e-12 m)."""
    from sofast_station.twin.station import TwinStation

    base = small_dish_station
    with_hook = TwinStation(base.geometry, base.design, base.facet, base.optics,
                            screen_shape=TrueScreen(base.geometry.screen))
    a, b = base.screen_position_m, with_hook.screen_position_m
    ok = np.isfinite(a)
    assert np.array_equal(ok, np.isfinite(b)) and np.max(np.abs(a[ok] - b[ok])) < 1e-12


def test_a_misplaced_camera_moves_the_screen_and_the_fixture_in_its_frame(small_dish_station):
    g = small_dish_station.geometry
    a = TrueAssembly(camera_shift_mm=(2.0, -1.0, 3.0), camera_turn_mrad=(0.5, -0.3, 0.2))
    t = true_geometry(g, a)
    # the camera's centre, seen from the fixture, moved by the shift (given in the designed camera frame)
    designed = g.fixture_to_camera.inverse().translation
    moved = t.fixture_to_camera.inverse().translation
    shift_fixture = g.fixture_to_camera.inverse().apply_vector(np.array([2e-3, -1e-3, 3e-3]))
    assert np.allclose(moved - designed, shift_fixture, atol=1e-12)
    # the screen stays where it was, relative to the fixture
    s_fix = g.fixture_to_camera.inverse().compose(g.screen_to_camera)
    s_fix_true = t.fixture_to_camera.inverse().compose(t.screen_to_camera)
    assert np.allclose(s_fix.rotation, s_fix_true.rotation, atol=1e-12)
    assert np.allclose(s_fix.translation, s_fix_true.translation, atol=1e-12)
    assert camera_error_pose(TrueAssembly()).translation.tolist() == [0.0, 0.0, 0.0]


def test_assemblies_out_of_range_are_refused_naming_the_key():
    with pytest.raises(ConfigError, match="screen_pitch_scale"):
        TrueAssembly(screen_pitch_scale=(3.0, 1.0))
    with pytest.raises(ConfigError, match="unknown key 'sag'"):
        TrueAssembly.from_dict({"sag": 1.0})


def test_the_handheld_views_show_the_fiducials_where_the_true_panel_puts_them():
    """The second camera's view of the screen showing ChArUco fiducials: OpenCV finds the corners within 0.15
    px (RMS; 0.10 here, ChArUco's own limit at 26-px squares) of where the true panel (1 % larger, 0.6 mm
    bow) projects them, with no bias beyond 0.03 px: the scene renders its truth (the screen fit rests on it)."""
    from sofast_station.measure import bundle
    from sofast_station.measure.fiducials import detect_charuco, screen_fiducials
    from sofast_station.twin.commissioning import HandheldCamera, ScreenScene, handheld_poses

    cam = CameraIntrinsics(640, 480, [[600.0, 0, 319.5], [0, 600.0, 239.5], [0, 0, 1]], [0.02, -0.05, 0, 0, 0])
    screen = TrueScreen(SPEC, TrueAssembly(screen_sag_mm=0.6, screen_pitch_scale=(1.01, 1.01)))
    scene = ScreenScene(screen, HandheldCamera(cam, read_noise_dn=0.0, electrons_per_dn=0.0), supersample=2)
    fid = screen_fiducials(1920, 1080)
    errors = []
    for pose in handheld_poses(2, np.random.default_rng(3), distance_m=(0.85, 0.9)):
        scene.move(pose)
        ids, px, _ = detect_charuco(scene.capture(fid.image()), fid.layout)
        uv = fid.positions_m(ids, SPEC.pitch_x_m, SPEC.pitch_y_m)
        true_px = bundle.project(bundle.camera_vector(cam), pose.apply(screen.points(uv[:, 0], uv[:, 1])))
        errors.append(px - true_px)
    e = np.concatenate(errors)
    print(f"\n{len(e)} corners: mean {e.mean(0)}, RMS {np.sqrt(np.mean(e ** 2)):.3f} px")
    assert len(e) > 100 and np.sqrt(np.mean(e ** 2)) < 0.15 and np.all(np.abs(e.mean(0)) < 0.03)


def test_through_the_mirror_the_fringes_say_what_geometry_says(small_station_toml):
    """The station camera through the reference mirror (MirrorScene) decodes, at every pixel, the display
    position that reflecting its ray in the mirror's plane onto the true screen gives (the pose fit's model,
    written independently in measure/): mean offset under 0.005 px, scatter under 0.1 px."""
    from sofast_station.calibrate.commission_settings import load_mirror_target
    from sofast_station.config import load_config
    from sofast_station.measure import bundle
    from sofast_station.measure.commission import _mirror_group, decode_positions, fringe_samples
    from sofast_station.measure.screen_shape import ScreenShape
    from sofast_station.station.factory import open_station
    from tests.conftest import ROOT

    config = load_config(small_station_toml)
    station = open_station(config, noise=False, calibration_checks=False)
    try:
        placer = station.mirror_placer(load_mirror_target(ROOT / "fixtures/targets/reference_mirror.toml"))
        placer.place(1, 2, "a shim")
        frames = []
        for pattern in config.fringes.patterns():
            station.display.show(pattern)
            frames.append(station.camera.grab())
        g = station.twin.geometry
        dec = decode_positions(np.stack(frames), config.fringes, (g.screen.width_m, g.screen.height_m))
        px, uv, _ = fringe_samples(dec, 3000)
        shape = ScreenShape("flat", g.screen.width_m, g.screen.height_m)
        base, design = shape.basis(uv[:, 0], uv[:, 1])
        target = g.fixture_to_camera.compose(placer.placements[-1])
        r = _mirror_group("t", px, base, np.zeros_like(base), design[:, :, :2])(
            {"screen": g.screen_to_camera, "t": target, "camera": bundle.camera_vector(g.camera),
             "pitch": np.zeros(2)}, False).reshape(-1, 2)
    finally:
        station.close()
    print(f"\n{len(r)} pixels: mean {r.mean(0)}, std {r.std(0)} px")
    assert len(r) > 1000 and np.all(np.abs(r.mean(0)) < 0.005) and np.all(r.std(0) < 0.1)
