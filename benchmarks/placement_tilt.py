"""Benchmark: the facet's placement tilt in the fixture, from its corners and from its slopes, against the twin's
truth (issue 44, item 6; docs/method.md#the-placement-tilt).

    .venv/bin/python benchmarks/placement_tilt.py                   # the 400 x 300 dish: ideal, drawn, commissioned
    .venv/bin/python benchmarks/placement_tilt.py --captures 12 --gore
    .venv/bin/python benchmarks/placement_tilt.py --quick           # the tests: 2 captures, the ideal station

Each capture places the twin's facet anew, turned by up to +-5 mrad about x and y (+-1 mrad about z, +-1 mm),
and is analysed with its uncertainty. Printed per axis: the corner pose's tilt (``placement`` rx, ry) against the
true placement, and the slopes' (``optical_tilt_mrad``: the boresight frame's tilt in the fixture, what the
console, the page and the verdict call the tilt) against the truth's optical tilt and against the true placement;
their U (k = 2) and how many errors it covers; and the facet's own boresight (the truth's optical tilt less its
placement: how far the facet's optical frame is from its mechanical one).

Stations: ``ideal`` (the small dish station, the twin's geometry the stated one), ``drawn`` (the same, the twin's
geometry drawn within ``[uncertainty]`` each capture), ``commissioned`` (a drawn assembly, commissioned by
``calibrate commission``, measured with its records: the fixture pose the pose record states), ``gore`` (the
shipped gore station at 1600 x 1200, ideal). Nothing is asserted.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _small(folder: Path) -> Path:
    from tests.conftest import SMALL_STATION

    path = folder / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=folder / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json"))
    return path


def _rows_from_repeats(config, n: int, perturb: bool) -> list[tuple]:
    from sofast_station.station.study import Placement, run_repeats

    out = []
    for r in run_repeats(config, n, seed=3, placement=Placement(mm=(1.0, 1.0, 0.5), mrad=(5.0, 5.0, 1.0)),
                         perturb_geometry=perturb):
        f, u, t = r["figures"], r["U"], r["truth"]
        for ax, i in (("x", 0), ("y", 1)):
            out.append((ax, f[f"placement.mrad.{i}"] - t[f"placement.mrad.{i}"], u[f"placement.mrad.{i}"],
                        f[f"optical_tilt_mrad.{ax}"] - t[f"optical_tilt_mrad.{ax}"],
                        f[f"optical_tilt_mrad.{ax}"] - t[f"placement.mrad.{i}"], u[f"optical_tilt_mrad.{ax}"],
                        t[f"optical_tilt_mrad.{ax}"] - t[f"placement.mrad.{i}"]))
    return out


def _rows_from_station(path: Path, n: int) -> list[tuple]:
    """Captures on the opened (simulated) station itself: its twin is the true assembly, its analysis the records'."""
    from sofast_station.config import load_config
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import inspect

    station = open_station(load_config(path))
    rng = np.random.default_rng(4)
    nominal = station.twin
    out = []
    try:
        for i in range(n):
            mrad = (*(float(v) for v in rng.uniform(-5, 5, 2)), float(rng.uniform(-1, 1)))
            mm = tuple(float(v) for v in rng.uniform(-1, 1, 3))
            twin = nominal.with_facet(dataclasses.replace(nominal.facet, placement_mm=mm, placement_mrad=mrad))
            station.twin = station.camera.twin = station.range_finder.twin = twin
            rec = inspect(station, f"TILT-{i}")
            t = rec["truth"]
            for ax, j in (("x", 0), ("y", 1)):
                out.append((ax, rec["placement"]["mrad"][j] - mrad[j], rec["placement_U"]["mrad"][j],
                            rec["optical_tilt_mrad"][ax] - t["optical_tilt_mrad"][ax],
                            rec["optical_tilt_mrad"][ax] - mrad[j], rec["optical_tilt_mrad_U"][ax],
                            t["optical_tilt_mrad"][ax] - mrad[j]))
    finally:
        station.close()
    return out


def _report(name: str, rows: list[tuple]) -> None:
    print(f"\n== {name}: {len(rows) // 2} captures")
    for ax in "xy":
        r = np.array([x[1:] for x in rows if x[0] == ax], float)
        rms = np.sqrt(np.mean(r[:, 0] ** 2))
        print(f"  about {ax}: corners {np.abs(r[:, 0]).max():.3f} mrad at worst (RMS {rms:.3f}), "
              f"their U {np.median(r[:, 1]):.2f} (median), covered {int(np.sum(np.abs(r[:, 0]) <= r[:, 1]))}/{len(r)}")
        print(f"           slopes {np.abs(r[:, 3]).max():.4f} mrad at worst from the true placement (RMS "
              f"{np.sqrt(np.mean(r[:, 3] ** 2)):.4f}), {np.abs(r[:, 2]).max():.4f} from the truth's optical tilt; "
              f"U {np.median(r[:, 4]):.3f} (median), covered {int(np.sum(np.abs(r[:, 3]) <= r[:, 4]))}/{len(r)}")
        print(f"           the facet's own boresight (optical less mechanical tilt): {np.abs(r[:, 5]).max():.4f} mrad "
              "at most")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--captures", type=int, default=8)
    p.add_argument("--gore", action="store_true", help="also the shipped gore station at 1600 x 1200 (slow)")
    p.add_argument("--no-commission", action="store_true", help="skip the commissioned station (minutes)")
    p.add_argument("--quick", action="store_true", help="2 captures on the ideal small station (the tests)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        os.environ["SOFAST_DATA_DIR"] = str(tmp / "data")
        from sofast_station.config import load_config

        small = load_config(_small(tmp))
        t = time.perf_counter()
        _report("ideal 400 x 300 dish", _rows_from_repeats(small, 2 if args.quick else args.captures, False))
        if args.quick:
            return 0
        _report("400 x 300 dish, the twin's geometry drawn within [uncertainty]",
                _rows_from_repeats(small, args.captures, True))
        if not args.no_commission:
            from sofast_station.station.commissioning import commission
            from tests.calibrate.commission_stations import draw_assembly, station_file

            path = station_file(tmp / "commissioned", draw_assembly(1))
            os.environ["SOFAST_DATA_DIR"] = str(tmp / "commissioned" / "data")
            steps, verdict = commission(path)
            print(f"\ncommissioned ({verdict}): " + "; ".join(s.data.get("headline", s.verdict) for s in steps))
            cfg = load_config(path)
            print(f"fixture rotation u (k = 1) in force: {cfg.uncertainty.fixture_rotation_mrad} mrad")
            _report("400 x 300 dish, a drawn assembly commissioned, measured with its records",
                    _rows_from_station(path, args.captures))
        if args.gore:
            os.environ["SOFAST_DATA_DIR"] = str(tmp / "gore")
            _report("gore station 1600 x 1200, ideal", _rows_from_repeats(
                load_config(ROOT / "fixtures/stations/gore.toml"), args.captures, False))
        print(f"\n({time.perf_counter() - t:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
