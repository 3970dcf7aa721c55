"""Benchmark: the analysis of one full-resolution capture, stage by stage, from each input path.

    .venv/bin/python benchmarks/analysis.py                      # twin capture, plain fit, 7 timed runs
    .venv/bin/python benchmarks/analysis.py --source dump --fit robust
    .venv/bin/python benchmarks/analysis.py --source all --fit both    # every path, each fit (6 processes)
    .venv/bin/python benchmarks/analysis.py --quick              # small station, 1 run (the test suite does this)

Sources (what a user of each path runs):

* ``twin``: a noisy capture of the simulated station, analysed as the station's analysis worker does it
  (per-camera data precomputed when the worker starts);
* ``dump``: the same kind of capture written to an HDF5 data dump and re-analysed by ``reprocess``
  (:func:`~sofast_station.reanalysis.reprocess.reprocess_content` on the dump read once);
* ``opencsp``: OpenCSP's real measured facet (``fixtures/opencsp``) upsampled ``--opencsp-scale`` times
  (8: 1624 x 1232 px; every frame resized bilinearly, the camera matrix scaled to match), written as
  OpenCSP files, read by our OpenCSP reader and analysed with its measured (distorted 2-D) screen shape,
  as ``import-opencsp`` does: with the uncertainty of an OpenCSP setup (docs/opencsp.md), its sensitivities
  computed in the cold run and reused after, as the command and the station's worker keep them.

Each (source, fit) runs in a fresh process, which analyses the capture repeatedly, as a long-running
process does facet after facet. The first analysis (cold: first calls into numpy and OpenCV, per-camera
caches filled) is reported on its own; the stage table is over the runs after it (steady state). Printed:
camera size, facet pixels, valid points, the median (min - max) wall time of every stage and of the
whole analysis, the process CPU time per analysis (both threads; less disturbed by other load on the
machine than wall time), the peak memory the analysis adds to the process (resident set from /proc,
peak reset after the inputs are loaded) and the machine's load average (``uptime``) before and after;
at the end a summary line per source and fit, with the robust fit's CPU time over the plain fit's.
Nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))          # run from a checkout, installed or not

_CHILD = r"""
import json, os, sys, time
import numpy as np

def rss_kb(field):
    for line in open("/proc/self/status"):
        if line.startswith(field):
            return int(line.split()[1])
    return 0

spec = json.loads(sys.argv[1])
source, robust, runs = spec["source"], spec["robust"], spec["runs"]


def keep_memory():
    try:
        from sofast_station.precompute import prepare_analysis_process
    except ImportError:                         # an older checkout
        try:
            from sofast_station.precompute import keep_freed_memory as prepare_analysis_process
        except ImportError:
            return
    prepare_analysis_process()


t = time.perf_counter()
if source == "twin":
    import dataclasses
    from sofast_station.config import load_config
    from sofast_station.measure.analysis import analyse
    cfg = load_config(spec["config"])
    d = np.load(spec["capture"])
    frames, distance = d["frames"], float(d["distance"])
    settings = dataclasses.replace(cfg.analysis, robust_fit=robust)
    try:                                        # what the station's analysis worker does when it starts
        from sofast_station.precompute import ray_table, warm_up
        warm_up(cfg.geometry.camera)
        rays = ray_table(cfg.geometry.camera)
    except ImportError:                         # an older checkout (before the per-camera ray table)
        from sofast_station.measure.camera import ray_grid
        rays = ray_grid(cfg.geometry.camera)
    cache = {}      # the uncertainty's sensitivities: computed in the cold run, reused after, as in the station
    def once():
        a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, settings, rays_cam=rays,
                    uncertainty=cfg.uncertainty, sensitivity_cache=cache)
        return a.figures, a.timings_s
elif source == "dump":
    import dataclasses
    keep_memory()                               # what `reprocess` and `batch` workers do when they start
    from sofast_station.archive.dumps import read_dump
    from sofast_station.reanalysis.reprocess import reprocess_content
    content = read_dump(spec["dump_robust" if robust else "dump"], load_frames=True)
    def once():
        res = reprocess_content(content)
        if res.analysis is None:
            raise SystemExit("the dump's analysis was refused: " + "; ".join(res.record.get("reasons", [])))
        return res.analysis.figures, res.analysis.timings_s
else:
    keep_memory()                               # what `import-opencsp` does
    from sofast_station.interop.opencsp import opencsp_test_data_paths, read_opencsp
    m = read_opencsp(**opencsp_test_data_paths(spec["opencsp"]))
    inputs = getattr(m, "uncertainty", None)      # None on an older checkout (no U for OpenCSP then)
    cache = {}      # as import-opencsp: the sensitivities computed in the cold run, reused after
    def once():
        a = (m.analyse(robust=robust) if inputs is None
             else m.analyse(robust=robust, uncertainty=inputs, sensitivity_cache=cache))
        return a.figures, a.timings_s
setup_s = time.perf_counter() - t
base = rss_kb("VmRSS:")
try:
    with open("/proc/self/clear_refs", "w") as fh:   # reset the peak (VmHWM) to the current RSS
        fh.write("5")
    reset = True
except OSError:
    reset = False
out = []
for i in range(runs + 1):
    t, c = time.perf_counter(), time.process_time()
    fig, stages = once()
    out.append({"total": time.perf_counter() - t, "cpu": time.process_time() - c, "stages": stages})
peak = rss_kb("VmHWM:")
print(json.dumps({"runs": out, "n_points": fig["n_points"], "facet_pixels": fig["facet_pixels"],
                  "f": [fig["focal_length_x_m"], fig["focal_length_y_m"]], "base_mb": base / 1024,
                  "peak_mb": peak / 1024, "peak_reset": reset, "setup_s": setup_s}))
"""


def _load() -> str:
    try:
        return Path("/proc/loadavg").read_text().split()[:3].__repr__()
    except OSError:
        return "unknown"


def _uptime() -> str:
    try:
        return subprocess.run(["uptime"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return f"load average {_load()}"


def _twin_capture(config: str):
    """A noisy capture of the simulated station (frames, distance) and the station's configuration."""
    from sofast_station.config import load_config
    from sofast_station.station.factory import open_station
    from sofast_station.station.inspection import capture

    cfg = load_config(config)
    t = time.perf_counter()
    station = open_station(cfg, seed=1)
    t_open = time.perf_counter() - t
    try:
        t = time.perf_counter()
        frames, distance = capture(station)
        t_capture = time.perf_counter() - t
    finally:
        station.close()
    print(f"setup (not part of the analysis): twin trace and renderer {t_open:.2f} s, simulated capture "
          f"{t_capture:.2f} s")
    return cfg, station, frames, distance


def prepare_twin(config: str, tmp: Path) -> dict:
    import numpy as np

    cfg, _, frames, distance = _twin_capture(config)
    path = tmp / "capture.npz"
    np.savez(path, frames=frames, distance=distance)
    cam = cfg.geometry.camera
    return {"capture": str(path), "config": config, "what": f"{cam.width_px} x {cam.height_px} pixels, facet "
            f"{cfg.design.name} ({cfg.name})"}


def prepare_dump(config: str, tmp: Path, fits, optics: bool = False) -> dict:
    """A twin capture, analysed once per fit, written as the station's data dumps (cropped frames, record,
    the analysis settings with that fit, the uncertainty's sensitivities the analysis kept), as a station
    configured for that fit writes them. *optics*: the record carries the optical figures, as the
    station's worker adds them (so ``reprocess`` traces them again, as it does a dump from the line);
    without, ``reprocess_content`` analyses like the other paths here, which trace no optics."""
    import dataclasses

    from sofast_station.archive.dumps import DumpContent, crop_to_facet, write_dump
    from sofast_station.measure.analysis import analyse
    from sofast_station.result.optical_figures import add_optics
    from sofast_station.result.record import build_record
    from sofast_station.result.verdict import judge

    cfg, station, frames, distance = _twin_capture(config)
    cropped, box, full = crop_to_facet(frames, cfg.analysis.mask_threshold_dn)
    spec = {}
    for fit in fits:
        settings = dataclasses.replace(cfg.analysis, robust_fit=fit == "robust")
        a = analyse(frames, cfg.fringes, cfg.geometry, cfg.design, distance, settings, uncertainty=cfg.uncertainty,
                    sensitivity_cache={})
        if optics:
            add_optics(a, cfg.design, cfg.optics)       # the optical figures, as the station's worker adds them
        record = build_record(station.record_head("BENCH-1"), figures=a.figures,
                              verdict=judge(a.figures, cfg.design, cfg.limits, cfg.quality), timings=dict(a.timings_s))
        content = DumpContent.from_station(station, cycle_id=f"bench-{fit}", record=record, frames_cropped=cropped,
                                           crop_box=box, full_shape=full, measured_distance_m=distance,
                                           analysis=settings, sensitivities=getattr(a, "sensitivities", None))
        path = tmp / f"bench-{fit}.h5"
        write_dump(path, content)
        spec["dump_robust" if fit == "robust" else "dump"] = str(path)
    cam = cfg.geometry.camera
    spec["what"] = (f"dump of {cam.width_px} x {cam.height_px} pixels, facet {cfg.design.name}, "
                    f"{path.stat().st_size / 1e6:.1f} MB")
    return spec


def upsample_opencsp(src: Path, dst: Path, scale: int) -> None:
    """OpenCSP's measured facet upsampled *scale* times into *dst*
    (:func:`sofast_station.interop.opencsp.upsample_test_data`)."""
    from sofast_station.interop.opencsp import upsample_test_data

    upsample_test_data(src, dst, scale)


def prepare_opencsp(scale: int, tmp: Path) -> dict:
    src = ROOT / "fixtures/opencsp/test_data"
    if scale == 1:
        return {"opencsp": str(src), "what": "OpenCSP's measured facet, native resolution"}
    dst = tmp / "opencsp"
    upsample_opencsp(src, dst, scale)
    return {"opencsp": str(dst), "what": f"OpenCSP's measured facet upsampled {scale}x (frames and intrinsics), "
            "distorted 2-D screen"}


def run_child(spec: dict) -> dict:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    out = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(spec)], capture_output=True, text=True, env=env)
    if out.returncode != 0:
        raise SystemExit(f"the analysis process failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


#: What each path does beyond the analysis (the "load inputs" time of its report is the once-per-input part).
BEYOND = {
    "twin": "the station's worker: the camera's ray table and the warm-up made when it starts (not per facet); "
            "the capture comes from the twin in memory",
    "dump": "reprocess: the dump read and checked once (its frames, record, settings, radiometric record, input "
            "uncertainties and sensitivities); per run the facet's job rebuilt from the dump and the frames "
            "restored to the camera's size; the dump's sensitivities reused (their hash matches)",
    "opencsp": "import-opencsp: OpenCSP's HDF5 files read and turned into our camera, screen shape (built once) "
               "and facet; its sensitivities computed in the cold run and reused",
}


def summary(rows: list) -> None:
    """One line per (source, fit): median CPU and wall time of the steady runs, memory added, each source's CPU
    over the twin path's (issue 46: every source within 1.2x) and the robust fit's CPU over the plain fit's of the
    same source (the issue's limit is 1.3); then what each path does beyond the analysis."""
    print("\nsummary (median of the steady runs; CPU is the process's, both threads)")
    print(f"  {'source':<8} {'fit':<7} {'cpu s':>6} {'wall s':>7} {'added MB':>9} {'cpu / twin':>11} "
          f"{'robust/plain cpu':>17}")
    cpu = {(src, fit): statistics.median(r["cpu"] for r in res["runs"][1:]) for src, fit, res in rows}
    for src, fit, res in rows:
        warm = res["runs"][1:]
        ratio = (f"{cpu[src, fit] / cpu[src, 'plain']:.2f}" if fit == "robust" and (src, "plain") in cpu
                 else "")
        vs_twin = f"{cpu[src, fit] / cpu['twin', fit]:.2f}" if ("twin", fit) in cpu else ""
        print(f"  {src:<8} {fit:<7} {cpu[src, fit]:6.3f} {statistics.median(r['total'] for r in warm):7.3f} "
              f"{res['peak_mb'] - res['base_mb']:9.0f} {vs_twin:>11} {ratio:>17}")
    print("\nbeyond the analysis (the 'load inputs' line of each source is its once-per-input part):")
    for src in dict.fromkeys(src for src, _, _ in rows):
        setup = statistics.median(res["setup_s"] for s_, _, res in rows if s_ == src)
        print(f"  {src:<8} load inputs {setup:.2f} s: {BEYOND[src]}")


def report(source: str, fit: str, what: str, result: dict) -> None:
    print(f"\n== source {source}, {fit} fit: {what}")
    print(f"facet pixels: {result['facet_pixels']:,}, valid pixels: {result['n_points']:,} "
          f"(f_x {result['f'][0]:.4f} m, f_y {result['f'][1]:.4f} m)")
    cold, warm = result["runs"][0], result["runs"][1:]
    print(f"load inputs {result['setup_s']:.2f} s; first analysis in a new process (cold): {cold['total']:.3f} s")
    if cold["stages"].get("uncertainty_sensitivities"):
        print(f"  of which the uncertainty's sensitivities {cold['stages']['uncertainty_sensitivities']:.2f} s "
              "(once per geometry and recipe; the 'uncertainty' row below is the per-facet cost)")
    print(f"analysis over {len(warm)} further run(s), seconds: median (min - max)")
    for s in cold["stages"]:
        v = [r["stages"].get(s, 0.0) for r in warm]
        print(f"  {s:<10} {statistics.median(v):7.3f}  ({min(v):.3f} - {max(v):.3f})")
    tot = [r["total"] for r in warm]
    cpu = [r["cpu"] for r in warm]
    print(f"  {'total':<10} {statistics.median(tot):7.3f}  ({min(tot):.3f} - {max(tot):.3f})")
    print(f"  {'cpu time':<10} {statistics.median(cpu):7.3f}  ({min(cpu):.3f} - {max(cpu):.3f})  "
          "(process CPU, both threads)")
    unc = [r["stages"]["uncertainty"] for r in warm if "uncertainty" in r["stages"]]
    if unc:
        print(f"per-facet uncertainty (noise propagation, corner-pose Monte Carlo, combination; sensitivities "
              f"cached): {statistics.median(unc):.3f} s, {100 * statistics.median(unc) / statistics.median(tot):.0f} % "
              "of the analysis")
    peak, base = result["peak_mb"], result["base_mb"]
    note = "" if result["peak_reset"] else " (peak could not be reset: includes loading)"
    print(f"memory: peak resident {peak:.0f} MB, of which the analysis added {peak - base:.0f} MB over the "
          f"{base:.0f} MB holding the inputs{note}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", choices=("twin", "dump", "opencsp", "all"), default="twin")
    p.add_argument("--fit", choices=("plain", "robust", "both"), default="plain")
    p.add_argument("--config", default=str(ROOT / "station.toml"), help="station for the twin and dump sources")
    p.add_argument("--opencsp-scale", type=int, default=8, help="upsampling of OpenCSP's measurement (1: native)")
    p.add_argument("--runs", type=int, default=7)
    p.add_argument("--quick", action="store_true", help="one run on the given (or small test) station")
    args = p.parse_args(argv)
    runs = 1 if args.quick else args.runs
    sources = ("twin", "dump", "opencsp") if args.source == "all" else (args.source,)
    fits = ("plain", "robust") if args.fit == "both" else (args.fit,)
    if args.opencsp_scale < 1:
        p.error("--opencsp-scale must be at least 1")

    print(f"before: {_uptime()}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for source in sources:
            if source == "twin":
                spec = prepare_twin(args.config, tmp)
            elif source == "dump":
                spec = prepare_dump(args.config, tmp, fits)
            else:
                spec = prepare_opencsp(args.opencsp_scale, tmp)
            what = spec.pop("what")
            if source == "twin":
                print(f"camera: {what.split(', facet')[0]}")     # the line the quick test looks for
            for fit in fits:
                result = run_child({**spec, "source": source, "robust": fit == "robust", "runs": runs})
                report(source, fit, what, result)
                rows.append((source, fit, result))
    summary(rows)
    print(f"\nafter: {_uptime()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
