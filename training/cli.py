"""`python -m training`: the segmentation lab's command line (train-seg: render training frames
from procedural towns, train RoadSegNet, export ONNX; needs the `.[train]` extra and a checkout,
since training/ is not part of the installed product)."""

import argparse
import logging
import sys

from common.config import FLIP_MODES, load_config
from common.errors import RoadmapError
from common.log import configure_logging
from training.archs import ARCHS

logger = logging.getLogger("roadmap.training")


def train_seg_options(p: argparse.ArgumentParser) -> None:
    """train-seg's options (training/train.py train_command reads them)."""
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
                   help="network size (training/archs.py; default s)")
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
                        "(for --init with --arch) and stop (training/prune.py)")
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
                        "crossing the view (default: training/data.py TURN_PROB)")
    p.add_argument("--synth-share", type=float, default=None,
                   help="share of the training frames rendered by training/synth.py, "
                        "the rest by the simulator's renderer, in tenths (default: "
                        "training/data.py SYNTH_SHARE)")
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
                        "a 2-core EPYC with AVX-512 BF16, training/bench/train_step.py, but "
                        "1.4-2.5x "
                        "on a CPU without native bfloat16 (AVX2 only: a warning says so; "
                        "default off: float32)")
    p.add_argument("--stream-junctions", default=None, type=lambda v: v.split(","),
                   metavar="D1,D2",
                   help="with --stream: the towns' junction-line doses (light, heavy), chunk k "
                        "of the stream drawn with dose k mod their number, one run on the mix "
                        "(default: light)")
    p.add_argument("--soup", default=None, type=lambda v: v.split(","), metavar="D1,D2",
                   help="one run per junction-line dose (light, heavy: training/data.py "
                        "JUNCTIONS), --frames, the budgets or --steps shared out evenly, and "
                        "their weights averaged into the export (default: one run, light)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m training", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("train-seg", help="train the segmentation model (needs .[train])")
    train_seg_options(p)
    g = p.add_argument_group("configuration")
    g.add_argument("--config", help="TOML file overriding the defaults")
    g.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one setting (repeatable; beats env ROADMAP_SECTION__KEY)")
    g.add_argument("--log-level", default="INFO")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Known errors (RoadmapError) become one line and exit 1, like `roadmap`'s commands."""
    args = build_parser().parse_args(argv)
    configure_logging(args.log_level)
    try:
        from training.train import train_command

        return int(train_command(args, load_config(args.config, sets=args.set)) or 0)
    except RoadmapError as exc:
        sys.stderr.write(f"python -m training {args.command}: error: {exc}\n")
        return 1
    except KeyboardInterrupt:
        return 130
    except Exception:
        logger.exception("training %s failed", args.command)
        return 1
