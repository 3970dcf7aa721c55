"""Benchmark: ``sofast-station calibrate camera`` on ten 2 MP photographs, the whole command as a user waits for it.

    .venv/bin/python benchmarks/camera_calibration.py                 # NSTTF Basler, 1626 x 1236, 3 counted runs
    .venv/bin/python benchmarks/camera_calibration.py --camera wide   # wide-angle lens, 1920 x 1080
    .venv/bin/python benchmarks/camera_calibration.py --quick         # 5 half-size photographs, 1 run (the tests)

Setup (not timed): ten photographs of the reported board (18 x 23 inner corners, 25 mm squares) rendered by
tests/calibrate/photos.py through the camera's true lens: eight whole views tilted up to 45 degrees, near
and far, and two reaching past the image's edge, with a lamp's gradient, vignetting, a slight blur, noise,
two of them JPEG; written to a temporary folder. Then the command runs as a fresh process
(``python -m sofast_station calibrate camera IMAGES... --json``), once uncounted (the operating system's
file cache filled), then ``--runs`` times: its wall time (median and range), CPU time (user + system of the
finished child, ``os.wait4``) and peak memory. Then, in this process, the search alone
(:func:`~sofast_station.calibrate.camera.judge_images`: reading and searching the ten files) with one thread
and with the machine's cores, so the thread pool's gain shows (``--quick``: one run, counted, and no
search alone). The machine's load average before and after
(it may be shared). What the command found is printed against the truth. Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))              # run from a checkout, installed or not
sys.path.insert(0, str(ROOT / "benchmarks"))

from commands import load, run_process, small_station  # noqa: E402  (after the path is set)


def photographs(folder: Path, camera, count: int) -> list[Path]:
    """*count* photographs (``count - 2`` whole views, 2 partly out of view) written to *folder*."""
    import cv2
    import numpy as np

    from tests.calibrate.photos import LAB_BOARD, Look, board_pose, render

    rng = np.random.default_rng(2024)
    files = []
    while len(files) < count:
        partial = len(files) >= count - 2
        if partial:                         # reaching past the left or the bottom edge
            centre, roll = ((0.12, 0.5) if len(files) % 2 else (0.5, 0.88)), rng.uniform(-8, 8)
        else:                               # anywhere in the middle, the board upright or turned
            centre, roll = tuple(rng.uniform(0.35, 0.65, 2)), rng.uniform(-8, 8) + 90 * int(rng.integers(0, 2))
        pose = board_pose(camera, LAB_BOARD, rng, tilt_deg=tuple(rng.uniform(-45, 45, 2)), fill=rng.uniform(0.4, 0.95),
                          centre=centre, roll_deg=roll, partial=(0.5, 0.85) if partial else None)
        if pose is None:
            continue
        look = replace(Look(samples=4), light_angle_deg=rng.uniform(0, 360), light_gradient=rng.uniform(0.3, 1.0),
                       blur_px=rng.uniform(0.7, 1.2))
        image = render(camera, LAB_BOARD, pose, look, rng)
        if len(files) in (2, 5):
            path = folder / f"DSC{len(files):04d}.jpg"
            cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        else:
            path = folder / f"DSC{len(files):04d}.png"
            cv2.imwrite(str(path), image)
        files.append(path)
    return files


def search_alone(files: list[Path], workers: int, repeats: int) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds (this process, all threads) of :func:`judge_images` on *files* with *workers*
    threads, *repeats* times."""
    from sofast_station.calibrate.camera import BoardSpec, judge_images

    board = BoardSpec("chessboard", 19, 24, 0.025)
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        judge_images([(p.name, p) for p in files], board, workers=workers, progress=lambda line: None)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return wall, cpu


def spread(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} s median ({min(values):.2f} - {max(values):.2f})"


def searched(times: tuple[list[float], list[float]]) -> str:
    return f"wall {spread(times[0])}, cpu {statistics.median(times[1]):.2f} s"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--camera", choices=("basler", "wide"), default="basler",
                   help="the NSTTF Basler's long lens (1626 x 1236) or a wide-angle lens (1920 x 1080)")
    p.add_argument("--images", type=int, default=10)
    p.add_argument("--runs", type=int, default=3, help="counted runs of the command")
    p.add_argument("--quick", action="store_true",
                   help="5 half-size photographs, 1 run, no search alone (the test suite does this)")
    p.add_argument("--render-into", default=None, help=argparse.SUPPRESS)     # the setup's own process
    args = p.parse_args(argv)

    from tests.calibrate.photos import NSTTF_BASLER, WIDE_ANGLE

    camera = NSTTF_BASLER if args.camera == "basler" else WIDE_ANGLE
    if args.quick:
        camera, args.images, args.runs = camera.scaled(0.5), 5, 1
    if args.render_into:
        print(json.dumps([str(f) for f in photographs(Path(args.render_into), camera, args.images)]))
        return 0
    tmp = Path(tempfile.mkdtemp(prefix="sofast-camera-"))
    try:
        print(f"calibrate camera: {args.images} photographs of an 18 x 23 inner-corner board, {camera.width_px} x "
              f"{camera.height_px} px ({args.camera}); {args.runs} counted run(s)"
              f"{'' if args.quick else ' after 1 uncounted'}; "
              f"{os.cpu_count()} CPU(s); python {sys.version.split()[0]}", flush=True)
        t = time.perf_counter()
        # rendered in a process of its own: Linux keeps a process's peak memory across exec, so the command,
        # started from a parent that had rendered, would report the renderer's peak as its own
        render = [sys.executable, __file__, "--render-into", str(tmp), "--camera", args.camera, "--images",
                  str(args.images)] + (["--quick"] if args.quick else [])
        setup = subprocess.run(render, stdout=subprocess.PIPE, text=True, check=True)
        files = [Path(f) for f in json.loads(setup.stdout.strip().splitlines()[-1])]
        print(f"setup: rendered in {time.perf_counter() - t:.1f} s (not counted)", flush=True)
        env = {**os.environ, "SOFAST_DATA_DIR": str(tmp / "data")}
        cmd = [sys.executable, "-m", "sofast_station", "calibrate", "camera", *map(str, files), "--squares", "19x24",
               "--square-mm", "25", "--config", small_station(tmp / "station.toml"), "--json"]
        cmd += ["--k3"] if args.camera == "wide" else []        # a wide-angle lens needs k3
        print(f"load average before: {load()}", flush=True)
        first = tmp / "first.log"
        runs = [run_process(cmd, env, tmp, first if k == 0 else tmp / "command.log")
                for k in range(args.runs + (0 if args.quick else 1))]
        log = first.read_text()
        if runs[0].code != 0:
            print(log[-3000:])
            raise SystemExit("the command failed")
        runs = runs if args.quick else runs[1:]          # the first fills the file cache: not counted
        wall, cpu = [r.wall_s for r in runs], [r.cpu_s for r in runs]
        print(f"whole command: wall {spread(wall)}, cpu {statistics.median(cpu):.2f} s median, peak memory "
              f"{statistics.median([r.peak_mb for r in runs]):.0f} MB; exit codes {sorted({r.code for r in runs})}")
        if not args.quick:
            threads = os.cpu_count() or 1
            one, many = search_alone(files, 1, args.runs), search_alone(files, threads, args.runs)
            print(f"search alone (read and search {len(files)} files, in this process): 1 thread {searched(one)}; "
                  f"{threads} threads {searched(many)}")
        # the log holds the progress lines (stderr), then the JSON summary (stdout) from a line "{" on
        out = json.loads(log[log.index("\n{\n") + 1:])
        k, std = out["camera"]["matrix"], out["std_intrinsics"]
        used = sum(i["accepted"] for i in out["images"])
        parts = sum(bool(i.get("partial")) for i in out["images"] if i["accepted"])
        print(f"found: {used} of {len(files)} images used ({parts} partly out of view), RMS {out['rms_px']:.3f} px, "
              f"verdict {out['verdict']}; fx {k[0][0]:.1f} +- {std['fx']:.1f} px (truth {camera.fx:.1f}), principal "
              f"point ({k[0][2]:.1f}, {k[1][2]:.1f}) +- ({std['cx']:.1f}, {std['cy']:.1f}) px (truth {camera.cx:.1f}, "
              f"{camera.cy:.1f})")
        for image in out["images"]:
            if not image["accepted"]:
                print(f"  rejected {Path(image['name']).name}: {image['reason']}")
        print(f"load average after: {load()}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
