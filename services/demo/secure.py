"""`roadmap demo/up --secure [DIR]`: the local fleet over mutual TLS with the role ACL.

One function turns the fleet's config and the option into the secure one: certificates from DIR
(or throwaway ones made in OUT/certs), bus.tls_dir, and the same setting in the environment
(ROADMAP_BUS__TLS_DIR) that every process of the fleet inherits, the demo's query helper
included; the supervisor then starts the router on a tls/ endpoint (fleet_scheme)."""

import dataclasses
import logging
import os
from pathlib import Path

from common.config import RoadmapConfig
from common.security import ROLES, check_cert_dir, write_certs

logger = logging.getLogger(__name__)

TLS_ENV = "ROADMAP_BUS__TLS_DIR"


def secure_fleet(cfg: RoadmapConfig, secure: str | None, out: Path) -> RoadmapConfig:
    """cfg unchanged when `secure` is None (no --secure); else the fleet's config over mTLS with
    the certificates in `secure`, or new throwaway ones in OUT/certs when it is empty."""
    if secure is None:
        return cfg
    if secure:
        cert_dir = Path(secure).resolve()
        for role in ROLES:
            check_cert_dir(cert_dir, role)
    else:
        cert_dir = Path(out).resolve() / "certs"
        write_certs(cert_dir)
    os.environ[TLS_ENV] = str(cert_dir)
    logger.info("secure fleet: mutual TLS and the role ACL, certificates in %s", cert_dir)
    connect = [e.replace("tcp/", "tls/", 1) for e in cfg.bus.connect]
    bus = dataclasses.replace(cfg.bus, tls_dir=str(cert_dir), connect=connect)
    return dataclasses.replace(cfg, bus=bus)


def fleet_scheme(env=None) -> str:
    """The router endpoints' scheme of a fleet whose processes get `env`."""
    return "tls" if (os.environ if env is None else env).get(TLS_ENV) else "tcp"
