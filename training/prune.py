"""Structured pruning of a trained RoadSegNet's 1/4-resolution channels (torch; training only).

Why: the 1/2-resolution decoder reads the 1/4 decoder features upsampled, and onnxruntime's
blocked convolutions pad channels to multiples of 16 on AVX-512, so the default network's 20
channels at 1/4 run as 32. At 16 a network pass takes 5.6 instead of 7.9 ms (one thread,
640x312; the other stages at the widths the blocked layout computes anyway, [16, 16, 48,
64]). Training that network from scratch costs the whole chain again; pruning the trained one
and fine-tuning it is one stage.

How: the 1/4 stage has two feature spaces of the same width, the encoder's (down1's output,
enc1's residual blocks, read by down2 and by dec1's skip) and the decoder's (dec1's output,
read upsampled by dec0). Channels are dropped one at a time, alternately from the decoder and
the encoder, each time the one whose removal raises the class-weighted cross-entropy on a few
town frames least (the network's own batch norms folded, so a dropped channel is exactly
zero), until both have the target width. The pruned network is then widened (net.widen) to the
target architecture's other widths, computing the same function, and saved as `--init` reads
it."""

import copy
import json
import logging
import time
from pathlib import Path

import numpy as np

from common.errors import ConfigError
from training import data as seg_data
from training.archs import ARCHS

logger = logging.getLogger(__name__)

PRUNE_FRAMES = 48  # frames the ablations' loss is measured on (drawn by default_rng(0))
WEIGHT_FRAMES = 600  # frames whose labels set the loss's class weights
SOURCE_ARCH = "s"  # the architecture of the models pruned: the packaged one's


def quarter_channels(model, enc_keep, dec_keep):
    """(name, convolution, out_map, in_map) for each convolution of `model`: the indices of
    its output and input channels (a depthwise convolution's one input channel is its
    output's) that a network keeping only the 1/4-resolution encoder channels `enc_keep` and
    decoder channels `dec_keep` computes and reads. The encoder's channels come out of down1's
    pointwise convolution and enc1's blocks, which read them, as down2 does and dec1 after the
    upsampled 1/8 channels of its concatenation; the decoder's come out of dec1 and are read by
    dec0, before its 1/2-resolution skip."""
    import torch
    from torch import nn

    w0, w1, w2, _ = model.arch["widths"]
    enc, dec = torch.as_tensor(enc_keep), torch.as_tensor(dec_keep)
    for name, conv in model.named_modules():
        if not isinstance(conv, nn.Conv2d):
            continue
        block, depthwise = name.split(".")[0], conv.groups > 1
        out_map = torch.arange(conv.out_channels)
        in_map = torch.arange(conv.in_channels // conv.groups)
        if (block == "down1" and not depthwise) or block == "enc1":
            out_map = enc
            if block == "enc1" and not depthwise:
                in_map = enc
        elif block == "down2":
            out_map, in_map = (enc, in_map) if depthwise else (out_map, enc)
        elif block == "dec1":
            cat = torch.cat([torch.arange(w2), w2 + enc])
            out_map, in_map = (cat, in_map) if depthwise else (dec, cat)
        elif block == "dec0":
            cat = torch.cat([dec, w1 + torch.arange(w0)])
            out_map, in_map = (cat, in_map) if depthwise else (out_map, cat)
        yield name, conv, out_map, in_map


def quarter_masked(model, enc_drop, dec_drop):
    """A copy of `model` (batch norms folded: scale 1, running mean 0) whose 1/4-resolution
    encoder channels `enc_drop` and decoder channels `dec_drop` are zero and read by nothing:
    what `narrowed_quarter` without them computes, at the full width."""
    import torch

    from training.net import _norm_after

    m = copy.deepcopy(model)
    w1 = model.arch["widths"][1]
    enc = [c for c in range(w1) if c not in enc_drop]
    dec = [c for c in range(w1) if c not in dec_drop]
    mods = dict(m.named_modules())
    with torch.no_grad():
        for name, conv, out_map, in_map in quarter_channels(m, enc, dec):
            dropped_out = _complement(out_map, conv.out_channels)
            conv.weight[dropped_out] = 0.0
            if (norm := _norm_after(mods, name)) is not None:
                norm.bias[dropped_out] = 0.0
            if conv.groups == 1:
                conv.weight[:, _complement(in_map, conv.in_channels)] = 0.0
    return m


def _complement(index, n: int):
    """The indices below n that `index` does not hold."""
    import torch

    keep = torch.zeros(n, dtype=torch.bool)
    keep[index] = True
    return (~keep).nonzero().flatten()


def narrowed_quarter(model, enc_keep, dec_keep):
    """`model` with only the 1/4-resolution encoder channels `enc_keep` and decoder channels
    `dec_keep` (as many of each), every other weight copied: a RoadSegNet of that width at
    1/4, eval mode."""
    from training.net import RoadSegNet, _norm_after, gather_channels

    if len(enc_keep) != len(dec_keep):
        raise ValueError(f"keep as many encoder as decoder channels ({len(enc_keep)}, "
                         f"{len(dec_keep)})")
    w0, _, w2, w3 = model.arch["widths"]
    new = RoadSegNet(widths=[w0, len(enc_keep), w2, w3], num_classes=model.head.out_channels,
                     depths=model.arch["depths"], rows=model.arch["rows"])
    old, mods = dict(model.named_modules()), dict(new.named_modules())
    for name, src, out_map, in_map in quarter_channels(model, enc_keep, dec_keep):
        gather_channels(mods[name], src, out_map, in_map, _norm_after(mods, name),
                        _norm_after(old, name))
    return new.eval()


def greedy_quarter_pruning(model, width: int, loss_of) -> tuple[list[int], list[int], list]:
    """Drop 1/4-resolution channels one at a time, decoder then encoder in turn, each the one
    whose removal leaves `loss_of(quarter_masked(...))` lowest, until `width` of each are left
    -> (encoder channels kept, decoder channels kept, [(group, channel, loss)] in order)."""
    w1 = model.arch["widths"][1]
    if not 0 < width <= w1:
        raise ConfigError(f"cannot prune {w1} channels at 1/4 resolution to {width}")
    drop = {"enc": [], "dec": []}
    steps = []
    for _ in range(w1 - width):
        for group in ("dec", "enc"):
            best = None
            for c in range(w1):
                if c in drop[group]:
                    continue
                trial = {**drop, group: drop[group] + [c]}
                loss = loss_of(quarter_masked(model, trial["enc"], trial["dec"]))
                if best is None or loss < best[0]:
                    best = (loss, c)
            drop[group].append(best[1])
            steps.append((group, best[1], round(best[0], 5)))
            logger.info("pruning: drop %s channel %d -> loss %.4f", group, best[1], best[0])
    keep = {g: [c for c in range(w1) if c not in d] for g, d in drop.items()}
    return keep["enc"], keep["dec"], steps


def prune_command(args, out: Path, input_size) -> int:
    """`roadmap train-seg --prune MODEL --arch A`: MODEL (an export of the default
    architecture) pruned at 1/4 resolution to A's width there, by the loss on PRUNE_FRAMES of
    the town frames of --seed (--frames of them, --soup's junction dose), then widened to A
    and written as DIR/roadseg.pt (for --init, with --arch A) with DIR/prune_log.json."""
    import torch
    from torch import nn

    from training.net import RoadSegNet, widen
    from training.weights import (
        NO_RENDER_BUDGET_S,
        THREADS,
        _load_init,
        check_export_file,
        class_weights,
        frame_cache,
        save_weights,
    )

    target = ARCHS[args.arch]
    source = ARCHS[SOURCE_ARCH]
    same_but_widths = ({k: v for k, v in target.items() if k != "widths"}
                       == {k: v for k, v in source.items() if k != "widths"})
    if not same_but_widths or any(t < s for i, (t, s) in enumerate(
            zip(target["widths"], source["widths"], strict=True)) if i != 1):
        raise ConfigError(f"--prune: --arch {args.arch} must be --arch {SOURCE_ARCH} with "
                          "its 1/4-resolution width changed (the others as wide or wider)")
    if args.soup and len(args.soup) > 1:
        raise ConfigError("--prune: give one --soup dose (the towns of the frames)")
    check_export_file("--prune", args.prune)
    t0 = time.perf_counter()
    torch.set_num_threads(THREADS)
    model = RoadSegNet(num_classes=seg_data.TRAIN_CLASSES, **source)
    _load_init(model, args.prune)
    model.eval()
    frames, labels = seg_data.training_set(
        seed=args.seed, input_size=input_size, budget_s=NO_RENDER_BUDGET_S,
        max_frames=args.frames, workers=args.workers, **frame_cache(args),
        turn_prob=args.turn_prob, synth_share=args.synth_share,
        junctions=args.soup[0] if args.soup else "light")
    pick = np.random.default_rng(0).choice(len(frames), min(PRUNE_FRAMES, len(frames)),
                                           replace=False)
    x = torch.from_numpy(frames[pick]).permute(0, 3, 1, 2).float() / 255.0
    y = torch.from_numpy(labels[pick]).long()
    weights = torch.tensor(class_weights(labels[:WEIGHT_FRAMES]), dtype=torch.float32)
    loss_fn = nn.CrossEntropyLoss(weight=weights)
    del frames, labels

    def loss_of(m) -> float:
        with torch.no_grad():
            return float(sum(loss_fn(m(x[i:i + 8]), y[i:i + 8]) for i in range(0, len(x), 8))
                         / (len(x) / 8))

    before = loss_of(model)
    enc, dec, steps = greedy_quarter_pruning(model, target["widths"][1], loss_of)
    pruned = narrowed_quarter(model, enc, dec)
    torch.manual_seed(args.seed)  # the new channels' weights (widen): the same file each run
    wide = RoadSegNet(num_classes=seg_data.TRAIN_CLASSES, **target)
    widen(pruned, wide)
    wide.eval()
    after = loss_of(wide)
    out.mkdir(parents=True, exist_ok=True)
    save_weights(wide, True, out / "roadseg.pt")
    log = {"source": str(args.prune), "arch": args.arch, "widths": target["widths"],
           "seed": args.seed, "frames": args.frames, "loss_frames": len(pick),
           "junctions": args.soup[0] if args.soup else "light",
           "encoder_kept": enc, "decoder_kept": dec, "steps": steps,
           "loss_before": round(before, 5), "loss_after": round(after, 5),
           "total_s": round(time.perf_counter() - t0, 1)}
    (out / "prune_log.json").write_text(json.dumps(log, indent=1))
    logger.info("pruned %s to %s: loss %.4f -> %.4f; fine-tune with --init %s --arch %s",
                args.prune, target["widths"], before, after, out / "roadseg.pt", args.arch)
    return 0
