"""Container healthcheck: exit 0 when a process's liveliness token is visible through the router.

`python -m services.demo.health --role merger --id s0` (router from ROADMAP_BUS__CONNECT or
--connect). Used by compose.yaml; any plain Zenoh client could do the same liveliness get."""

import argparse
import signal
import sys

from common import keys


def main(argv: list[str] | None = None) -> int:
    from common.bus import open_session
    from common.config import load_config

    p = argparse.ArgumentParser(prog="python -m services.demo.health")
    p.add_argument("--role", required=True)
    p.add_argument("--id", required=True)
    p.add_argument("--connect", default=None)
    p.add_argument("--timeout", type=float, default=3.0)
    args = p.parse_args(argv)
    sets = [f'bus.connect=["{args.connect}"]'] if args.connect else []
    cfg = load_config(sets=sets)
    signal.alarm(int(args.timeout * 3) + 1)  # clients wait for the router forever: bound it
    with open_session(cfg.bus, "monitor") as session:  # a secure bus: the monitor's certificate
        replies = session.liveliness().get(keys.alive(args.role, args.id), timeout=args.timeout)
        alive = any(r.ok is not None for r in replies)
    sys.stderr.write(f"{keys.alive(args.role, args.id)}: {'alive' if alive else 'not alive'}\n")
    return 0 if alive else 1


if __name__ == "__main__":
    sys.exit(main())
