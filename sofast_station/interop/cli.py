"""``sofast-station import-opencsp``: analyse an OpenCSP SOFAST fringe measurement with our pipeline."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..commands import add_command, json_safe


def register(subparsers) -> None:
    """Add ``import-opencsp`` to the ``sofast-station`` *subparsers*."""
    p = add_command(
        subparsers, "import-opencsp", help="analyse a SOFAST fringe measurement from Sandia's OpenCSP",
        description="""
            Read a fringe measurement in the HDF5 files of Sandia's OpenCSP (measurement, camera, display
            shape, spatial orientation, image calibration, facet definition) and analyse it with this
            station's pipeline. --test-data names a folder in the layout of OpenCSP's test data (the facet
            shipped in fixtures/opencsp/test_data); each file can also be given on its own, and overrides
            the folder's. --compare also analyses OpenCSP's own pixel selection and prints both results
            (docs/opencsp.md).""")
    p.add_argument("--test-data", default=None, metavar="DIR",
                   help="a folder in the layout of OpenCSP's opencsp/test/data (sets the six files below)")
    for name, what in (("measurement", "MeasurementSofastFringe HDF5"), ("camera", "Camera HDF5"),
                       ("display", "DisplayShape HDF5"), ("orientation", "SpatialOrientation HDF5"),
                       ("calibration", "ImageCalibration HDF5"), ("facet", "facet definition JSON")):
        p.add_argument(f"--{name}", default=None, metavar="FILE", help=f"{what} (default: from --test-data)")
    p.add_argument("--focal-length", type=float, default=100.0, metavar="M",
                   help="design focal length, metres (OpenCSP keeps it with the processing, not the files)")
    p.add_argument("--robust", action="store_true", help="bisquare-weighted (robust) slope fits, like OpenCSP's "
                   "robust_least_squares")
    p.add_argument("--compare", default=None, metavar="FILE",
                   help="OpenCSP's own result (its data.h5): also analyse on its pixels and print both "
                        "(default: no comparison)")
    p.add_argument("--json", action="store_true", help="print one JSON object and nothing else on stdout")
    p.set_defaults(func=cmd_import_opencsp)


def cmd_import_opencsp(args) -> int:
    from ..errors import ConfigError
    from ..precompute import prepare_analysis_process
    from .opencsp import opencsp_test_data_paths, read_opencsp, read_opencsp_result

    paths = opencsp_test_data_paths(Path(args.test_data)) if args.test_data else {}
    for key in ("measurement", "camera", "display", "orientation", "calibration", "facet"):
        if getattr(args, key):
            paths[key] = Path(getattr(args, key))
        if key not in paths:
            raise ConfigError(f"import-opencsp needs --{key} (or --test-data with OpenCSP's folder layout)")
    m = read_opencsp(**paths, focal_length_m=args.focal_length)
    prepare_analysis_process()      # as the station's worker: memory reused, kernels loaded first
    a = m.analyse(robust=args.robust)
    fig = a.figures
    keys = ("focal_length_x_m", "focal_length_y_m", "twist_mrad_per_m", "twist_e1_mrad_per_m",
            "twist_e2_mrad_per_m", "slope_rms_mrad", "n_points", "boresight_mrad", "subsample_fit")
    out = {"facet": m.name, "measured": m.date, "robust": args.robust, **{k: fig[k] for k in keys},
           "assumptions": list(m.assumptions)}
    # What the facet does with sunlight: default [optics] (pillbox sun, target at the design focal length);
    # 'report flux --opencsp' draws the map and takes other conditions.
    from ..optics import OpticsSettings
    from ..station.optics import analysis_optics
    out["optics"] = analysis_optics(a, m.design, OpticsSettings()).figures
    if args.compare:
        ref = read_opencsp_result(Path(args.compare))
        same = m.analyse(robust=ref.robust, pixel_mask=ref.mask).figures["subsample_fit"]
        out["opencsp"] = {"file": args.compare, "robust": ref.robust, "focal_length_x_m": ref.focal_length_x_m,
                          "focal_length_y_m": ref.focal_length_y_m, "n_points": int(ref.mask.sum()),
                          "ours_on_its_pixels": same}
    out = json_safe(out)
    if args.json:
        json.dump(out, sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    print(f"OpenCSP measurement {out['facet']} ({out['measured']}), {out['n_points']} points"
          f"{', robust fit' if args.robust else ''}")
    print("  assumed (OpenCSP's files do not say):" + "".join(f"\n    - {a}" for a in out["assumptions"]))
    print(f"  focal length x {out['focal_length_x_m']:.3f} m, y {out['focal_length_y_m']:.3f} m; twist "
          f"{out['twist_mrad_per_m']:.4f} mrad/m (E1 {out['twist_e1_mrad_per_m']:.4f}, E2 "
          f"{out['twist_e2_mrad_per_m']:.4f})")
    for model, r in out["slope_rms_mrad"].items():
        print(f"  slope error RMS vs {model:<12} x {r['x']:.3f}  y {r['y']:.3f}  magnitude {r['magnitude']:.3f} mrad")
    o = out["optics"]
    print(f"  optics (pillbox sun, target at {o['conditions']['slant_range_m']:g} m, aperture radius "
          f"{o['conditions']['aperture']['radius_m']:.3f} m): intercept {o['intercept']:.4f}, 90 % spot radius "
          f"{o['spot_radius_m']:.3f} m ({o['spot_radius_mrad']:.2f} mrad; design {o['design']['spot_radius_m']:.3f} m), "
          f"centroid {o['centroid_offset_mrad']['magnitude']:.3f} mrad off aim")
    if "opencsp" in out:
        o = out["opencsp"]
        s = o["ours_on_its_pixels"]
        print(f"  OpenCSP ({'robust' if o['robust'] else 'plain'} fit on every 10th of its {o['n_points']} pixels): "
              f"f_x {o['focal_length_x_m']:.3f} m, f_y {o['focal_length_y_m']:.3f} m; ours on the same pixels: "
              f"f_x {s['focal_length_x_m']:.3f} m ({100 * (s['focal_length_x_m'] / o['focal_length_x_m'] - 1):+.2f} %), "
              f"f_y {s['focal_length_y_m']:.3f} m ({100 * (s['focal_length_y_m'] / o['focal_length_y_m'] - 1):+.2f} %)")
    return 0
