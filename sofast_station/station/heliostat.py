"""The station's side of a heliostat: its optics from an analysis, and its figures as a record.

The analysis itself is :func:`~sofast_station.measure.heliostat.analyse_heliostat`; the optics
:func:`~sofast_station.optics.heliostat.heliostat_optics`; what an assembler does with the canting errors
:mod:`sofast_station.report.canting`.
"""

from __future__ import annotations

import numpy as np

from ..ensemble import EnsembleDesign
from ..optics.facet import OpticsSettings, outline_area_m2
from ..optics.heliostat import FacetSurface, HeliostatOptics, heliostat_optics


def facet_surfaces(result, ensemble: EnsembleDesign) -> list[FacetSurface]:
    """Every measured facet of a :class:`~sofast_station.measure.heliostat.HeliostatAnalysis` as the optics
    trace it: its points and slopes, where it is in the heliostat's optical frame, and its canting U."""
    by_index = {f["index"]: f for f in result.figures["facets"]}
    out = []
    for i in sorted(result.analyses):
        a = result.analyses[i]
        rotation, translation = result.facet_in_heliostat(i)
        corrected, _ = result.facet_in_heliostat(i, corrected=True)
        u = by_index[i].get("canting_mrad_U")
        u = None if u is None or u["x"] is None or u["y"] is None else np.array([u["x"], u["y"]])
        design = ensemble.facets[i].design
        out.append(FacetSurface(label=ensemble.facets[i].label, points_m=a.points_facet_m, slopes=a.slopes,
                                camera_m=a.facet_to_camera.inverse().translation,
                                area_m2=outline_area_m2(design.outline_m), rotation=rotation, translation=translation,
                                corrected_rotation=corrected, canting_u_mrad=u))
    return out


def analysis_optics(result, ensemble: EnsembleDesign, settings: OpticsSettings) -> HeliostatOptics:
    """The heliostat's design, measured and canting-corrected traces of an analysis."""
    return heliostat_optics(facet_surfaces(result, ensemble), ensemble, settings)
