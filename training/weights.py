"""Model weights and run options shared by train-seg's training and pruning (training/train.py,
training/prune.py): saving and loading RoadSegNet weights, checking export files, class weights
and the frame cache options. torch is imported lazily by the callers' functions."""

from pathlib import Path

import numpy as np

from common.classes import Cls
from common.errors import ConfigError
from training import data as seg_data

THREADS = 2
NO_RENDER_BUDGET_S = 24 * 3600.0  # "render every frame asked for": no time budget


def frame_cache(args) -> dict:
    """training_set's cache options as --no-cache and --cache-dir give them."""
    return {"cache": not args.no_cache,
            "cache_dir": Path(args.cache_dir) if args.cache_dir else None}


def class_weights(labels: np.ndarray) -> np.ndarray:
    """Median-frequency balancing, softened by a power of 0.35 and clipped to [1, 6]: stronger
    weights buy recall of thin paint with false positives, which IoU punishes as much."""
    counts = np.bincount(labels.reshape(-1), minlength=seg_data.TRAIN_CLASSES) + 1.0
    freq = counts / counts.sum()
    w = (np.median(freq) / freq) ** 0.35
    return np.clip(w / w[Cls.ROAD], 1.0, 6.0)


def save_weights(model, frozen_norms: bool, path: Path) -> dict:
    """Write a model's weights as `--init` and `--export-only` read them (architecture, state
    on the CPU, whether its batch norms were kept frozen) -> that state."""
    import torch

    state = {k: v.cpu() for k, v in model.state_dict().items()}
    torch.save({"arch": model.arch, "state": state, "frozen_norms": frozen_norms}, path)
    return state


def _load_init(model, init: str) -> bool:
    """Weights from a trained model: roadseg.pt (same architecture; batch norms as trained,
    or kept frozen if that run kept them frozen) or an exported ONNX file (batch norms folded:
    kept frozen). -> whether norms must stay frozen.

    Unfreezing folded norms (running mean 0, variance 1) swaps the identity for each batch's
    statistics: continuing a fine-tune of the packaged export from its roadseg.pt did that,
    and the loss went from 0.12 to 0.51 in the first 100 steps."""
    import torch

    from training.net import load_onnx_weights, onnx_widths, widen

    if str(init).endswith(".onnx"):
        widths = onnx_widths(init)
        if widths == model.arch["widths"]:
            load_onnx_weights(model, init)
            return True
        other = exported_model_like(init, model)
        if all(a >= b for a, b in zip(widths, model.arch["widths"], strict=True)):
            _narrow_checked(other, model, init)  # e.g. an export's zero padding channels
        else:  # a narrower model's weights, new channels added (net.widen)
            widen(other, model)
        return True
    saved = torch.load(init, map_location="cpu")
    if saved["arch"] != model.arch:
        raise ValueError(f"{init}: architecture {saved['arch']}, the model is {model.arch}")
    state = saved["state"]
    head_w = model.head.weight.shape[0]
    if state["head.weight"].shape[0] < head_w:  # auxiliary classes start as copies of none
        extra = head_w - state["head.weight"].shape[0]
        for key in ("head.weight", "head.bias"):
            state[key] = torch.cat([state[key], state[key][:1].repeat_interleave(extra, 0)])
    model.load_state_dict(state)
    return bool(saved.get("frozen_norms", False))


def check_export_file(flag: str, path) -> None:
    """`flag`'s value must be an existing exported RoadSegNet (.onnx) file."""
    if not str(path).endswith(".onnx") or not Path(path).is_file():
        raise ConfigError(f"{flag} {path}: an exported RoadSegNet (.onnx) file")


def _narrow_checked(wide, model, init) -> None:
    """`model` takes the channels of `wide` (loaded from `init`) that it has (net.narrow),
    if the rest are never read: else a ConfigError names the architecture to train."""
    import torch

    from training.net import narrow

    narrow(wide, model)
    was_training = model.training
    wide.eval()
    model.eval()
    x = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        same = torch.allclose(wide(x), model(x), atol=1e-4)
    model.train(was_training)
    if not same:
        raise ConfigError(f"{init}: its widths {wide.arch['widths']} are wider than the "
                          f"model's {model.arch['widths']} and it uses the extra channels; "
                          "train an architecture as wide (--arch)")


def exported_model_like(path, model):
    """The RoadSegNet exported as `path`, at the file's own widths with `model`'s depths, rows,
    head and classes (training mode, as built): an --init of other widths before it is
    narrowed or widened into `model`."""
    from training.net import RoadSegNet, load_onnx_weights, onnx_widths

    s2 = model.subpixel ** 2
    other = RoadSegNet(widths=onnx_widths(path), num_classes=model.head.out_channels // s2,
                       depths=model.arch["depths"], rows=model.arch["rows"],
                       subpixel=model.subpixel)
    load_onnx_weights(other, path)
    return other
