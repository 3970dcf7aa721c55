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
import datetime as _dt
import hmac
import logging
import math

from ..errors import ConfigError
from ..result.record import figure_uncertainty, figure_value
from ..result.shift import cycle_seconds
from ..result.specs import figure_specs
from ..times import parse_time
from .settings import OpcUaSettings

log = logging.getLogger(__name__)

ROOT = "SofastStation"
POLL_S = 0.25

#: The node tree: folder -> [(name, type, description, unit)]. docs/opcua.md documents the same table.
#: DOUBLE variables are analog items: ``AnalogItemType`` with an ``EURange`` where a limit applies (the last
#: facet's recipe's), else ``BaseAnalogType``; both carry ``EngineeringUnits`` (:data:`UNITS`).
STRING, DOUBLE, UINT32, BOOLEAN, STRINGS, DATETIME = "String", "Double", "UInt32", "Boolean", "String[]", "DateTime"
STATE, VERDICT = "StationState", "FacetVerdict"
#: The enumerations' values, in order (OPC UA enumerations count from 0).
ENUMS = {STATE: ("idle", "measuring", "fault", "paused", "offline"),
         VERDICT: ("none", "pass", "fail", "indeterminate", "invalid", "fault")}
#: Units of UN/CEFACT Recommendation 20 (common code, symbol, name): the OPC UA EUInformation of each.
UNITS = {"m": ("MTR", "m", "metre"), "1/m": ("C92", "m⁻¹", "reciprocal metre"), "mrad": ("C25", "mrad", "milliradian"),
         "rad/m": ("C84", "rad/m", "radian per metre"), "s": ("SEC", "s", "second"), "h": ("HUR", "h", "hour"),
         "GB": ("E34", "GB", "gigabyte"), "1": ("C62", "1", "one")}
UNECE_URI = "http://www.opcfoundation.org/UA/units/un/cefact"
TREE = {
    "Station": [
        ("Name", STRING, "the station's name ([station] name)", None),
        ("State", STATE, "idle, measuring, fault, paused or offline (enumeration StationState)", None),
        ("StateSince", DATETIME, "when the state last changed (UTC)", None),
        ("CalibrationRecord", STRING, "the radiometric calibration record in force", None),
        ("CalibrationAge", DOUBLE, "its age (NaN when unknown)", "h"),
        ("FreeDisk", DOUBLE, "free space in data_dir", "GB"),
        ("ArchiveBacklog", UINT32, "journal rows waiting for the workbook", None),
    ],
    "LastFacet": [
        ("CycleId", STRING, "the cycle's id (unique)", None),
        ("Serial", STRING, "the facet's serial", None),
        ("Recipe", STRING, "the recipe it was judged with", None),
        ("Verdict", VERDICT, "none (no facet yet), pass, fail, indeterminate, invalid or fault (enumeration "
                             "FacetVerdict)", None),
        ("Reasons", STRINGS, "every reason of a fail, invalid or fault", None),
        ("Time", DATETIME, "when it was measured (UTC)", None),
        ("FocalLengthX", DOUBLE, "focal length x (NaN: none); EURange: the recipe's limits", "m"),
        ("FocalLengthX_U", DOUBLE, "its expanded uncertainty, k = 2 (NaN: not reported)", "m"),
        ("FocalLengthY", DOUBLE, "focal length y; EURange: the recipe's limits", "m"),
        ("FocalLengthY_U", DOUBLE, "its expanded uncertainty, k = 2", "m"),
        ("Twist", DOUBLE, "twist; EURange: the recipe's limits", "rad/m"),
        ("Twist_U", DOUBLE, "its expanded uncertainty, k = 2", "rad/m"),
        ("SlopeRmsDesign", DOUBLE, "slope-error magnitude RMS against the design; EURange: 0 to the limit", "mrad"),
        ("SlopeRmsDesign_U", DOUBLE, "its expanded uncertainty, k = 2", "mrad"),
        ("SlopeRmsParabola", DOUBLE, "slope-error magnitude RMS against the fitted parabola; EURange: 0 to the "
                                     "limit", "mrad"),
        ("SlopeRmsParabola_U", DOUBLE, "its expanded uncertainty, k = 2", "mrad"),
        ("CycleTime", DOUBLE, "trigger to journal row (as the console and the page count it)", "s"),
    ],
    "Counters": [
        ("ShiftStart", DATETIME, "start of the shift the counters cover (UTC)", None),
        ("Facets", UINT32, "facets measured in the shift", None),
        ("Pass", UINT32, "passed", None),
        ("Fail", UINT32, "failed", None),
        ("Indeterminate", UINT32, "within U of a limit under the guarded decision rule", None),
        ("Invalid", UINT32, "invalid measurements", None),
        ("Fault", UINT32, "faults", None),
        ("Yield", DOUBLE, "passed / measured, 0 to 1 (NaN before the first facet)", "1"),
        ("CycleMedian", DOUBLE, "median cycle time", "s"),
        ("CycleWorst", DOUBLE, "worst cycle time", "s"),
    ],
    "Alarms": [
        ("Active", BOOLEAN, "any alarm in force", None),
        ("Offline", BOOLEAN, "no station process runs", None),
        ("Calibration", BOOLEAN, "stale calibration", None),
        ("Drift", BOOLEAN, "a drift alarm of the control-chart rules (any recipe)", None),
        ("Disk", BOOLEAN, "data_dir nearly full", None),
        ("Camera", BOOLEAN, "camera lost", None),
        ("Plc", BOOLEAN, "robot/PLC handshake lost", None),
        ("Line", BOOLEAN, "the line is failing as a line: faults in a row, yield far below the recipe's recent "
                          "yield, cycles at the deadline, or a machine too slow for it (result/health.py)", None),
        ("Messages", STRINGS, "every alarm in force, as text", None),
    ],
}

#: The last facet's figures: node name -> (record path, factor from the record's unit to the node's).
_FIGURES = {"FocalLengthX": ("focal_length_x_m", 1.0), "FocalLengthY": ("focal_length_y_m", 1.0),
            "Twist": ("twist_mrad_per_m", 1e-3), "SlopeRmsDesign": ("slope_rms_mrad.design.magnitude", 1.0),
            "SlopeRmsParabola": ("slope_rms_mrad.parabola.magnitude", 1.0)}
#: OPC UA's null DateTime (1601-01-01 UTC): a time not known yet.
NO_TIME = _dt.datetime(1601, 1, 1, tzinfo=_dt.timezone.utc)


def unit_id(code: str) -> int:
    """The EUInformation UnitId of a UN/CEFACT common code (OPC UA Part 8: its characters' bytes, big-endian)."""
    value = 0
    for ch in code:
        value = (value << 8) | ord(ch)
    return value


def _d(v, factor: float = 1.0) -> float:
    return float(v) * factor if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) \
        else math.nan


def _time(text) -> _dt.datetime:
    try:
        return parse_time(text).astimezone(_dt.timezone.utc) if text else NO_TIME
    except (TypeError, ValueError):
        return NO_TIME


def _enum(kind: str, value) -> int:
    names = ENUMS[kind]
    return names.index(value) if value in names else (names.index("offline") if kind == STATE else 0)


def values(snap: dict) -> dict:
    """The tree's values ("Folder/Name" -> value) from a LineData snapshot: numbers in the nodes' units,
    times as UTC datetimes, the state and the verdict as their enumerations' indices."""
    status, last, s = snap["status"], snap.get("last") or {}, snap["summary"]
    cal, disk = snap["calibration"], snap["disk"]
    out = {"Station/Name": snap["station"], "Station/State": _enum(STATE, status.get("state", "offline")),
           "Station/StateSince": _time(status.get("since")),
           "Station/CalibrationRecord": str(cal.get("record") or ""),
           "Station/CalibrationAge": _d(cal.get("age_h")), "Station/FreeDisk": _d(disk.get("free_gb")),
           "Station/ArchiveBacklog": int(disk.get("workbook_backlog") or 0),
           "LastFacet/CycleId": str(last.get("cycle_id") or ""), "LastFacet/Serial": str(last.get("serial") or ""),
           "LastFacet/Recipe": str(last.get("recipe") or ("default" if last else "")),
           "LastFacet/Verdict": _enum(VERDICT, last.get("verdict") or "none"),
           "LastFacet/Reasons": [str(r) for r in last.get("reasons") or []],
           "LastFacet/Time": _time(last.get("time")),
           "LastFacet/CycleTime": _d(cycle_seconds(last)),
           "Counters/ShiftStart": _time(snap["shift_start"]), "Counters/Facets": s.total,
           "Counters/Yield": _d(s.yield_fraction), "Counters/CycleMedian": _d(s.cycle_median_s),
           "Counters/CycleWorst": _d(s.cycle_worst_s)}
    for name, (path, factor) in _FIGURES.items():
        out[f"LastFacet/{name}"] = _d(figure_value(last, path), factor)
        out[f"LastFacet/{name}_U"] = _d(figure_uncertainty(last, path), factor)
    for verdict in ("pass", "fail", "indeterminate", "invalid", "fault"):
        out[f"Counters/{verdict.capitalize()}"] = int(s.counts.get(verdict, 0))
    kinds = {kind.split("-", 1)[0] for kind, _ in snap["alarms"]}      # drift-RECIPE -> drift
    out["Alarms/Active"] = bool(kinds)
    for name in ("Offline", "Calibration", "Drift", "Disk", "Camera", "Plc", "Line"):
        out[f"Alarms/{name}"] = name.lower() in kinds
    out["Alarms/Messages"] = [f"{kind}: {text}" for kind, text in snap["alarms"]]
    return out


def eu_ranges(recipe) -> dict:
    """The analog items' EURange ("Folder/Name" -> (low, high), node units) from *recipe*'s limits (its
    specification limits, :func:`~sofast_station.result.specs.figure_specs`; focal lengths from the focal
    powers' limits above 20 m)."""
    out = {"Counters/Yield": (0.0, 1.0)}
    for spec in figure_specs(recipe.design.focal_length_m, recipe.limits):
        axis = spec.key[-3].upper() if spec.key.startswith(("focal_length_", "curvature_")) else None
        if spec.key.startswith("focal_length_"):
            out[f"LastFacet/FocalLength{axis}"] = (spec.lsl, spec.usl)
        elif spec.key.startswith("curvature_") and spec.lsl > 0:
            out[f"LastFacet/FocalLength{spec.key[10].upper()}"] = (1.0 / spec.usl, 1.0 / spec.lsl)
        elif spec.key == "twist_mrad_per_m":
            out["LastFacet/Twist"] = (1e-3 * spec.lsl, 1e-3 * spec.usl)
        elif spec.key.startswith("slope_rms_mrad.") and spec.usl is not None:
            model = spec.key.split(".")[1]
            out[f"LastFacet/SlopeRms{model.capitalize()}"] = (0.0, float(spec.usl))
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
    # optional: asyncua is the opcua extra
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
        self._ranges: dict = {}
        self._range_values: dict = {}
        self._version = None
        self._stopping = False

    async def start(self) -> None:
        try:
            # optional: asyncua is the opcua extra
            from asyncua import Server, ua
            from asyncua.crypto.permission_rules import User, UserRole
            from asyncua.server.user_managers import UserManager
        except ImportError:
            raise ConfigError("[opcua] enabled = true needs the asyncua library: pip install "
                              "'sofast-station[opcua]' (or set enabled = false)") from None
        # optional: asyncua is the opcua extra
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
        self._building = server
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
        # optional: asyncua is the opcua extra
        from asyncua.common.structures104 import new_enum

        enums = {kind: (await new_enum(server, idx, kind, list(names))).nodeid for kind, names in ENUMS.items()}
        root = await server.nodes.objects.add_object(idx, ROOT)
        kinds = {STRING: (ua.VariantType.String, ""), DOUBLE: (ua.VariantType.Double, math.nan),
                 UINT32: (ua.VariantType.UInt32, 0), BOOLEAN: (ua.VariantType.Boolean, False),
                 STRINGS: (ua.VariantType.String, []), DATETIME: (ua.VariantType.DateTime, NO_TIME),
                 STATE: (ua.VariantType.Int32, _enum(STATE, "offline")), VERDICT: (ua.VariantType.Int32, 0)}
        ranges = eu_ranges(self.data.recipes["default"])
        for folder, variables in TREE.items():
            obj = await root.add_object(idx, folder)
            for name, kind, description, unit in variables:
                vtype, initial = kinds[kind]
                key = f"{folder}/{name}"
                if kind == DOUBLE:
                    node = await self._add_analog(obj, idx, key, name, description, unit, ranges.get(key))
                else:
                    node = await obj.add_variable(idx, name, ua.Variant(initial, vtype), varianttype=vtype,
                                                  datatype=enums.get(kind))
                    await node.write_attribute(ua.AttributeIds.Description,
                                               ua.DataValue(ua.Variant(ua.LocalizedText(description),
                                                                       ua.VariantType.LocalizedText)))
                if kind == STRINGS:
                    await node.write_attribute(ua.AttributeIds.ValueRank,
                                               ua.DataValue(ua.Variant(1, ua.VariantType.Int32)))
                self._nodes[key] = node
                self._types[key] = vtype
        await server.start()
        self.server = server
        self.namespace_index = idx
        log.info("OPC UA server at %s (%s; security %s)", self.settings.endpoint,
                 ", ".join(["anonymous read-only"] * self.settings.anonymous + [f"{len(users)} user(s)"] * bool(users)),
                 " and ".join(["None"] * self.settings.security_none
                              + ["Basic256Sha256 Sign & Encrypt"] * self.settings.encrypted))
        if users and self.settings.allow_plain_passwords:
            log.warning("OPC UA: allow_plain_passwords = true: a user's password may cross the network in clear text")

    async def _add_analog(self, parent, idx: int, key: str, name: str, description: str, unit: str, eu_range):
        """A Double variable of type AnalogItemType (with *eu_range*) or BaseAnalogType (without), with its
        EngineeringUnits and EURange properties (browse names in namespace 0, as the standard's)."""
        ua = self.ua
        item = ua.AddNodesItem()
        item.RequestedNewNodeId = ua.NodeId(f"{ROOT}.{key.replace('/', '.')}", idx)
        item.BrowseName = ua.QualifiedName(name, idx)
        item.NodeClass = ua.NodeClass.Variable
        item.ParentNodeId = parent.nodeid
        item.ReferenceTypeId = ua.NodeId(ua.ObjectIds.HasComponent)
        item.TypeDefinition = ua.NodeId(ua.ObjectIds.AnalogItemType if eu_range else ua.ObjectIds.BaseAnalogType)
        attrs = ua.VariableAttributes()
        attrs.DisplayName = ua.LocalizedText(name)
        attrs.Description = ua.LocalizedText(description)
        attrs.DataType = ua.NodeId(ua.ObjectIds.Double)
        attrs.Value = ua.Variant(math.nan, ua.VariantType.Double)
        attrs.ValueRank = ua.ValueRank.Scalar
        attrs.AccessLevel = attrs.UserAccessLevel = ua.AccessLevel.CurrentRead.mask
        item.NodeAttributes = attrs
        result = (await self._building.iserver.isession.add_nodes([item]))[0]
        result.StatusCode.check()
        node = self._building.get_node(result.AddedNodeId)
        code, symbol, long_name = UNITS[unit]
        units = ua.EUInformation(NamespaceUri=UNECE_URI, UnitId=unit_id(code), DisplayName=ua.LocalizedText(symbol),
                                 Description=ua.LocalizedText(long_name))
        await node.add_property(ua.NodeId(f"{item.RequestedNewNodeId.Identifier}.EngineeringUnits", idx),
                                ua.QualifiedName("EngineeringUnits", 0), units,
                                datatype=ua.NodeId(ua.ObjectIds.EUInformation))
        if eu_range:
            self._ranges[key] = await node.add_property(
                ua.NodeId(f"{item.RequestedNewNodeId.Identifier}.EURange", idx), ua.QualifiedName("EURange", 0),
                ua.Range(Low=float(eu_range[0]), High=float(eu_range[1])), datatype=ua.NodeId(ua.ObjectIds.Range))
            self._range_values[key] = tuple(eu_range)
        return node

    async def publish(self) -> bool:
        """Write the newest values when the station's files changed; True when it wrote. The analog items'
        EURange follows the last facet's recipe."""
        version = await asyncio.to_thread(self.data.version)
        if version == self._version:
            return False
        snap = await asyncio.to_thread(self.data.snapshot)
        for key, value in values(snap).items():
            await self._nodes[key].write_value(self.ua.Variant(value, self._types[key]))
        last = snap.get("last") or {}
        recipe = self.data.recipes.get(last.get("recipe") or "default", self.data.recipes["default"])
        for key, eu_range in eu_ranges(recipe).items():
            if key in self._ranges and tuple(eu_range) != self._range_values.get(key):
                await self._ranges[key].write_value(self.ua.Range(Low=float(eu_range[0]), High=float(eu_range[1])))
                self._range_values[key] = tuple(eu_range)
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
