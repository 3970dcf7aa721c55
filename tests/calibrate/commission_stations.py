"""Drawn simulated stations for the commissioning tests and the study in docs/calibration.md: a bowed,
twisted screen of another pitch than station.toml says, a camera misplaced by millimetres, all drawn from a
seed; and the figures of one capture measured with the stated geometry and with the records in force."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tests.conftest import ROOT, SMALL_STATION

#: The second camera of the tests' stations (what [calibration.screen] camera states; the twin's is the same).
HANDHELD = "{ width_px = 640, height_px = 480, focal_length_px = 600.0, distortion = [0.02, -0.05, 0.0, 0.0, 0.0] }"


def draw_assembly(seed: int) -> dict:
    """A real assembly: sag 0.1-1 mm, twist up to +-0.3 mm, pitch 0.6-1 % off (either sign), the camera
    2-5 mm off along its axis (what moves a focal length), up to 3 mm sideways, turned up to 1 mrad."""
    rng = np.random.default_rng([int(seed), 31])
    sign = rng.choice([-1.0, 1.0], 2)
    pitch = 1.0 + sign[0] * rng.uniform(0.006, 0.01)
    return {"screen_sag_mm": round(float(rng.uniform(0.1, 1.0)), 3),
            "screen_twist_mm": round(float(rng.uniform(-0.3, 0.3)), 3),
            "screen_pitch_scale": [round(pitch, 5), round(pitch, 5)],
            "camera_shift_mm": [round(float(v), 3) for v in (*rng.uniform(-3, 3, 2), sign[1] * rng.uniform(2, 5))],
            "camera_turn_mrad": [round(float(v), 3) for v in rng.uniform(-1, 1, 3)]}


def station_file(folder: Path, assembly: dict, views: int = 6, placements: int = 5, seed: int = 3) -> Path:
    """The quarter-resolution simulated dish station with *assembly* as its twin's truth; data under
    ``folder/data``."""
    folder.mkdir(parents=True, exist_ok=True)
    text = SMALL_STATION.format(data_dir=folder / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                radiometric=ROOT / "calibration/simulated_radiometric.json")
    text = text.replace("[simulation]\nseed = 3", f"[simulation]\nseed = {int(seed)}")
    text = text.replace("[calibration]\n", f"""[calibration]
screen = {{ views = {views}, camera = {HANDHELD} }}
pose = {{ placements = {placements}, target = "{ROOT / 'fixtures/targets/reference_mirror.toml'}" }}
""")

    def value(v):
        return "[" + ", ".join(str(x) for x in v) + "]" if isinstance(v, list) else str(v)

    text += "\n[simulation.assembly]\n" + "".join(f"{k} = {value(v)}\n" for k, v in assembly.items())
    path = folder / "station.toml"
    path.write_text(text)
    return path


def true_geometry(twin, stated):
    """The twin's true geometry as the analysis takes a geometry: its true poses, and its true panel as a
    measured screen on a fine grid (what a perfect commissioning would hand the analysis)."""
    import dataclasses

    from sofast_station.geometry import MeasuredScreen
    from sofast_station.twin.assembly import TrueScreen

    screen = twin.screen_shape if twin.screen_shape is not None else TrueScreen(stated.screen)
    s = stated.screen
    gu, gv = np.meshgrid(np.linspace(0, s.width_m, 97), np.linspace(0, s.height_m, 55))
    pts = screen.points(gu.ravel(), gv.ravel())
    nodes_px = np.column_stack([gu.ravel() / s.pitch_x_m, gv.ravel() / s.pitch_y_m])
    return dataclasses.replace(stated, screen_to_camera=twin.geometry.screen_to_camera,
                               fixture_to_camera=twin.geometry.fixture_to_camera,
                               measured_screen=MeasuredScreen(nodes_px, pts, np.zeros((0,) + pts.shape), "truth"))


def figure_errors(config_path: Path, seed: int | None = None, with_truth: bool = False, noise: bool = True) -> dict:
    """One capture of the twin's facet, measured with the stated geometry and with the geometry in force
    (the records'), and with the twin's true geometry (*with_truth*), each against the twin's truth at the
    pixels it kept: relative focal-length errors and slope RMS errors (design, magnitude, mrad)."""
    import dataclasses

    from sofast_station.config import load_config
    from sofast_station.measure.pipeline import reduce_stages, to_analysis
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture

    config = load_config(config_path)
    station = open_station(config, seed=seed, noise=noise)
    try:
        frames, distance = capture(station)
        out = {}
        runs = [("stated", config.stated_geometry), ("records", config.geometry)]
        if with_truth:
            runs.append(("true", true_geometry(station.twin, config.stated_geometry)))
        for name, geometry in runs:
            red, _ = reduce_stages(frames, config.fringes, geometry, config.design, distance,
                                   dataclasses.replace(config.analysis, threads=1))
            fig = red.figures
            truth = station.truth(to_analysis(red).valid)
            out[name] = {f"f_{a}": fig[f"focal_length_{a}_m"] / truth[f"focal_length_{a}_m"] - 1.0 for a in "xy"}
            out[name]["rms_mrad"] = (fig["slope_rms_mrad"]["design"]["magnitude"]
                                     - truth["slope_rms_mrad"]["design"]["magnitude"])
        return out
    finally:
        station.close()
