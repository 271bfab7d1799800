"""`roadmap`: one console script, argparse subcommands, each importing its service lazily.

Every handler is `fn(args, cfg) -> int | None` in the module named in COMMANDS; everything a
command does is also a plain Python function the tests call directly. Known errors (RoadmapError)
become one line and exit 1; anything else logs a traceback and exits 1."""

import argparse
import importlib
import logging
import sys

from common.config import load_config, to_toml
from common.errors import RoadmapError
from common.log import configure_logging

logger = logging.getLogger("roadmap")

WORLD_HELP = ("town | town:<km> | lanelet2:PATH | av2:PATH "
              "(default: Karlsruhe when ../shared/data exists)")

# subcommand -> "module:function"
COMMANDS = {
    "sim": "services.sim.cli:sim_command",
    "world": "services.sim.cli:world_command",
    "vehicle": "services.vehicle.node:main",
    "merger": "services.merger.node:main",
    "worker": "services.merger.worker:main",
    "tileserver": "services.merger.tileserver:main",
    "localize": "services.localizer.node:main",
    "router": "services.router:command",
    "demo": "services.demo.run:demo_command",
    "up": "services.demo.run:up_command",
    "bench": "services.bench.runner:bench_command",
    "eval": "services.eval.command:eval_command",
    "dump-config": "services.cli:dump_config",
    "certs": "services.certs:command",
    "export": "services.export.command:export_command",
    "viewer": "services.viewer.server:viewer_command",
    "status": "services.status:status_command",
    "trajectory": "services.demo.trajectories:trajectory_command",
}


def _common(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("configuration")
    g.add_argument("--config", help="TOML file overriding the defaults")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one setting (repeatable; beats env ROADMAP_SECTION__KEY)")
    g.add_argument("--log-level", default="INFO")
    z = p.add_argument_group("zenoh")
    z.add_argument("--connect", action="append", help="router endpoint, e.g. tcp/127.0.0.1:7447")
    z.add_argument("--mode", choices=["client", "peer"], help="zenoh mode (default client)")


def _sim(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", default=None, help=WORLD_HELP)
    p.add_argument("--out", required=True, help="directory for the drive logs")
    p.add_argument("--vehicles", type=int, default=1)
    p.add_argument("--drives", type=int, default=1, help="drives per vehicle")
    p.add_argument("--profile", choices=["mapping", "production"], default="mapping")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-km", type=float, default=None, help="cap each drive's length")
    p.add_argument("--no-images", action="store_true", help="labels and sensors only")
    _common(p)


def _world(p: argparse.ArgumentParser) -> None:
    wsub = p.add_subparsers(dest="world_command", required=True)
    r = wsub.add_parser("render", help="render a world to a PNG in the paper's colours")
    r.add_argument("--world", default=None, help=WORLD_HELP)
    r.add_argument("--out", required=True)
    r.add_argument("--seed", type=int, default=0)
    _common(r)


def _vehicle(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log", required=True, help="drive log directory")
    p.add_argument("--id", default=None, help="vehicle id (default: from the log)")
    p.add_argument("--state", default=None, help="directory for the outbox (default: LOG/.vehicle)")
    p.add_argument("--segmenter", choices=["onnx", "truth"], default=None,
                   help="shorthand for --set segmentation.kind=KIND")
    _common(p)


def _merger(p: argparse.ArgumentParser) -> None:
    p.add_argument("--shard", type=int, required=True)
    p.add_argument("--shards", type=int, required=True)
    p.add_argument("--store", default=None, help="SQLite file (default ./merger-s<I>.sqlite)")
    _common(p)


def _worker(p: argparse.ArgumentParser) -> None:
    p.add_argument("--id", default=None, help="worker name, unique in the fleet "
                   "(default HOST-PID)")
    p.add_argument("--store", default=None, help="postgresql://... (default merger.store)")
    _common(p)


def _tileserver(p: argparse.ArgumentParser) -> None:
    _worker(p)
    p.add_argument("--threads", type=int, default=2, help="serve threads (one connection each)")


def _localize(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log", required=True)
    p.add_argument("--out", default=None)
    p.add_argument("--id", default=None)
    _common(p)


def _router(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", default=None, help="default tcp/127.0.0.1:7447")
    p.add_argument("--peer", action="append", default=[], help="another router to mesh with")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--config", default=None)
    p.add_argument("--set", action="append", default=[])


def _fleet(p: argparse.ArgumentParser) -> None:
    """The options `demo` and `up` share: the world and the fleet's size."""
    p.add_argument("--world", default=None, help=WORLD_HELP)
    p.add_argument("--vehicles", type=int, default=3)
    p.add_argument("--shards", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out")
    p.add_argument("--store", default=None, metavar="postgresql://URL",
                   help="run --shards workers on this PostgreSQL database instead of SQLite "
                        "shards (the demo empties its tables first)")
    p.add_argument("--tile-servers", type=int, default=1,
                   help="read-only tile servers beside the workers (with --store)")


def _secure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--secure", nargs="?", const="", default=None, metavar="DIR",
                   help="mutual TLS + role ACL with the certificates in DIR (roadmap certs); "
                        "without DIR, throwaway ones in OUT/certs")


def _demo(p: argparse.ArgumentParser) -> None:
    _fleet(p)
    _secure(p)
    p.add_argument("--scenario", choices=["default", "repaint"], default="default")
    p.add_argument("--chaos", action="store_true", help="kill and restart a shard and a vehicle")
    p.add_argument("--small", action="store_true", help="a short drive (for tests)")
    p.add_argument("--viewer", type=int, default=None, metavar="PORT", nargs="?", const=8765,
                   help="keep `roadmap viewer` up on PORT during the run")
    _common(p)


def _up(p: argparse.ArgumentParser) -> None:
    _fleet(p)
    _secure(p)
    p.add_argument("--listen", default=None, help="router endpoint (default tcp/127.0.0.1:7447)")
    _common(p)


def _bench(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="out")
    p.add_argument("--quick", action="store_true")
    _common(p)


def _eval(p: argparse.ArgumentParser) -> None:
    p.add_argument("--suite", choices=["default", "quick"], default="default")
    p.add_argument("--world", action="append", default=None, help="a world instead of the "
                   "suite's (repeatable): " + WORLD_HELP)
    p.add_argument("--seeds", default=None, help="seeds instead of the suite's, e.g. 101-108")
    p.add_argument("--workers", type=int, default=2, help="drives at once (default 2)")
    p.add_argument("--vehicles", type=int, default=3, help="mapping vehicles per drive")
    p.add_argument("--out", default="out/eval")
    p.add_argument("--relocalize", metavar="RUN", default=None, help="re-localize the drives "
                   "of an earlier run (its --out) offline with today's localizer and --set, "
                   "and write the suite's eval.json for them to --out")
    p.add_argument("--truth-map", action="store_true", help="with --relocalize: the car "
                   "matches the world's true markings in the tiles it received, through the "
                   "tile codec, instead of the fleet's map (what the car loses to the map)")
    p.add_argument("--remerge", metavar="RUN", default=None, help="rebuild the maps of an "
                   "earlier run's drives offline from their shards' stored patches with today's "
                   "merger and --set, and write the suite's eval.json with their map figures")
    p.add_argument("--remap", metavar="RUN", default=None, help="make the maps of an earlier "
                   "run's drives again offline from their mapping drives' stored frames with "
                   "today's mapper and --set (vehicle., segmentation., merger.), and write the "
                   "suite's eval.json with their map figures")
    p.add_argument("--compare", nargs="+", metavar="RUN", default=None, help="two runs A B "
                   "(their --out, or eval.json files) paired by drive: per metric each side's "
                   "median / p90 / worst, the mean difference B - A and its paired t, the drives "
                   "better and worse, integrity; more pairs (A B A2 B2 ...: the suite and "
                   "held-out sets before and after) are pooled; writes --out/compare.json")
    _common(p)


def _certs(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, help="directory for ca.pem, <role>.pem, <role>.key")
    p.add_argument("--host", action="append", default=[],
                   help="another name of the router (repeatable; localhost, 127.0.0.1, ::1 and "
                        "zenoh-router are always in)")
    p.add_argument("--days", type=int, default=365, help="validity (default 365)")
    p.add_argument("--reuse-ca", action="store_true",
                   help="keep DIR's ca.pem + ca.key and issue new role certificates (rotation)")
    p.add_argument("--log-level", default="INFO")


def _export(p: argparse.ArgumentParser) -> None:
    p.add_argument("--format", choices=["geojson", "lanelet2"], required=True)
    p.add_argument("--out", required=True, help="file to write (.geojson / .osm)")
    p.add_argument("--from", dest="from_dir", metavar="DIR", default=None,
                   help="a demo's output folder, shard stores (*.sqlite) or a tiles.npz "
                        "(default: the running fleet, --connect)")
    p.add_argument("--classes", default=None, metavar="NAME,...",
                   help="classes to export (default: the markings lane_line, stop_line, "
                        "crosswalk, ground_sign)")
    p.add_argument("--road", action="store_true", help="also the road surface (polygons)")
    _common(p)


def _viewer(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", type=int, default=8765)
    p.add_argument("--host", default="127.0.0.1", help="address to serve on")
    p.add_argument("--from", dest="from_dir", metavar="DIR", default=None,
                   help="show a demo's output folder or shard stores instead of a live fleet")
    p.add_argument("--stats-every", type=float, default=3.0, metavar="S",
                   help="seconds between queries of the shards' stats and tile lists")
    _common(p)


def _status(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--from", dest="from_dir", metavar="DIR", default=None,
                   help="a demo's output folder or shard stores instead of a live fleet")
    p.add_argument("--interval", type=float, default=1.0, metavar="S",
                   help="seconds between the two stats samples patches/s is taken over")
    _common(p)


def _trajectory(p: argparse.ArgumentParser) -> None:
    p.add_argument("--from", dest="from_dir", metavar="DIR", required=True,
                   help="a demo's output folder")
    p.add_argument("--format", choices=["tum", "kitti"], default="tum")
    p.add_argument("--out", required=True, help="folder for estimate.* and truth.*")
    p.add_argument("--localizer", default="localizer",
                   help="the localizer run's folder in DIR (default localizer)")
    _common(p)


# subcommand -> (help, its options)
PARSERS = {
    "sim": ("simulate drives and write drive logs", _sim),
    "world": ("world tools", _world),
    "vehicle": ("on-vehicle mapping of one drive log", _vehicle),
    "merger": ("a tile merger shard", _merger),
    "worker": ("a tile merger worker holding regions by lease in PostgreSQL", _worker),
    "tileserver": ("a read-only tile server over the PostgreSQL store", _tileserver),
    "localize": ("localize a production drive log against the map", _localize),
    "router": ("run a local Zenoh router", _router),
    "demo": ("run the whole fleet locally and write a report", _demo),
    "up": ("start the deployment topology as local processes", _up),
    "bench": ("benchmark every stage and write bench.json", _bench),
    "eval": ("run the evaluation suite and write eval.json", _eval),
    "certs": ("write a CA and a certificate + key per role", _certs),
    "export": ("export the map as GeoJSON or Lanelet2 OSM (WGS84)", _export),
    "viewer": ("a live web map of the fleet (local page, no internet)", _viewer),
    "status": ("the fleet at a glance: shards, tiles, rates, who is alive", _status),
    "trajectory": ("a demo's localizer trajectory and its ground truth as TUM or KITTI files "
                   "(for evo)", _trajectory),
    "dump-config": ("print the effective configuration as TOML", _common),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="roadmap", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version="roadmap 0.1.0")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (text, options) in PARSERS.items():
        options(sub.add_parser(name, help=text))
    return parser


def dump_config(args, cfg) -> int:
    sys.stdout.write(to_toml(cfg))
    return 0


def command_config(args):
    """Effective config for a command: defaults < --config < env < --set < the shorthands
    (--connect, --segmenter, --mode)."""
    sets = list(getattr(args, "set", []) or [])
    if getattr(args, "connect", None):
        sets.append("bus.connect=[" + ", ".join(f'"{c}"' for c in args.connect) + "]")
    if getattr(args, "segmenter", None):
        sets.append(f'segmentation.kind="{args.segmenter}"')
    if getattr(args, "mode", None):
        sets.append(f'bus.mode="{args.mode}"')
    return load_config(getattr(args, "config", None), sets=sets)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(getattr(args, "log_level", "INFO"))
    try:
        cfg = command_config(args)
        module, func = COMMANDS[args.command].split(":")
        handler = getattr(importlib.import_module(module), func)
        return int(handler(args, cfg) or 0)
    except RoadmapError as exc:
        sys.stderr.write(f"roadmap {args.command}: error: {exc}\n")
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception:
        logger.exception("roadmap %s failed", args.command)
        return 1


if __name__ == "__main__":
    sys.exit(main())
