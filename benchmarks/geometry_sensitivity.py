"""What each part of the camera-to-screen pose does to a facet's figures (docs/calibration.md#the-cameras-pose).

One noise-free capture of the simulated station's facet is reduced again with the screen moved by 1 mrad
about, or 1 mm along, each of its own axes (through its centre), and with the whole camera moved so: the
changes of f_x, f_y, the slope RMS against the design and the twist. What calibrate pose must determine,
and how well, follows from these.

    python benchmarks/geometry_sensitivity.py [--config station.toml]
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default=None, help="station file (default: the tests' small dish station)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    import tempfile

    from sofast_station.config import load_config
    from sofast_station.measure.pipeline import default_screen, reduce_stages, rerun
    from sofast_station.measure.uncertainty import small_motion
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture

    path = args.config
    if path is None:
        from tests.conftest import ROOT, SMALL_STATION
        folder = Path(tempfile.mkdtemp(prefix="sensitivity-"))
        path = folder / "station.toml"
        path.write_text(SMALL_STATION.format(data_dir=folder / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                             radiometric=ROOT / "calibration/simulated_radiometric.json"))
    config = load_config(path)
    station = open_station(config, noise=False)
    try:
        frames, distance = capture(station)
    finally:
        station.close()
    g = config.geometry
    red, _ = reduce_stages(frames, config.fringes, g, config.design, distance, config.analysis)
    f0 = red.figures
    print(f"{config.name}: camera {g.camera.width_px} x {g.camera.height_px}, f_x {f0['focal_length_x_m']:.4f} m, "
          f"f_y {f0['focal_length_y_m']:.4f} m")
    print(f"{'moved by 1 mrad / 1 mm':26s} {'df_x %':>9} {'df_y %':>9} {'dRMS mrad':>10} {'dtwist mrad/m':>13}")

    def show(tag, fig):
        print(f"{tag:26s} {100 * (fig['focal_length_x_m'] / f0['focal_length_x_m'] - 1):>+9.5f} "
              f"{100 * (fig['focal_length_y_m'] / f0['focal_length_y_m'] - 1):>+9.5f} "
              f"{fig['slope_rms_mrad']['design']['magnitude'] - f0['slope_rms_mrad']['design']['magnitude']:>+10.6f} "
              f"{fig['twist_mrad_per_m'] - f0['twist_mrad_per_m']:>+13.6f}")

    for what in ("screen", "camera"):
        for kind in ("r", "t"):
            for a in range(3):
                v = np.zeros(3)
                v[a] = 1.0
                delta = small_motion(rotation_mrad=v) if kind == "r" else small_motion(translation_mm=v)
                if what == "screen":
                    screen = default_screen(g).moved(delta)
                    g2 = dataclasses.replace(g, screen_to_camera=screen.screen_to_camera)
                else:       # the camera moved: screen and fixture move the other way in its frame
                    inv = delta.inverse()
                    g2 = dataclasses.replace(g, screen_to_camera=inv.compose(g.screen_to_camera),
                                             fixture_to_camera=inv.compose(g.fixture_to_camera))
                    screen = default_screen(g2)
                r2 = rerun(red, "rays", fringes=config.fringes, geometry=g2, design=config.design,
                           measured_distance_m=distance, settings=config.analysis, screen=screen)
                show(f"{what} {'about' if kind == 'r' else 'along'} {'xyz'[a]}", r2.figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
