"""OpenCSP's own single-facet SOFAST processing of one measurement: the other side of ``vs_opencsp.py``.

Run with the Python of an environment where OpenCSP is installed (not this repository's), for example

    /path/to/opencsp-venv/bin/python benchmarks/opencsp_process.py fixtures/opencsp/test_data

It does what OpenCSP's single-facet example (``example/sofast_fringe/example_process_single_facet.py``) and
its integration test (``opencsp/app/sofast/test/test_integration_single_facet.py``) do: load the camera,
display shape, spatial orientation, measurement, image calibration and facet definition; calibrate the
fringe images; ``ProcessSofastFringe`` with the parameters stored in OpenCSP's expected result
(``data.h5``); a robust parabolic surface (``Surface2DParabolic((100, 100), robust_least_squares=True,
downsample=10)``, as recorded there); ``process_optic_singlefacet``. Then it prints f x, f y (f = 1 / (4 a)
of z = a x^2 + ...), the number of surface points, the slope residual against the fitted parabola, and
exits: no plots, no files. On OpenCSP's own data it reproduces OpenCSP's stored coefficients (within
6e-11 at commit 356e3a9, ``--compare`` prints the difference).

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
    from opencsp.app.sofast.lib.DefinitionFacet import DefinitionFacet
    from opencsp.app.sofast.lib.DisplayShape import DisplayShape
    from opencsp.app.sofast.lib.ImageCalibrationScaling import ImageCalibrationScaling
    from opencsp.app.sofast.lib.MeasurementSofastFringe import MeasurementSofastFringe
    from opencsp.app.sofast.lib.ParamsSofastFringe import ParamsSofastFringe
    from opencsp.app.sofast.lib.ProcessSofastFringe import ProcessSofastFringe
    from opencsp.app.sofast.lib.SpatialOrientation import SpatialOrientation
    from opencsp.common.lib.camera.Camera import Camera
    from opencsp.common.lib.deflectometry.Surface2DParabolic import Surface2DParabolic
except ImportError as exc:          # vs_opencsp.py reads this line: exit code 3
    print(f"OpenCSP is not importable by {sys.executable}: {exc}", file=sys.stderr)
    sys.exit(3)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data", help="folder in the layout of OpenCSP's opencsp/test/data")
    p.add_argument("--plain", action="store_true", help="plain least squares (default: robust, as data.h5)")
    p.add_argument("--compare", action="store_true", help="also print OpenCSP's stored expected result")
    a = p.parse_args()
    j = os.path.join
    d = a.data
    expected = j(d, "sofast_fringe/data_expected_facet", "data_no_ls.h5" if a.plain else "data.h5")
    t_imports = time.perf_counter()
    camera = Camera.load_from_hdf(j(d, "sofast_common/camera_sofast_downsampled.h5"))
    display = DisplayShape.load_from_hdf(j(d, "sofast_common/display_distorted_2d.h5"))
    orientation = SpatialOrientation.load_from_hdf(j(d, "sofast_common/spatial_orientation.h5"))
    measurement = MeasurementSofastFringe.load_from_hdf(j(d, "sofast_fringe/data_measurement/measurement_facet.h5"))
    calibration = ImageCalibrationScaling.load_from_hdf(j(d, "sofast_fringe/data_measurement/image_calibration.h5"))
    facet = DefinitionFacet.load_from_json(j(d, "sofast_common/Facet_NSTTF.json"))
    params = ParamsSofastFringe.load_from_hdf(expected, "DataSofastInput/")
    surface = Surface2DParabolic(initial_focal_lengths_xy=(100.0, 100.0), robust_least_squares=not a.plain,
                                 downsample=10)
    t_loaded = time.perf_counter()
    measurement.calibrate_fringe_images(calibration)
    sofast = ProcessSofastFringe(measurement, orientation, camera, display)
    sofast.params = params
    sofast.process_optic_singlefacet(facet, surface)
    t_done = time.perf_counter()

    calc = sofast.data_calculation_facet[0]
    c = np.asarray(calc.surf_coefs_facet, float)             # z = c0 + c1 x + c2 x^2 + c3 y + c4 x y + c5 y^2
    s = np.asarray(calc.slopes_facet_xy, float)
    x, y = np.asarray(calc.v_surf_points_facet.data, float)[:2]
    rx = s[0] - (c[1] + 2 * c[2] * x + c[4] * y)
    ry = s[1] - (c[3] + c[4] * x + 2 * c[5] * y)

    def rms_mrad(r):
        return 1e3 * float(np.sqrt(np.mean(r ** 2)))

    h, w = measurement.mask_images.shape[:2]
    print(f"OpenCSP ProcessSofastFringe.process_optic_singlefacet, {w} x {h} px, "
          f"{'plain' if a.plain else 'robust'} parabolic fit (downsample 10), {s.shape[1]} points")
    print(f"  f x {1 / 4 / c[2]:.3f} m   f y {1 / 4 / c[5]:.3f} m   xy coefficient {1e3 * c[4]:.4f} mrad/m")
    print(f"  slope RMS against the fitted parabola (all points) x {rms_mrad(rx):.4f}  y {rms_mrad(ry):.4f}  "
          f"magnitude {rms_mrad(np.hypot(rx, ry)):.4f} mrad")
    print(f"  time: imports {t_imports - T0:.2f} s, loading {t_loaded - t_imports:.2f} s, "
          f"processing {t_done - t_loaded:.2f} s")
    if a.compare:
        import h5py

        with h5py.File(expected) as f:
            ce = f["DataSofastCalculation/facet/facet_000/SlopeSolverData/surf_coefs_facet"][()]
        print(f"  stored expected ({os.path.basename(expected)}): f x {1 / 4 / ce[2]:.3f} m  f y {1 / 4 / ce[5]:.3f} m"
              f"  largest coefficient difference {np.abs(ce - c).max():.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
