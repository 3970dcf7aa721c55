"""Issue 15: the station as an OPC UA server; an asyncua client reads the documented node tree and sees
the verdict change after a facet. Issue 29: as a SCADA integrator expects it: numbers are analog items
with UN/CEFACT engineering units (and an EURange from the recipe's limits), times are DateTime, the
state and the verdict enumerations."""

from __future__ import annotations

import datetime as dt
import math
import os
import re
import subprocess
import sys
import time

import pytest

from sofast_station.config import load_config
from sofast_station.web.opcua import UNECE_URI, unit_id
from sofast_station.devices.protocols import FacetRequest
from sofast_station.station.service import Service
from tests.conftest import ROOT, SMALL_STATION
from tests.web.serving import free_port, stop_server

from asyncua import ua   # a test dependency: missing, the suite fails (setup-env test installs it)

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


def _documented_paths() -> list[str]:
    text = (ROOT / "docs" / "opcua.md").read_text()
    return re.findall(r"^\| `([A-Za-z]+/[A-Za-z0-9_]+)` \|", text, flags=re.M)


def test_opcua_client_sees_the_tree_and_the_verdict_change(tmp_path, monkeypatch):
    from asyncua.sync import Client

    data = tmp_path / "data"
    port = free_port()
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

            client.load_data_type_definitions()            # the station's enumerations, as named values
            verdict_type, state_type = ua.FacetVerdict, ua.StationState
            # (asyncua names the member "pass_": pass is a Python keyword)
            assert [v.name.rstrip("_") for v in verdict_type] == ["none", "pass", "fail", "indeterminate", "invalid",
                                                                  "fault"]
            assert verdict_type(node("LastFacet/Verdict").read_value()).name == "none"
            assert state_type(node("Station/State").read_value()).name == "offline"
            assert node("Alarms/Offline").read_value() is True
            assert node("LastFacet/Verdict").read_data_type() == client.nodes.base_data_type.get_child(
                ["0:Enumeration", f"{ns}:FacetVerdict"]).nodeid
            # analog items: AnalogItemType with EURange where a limit applies, else BaseAnalogType; UNECE units
            fx = node("LastFacet/FocalLengthX")
            assert fx.read_type_definition() == ua.NodeId(ua.ObjectIds.AnalogItemType)
            units = fx.get_child("0:EngineeringUnits").read_value()
            assert (units.NamespaceUri, units.UnitId, units.DisplayName.Text) == (UNECE_URI, unit_id("MTR"), "m")
            assert unit_id("MTR") == 5067858                  # "MTR": 0x4D5452 (OPC UA Part 8)
            limits = fx.get_child("0:EURange").read_value()
            assert (limits.Low, limits.High) == pytest.approx((5.33 * 0.98, 5.33 * 1.02))
            twist = node("LastFacet/Twist")
            assert twist.get_child("0:EngineeringUnits").read_value().UnitId == unit_id("C84")
            assert twist.get_child("0:EURange").read_value().High == pytest.approx(1e-3)    # 1 mrad/m, in rad/m
            rms = node("LastFacet/SlopeRmsDesign")
            assert rms.get_child("0:EngineeringUnits").read_value().UnitId == unit_id("C25")
            assert (rms.get_child("0:EURange").read_value().Low, rms.get_child("0:EURange").read_value().High) \
                == (0.0, 3.0)
            cycle = node("LastFacet/CycleTime")
            assert cycle.read_type_definition() == ua.NodeId(ua.ObjectIds.BaseAnalogType)
            assert cycle.get_child("0:EngineeringUnits").read_value().UnitId == unit_id("SEC")
            assert node("Station/StateSince").read_data_type() == ua.NodeId(ua.ObjectIds.DateTime)
            seen = []

            def look(outcome):
                end = time.monotonic() + 60
                while node("LastFacet/CycleId").read_value() != outcome.cycle_id:
                    assert time.monotonic() < end, "the OPC UA server did not publish the facet"
                    time.sleep(0.05)
                seen.append({p: node(p).read_value() for p in (
                    "LastFacet/Serial", "LastFacet/Verdict", "LastFacet/Reasons", "LastFacet/FocalLengthX",
                    "LastFacet/Time", "Counters/Facets", "Counters/Pass", "Counters/Fault", "Counters/Yield")})

            cfg = load_config(config)
            service = Service(cfg, simulated_facets=[FacetRequest("SIM-0001"), FacetRequest("X-0002")],
                              console=lambda line: None, archiver_process=False)
            service.runner.hooks.append(look)
            try:
                outcomes = service.runner.run()
            finally:
                service.close()
            first, second = seen
            assert first["LastFacet/Serial"] == "SIM-0001" and verdict_type(first["LastFacet/Verdict"]).name == "pass_"
            assert first["LastFacet/FocalLengthX"] == pytest.approx(outcomes[0].record["focal_length_x_m"])
            measured = dt.datetime.fromisoformat(outcomes[0].record["time"])
            assert abs((first["LastFacet/Time"].replace(tzinfo=dt.timezone.utc) - measured).total_seconds()) < 1e-3
            assert (first["Counters/Facets"], first["Counters/Pass"], first["Counters/Yield"]) == (1, 1, 1.0)
            assert second["LastFacet/Serial"] == "X-0002" and verdict_type(second["LastFacet/Verdict"]).name == "fault"
            assert "dark everywhere" in second["LastFacet/Reasons"][0]
            assert math.isnan(second["LastFacet/FocalLengthX"])
            assert (second["Counters/Facets"], second["Counters/Fault"], second["Counters/Yield"]) == (2, 1, 0.5)
            # nobody writes: the verdict stays the station's
            with pytest.raises(ua.UaStatusCodeError):
                node("LastFacet/Verdict").write_value(ua.Variant(1, ua.VariantType.Int32))
            assert verdict_type(node("LastFacet/Verdict").read_value()).name == "fault"
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
        _the_documented_example_waits_out_a_slow_server(server.pid, endpoint)
    finally:
        stop_server(server)


def _the_documented_example_waits_out_a_slow_server(server_pid: int, endpoint: str) -> None:
    """Issue 43: the example of docs/opcua.md failed 3 of 3 at `load_data_type_definitions()` on a loaded
    machine: its client waited asyncua's default 4 s per request, and the starved server answered later. Here
    the example (the documented code as written, its endpoint the test server's) runs against a server that
    stops answering for 8 s, as a monitor given no processor does: the server is stopped (SIGSTOP) just
    before the client loads the data type definitions and continued 8 s later. A client that waits 4 s
    fails there; the documented one reads the last facet's verdict and units."""
    import signal
    import textwrap

    text = (ROOT / "docs" / "opcua.md").read_text().split("## Reading it", 1)[1]
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    documented = "opc.tcp://127.0.0.1:4840/sofast-station/"
    assert documented in code and "load_data_type_definitions()" in code
    lines = code.replace(documented, endpoint).splitlines()
    at = next(i for i, line in enumerate(lines) if "load_data_type_definitions()" in line)
    indent = lines[at][:len(lines[at]) - len(lines[at].lstrip())]
    lines.insert(at, f"{indent}import os, signal; os.kill({server_pid}, signal.SIGSTOP)  # continued 8 s later")
    script = "\n".join(lines) + "\n"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    example = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, env=env)
    try:
        end = time.monotonic() + 120
        while _state(server_pid) != "T":               # stopped by the example, connected
            assert example.poll() is None, example.communicate()
            assert time.monotonic() < end, "the example did not start"
            time.sleep(0.02)
        time.sleep(8.0)
    finally:
        os.kill(server_pid, signal.SIGCONT)
    out, err = example.communicate(timeout=300)
    assert example.returncode == 0, textwrap.shorten(err, 2000)
    verdict, figure = out.splitlines()
    assert verdict == "fault"                           # the last facet (X-0002) was a fault
    assert figure.startswith("nan m within ")           # no focal length, its unit and the recipe's limits


def _state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as fh:
        return fh.read().rsplit(")", 1)[1].split()[0]


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
    # the camera fault is the station's: the yield is over the 4 facets judged (result/health.py)
    assert out["Counters/Facets"] == 5 and out["Counters/Yield"] == 0.25
    assert out["LastFacet/Verdict"] == 5 and out["Station/State"] == 0          # fault; idle (enumerations)
    assert "Counters/Indeterminate" in _documented_paths()
