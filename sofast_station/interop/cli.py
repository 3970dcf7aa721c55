"""``sofast-station import-opencsp``: analyse an OpenCSP SOFAST fringe measurement with our pipeline."""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

from ..commands import add_command, single_thread_blas
from ..files import json_ready


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
            (docs/opencsp.md). Every figure carries its expanded uncertainty U (k = 2) from input
            uncertainties suited to an OpenCSP setup (listed with the assumptions; docs/opencsp.md).""")
    p.add_argument("--test-data", default=None, metavar="DIR",
                   help="a folder in the layout of OpenCSP's opencsp/test/data (sets the six files below)")
    for name, what in (("measurement", "MeasurementSofastFringe HDF5"), ("camera", "Camera HDF5"),
                       ("display", "DisplayShape HDF5"), ("orientation", "SpatialOrientation HDF5"),
                       ("calibration", "ImageCalibration HDF5"), ("facet", "facet definition JSON")):
        p.add_argument(f"--{name}", default=None, metavar="FILE", help=f"{what} (default: from --test-data)")
    p.add_argument("--dots", default=None, metavar="FILE",
                   help="OpenCSP's DotLocationsFixedPattern HDF5: the dot locations of a fixed-pattern (dot grid) "
                        "measurement (--measurement a MeasurementSofastFixed file; docs/opencsp.md)")
    p.add_argument("--fixed", action="store_true",
                   help="with --test-data: its fixed-pattern (dot grid) measurement (sofast_fixed/: one dot frame, "
                        "its dot locations; the full-size camera camera_sofast.h5), measured by the fixed-pattern "
                        "method (docs/method.md)")
    p.add_argument("--ensemble", default=None, metavar="FILE",
                   help="OpenCSP's ensemble definition JSON: the measurement is a multi-facet one (every facet of "
                        "--facet, placed and canted as the ensemble says; docs/heliostats.md)")
    p.add_argument("--multi-facet", action="store_true",
                   help="with --test-data: its multi-facet measurement (measurement_ensemble.h5: a lab heliostat of 24 "
                        "facets, Facet_lab_6x4.json and Ensemble_lab_6x4.json)")
    p.add_argument("--split-facet", action="store_true",
                   help="with --test-data: the single facet's measurement analysed as two halves "
                        "(Facet_split_NSTTF.json and Ensemble_split_NSTTF_facet.json)")
    p.add_argument("--focal-length", type=float, default=100.0, metavar="M",
                   help="design focal length, metres (OpenCSP keeps it with the processing, not the files)")
    p.add_argument("--robust", action="store_true", help="bisquare-weighted (robust) slope fits, like OpenCSP's "
                   "robust_least_squares")
    p.add_argument("--surface", choices=("parabolic", "plano"), default="parabolic",
                   help="the shape model: OpenCSP's parabolic (default) or plano surface (a plane: where the mirror "
                        "points, no focal length)")
    p.add_argument("--undefined", action="store_true",
                   help="a mirror of unknown outline (OpenCSP's undefined optic): no facet definition, the frame "
                        "placed at the lit region's centroid; placement and boresight are then not measured")
    p.add_argument("--compare", default=None, metavar="FILE",
                   help="OpenCSP's own processing of the measurement (a data.h5): also redo it the way OpenCSP did "
                        "(its calibration, screen model, fit and pixels) and print both, each figure with our U "
                        "(default: no comparison)")
    p.add_argument("--conformance", action="store_true",
                   help="with --test-data: redo every fringe result of OpenCSP's test data that way and print the "
                        "table docs/opencsp.md shows (the measurement itself is not analysed on its own)")
    p.add_argument("--what", nargs="+", default=None, metavar="FILE",
                   help="say what each OpenCSP file holds and what the station does with it, and stop")
    p.add_argument("--uncertainty", default=None, metavar="FILE",
                   help="a TOML file whose [uncertainty] table (station.toml's keys, docs/uncertainty.md) overrides "
                        "the OpenCSP setup's input uncertainties (default: those of docs/opencsp.md)")
    p.add_argument("--budget", action="store_true", help="also print the uncertainty budget (as inspect --budget)")
    p.add_argument("--json", action="store_true", help="print one JSON object and nothing else on stdout")
    p.set_defaults(func=cmd_import_opencsp)


#: The figures import-opencsp reports, each with its ``_U`` and ``_U_random`` (k = 2) where it has one.
#: Not the placement and optical tilt: they are measured against a fixture, and OpenCSP has none.
FIGURE_KEYS = ("focal_length_x_m", "focal_length_y_m", "curvature_x_per_m", "curvature_y_per_m",
               "principal_focal_lengths_m", "principal_curvatures_per_m", "axis_angle_rad", "twist_mrad_per_m",
               "twist_e1_mrad_per_m", "twist_e2_mrad_per_m", "slope_rms_mrad", "boresight_mrad", "subsample_fit")
#: The noise floor of the slope RMS values and the budget (as in the station's result record).
UNCERTAINTY_KEYS = ("coverage_factor", "slope_rms_noise_mrad", "slope_rms_noise_mrad_U", "slope_rms_corrected_mrad",
                    "slope_rms_corrected_mrad_U", "intensity_noise_dn", "uncertainty_budget")


def read_uncertainty_table(path: Path) -> dict:
    """The ``[uncertainty]`` table of the TOML file *path* (checked against the keys by the reader)."""
    import tomllib

    from ..errors import ConfigError
    try:
        data = tomllib.loads(Path(path).read_text())
    except OSError as exc:
        raise ConfigError(f"--uncertainty {path}: cannot read it ({exc.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--uncertainty {path} is not valid TOML ({exc})") from None
    table = data.get("uncertainty")
    if not isinstance(table, dict):
        raise ConfigError(f"--uncertainty {path} has no [uncertainty] table (station.toml's keys, docs/uncertainty.md)")
    return table


def figures_with_u(fig: dict, keys=FIGURE_KEYS) -> dict:
    """*keys* of the analysis's figures, each followed by its ``_U`` and ``_U_random`` siblings (k = 2),
    and the uncertainty's other keys: the structure of the station's result record. The budget keeps only
    the columns of the figures reported (not placement and optical tilt)."""
    out = {}
    for k in keys:
        out[k] = fig[k]
        for suffix in ("_U", "_U_random"):
            if f"{k}{suffix}" in fig:
                out[f"{k}{suffix}"] = fig[f"{k}{suffix}"]
    out["n_points"] = fig["n_points"]
    # what this measurement does not report, and why (an unknown outline's, the plano model's)
    out.update({k: fig[k] for k in ("surface", "outline", "mirror_centre_px", "not_measured") if k in fig})
    out.update({k: fig[k] for k in UNCERTAINTY_KEYS if k in fig})
    if isinstance(out.get("uncertainty_budget"), dict):
        out["uncertainty_budget"] = _budget_of(out["uncertainty_budget"], keys)
    return out


def _budget_of(budget: dict, keys) -> dict:
    """*budget* (:func:`~sofast_station.measure.uncertainty.budget_table`'s layout: per-figure lists) with
    only the columns of figures under *keys*."""
    names = budget.get("figures", [])
    keep = [i for i, n in enumerate(names) if n.split(".")[0] in keys]
    out = dict(budget)
    out["figures"] = [names[i] for i in keep]
    for key in ("combined_standard", "random_standard"):
        if isinstance(budget.get(key), list):
            out[key] = [budget[key][i] for i in keep]
    out["rows"] = [dict(r, contributions=[r["contributions"][i] for i in keep]) for r in budget.get("rows", [])]
    return out


def _pm(v, u, unit: str = "", digits: int = 3) -> str:
    """``115.7 ± 1.6 m`` (:func:`~sofast_station.result.formatting.with_u`); *digits* decimals without U."""
    from ..result.formatting import with_u

    return with_u(v, u, unit, digits)


def cmd_import_opencsp(args) -> int:
    single_thread_blas()            # before numpy: bit-exact as reprocess, and no BLAS thread pool to start
    from ..errors import ConfigError
    from .paths import FILES, check_files, opencsp_test_data_paths

    if args.what:
        from .identify import describe

        for f in args.what:
            print(f"{f}: {describe(Path(f))}")
        return 0
    if args.conformance:
        return _conformance(args)
    if args.fixed or args.dots or (args.measurement and _is_fixed(Path(args.measurement))):
        return _import_fixed(args)

    paths = opencsp_test_data_paths(Path(args.test_data), args.multi_facet, args.split_facet) if args.test_data else {}
    for flag in ("multi_facet", "split_facet"):
        if getattr(args, flag) and not args.test_data:
            raise ConfigError(f"import-opencsp --{flag.replace('_', '-')} reads OpenCSP's test-data layout: give "
                              "--test-data DIR (or --ensemble FILE with the measurement's files)")
    for key in FILES:
        if getattr(args, key, None):
            paths[key] = Path(getattr(args, key))
        if key not in paths and key != "ensemble" and not (key == "facet" and args.undefined):
            raise ConfigError(f"import-opencsp needs --{key} (or --test-data with OpenCSP's folder layout)")
    if args.undefined:
        if args.facet or "ensemble" in paths:
            raise ConfigError("import-opencsp --undefined measures a mirror of unknown outline: leave out --facet, "
                              "--ensemble and --multi-facet")
        paths.pop("facet", None)
    for key in ("compare", "uncertainty"):
        if getattr(args, key) and not Path(getattr(args, key)).is_file():
            raise ConfigError(f"--{key} {getattr(args, key)} does not exist")
    if "ensemble" in paths:
        missing = [f"{k} {v}" for k, v in paths.items() if not Path(v).is_file()]
        if missing:
            raise ConfigError("the multi-facet measurement's files are not all present: missing " + "; ".join(missing)
                              + " (OpenCSP's test data ships measurement_ensemble.h5 with Facet_lab_6x4.json and "
                                "Ensemble_lab_6x4.json, and Facet_split_NSTTF.json with "
                                "Ensemble_split_NSTTF_facet.json)")
    check_files(paths, Path(args.test_data) if args.test_data else None)   # before numpy and HDF5 are loaded
    from ..cache import SensitivityStore, capture_basis, open_cache
    from ..commands import default_config
    from ..files import station_data_dir
    from ..precompute import keep_rays, prepare_analysis_process, use_disk_cache
    from .opencsp import read_opencsp, read_opencsp_result

    # The uncertainty's sensitivities (per geometry, recipe and inputs), the camera's rays and the display
    # grid's triangulation, computed from these files before and kept in the station's cache (data_dir/cache;
    # sofast_station/cache.py): a second import of the same files reads them. The figures are the same bits
    # either way.
    disk = open_cache(station_data_dir(default_config()))
    table = read_uncertainty_table(Path(args.uncertainty)) if args.uncertainty else None
    m = read_opencsp(**{"facet": None, **paths}, focal_length_m=args.focal_length, uncertainty=table, cache=disk)
    if args.surface != "parabolic":
        from dataclasses import replace

        m.settings = replace(m.settings, surface=args.surface)
    prepare_analysis_process()      # as the station's worker: memory reused, kernels loaded first
    if m.ensemble is not None:
        # every facet's sensitivities (each under its own key) kept on disk as a single facet's are
        return _import_ensemble(m, args, SensitivityStore(
            disk, lambda: capture_basis(m.frames, m.distance_m, source="opencsp-ensemble")))
    use_disk_cache(disk)
    cache = SensitivityStore(disk, lambda: capture_basis(m.frames, m.distance_m, source="opencsp"))
    a = m.analyse(robust=args.robust, uncertainty=m.uncertainty, sensitivity_cache=cache)
    fig = a.figures
    out = {"facet": m.name, "measured": m.date, "robust": args.robust, **figures_with_u(fig),
           "input_uncertainties": m.uncertainty.to_dict(), "assumptions": list(m.assumptions)}
    # What the facet does with sunlight: default [optics] (pillbox sun, target at the design focal length);
    # 'report flux --opencsp' draws the map and takes other conditions. With the analysis's U, the optics'.
    from ..optics import OpticsSettings
    from ..result.optical_figures import analysis_optics
    out["optics"] = (None if fig.get("surface") == "plano" else    # a plane's fit says nothing of its focus
                     analysis_optics(a, m.design, OpticsSettings()).figures)
    compared = None
    if args.compare:
        from .conformance import conform_file

        ref = read_opencsp_result(Path(args.compare))
        # The sensitivities of the analysis above first (as before the cache), else those kept for OpenCSP's
        # pixels (its mask is part of their key).
        on_its_pixels = SensitivityStore(disk, lambda: capture_basis(m.frames, m.distance_m, ref.mask,
                                                                     source="opencsp"), initial=dict(cache))
        compared = conform_file(Path(args.compare), paths["measurement"], args.focal_length, on_its_pixels)
        theirs = compared.figures
        out["opencsp"] = {"file": args.compare, "robust": ref.robust, "surface": ref.surface, "optic": ref.optic,
                          "focal_length_x_m": ref.focal_length_x_m, "focal_length_y_m": ref.focal_length_y_m,
                          "n_points": int(ref.mask.sum()),
                          "ours_on_its_pixels": theirs["subsample_fit"],
                          "ours_on_its_pixels_U": theirs.get("subsample_fit_U"),
                          "ours_on_its_pixels_U_random": theirs.get("subsample_fit_U_random"),
                          **{k: v for k, v in compared.to_dict().items() if k in ("rows", "slopes")}}
    keep_rays()
    hits = cache.hits + (on_its_pixels.hits if args.compare else 0)
    if hits:
        logging.getLogger(__name__).info("%d set(s) of the uncertainty's sensitivities read from the cache in %s "
                                         "(computed from these files before)", hits, disk.directory)
    out = json_ready(out)
    if args.json:
        json.dump(out, sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    print(summary_text(out, args.robust))
    if compared is not None:
        from .conformance import conformance_text

        print(conformance_text(compared))
    if args.budget:
        from ..result.formatting import BUDGET_COLUMNS, budget_text
        print(budget_text(out, [c for c in BUDGET_COLUMNS if not c[0].startswith(("optical_tilt", "placement"))]))
    return 0


#: What a multi-facet import reports of each facet (with U): a facet's figures, and its canting.
FACET_KEYS = FIGURE_KEYS[:-1] + ("canting_mrad",)


def _conformance(args) -> int:
    """import-opencsp --conformance: every fringe result of OpenCSP's test data redone and compared."""
    from ..errors import ConfigError
    from .conformance import FRINGE_RESULTS, conform, conformance_text

    if not args.test_data:
        raise ConfigError("import-opencsp --conformance redoes OpenCSP's test data: give --test-data DIR "
                          "(fixtures/opencsp/test_data is one)")
    from .conformance import FIXED_RESULT, conform_fixed
    from .paths import opencsp_fixed_paths

    cache: dict = {}
    results = [conform(Path(args.test_data), ds, args.focal_length, cache) for ds in FRINGE_RESULTS]
    results.append(conform_fixed(opencsp_fixed_paths(Path(args.test_data)), Path(args.test_data) / FIXED_RESULT,
                                 args.focal_length, cache))
    if args.json:
        json.dump(json_ready([c.to_dict() for c in results]), sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    print("\n".join(f"[{c.dataset}] " + conformance_text(c) for c in results))
    outside = [f"{c.dataset}: {r.figure}" for c in results for r in c.rows if r.within_u is False]
    print(f"{sum(len(c.rows) for c in results)} figures compared on {len(results)} results; outside U: "
          + ("none" if not outside else "; ".join(outside) + " (docs/opencsp.md says why)"))
    return 0


def _is_fixed(path: Path) -> bool:
    """Whether *path* is an OpenCSP fixed-pattern measurement (an HDF5 file with a MeasurementSofastFixed group)."""
    try:
        import h5py

        with h5py.File(path, "r") as h:
            return "MeasurementSofastFixed" in h
    except OSError:
        return False


def _import_fixed(args) -> int:
    """import-opencsp of a fixed-pattern (dot grid) measurement: the fixed-pattern method's figures with U, and
    with --compare OpenCSP's processing beside them (:func:`~.conformance.conform_fixed`)."""
    from ..cache import SensitivityStore, capture_basis, open_cache
    from ..commands import default_config
    from ..errors import ConfigError
    from ..files import station_data_dir
    from .opencsp_fixed import read_opencsp_fixed
    from .paths import FIXED_FILES, check_files, opencsp_fixed_paths

    for flag in ("ensemble", "multi_facet", "split_facet", "robust"):
        if getattr(args, flag):
            raise ConfigError(f"import-opencsp --{flag.replace('_', '-')} is for fringe measurements; a fixed-pattern "
                              "measurement is one facet, plain fit")
    paths = opencsp_fixed_paths(Path(args.test_data)) if args.test_data else {}
    for key in FIXED_FILES:
        if getattr(args, key, None):
            paths[key] = Path(getattr(args, key))
        if key not in paths and not (key == "facet" and args.undefined):
            raise ConfigError(f"import-opencsp of a fixed-pattern measurement needs --{key} (or --test-data with "
                              "OpenCSP's folder layout and --fixed)")
    if args.undefined:
        paths.pop("facet", None)
    for key in ("compare", "uncertainty"):
        if getattr(args, key) and not Path(getattr(args, key)).is_file():
            raise ConfigError(f"--{key} {getattr(args, key)} does not exist")
    check_files(paths, Path(args.test_data) if args.test_data else None)
    disk = open_cache(station_data_dir(default_config()))
    table = read_uncertainty_table(Path(args.uncertainty)) if args.uncertainty else None
    m = read_opencsp_fixed(**{"facet": None, **paths}, focal_length_m=args.focal_length, uncertainty=table)
    if args.surface != "parabolic":
        from dataclasses import replace

        m.settings = replace(m.settings, surface=args.surface)
    cache = SensitivityStore(disk, lambda: capture_basis(m.image, m.distance_m, source="opencsp-fixed"))
    a = m.analyse(uncertainty=m.uncertainty, sensitivity_cache=cache)
    fig = a.figures
    out = {"facet": m.name, "measured": m.date, "method": "fixed", "robust": False, **figures_with_u(fig),
           "dots": fig.get("dots"), "dropped": fig.get("dropped"),
           "input_uncertainties": m.uncertainty.to_dict(), "assumptions": list(m.assumptions)}
    from ..optics import OpticsSettings
    from ..result.optical_figures import analysis_optics
    out["optics"] = (None if fig.get("surface") == "plano" else
                     analysis_optics(a, m.design, OpticsSettings()).figures)
    compared = None
    if args.compare:
        from .conformance import conform_fixed

        compared = conform_fixed(paths, Path(args.compare), args.focal_length, cache)
        out["opencsp"] = {"file": args.compare,
                          **{k: v for k, v in compared.to_dict().items() if k in ("rows", "slopes")}}
    out = json_ready(out)
    if args.json:
        json.dump(out, sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    d = out["dots"] or {}
    print(summary_text(out, False).replace(f"{out['n_points']} points", f"{out['n_points']} dots (fixed pattern)", 1))
    print(f"  dots: {d.get('found')} found, {d.get('indexed')} indexed from the origin ({d.get('origin_from')} at "
          f"{[round(v, 1) for v in d.get('origin_px') or []]} px), {d.get('used')} used; dropped: {out['dropped']}")
    if compared is not None:
        from .conformance import conformance_text

        print(conformance_text(compared))
    if args.budget:
        from ..result.formatting import BUDGET_COLUMNS, budget_text
        print(budget_text(out, [c for c in BUDGET_COLUMNS if not c[0].startswith(("optical_tilt", "placement"))]))
    return 0


def _import_ensemble(m, args, cache: dict | None = None) -> int:
    """import-opencsp of a multi-facet measurement: every facet's figures and canting error (with U), the
    facets' common tilt against their corners (OpenCSP has no fixture: no placement)."""
    res = m.analyse_heliostat(uncertainty=m.uncertainty, sensitivity_cache={} if cache is None else cache)
    facets = []
    for f in res.figures["facets"]:
        entry = {"label": f["label"], "status": f["status"]}
        if "canting_mrad" in f:
            entry.update(figures_with_u(f, FACET_KEYS))
            entry.pop("uncertainty_budget", None)
        else:
            entry["reason"] = f.get("reason")
        facets.append(entry)
    h = res.figures["heliostat"]
    out = {"ensemble": m.ensemble.name, "measured": m.date,
           "heliostat": {k: h[k] for k in ("n_facets", "n_measured", "common_tilt_mrad", "common_tilt_mrad_U",
                                           "canting_rms_mrad", "canting_max_mrad", "canting_max_facet",
                                           "corner_reprojection_rms_px", "measured_distance_m") if k in h},
           "facets": facets, "input_uncertainties": m.uncertainty.to_dict(), "assumptions": list(m.assumptions)}
    out = json_ready(out)
    if args.json:
        json.dump(out, sys.stdout, indent=1)
        sys.stdout.write("\n")
        return 0
    lines = [f"OpenCSP multi-facet measurement {out['ensemble']} ({out['measured']}): {out['heliostat']['n_measured']}"
             f" of {out['heliostat']['n_facets']} facets measured",
             "  assumed (OpenCSP's files do not say):" + "".join(f"\n    - {a}" for a in out["assumptions"]),
             "  figures are value ± U, the expanded uncertainty (k=2)",
             "  facet   canting x (mrad)    canting y (mrad)    f x (m)               f y (m)               "
             "slope RMS vs "
             "parabola (mrad)"]
    for f in facets:
        if "canting_mrad" not in f:
            lines.append(f"  {f['label']:<7} {f['status']}: {f.get('reason')}")
            continue
        c, u = f["canting_mrad"], f.get("canting_mrad_U") or {}
        r = f["slope_rms_mrad"]["parabola"]["magnitude"]
        ru = ((f.get("slope_rms_mrad_U") or {}).get("parabola") or {}).get("magnitude")
        lines.append(f"  {f['label']:<7} {_pm(c['x'], u.get('x')):<19} {_pm(c['y'], u.get('y')):<19} "
                     f"{_pm(f['focal_length_x_m'], f.get('focal_length_x_m_U')):<21} "
                     f"{_pm(f['focal_length_y_m'], f.get('focal_length_y_m_U')):<21} {_pm(r, ru)}")
    ct, cu = out["heliostat"]["common_tilt_mrad"], out["heliostat"].get("common_tilt_mrad_U") or {}
    lines.append(f"  facets' common tilt against their corners {_pm(ct['x'], cu.get('x'))}, "
                 f"{_pm(ct['y'], cu.get('y'))} "
                 "mrad (where the ensemble points: not a canting error)")
    print("\n".join(lines))
    return 0


def summary_text(out: dict, robust: bool) -> str:
    """The console summary of import-opencsp's result *out*: every figure as value ± U (k = 2)."""
    from ..result.formatting import aperture_text

    def u_of(key, *sub):
        v = out.get(f"{key}_U")
        for s_ in sub:
            v = None if v is None else v[s_]
        return v

    k = out.get("coverage_factor", 2)
    kk = f" (k={k:g})"
    not_measured = out.get("not_measured") or {}
    lines = [f"OpenCSP measurement {out['facet']} ({out['measured']}), {out['n_points']} points"
             f"{', robust fit' if robust else ''}{', plano surface' if out.get('surface') == 'plano' else ''}"
             f"{', mirror of unknown outline' if out.get('outline') == 'unknown' else ''}",
             "  assumed (OpenCSP's files do not say):" + "".join(f"\n    - {a}" for a in out["assumptions"]),
             f"  figures are value ± U, the expanded uncertainty{kk}"]
    if out["focal_length_x_m"] is None and "focal_length_x_m" in not_measured:
        lines.append(f"  focal lengths and twist: not measured ({not_measured['focal_length_x_m']})")
    else:
        lines += [f"  f x {_pm(out['focal_length_x_m'], u_of('focal_length_x_m'), ' m')}{kk}",
                  f"  f y {_pm(out['focal_length_y_m'], u_of('focal_length_y_m'), ' m')}{kk}",
                  f"  twist {_pm(out['twist_mrad_per_m'], u_of('twist_mrad_per_m'), ' mrad/m', 4)}{kk}"
                  f" (E1 {_pm(out['twist_e1_mrad_per_m'], u_of('twist_e1_mrad_per_m'), '', 4)}, E2 "
                  f"{_pm(out['twist_e2_mrad_per_m'], u_of('twist_e2_mrad_per_m'), '', 4)})"]
    for model, r in out["slope_rms_mrad"].items():
        shown = "plane" if model == "parabola" and out.get("surface") == "plano" else model
        lines.append(f"  slope RMS vs {shown:<12} x {_pm(r['x'], u_of('slope_rms_mrad', model, 'x'))}  y "
                     f"{_pm(r['y'], u_of('slope_rms_mrad', model, 'y'))}  magnitude "
                     f"{_pm(r['magnitude'], u_of('slope_rms_mrad', model, 'magnitude'))} mrad{kk}")
    noise = out.get("slope_rms_noise_mrad")
    if noise:
        model, n = next(iter(noise.items()))
        nx, ny = (_pm(n[a], u_of("slope_rms_noise_mrad", model, a)) for a in ("x", "y"))
        lines.append(f"    (the capture's own intensity noise explains {nx} x, {ny} y mrad of slope noise{kk})")
    b = out["boresight_mrad"]
    if b is None:
        lines.append(f"  boresight: not measured ({not_measured.get('boresight_mrad', 'no corners')})")
    else:
        lines.append(f"  boresight x {_pm(b['x'], u_of('boresight_mrad', 'x'), '', 2)}, y "
                     f"{_pm(b['y'], u_of('boresight_mrad', 'y'), '', 2)} mrad{kk} "
                     f"({'the plane' if out.get('surface') == 'plano' else 'the fitted normal'}'s tilt from the "
                     "corner pose)")
    o = out["optics"]
    if o is None:
        lines.append("  optics: not computed (the plano model fits no curvature: a plane's focus is not measured)")
        return "\n".join(lines)
    centroid_u = (o.get("centroid_offset_mrad_U") or {}).get("magnitude")
    lines.append(f"  optics (pillbox sun, target at {o['conditions']['slant_range_m']:g} m, aperture "
                 f"{aperture_text(o['conditions']['aperture'])}): "
                 f"intercept {_pm(o['intercept'], o.get('intercept_U'), '', 4)}, "
                 f"90 % spot radius {_pm(o['spot_radius_m'], o.get('spot_radius_m_U'), ' m')} (design "
                 f"{o['design']['spot_radius_m']:.3f} m), centroid "
                 f"{_pm(o['centroid_offset_mrad']['magnitude'], centroid_u)} mrad off aim{kk}")
    return "\n".join(lines)
