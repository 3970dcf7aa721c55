"""``[web]`` and ``[opcua]`` in station.toml: the monitor's page and its OPC UA server.

Validated here, with messages that name the file, the section, the key, the value and what is allowed.
Importing this module imports no web or OPC UA library.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import re
import ssl
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ConfigError, check_table

_TIME = re.compile(r"^([01][0-9]|2[0-3]):[0-5][0-9]$")

#: Largest request body the page takes, bytes: an action's body is a few dozen bytes (a serial); a larger
#: one is refused (413) before it is read, so a client cannot fill the monitor's memory.
MAX_BODY_BYTES = 16 * 1024


def is_loopback(host: str) -> bool:
    """Whether *host* is this computer only (127.0.0.0/8, ::1, ``localhost``); anything else, a name
    included, may be reached from the network."""
    host = host.strip().strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class WebSettings:
    """``[web]``.

    Attributes
    ----------
    host : str
        Address the page is served on; 127.0.0.1 (this computer only) unless set.
    port : int
    token : str
        The token the guarded actions need (pause, resume, dump next, re-measure, serial by hand);
        empty: the page is read-only.
    keep_pictures : int
        How many facets' pictures (white frame, outline, slope-error map) the station keeps in data_dir.
    shift_starts : tuple of str
        Local times ("HH:MM") at which a shift starts; the page's shift runs from the latest one.
    nice : int
        How much lower than the station the monitor process runs (os.nice increment, 0-19). 2 by default:
        close enough to the station's share that the page and OPC UA keep answering on a busy machine (at 10
        the monitor got about 1 s of processor in 2 minutes and OPC UA never came up), while the measuring
        loop still wins a contested core (docs/reliability.md, "Under load").
    stale_after_s : float
        The last verdict is shown greyed (no verdict colour), with its age, once it is older than this, in
        seconds (60: three cycles of a 20 s line), or whenever the station is offline.
    """

    host: str = "127.0.0.1"
    port: int = 8080
    token: str = ""
    keep_pictures: int = 200
    shift_starts: tuple = ("06:00", "14:00", "22:00")
    nice: int = 2
    certificate: str = ""
    key: str = ""
    allow_plain_http: bool = False
    stale_after_s: float = 60.0
    #: What the monitor logs as it starts to serve (the certificate expired, or about to: :func:`certificate_dates`).
    warnings: tuple = ()

    @property
    def tls(self) -> bool:
        """Whether the page is served over HTTPS (``certificate`` and ``key`` given)."""
        return bool(self.certificate and self.key)

    def exposure(self, where: str = "[web]") -> str | None:
        """The start's warning when the page is reachable beyond this computer (None on loopback).

        Raises
        ------
        ConfigError
            Beyond loopback without HTTPS and without ``allow_plain_http = true``: serving the network in
            plain text is a decision the station file must state.
        """
        if is_loopback(self.host):
            return None
        if not self.tls and not self.allow_plain_http:
            raise ConfigError(
                f"{where} host = {self.host!r} serves the page beyond this computer over plain HTTP, where the "
                "token of every action crosses the network in clear text: give certificate and key (HTTPS, "
                "docs/network.md), or set allow_plain_http = true to decide for plain HTTP on a network you "
                "trust, or serve on host = \"127.0.0.1\"")
        how = "HTTPS" if self.tls else "plain HTTP (allow_plain_http = true: the token crosses the network in " \
                                       "clear text)"
        who = ("actions need [web] token" if self.token
               else "no [web] token: the page is read-only, and anyone who reaches it can read the line's results")
        return f"the line's page is served beyond this computer on {self.host}:{self.port} over {how}; {who}"


@dataclass(frozen=True)
class OpcUaSettings:
    """``[opcua]``.

    Attributes
    ----------
    enabled : bool
        Off by default.
    endpoint : str
        ``opc.tcp://HOST:PORT/PATH``; the host is 127.0.0.1 unless set.
    namespace : str
        The namespace URI of the station's nodes.
    anonymous : bool
        Whether clients may connect without a user name (always read-only).
    users : dict
        User name -> password of clients that may log in (read-only as well).
    certificate, private_key : str
        The server's certificate (PEM or DER) and its private key (PEM or DER, unencrypted), absolute paths;
        with them the server offers security policy Basic256Sha256 with Sign & Encrypt. "": none.
    security_none : bool
        Whether the endpoint without message security (policy None) is offered too (plain readers).
    allow_plain_passwords : bool
        Whether a user's password may come in clear text (over policy None, without the token encryption
        the server asks for); refused unless true.
    """

    enabled: bool = False
    endpoint: str = "opc.tcp://127.0.0.1:4840/sofast-station/"
    namespace: str = "urn:sofast-station"
    anonymous: bool = True
    users: dict = field(default_factory=dict)
    certificate: str = ""
    private_key: str = ""
    security_none: bool = True
    allow_plain_passwords: bool = False
    #: What the monitor logs as it starts the server (the certificate expired, or about to).
    warnings: tuple = ()

    @property
    def encrypted(self) -> bool:
        """Whether the server offers Basic256Sha256 Sign & Encrypt (a certificate and key are given)."""
        return bool(self.certificate and self.private_key)


def _where(config, section: str) -> str:
    return f"{config.path} [{section}]"


def _unknown(table: dict, allowed: set, where: str) -> None:
    check_table(table, allowed, where)


def web_settings(config) -> WebSettings:
    """The ``[web]`` table of *config* (a StationConfig), validated."""
    table = config.raw.get("web", {})
    where = _where(config, "web")
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    _unknown(table, {"host", "port", "token", "keep_pictures", "shift_starts", "nice", "certificate", "key",
                     "allow_plain_http", "stale_after_s"}, where)
    d = WebSettings()
    host = table.get("host", d.host)
    if not isinstance(host, str) or not host.strip():
        raise ConfigError(f"{where} host = {host!r}: give an address such as \"127.0.0.1\" (this computer "
                          "only) or \"0.0.0.0\" (every network interface)")
    port = table.get("port", d.port)
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise ConfigError(f"{where} port = {port!r}: must be a whole number from 1 to 65535 (0: any free port)")
    token = table.get("token", d.token)
    if not isinstance(token, str) or (token and len(token) < 8):
        raise ConfigError(f"{where} token = {token!r}: must be a string of at least 8 characters, or \"\" "
                          "for a read-only page")
    keep = table.get("keep_pictures", d.keep_pictures)
    if isinstance(keep, bool) or not isinstance(keep, int) or keep < 1:
        raise ConfigError(f"{where} keep_pictures = {keep!r}: must be a whole number of at least 1")
    starts = table.get("shift_starts", list(d.shift_starts))
    if not isinstance(starts, list) or not starts or not all(isinstance(t, str) and _TIME.match(t) for t in starts):
        raise ConfigError(f"{where} shift_starts = {starts!r}: must be a list of local times \"HH:MM\", "
                          "e.g. [\"06:00\", \"14:00\", \"22:00\"]")
    nice = table.get("nice", d.nice)
    if isinstance(nice, bool) or not isinstance(nice, int) or not 0 <= nice <= 19:
        raise ConfigError(f"{where} nice = {nice!r}: must be a whole number from 0 to 19")
    stale = table.get("stale_after_s", d.stale_after_s)
    if isinstance(stale, bool) or not isinstance(stale, (int, float)) or not 1.0 <= stale <= 86400.0:
        raise ConfigError(f"{where} stale_after_s = {stale!r}: must be a number of seconds from 1 to 86400 (the "
                          "last verdict is greyed once it is this old; 60 is three cycles of a 20 s line)")
    allow_plain = table.get("allow_plain_http", d.allow_plain_http)
    if not isinstance(allow_plain, bool):
        raise ConfigError(f"{where} allow_plain_http = {allow_plain!r}: must be true or false")
    cert, key = _pair(config, table, ("certificate", "key"), where, "(PEM files) to serve the page over HTTPS",
                      _check_tls_pair)
    warnings = (certificate_dates(cert, f"{where} certificate"),) if cert else ()
    settings = WebSettings(host.strip(), port, token, keep, tuple(sorted(starts)), nice, cert, key, allow_plain,
                           float(stale), tuple(w for w in warnings if w))
    settings.exposure(where)
    return settings


def _file(config, table: dict, name: str, where: str) -> str:
    """A file named by *name* in *table* (relative to the station file's folder), as an absolute path;
    "" when not given. ConfigError when it is not a string or not a file."""
    value = table.get(name, "")
    if not isinstance(value, str):
        raise ConfigError(f"{where} {name} = {value!r}: must be the path of a file (relative to the station file)")
    if not value:
        return ""
    path = Path(value).expanduser()
    if not path.is_absolute():
        path = Path(str(config.path)).parent / path
    if not path.is_file():
        raise ConfigError(f"{where} {name} = {value!r}: no such file ({path})")
    return str(path)


def _pair(config, table: dict, names: tuple, where: str, purpose: str, check) -> tuple[str, str]:
    """A certificate and its key (*names* in *table*) as absolute paths, both or neither ("", ""), checked
    together by *check* (certificate, key, where)."""
    cert, key = (_file(config, table, name, where) for name in names)
    if bool(cert) != bool(key):
        raise ConfigError(f"{where}: give both {names[0]} and {names[1]} {purpose}, or neither")
    if cert:
        check(cert, key, where)
    return cert, key


def _check_tls_pair(certificate: str, key: str, where: str) -> None:
    """The page's certificate and key load together (the ssl module's own check)."""
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(certificate, key)
    except (ssl.SSLError, OSError, ValueError) as exc:
        raise ConfigError(f"{where} certificate = {certificate!r} and key = {key!r} do not make a TLS server "
                          f"({exc}): give a PEM certificate (chain) and its PEM private key, unencrypted") from None


def opcua_settings(config) -> OpcUaSettings:
    """The ``[opcua]`` table of *config*, validated."""
    table = config.raw.get("opcua", {})
    where = _where(config, "opcua")
    if not isinstance(table, dict):
        raise ConfigError(f"{where} must be a table")
    _unknown(table, {"enabled", "endpoint", "namespace", "anonymous", "users", "certificate", "private_key",
                     "security_none", "allow_plain_passwords"}, where)
    d = OpcUaSettings()
    for key in ("enabled", "anonymous", "security_none", "allow_plain_passwords"):
        if not isinstance(table.get(key, False), bool):
            raise ConfigError(f"{where} {key} = {table[key]!r}: must be true or false")
    endpoint = table.get("endpoint", d.endpoint)
    if not isinstance(endpoint, str) or not re.match(r"^opc\.tcp://[^/:]+:[0-9]+(/.*)?$", endpoint):
        raise ConfigError(f"{where} endpoint = {endpoint!r}: must look like "
                          "\"opc.tcp://127.0.0.1:4840/sofast-station/\"")
    namespace = table.get("namespace", d.namespace)
    if not isinstance(namespace, str) or not namespace:
        raise ConfigError(f"{where} namespace = {namespace!r}: must be a non-empty URI string")
    users = table.get("users", {})
    if not isinstance(users, dict) or not all(isinstance(k, str) and isinstance(v, str) and v
                                              for k, v in users.items()):
        raise ConfigError(f"{where} users must be a table of user name = \"password\"")
    anonymous = table.get("anonymous", d.anonymous)
    if not anonymous and not users:
        raise ConfigError(f"{where} anonymous = false but no users are configured: nobody could connect; "
                          "add users = { NAME = \"PASSWORD\" } or allow anonymous reading")
    cert, key = _pair(config, table, ("certificate", "private_key"), where, "for Basic256Sha256 Sign & Encrypt",
                      _check_opcua_pair)
    security_none = table.get("security_none", d.security_none)
    allow_plain = table.get("allow_plain_passwords", d.allow_plain_passwords)
    if not cert and not security_none:
        raise ConfigError(f"{where} security_none = false but no certificate and private_key: no endpoint would be "
                          "left; give them (Basic256Sha256 Sign & Encrypt) or offer policy None")
    if users and not cert and not allow_plain:
        raise ConfigError(f"{where} users are configured but the server has no certificate: their passwords would "
                          "cross the network in clear text (security policy None). Give certificate and private_key "
                          "(the server then offers Basic256Sha256 Sign & Encrypt and encrypts passwords; "
                          "docs/opcua.md), or set allow_plain_passwords = true to decide for clear text on a network "
                          "you trust")
    warnings = (certificate_dates(cert, f"{where} certificate"),) if cert else ()
    return OpcUaSettings(table.get("enabled", d.enabled), endpoint, namespace, anonymous, dict(users), cert, key,
                         security_none, allow_plain, tuple(w for w in warnings if w))


def _load(path: str, pem, der, what: str, where: str):
    """A certificate or key file read by *pem* or *der* (by its first bytes); ConfigError naming it otherwise."""
    data = Path(path).read_bytes()
    try:
        return pem(data) if data.lstrip().startswith(b"-----BEGIN") else der(data)
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"{where} {what} = {path!r} cannot be read ({exc}): give a PEM or DER file"
                          + (", unencrypted" if what == "private_key" else "")) from None


def _read_certificate(path: str, where: str):
    # optional: cryptography comes with asyncua (the opcua extra), not as a dependency of ours
    from cryptography import x509

    return _load(path, x509.load_pem_x509_certificate, x509.load_der_x509_certificate, "certificate", where)


#: A certificate that expires within this many days is announced as the monitor starts (time to renew it).
EXPIRY_NOTICE_DAYS = 14


def certificate_dates(path: str, where: str, now=None) -> str | None:
    """A warning when the certificate *path* (PEM or DER; the first of a PEM chain) is not valid now or expires
    within :data:`EXPIRY_NOTICE_DAYS` days (*now*: tz-aware, the present by default); None when it is valid.

    An expired certificate still loads (the ssl module and asyncua do not look at its dates), and every
    browser and OPC UA client then refuses the station or asks the operator to click through: said at the
    start, it is renewed before that, or at least understood.
    """
    cert = _read_certificate(path, where)
    now = now or dt.datetime.now(dt.timezone.utc)
    start, end = cert.not_valid_before_utc, cert.not_valid_after_utc
    renew = "make a new certificate (docs/network.md, docs/opcua.md) and restart the station"
    def days(delta) -> str:
        return f"{delta.days} day{'' if delta.days == 1 else 's'}"
    if now > end:
        return (f"{where} {path} expired on {end:%Y-%m-%d %H:%M} UTC ({days(now - end)} ago): browsers and OPC UA "
                f"clients refuse it or warn their users; {renew}")
    if now < start:
        return (f"{where} {path} is not valid before {start:%Y-%m-%d %H:%M} UTC (is this computer's clock right?): "
                f"clients refuse it until then; check the clock, or {renew}")
    if end - now < dt.timedelta(days=EXPIRY_NOTICE_DAYS):
        return f"{where} {path} expires on {end:%Y-%m-%d %H:%M} UTC, in {days(end - now)}: {renew} before then"
    return None


#: Key sizes OPC UA's Basic256Sha256 policy allows for the application's RSA key (OPC 10000-7), bits.
OPCUA_RSA_BITS = (2048, 4096)


def _check_opcua_pair(certificate: str, private_key: str, where: str) -> None:
    """The OPC UA certificate (PEM or DER) and private key (PEM or DER, unencrypted) load, belong together and
    are what Basic256Sha256 signs and encrypts with: an RSA key of 2048 to 4096 bits (read with the
    cryptography package, which asyncua uses; imported only when they are given)."""
    # optional: cryptography comes with asyncua (the opcua extra), not as a dependency of ours
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import rsa

    cert = _read_certificate(certificate, where)
    key = _load(private_key, lambda b: serialization.load_pem_private_key(b, None),
                lambda b: serialization.load_der_private_key(b, None), "private_key", where)
    if cert.public_key().public_numbers() != key.public_key().public_numbers():
        raise ConfigError(f"{where} certificate = {certificate!r} and private_key = {private_key!r} do not belong "
                          "together: give the key the certificate was made for")
    public = cert.public_key()
    if not isinstance(public, rsa.RSAPublicKey):
        kind = type(public).__name__.replace("PublicKey", "").lstrip("_") or "non-RSA"
        raise ConfigError(f"{where} certificate = {certificate!r} holds an {kind} key, but the Basic256Sha256 policy "
                          "signs and encrypts with RSA (clients could not connect): give an RSA certificate of "
                          f"{OPCUA_RSA_BITS[0]} to {OPCUA_RSA_BITS[1]} bits (docs/opcua.md makes one)")
    if not OPCUA_RSA_BITS[0] <= public.key_size <= OPCUA_RSA_BITS[1]:
        raise ConfigError(f"{where} certificate = {certificate!r} holds a {public.key_size}-bit RSA key; "
                          f"Basic256Sha256 needs {OPCUA_RSA_BITS[0]} to {OPCUA_RSA_BITS[1]} bits: make a new "
                          "certificate (docs/opcua.md)")
