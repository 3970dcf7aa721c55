"""OpenCSP's own SOFAST processing of one of its test datasets: the other side of ``vs_opencsp.py``.

Run with the Python of an environment where OpenCSP is installed (not this repository's), for example

    /path/to/opencsp-venv/bin/python benchmarks/opencsp_process.py fixtures/opencsp/test_data --dataset robust

It does what OpenCSP's examples (``example/sofast_fringe/example_process_single_facet.py``,
``example_process_undefined_shape.py``, ``example_process_facet_ensemble.py``) and its integration tests do:
load the camera, display shape, spatial orientation, measurement, image calibration and (for a facet or an
ensemble) the facet and ensemble definitions; calibrate the fringe images; ``ProcessSofastFringe`` (with the
parameters stored in OpenCSP's expected result where there is one); the dataset's surface
(``Surface2DParabolic((100, 100), robust, downsample=10)``, or ``Surface2DPlano``); and
``process_optic_singlefacet``, ``process_optic_undefined`` or ``process_optic_multifacet``. Then it prints f x,
f y of the first facet (f = 1 / (4 a) of z = a x^2 + ...; none for a plane), the number of surface points and
the slope residual against the fit, and exits: no plots, no files. On OpenCSP's own data it reproduces
OpenCSP's stored coefficients (within 6e-11 at commit 356e3a9 for ``robust``; ``--compare`` prints the
difference where a stored result exists).

Datasets (``--dataset``): robust, plain, rectangular, distorted_3d, plano, undefined (the single facet's
capture), multi_facet (``measurement_ensemble.h5``, the lab heliostat of 24 facets), split_facet (the single
facet as two halves).

DATA is a folder in the layout of OpenCSP's ``opencsp/test/data`` (``fixtures/opencsp/test_data``, or an
upsampled copy made by ``benchmarks/analysis.py``'s ``upsample_opencsp``).
"""

import argparse
import os
import sys
import time

T0 = time.perf_counter()

try:
    import numpy as np
    from opencsp.app.sofast.lib.DefinitionEnsemble import DefinitionEnsemble
    from opencsp.app.sofast.lib.DefinitionFacet import DefinitionFacet
    from opencsp.app.sofast.lib.DisplayShape import DisplayShape
    from opencsp.app.sofast.lib.ImageCalibrationScaling import ImageCalibrationScaling
    from opencsp.app.sofast.lib.MeasurementSofastFringe import MeasurementSofastFringe
    from opencsp.app.sofast.lib.ParamsSofastFringe import ParamsSofastFringe
    from opencsp.app.sofast.lib.ProcessSofastFringe import ProcessSofastFringe
    from opencsp.app.sofast.lib.SpatialOrientation import SpatialOrientation
    from opencsp.common.lib.camera.Camera import Camera
    from opencsp.common.lib.deflectometry.Surface2DParabolic import Surface2DParabolic
    from opencsp.common.lib.deflectometry.Surface2DPlano import Surface2DPlano
except ImportError as exc:          # vs_opencsp.py reads this line: exit code 3
    print(f"OpenCSP is not importable by {sys.executable}: {exc}", file=sys.stderr)
    sys.exit(3)


#: dataset -> (display file, measurement, facet file, ensemble file or None, expected result or None, robust,
#: surface kind, optic kind)
DATASETS = {
    "robust": ("display_distorted_2d.h5", "measurement_facet.h5", "Facet_NSTTF.json", None, "data.h5", True,
               "parabolic", "single"),
    "plain": ("display_distorted_2d.h5", "measurement_facet.h5", "Facet_NSTTF.json", None, "data_no_ls.h5", False,
              "parabolic", "single"),
    "rectangular": ("display_rectangular.h5", "measurement_facet.h5", "Facet_NSTTF.json", None, "data_rectangular.h5",
                    True, "parabolic", "single"),
    "distorted_3d": ("display_distorted_3d.h5", "measurement_facet.h5", "Facet_NSTTF.json", None,
                     "data_distorted_3d.h5", True, "parabolic", "single"),
    "plano": ("display_distorted_2d.h5", "measurement_facet.h5", "Facet_NSTTF.json", None, "data_plano.h5", True,
              "plano", "single"),
    "undefined": ("display_distorted_2d.h5", "measurement_facet.h5", None, None, None, False, "parabolic",
                  "undefined"),
    "multi_facet": ("display_distorted_2d.h5", "measurement_ensemble.h5", "Facet_lab_6x4.json",
                    "Ensemble_lab_6x4.json", None, False, "parabolic", "multi"),
    "split_facet": ("display_distorted_2d.h5", "measurement_facet.h5", "Facet_split_NSTTF.json",
                    "Ensemble_split_NSTTF_facet.json", None, False, "parabolic", "multi"),
}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data", help="folder in the layout of OpenCSP's opencsp/test/data")
    p.add_argument("--dataset", default="robust", choices=sorted(DATASETS), help="which processing (default robust)")
    p.add_argument("--plain", action="store_true", help="the same as --dataset plain (kept for older scripts)")
    p.add_argument("--compare", action="store_true", help="also print OpenCSP's stored expected result")
    a = p.parse_args()
    name = "plain" if a.plain else a.dataset
    display_file, meas_file, facet_file, ens_file, expected_file, robust, kind, optic = DATASETS[name]
    j = os.path.join
    d = a.data
    common = j(d, "sofast_common")
    expected = None if expected_file is None else j(d, "sofast_fringe/data_expected_facet", expected_file)
    t_imports = time.perf_counter()
    camera = Camera.load_from_hdf(j(common, "camera_sofast_downsampled.h5"))
    display = DisplayShape.load_from_hdf(j(common, display_file))
    orientation = SpatialOrientation.load_from_hdf(j(common, "spatial_orientation.h5"))
    measurement = MeasurementSofastFringe.load_from_hdf(j(d, "sofast_fringe/data_measurement", meas_file))
    calibration = ImageCalibrationScaling.load_from_hdf(j(d, "sofast_fringe/data_measurement/image_calibration.h5"))
    params = ParamsSofastFringe.load_from_hdf(expected, "DataSofastInput/") if expected else ParamsSofastFringe()

    def surface():
        if kind == "plano":
            return Surface2DPlano(robust_least_squares=robust, downsample=10)
        return Surface2DParabolic(initial_focal_lengths_xy=(100.0, 100.0), robust_least_squares=robust, downsample=10)
    t_loaded = time.perf_counter()
    measurement.calibrate_fringe_images(calibration)
    sofast = ProcessSofastFringe(measurement, orientation, camera, display)
    sofast.params = params
    if optic == "single":
        sofast.process_optic_singlefacet(DefinitionFacet.load_from_json(j(common, facet_file)), surface())
    elif optic == "undefined":
        sofast.process_optic_undefined(surface())
    else:
        ensemble = DefinitionEnsemble.load_from_json(j(common, ens_file))
        n = ensemble.num_facets
        facets = [DefinitionFacet.load_from_json(j(common, facet_file))] * n
        sofast.process_optic_multifacet(facets, ensemble, [surface() for _ in range(n)])
    t_done = time.perf_counter()

    calc = sofast.data_calculation_facet[0]
    c = np.asarray(calc.surf_coefs_facet, float)
    s = np.asarray(calc.slopes_facet_xy, float)
    x, y = np.asarray(calc.v_surf_points_facet.data, float)[:2]
    h, w = measurement.mask_images.shape[:2]
    print(f"OpenCSP ProcessSofastFringe ({name}: {optic} optic), {w} x {h} px, {'robust' if robust else 'plain'} "
          f"{kind} fit (downsample 10), {len(sofast.data_calculation_facet)} facet(s), {s.shape[1]} points in the "
          "first")

    def rms_mrad(r):
        return 1e3 * float(np.sqrt(np.mean(r ** 2)))

    if kind == "plano":                                    # z = c0 + c1 x + c2 y
        rx, ry = s[0] - c[1], s[1] - c[2]
        print("  f x none f y none (a plane)")
    else:                                                 # z = c0 + c1 x + c2 x^2 + c3 y + c4 x y + c5 y^2
        rx = s[0] - (c[1] + 2 * c[2] * x + c[4] * y)
        ry = s[1] - (c[3] + c[4] * x + 2 * c[5] * y)
        print(f"  f x {1 / 4 / c[2]:.3f} m   f y {1 / 4 / c[5]:.3f} m   xy coefficient {1e3 * c[4]:.4f} mrad/m")
    print(f"  slope RMS against the fit (all points) x {rms_mrad(rx):.4f}  y {rms_mrad(ry):.4f}  "
          f"magnitude {rms_mrad(np.hypot(rx, ry)):.4f} mrad")
    print(f"  time: imports {t_imports - T0:.2f} s, loading {t_loaded - t_imports:.2f} s, "
          f"processing {t_done - t_loaded:.2f} s")
    if a.compare and expected:
        import h5py

        with h5py.File(expected) as f:
            ce = f["DataSofastCalculation/facet/facet_000/SlopeSolverData/surf_coefs_facet"][()]
        print(f"  stored expected ({os.path.basename(expected)}): largest coefficient difference "
              f"{np.abs(ce - c).max():.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
