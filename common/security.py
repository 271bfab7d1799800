"""Security of the bus: role certificates (a CA and one certificate per role), the Zenoh TLS
settings of a process, and the router's access control (default deny, one rule set per role,
subjects by certificate common name over mutual TLS). deploy/README.md holds the threat model.

Transport-free: this module builds files and plain dicts of Zenoh config keys; common.bus
applies them to a zenoh.Config."""

import datetime
import ipaddress
import json
import logging
import os
from pathlib import Path

from common import keys
from common.errors import ConfigError

logger = logging.getLogger(__name__)

ROLES = ("router", "merger", "vehicle", "localizer", "monitor")
CA_CERT = "ca.pem"
CA_KEY = "ca.key"  # needed only to issue certificates: keep it off the machines that run roles
# names the router's certificate answers to: the local fleet (localhost, loopback) and compose's
# service name; `roadmap certs --host NAME` adds more
ROUTER_HOSTS = ("localhost", "127.0.0.1", "::1", "zenoh-router")
DEFAULT_DAYS = 365


def cert_path(cert_dir: str | os.PathLike, role: str) -> Path:
    return Path(cert_dir) / f"{role}.pem"


def key_path(cert_dir: str | os.PathLike, role: str) -> Path:
    return Path(cert_dir) / f"{role}.key"


# -- certificates ------------------------------------------------------------------------------


def write_certs(out: str | os.PathLike, *, hosts: tuple[str, ...] = (), days: int = DEFAULT_DAYS,
                reuse_ca: bool = False, now: datetime.datetime | None = None) -> list[Path]:
    """A CA (ca.pem, ca.key) and, for every role, <role>.pem + <role>.key signed by it, in OUT.

    Certificates carry the role as common name (the ACL's subject) and both TLS client and
    server use (a router also connects to other routers). The router's names are ROUTER_HOSTS
    plus `hosts`. reuse_ca: keep OUT's CA and issue new role certificates (rotation without
    redistributing ca.pem). Keys are EC P-256 in PKCS#8, written with mode 0600."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    now = now or datetime.datetime.now(datetime.UTC)
    if reuse_ca:
        try:
            ca_cert = x509.load_pem_x509_certificate((out / CA_CERT).read_bytes())
            ca_key = serialization.load_pem_private_key((out / CA_KEY).read_bytes(), None)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"reusing the CA needs {out / CA_CERT} and {out / CA_KEY}: "
                              f"{exc}") from exc
    else:
        ca_key = ec.generate_private_key(ec.SECP256R1())
        ca_cert = _ca_certificate(ca_key, now, days)
        _write_key(out / CA_KEY, ca_key)
        (out / CA_CERT).write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    written = [out / CA_CERT]
    for role in ROLES:
        key = ec.generate_private_key(ec.SECP256R1())
        names = (*ROUTER_HOSTS, *hosts) if role == "router" else (role,)
        cert = _role_certificate(role, key, ca_cert, ca_key, names, now, days)
        _write_key(key_path(out, role), key)
        cert_path(out, role).write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        written += [cert_path(out, role), key_path(out, role)]
    logger.info("certificates for %s in %s (valid %d days)", ", ".join(ROLES), out, days)
    return written


def _name(common_name: str):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "RoadMap"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _ca_certificate(key, now, days):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes

    return (x509.CertificateBuilder()
            .subject_name(_name("RoadMap CA")).issuer_name(_name("RoadMap CA"))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, key_cert_sign=True, crl_sign=True,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                           critical=False)
            .sign(key, hashes.SHA256()))


def _role_certificate(role, key, ca_cert, ca_key, names, now, days):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.x509.oid import ExtendedKeyUsageOID

    sans = []
    for n in names:
        try:
            sans.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            sans.append(x509.DNSName(n))
    ski = ca_cert.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    return (x509.CertificateBuilder()
            .subject_name(_name(role)).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(min(now + datetime.timedelta(days=days),
                                 ca_cert.not_valid_after_utc))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False,
                                         key_agreement=False, key_cert_sign=False, crl_sign=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ski),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))


def _write_key(path: Path, key) -> None:
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)  # also when the file was there before


def check_cert_dir(cert_dir: str | os.PathLike, role: str) -> None:
    """ConfigError unless cert_dir holds ca.pem and the role's certificate and key."""
    if role not in ROLES:
        raise ConfigError(f"unknown bus role {role!r} (known: {', '.join(ROLES)})")
    missing = [p for p in (Path(cert_dir) / CA_CERT, cert_path(cert_dir, role),
                           key_path(cert_dir, role)) if not p.is_file()]
    if missing:
        raise ConfigError(f"bus.tls_dir {cert_dir}: missing {', '.join(map(str, missing))} "
                          f"(make them with `roadmap certs --out {cert_dir}`)")


# -- zenoh settings ------------------------------------------------------------------------------


def tls_settings(cert_dir: str | os.PathLike, role: str, *, listen: bool) -> dict:
    """Zenoh config keys (path -> value) for mutual TLS with the role's certificate: a router
    presents it when it listens (and asks every client for one), every process when it
    connects. The peer's certificate must chain to ca.pem; a client checks the router's name."""
    check_cert_dir(cert_dir, role)
    d = Path(cert_dir).resolve()
    base = "transport/link/tls"
    out = {f"{base}/root_ca_certificate": str(d / CA_CERT),
           f"{base}/enable_mtls": True,
           f"{base}/connect_certificate": str(cert_path(d, role)),
           f"{base}/connect_private_key": str(key_path(d, role)),
           f"{base}/verify_name_on_connect": True,
           f"{base}/close_link_on_expiration": True}
    if listen:
        out[f"{base}/listen_certificate"] = str(cert_path(d, role))
        out[f"{base}/listen_private_key"] = str(key_path(d, role))
    return out


# What each role may do (DESIGN.md: Key space), as (messages, key expressions) per flow as the
# router sees it: "ingress" = what the role sends to the router, "egress" = what the router
# delivers to it. Anything not listed is denied (default_permission deny).
_ALIVE = "roadmap/alive"
_REGION_INGEST = keys.REGION_INGEST_ALL  # roadmap/region/*/*/ingest (grid.routing = "region")
_SERVER_TILES = keys.tileserver_tile_all("*")  # roadmap/tileserver/*/tile/*/*: a server's own
ROLE_RULES: dict[str, dict[str, list[tuple[list[str], list[str]]]]] = {
    "vehicle": {
        "ingress": [(["query"], ["roadmap/ingest/*", _REGION_INGEST]),
                    (["liveliness_token"], [f"{_ALIVE}/vehicle/*"]),
                    (["liveliness_query", "declare_liveliness_subscriber"],
                     [f"{_ALIVE}/merger/*"])],  # waits for the owner shard before sending
        "egress": [(["reply"], ["roadmap/ingest/*", _REGION_INGEST]),
                   (["liveliness_token"], [f"{_ALIVE}/merger/*"])],
    },
    "localizer": {
        "ingress": [(["query"], ["roadmap/tile/*/*", _SERVER_TILES]),
                    (["declare_subscriber"], ["roadmap/tile-update/*/*"]),
                    (["put"], ["roadmap/pose/*"]),
                    (["liveliness_token"], [f"{_ALIVE}/localizer/*"]),
                    (["liveliness_query", "declare_liveliness_subscriber"],
                     [f"{_ALIVE}/tileserver/*"])],  # spreads its reads over the tile servers
        "egress": [(["reply"], ["roadmap/tile/*/*", _SERVER_TILES]),
                   (["put"], ["roadmap/tile-update/*/*"]),
                   (["liveliness_token"], [f"{_ALIVE}/tileserver/*"])],
    },
    # shards, PostgreSQL workers (region ingest, lease peers' liveliness) and tile servers
    "merger": {
        "ingress": [(["declare_queryable", "reply"],
                     ["roadmap/ingest/*", _REGION_INGEST, "roadmap/tile/*/*", _SERVER_TILES,
                      "roadmap/stats/merger/*", "roadmap/stats/tileserver/*"]),
                    (["put"], ["roadmap/tile-update/*/*"]),
                    (["liveliness_token"], [f"{_ALIVE}/merger/*", f"{_ALIVE}/tileserver/*"]),
                    (["liveliness_query", "declare_liveliness_subscriber"],
                     [f"{_ALIVE}/merger/*"])],  # a worker watches its peers (rendezvous)
        "egress": [(["query"],
                    ["roadmap/ingest/*", _REGION_INGEST, "roadmap/tile/*/*", _SERVER_TILES,
                     "roadmap/stats/merger/*", "roadmap/stats/tileserver/*"]),
                   (["liveliness_token"], [f"{_ALIVE}/merger/*"])],
    },
    "monitor": {
        "ingress": [(["query"], ["roadmap/stats/**"]),
                    (["liveliness_query", "declare_liveliness_subscriber"], [f"{_ALIVE}/**"])],
        "egress": [(["reply"], ["roadmap/stats/**"]),
                   (["liveliness_token"], [f"{_ALIVE}/**"])],
    },
}
ALL_MESSAGES = ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]


def acl_config() -> dict:
    """The router's `access_control` section: default deny; each role's rules for its subject
    (certificate common name = role); routers (common name "router") mesh with full rights."""
    rules, subjects, policies = [], [], []
    for role, flows in ROLE_RULES.items():
        ids = []
        for flow, entries in flows.items():
            for i, (messages, key_exprs) in enumerate(entries):
                rule_id = f"{role}-{flow}-{i}"
                rules.append({"id": rule_id, "messages": messages, "flows": [flow],
                              "permission": "allow", "key_exprs": key_exprs})
                ids.append(rule_id)
        subjects.append({"id": role, "cert_common_names": [role]})
        policies.append({"id": role, "rules": ids, "subjects": [role]})
    rules.append({"id": "router-all", "messages": ALL_MESSAGES, "flows": ["ingress", "egress"],
                  "permission": "allow", "key_exprs": ["**"]})
    subjects.append({"id": "router", "cert_common_names": ["router"]})
    policies.append({"id": "router", "rules": ["router-all"], "subjects": ["router"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}


def acl_json5() -> str:
    """acl_config() as JSON (valid JSON5), one rule, subject or policy a line."""
    acl = acl_config()
    lines = ["{"]
    for key, value in acl.items():
        if isinstance(value, list):
            lines.append(f'  "{key}": [')
            lines += [f"    {json.dumps(item)}," for item in value]
            lines.append("  ],")
        else:
            lines.append(f'  "{key}": {json.dumps(value)},')
    return "\n".join(lines) + "\n}"
