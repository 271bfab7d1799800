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
