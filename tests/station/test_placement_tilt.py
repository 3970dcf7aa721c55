"""Issue 44 item 6: the facet's placement tilt to 1 mrad or better (U) once the fixture's pose is known as
commissioning leaves it (docs/method.md#the-placement-tilt): from the slopes (``optical_tilt_mrad``), not from
the corners, which cannot resolve it at this geometry."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_slopes_give_the_placement_tilt_to_1_mrad_where_the_corners_cannot(tmp_path):
    """The small 400 x 300 dish station with the fixture's rotation known to 0.2 mrad (k = 1: what a pose record
    of calibrate commission states, 0.20-0.21 mrad on the drawn assemblies; the marks keep it so through a
    shift). 4 captures (seed 7), the facet turned by up to 5 mrad about x and y, the twin's geometry drawn within
    [uncertainty] each capture (the analysis keeps the nominal one). The truth is the twin's placement.

    Claims: the slopes' tilt has U (k = 2) at or under 1 mrad, and covers its error against the true placement
    in at least 7 of the 8 cases (with a true coverage of 95 %, 7 or 8 of 8 happen with probability 0.94; when
    written, 8 of 8, errors up to 0.63 mrad, U 0.71); the corners' U is above 6 mrad in every case (their
    errors reached 6 mrad): they cannot give it."""
    import numpy as np

    from tests.conftest import SMALL_STATION

    from sofast_station.config import load_config
    from sofast_station.station.study import Placement, run_repeats

    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json")
                    + "\n[uncertainty]\nfixture_rotation_mrad = [0.2, 0.2, 0.2]\n")
    config = load_config(path)
    errors, slope_u, corner_u = [], [], []
    for r in run_repeats(config, 4, seed=7, placement=Placement(mm=(1.0, 1.0, 0.5), mrad=(5.0, 5.0, 1.0)),
                         perturb_geometry=True):
        f, u, truth = r["figures"], r["U"], r["truth"]
        for axis, i in (("x", 0), ("y", 1)):
            errors.append(f[f"optical_tilt_mrad.{axis}"] - truth[f"placement.mrad.{i}"])
            slope_u.append(u[f"optical_tilt_mrad.{axis}"])
            corner_u.append(u[f"placement.mrad.{i}"])
    errors, slope_u = np.abs(errors), np.array(slope_u)
    print(f"slopes' tilt: errors {np.round(errors, 3).tolist()} mrad, U {np.round(slope_u, 3).tolist()}; "
          f"corners' U {np.round(corner_u, 1).tolist()}")
    assert np.all(slope_u <= 1.0)
    assert np.count_nonzero(errors <= slope_u) >= 7
    assert min(corner_u) > 6.0
