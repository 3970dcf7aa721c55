"""A noise-free capture of one of the population's drawn stations, analysed, and the twin's truth over the
pixels the analysis kept: the start of the tests that put the twin's truth into the pipeline one stage at a
time on drawn stations (test_heliostat_near.py, test_gore_surface_heights.py)."""

from __future__ import annotations

import numpy as np

from sofast_station.measure import pipeline
from sofast_station.station.population import PopulationStation, draw_station
from sofast_station.twin.truth import ground_truth


def noise_free_capture(index: int, kind: str, images: dict, data_dir, surface_seed: int | None = None) -> tuple:
    """Station *index* of the population of seed 0 (of facet *kind*), its facet at the fixture's nominal pose,
    a noise-free capture (the rng draws only the flicker phase) analysed without uncertainty. *surface_seed*:
    another draw of the facet's slope errors (the station's own when None).

    Returns (station, twin, reduction, args): ``args`` the keyword arguments :func:`~pipeline.rerun` takes."""
    spec = draw_station(index, 0)
    assert spec["kind"] == kind
    if surface_seed is not None:
        spec["facet"]["surface_seed"] = surface_seed
    st = PopulationStation(spec, data_dir, images)
    cfg = st.config
    twin = st.twin(cfg.geometry, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), optics=st.optics.noise_free())
    frames = st.capture(twin, np.random.default_rng(index))
    distance = twin.measured_distance_m()
    args = dict(fringes=cfg.fringes, geometry=cfg.geometry, design=cfg.design, measured_distance_m=distance,
                settings=cfg.analysis)
    reduction, _ = pipeline.reduce_stages(frames, cfg.fringes, cfg.geometry, cfg.design, distance, cfg.analysis)
    return st, twin, reduction, args


def truth_of(twin, reduction) -> dict:
    """The twin's :func:`~sofast_station.twin.truth.ground_truth` over the pixels *reduction* kept."""
    valid = np.zeros(twin.geometry.camera.shape, dtype=bool)
    valid.ravel()[reduction.rays.vidx] = True
    return ground_truth(twin, valid)
