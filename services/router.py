"""`roadmap router`: a local Zenoh router (a Python session in router mode); with bus.tls_dir
(--config, ROADMAP_BUS__TLS_DIR or --set), over mutual TLS and enforcing the role ACL."""

from common.bus import run_router, stop_event


def main(listen: list[str], peers: list[str], tls_dir: str = "") -> None:
    run_router(listen, stop_event(), peers=peers, tls_dir=tls_dir)


def command(args, cfg) -> int:
    scheme = "tls" if cfg.bus.tls_dir else "tcp"
    main(args.listen or [f"{scheme}/127.0.0.1:7447"], args.peer, tls_dir=cfg.bus.tls_dir)
    return 0
