"""Benchmark: the production cycle, trigger -> robot release, stage by stage, over 20 facets.

    .venv/bin/python benchmarks/cycle.py               # default full-resolution station, 20 facets
    .venv/bin/python benchmarks/cycle.py --quick       # the test suite's smoke run: 3 facets
    .venv/bin/python benchmarks/cycle.py --config fixtures/stations/heliostat.toml            # the fringes ...
    .venv/bin/python benchmarks/cycle.py --config fixtures/stations/heliostat.toml --fixed    # ... and a dot grid

So that the figure is what real hardware would see, the camera replays one capture rendered by the
digital twin beforehand (its render time is reported separately), waiting per frame for a modelled
display settle (``--settle-frames`` refreshes at ``--refresh-hz``) plus the exposure
(``--exposure-frames`` refreshes). Everything else is the station's real loop: busy, capture,
four-step check, crop, analysis in the worker process, verdict, journal (SQLite, synchronous), spool
of every 5th facet's frames, answer; the archiver writes workbook and dumps in its own process, off the
critical path. Prints, for each stage, the first facet on its own (after the worker's warm-up capture)
and the median and worst of the others; then runs the same facets again with a two-worker
``sofast-station batch`` re-analysing the first run's dumps beside the line (``--batch-workers``), to show
what a process engineer's batch costs the line. Nothing is asserted.

``--fixed`` measures every facet by the fixed-pattern method instead (a recipe of ``method = "fixed"``,
``fixed = { spacing_px = 12 }``, named by every request: one dot frame per facet; issue 42 item 6 asks its
whole cycle to take at most half the fringes'), on a station whose layout allows it (the heliostat's).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class NullDisplay:
    """The display is modelled by the replay camera's per-frame delay."""

    def show(self, pattern) -> None:
        pass

    def close(self) -> None:
        pass


class FixedRangeFinder:
    def __init__(self, distance_m: float):
        self.distance_m = distance_m

    def measure(self) -> float:
        return self.distance_m


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default=str(ROOT / "station.toml"))
    p.add_argument("--facets", type=int, default=20)
    p.add_argument("--refresh-hz", type=float, default=60.0)
    p.add_argument("--settle-frames", type=float, default=2.0, help="display refreshes before the exposure")
    p.add_argument("--exposure-frames", type=float, default=1.0, help="exposure, in display refreshes")
    p.add_argument("--batch-workers", type=int, default=2,
                   help="then the same facets again with 'sofast-station batch --workers N' re-analysing the first "
                        "run's dumps beside the line (0: skip)")
    p.add_argument("--quick", action="store_true", help="3 facets (the test suite's smoke run)")
    p.add_argument("--fixed", action="store_true",
                   help="the fixed-pattern method (one dot frame) instead of the fringes (a heliostat-like layout)")
    args = p.parse_args(argv)
    n = 3 if args.quick else args.facets
    import os
    os.environ.setdefault("SOFAST_DATA_DIR", tempfile.mkdtemp(prefix="cycle-bench-"))   # never the user's

    import logging
    logging.basicConfig(level=logging.WARNING)
    from sofast_station.calibrate.records import load_radiometric
    from sofast_station.config import load_config
    from sofast_station.devices.cameras.replay import ReplayCamera
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture
    from sofast_station.station.opened import Station
    from sofast_station.station.service import Service

    cfg = load_config(args.config)
    cam = cfg.geometry.camera
    recipes = {}
    if args.fixed:
        from sofast_station.job import job_for
        from sofast_station.recipes import recipes_from_config

        recipes = {"dots": {"method": "fixed", "fixed": {"spacing_px": 12.0}}}
        job = job_for(recipes_from_config(dataclasses.replace(cfg, raw=dict(cfg.raw, recipes=recipes)))["dots"], cfg)
    t = time.perf_counter()
    twin_station = open_station(cfg, seed=1)
    t_trace = time.perf_counter() - t
    try:
        t = time.perf_counter()
        if args.fixed:                     # the dot grid the recipe's job shows, through the twin's display
            import numpy as np
            shots = []
            for pattern in job.shows(cfg.fringes).patterns():
                twin_station.display.show(pattern)
                shots.append(twin_station.camera.grab())
            frames, distance = np.stack(shots), float(twin_station.range_finder.measure())
        else:
            frames, distance = capture(twin_station)
        t_render = time.perf_counter() - t
    finally:
        twin_station.close()
    frame_delay = (args.settle_frames + args.exposure_frames) / args.refresh_hz
    print(f"station: {cfg.name}; camera {cam.width_px} x {cam.height_px}; {n} facets")
    print(f"digital twin (not in the cycle): trace {t_trace:.2f} s, render and image one capture {t_render:.2f} s")
    print(f"modelled per frame: {args.settle_frames:g} + {args.exposure_frames:g} refreshes at {args.refresh_hz:g} Hz "
          f"= {1000 * frame_delay:.0f} ms, {frames.shape[0]} frames = {frames.shape[0] * frame_delay:.2f} s")

    def line(data: Path, dump_every: int):
        """Run the real service with replay hardware on *data* for n facets: (outcomes, start s, close s)."""
        raw = dict(cfg.raw, run={"dump_every_n": dump_every, **({"warmup": False} if args.fixed else {})},
                   archive={"workbook_interval_s": 5.0}, **({"recipes": recipes} if recipes else {}))
        bench_cfg = dataclasses.replace(cfg, data_dir=data, raw=raw, simulation={})
        lines: list[str] = []
        service = Service.__new__(Service)           # the real service, with replay hardware
        devices = Station(config=bench_cfg, display=NullDisplay(),
                          camera=ReplayCamera(frames, frame_delay_s=frame_delay, loop=True),
                          range_finder=FixedRangeFinder(distance),
                          radiometric=load_radiometric(cfg.radiometric_path), twin=None)
        t = time.perf_counter()
        requests = n
        if args.fixed:                     # every facet by the fixed recipe (the warm-up's default is the fringes)
            from sofast_station.devices.protocols import FacetRequest
            requests = [FacetRequest(f"DOTS-{i + 1:04d}", recipe="dots") for i in range(n)]
        Service.__init__(service, bench_cfg, simulated_facets=requests, console=lines.append, station=devices)
        t_start = time.perf_counter() - t
        try:
            outcomes = service.runner.run()
        finally:
            t = time.perf_counter()
            service.close()
            t_close = time.perf_counter() - t
        return outcomes, t_start, t_close

    def table(outcomes, title: str) -> None:
        answers = {}
        for o in outcomes:
            answers[o.answer] = answers.get(o.answer, 0) + 1
        print(f"{title}: answers " + ", ".join(f"{v} {k}" for k, v in sorted(answers.items())))
        rows = []
        for o in outcomes:
            ts = o.record.get("timings_s", {})
            rows.append({"capture": ts.get("capture", float("nan")), "analysis": ts.get("analysis", float("nan")),
                         "until journal": ts.get("until_journal", float("nan")), "trigger -> release": o.release_s})
        # The first facet is reported on its own: the median of the others is the steady state.
        print("seconds per facet:     first   median   worst   (median and worst of facets 2..n)")
        for key in rows[0]:
            rest = [r[key] for r in rows[1:]] or [rows[0][key]]
            print(f"  {key:<20} {rows[0][key]:6.3f} {statistics.median(rest):8.3f} {max(rest):7.3f}")

    with tempfile.TemporaryDirectory() as tmp:
        outcomes, t_start, t_close = line(Path(tmp) / "alone", max(1, min(5, n // 4)))
        print(f"station start (worker process and its warm-up capture, archiver process): {t_start:.2f} s; "
              f"shutdown with archive drained: {t_close:.2f} s")
        table(outcomes, "the station alone")
        if args.batch_workers:
            import os
            import subprocess
            dumps = sorted(str(p) for p in (Path(tmp) / "alone" / "dumps").rglob("*.h5"))
            stop = [False]
            runs = [0]
            procs = []

            def batch_loop():
                # re-analysis beside the line, as the process engineer would run it (its own priority)
                while not stop[0]:
                    out = Path(tmp) / f"batch-{runs[0]}"
                    proc = subprocess.Popen([sys.executable, "-m", "sofast_station", "batch", *dumps, "--out", str(out),
                                             "--workers", str(args.batch_workers), "--no-progress"],
                                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
                    procs.append(proc)
                    proc.wait()
                    runs[0] += 1
            import threading
            thread = threading.Thread(target=batch_loop, daemon=True)
            thread.start()
            time.sleep(3.0)                          # the batch is under way before the first facet
            try:
                beside, _, _ = line(Path(tmp) / "beside", max(1, min(5, n // 4)))
            finally:
                stop[0] = True
                for proc in procs:
                    if proc.poll() is None:
                        proc.terminate()
                thread.join(60)
            table(beside, f"with a {args.batch_workers}-worker batch beside it ({len(dumps)} dumps, "
                          f"{runs[0]} batch run(s) finished meanwhile, batch at its default lower priority)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
