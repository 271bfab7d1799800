"""`roadmap certs`: a CA and a certificate + key per role, common name = role, keys private;
--reuse-ca issues new role certificates under the same CA (rotation)."""

import stat

from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from common.security import ROLES
from tests.conftest import roadmap


def _cert(path):
    return x509.load_pem_x509_certificate(path.read_bytes())


def test_certs_writes_a_ca_and_every_role(tmp_path):
    res = roadmap("certs", "--out", tmp_path, "--host", "router.example.org", timeout=60)
    assert res.returncode == 0, res.stderr
    ca = _cert(tmp_path / "ca.pem")
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for role in ROLES:
        cert = _cert(tmp_path / f"{role}.pem")
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == role
        assert cert.issuer == ca.subject
        cert.verify_directly_issued_by(ca)
        eku = cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
        assert {ExtendedKeyUsageOID.CLIENT_AUTH, ExtendedKeyUsageOID.SERVER_AUTH} <= set(eku)
        assert stat.S_IMODE((tmp_path / f"{role}.key").stat().st_mode) == 0o600
    names = _cert(tmp_path / "router.pem").extensions.get_extension_for_class(
        x509.SubjectAlternativeName).value
    assert {"localhost", "zenoh-router", "router.example.org"} <= set(
        names.get_values_for_type(x509.DNSName))


def test_reuse_ca_rotates_role_certificates_only(tmp_path):
    assert roadmap("certs", "--out", tmp_path).returncode == 0
    ca_before = (tmp_path / "ca.pem").read_bytes()
    old = _cert(tmp_path / "vehicle.pem")
    res = roadmap("certs", "--out", tmp_path, "--reuse-ca", "--days", "30")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "ca.pem").read_bytes() == ca_before
    new = _cert(tmp_path / "vehicle.pem")
    assert new.serial_number != old.serial_number
    new.verify_directly_issued_by(_cert(tmp_path / "ca.pem"))
    days = (new.not_valid_after_utc - new.not_valid_before_utc).days
    assert 29 <= days <= 30


def test_reuse_ca_without_a_ca_is_a_one_line_error(tmp_path):
    res = roadmap("certs", "--out", tmp_path, "--reuse-ca")
    assert res.returncode == 1 and "ca.pem" in res.stderr and "Traceback" not in res.stderr


def test_deploy_acl_is_the_one_the_router_applies():
    """deploy/acl.json5 is generated: python -m services.certs > deploy/acl.json5"""
    import json

    import zenoh

    from common.security import acl_config
    from services.certs import render_acl
    from tests.conftest import REPO

    text = (REPO / "deploy" / "acl.json5").read_text()
    assert text == render_acl(), "stale: python -m services.certs > deploy/acl.json5"
    conf = zenoh.Config()
    conf.insert_json5("access_control", text)  # zenoh's own json5 parser takes it
    parsed = json.loads(conf.get_json("access_control"))
    assert parsed["default_permission"] == "deny" and parsed["enabled"] is True
    assert [r["id"] for r in parsed["rules"]] == [r["id"] for r in acl_config()["rules"]]


def test_compose_secure_mounts_each_role_its_own_key_only():
    yaml = __import__("pytest").importorskip("yaml")
    from tests.conftest import REPO

    base = yaml.safe_load((REPO / "compose.yaml").read_text())["services"]
    secure = yaml.safe_load((REPO / "compose.secure.yaml").read_text())["services"]
    assert set(secure) <= set(base)  # an override of compose.yaml's services
    roles = {"zenoh-router": "router", "merger-0": "merger", "merger-1": "merger",
             "vehicle": "vehicle", "localizer": "localizer"}
    for name, role in roles.items():
        mounts = [v.rsplit(":", 2)[1] for v in secure[name]["volumes"]]  # HOST:PATH:ro
        keys = {m for m in mounts if m.endswith(".key")}
        allowed = {f"/certs/{role}.key"} | ({"/certs/monitor.key"} if role == "merger" else set())
        assert keys == allowed and "/certs/ca.key" not in mounts, name
        assert "/certs/ca.pem" in mounts and f"/certs/{role}.pem" in mounts
        assert secure[name]["environment"]["ROADMAP_BUS__TLS_DIR"] == "/certs"
        if role != "router":
            assert secure[name]["environment"]["ROADMAP_BUS__CONNECT"].startswith('["tls/')
    assert secure["zenoh-router"]["command"][:3] == ["router", "--listen", "tls/[::]:7447"]


def test_acl_lets_vehicles_and_workers_use_the_region_ingest_keys():
    """grid.routing = "region": vehicles query roadmap/region/<rx>/<ry>/ingest, PostgreSQL
    workers declare it (and the fallback) and reply; localizers may not ingest there."""
    from common import keys
    from common.security import ROLE_RULES

    def allowed(role, flow, message):
        return {k for messages, exprs in ROLE_RULES[role][flow] if message in messages
                for k in exprs}

    assert keys.REGION_INGEST_ALL in allowed("vehicle", "ingress", "query")
    assert keys.REGION_INGEST_ALL in allowed("vehicle", "egress", "reply")
    assert keys.REGION_INGEST_ALL in allowed("merger", "ingress", "declare_queryable")
    assert keys.REGION_INGEST_ALL in allowed("merger", "ingress", "reply")
    assert keys.REGION_INGEST_ALL in allowed("merger", "egress", "query")
    assert f"{keys.PREFIX}/alive/merger/*" in allowed("merger", "ingress",
                                                       "declare_liveliness_subscriber")
    assert not any("region" in k for k in allowed("localizer", "ingress", "query"))
