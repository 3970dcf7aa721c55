"""The station as an OPC UA server for the plant's SCADA/MES (``[opcua]`` in station.toml; asyncua).

It publishes what the page shows, from the same :class:`~.data.LineData` (journal, live status), in the
node tree documented in docs/opcua.md: the station's state, the last facet (serial, recipe, verdict,
reasons, figures with their expanded uncertainties), the shift's counters and the alarms. Every variable
is read-only; clients connect anonymously unless ``anonymous = false``, and users listed in
``[opcua] users`` may log in by name (read-only as well). With ``certificate`` and ``private_key`` the
server offers security policy Basic256Sha256 with Sign & Encrypt (and None beside it unless
``security_none = false``); a password in clear text is refused unless ``allow_plain_passwords = true``.
It runs in the monitor process, never in the station's loop.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import math

from ..errors import ConfigError
from ..result.record import figure_uncertainty, figure_value
from .settings import OpcUaSettings

log = logging.getLogger(__name__)

ROOT = "SofastStation"
POLL_S = 0.25

#: The node tree: folder -> [(name, type, description)]. docs/opcua.md documents the same table.
STRING, DOUBLE, UINT32, BOOLEAN, STRINGS = "String", "Double", "UInt32", "Boolean", "String[]"
TREE = {
    "Station": [
        ("Name", STRING, "the station's name ([station] name)"),
        ("State", STRING, "idle, measuring, fault, paused or offline"),
        ("StateSince", STRING, "when the state last changed, ISO 8601"),
        ("CalibrationRecord", STRING, "the radiometric calibration record in force"),
        ("CalibrationAge_h", DOUBLE, "its age, hours (NaN when unknown)"),
        ("FreeDisk_GB", DOUBLE, "free space in data_dir, GB"),
        ("ArchiveBacklog", UINT32, "journal rows waiting for the workbook"),
    ],
    "LastFacet": [
        ("CycleId", STRING, "the cycle's id (unique)"),
        ("Serial", STRING, "the facet's serial"),
        ("Recipe", STRING, "the recipe it was judged with"),
        ("Verdict", STRING, "pass, fail, indeterminate, invalid or fault"),
        ("Reasons", STRINGS, "every reason of a fail, invalid or fault"),
        ("Time", STRING, "when it was measured, ISO 8601"),
        ("FocalLengthX_m", DOUBLE, "focal length x, m (NaN: none)"),
        ("FocalLengthX_U_m", DOUBLE, "its expanded uncertainty (k = 2), m (NaN: not reported)"),
        ("FocalLengthY_m", DOUBLE, "focal length y, m"),
        ("FocalLengthY_U_m", DOUBLE, "its expanded uncertainty (k = 2), m"),
        ("Twist_mrad_per_m", DOUBLE, "twist, mrad/m"),
        ("Twist_U_mrad_per_m", DOUBLE, "its expanded uncertainty (k = 2), mrad/m"),
        ("SlopeRmsDesign_mrad", DOUBLE, "slope-error magnitude RMS against the design, mrad"),
        ("SlopeRmsDesign_U_mrad", DOUBLE, "its expanded uncertainty (k = 2), mrad"),
        ("SlopeRmsParabola_mrad", DOUBLE, "slope-error magnitude RMS against the fitted parabola, mrad"),
        ("SlopeRmsParabola_U_mrad", DOUBLE, "its expanded uncertainty (k = 2), mrad"),
        ("CycleTime_s", DOUBLE, "trigger to journal, s"),
    ],
    "Counters": [
        ("ShiftStart", STRING, "start of the shift the counters cover, ISO 8601"),
        ("Facets", UINT32, "facets measured in the shift"),
        ("Pass", UINT32, "passed"),
        ("Fail", UINT32, "failed"),
        ("Indeterminate", UINT32, "within U of a limit under the guarded decision rule"),
        ("Invalid", UINT32, "invalid measurements"),
        ("Fault", UINT32, "faults"),
        ("Yield", DOUBLE, "passed / measured, 0 to 1 (NaN before the first facet)"),
        ("CycleMedian_s", DOUBLE, "median cycle time, s"),
        ("CycleWorst_s", DOUBLE, "worst cycle time, s"),
    ],
    "Alarms": [
        ("Active", BOOLEAN, "any alarm in force"),
        ("Calibration", BOOLEAN, "stale calibration"),
        ("Drift", BOOLEAN, "a drift alarm of the control-chart rules (any recipe)"),
        ("Disk", BOOLEAN, "data_dir nearly full"),
        ("Camera", BOOLEAN, "camera lost"),
        ("Plc", BOOLEAN, "robot/PLC handshake lost"),
        ("Messages", STRINGS, "every alarm in force, as text"),
    ],
}

_FIGURES = {"FocalLengthX": "focal_length_x_m", "FocalLengthY": "focal_length_y_m", "Twist": "twist_mrad_per_m",
            "SlopeRmsDesign": "slope_rms_mrad.design.magnitude",
            "SlopeRmsParabola": "slope_rms_mrad.parabola.magnitude"}


def _d(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else math.nan


def values(snap: dict) -> dict:
    """The tree's values ("Folder/Name" -> value) from a LineData snapshot."""
    status, last, s = snap["status"], snap.get("last") or {}, snap["summary"]
    cal, disk = snap["calibration"], snap["disk"]
    out = {"Station/Name": snap["station"], "Station/State": status.get("state", "offline"),
           "Station/StateSince": str(status.get("since") or ""),
           "Station/CalibrationRecord": str(cal.get("record") or ""),
           "Station/CalibrationAge_h": _d(cal.get("age_h")), "Station/FreeDisk_GB": _d(disk.get("free_gb")),
           "Station/ArchiveBacklog": int(disk.get("workbook_backlog") or 0),
           "LastFacet/CycleId": str(last.get("cycle_id") or ""), "LastFacet/Serial": str(last.get("serial") or ""),
           "LastFacet/Recipe": str(last.get("recipe") or ("default" if last else "")),
           "LastFacet/Verdict": str(last.get("verdict") or ""),
           "LastFacet/Reasons": [str(r) for r in last.get("reasons") or []],
           "LastFacet/Time": str(last.get("time") or ""),
           "LastFacet/CycleTime_s": _d(figure_value(last, "timings_s.until_journal")),
           "Counters/ShiftStart": snap["shift_start"], "Counters/Facets": s.total,
           "Counters/Yield": _d(s.yield_fraction), "Counters/CycleMedian_s": _d(s.cycle_median_s),
           "Counters/CycleWorst_s": _d(s.cycle_worst_s)}
    for name, path in _FIGURES.items():
        unit = next(n for n, *_ in TREE["LastFacet"] if n.startswith(name + "_") and "_U_" not in n)
        u_name = name + "_U_" + unit[len(name) + 1:]
        out[f"LastFacet/{unit}"] = _d(figure_value(last, path))
        out[f"LastFacet/{u_name}"] = _d(figure_uncertainty(last, path))
    for verdict in ("pass", "fail", "indeterminate", "invalid", "fault"):
        out[f"Counters/{verdict.capitalize()}"] = int(s.counts.get(verdict, 0))
    kinds = {kind.split("-", 1)[0] for kind, _ in snap["alarms"]}      # drift-RECIPE -> drift
    out["Alarms/Active"] = bool(kinds)
    for name in ("Calibration", "Drift", "Disk", "Camera", "Plc"):
        out[f"Alarms/{name}"] = name.lower() in kinds
    out["Alarms/Messages"] = [f"{kind}: {text}" for kind, text in snap["alarms"]]
    return out


#: The server's application URI (a certificate made for it names it as its subjectAltName URI).
APPLICATION_URI = "urn:sofast-station:server"


def _refuse_clear_text_passwords(server, ua) -> None:
    """Refuse a user-name token whose password comes in clear text over a channel without encryption.

    asyncua takes any password its user manager accepts, whatever the channel. With a certificate the
    server tells clients on the None endpoint to encrypt the password with it (the token's own security
    policy); a client that sends it in clear text over policy None (no peer certificate on the channel) is
    refused here with BadIdentityTokenRejected, before its password is even compared. On the Sign & Encrypt
    channel the whole message, password included, is encrypted.
    """
    from asyncua.common.utils import ServiceError

    iserver = server.iserver
    create = iserver.create_session

    def create_session(name, *args, **kwargs):
        session = create(name, *args, **kwargs)
        activate = session.activate_session

        def activate_session(params, peer_certificate):
            token = params.UserIdentityToken
            if (isinstance(token, ua.UserNameIdentityToken) and not token.EncryptionAlgorithm
                    and not peer_certificate):          # None: no certificate on the channel (b"")
                log.warning("OPC UA: refused user %r: the password came in clear text over security policy None "
                            "(connect with Basic256Sha256 Sign & Encrypt, or let the client encrypt the token)",
                            str(token.UserName)[:40])
                raise ServiceError(ua.StatusCodes.BadIdentityTokenRejected)
            return activate(params, peer_certificate)
        session.activate_session = activate_session
        return session
    iserver.create_session = create_session


class OpcUaPublisher:
    """The OPC UA server and the task that keeps its variables current.

    Parameters
    ----------
    data : LineData
    settings : OpcUaSettings
    """

    def __init__(self, data, settings: OpcUaSettings):
        self.data = data
        self.settings = settings
        self.endpoint = settings.endpoint
        self.server = None
        self._nodes: dict = {}
        self._types: dict = {}
        self._version = None
        self._stopping = False

    async def start(self) -> None:
        try:
            from asyncua import Server, ua
            from asyncua.crypto.permission_rules import User, UserRole
            from asyncua.server.user_managers import UserManager
        except ImportError:
            raise ConfigError("[opcua] enabled = true needs the asyncua library: pip install "
                              "'sofast-station[opcua]' (or set enabled = false)") from None
        from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset

        users = dict(self.settings.users)
        read_only = {ua.NodeId(t) for t in USER_TYPES} - {
            ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary),
            ua.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)}

        class ReadOnly(PermissionRuleset):
            """Every client may browse, read and subscribe; nobody may write, call or change the tree."""

            def check_validity(self, user, action_type_id, body):
                return action_type_id in read_only

        class Users(UserManager):
            def get_user(self, iserver, username=None, password=None, certificate=None):
                if username is None:                 # anonymous: only offered when [opcua] anonymous = true
                    return User(role=UserRole.User)
                if username in users and hmac.compare_digest(str(password or ""), users[username]):
                    return User(role=UserRole.User, name=username)
                return None

        self.ua = ua
        logging.getLogger("asyncua").setLevel(logging.WARNING)   # its address-space loading is chatty
        server = Server(user_manager=Users())
        await server.init()
        server.set_endpoint(self.settings.endpoint)
        server.set_server_name(f"sofast-station: {self.data.config.name}")
        await server.set_application_uri(APPLICATION_URI)
        policies = [ua.SecurityPolicyType.NoSecurity] if self.settings.security_none else []
        if self.settings.encrypted:
            await server.load_certificate(self.settings.certificate)
            await server.load_private_key(self.settings.private_key)
            policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
        server.set_security_policy(policies, permission_ruleset=ReadOnly())
        server.set_identity_tokens(([ua.AnonymousIdentityToken] if self.settings.anonymous else [])
                                   + ([ua.UserNameIdentityToken] if users else []))
        if not self.settings.allow_plain_passwords:
            _refuse_clear_text_passwords(server, ua)
        idx = await server.register_namespace(self.settings.namespace)
        root = await server.nodes.objects.add_object(idx, ROOT)
        kinds = {STRING: (ua.VariantType.String, ""), DOUBLE: (ua.VariantType.Double, math.nan),
                 UINT32: (ua.VariantType.UInt32, 0), BOOLEAN: (ua.VariantType.Boolean, False),
                 STRINGS: (ua.VariantType.String, [])}
        for folder, variables in TREE.items():
            obj = await root.add_object(idx, folder)
            for name, kind, description in variables:
                vtype, initial = kinds[kind]
                node = await obj.add_variable(idx, name, ua.Variant(initial, vtype), varianttype=vtype)
                await node.write_attribute(ua.AttributeIds.Description,
                                           ua.DataValue(ua.Variant(ua.LocalizedText(description),
                                                                   ua.VariantType.LocalizedText)))
                if kind == STRINGS:
                    await node.write_attribute(ua.AttributeIds.ValueRank,
                                               ua.DataValue(ua.Variant(1, ua.VariantType.Int32)))
                self._nodes[f"{folder}/{name}"] = node
                self._types[f"{folder}/{name}"] = vtype
        await server.start()
        self.server = server
        self.namespace_index = idx
        log.info("OPC UA server at %s (%s; security %s)", self.settings.endpoint,
                 ", ".join(["anonymous read-only"] * self.settings.anonymous + [f"{len(users)} user(s)"] * bool(users)),
                 " and ".join(["None"] * self.settings.security_none
                              + ["Basic256Sha256 Sign & Encrypt"] * self.settings.encrypted))
        if users and self.settings.allow_plain_passwords:
            log.warning("OPC UA: allow_plain_passwords = true: a user's password may cross the network in clear text")

    async def publish(self) -> bool:
        """Write the newest values when the station's files changed; True when it wrote."""
        version = await asyncio.to_thread(self.data.version)
        if version == self._version:
            return False
        snap = await asyncio.to_thread(self.data.snapshot)
        for key, value in values(snap).items():
            await self._nodes[key].write_value(self.ua.Variant(value, self._types[key]))
        self._version = version
        return True

    async def run(self) -> None:
        while not self._stopping:
            try:
                await self.publish()
            except Exception:
                log.exception("updating the OPC UA variables failed; trying again")
            await asyncio.sleep(POLL_S)

    async def stop(self) -> None:
        self._stopping = True
        if self.server is not None:
            await self.server.stop()
            self.server = None
        self.data.close()
