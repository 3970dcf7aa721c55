"""Issue 28: OPC UA on the plant network: Basic256Sha256 Sign & Encrypt with a certificate, and no password
in clear text unless the station file says so.

The server runs in this process (asyncua, on a free loopback port) on a stand-in for the journal's data;
the certificates are throwaway ones made in a temporary folder (nothing secret is committed).
"""

from __future__ import annotations

import asyncio
import dataclasses
import socket
from types import SimpleNamespace

import pytest

# asyncua is a test dependency (pyproject.toml's [test] extra, installed by 'setup-env test'): a missing one is
# a broken test environment and fails here, not a reason to skip the plant network's security tests.
import asyncua  # noqa: F401

from sofast_station.errors import ConfigError
from sofast_station.web.settings import opcua_settings


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _app_certificate(folder, name: str, uri: str, server: bool):
    """A throwaway OPC UA application certificate (DER) and key (PEM), made as OPC 10000-6 asks."""
    from asyncua.crypto.cert_gen import (dump_private_key_as_pem, generate_private_key,
                                         generate_self_signed_app_certificate)
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = generate_private_key()
    cert = generate_self_signed_app_certificate(
        key, name, {}, [x509.UniformResourceIdentifier(uri), x509.DNSName("localhost")],
        extended=[ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH], days=2)
    cert_path, key_path = folder / f"{name}.der", folder / f"{name}-key.pem"
    cert_path.write_bytes(cert.public_bytes(Encoding.DER))
    key_path.write_bytes(dump_private_key_as_pem(key))
    return cert_path, key_path


def _settings(tmp_path, **opcua):
    return opcua_settings(SimpleNamespace(path=str(tmp_path / "station.toml"), raw={"opcua": opcua}))


def test_passwords_without_encryption_are_a_decision(tmp_path):
    """Users with no certificate: their passwords would cross the network in clear text (policy None only),
    refused at load unless allow_plain_passwords = true; the certificate and key are checked as a pair."""
    with pytest.raises(ConfigError, match=r"passwords would cross the network in clear text.*certificate and "
                                          r"private_key.*allow_plain_passwords = true"):
        _settings(tmp_path, enabled=True, users={"scada": "a-password"})
    assert _settings(tmp_path, enabled=True, users={"scada": "a-password"}, allow_plain_passwords=True)
    cert, key = _app_certificate(tmp_path, "server", "urn:sofast-station:server", server=True)
    other_cert, _ = _app_certificate(tmp_path, "other", "urn:other", server=True)
    good = _settings(tmp_path, enabled=True, users={"scada": "a-password"}, certificate=cert.name, private_key=key.name)
    assert good.encrypted and good.certificate == str(cert) and not good.allow_plain_passwords
    with pytest.raises(ConfigError, match="give both certificate and private_key"):
        _settings(tmp_path, certificate=str(cert))
    with pytest.raises(ConfigError, match="do not belong together"):
        _settings(tmp_path, certificate=str(other_cert), private_key=str(key))
    with pytest.raises(ConfigError, match="cannot be read"):
        _settings(tmp_path, certificate=str(key), private_key=str(key))
    with pytest.raises(ConfigError, match="no endpoint would be left"):
        _settings(tmp_path, security_none=False)


def test_a_certificate_basic256sha256_cannot_use_is_refused_at_load(tmp_path):
    """Issue 43: an EC certificate (the page's kind) was accepted for OPC UA, whose Basic256Sha256 policy signs
    and encrypts with RSA: no client could connect. Refused at load, naming the key and what to give."""
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "station")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now)
            .not_valid_after(now + datetime.timedelta(days=30)).sign(key, hashes.SHA256()))
    (tmp_path / "ec.der").write_bytes(cert.public_bytes(serialization.Encoding.DER))
    (tmp_path / "ec-key.pem").write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                                            serialization.PrivateFormat.PKCS8,
                                                            serialization.NoEncryption()))
    with pytest.raises(ConfigError, match=r"holds an EC key, but the Basic256Sha256 policy signs and encrypts with "
                                          r"RSA.*RSA certificate of 2048 to 4096 bits"):
        _settings(tmp_path, enabled=True, certificate="ec.der", private_key="ec-key.pem")
    rsa_cert, rsa_key = _app_certificate(tmp_path, "server", "urn:sofast-station:server", server=True)
    assert _settings(tmp_path, enabled=True, certificate=rsa_cert.name, private_key=rsa_key.name).encrypted


class _Data:
    """What the publisher needs of LineData to start (it publishes nothing in this test): the station's name
    and recipes (the analog items' EURange comes from the default recipe's limits)."""

    config = SimpleNamespace(name="line-1")

    @property
    def recipes(self):
        from sofast_station.config import load_config
        from sofast_station.recipes import recipes_from_config
        from tests.conftest import ROOT

        return recipes_from_config(load_config(ROOT / "station.toml", use_camera_record=False))

    def close(self):
        pass


async def _read_name(endpoint, user=None, password=None, security=None, plain_text=False):
    """Connect as a client, read Station/Name, disconnect; returns the value."""
    from asyncua import Client, ua

    client = Client(endpoint, timeout=30)
    if security:
        await client.set_security_string(security)
    if user:
        client.set_user(user)
        client.set_password(password)
    if plain_text:                     # a client that sends the password as it is, ignoring the token policy
        policy = client.server_policy

        def server_policy(kind):
            found = policy(kind)
            return dataclasses.replace(found, SecurityPolicyUri=None) if kind == ua.UserTokenType.UserName else found
        client.server_policy = server_policy
    async with client:
        ns = await client.get_namespace_index("urn:sofast-station")
        node = await client.nodes.objects.get_child([f"{ns}:SofastStation", f"{ns}:Station", f"{ns}:Name"])
        return await node.read_value()


def test_sign_and_encrypt_with_a_certificate_and_no_clear_text_password(tmp_path):
    """The server offers None (anonymous readers) and Basic256Sha256 Sign & Encrypt; a user logs in over
    Sign & Encrypt, and over None with the token encrypted as the server asks; a password sent in clear
    text over None is refused (BadIdentityTokenRejected) before it is compared."""
    from asyncua import ua

    from sofast_station.web.opcua import APPLICATION_URI, OpcUaPublisher

    cert, key = _app_certificate(tmp_path, "server", APPLICATION_URI, server=True)
    client_cert, client_key = _app_certificate(tmp_path, "client", "urn:plant:scada", server=False)
    port = _free_port()
    endpoint = f"opc.tcp://127.0.0.1:{port}/sofast-station/"
    settings = _settings(tmp_path, enabled=True, endpoint=endpoint, users={"scada": "s3cret-pass"},
                         certificate=str(cert), private_key=str(key))
    secure = f"Basic256Sha256,SignAndEncrypt,{client_cert},{client_key}"

    async def scenario():
        publisher = OpcUaPublisher(_Data(), settings)
        await publisher.start()
        try:
            offered = {(e.SecurityPolicyUri.rsplit("#", 1)[-1], e.SecurityMode)
                       for e in await publisher.server.get_endpoints()}
            assert offered == {("None", ua.MessageSecurityMode.None_),
                               ("Basic256Sha256", ua.MessageSecurityMode.SignAndEncrypt)}
            assert await _read_name(endpoint) == ""                                      # anonymous, None
            assert await _read_name(endpoint, "scada", "s3cret-pass", security=secure) == ""
            assert await _read_name(endpoint, "scada", "s3cret-pass") == ""              # token encrypted
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await _read_name(endpoint, "scada", "s3cret-pass", plain_text=True)
            assert refused.value.code == ua.StatusCodes.BadIdentityTokenRejected
            with pytest.raises(ua.UaStatusCodeError):
                await _read_name(endpoint, "scada", "guess", security=secure)
        finally:
            await publisher.stop()
    asyncio.run(scenario())
