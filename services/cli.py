"""`roadmap`: one console script, argparse subcommands, each importing its service lazily.

Every handler is `fn(args, cfg) -> int | None` in the module named in COMMANDS; everything a
command does is also a plain Python function the tests call directly. Known errors (RoadmapError)
become one line and exit 1; anything else logs a traceback and exits 1."""

import argparse
import importlib
import logging
import sys

from common.config import FLIP_MODES, load_config, to_toml
from common.errors import RoadmapError
from common.log import configure_logging
from services.segtrain.archs import ARCHS

logger = logging.getLogger("roadmap")

WORLD_HELP = ("town | town:<km> | lanelet2:PATH | av2:PATH "
              "(default: Karlsruhe when ../shared/data exists)")

# subcommand -> "module:function"
COMMANDS = {
    "sim": "services.sim.cli:sim_command",
    "world": "services.sim.cli:world_command",
    "vehicle": "services.vehicle.node:main",
    "merger": "services.merger.node:main",
    "localize": "services.localizer.node:main",
    "router": "services.router:command",
    "demo": "services.demo.run:demo_command",
    "up": "services.demo.run:up_command",
    "bench": "services.demo.bench:bench_command",
    "train-seg": "services.segtrain.train:train_command",
    "dump-config": "services.cli:dump_config",
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="roadmap", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version="roadmap 0.1.0")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("sim", help="simulate drives and write drive logs")
    p.add_argument("--world", default=None, help=WORLD_HELP)
    p.add_argument("--out", required=True, help="directory for the drive logs")
    p.add_argument("--vehicles", type=int, default=1)
    p.add_argument("--drives", type=int, default=1, help="drives per vehicle")
    p.add_argument("--profile", choices=["mapping", "production"], default="mapping")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-km", type=float, default=None, help="cap each drive's length")
    p.add_argument("--no-images", action="store_true", help="labels and sensors only")
    _common(p)

    p = sub.add_parser("world", help="world tools")
    wsub = p.add_subparsers(dest="world_command", required=True)
    r = wsub.add_parser("render", help="render a world to a PNG in the paper's colours")
    r.add_argument("--world", default=None, help=WORLD_HELP)
    r.add_argument("--out", required=True)
    r.add_argument("--seed", type=int, default=0)
    _common(r)

    p = sub.add_parser("vehicle", help="on-vehicle mapping of one drive log")
    p.add_argument("--log", required=True, help="drive log directory")
    p.add_argument("--id", default=None, help="vehicle id (default: from the log)")
    p.add_argument("--state", default=None, help="directory for the outbox (default: LOG/.vehicle)")
    p.add_argument("--segmenter", choices=["onnx", "truth"], default=None)
    _common(p)

    p = sub.add_parser("merger", help="a tile merger shard")
    p.add_argument("--shard", type=int, required=True)
    p.add_argument("--shards", type=int, required=True)
    p.add_argument("--store", default=None, help="SQLite file (default ./merger-s<I>.sqlite)")
    _common(p)

    p = sub.add_parser("localize", help="localize a production drive log against the map")
    p.add_argument("--log", required=True)
    p.add_argument("--out", default=None)
    p.add_argument("--id", default=None)
    _common(p)

    p = sub.add_parser("router", help="run a local Zenoh router")
    p.add_argument("--listen", action="append", default=None, help="default tcp/127.0.0.1:7447")
    p.add_argument("--peer", action="append", default=[], help="another router to mesh with")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--config", default=None)
    p.add_argument("--set", action="append", default=[])

    for name, text in (("demo", "run the whole fleet locally and write a report"),
                       ("up", "start the deployment topology as local processes")):
        p = sub.add_parser(name, help=text)
        p.add_argument("--world", default=None, help=WORLD_HELP)
        p.add_argument("--vehicles", type=int, default=3)
        p.add_argument("--shards", type=int, default=2)
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--out", default="out")
        if name == "demo":
            p.add_argument("--scenario", choices=["default", "repaint"], default="default")
            p.add_argument("--chaos", action="store_true",
                           help="kill and restart a shard and a vehicle")
            p.add_argument("--small", action="store_true", help="a short drive (for tests)")
            p.add_argument("--viewer", type=int, default=None, metavar="PORT", nargs="?",
                           const=8765, help="keep `roadmap viewer` up on PORT during the run")
        else:
            p.add_argument("--listen", default=None,
                           help="router endpoint (default tcp/127.0.0.1:7447)")
        _common(p)

    p = sub.add_parser("bench", help="benchmark every stage and write bench.json")
    p.add_argument("--out", default="out")
    p.add_argument("--quick", action="store_true")
    _common(p)

    p = sub.add_parser("train-seg", help="train the segmentation model (needs .[train])")
    p.add_argument("--out", default=None,
                   help="output folder (default common/models; with --border-only, MODEL's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--minutes", type=float, default=45.0,
                   help="wall-clock budget of rendering + training (default 45)")
    p.add_argument("--frames", type=int, default=6000, help="training frames to render")
    p.add_argument("--steps", type=int, default=None, metavar="N",
                   help="train exactly N steps (the schedule spread over steps) in place of "
                        "--minutes' budget; without --render-minutes every frame is rendered: "
                        "a run that does not depend on the machine's speed")
    p.add_argument("--render-minutes", type=float, default=None,
                   help="rendering budget (default: 20 %% of --minutes, at most 10)")
    p.add_argument("--workers", type=int, default=1, help="processes rendering frames")
    p.add_argument("--no-cache", action="store_true",
                   help="do not read or write the rendered frames' cache (a temp-dir .npz)")
    p.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="where the rendered frames are cached (default: roadmap-segtrain in the "
                        "temp dir; 4800 frames take 4.4 GB)")
    p.add_argument("--device", default="cpu", help="torch device: cpu (2 threads) or cuda")
    p.add_argument("--batch", type=int, default=8, help="crops per training step")
    p.add_argument("--init", default=None,
                   help="fine-tune from a trained model: an exported RoadSegNet ONNX file (the "
                        "default architecture) or the roadseg.pt a run writes beside it (any)")
    p.add_argument("--arch", default="s", choices=list(ARCHS),
                   help="network size (services/segtrain/archs.py; default s)")
    p.add_argument("--stream", action="store_true",
                   help="train while --workers processes render (GPU runs: training starts after "
                        "the first 480 frames; --render-minutes is not used)")
    p.add_argument("--render-only", action="store_true",
                   help="render the training frames into the cache and stop (several training "
                        "runs with the same rendering settings then share them)")
    p.add_argument("--crop", default="384x224",
                   help="training windows WxH cut from the 640x360 frames, or full (whole "
                        "frames: about 2.7x the time per step; default 384x224)")
    p.add_argument("--full-after", type=float, default=1.0, metavar="FRAC",
                   help="train on --crop's windows for this share of the run, then on whole "
                        "frames (one run from scratch that ends as the fine-tunes do; "
                        "default 1: crops throughout)")
    p.add_argument("--refine-only", default=None, metavar="MODEL",
                   help="set the paint-border settings of a trained ONNX model (metadata "
                        "`refine`) on the calibration frames of these rendering settings, and "
                        "stop (done by every training run)")
    p.add_argument("--export-only", default=None, metavar="PT[,PT...]",
                   help="calibrate and export a run's saved weights (roadseg.pt, or an --ema "
                        "run's roadseg-last.pt) as that run would have, on the held-out frames "
                        "of --seed and --frames (give the run's; --soup DOSE: of that dose's "
                        "towns; --stream: a streamed run's, of --stream-junctions' towns), "
                        "with flip averaging and --border-frames, to "
                        "--out/roadseg.onnx, and stop; several runs' weights are averaged name "
                        "by name first")
    p.add_argument("--keep-offsets", action="store_true",
                   help="with --export-only: the weights carry their run's logit offsets "
                        "already (a run's roadseg.pt; not an --ema run's roadseg-last.pt): "
                        "export them as they are, setting the paint borders and the rest as "
                        "that run did (default: calibrate offsets on top)")
    p.add_argument("--border-only", default=None, metavar="MODEL",
                   help="fit the learned paint-border classifier of a trained ONNX model "
                        "(metadata `border_net`) on --frames town frames of --seed (use a seed "
                        "the model never trained on), keep it if it beats the model's "
                        "brightness rule on the last 10 %%, and stop")
    p.add_argument("--prune", default=None, metavar="MODEL",
                   help="prune an exported model of the default architecture to --arch's "
                        "channels at 1/4 resolution (greedily, by the loss on 48 of --frames "
                        "town frames of --seed), widen it to --arch, write --out/roadseg.pt "
                        "(for --init with --arch) and stop (services/segtrain/prune.py)")
    p.add_argument("--border-frames", type=int, default=0, metavar="N",
                   help="after training, fit the learned paint-border classifier (as "
                        "--border-only does) on N town frames of --border-seed, all rendered "
                        "(2880 on 2 cores: about 9.5 more minutes); default 0: none")
    p.add_argument("--no-flip-average", dest="flip_average", action="store_false",
                   help="leave the export's metadata `flip_average` off (default on: the "
                        "runtime averages the network's logits of the image and of its mirror "
                        "image, and the border classifier is fitted on those averaged logits)")
    p.add_argument("--sky-margin-deg", type=float, default=None, metavar="D",
                   help="write the export's metadata `sky_margin_deg`: the runtime leaves out "
                        "the rows above rays rising D degrees above level (-1: none, for a "
                        "network whose coarsest stage reads the whole frame, as m64's does); "
                        "default: not written (the runtime's default, 10)")
    p.add_argument("--sky-cut-training", action="store_true",
                   help="train, set the logit offsets and paint borders and fit the border "
                        "classifier on frames without the top rows that --sky-margin-deg "
                        "leaves out for the default camera, as the runtime will segment them "
                        "(also with --export-only)")
    p.add_argument("--border-seed", type=int, default=None,
                   help="the towns of the border classifier's frames (default: --seed + 31)")
    p.add_argument("--reexport", default=None, metavar="MODEL",
                   help="write a trained RoadSegNet ONNX file again as this version exports it "
                        "(weights and metadata kept; since 2026-11-25: a dynamic input height, "
                        "for OnnxSegmenter's sky rows) to --out/roadseg.onnx, check it, and stop")
    p.add_argument("--set-flip", choices=FLIP_MODES, default=None,
                   help="with --reexport: set what the runtime does with a frame's mirror "
                        "image (metadata `flip_average`, and `flip` for alternate): off, "
                        "average (a second, mirrored pass, the two averaged) or alternate (one "
                        "pass a frame, on the image and on its mirror in turn); its logit "
                        "offsets and border classifier stay as they were fitted (default: kept)")
    p.add_argument("--add-offsets", default=None, metavar="CLASS=LOGITS,...",
                   help="with --reexport: add logits to classes' rows of the head's bias, "
                        "where a run's logit offsets ride (e.g. lane_line=0.4 calls more "
                        "pixels lane line); road and the markings, by their report names")
    p.add_argument("--turn-prob", type=float, default=None,
                   help="share of training poses turned 15-90 deg off the route, lane lines "
                        "crossing the view (default: services/segtrain/data.py TURN_PROB)")
    p.add_argument("--synth-share", type=float, default=None,
                   help="share of the training frames rendered by services/segtrain/synth.py, "
                        "the rest by the simulator's renderer, in tenths (default: "
                        "services/segtrain/data.py SYNTH_SHARE)")
    p.add_argument("--iou-loss", type=float, default=0.0,
                   help="weight of a soft-Jaccard term (paint and curb classes) added to the "
                        "cross-entropy (default 0: cross-entropy alone)")
    p.add_argument("--hard-pixels", type=float, default=1.0,
                   help="share of each batch's pixels, those with the largest loss, that the "
                        "cross-entropy averages over (online hard example mining; default 1: "
                        "all pixels)")
    p.add_argument("--mirror-consistency", type=float, default=0.0, metavar="WEIGHT",
                   help="half of each batch is the other half mirrored, and this weight x the "
                        "divergence of each frame's and its mirror's class probabilities from "
                        "their average joins the loss (default 0: off)")
    p.add_argument("--ema", type=float, default=0.0, metavar="DECAY",
                   help="export the moving average of the weights over the training steps "
                        "(this decay per step, bias-corrected) in place of the last step's, "
                        "which are saved as roadseg-last.pt (default 0: off)")
    p.add_argument("--average-init", type=float, default=0.0, metavar="WEIGHT",
                   help="export (1 - WEIGHT) x the trained weights + WEIGHT x --init's (a "
                        "fine-tune averaged with the model it started from; the trained ones "
                        "are saved as roadseg-trained.pt, with --soup the last run's; default "
                        "0: the trained ones)")
    p.add_argument("--distill", type=float, default=0.0, metavar="WEIGHT",
                   help="add WEIGHT x the cross-entropy against the teacher's (--teacher, "
                        "else --init; frozen) flip-averaged class probabilities to the loss, "
                        "so that one pass learns what the runtime's two passes decide "
                        "(default 0: off)")
    p.add_argument("--teacher", default=None, metavar="MODEL.onnx",
                   help="with --distill: the teacher, an exported RoadSegNet of any size "
                        "(run by onnxruntime), e.g. a larger network (--arch xl) or the "
                        "packaged model for a network pruned from it (default: --init)")
    p.add_argument("--bf16", action="store_true",
                   help="run the training forward pass under bfloat16 autocast (weights, "
                        "optimizer and loss stay float32): 0.69-0.75x float32's time a step on "
                        "a 2-core EPYC with AVX-512 BF16, bench/bench_train_step.py, but 1.4-2.5x "
                        "on a CPU without native bfloat16 (AVX2 only: a warning says so; "
                        "default off: float32)")
    p.add_argument("--stream-junctions", default=None, type=lambda v: v.split(","),
                   metavar="D1,D2",
                   help="with --stream: the towns' junction-line doses (light, heavy), chunk k "
                        "of the stream drawn with dose k mod their number, one run on the mix "
                        "(default: light)")
    p.add_argument("--soup", default=None, type=lambda v: v.split(","), metavar="D1,D2",
                   help="one run per junction-line dose (light, heavy: services/segtrain/data.py "
                        "JUNCTIONS), --frames, the budgets or --steps shared out evenly, and "
                        "their weights averaged into the export (default: one run, light)")
    _common(p)

    p = sub.add_parser("dump-config", help="print the effective configuration as TOML")
    _common(p)
    for name, (text, options) in TOOL_PARSERS.items():
        options(sub.add_parser(name, help=text))
    return parser


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


# where the map and the fleet leave the system: name -> (help, options)
TOOL_PARSERS = {
    "export": ("export the map as GeoJSON or Lanelet2 OSM (WGS84)", _export),
    "viewer": ("a live web map of the fleet (local page, no internet)", _viewer),
    "status": ("the fleet at a glance: shards, tiles, rates, who is alive", _status),
    "trajectory": ("a demo's localized trajectory and its ground truth as TUM or KITTI files "
                   "(for evo)", _trajectory),
}


def dump_config(args, cfg) -> int:
    sys.stdout.write(to_toml(cfg))
    return 0


def command_config(args):
    """Effective config for a command: defaults < --config < env < --set < --connect/--mode."""
    sets = list(getattr(args, "set", []) or [])
    if getattr(args, "connect", None):
        sets.append("bus.connect=[" + ", ".join(f'"{c}"' for c in args.connect) + "]")
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
