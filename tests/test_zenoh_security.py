"""Zenoh secured by its own config file: mTLS with certificates made here (``cryptography``)
and user/password authentication. The authorised robot localizes; a peer with a certificate
from another authority, one without a certificate, one with a wrong password and a plain-TCP
one are refused."""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import zenoh
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from client.transports import SwarmlocError, ZenohClient
from service.engine.localization_service import LocalizationService
from service.maps.route_map import save_map
from service.server import free_port, running_server
from service.settings import Settings
from service.zenoh.config import zenoh_config

TOKEN = "http-token"


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> Path:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                       serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    return path


def _cert(subject: str, key: ec.EllipticCurvePrivateKey, issuer: str,
          issuer_key: ec.EllipticCurvePrivateKey, ca: bool = False) -> x509.Certificate:
    now = dt.datetime.now(dt.UTC)
    b = (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(_name(issuer))
         .public_key(key.public_key()).serial_number(x509.random_serial_number())
         .not_valid_before(now - dt.timedelta(minutes=5))
         .not_valid_after(now + dt.timedelta(days=1))
         .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if ca:
        b = b.add_extension(x509.KeyUsage(
            digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
            key_encipherment=False, data_encipherment=False, key_agreement=False,
            encipher_only=False, decipher_only=False), critical=True)
    else:
        b = b.add_extension(x509.SubjectAlternativeName(
            [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False).add_extension(x509.ExtendedKeyUsage(
                [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False)
    return b.sign(issuer_key, hashes.SHA256())


def _pki(d: Path, tag: str) -> dict[str, Path]:
    """A certificate authority and one leaf certificate signed by it (for 127.0.0.1)."""
    ca_key, leaf_key = ec.generate_private_key(ec.SECP256R1()), ec.generate_private_key(
        ec.SECP256R1())
    ca = _cert(f"{tag} CA", ca_key, f"{tag} CA", ca_key, ca=True)
    leaf = _cert(f"{tag} node", leaf_key, f"{tag} CA", ca_key)
    out = {"ca": d / f"{tag}-ca.pem", "cert": d / f"{tag}-cert.pem",
           "key": _write_key(leaf_key, d / f"{tag}-key.pem")}
    out["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    out["cert"].write_bytes(leaf.public_bytes(serialization.Encoding.PEM))
    return out


def _json5(path: Path, body: dict) -> Path:
    path.write_text(json.dumps(body, indent=1))  # JSON is JSON5
    return path


@pytest.fixture(scope="module")
def tls_server(tmp_path_factory: pytest.TempPathFactory, small_map) -> Iterator[dict]:
    d = tmp_path_factory.mktemp("zenoh_tls")
    maps = d / "maps"
    save_map(small_map, maps / "small")
    good, rogue = _pki(d, "fleet"), _pki(d, "rogue")
    (d / "users.txt").write_text("robot1:secret1\n")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    server_cfg = _json5(d / "service.json5", {
        "mode": "peer",
        "listen": {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "link": {"tls": {"root_ca_certificate": str(good["ca"]),
                             "listen_certificate": str(good["cert"]),
                             "listen_private_key": str(good["key"]),
                             "enable_mtls": True}},
            "auth": {"usrpwd": {"dictionary_file": str(d / "users.txt")}},
        },
        # access control: robot1 may only use its own keys
        "access_control": {
            "enabled": True,
            "default_permission": "deny",
            "rules": [{"id": "own-keys", "permission": "allow",
                       "flows": ["ingress", "egress"],
                       "messages": ["put", "query", "reply", "declare_subscriber",
                                    "declare_queryable"],
                       "key_exprs": ["swarmloc/robot1/**"]}],
            "subjects": [{"id": "robot1", "usernames": ["robot1"]}],
            "policies": [{"rules": ["own-keys"], "subjects": ["robot1"]}],
        },
    })
    settings = Settings(maps_dir=maps, host="127.0.0.1", port=free_port(), workers=2,
                        auth_token=TOKEN, zenoh_config_file=server_cfg)
    service = LocalizationService(settings)
    with running_server(service) as url:
        yield {"url": url, "endpoint": endpoint, "dir": d, "good": good, "rogue": rogue}


def _client_cfg(srv: dict, name: str, pki: dict[str, Path] | None, password: str | None
                ) -> Path:
    tls: dict = {"root_ca_certificate": str(srv["good"]["ca"])}
    if pki is not None:
        tls |= {"enable_mtls": True, "connect_certificate": str(pki["cert"]),
                "connect_private_key": str(pki["key"])}
    transport: dict = {"link": {"tls": tls}}
    if password is not None:
        transport["auth"] = {"usrpwd": {"user": "robot1", "password": password}}
    return _json5(srv["dir"] / f"{name}.json5", {"transport": transport})


def test_authorised_robot_localizes_over_mtls(tls_server, sunny2) -> None:
    cfg = _client_cfg(tls_server, "robot1", tls_server["good"], "secret1")
    z = ZenohClient([tls_server["endpoint"]], config_file=cfg, timeout=20)
    try:
        z.create_session("robot1", "small", seed=1)
        est = z.localize("robot1", sunny2.image_path(4).read_bytes(), t=0.0)
        assert est.seq == 1 and est.robot_id == "robot1"
    finally:
        z.close()
    # the session is the HTTP one, behind the token
    r = httpx.get(tls_server["url"] + "/sessions/robot1",
                  headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200 and r.json()["frames"] == 1


@pytest.mark.parametrize(("who", "use_rogue", "cert", "password"), [
    ("rogue", True, True, "secret1"),  # a certificate from another authority
    ("nocert", False, False, "secret1"),  # no client certificate (mTLS)
    ("badpass", False, True, "guess"),  # a good certificate, a wrong password
    ("nopass", False, True, None),  # a good certificate, no user/password
])
def test_unauthorised_peers_are_refused(tls_server, who, use_rogue, cert, password) -> None:
    pki = (tls_server["rogue"] if use_rogue else tls_server["good"]) if cert else None
    cfg = _client_cfg(tls_server, who, pki, password)
    with pytest.raises((zenoh.ZError, SwarmlocError)):
        z = ZenohClient([tls_server["endpoint"]], config_file=cfg, timeout=5)
        try:  # should the session open at all, no query may reach the service
            z.session("robot1")
        finally:
            z.close()


def test_access_control_keeps_a_robot_to_its_own_keys(tls_server, sunny2) -> None:
    httpx.put(tls_server["url"] + "/sessions/robot2", json={"map": "small"},
              headers={"Authorization": f"Bearer {TOKEN}"}).raise_for_status()
    cfg = _client_cfg(tls_server, "robot1-acl", tls_server["good"], "secret1")
    z = ZenohClient([tls_server["endpoint"]], config_file=cfg, timeout=3)
    try:
        try:  # its own keys pass the ACL: an answer, a session or a 404
            z.session("robot1")
        except SwarmlocError as exc:
            assert exc.status == 404
        for action in ({"action": "get"}, {"action": "delete"}):
            with pytest.raises(SwarmlocError) as exc:
                z._control("robot2", action)  # the ACL drops the query: no answer
            assert exc.value.status == 0
    finally:
        z.close()
    r = httpx.get(tls_server["url"] + "/sessions/robot2",
                  headers={"Authorization": f"Bearer {TOKEN}"})
    assert r.status_code == 200  # still there


def test_plain_tcp_gets_nowhere(tls_server) -> None:
    port = tls_server["endpoint"].rsplit(":", 1)[1]
    with pytest.raises(zenoh.ZError):
        zenoh.open(zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
