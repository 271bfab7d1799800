"""`roadmap certs --out DIR`: a CA and a certificate + key per role (common.security), for
`roadmap up/demo --secure DIR`, `roadmap router` with bus.tls_dir, and compose.secure.yaml."""

import sys

from common.security import ROLES, write_certs


def command(args, cfg) -> int:
    written = write_certs(args.out, hosts=tuple(args.host or ()), days=args.days,
                          reuse_ca=args.reuse_ca)
    sys.stdout.write(f"{'issued' if args.reuse_ca else 'new CA and'} certificates for "
                     f"{', '.join(ROLES)} in {args.out}:\n")
    sys.stdout.writelines(f"  {p}\n" for p in written)
    sys.stdout.write("ca.key signs new certificates: keep it off the machines that run roles\n")
    return 0


def render_acl() -> str:
    """deploy/acl.json5: the router's access_control section as common.security builds it."""
    from common.security import acl_json5

    return ("// The role ACL of a RoadMap router (`access_control` of a Zenoh 1.x config),\n"
            "// generated from common/security.py ROLE_RULES:\n"
            "//   python -m services.certs > deploy/acl.json5\n"
            "// Default deny; subjects are certificate common names over mutual TLS (one per\n"
            "// role); `roadmap router` with bus.tls_dir applies it (deploy/README.md).\n"
            + acl_json5() + "\n")


if __name__ == "__main__":
    sys.stdout.write(render_acl())
