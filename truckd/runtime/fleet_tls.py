"""Only trucks of the fleet speak: certificates per truck (mutual TLS) and the router's
access control by certificate common name.

:func:`make_fleet` writes a fleet's certificate authority and one certificate per truck,
per operator and for the router (``cryptography`` package, the ``tls`` extra: ``pip
install 'truckd[tls]'``); :func:`router_config` and :func:`client_config` give the Zenoh
configurations (zenoh 1.x JSON, valid JSON5) that use them.  The router admits only TLS
links whose client certificate the fleet's authority signed (``enable_mtls``), and its
access control (default deny) lets a truck whose certificate names ``<id>``:

- publish only its own keys, ``truckd/<id>/state``, ``health``, ``plan``,
  ``characterize`` (never another truck's, nor its own ``inject``, ``platoon_fault`` or
  ``platoon_join``),
  hold its liveliness token ``truckd/<id>/alive``, answer queries on
  ``truckd/<id>/params``;
- subscribe to every ``truckd/**`` key (the platoon reads its predecessor's plan).

Only an operator certificate may query parameters (``truckd/*/params``), inject faults
(``truckd/*/inject``, ``truckd/*/platoon_fault``) or tell a truck to join
(``truckd/*/platoon_join``).  Every endpoint is on 127.0.0.1 unless
given otherwise; multicast scouting and gossip are off.
"""

from __future__ import annotations

import datetime
import ipaddress
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from truckd.errors import InputError

ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
"""A vehicle id or operator name: a Zenoh key chunk without wildcards, and a CN."""

TRUCK_PUBLISHES = ("state", "health", "plan", "characterize")
OPERATOR_PUTS = ("inject", "platoon_fault", "platoon_join")


@dataclass(frozen=True)
class Fleet:
    """The files of a fleet (PEM): ``ca.pem``, and ``<name>.pem`` with ``<name>-key.pem``
    for each truck, each operator and the router."""

    directory: Path
    trucks: tuple[str, ...]
    operators: tuple[str, ...]

    def cert(self, name: str) -> Path:
        return self.directory / f"{name}.pem"

    def key(self, name: str) -> Path:
        return self.directory / f"{name}-key.pem"

    @property
    def ca(self) -> Path:
        return self.directory / "ca.pem"


def check_names(names: Sequence[str], what: str) -> tuple[str, ...]:
    """Names usable as key chunks and common names; InputError naming the bad one."""
    for n in names:
        if not ID_RE.match(n) or n in ("router", "ca"):
            raise InputError(
                f"{what} {n!r}: expected letters, digits, '-' or '_' (1-64), not 'router'/'ca'"
            )
    if len(set(names)) != len(names):
        raise InputError(f"{what}: a name appears twice")
    return tuple(names)


def make_fleet(
    directory: str | Path,
    trucks: Sequence[str],
    operators: Sequence[str] = ("operator",),
    days: int = 365,
    hosts: Sequence[str] = ("127.0.0.1", "localhost"),
) -> Fleet:
    """Write a fleet's authority and certificates into ``directory`` (created; existing
    files are replaced).  Every certificate names ``hosts`` (IP addresses or DNS names)
    so any member may listen; ECDSA P-256 keys, valid ``days``.

    Long because each certificate is one chain of the ``cryptography`` builder's calls,
    written out so a reader can check every field, and the Zenoh configurations follow."""
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
    except ImportError:
        raise InputError(
            "making certificates needs the cryptography package: pip install 'truckd[tls]'"
        ) from None
    trucks_t = check_names(trucks, "truck")
    ops_t = check_names(operators, "operator")
    if set(trucks_t) & set(ops_t):
        raise InputError("a name is both a truck and an operator")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "truckd fleet CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    sans: list[x509.GeneralName] = []
    for h in hosts:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            sans.append(x509.DNSName(h))
    fleet = Fleet(out, trucks_t, ops_t)
    (out / "ca.pem").write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    for name in (*trucks_t, *ops_t, "router"):
        key = ec.generate_private_key(ec.SECP256R1())
        cert = (
            x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_name)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage(
                    [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
                ),
                critical=False,
            )
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .sign(ca_key, hashes.SHA256())
        )
        fleet.key(name).write_bytes(
            key.private_bytes(
                serialization.Encoding.PEM,
                serialization.PrivateFormat.PKCS8,
                serialization.NoEncryption(),
            )
        )
        fleet.key(name).chmod(0o600)
        fleet.cert(name).write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return fleet


def _tls(fleet: Fleet, name: str) -> dict[str, Any]:
    return {
        "root_ca_certificate": str(fleet.ca),
        "listen_certificate": str(fleet.cert(name)),
        "listen_private_key": str(fleet.key(name)),
        "connect_certificate": str(fleet.cert(name)),
        "connect_private_key": str(fleet.key(name)),
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }


def access_control(trucks: Sequence[str], operators: Sequence[str]) -> dict[str, Any]:
    """The router's ``access_control`` section (see the module docstring).

    Long because it is data: Zenoh's rules, subjects and policies written out literally,
    one dict each, to be read against Zenoh's access-control documentation."""
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    everyone = [*trucks, *operators]
    rules.append(
        {
            "id": "fleet reads",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"],
            "key_exprs": ["truckd/**"],
        }
    )
    rules.append(
        {
            "id": "fleet receives",
            "permission": "allow",
            "flows": ["egress"],
            "messages": [
                "put",
                "delete",
                "liveliness_token",
                "declare_subscriber",
                "declare_queryable",
                "declare_liveliness_subscriber",
            ],
            "key_exprs": ["truckd/**"],
        }
    )
    for v in trucks:
        rules.append(
            {
                "id": f"{v} publishes",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put", "delete"],
                "key_exprs": [f"truckd/{v}/{k}" for k in TRUCK_PUBLISHES],
            }
        )
        rules.append(
            {
                "id": f"{v} serves",
                "permission": "allow",
                "flows": ["ingress", "egress"],
                "messages": ["declare_queryable", "reply", "query", "liveliness_token"],
                "key_exprs": [f"truckd/{v}/params", f"truckd/{v}/alive"],
            }
        )
        subjects.append({"id": v, "cert_common_names": [v]})
        policies.append({"rules": ["fleet reads", "fleet receives", f"{v} publishes",
                                   f"{v} serves"], "subjects": [v]})  # fmt: skip
    rules.append(
        {
            "id": "operator acts",
            "permission": "allow",
            "flows": ["ingress"],
            "messages": ["put", "query"],
            "key_exprs": [f"truckd/*/{k}" for k in (*OPERATOR_PUTS, "params")],
        }
    )
    rules.append(
        {
            "id": "operator hears replies",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["reply"],
            "key_exprs": ["truckd/*/params"],
        }
    )
    for o in operators:
        subjects.append({"id": o, "cert_common_names": [o]})
        policies.append({"rules": ["fleet reads", "fleet receives", "operator acts",
                                   "operator hears replies"], "subjects": [o]})  # fmt: skip
    assert len(subjects) == len(everyone)
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _base(mode: str) -> dict[str, Any]:
    return {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
    }


def router_config(fleet: Fleet, listen: str = "tls/127.0.0.1:7449") -> dict[str, Any]:
    """The router's Zenoh configuration: TLS only, mutual, with the fleet's access
    control."""
    conf = _base("router")
    conf["listen"] = {"endpoints": [listen]}
    conf["connect"] = {"endpoints": []}
    conf["transport"] = {"link": {"protocols": ["tls"], "tls": _tls(fleet, "router")}}
    conf["access_control"] = access_control(fleet.trucks, fleet.operators)
    return conf


def client_config(fleet: Fleet, name: str, connect: str = "tls/127.0.0.1:7449") -> dict[str, Any]:
    """A truck's or an operator's Zenoh configuration: a client of the router, over TLS
    with its own certificate."""
    if name not in (*fleet.trucks, *fleet.operators):
        raise InputError(f"{name!r} is not in the fleet")
    conf = _base("client")
    conf["listen"] = {"endpoints": []}
    conf["connect"] = {"endpoints": [connect]}
    conf["transport"] = {"link": {"protocols": ["tls"], "tls": _tls(fleet, name)}}
    return conf
