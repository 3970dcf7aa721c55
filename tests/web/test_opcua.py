"""Issue 15: the station as an OPC UA server; an asyncua client reads the documented node tree and sees
the verdict change after a facet."""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import subprocess
import sys
import time

import pytest

from sofast_station.config import load_config
from sofast_station.devices.protocols import FacetRequest
from sofast_station.station.service import Service
from tests.conftest import ROOT, SMALL_STATION, require

require("asyncua")

EXTRA = """
[run]
deadline_s = 300          # a busy machine must not turn a facet into a timeout fault

[simulation.faults]
"X-0002" = "dark"

[web]
port = 0
nice = 0

[opcua]
enabled = true
endpoint = "opc.tcp://127.0.0.1:{port}/sofast-station/"
anonymous = true
users = {{ scada = "s3cret-pass" }}
allow_plain_passwords = true   # loopback only; Sign & Encrypt with a certificate: test_opcua_security.py
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _documented_paths() -> list[str]:
    text = (ROOT / "docs" / "opcua.md").read_text()
    return re.findall(r"^\| `([A-Za-z]+/[A-Za-z0-9_]+)` \|", text, flags=re.M)


def test_opcua_client_sees_the_tree_and_the_verdict_change(tmp_path, monkeypatch):
    from asyncua import ua
    from asyncua.sync import Client

    data = tmp_path / "data"
    port = _free_port()
    endpoint = f"opc.tcp://127.0.0.1:{port}/sofast-station/"
    config = tmp_path / "station.toml"
    config.write_text(SMALL_STATION.format(data_dir=data, facet=ROOT / "fixtures/facets/dish_5m33.toml",
                                           radiometric=ROOT / "calibration/simulated_radiometric.json")
                      + EXTRA.format(port=port))
    monkeypatch.setenv("SOFAST_DATA_DIR", str(data))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    server = subprocess.Popen([sys.executable, "-m", "sofast_station", "serve", "--config", str(config)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        end = time.monotonic() + 180
        while True:                                  # the server loads the standard address space first
            line = server.stdout.readline()
            assert line or server.poll() is None, server.communicate()
            if line.startswith("OPC UA server:"):
                break
            assert time.monotonic() < end, "the OPC UA server did not start"
        client = Client(endpoint, timeout=30)
        client.connect()
        try:
            ns = client.get_namespace_index("urn:sofast-station")
            root = client.nodes.objects.get_child(f"{ns}:SofastStation")
            tree = {f"{folder.read_browse_name().Name}/{v.read_browse_name().Name}"
                    for folder in root.get_children() for v in folder.get_children()}
            assert tree == set(_documented_paths()), "docs/opcua.md documents the node tree as served"

            def node(path):
                return root.get_child([f"{ns}:{p}" for p in path.split("/")])

            assert node("LastFacet/Verdict").read_value() == ""
            assert node("Station/State").read_value() == "offline"
            seen = []

            def look(outcome):
                end = time.monotonic() + 60
                while node("LastFacet/CycleId").read_value() != outcome.cycle_id:
                    assert time.monotonic() < end, "the OPC UA server did not publish the facet"
                    time.sleep(0.05)
                seen.append({p: node(p).read_value() for p in (
                    "LastFacet/Serial", "LastFacet/Verdict", "LastFacet/Reasons", "LastFacet/FocalLengthX_m",
                    "Counters/Facets", "Counters/Pass", "Counters/Fault", "Counters/Yield")})

            cfg = load_config(config)
            service = Service(cfg, simulated_facets=[FacetRequest("SIM-0001"), FacetRequest("X-0002")],
                              console=lambda line: None, archiver_process=False)
            service.runner.hooks.append(look)
            try:
                outcomes = service.runner.run()
            finally:
                service.close()
            first, second = seen
            assert first["LastFacet/Serial"] == "SIM-0001" and first["LastFacet/Verdict"] == "pass"
            assert first["LastFacet/FocalLengthX_m"] == pytest.approx(outcomes[0].record["focal_length_x_m"])
            assert (first["Counters/Facets"], first["Counters/Pass"], first["Counters/Yield"]) == (1, 1, 1.0)
            assert second["LastFacet/Serial"] == "X-0002" and second["LastFacet/Verdict"] == "fault"
            assert "dark everywhere" in second["LastFacet/Reasons"][0]
            assert math.isnan(second["LastFacet/FocalLengthX_m"])
            assert (second["Counters/Facets"], second["Counters/Fault"], second["Counters/Yield"]) == (2, 1, 0.5)
            # nobody writes: the verdict stays the station's
            with pytest.raises(ua.UaStatusCodeError):
                node("LastFacet/Verdict").write_value(ua.Variant("pass", ua.VariantType.String))
            assert node("LastFacet/Verdict").read_value() == "fault"
        finally:
            client.disconnect()
        # a configured user logs in (read-only as well); a wrong password is refused
        user = Client(endpoint, timeout=30)
        user.set_user("scada")
        user.set_password("s3cret-pass")
        with user:
            ns = user.get_namespace_index("urn:sofast-station")
            assert user.nodes.objects.get_child([f"{ns}:SofastStation", f"{ns}:LastFacet",
                                                 f"{ns}:Serial"]).read_value() == "X-0002"
        wrong = Client(endpoint, timeout=30)
        wrong.set_user("scada")
        wrong.set_password("guess")
        with pytest.raises(ua.UaStatusCodeError):
            wrong.connect()
        wrong.disconnect()
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def test_counters_count_indeterminate_facets_apart():
    """A guarded-rule `indeterminate` facet is counted in its own node, not lost among pass/fail."""
    from sofast_station.result.shift import summarize
    from sofast_station.web.opcua import values

    verdicts = ["pass", "indeterminate", "indeterminate", "fail", "fault"]
    records = [{"cycle_id": f"c{i}", "verdict": v, "reasons": ["camera: lost"] if v == "fault" else []}
               for i, v in enumerate(verdicts)]
    snap = {"status": {"state": "idle"}, "last": records[-1], "summary": summarize(records),
            "calibration": {}, "disk": {}, "station": "line-1", "shift_start": "2026-12-02T06:00",
            "alarms": []}
    out = values(snap)
    assert (out["Counters/Indeterminate"], out["Counters/Pass"], out["Counters/Fail"], out["Counters/Fault"]) \
        == (2, 1, 1, 1)
    assert out["Counters/Facets"] == 5 and out["Counters/Yield"] == 0.2
    assert "Counters/Indeterminate" in _documented_paths()
