"""Issue 42 item 4: OpenCSP's real fixed-pattern capture (fixtures/opencsp/test_data/sofast_fixed: one frame of
an NSTTF facet reflecting an 85 x 85 dot grid) through our files route and the fixed-pattern method, beside
OpenCSP's own processing of it (its slopes at 3,782 dots; the file keeps no fit and no pose).

What must hold, and why (docs/opencsp.md, "The fixed-pattern capture"):

* the two programs' dots are the same points of the facet: after the 2-D rigid motion between the two facet
  frames (each placed by its own program's corners) they lie within a fraction of a millimetre (a centre 0.12 px
  off moves the point by 0.25 mm there);
* fitted the same way on the same dots, the focal lengths and the twist's E1, E2 agree within our U (k = 2);
* the dots' slopes differ by what the two programs' centres of the same dots explain (OpenCSP's blob detector's
  contour centres are 0.12 px from ours): the slope that offset predicts through each dot's geometry takes
  out nearly all of the difference (correlation above 0.9), and what is left lies within our per-dot U from
  the image's noise at 97 % of the dots or more (95 % per axis expected for noise alone).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from sofast_station.interop.conformance import FIXED_RESULT, conform_fixed
from sofast_station.interop.identify import describe
from sofast_station.interop.opencsp_fixed import read_opencsp_fixed
from sofast_station.interop.paths import opencsp_fixed_paths
from sofast_station.measure.dots import find_pattern_dots, pattern_background
from sofast_station.measure.fixed import FixedSettings, find_origin_mark


@pytest.fixture(scope="module")
def root(repo_root):
    return repo_root / "fixtures/opencsp/test_data"


@pytest.fixture(scope="module")
def compared(root):
    return conform_fixed(opencsp_fixed_paths(root), root / FIXED_RESULT, cache={})


def test_the_fixed_capture_agrees_with_opencsps_processing_within_our_u(compared):
    s = compared.slopes
    assert s["pixels_compared"] >= 3500 and s["pixels_opencsp"] == 3782
    assert s["registration"]["residual_median_mm"] < 0.5
    rows = {r.figure: r for r in compared.rows}
    common = [r for name, r in rows.items() if "dots both use" in name]
    assert len(common) == 4 and all(r.within_u for r in common), [r.to_dict() for r in common]
    # on every dot each uses, OpenCSP's fit takes in the dots the edge cuts: its f y moves beyond our U
    own = [r for name, r in rows.items() if "every dot each uses" in name]
    assert any(not r.within_u for r in own)
    c = s["centres"]
    assert min(c["correlation"]) > 0.9
    assert all(left < 0.35 * total for left, total in zip(c["remaining_rms_mrad"], s["rms_mrad"]))
    assert c["fraction_within_U_after"] >= 0.97
    assert compared.figures["method"] == "fixed" and compared.figures["focal_length_x_m_U"] > 0


def test_the_origin_mark_and_the_grids_directions_are_opencsps(root):
    """The mark is found within half a pixel of the pixel the capture stores; the nominal geometry predicts
    OpenCSP's index directions (x along the image's columns, y along its rows)."""
    m = read_opencsp_fixed(**opencsp_fixed_paths(root))
    red, _ = m.reduce(FixedSettings())            # the directions predicted, not OpenCSP's given
    assert red.figures["dots"]["index_axes"] == [[1, 0], [0, 1]]
    bg = pattern_background(m.image, 24)
    found = find_pattern_dots(m.image, red.region.region, background=bg)
    mark = find_origin_mark(m.image, red.region.region, bg, found.diameter_px, found.noise_dn)
    assert abs(mark - m.origin_px).max() < 0.5, (mark, m.origin_px)


def test_import_opencsp_fixed_reports_the_methods_figures_and_the_files_are_named(root):
    assert "import-opencsp --fixed" in describe(root / "sofast_fixed/data_measurement/measurement_facet.h5")
    assert "import-opencsp --dots" in describe(root / "sofast_fixed/data_measurement/fixed_pattern_dot_locations.h5")
    assert "--fixed --compare" in describe(root / FIXED_RESULT)
    proc = subprocess.run([sys.executable, "-m", "sofast_station", "import-opencsp", "--test-data", str(root),
                           "--fixed", "--json"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["method"] == "fixed" and out["n_points"] == out["dots"]["used"] >= 3500
    assert out["focal_length_x_m_U"] > 0 and out["dots"]["origin_from"] == "given"
    bad = subprocess.run([sys.executable, "-m", "sofast_station", "import-opencsp", "--test-data", str(root), "--fixed",
                          "--dots", str(root / "sofast_common/camera_sofast.h5")], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "camera_sofast.h5" in bad.stderr


def test_an_imports_one_analysis_cache_shares_the_grid_prediction_with_its_callers():
    """An import analyses with a cache of its own that shares with the caller's only what is the same for every
    capture of a recipe: the sensitivities and the fixed pattern's predicted grid picture (a GridPrediction);
    the frame-brightness pool stays with the one analysis."""
    from collections import deque

    import numpy as np

    from sofast_station.interop.opencsp import _SensitivitiesOnly
    from sofast_station.measure.fixed import GridPrediction

    shared: dict = {}
    kept = GridPrediction(np.eye(2), True)
    local = _SensitivitiesOnly(shared)
    local[("grid prediction", "0123")] = kept
    local[("frame brightness", "0123")] = deque()
    assert shared == {("grid prediction", "0123"): kept}
    assert _SensitivitiesOnly(shared).get(("grid prediction", "0123")) is kept
    assert _SensitivitiesOnly(shared).get(("frame brightness", "0123")) is None
