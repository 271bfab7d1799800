"""`roadmap router`: a local Zenoh router (a Python session in router mode)."""

from common.bus import run_router, stop_event


def main(listen: list[str], peers: list[str]) -> None:
    run_router(listen, stop_event(), peers=peers)


def command(args, cfg) -> int:
    main(args.listen or ["tcp/127.0.0.1:7447"], args.peer)
    return 0
