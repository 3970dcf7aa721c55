"""A short line on the small simulated station, for the tests of the station's checks of itself: the station
file (with *extra* TOML), the service, its run with a callback between facets, and what it answered and
journaled."""

from __future__ import annotations

from pathlib import Path

from sofast_station.config import load_config

ROOT = Path(__file__).resolve().parents[2]


def small_line(tmp_path, serials, extra: str = ""):
    """The small station's service with the facets *serials* queued (no warm-up, no standby worker, a deadline
    no loaded machine reaches); returns (config, service)."""
    from tests.conftest import SMALL_STATION

    from sofast_station.devices.protocols import FacetRequest
    from sofast_station.station.service import Service

    path = tmp_path / "station.toml"
    path.write_text(SMALL_STATION.format(data_dir=tmp_path / "data", facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                         radiometric=ROOT / "calibration/simulated_radiometric.json")
                    + extra + "\n[run]\ndeadline_s = 600.0\nwarmup = false\nstandby_worker = false\n")
    config = load_config(path)
    service = Service(config, simulated_facets=[FacetRequest(s) for s in serials], console=lambda line: None)
    return config, service


def run_line(config, service, between) -> tuple[dict, dict, dict]:
    """Run the queued facets (*between* called with each outcome), close the service; returns the robot's final
    answers by serial, the status file after the run, and the journal's records by serial."""
    from sofast_station.archive import Journal
    from sofast_station.live.status import read_status

    try:
        service.runner.run(on_outcome=between)
        final_status = read_status(config.data_dir)
    finally:
        service.close()
    answers = {a.serial: a for a in service.trigger.answers if a.kind in ("done", "fault")}
    journal = Journal(config.data_dir / "journal.sqlite3")
    try:
        rows = {r.serial: r.record for r in journal.rows()}
    finally:
        journal.close()
    return answers, final_status, rows
