"""`roadmap train-seg`: render training frames from procedural towns, train RoadSegNet, export ONNX.

Reproducible from (seed, minutes): frames come only from seeded procedural towns (never the
Karlsruhe or Argoverse 2 benchmark worlds), with the renderer's randomization plus camera
height/pitch/intrinsics jitter here and colour/blur/noise augmentation in the training loop.
Training is time-boxed on 2 CPU threads; the model is exported at a fixed input size (opset 17),
checked against torch with onnxruntime and written with its card to --out. torch is imported
lazily (optional extra `.[train]`)."""

import json
import logging
import math
import time
from pathlib import Path

import cv2
import numpy as np

from common.classes import MARKINGS, NAMES, NUM_CLASSES, Cls
from common.errors import ConfigError
from common.segmentation import DEFAULT_SKY_MARGIN_DEG, META_KEY, OnnxSegmenter, session_metadata
from common.segmentation.refine import refine_paint_borders
from services.bench.heldout import IouAccumulator, mean_paint_iou, segmenter_iou
from training import data as seg_data
from training.archs import ARCHS
from training.weights import (  # noqa: F401 -- train-seg's tests read them here too
    NO_RENDER_BUDGET_S,
    THREADS,
    _load_init,
    _narrow_checked,
    check_export_file,
    class_weights,
    exported_model_like,
    frame_cache,
    save_weights,
)

logger = logging.getLogger(__name__)

INPUT_SIZE = (640, 360)  # (W, H) of the model input = the camera image (no resize)
CROP_HW = (224, 384)  # training crops (H, W) from the model-size frames (--crop; default)
BATCH = 8
LR_MAX = 6e-3
LR_FINETUNE = 2e-3  # peak learning rate when starting from a trained model (--init)
DEFAULT_CROP = f"{CROP_HW[1]}x{CROP_HW[0]}"
TRIM_EVERY = 50  # steps between heap trims (_heap_trimmer)
DEFAULT_OUT = Path("common/models")  # --out's default: the packaged model's folder
BORDER_SEED_OFFSET = 31  # --border-seed's default: --seed + 31, towns the network never saw


def out_dir(args) -> Path:
    """Where a train-seg command writes: --out; without it, the packaged model's folder, except
    for --border-only, which writes its log beside the model it changes in place."""
    if args.out:
        return Path(args.out)
    return Path(args.border_only).parent if args.border_only else DEFAULT_OUT


def train_command(args, cfg) -> int:
    out = out_dir(args)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    minutes = float(args.minutes)
    if args.turn_prob is None:
        args.turn_prob = seg_data.TURN_PROB
    if args.synth_share is None:
        args.synth_share = seg_data.SYNTH_SHARE
    seg_data.check_synth_share(args.synth_share)
    check_hard_pixels(args.hard_pixels)  # before minutes of rendering
    check_mirror(args.mirror_consistency, args.batch)
    check_ema(args.ema)
    check_average_init(args.average_init, args.init)
    check_distill(args.distill, args.init, not args.stream, args.teacher,
                  crop_size(args.crop, INPUT_SIZE[::-1]))  # the frames' size, before rendering
    check_full_after(args.full_after, args.crop)
    if training_sky_rows(args) and (args.prune or args.border_only):
        raise ConfigError("--sky-cut-training is a training run's (or its --export-only's): "
                          "leave it out of --prune and --border-only")
    if args.no_cache and args.cache_dir:
        raise ConfigError("--cache-dir with --no-cache: leave one out")
    for weights in export_weights(args):
        if not Path(weights).is_file():
            raise ConfigError(f"--export-only {weights}: no such file (a run's roadseg.pt "
                              "or roadseg-last.pt)")
    if args.border_seed is None:
        args.border_seed = args.seed + BORDER_SEED_OFFSET
    if args.border_frames and args.border_seed == args.seed:
        raise ConfigError(f"--border-seed {args.border_seed}: the border classifier must be "
                          "fitted on towns the network did not train on (another seed)")
    if args.keep_offsets and not args.export_only:
        raise ConfigError("--keep-offsets is --export-only's: give --export-only PT")
    flip = args.set_flip
    if flip is not None and not args.reexport:
        raise ConfigError("--set-flip rewrites a file's metadata: give --reexport MODEL")
    if args.add_offsets and not args.reexport:
        raise ConfigError("--add-offsets changes a file's head: give --reexport MODEL")
    offsets = class_offsets(args.add_offsets)  # refused here, before anything is written
    if args.reexport:
        # `flip` is written only for what `flip_average` cannot say, so that "average" and
        # "off" give the files they gave before the mode existed
        updates = {} if flip is None else {"flip_average": flip == "average",
                                           "flip": "alternate" if flip == "alternate" else None}
        logger.info("%s -> %s: %s", args.reexport, out / "roadseg.onnx",
                    reexport_onnx(args.reexport, out / "roadseg.onnx", offsets=offsets,
                                  **updates))
        return 0
    if args.border_only:
        return _border_only(args, out)
    if args.prune:
        from training.prune import prune_command

        return prune_command(args, out, INPUT_SIZE)
    warning = bf16_warning(args.bf16, args.device)  # a run that trains
    if warning:
        logger.warning(warning)
    if args.steps is not None and args.steps < 1:
        raise ConfigError(f"--steps {args.steps}: at least 1")
    check_soup(args)
    if args.stream_junctions and not args.stream:  # FrameStream checks the doses
        raise ConfigError("--stream-junctions: the junction-line doses of a streamed run's "
                          "towns; give --stream (without it: --soup DOSE)")
    if args.stream:
        if args.steps is not None:
            raise ConfigError("--steps with --stream: streamed frames arrive at the machine's "
                              "pace, so the run would not be reproducible; leave one out")
        if args.export_only:
            members = load_export_members(args)  # before the frames are rendered
            return _export_only(args, out, *streamed_held_out(args), members)
        return _train_streamed(args, out, t_start)
    if args.soup and not args.export_only:
        return _train_soup(args, out, t_start)
    members = load_export_members(args)  # before minutes of rendering
    for weights in export_weights(args):
        run_log = Path(weights).parent / "train_log.json"
        differences = (export_frame_differences(args, json.loads(run_log.read_text()))
                       if run_log.is_file() else [])
        if differences:
            logger.warning("--export-only %s: calibrating on held-out frames other than its "
                           "run's: %s", weights, "; ".join(differences))
    render_budget_s = _render_budget_s(args)
    frames, labels = seg_data.training_set(seed=args.seed, input_size=INPUT_SIZE,
                                           budget_s=render_budget_s, max_frames=args.frames,
                                           workers=args.workers, **frame_cache(args),
                                           turn_prob=args.turn_prob,
                                           synth_share=args.synth_share,
                                           junctions=export_junctions(args))
    render_s = time.perf_counter() - t_start
    if args.render_only:
        logger.info("%d training frames rendered in %.0f s (cached)", len(frames), render_s)
        return 0
    if args.export_only:
        n_val = validation_frames(len(frames))
        return _export_only(args, out, frames[:n_val], labels[:n_val], members)
    if args.refine_only:  # the calibration frames a training run on these frames would use
        n_cal = validation_frames(len(frames)) // 2
        refine = calibrate_refine(args.refine_only, frames[:n_cal], labels[:n_cal])
        set_metadata(args.refine_only, refine=refine)
        logger.info("%s: refine %s (set on the first %d of %d town frames, seed %d)",
                    args.refine_only, refine, min(n_cal, CALIBRATE_FRAMES), len(frames),
                    args.seed)
        return 0
    # the training time does not depend on whether the frames came from the cache: a rerun
    # with a warm cache trains exactly as long as the first run did
    train_s = max(minutes * 60.0 - max(render_s, render_budget_s) - 60.0, 60.0)
    result = train_and_export(frames, labels, out, seed=args.seed, train_s=train_s,
                              steps=args.steps, **run_options(args, frames.shape[1:3]))
    del frames, labels  # before the border step renders its own
    result["render_s"] = round(render_s, 1)
    return _finish(args, out, result, t_start)


def export_weights(args) -> list[str]:
    """--export-only PT[,PT...]: the saved weights it names (none without it)."""
    return [w for w in (args.export_only or "").split(",") if w]


def load_export_members(args) -> list[dict]:
    """--export-only's saved weights (none without it), each a run's {arch, state,
    frozen_norms}; refused unless all are of the first's architecture."""
    if not args.export_only:
        return []
    import torch

    paths = export_weights(args)
    members = [torch.load(p, map_location="cpu") for p in paths]
    first = members[0]
    for path, member in zip(paths[1:], members[1:], strict=True):
        if member["arch"] != first["arch"] or member.keys() != first.keys():
            raise ConfigError(f"--export-only: {path} is not of {paths[0]}'s architecture "
                              f"({member['arch']} against {first['arch']})")
    return members


def export_frame_differences(args, run_log: dict) -> list[str]:
    """How --export-only's rendering settings differ from those of the run that saved the
    weights (its train_log.json): each difference gives held-out frames other than the run's
    to calibrate on. A soup of runs, or another set on purpose, is allowed: the caller warns.
    A --steps run renders every frame and a budgeted one what its minutes allow, so an export
    of a --steps run without --steps calibrates on a set it renders anew (2026-11-28)."""
    diffs = []
    for key in ("seed", "frames"):
        if run_log.get(key) is not None and run_log[key] != getattr(args, key):
            diffs.append(f"--{key} {getattr(args, key)}, the run's {run_log[key]}")
    if "command" in run_log and ("--steps" in run_log["command"].split()) != (
            args.steps is not None):
        diffs.append("--steps given to " + ("the run, not to the export" if args.steps is None
                                            else "the export, not to the run"))
    doses = {member.get("junctions") for member in run_log.get("soup", [])}
    if len(doses) == 1 and doses != {export_junctions(args)}:
        diffs.append(f"junction lines {export_junctions(args)}, the run's {doses.pop()}"
                     " (--soup DOSE)")
    return diffs


def export_junctions(args) -> str:
    """The junction-line dose of one run's frames: --soup DOSE's (with --export-only, the
    towns of its calibration frames), else light."""
    return args.soup[0] if args.soup else "light"


def check_soup(args) -> None:
    """--soup: known junction-line doses, and none of the ways of running that it replaces
    (with --export-only, one dose: the towns whose held-out frames calibrate the export)."""
    if not args.soup:
        return
    for dose in args.soup:
        seg_data.check_junctions(dose)
    if args.export_only and len(args.soup) > 1:
        raise ConfigError(f"--soup {','.join(args.soup)} with --export-only: give one dose, "
                          "the towns of the held-out frames that calibrate the export")
    clash = [flag for flag, on in (("--stream", args.stream), ("--ema", args.ema),
                                   ("--refine-only", args.refine_only),
                                   ("--render-only", args.render_only)) if on]
    if clash:
        raise ConfigError(f"--soup with {', '.join(clash)}: leave one out")
    if args.frames // len(args.soup) < 8:
        raise ConfigError(f"--soup: --frames {args.frames} leaves under 8 frames to each of "
                          f"its {len(args.soup)} runs")
    if args.steps is not None and args.steps < len(args.soup):
        raise ConfigError(f"--soup: --steps {args.steps} leaves a run of its "
                          f"{len(args.soup)} no step")


def run_options(args, frame_hw) -> dict:
    """train_model's options as the command line gives them (the same for a plain, a soup
    and a streamed run), for frames of (H, W) `frame_hw`."""
    return {"device": args.device, "batch": args.batch, "init": args.init,
            "iou_loss": args.iou_loss, "arch": args.arch, "hard_pixels": args.hard_pixels,
            "mirror": args.mirror_consistency, "ema": args.ema,
            "average_init": args.average_init, "distill": args.distill,
            "teacher": args.teacher, "bf16": args.bf16,
            "crop_hw": crop_size(args.crop, frame_hw), "full_after": args.full_after,
            "top_rows": training_sky_rows(args)}


def training_sky_rows(args) -> int:
    """--sky-cut-training: the top rows of INPUT_SIZE frames that --sky-margin-deg leaves out
    for the default camera (as OnnxSegmenter computes them), which the run then trains without;
    else 0."""
    if not getattr(args, "sky_cut_training", False):
        return 0
    if args.sky_margin_deg is None or args.sky_margin_deg < 0:
        raise ConfigError("--sky-cut-training trains without the rows a sky margin leaves out: "
                          "give --sky-margin-deg D (D >= 0)")
    from common.camera import camera_from_config, sky_fraction
    from common.config import CameraConfig
    from common.segmentation import sky_rows_of

    camera = camera_from_config(CameraConfig())
    if (camera.width, camera.height) != INPUT_SIZE:
        raise ConfigError(f"--sky-cut-training: the default camera is {camera.width}x"
                          f"{camera.height}, the training frames {INPUT_SIZE[0]}x{INPUT_SIZE[1]}")
    return sky_rows_of(sky_fraction(camera, args.sky_margin_deg), INPUT_SIZE[1])


def training_sky_share(args) -> float:
    """training_sky_rows as a share of the frames' height (OnnxSegmenter's sky_fraction)."""
    return training_sky_rows(args) / INPUT_SIZE[1]


def check_top_rows(top_rows: int, frame_hw, crop_hw) -> None:
    """Rows left out at the top of every training frame (H, W) `frame_hw`: even (a teacher's
    1/2-resolution logits are cut with them), leaving some, and room for the crops (whole
    frames are whole frames without those rows)."""
    if top_rows < 0 or top_rows % 2 or top_rows >= frame_hw[0]:
        raise ConfigError(f"top rows {top_rows}: an even count >= 0 under the frames' "
                          f"{frame_hw[0]}")
    if tuple(crop_hw) != tuple(frame_hw) and crop_hw[0] > frame_hw[0] - top_rows:
        raise ConfigError(f"crops of {crop_hw[0]} rows do not fit frames of {frame_hw[0]} "
                          f"rows without their top {top_rows}")


def _render_budget_s(args) -> float:
    """Seconds of rendering: --render-minutes; a run by --steps renders every frame; else 20 %
    of --minutes, at most 10 minutes."""
    if args.render_minutes is not None:
        return 60.0 * args.render_minutes
    if args.steps is not None:
        return NO_RENDER_BUDGET_S
    return min(0.2 * float(args.minutes) * 60.0, 10 * 60.0)


def _train_soup(args, out: Path, t_start: float) -> int:
    """--soup D1,D2,...: one run per junction-line dose (data.JUNCTIONS), one after the other,
    each from --init on its own towns' frames (--frames, the render budget and the training
    budget or --steps shared out evenly), then the runs' weights averaged name by name (a
    "model soup": runs from one start average into one network that does what the runs do on
    average, at one network's cost), calibrated on the runs' held-out frames and exported as
    one run's would be.

    Why (2026-11-26, HISTORY.md, the evening section): two full runs of the recipe, one on light
    and one on heavy junction lines, averaged, scored mean lane line 0.001-0.003 above their
    mean (runs J1 + J2, run SH); averaging runs of the same towns gave less. Members of half a
    run each (the recipe's hour shared out) scored 0.005 below one full run: the soup pays
    only where full-length members fit, on a GPU."""
    doses, k = args.soup, len(args.soup)
    render_budget_s = _render_budget_s(args)
    train_s = max(float(args.minutes) * 60.0 - render_budget_s - 60.0, 60.0 * k) / k
    # each run's share of the render budget; a run that renders every frame (--steps) gives
    # each of its runs no budget either, so they are a lone run's frames (and cache) of the dose
    run_budget_s = render_budget_s if render_budget_s >= NO_RENDER_BUDGET_S else render_budget_s / k
    states, held, runs, render_s = [], [], [], 0.0
    for i, dose in enumerate(doses):
        t0 = time.perf_counter()
        frames, labels = seg_data.training_set(
            seed=args.seed, input_size=INPUT_SIZE, budget_s=run_budget_s,
            max_frames=args.frames // k, workers=args.workers, **frame_cache(args),
            turn_prob=args.turn_prob, synth_share=args.synth_share, junctions=dose)
        render_s += time.perf_counter() - t0
        logger.info("soup run %d of %d: junction lines %s, %d frames", i + 1, k, dose,
                    len(frames))
        model, frozen_norms, held_out, run = train_model(
            frames, labels, out, seed=args.seed, train_s=train_s,
            steps=None if args.steps is None else args.steps // k,
            **run_options(args, frames.shape[1:3]))
        # the held-out arrays are views of this run's frames: copied, so the frames can go
        x_val, y_val, frames_val, labels_val = held_out
        held.append((x_val, y_val, frames_val.copy(), labels_val.copy()))
        del frames, labels, held_out
        states.append({name: v.detach().clone() for name, v in model.state_dict().items()})
        runs.append({"junctions": dose, **run})
    model.load_state_dict(average_states(states))
    x_val, y_val, frames_val, labels_val = _calibration_first(held)
    exported = calibrate_and_export(model, x_val, y_val, frames_val, labels_val, out,
                                    seed=args.seed, frozen_norms=frozen_norms,
                                    sky_fraction=training_sky_share(args))
    result = {"soup": runs, "steps": sum(r["steps"] for r in runs),
              "frames": sum(r["frames"] for r in runs),
              "train_s": round(sum(r["train_s"] for r in runs), 1),
              "render_s": round(render_s, 1),
              **{key: runs[0][key] for key in ("class_weights", "lr_max", "seed", "device",
                                               "batch", "init", "arch", "iou_loss_weight",
                                               "hard_pixels", "mirror_consistency", "average_init",
                                               "distill", "teacher", "bf16", "crop_hw",
                                               "full_after", "frozen_norms", "top_rows")},
              **exported}
    return _finish(args, out, result, t_start)


def average_states(states: list[dict], weights: list[float] | None = None) -> dict:
    """The name-by-name mean of state dicts of one architecture, weighted by `weights` (they
    sum to 1; default equal), integer buffers (batch norms' step counts) from the first."""
    weights = [1.0 / len(states)] * len(states) if weights is None else weights
    return {name: (sum(w * st[name] for w, st in zip(weights, states, strict=True))
                   if v.is_floating_point() else v)
            for name, v in states[0].items()}


def check_average_init(weight: float, init: str | None) -> None:
    """--average-init needs --init and a weight in [0, 1) (0: off)."""
    if not 0.0 <= weight < 1.0:
        raise ConfigError(f"--average-init {weight:g}: the weight must be in [0, 1) (0: off)")
    if weight and not init:
        raise ConfigError("--average-init: averages with --init's weights; give --init")


def _calibration_first(held: list[tuple]) -> tuple:
    """The runs' held-out frames as one run's: every run's first half (calibration) ahead of
    every run's second half (validation), as calibrate_and_export splits them (to within a
    frame where a run holds out an odd number)."""
    import torch

    halves = [len(h[0]) // 2 for h in held]
    first = [[part[:n] for part in h] for h, n in zip(held, halves, strict=True)]
    second = [[part[n:] for part in h] for h, n in zip(held, halves, strict=True)]
    joined = []
    for j in range(4):
        parts = [f[j] for f in first] + [s_[j] for s_ in second]
        joined.append(torch.cat(parts) if j < 2 else np.concatenate(parts))
    return tuple(joined)


def _export_only(args, out: Path, frames: np.ndarray, labels: np.ndarray,
                 members: list[dict]) -> int:
    """--export-only PT: a training run's saved weights (roadseg.pt, or the roadseg-last.pt of
    an --ema run) calibrated and exported as that run would have (calibrate_and_export on
    `frames`, `labels`: the held-out frames of these rendering settings, flip averaging,
    --border-frames) to --out/roadseg.onnx; the log goes to --out/export_log.json. With the
    run's --seed and --frames (and --soup DOSE for a run on that dose's towns; with --stream,
    its --seed and --stream-junctions), the held-out frames are the run's: an --ema run's two
    weights, compared alike. --export-only PT1,PT2,...: the runs' weights averaged name by
    name first (a soup of finished runs of one architecture). With --sky-cut-training, the
    offsets are set without the rows the sky margin leaves out, as that run's were. A run's
    roadseg.pt carries its logit offsets in the head's bias: --keep-offsets exports it with
    them (calibrated again, they move on from where the run's search stopped)."""
    import torch

    from training.net import RoadSegNet

    saved = members[0]  # load_export_members: all of its architecture
    model = RoadSegNet(num_classes=seg_data.TRAIN_CLASSES, **saved["arch"])
    model.load_state_dict(average_states([m["state"] for m in members]))
    model.eval()  # every batch norm on its running statistics, frozen or not
    n_val, top = len(frames), training_sky_rows(args)  # cut as the run's
    x_val = torch.from_numpy(frames[:, top:]).permute(0, 3, 1, 2)
    y_val = torch.from_numpy(labels[:, top:])
    log = calibrate_and_export(model, x_val, y_val, frames, labels, out,
                               seed=args.seed, frozen_norms=bool(saved.get("frozen_norms")),
                               sky_fraction=top / INPUT_SIZE[1],
                               offsets=not args.keep_offsets)
    log.update(_flip_and_border(args, out), weights=str(args.export_only), seed=args.seed,
               junctions=export_junctions(args),
               frames=n_val)
    (out / "export_log.json").write_text(json.dumps(log, indent=2))
    logger.info("%s -> %s: %s", args.export_only, out / "roadseg.onnx", log)
    return 0


def _flip_and_border(args, out: Path) -> dict:
    """Flip averaging (and --sky-margin-deg) into out/roadseg.onnx's metadata, then
    (--border-frames) its border classifier, fitted on the logits the runtime will decide ->
    their part of the log."""
    log = {"flip_average": bool(args.flip_average)}
    if args.sky_margin_deg is not None:
        log["sky_margin_deg"] = args.sky_margin_deg
    set_metadata(out / "roadseg.onnx", **log)
    if args.border_frames:  # all its frames rendered: no time budget
        log["border"] = fit_border_step(out / "roadseg.onnx", seed=args.border_seed,
                                        frames=args.border_frames, args=args,
                                        budget_s=NO_RENDER_BUDGET_S)
    return log


def _border_only(args, out: Path) -> int:
    """--border-only MODEL: fit its BorderNet (training/border.py) on --frames town
    frames of --seed, all of them rendered (no time budget), and write it into MODEL's metadata
    when it beats the model's brightness rule; the log goes to border_log.json in `out`
    (--out, or MODEL's folder)."""
    trained_seed = _metadata(args.border_only).get("seed")
    if trained_seed == args.seed:
        raise ConfigError(f"--border-only: {args.border_only} was trained on the towns of seed "
                          f"{args.seed}; fit its border classifier on another --seed")
    budget_s = 60.0 * args.render_minutes if args.render_minutes else NO_RENDER_BUDGET_S
    log = fit_border_step(args.border_only, seed=args.seed, frames=args.frames, args=args,
                          budget_s=budget_s)
    (out / "border_log.json").write_text(json.dumps(log, indent=2))
    return 0


def fit_border_step(model_path, *, seed: int, frames: int, args, budget_s: float) -> dict:
    """Render `frames` town frames of `seed` (cached like the training frames), fit the
    model's BorderNet on them (training/border.py) and write it into the model's
    metadata when it beats the model's brightness rule -> the log."""
    from training.border import calibrate_border_net

    t0 = time.perf_counter()
    images, labels = seg_data.training_set(seed=seed, input_size=INPUT_SIZE, budget_s=budget_s,
                                           max_frames=frames, workers=args.workers,
                                           **frame_cache(args), turn_prob=args.turn_prob,
                                           synth_share=args.synth_share)
    render_s = time.perf_counter() - t0
    result = calibrate_border_net(model_path, images, labels, seed=seed,
                                  sky_fraction=training_sky_share(args))
    if result["border_net"] is not None:
        set_metadata(model_path, border_net=result["border_net"])
    log = {k: v for k, v in result.items() if k != "border_net"}
    log.update(kept=result["border_net"] is not None, model=str(model_path), seed=seed,
               frames=len(images), render_s=round(render_s, 1))
    logger.info("border classifier of %s: %s", model_path, log)
    return log


def _metadata(path) -> dict:
    """The `roadmap.segmentation` metadata of an ONNX model ({} when it has none)."""
    import onnx

    entry = _meta_entry(onnx.load(str(path)))
    return json.loads(entry.value) if entry else {}


def crop_size(text: str, frame_hw) -> tuple[int, int]:
    """--crop: "WxH" (e.g. 384x224) or "full" (whole frames) -> (H, W) within the frames."""
    if text == "full":
        return tuple(int(v) for v in frame_hw)
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--crop must be WxH or full, got {text!r}") from None
    if not (0 < h <= frame_hw[0] and 0 < w <= frame_hw[1]):
        raise ConfigError(f"--crop {text}: outside the {frame_hw[1]}x{frame_hw[0]} frames")
    return h, w


# Streamed training (--stream): training starts once STREAM_START_FRAMES have arrived, the
# first STREAM_VAL_FRAMES of them (10 chunks: 3 synth.py, 7 simulator) held out.
STREAM_START_FRAMES = 480
STREAM_VAL_FRAMES = 240


def streamed_held_out(args) -> tuple[np.ndarray, np.ndarray]:
    """The held-out frames of a streamed run of --seed (and --stream-junctions, --turn-prob,
    --synth-share): the stream's first frames (STREAM_VAL_FRAMES for a run of
    STREAM_START_FRAMES or more), each chunk rendered from (seed, k) alone, in the order
    train_model holds them (interleaved_halves) -> (frames, labels). A
    streamed run trains on what arrived in time, but these it holds out whatever the
    machine, so --export-only --stream calibrates its weights as the run did."""
    # the run starts on the first min(STREAM_START_FRAMES, --frames), whole chunks
    chunk = seg_data.CHUNK_FRAMES
    n_val = streamed_validation_frames(-(-min(STREAM_START_FRAMES, args.frames) // chunk) * chunk)
    stream = _frame_stream(args, n_val)
    try:
        frames, labels = stream.wait(n_val, timeout_s=30 * 60.0)
    finally:
        stream.close()
    if len(frames) < n_val:
        raise RuntimeError(f"--export-only --stream: {len(frames)} of the stream's {n_val} "
                           "held-out frames rendered in 30 min")
    order = interleaved_halves(n_val)
    return frames[:n_val][order], labels[:n_val][order]


def streamed_validation_frames(n_start: int) -> int:
    """How many of the first n_start frames a streamed run trains on holds out (the first half
    of them sets the logit offsets and paint borders, the second validates)."""
    return min(STREAM_VAL_FRAMES, n_start // 2)


def _frame_stream(args, max_frames: int):
    """The FrameStream of a streamed run's towns (--seed, --workers, --turn-prob,
    --synth-share, --stream-junctions), its first max_frames."""
    return seg_data.FrameStream(seed=args.seed, input_size=INPUT_SIZE, max_frames=max_frames,
                                workers=args.workers, turn_prob=args.turn_prob,
                                synth_share=args.synth_share,
                                junctions=tuple(args.stream_junctions or ("light",)))


def _train_streamed(args, out: Path, t_start: float) -> int:
    import os

    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"  # for the render workers (spawned: they read it at import)
    stream = _frame_stream(args, args.frames)
    try:
        frames, labels = stream.wait(min(STREAM_START_FRAMES, args.frames), timeout_s=30 * 60.0)
        render_s = time.perf_counter() - t_start
        logger.info("%d frames after %.0f s; training while %d processes render on",
                    len(frames), render_s, args.workers)
        train_s = max(float(args.minutes) * 60.0 - render_s - 60.0, 60.0)
        result = train_and_export(frames, labels, out, seed=args.seed, train_s=train_s,
                                  more=stream.take, capacity=args.frames,
                                  **run_options(args, frames.shape[1:3]))
    finally:
        stream.close()
    result["render_s"] = round(render_s, 1)
    result["stream"] = True
    return _finish(args, out, result, t_start)


def _finish(args, out: Path, result: dict, t_start: float) -> int:
    minutes = float(args.minutes)
    # flip averaging is on before the border classifier is fitted, so that it learns the
    # borders of the averaged logits the runtime will decide (as the packaged file was made)
    result.update(_flip_and_border(args, out))
    result["minutes"] = minutes
    result["turn_prob"] = args.turn_prob
    result["synth_share"] = args.synth_share
    result["command"] = " ".join(
        ["roadmap train-seg --out DIR", f"--seed {args.seed}"]
        + ([f"--minutes {minutes:g}"] if args.steps is None else [f"--steps {args.steps}"])
        + [f"--frames {args.frames}", f"--workers {args.workers}"]
        + ([f"--render-minutes {args.render_minutes:g}"] if args.render_minutes else [])
        + (["--stream"] if args.stream else [])
        + ([f"--stream-junctions {','.join(args.stream_junctions)}"]
           if args.stream_junctions else [])
        + [f"--device {args.device}", f"--batch {args.batch}"]
        + ([f"--arch {args.arch}"] if args.arch != "s" else [])
        + ([f"--init {args.init}"] if args.init else [])
        + ([f"--turn-prob {args.turn_prob:g}"] if args.turn_prob != seg_data.TURN_PROB else [])
        + ([f"--synth-share {args.synth_share:g}"]
           if args.synth_share != seg_data.SYNTH_SHARE else [])
        + ([f"--iou-loss {args.iou_loss:g}"] if args.iou_loss else [])
        + ([f"--hard-pixels {args.hard_pixels:g}"] if args.hard_pixels < 1.0 else [])
        + ([f"--mirror-consistency {args.mirror_consistency:g}"]
           if args.mirror_consistency else [])
        + ([f"--ema {args.ema:g}"] if args.ema else [])
        + ([f"--average-init {args.average_init:g}"] if args.average_init else [])
        + ([f"--distill {args.distill:g}"] if args.distill else [])
        + ([f"--teacher {args.teacher}"] if args.teacher else [])
        + (["--bf16"] if args.bf16 else [])
        + ([f"--soup {','.join(args.soup)}"] if args.soup else [])
        + ([f"--crop {args.crop}"] if args.crop != DEFAULT_CROP else [])
        + ([f"--full-after {args.full_after:g}"] if args.full_after < 1.0 else [])
        + ([] if args.flip_average else ["--no-flip-average"])
        + ([f"--sky-margin-deg {args.sky_margin_deg:g}"]
           if args.sky_margin_deg is not None else [])
        + (["--sky-cut-training"] if getattr(args, "sky_cut_training", False) else [])
        + ([f"--border-frames {args.border_frames}"] if args.border_frames else [])
        + ([f"--border-seed {args.border_seed}"]
           if args.border_frames and args.border_seed != args.seed + BORDER_SEED_OFFSET
           else []))
    result["total_s"] = round(time.perf_counter() - t_start, 1)
    (out / "train_log.json").write_text(json.dumps(result, indent=2))
    (out / "MODEL_CARD.md").write_text(model_card(result))
    logger.info("trained in %.1f min: %s", result["total_s"] / 60.0, result)
    return 0


def train_and_export(frames, labels, out: Path, *, seed: int, **kw) -> dict:
    """train_model, then calibrate_and_export on the run's held-out frames -> the training
    log's entries."""
    model, frozen_norms, held_out, result = train_model(frames, labels, out, seed=seed, **kw)
    exported = calibrate_and_export(model, *held_out, out, seed=seed, frozen_norms=frozen_norms,
                                    sky_fraction=kw.get("top_rows", 0) / frames.shape[1])
    return {**result, **exported}


def train_model(frames, labels, out: Path, *, seed: int, train_s: float,
                steps: int | None = None,
                device: str = "cpu", batch: int = BATCH, init: str | None = None,
                iou_loss: float = 0.0, arch: str = "s", more=None,
                capacity: int = 0, crop_hw: tuple[int, int] = CROP_HW,
                hard_pixels: float = 1.0, mirror: float = 0.0, ema: float = 0.0,
                average_init: float = 0.0, distill: float = 0.0, teacher: str | None = None,
                bf16: bool = False, full_after: float = 1.0, top_rows: int = 0):
    """Train RoadSegNet of size `arch` (archs.ARCHS) for train_s seconds (or, with `steps`,
    for exactly that many steps, the schedule spread over them) on `device` (cpu: 2
    threads; cuda: the frames live on the GPU), from scratch or, with `init`, from a trained
    model (fine-tuning at LR_FINETUNE; an exported ONNX file's folded batch norms are kept
    frozen), on class-weighted cross-entropy (over the `hard_pixels` share of each batch's
    pixels with the largest loss: hard_pixel_loss) plus `iou_loss` x soft_jaccard_loss, plus,
    with `mirror` > 0, `mirror` x mirror_consistency_loss (half of each batch mirrors the
    other half); with `ema` > 0, the exported weights are their moving average over the
    steps (WeightAverage; the last step's are saved as roadseg-last.pt); with `average_init`
    > 0, they are (1 - average_init) x the trained weights + average_init x `init`'s (the
    trained ones saved as roadseg-trained.pt); with `distill` > 0, `distill` x the
    class-weighted cross-entropy against the flip-averaged class probabilities of `teacher`
    (an exported RoadSegNet; default `init`) joins the loss (distillation_loss); with
    `bf16`, the forward pass runs under bfloat16 autocast
    (weights, optimizer and loss stay float32); with `more`
    (FrameStream.take) frames keep arriving while it trains, up to `capacity` in all;
    batches are random `crop_hw` (H, W) windows of the frames (the whole frame when it is the
    frame's size), whole frames once `full_after` of the run has passed; with `top_rows`,
    every frame without its top rows, as the runtime segments frames under a sky margin
    (training, the logit offsets and the validation; whole frames are then the rest) ->
    (the model in eval mode, whether its batch norms were kept frozen, the
    held-out frames (x_val, y_val: copies as uint8 tensors NCHW and NHW on `device`; the same
    as views of `frames`, `labels`), the training log's entries)."""
    import torch

    from training.net import RoadSegNet, count_parameters, freeze_batch_norm

    torch.manual_seed(seed)
    torch.set_num_threads(THREADS)
    trim_heap = _heap_trimmer()
    torch.backends.cudnn.benchmark = True
    dev = torch.device(device)
    rng = np.random.default_rng(seed)
    n_val = (validation_frames(len(frames)) if more is None
             else streamed_validation_frames(len(frames)))
    if more is not None:  # streamed frames come in chunk order: halves with the same mix
        frames, labels = frames.copy(), labels.copy()
        order = interleaved_halves(n_val)
        frames[:n_val], labels[:n_val] = frames[order], labels[order]
    check_top_rows(top_rows, frames.shape[1:3], crop_hw)  # before gigabytes are allocated
    n_loaded, cap = len(frames), max(capacity, len(frames)) if more is not None else len(frames)
    x_all = torch.empty((cap, 3) + frames.shape[1:3], dtype=torch.uint8, device=dev)  # NCHW
    y_all = torch.empty((cap,) + labels.shape[1:], dtype=torch.uint8, device=dev)  # int64/batch
    x_all[:n_loaded] = torch.from_numpy(frames).to(dev).permute(0, 3, 1, 2)
    y_all[:n_loaded] = torch.from_numpy(labels).to(dev)
    x_rows, y_rows = x_all[:, :, top_rows:], y_all[:, top_rows:]  # views: filled with x_all
    if tuple(crop_hw) == tuple(frames.shape[1:3]):
        crop_hw = tuple(x_rows.shape[2:4])
    weights = class_weights(labels[n_val:, top_rows:])
    model = RoadSegNet(num_classes=seg_data.TRAIN_CLASSES, **ARCHS[arch])
    frozen_norms = _load_init(model, init) if init else False
    check_average_init(average_init, init)
    start = ({k: v.detach().clone() for k, v in model.state_dict().items()}
             if average_init else None)
    whole = tuple(crop_hw) == tuple(x_rows.shape[2:4])
    check_distill(distill, init, more is None, teacher, crop_hw)
    check_full_after(full_after, "full" if whole else "crops")
    model = model.to(dev)
    targets = None
    if distill:
        t_teach = time.perf_counter()
        if teacher:  # an exported file: onnxruntime on the CPU, about 5x faster than torch
            targets = onnx_teacher_logits(teacher, x_all[:n_loaded])
        else:
            targets = teacher_logits(_frozen_copy(model), x_all[:n_loaded])
        logger.info("%s's flip-averaged logits of %d frames in %.0f s", teacher or "--init",
                    n_loaded, time.perf_counter() - t_teach)
        targets = targets[:, :, top_rows // 2:]  # at 1/2 resolution; top_rows is even
    lr_max = LR_FINETUNE if init else LR_MAX
    opt = torch.optim.AdamW(model.parameters(), lr=lr_max, weight_decay=1e-4)
    check_hard_pixels(hard_pixels)
    check_mirror(mirror, batch)
    check_ema(ema)
    class_w = torch.tensor(weights, dtype=torch.float32, device=dev)
    loss_fn = torch.nn.CrossEntropyLoss(weight=class_w)
    logger.info("training %d params on %d frames (%d held for validation), weights %s%s",
                count_parameters(model), len(frames) - n_val, n_val, np.round(weights, 2),
                f", from {init}" if init else "")
    model.train()
    if frozen_norms:
        freeze_batch_norm(model)
    average = WeightAverage(model, ema) if ema else None
    t0, step, losses = time.perf_counter(), 0, []
    while True:
        elapsed = time.perf_counter() - t0  # logged by steps too
        frac = elapsed / train_s if steps is None else step / steps
        if frac >= 1.0:
            break
        for g in opt.param_groups:
            g["lr"] = _lr(frac, lr_max)
        if more is not None and step % 20 == 0 and n_loaded < cap and (got := more()):
            k = min(len(got[0]), cap - n_loaded)
            x_all[n_loaded:n_loaded + k] = torch.from_numpy(got[0][:k]).to(dev).permute(0, 3, 1, 2)
            y_all[n_loaded:n_loaded + k] = torch.from_numpy(got[1][:k]).to(dev)
            n_loaded += k
        n_drawn = batch // 2 if mirror else batch  # with `mirror`, the rest are their mirrors
        idx = torch.from_numpy(rng.integers(n_val, n_loaded, n_drawn)).to(dev)
        window = crop_hw if frac < full_after else tuple(x_rows.shape[2:4])
        xb, yb, top, tb = _crop_batch(x_rows[idx], y_rows[idx], rng, window,
                                      None if targets is None else targets[idx])
        model.crop_rows = (top_rows + top, x_all.shape[2])
        if targets is None:
            xb, yb = augment(xb, yb.long(), rng)
        else:
            xb, yb, tb = augment(xb, yb.long(), rng, extra=tb)
        if mirror:  # each frame and its mirror image, with the same photometric draw
            xb, yb = torch.cat([xb, xb.flip(-1)]), torch.cat([yb, yb.flip(-1)])
        with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=bf16):
            logits = model(xb)
        logits = logits.float()
        loss = (loss_fn(logits, yb) if hard_pixels >= 1.0
                else hard_pixel_loss(logits, yb, class_w, hard_pixels, rng))
        if iou_loss:
            loss = loss + iou_loss * soft_jaccard_loss(logits, yb)
        if mirror:
            loss = loss + mirror * mirror_consistency_loss(logits)
        if targets is not None:
            loss = loss + distill * distillation_loss(logits, tb, yb, class_w)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if average is not None:
            average.update(model)
        losses.append(loss.detach())  # no device sync per step
        step += 1
        if step % TRIM_EVERY == 0:
            trim_heap()
        if step % 100 == 0:
            logger.info("step %d  %.0f s  lr %.4f  loss %.4f  frames %d", step, elapsed,
                        _lr(frac, lr_max), _mean_loss(losses), n_loaded)
    model.eval()
    model.crop_rows = None  # whole frames from here on
    if average is not None:  # the last step's weights, for comparing (no logit offsets)
        save_weights(model, frozen_norms, out / "roadseg-last.pt")
        average.load_into(model)
    if start is not None:  # a fine-tune averaged with its start ("WiSE-FT")
        trained = save_weights(model, frozen_norms, out / "roadseg-trained.pt")
        model.load_state_dict(average_states([trained, start],
                                             [1.0 - average_init, average_init]))
    # the held-out frames' first half sets the logit offsets and paint borders (the tensors
    # copied, so the training tensors can go)
    held_out = (x_rows[:n_val].clone(), y_rows[:n_val].clone(), frames[:n_val], labels[:n_val])
    return model, frozen_norms, held_out, {
        "steps": step, "train_s": round(time.perf_counter() - t0, 1), "frames": n_loaded,
        "class_weights": np.round(weights, 3).tolist(),
        "final_loss": _mean_loss(losses) if losses else None,
        "seed": seed, "device": device,
        "batch": batch, "init": init, "lr_max": lr_max,
        "iou_loss_weight": iou_loss, "hard_pixels": hard_pixels, "arch": arch,
        "mirror_consistency": mirror, "ema": ema, "average_init": average_init,
        "distill": distill, "teacher": teacher, "bf16": bf16, "crop_hw": list(crop_hw),
        "full_after": full_after, "frozen_norms": frozen_norms, "top_rows": top_rows,
    }


def calibrate_and_export(model, x_val, y_val, frames_val: np.ndarray, labels_val: np.ndarray,
                         out: Path, *, seed: int, frozen_norms: bool,
                         sky_fraction: float = 0.0, offsets: bool = True) -> dict:
    """A trained model (eval mode, whole frames) and its run's held-out frames (x_val, y_val:
    uint8 tensors NCHW and NHW on the model's device; frames_val, labels_val: the same as
    arrays): the first half sets the logit offsets (calibrate_bias) and the paint-border
    settings (calibrate_refine), the second half validates; writes out/roadseg.pt and the
    checked out/roadseg.onnx -> what it measured, for the training log. `sky_fraction`: the
    share of the frames' top rows the runtime will leave out (x_val are already without
    them), for the paint-border settings and the runtime's validation. `offsets` False: the
    model's head keeps its bias (weights that carry their run's offsets already)."""
    from training.net import count_parameters

    n_cal = len(x_val) // 2
    bias = (calibrate_bias(model, x_val[:n_cal], y_val[:n_cal]) if offsets
            else [0.0] * int(model.head.bias.numel() // model.subpixel ** 2))
    model.export_classes = NUM_CLASSES  # auxiliary classes folded into none from here on
    val_iou = _validate(model, x_val[n_cal:], y_val[n_cal:])
    logger.info("validation IoU (procedural towns, held out): %s", val_iou)
    model, x_check = model.cpu(), x_val[:4].cpu()
    model_path = out / "roadseg.onnx"
    # for fine-tuning (--init); not packaged. Saved with the logit offsets in the head's bias,
    # and whether its batch norms were frozen (a fine-tune of an export: norms folded into the
    # convolutions, running statistics the identity); a fine-tune of this file keeps them so
    save_weights(model, frozen_norms, out / "roadseg.pt")
    export_onnx(model, model_path, seed=seed)
    max_diff, agree = verify_onnx(model, model_path, x_check)
    refine = calibrate_refine(model_path, frames_val[:n_cal], labels_val[:n_cal],
                              sky_fraction=sky_fraction)
    set_metadata(model_path, refine=refine)
    val_runtime = runtime_iou(model_path, frames_val[n_cal:], labels_val[n_cal:],
                              sky_fraction=sky_fraction)
    logger.info("paint borders: %s; validation IoU as the runtime segments: %s", refine,
                val_runtime)
    return {"params": count_parameters(model), "val_iou_town": val_iou,
            "onnx_max_abs_diff": max_diff, "onnx_argmax_agreement": agree,
            "model_bytes": model_path.stat().st_size, "logit_bias": bias, "refine": refine,
            "val_iou_town_runtime": val_runtime}


def interleaved_halves(n: int) -> np.ndarray:
    """An order of n frames that puts the even ones first: the calibration half (logit
    offsets, paint borders) and the validation half of a streamed run's held-out frames, which
    arrive in chunk order (chunks 0-2 of every 10 from synth.py). Split as they came, the
    calibration half held chunks 0-4, 60 % synth.py frames against 30 % in training, and set
    the offsets for those."""
    return np.r_[0:n:2, 1:n:2]


def validation_frames(n_frames: int) -> int:
    """How many of a pre-rendered training set's first frames are held out (the first half
    of them sets the logit offsets and the paint-border settings, the second validates)."""
    return max(n_frames // 20, 4)


# the curb too: a light curb looks like an edge line
IOU_CLASSES = MARKINGS + (seg_data.CURB_AUX,)


def soft_jaccard_loss(logits, y):
    """1 - soft IoU (softmax probabilities against one-hot truth, summed over the batch),
    averaged over the IOU_CLASSES present in the batch. Cross-entropy scores every pixel on
    its own; thin paint's IoU is lost at its borders (a line fattened by one pixel at 20 m has
    half again its true area), which this term prices the way the benchmark does."""
    import torch

    prob = torch.softmax(logits, 1)[:, list(IOU_CLASSES)]  # (N, K, H, W)
    truth = torch.stack([y == c for c in IOU_CLASSES], 1).to(prob.dtype)
    inter = (prob * truth).sum((0, 2, 3))
    t_sum = truth.sum((0, 2, 3))
    iou = inter / (prob.sum((0, 2, 3)) + t_sum - inter + 1.0)
    present = (t_sum > 0).to(prob.dtype)  # absent classes: no term (no device sync)
    return ((1.0 - iou) * present).sum() / present.sum().clamp(min=1.0)


def check_mirror(weight: float, batch: int) -> None:
    """--mirror-consistency needs a weight >= 0 and, when on, an even batch (frame + mirror)."""
    if weight < 0 or (weight > 0 and batch % 2):
        raise ConfigError(f"--mirror-consistency {weight:g} needs a weight >= 0 and an even "
                          f"--batch (each frame and its mirror), got batch {batch}")


def check_ema(decay: float) -> None:
    """--ema needs a decay in [0, 1) (0: off)."""
    if not 0.0 <= decay < 1.0:
        raise ConfigError(f"--ema {decay:g}: the decay must be in [0, 1) (0: off)")


class WeightAverage:
    """An exponential moving average of a model's weights over training steps, bias-corrected
    as Adam's moments are: it starts from zero, not from the first weights, and is divided by
    1 - decay^steps, so after t steps the weights of step s count decay^(t - s) (normalised)
    and the starting model counts nothing. Floating-point parameters and buffers are averaged;
    integer buffers (batch-norm step counters) are the last step's.

    Batch 8 on two cores is a noisy gradient: the last step's weights sit at a random point of
    the late, low-learning-rate walk, the average near its centre."""

    def __init__(self, model, decay: float):
        import torch

        self.decay, self.steps = float(decay), 0
        self.sums = {k: torch.zeros_like(v) for k, v in model.state_dict().items()
                     if v.is_floating_point()}

    def update(self, model) -> None:
        state = model.state_dict()
        for k, acc in self.sums.items():
            acc.mul_(self.decay).add_(state[k].detach(), alpha=1.0 - self.decay)
        self.steps += 1

    def load_into(self, model) -> None:
        """Set the model's weights to the average (needs one update)."""
        if not self.steps:
            raise ValueError("WeightAverage.load_into before any update")
        norm = 1.0 - self.decay ** self.steps
        model.load_state_dict({**model.state_dict(),
                               **{k: v / norm for k, v in self.sums.items()}})


def mirror_consistency_loss(logits):
    """Logits (2n, C, H, W) of n frames then their n mirror images -> the mean over pixels of
    KL(m || p) + KL(m || q), where p is a frame's class distribution, q its mirror's mirrored
    back, and m = (p + q) / 2 held fixed: both are pulled towards their average, as a
    mirrored second pass averaged in at test time would do (HISTORY.md: +0.014 held-out lane
    line for a second pass), so that one pass may carry some of it."""
    import torch
    from torch.nn import functional as F

    n = logits.shape[0] // 2
    log_p = F.log_softmax(logits[:n], dim=1)
    log_q = F.log_softmax(logits[n:], dim=1).flip(-1)
    with torch.no_grad():
        m = 0.5 * (log_p.exp() + log_q.exp())
        log_m = torch.log(m.clamp_min(1e-8))
    kl = (m * (2.0 * log_m - log_p - log_q)).sum(1)
    return kl.mean()


def check_full_after(frac: float, crop: str) -> None:
    """--full-after: a share of the run in (0, 1], and crops to switch from."""
    if not 0.0 < frac <= 1.0:
        raise ConfigError(f"--full-after {frac:g}: a share of the run in (0, 1]")
    if frac < 1.0 and crop == "full":
        raise ConfigError("--full-after with --crop full: the run trains on whole frames "
                          "throughout; leave one out")


def check_distill(weight: float, init: str | None, frames_at_start: bool = True,
                  teacher: str | None = None, crop_hw: tuple[int, int] = CROP_HW) -> None:
    """--distill needs a teacher (--teacher, an exported model, or else --init), a weight >=
    0 (0: off), every frame at the start, not streamed (the teacher's outputs are computed
    once per frame, then cropped with it), and crops (H, W) `crop_hw` of even sides (the
    teacher's logits are at 1/2 resolution); --teacher needs --distill."""
    if weight < 0:
        raise ConfigError(f"--distill {weight:g}: the weight must be >= 0 (0: off)")
    if teacher is not None:
        if not weight:
            raise ConfigError("--teacher is the --distill teacher: give --distill WEIGHT")
        check_export_file("--teacher", teacher)
    if weight and not (init or teacher):
        raise ConfigError("--distill: distils --init's (or --teacher's) flip-averaged output; "
                          "give --init or --teacher")
    if weight and not frames_at_start:
        raise ConfigError("--distill computes the teacher's outputs once per frame before "
                          "training: it cannot take --stream's frames")
    if weight:
        check_even_crop(crop_hw)


def bf16_warning(bf16: bool, device: str, native: bool | None = None) -> str | None:
    """What to tell a `--bf16` run on a CPU without native bfloat16 arithmetic (`native`:
    whether it has AVX-512 BF16 or AMX; None asks torch), else None. There torch emulates
    bfloat16 arithmetic with conversions around every operation: on a 2-core AVX2 EPYC
    (training/bench/train_step.py, 2026-11-27) a step of 8 384x224 crops from scratch took
    2.2-2.55x float32's time (1.10 against 0.43 s) and a whole-frame fine-tune step 1.4-1.55x
    (2.59 against 1.68 s), where an AVX-512 BF16 EPYC gave 0.69-0.75x. The run goes on as
    asked (a bf16 run's weights differ from a float32 run's), slower."""
    if not bf16 or not str(device).startswith("cpu"):
        return None
    if native is None:
        native = cpu_has_native_bf16()
    if native:
        return None
    return ("--bf16 on a CPU without native bfloat16 (no AVX-512 BF16 or AMX): torch emulates "
            "it, and a training step takes 1.4-2.5x float32's time here; leave --bf16 out "
            "for speed (the weights then differ from a bf16 run's)")


def cpu_has_native_bf16() -> bool:
    """Whether torch's CPU kernels can run bfloat16 natively here (AVX-512 BF16 or AMX)."""
    import torch

    probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch >= 2.1
    return any(getattr(torch.cpu, name, lambda: False)() for name in probes)


def check_even_crop(crop_hw) -> None:
    """Crops (H, W) that a teacher's 1/2-resolution logits can be cropped with."""
    h, w = crop_hw
    if h % 2 or w % 2:
        raise ConfigError(f"crops of {h}x{w}: a teacher's 1/2-resolution logits need an "
                          f"even crop height and width")


def _frozen_copy(model):
    """A copy of `model` in eval mode with no gradients (a teacher)."""
    import copy

    teacher = copy.deepcopy(model).eval()
    for p in teacher.parameters():
        p.requires_grad_(False)
    return teacher


def teacher_logits(teacher, x_u8, batch: int = 8):
    """The teacher's flip-averaged logits at its output resolution (1/2) for uint8 frames
    (N, 3, H, W): the mean of its logits on each frame and, mirrored back, on the frame's
    mirror image, what the runtime's flip averaging decides from -> float16 (N, C, H/2, W/2)
    on the frames' device (0.8 MB a 640x360 frame). Computed once per run on the frames
    before augmentation: a third of the passes of computing them per batch."""
    import torch

    half_res, teacher.half_res_logits = teacher.half_res_logits, True
    try:
        out = None  # filled in place: the logits of 4800 frames take 3.9 GB
        with torch.no_grad():
            for i in range(0, len(x_u8), batch):
                x = x_u8[i:i + batch].float() / 255.0
                logits = 0.5 * (teacher(x) + teacher(x.flip(-1)).flip(-1))
                if out is None:
                    out = torch.empty((len(x_u8),) + logits.shape[1:], dtype=torch.float16,
                                      device=logits.device)
                out[i:i + batch] = logits
        return out
    finally:
        teacher.half_res_logits = half_res


def onnx_teacher_logits(path, x_u8, threads: int | None = None):
    """`teacher_logits` of an exported RoadSegNet file, run by onnxruntime: the flip-averaged
    logits of its head (every trained class, the auxiliary ones too: the head's output before
    the export folds them into none) at 1/2 resolution -> float16 (N, C, H/2, W/2) on the
    frames' device. The file's metadata offsets are not applied (nor are they by torch).

    Why not torch: a file of any depths loads as is, and on 2 CPU cores onnxruntime is 4.7x
    faster (the packaged model's logits of 16 frames: 1.70 s in torch, 0.36 s; of 4800 frames
    in torch: 516 s); a 410 k-parameter teacher (archs "xl") took 371 s for 4800 frames. It
    runs on the CPU for a --device cuda run too, where torch on the GPU would be faster."""
    import onnx
    import onnxruntime as ort
    import torch

    proto = onnx.load(str(path))
    head = [n for n in proto.graph.node if n.op_type == "Conv"][-1]
    proto.graph.output.append(onnx.helper.make_empty_tensor_value_info(head.output[0]))
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads or torch.get_num_threads()
    session = ort.InferenceSession(proto.SerializeToString(), opts,
                                   providers=["CPUExecutionProvider"])
    return teacher_logits(_OnnxHead(session, head.output[0]), x_u8)


class _OnnxHead:
    """An onnxruntime session's `output` as `teacher_logits` calls a teacher: float images
    (N, 3, H, W) in [0, 1] -> that output (N, ...) on the images' device, one frame a run
    (the export's batch is 1). Its logits are at 1/2 resolution whatever `half_res_logits` says."""

    half_res_logits = True

    def __init__(self, session, output: str):
        self.session, self.output = session, output
        self.input = session.get_inputs()[0].name

    def __call__(self, x):
        import torch

        frames = x.cpu().numpy()
        logits = [self.session.run([self.output], {self.input: frames[i:i + 1]})[0]
                  for i in range(len(frames))]
        return torch.from_numpy(np.concatenate(logits)).to(x.device)


def distillation_loss(logits, target_logits, y, class_w):
    """Cross-entropy of the student's logits (N, C, H, W) against the class probabilities of
    the teacher's logits (N, C, h, w; upsampled bilinearly as the student's are), each pixel
    weighted by its true class's weight (as the labels' cross-entropy is) and averaged by the
    weights' sum.

    Why (2026-11-27): flip averaging, a second network pass, is worth +0.011 of held-out lane
    line; a student started from the teacher and pulled towards its flip-averaged output may
    carry some of that in one pass (HISTORY.md), where a consistency term between a frame and
    its mirror (--mirror-consistency) did not."""
    import torch

    from training.net import upsample_like  # the student's own upsampling

    target = upsample_like(target_logits.float(), logits)
    per_px = -(torch.softmax(target, 1) * torch.log_softmax(logits, 1)).sum(1)
    w = class_w[y]
    return (per_px * w).sum() / w.sum()


def check_hard_pixels(share: float) -> None:
    if not 0.0 < share <= 1.0:
        raise ConfigError(f"--hard-pixels must be a share in (0, 1], got {share}")


def hard_pixel_loss(logits, y, class_w, share: float, rng, sample: int = 65536):
    """Class-weighted cross-entropy averaged over the `share` of the batch's pixels with the
    largest loss (online hard example mining, as BiSeNet's training does): the easy road and
    sky pixels, most of a frame, stop steering the gradient, and the borders of thin lines,
    curbs beside lines and far paint get it. The cut-off is the (1 - share) quantile of the
    per-pixel losses of `sample` pixels drawn at random (a full sort of 1.8 M losses costs
    more than the step's backward pass), or of all of them in a smaller batch. The hard
    pixels' weighted losses are averaged per pixel (torch's CrossEntropyLoss with weights
    divides by the sum of the weights instead), so the training loop keeps that loss for a
    share of 1, as before the option existed."""
    import torch

    per_px = torch.nn.functional.cross_entropy(logits, y, weight=class_w, reduction="none")
    flat = per_px.reshape(-1)
    probe = flat.detach()
    if probe.numel() > sample:
        probe = probe[torch.from_numpy(rng.integers(0, probe.numel(), sample)).to(flat.device)]
    cut = torch.quantile(probe, 1.0 - share)
    hard = flat >= cut
    return (flat * hard).sum() / hard.sum().clamp(min=1)


CALIBRATE_FRAMES = 128
BIAS_GRID = np.round(np.arange(-2.0, 1.01, 0.2), 2)


def calibrate_bias(model, x_u8, y, rounds: int = 2) -> list[float]:
    """Per-class logit offsets that maximise the mean IoU of the paint classes on the
    validation frames (procedural towns, never the benchmark worlds), added to the head's bias.
    Class-weighted training buys recall of thin paint with fattened lines (more false positives
    at their borders than misses); this moves each class's boundary back to where its IoU peaks.
    Coordinate ascent over a grid, `rounds` passes; the offsets are exact at any resolution
    (bilinear upsampling commutes with adding a constant per channel). Only pixels whose top
    two logits are closer than the grid's span can change class: the others are counted once."""
    import torch

    x_u8, y = x_u8[:CALIBRATE_FRAMES], y[:CALIBRATE_FRAMES].long().cpu()
    with torch.no_grad():
        logits = torch.cat([model(x_u8[i:i + 4].float() / 255.0).cpu()
                            for i in range(0, len(x_u8), 4)])
    y = torch.where(y >= NUM_CLASSES, 0, y)
    paint = [c for c in MARKINGS if bool((y == c).any())]
    top2 = logits.topk(2, dim=1).values
    open_ = (top2[:, 0] - top2[:, 1]) <= float(BIAS_GRID.max() - BIAS_GRID.min())
    pred0 = logits.argmax(1)
    fixed_pred = torch.where(pred0 >= NUM_CLASSES, 0, pred0)[~open_]
    fixed_y = y[~open_]
    fixed = {c: (int(((fixed_pred == c) & (fixed_y == c)).sum()),
                 int(((fixed_pred == c) | (fixed_y == c)).sum())) for c in paint}
    search = OffsetSearch(logits.permute(0, 2, 3, 1)[open_].numpy(), y[open_].numpy(),
                          [int(c) for c in paint], fixed)
    bias = [0.0] * logits.shape[1]
    best = before = search.score(bias)
    for _ in range(rounds):
        for c in list(paint) + list(range(NUM_CLASSES, logits.shape[1])):
            # every trial differs from `bias` in class c alone: all of c's scored at once
            scores = search.scores_along(bias, int(c), BIAS_GRID)
            for v, got in zip(BIAS_GRID, scores, strict=True):
                if got > best + 1e-4:
                    best, bias = got, bias[:c] + [float(v)] + bias[c + 1:]
    with torch.no_grad():  # a sub-pixel head: each class's offset on all its sub-pixels
        model.head.bias += torch.tensor(bias, dtype=model.head.bias.dtype,
                                        device=model.head.bias.device
                                        ).repeat_interleave(model.subpixel ** 2)
    logger.info("logit offsets %s: mean paint IoU on calibration frames %.4f -> %.4f "
                "(%.1f %% of pixels open)", bias, before, best,
                100.0 * float(open_.float().mean()))
    return bias


class OffsetSearch:
    """The mean IoU of the paint classes when each pixel takes the class of its largest offset
    logit, for calibrate_bias's coordinate ascent. `logits` (P, classes) float32 and `truth`
    (P,) are its open pixels; `fixed` holds each paint class's (intersection, union) over the
    pixels no offset on the grid can change. The labels are argmax's, ties to the lower class
    as torch and numpy break them, and the counts exact, so a search finds the offsets that an
    argmax per trial finds, in a fraction of the time."""

    def __init__(self, logits: np.ndarray, truth: np.ndarray, paint: list[int], fixed: dict):
        self.logits, self.truth = np.ascontiguousarray(logits, np.float32), truth.astype(np.int64)
        self.paint, self.fixed = paint, fixed
        self.n = self.logits.shape[1]

    def score(self, bias: list[float]) -> float:
        pred = (self.logits + np.asarray(bias, np.float32)).argmax(1)
        return self._mean_iou(np.bincount(pred * self.n + self.truth, minlength=self.n ** 2)
                              .reshape(self.n, self.n))

    def scores_along(self, bias: list[float], c: int, values: np.ndarray) -> list[float]:
        """The scores of `bias` with class c's offset set to each of `values` (ascending).
        Each pixel's label is then c or the best of the other classes, whichever wins, and
        once c wins at one value it wins at every larger one: one count of the pixels by the
        number of values at which c loses, their other class and their truth gives every
        value's confusion matrix."""
        if np.any(np.diff(values) <= 0):
            raise ValueError(f"offsets must ascend: {values}")
        others = self.logits + np.asarray(bias, np.float32)
        others[:, c] = -np.inf
        best_other, other = others.max(1), others.argmax(1)
        del others
        wins_tie = c < other  # an equal logit goes to the lower class
        own = np.ascontiguousarray(self.logits[:, c])
        loses = np.zeros(len(own), np.uint16)  # at how many of the values c loses the pixel
        for v in values:
            shifted = own + np.float32(v)
            loses += ~((shifted > best_other) | ((shifted == best_other) & wins_tie))
        k, n = len(values), self.n
        counts = np.bincount((loses.astype(np.int64) * n + other) * n + self.truth,
                             minlength=(k + 1) * n * n).reshape(k + 1, n, n)
        scores = []
        for i in range(k):  # at values[i], c has the pixels it loses at i or fewer values
            confusion = counts[i + 1:].sum(0)
            confusion[c] += counts[:i + 1].sum((0, 1))
            scores.append(self._mean_iou(confusion))
        return scores

    def _mean_iou(self, confusion: np.ndarray) -> float:
        """From a confusion matrix of the open pixels (rows: label, columns: truth)."""
        ious = []
        for c in self.paint:
            inter = self.fixed[c][0] + int(confusion[c, c])
            union = (self.fixed[c][1] + int(confusion[c].sum()) + int(confusion[:, c].sum())
                     - int(confusion[c, c]))
            ious.append(inter / max(union, 1))
        return float(np.mean(ious)) if ious else 0.0


REFINE_WINDOWS = (3, 5, 7, 9)
REFINE_LEVELS = (0.4, 0.5, 0.6, 0.7, 0.8)


def calibrate_refine(model_path, frames: np.ndarray, labels: np.ndarray,
                     sky_fraction: float = 0.0) -> dict:
    """The paint-border settings (common.segmentation.refine_paint_borders: box `window`,
    threshold `level`) that maximise the mean paint IoU of the exported model as the runtime
    runs it, on up to CALIBRATE_FRAMES town frames (N, H, W, 3) at the model's input size;
    {} (no refinement) when no setting beats the labels as they are. `sky_fraction`: the
    top share of rows left out, as OnnxSegmenter's."""
    seg = OnnxSegmenter(model_path, refine={}, border_net=False, sky_fraction=sky_fraction)
    frames, labels = frames[:CALIBRATE_FRAMES], labels[:CALIBRATE_FRAMES]
    raw = [seg.segment_model_size(f) for f in frames]
    grays = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]

    def score(settings):
        acc = IouAccumulator()
        for g, p, truth in zip(grays, raw, labels, strict=True):
            acc.add(refine_paint_borders(g, p, **settings) if settings else p, truth)
        return mean_paint_iou(acc.result())

    best, best_score = {}, score({})
    for window in REFINE_WINDOWS:
        for level in REFINE_LEVELS:
            settings = {"window": window, "level": level}
            if (s := score(settings)) > best_score:
                best, best_score = settings, s
    return best


def runtime_iou(model_path, frames: np.ndarray, labels: np.ndarray,
                sky_fraction: float = 0.0) -> dict:
    """Per-class IoU (None: absent from the truth) of the exported model as OnnxSegmenter
    segments (its metadata's settings; `sky_fraction` as its own) on town frames at the
    model's input size."""
    return segmenter_iou(OnnxSegmenter(model_path, sky_fraction=sky_fraction), frames, labels)


def set_metadata(path, **updates) -> None:
    """Update keys of an exported model's `roadmap.segmentation` metadata in place."""
    import onnx

    proto = onnx.load(str(path))
    entry = _meta_entry(proto)
    if entry is None:
        entry = proto.metadata_props.add()
        entry.key, entry.value = META_KEY, "{}"
    entry.value = json.dumps({**json.loads(entry.value), **updates})
    onnx.save(proto, str(path))


def _meta_entry(proto):
    """The `roadmap.segmentation` metadata entry of an ONNX model proto, or None."""
    return next((e for e in proto.metadata_props if e.key == META_KEY), None)


def _heap_trimmer():
    """A function handing the heap's free pages back to the OS (glibc malloc_trim), else a
    no-op. Every step's batch-sized tensors (5-8 MB, several sizes) come from the heap (glibc
    raises its mmap threshold after large frees), which fragments: CPU training grew ~7 MB per
    step and was killed for memory (24 GB) after 2100 steps. Trimming every TRIM_EVERY steps
    keeps it bounded at full speed (a 40 min CPU run, 5352 frames, 10382 steps at 4.3 steps/s:
    9.2-9.9 GB throughout, the frames being 8.7 GB of it); forcing
    large blocks to mmap instead (mallopt) cost 2.7x the step time (page faults)."""
    import ctypes
    import ctypes.util

    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return lambda: None
    return lambda: trim(0)


def _mean_loss(losses: list) -> float:
    """Mean of the last 100 step losses (0-d tensors): one device sync."""
    import torch

    return float(torch.stack(losses[-100:]).mean())


def _lr(frac: float, peak: float = LR_MAX) -> float:
    """Linear warm-up over the first 3 %, then cosine decay to 2 % of the peak."""
    if frac < 0.03:
        return peak * (0.1 + 0.9 * frac / 0.03)
    p = (frac - 0.03) / 0.97
    return peak * (0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * min(p, 1.0))))


def _crop_batch(x, y, rng, crop_hw=CROP_HW, half=None):
    """Random crops (H, W) = crop_hw; same window for the whole batch (cheap, still varied).
    Mostly from the lower part of the frame (the road; the sky is easy), sometimes anywhere.
    `half` (N, C, H/2, W/2: a teacher's logits at 1/2 resolution), when given, is cropped to
    the same window, which then starts on an even row and column so that its 1/2-resolution
    grid is the frame's. -> (images, labels, the crop's top row in the frame, `half`'s crop or
    None)."""
    h, w = crop_hw
    span = x.shape[2] - h
    lo = 0 if rng.random() < 0.3 else span // 2
    top = int(rng.integers(lo, span + 1))
    left = int(rng.integers(0, x.shape[3] - w + 1))
    if half is not None:
        check_even_crop(crop_hw)
        top, left = top - top % 2, left - left % 2
        half = half[:, :, top // 2:(top + h) // 2, left // 2:(left + w) // 2]
    return x[:, :, top:top + h, left:left + w], y[:, top:top + h, left:left + w], top, half


def augment(x_u8, y, rng, extra=None):
    """Photometric augmentation on a uint8 batch -> float [0, 1]: brightness, contrast, colour
    cast, gamma, blur, noise; plus horizontal flips (paint classes are mirror-invariant) ->
    (images, labels), and `extra` (N, C, h, w: e.g. a teacher's logits) flipped with them as
    a third when given (the random draws are the same either way)."""
    import torch
    from torch.nn import functional as F

    n, dev = x_u8.shape[0], x_u8.device

    def draw(lo, hi, shape):
        return torch.from_numpy(rng.uniform(lo, hi, shape).astype(np.float32)).to(dev)

    x = x_u8.float() / 255.0
    gain, cast = draw(0.55, 1.45, (n, 1, 1, 1)), draw(0.85, 1.15, (n, 3, 1, 1))
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    contrast = draw(0.6, 1.3, (n, 1, 1, 1))
    x = ((x - mean) * contrast + mean) * gain * cast
    x = x.clamp(1e-4, 1.0) ** draw(0.7, 1.4, (n, 1, 1, 1))
    if rng.random() < 0.4:
        sigma = float(rng.uniform(0.4, 1.2))
        k = torch.from_numpy(_gauss_kernel(sigma)).to(dev).expand(3, 1, 5, 5).contiguous()
        x = F.conv2d(F.pad(x, (2, 2, 2, 2), mode="replicate"), k, groups=3)
    x = x + torch.randn_like(x) * draw(0.0, 0.05, (n, 1, 1, 1))
    flip = torch.from_numpy(rng.random(n) < 0.5).to(dev)
    x[flip] = x[flip].flip(-1)
    y = y.clone()
    y[flip] = y[flip].flip(-1)
    if extra is None:
        return x.clamp(0.0, 1.0), y
    extra = extra.clone()
    extra[flip] = extra[flip].flip(-1)
    return x.clamp(0.0, 1.0), y, extra


def _gauss_kernel(sigma: float) -> np.ndarray:
    r = np.arange(-2, 3, dtype=np.float32)
    g = np.exp(-0.5 * (r / sigma) ** 2)
    k = np.outer(g, g)
    return (k / k.sum()).astype(np.float32)[None, None]


def _validate(model, x_u8, y) -> dict:
    import torch

    with torch.no_grad():
        pred = np.concatenate([model(x_u8[i:i + 8].float() / 255.0).argmax(1).cpu().numpy()
                               for i in range(0, len(x_u8), 8)])
    y = y.cpu().numpy()
    y = np.where(y >= NUM_CLASSES, 0, y)  # auxiliary classes count as none (folded)
    out = {}
    for c in Cls:
        if c == Cls.NONE:
            continue
        p, t = pred == c, y == c
        union = int((p | t).sum())
        out[NAMES[c]] = round(float((p & t).sum() / union), 4) if union else None
    return out


def export_onnx(model, path: Path, *, seed: int, block: int = 16) -> None:
    """Input (1, 3, H, W) float RGB / 255 (W fixed, H dynamic, nominally INPUT_SIZE's);
    output `logits` (1, 6, H/2, W/2), which
    OnnxSegmenter upsamples bilinearly to (H, W) before its argmax (a sub-pixel head: (1, 6 x 4,
    H/2, W/2), argmaxed per sub-pixel); self-describing metadata under `roadmap.segmentation`
    (read by OnnxSegmenter). The graph is `model` with its channels padded to multiples of 16
    (net.aligned) and its decoder blocks without their concatenations
    (onnx_graph.split_concatenations): the same function, 2.4 ms a frame faster in
    onnxruntime (9.5 -> 7.1 ms, one thread, 640x312); its metadata's `arch` gives the padded
    widths. `block`: the alignment (8 suits the blocked convolutions of AVX2 alone; only
    training/bench/archs.py asks for it)."""
    import onnx
    import torch

    from training.net import aligned
    from training.onnx_graph import split_concatenations

    w, h = INPUT_SIZE
    model.half_res_logits = True  # the runtime upsamples (OnnxSegmenter.segment_model_size)
    model = aligned(model, block)
    dummy = torch.rand(1, 3, h, w)
    # the height is dynamic, so the runtime can leave out the rows above the horizon
    # (OnnxSegmenter's sky_fraction; it fixes the height it runs at when it loads the file)
    torch.onnx.export(model, (dummy,), str(path), input_names=["image"],
                      output_names=["logits"], opset_version=17, dynamo=False,
                      do_constant_folding=True,
                      dynamic_axes={"image": {2: "height"}, "logits": {2: "logit_height"}})
    proto = onnx.load(str(path))
    split_concatenations(proto)
    meta = {"name": "roadseg", "arch": model.arch, "input_size": [w, h], "scale": 1.0 / 255.0,
            "mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0],
            "classes": [NAMES[c] for c in Cls], "seed": seed}
    if model.subpixel > 1:  # logits (1, 6 * s * s, H/2, W/2), laid out as F.pixel_shuffle's
        meta["subpixel"] = model.subpixel
    entry = proto.metadata_props.add()
    entry.key, entry.value = META_KEY, json.dumps(meta)
    proto.producer_name = "roadmap train-seg"
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))


def class_offsets(text: str | None) -> dict[int, float]:
    """--add-offsets' "lane_line=0.4,crosswalk=-0.2" -> {class id: logits} (road and the
    markings, by their report names)."""
    ids = {name: int(c) for c, name in NAMES.items() if c != Cls.NONE}
    offsets = {}
    for item in filter(None, (text or "").split(",")):
        name, _, value = item.partition("=")
        try:
            cls, logits = ids[name.strip()], float(value)
        except (KeyError, ValueError):
            raise ConfigError(f"--add-offsets {item!r}: give CLASS=LOGITS, CLASS one of "
                              f"{sorted(ids)}") from None
        if not np.isfinite(logits):
            raise ConfigError(f"--add-offsets {item!r}: give CLASS=LOGITS (a finite number)")
        offsets[cls] = logits
    return offsets


def reexport_onnx(src, dst, offsets: dict[int, float] | None = None, **updates) -> dict:
    """The RoadSegNet export `src` written again to `dst` by export_onnx (same weights, its
    metadata kept but for `updates`; a key updated to None is removed), checked against `src`
    on random frames -> {max_abs_diff, argmax_agreement}. For files exported before
    export_onnx changed (a fixed input height before 2026-11-25), and for a file fitted for
    one pass that the runtime is to run otherwise (flip_average=True: run G2 of 2026-11-28,
    whose offsets and border classifier fitted for one pass localized better in two passes
    than refitted for two; flip="alternate": the same file in one pass a frame, on the image
    and on its mirror in turn, 2026-11-29). `offsets` {class: logits} are added to those
    classes' rows of the head's bias (where a run's own offsets ride), and the check expects
    them in the new file's logits."""
    import onnxruntime as ort
    import torch

    from training.net import RoadSegNet, load_onnx_weights

    sess = ort.InferenceSession(str(src), providers=["CPUExecutionProvider"])
    meta = session_metadata(sess)
    if "arch" not in meta:
        raise ConfigError(f"{src}: not a RoadSegNet export (no 'arch' in its metadata)")
    arch = dict(meta["arch"])
    model = RoadSegNet(num_classes=seg_data.TRAIN_CLASSES, widths=arch["widths"],
                       depths=arch["depths"], rows=arch.get("rows", False),
                       subpixel=arch.get("subpixel", 1))
    load_onnx_weights(model, src)  # a 6-class head: the curb row starts as none (same output)
    model.eval()
    model.export_classes = NUM_CLASSES
    shift = np.zeros(NUM_CLASSES, np.float32)
    for cls, logits in (offsets or {}).items():
        if not Cls.ROAD <= cls < NUM_CLASSES:  # none's row is folded with the curb's
            raise ConfigError(f"offsets: class {cls} is not one of road and the markings")
        shift[cls] = logits
    with torch.no_grad():
        model.head.bias.view(-1, model.subpixel ** 2)[:NUM_CLASSES] += torch.from_numpy(
            shift)[:, None]
    Path(dst).parent.mkdir(parents=True, exist_ok=True)
    export_onnx(model, Path(dst), seed=meta.get("seed", 0))
    kept = {k: v for k, v in (meta | updates).items() if k != "arch" and v is not None}
    set_metadata(dst, **kept)  # export_onnx wrote its arch
    new = ort.InferenceSession(str(dst), providers=["CPUExecutionProvider"])
    w, h = INPUT_SIZE
    x = np.random.default_rng(0).random((4, 3, h, w), np.float32)
    diffs, agree = [], []
    for frame in x:
        a = sess.run(None, {sess.get_inputs()[0].name: frame[None]})[0]
        a = a + np.repeat(shift, a.shape[1] // NUM_CLASSES)[None, :, None, None]
        b = new.run(None, {"image": frame[None]})[0]
        diffs.append(float(np.abs(a - b).max()))
        agree.append(float((a.argmax(1) == b.argmax(1)).mean()))
    if max(diffs) > 1e-3 or min(agree) < 0.9999:
        raise RuntimeError(f"re-export of {src} differs: max diff {max(diffs)}, "
                           f"argmax agreement {min(agree)}")
    return {"max_abs_diff": max(diffs), "argmax_agreement": min(agree)}


def verify_onnx(model, path: Path, x_u8) -> tuple[float, float]:
    """(max |onnxruntime - torch| over logits, argmax agreement) on full frames."""
    import onnxruntime as ort
    import torch

    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    diffs, agree = [], []
    for i in range(len(x_u8)):
        x = x_u8[i:i + 1].float() / 255.0
        with torch.no_grad():
            ref = model(x).numpy()
        got = sess.run(None, {"image": x.numpy()})[0]
        diffs.append(float(np.abs(ref - got).max()))
        agree.append(float((ref.argmax(1) == got.argmax(1)).mean()))
    max_diff, agreement = max(diffs), float(np.mean(agree))
    if max_diff > 1e-2 or agreement < 0.999:
        raise RuntimeError(f"ONNX export differs from torch: max diff {max_diff}, "
                           f"argmax agreement {agreement}")
    return max_diff, agreement


def _flip_text(result: dict) -> str:
    if result.get("flip_average"):
        return ("on (metadata `flip_average`): the runtime averages the network's logits of the "
                "image and of its mirror image (mirrored back), twice the network's time.")
    return "off (`--no-flip-average`)."


def _sky_text(result: dict) -> str:
    margin = result.get("sky_margin_deg")
    if margin is None:
        return ("the runtime's default (segmentation.sky_margin_deg): rows above rays rising "
                f"{DEFAULT_SKY_MARGIN_DEG:g} degrees above level are not segmented.")
    if margin < 0:
        return (f"every row segmented (metadata `sky_margin_deg` {margin:g}): the network's "
                "coarsest stage reads the whole frame, so leaving out the sky changes its output.")
    return (f"rows above rays rising {margin:g} degrees above level are not segmented "
            "(metadata `sky_margin_deg`).")


def model_card(result: dict) -> str:
    w, h = INPUT_SIZE
    share = result.get("synth_share", seg_data.SYNTH_SHARE)
    return f"""# roadseg.onnx: road-marking segmentation (RoadMap)

- **Classes** (output channel = our class id, DESIGN.md): 0 none/unknown, 1 road surface,
  2 lane line, 3 stop line, 4 crosswalk, 5 ground sign (arrows, text).
- **Input** `image`: float32 [1, 3, {h}, {w}] (N, C, H, W), RGB, value = pixel / 255
  (no mean/std: mean 0, std 1). {w}x{h} is the camera's own size: frames of the default
  camera go in unresized (other sizes are resized with cv2.INTER_AREA).
- **Output** `logits`: {_output_text(result, w, h)}, re-decides the paint borders on the image
  (below), then resizes the labels to the frame size (nearest). The
  same settings are stored in the model's metadata (`roadmap.segmentation`), so
  `OnnxSegmenter()` needs no arguments.
- **Flip averaging**: {_flip_text(result)}
- **Sky rows**: {_sky_text(result)}
- **Network**: RoadSegNet (training/net.py): 4x4 stride-2 stem on the full-resolution
  image, depthwise-separable encoder-decoder with stages at 1/4, 1/8, 1/16 (dilated context),
  U-Net skips back to 1/2, logits at 1/2 (upsampled by the runtime);
  {result["params"]} trained parameters, {result["model_bytes"] / 1024:.0f} KiB, ONNX opset 17;
  the graph pads the channels to multiples of 16 and splits the decoder's concatenations (the
  same function, faster in onnxruntime: net.aligned, onnx_graph.split_concatenations).
- **Training data**: only seeded procedural towns (services/sim/town.py), never the Karlsruhe or
  Argoverse 2 benchmark worlds: {result["frames"]} frames in chunks of one town each (seeded by
  (seed, chunk), training/data.py); roads of 1 / 2 / 3 / 4 lanes each way in
  {_percent_list(seg_data.LANE_MIX)} % of the towns' roads, {100 * seg_data.MEDIAN_PROB:.0f} % of
  those of two or more split by a raised median 1-4 m wide; {100 * (1 - share):.0f} % rendered by
  the simulator's renderer (services/sim/render.py: random looks, worn paint, raised curbs and
  sidewalks, shadows, haze, skyline, other cars) and {100 * share:.0f} % by
  training/synth.py (more materials, curb face / top
  / sidewalk bands); curb faces sunlit in {100 * seg_data.SUNLIT_CURB:.0f} % of the looks (then the
  curb is often brighter than worn paint), else in shade; at random route poses (half facing stop
  lines, crosswalks or signs, {100 * result.get("turn_prob", seg_data.TURN_PROB):.0f} % turned 15-90
  deg off the route: lane lines crossing the view), with camera height 1.25-1.75 m, pitch 1.5-7 deg,
  roll/yaw jitter, focal length +-15 %, principal point and distortion jitter. The towns' paint is
  restyled per town (`restyled`, `thinned`): edge lines dropped on 40-100 % of road sides (curb-only
  edges; 85 % of looks draw curbs), shoulders narrowed to none, lane-line widths 0.10-0.16 m and
  patches of thick 0.2-0.3 m lines, 5-35 % of lane-line pieces removed; dashed lane lines through
  30-90 % of the junctions of 80 % of the towns (`junction_lines`: straight across, and curved turn
  guides). Training-time augmentation: brightness, contrast, colour cast, gamma, blur, noise,
  horizontal flips, {_crop_text(result)}.
- **Auxiliary class**: training labels mark raised curbs (their vertical face and top band, from
  the renderers' curb geometry) as a 7th class; the export folds it into none (channel 0 = max
  of none and curb logits at 1/2 resolution), so the model's outputs are our 6 classes. A light
  curb looks like an edge line: labelled none, it held most lane-line false positives.
- **Training**: `{result.get("command", "roadmap train-seg")}`
  (`pip install .[train]`){_init_text(result)}, RoadSegNet {_arch_text(result)}, AdamW,
  cosine schedule (peak learning rate {result.get("lr_max", LR_MAX):g}),
  class-weighted cross-entropy (weights {result["class_weights"]}){_loss_text(result)}, device
  `{result.get("device", "cpu")}`{" (bfloat16 autocast)" if result.get("bf16") else ""},
  batch {result.get("batch", BATCH)}; {result["steps"]} steps in
  {result["train_s"] / 60:.1f} min after {result.get("render_s", 0) / 60:.1f} min of rendering{
    " (the first frames; rendering went on while it trained)" if result.get("stream") else ""}.{
    _ema_text(result)}{_soup_text(result)}{_average_init_text(result)}
  The export is checked against torch with onnxruntime
  (max |diff| {result["onnx_max_abs_diff"]:.1e},
  argmax agreement {result["onnx_argmax_agreement"]:.4f}).
- **Logit offsets** added to the head's bias after training (calibrate_bias: per class, the
  offset maximising the mean paint IoU on half of the held-out town frames):
  {result.get("logit_bias")}.
- **Paint borders** re-decided on the image's brightness by the runtime (metadata `refine`,
  common.segmentation.refine_paint_borders; calibrate_refine: the setting maximising the mean
  paint IoU on the same town frames as the offsets, {{}} = off): {result.get("refine")}.
  A learned border classifier (metadata `border_net`, which the runtime then uses instead:
  `segmentation.border_net`, on by default) is fitted afterwards on town frames of another
  seed (`--border-frames N`, or later `roadmap train-seg --border-only DIR/roadseg.onnx --out
  DIR --seed S --frames 2880`): {_border_text(result.get("border"))}.
- **Validation** (the other half of the held-out procedural-town frames, model input size):
  {result["val_iou_town"]} (torch, before the border refinement); as the runtime segments them:
  {result.get("val_iou_town_runtime")}.
- **Held-out benchmark worlds**: see the metrics section below (services/bench/segmentation.py).
"""


def _arch_text(result: dict) -> str:
    a = ARCHS[result.get("arch", "s")]
    rows = ", row embedding at 1/8 and 1/16" if a["rows"] else ""
    sub = ", sub-pixel head: full-resolution logits" if a.get("subpixel", 1) > 1 else ""
    return (f"`{result.get('arch', 's')}` (widths {a['widths']} at 1/2..1/16, blocks "
            f"{a['depths']} at 1/4, 1/8, 1/16{rows}{sub})")


def _output_text(result: dict, w: int, h: int) -> str:
    s = ARCHS[result.get("arch", "s")].get("subpixel", 1)
    if s > 1:
        return (f"float32 [1, 6 x {s * s}, {h // 2}, {w // 2}] (sub-pixel logits at 1/2 of the "
                f"input, channel c x {s * s} + {s}i + j: class c at pixel ({s}y + i, {s}x + j); "
                "metadata `subpixel`); OnnxSegmenter takes the argmax of each sub-grid and "
                f"interleaves them into {w}x{h} labels")
    return (f"float32 [1, 6, {h // 2}, {w // 2}] (1/2 of the input); OnnxSegmenter upsamples "
            f"them bilinearly to {w}x{h} (half-pixel centres, as torch's align_corners=False) "
            "and takes the argmax over axis 1")


def _border_text(border: dict | None) -> str:
    if not border:
        return "none fitted by this run"
    check = border["check"]
    verdict = "kept" if border["kept"] else "not kept: it did not beat the rule"
    return (f"{border['frames']} frames of seed {border['seed']} (fitted on "
            f"{border['samples']} border pixels of the first {border['fit_frames']}); mean "
            f"paint IoU on the last {border['check_frames']} "
            f"{check['border_net']['paint']:.4f} against the rule's "
            f"{check['rule']['paint']:.4f}: {verdict}")


def _percent_list(shares) -> str:
    return " / ".join(f"{100 * p:.0f}" for p in shares)


def _crop_text(result: dict) -> str:
    h, w = result.get("crop_hw", CROP_HW)
    top = result.get("top_rows", 0)
    if (w, h + top) == INPUT_SIZE:
        return (f"whole {w}x{h} frames (no crops)" if not top else
                f"whole {w}x{h + top} frames without their top {top} rows (no crops; the rows "
                "the sky margin leaves out, --sky-cut-training)")
    full_after = result.get("full_after", 1.0)
    if full_after < 1.0:
        return (f"random {w}x{h} crops for the first {100 * full_after:g} % of the steps, "
                "whole frames after")
    return f"random {w}x{h} crops"


def _loss_text(result: dict) -> str:
    w, hard = result.get("iou_loss_weight"), result.get("hard_pixels", 1.0)
    text = f" over the {100 * hard:g} % hardest pixels of each batch" if hard < 1.0 else ""
    text += f" plus {w:g} x soft-Jaccard loss on the paint and curb classes" if w else ""
    mirror = result.get("mirror_consistency", 0.0)
    return text + (f" plus {mirror:g} x mirror consistency (half of each batch mirrored)"
                   if mirror else "")


def _soup_text(result: dict) -> str:
    runs = result.get("soup")
    if not runs:
        return ""
    each = "; ".join(f"junction lines {r['junctions']}: {r['steps']} steps on {r['frames']} "
                     f"frames in {r['train_s'] / 60:.1f} min" for r in runs)
    return (f"\n  A soup of {len(runs)} runs (`--soup`), one after the other from the same "
            f"start, each on its own towns ({each}; the class weights above are the first "
            "run's); the export is their weights averaged name by name.")


def _ema_text(result: dict) -> str:
    if not result.get("ema"):
        return ""
    return ("\n  The exported weights are the moving average of every step's (decay "
            f"{result['ema']:g} per step,\n  bias-corrected: WeightAverage), not the last "
            "step's.")


def _average_init_text(result: dict) -> str:
    w = result.get("average_init")
    if not w:
        return ""
    return (f"\n  The exported weights are {1 - w:g} x the trained ones + {w:g} x those of the\n"
            "  model it started from (`--average-init`: a fine-tune averaged with its start).")


def _init_text(result: dict) -> str:
    if not result.get("init"):
        return ""
    # an export's folded norms stay frozen; a roadseg.pt's train on unless its run froze them
    norms = ("its folded batch norms kept frozen" if result.get("frozen_norms", True)
             else "its batch norms training on from its statistics")
    return (f",\n  fine-tuned from `{result['init']}` ({norms}; see\n"
            "  'Reproducing it' for the model it started from)")
