"""Benchmark of a segmentation training step: seconds per step of `train_model`'s own loop
(crop, augmentation, forward, loss, backward, AdamW) in float32 and under bfloat16 autocast
(`roadmap train-seg --bf16`), for the two kinds of run in the recipe: a fine-tune of the
packaged model on whole 640x360 frames (its batch norms frozen) and a run from scratch on the
default 384x224 crops, both of the packaged model's architecture (its metadata `arch`).
Writes JSON; the bf16 / float32 ratios, measured in one run on the same machine, are the
figures to compare (absolute times move with the machine and its load).

Frames are random pixels and labels: a step's arithmetic does not depend on what they show.
Needs the optional training extra (`pip install -e '.[train]'`).

    python -m services.bench.train_step --out DIR [--steps 30] [--batch 8]
"""

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

from common.segmentation import DEFAULT_MODEL
from services.bench.runner import cpu_description

RUNS = {  # name -> (init, crop (H, W))
    "finetune_whole_frames": (str(DEFAULT_MODEL), (360, 640)),
    "scratch_384x224_crops": (None, (224, 384)),
}


def _frames(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    from training.data import TRAIN_CLASSES

    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 256, (n, 360, 640, 3), dtype=np.uint8)
    labels = rng.integers(0, TRAIN_CLASSES, (n, 360, 640), dtype=np.uint8)
    return frames, labels


def packaged_arch() -> str:
    """The train-seg --arch name of the packaged model's network (its metadata `arch`)."""
    from training.archs import ARCHS
    from training.train import _metadata

    arch = _metadata(DEFAULT_MODEL).get("arch")
    names = [name for name, spec in ARCHS.items() if spec == arch]
    if not names:
        raise SystemExit(f"bench_train_step: {DEFAULT_MODEL} names no known architecture "
                         f"(metadata arch {arch}; training/archs.py)")
    return names[0]


def time_steps(frames, labels, *, init, crop_hw, bf16: bool, steps: int, batch: int,
               arch: str) -> dict:
    """Two fresh train_model runs: s_per_step is a `steps`-step run's training time over its
    steps, its first step (allocation, oneDNN's kernel choice) included; first_step_s is a
    1-step run's time, to show how much of it that first step is."""
    from training.train import train_model

    def run(n):
        with tempfile.TemporaryDirectory() as out:
            _, _, _, log = train_model(frames, labels, Path(out), seed=0, train_s=0.0,
                                       steps=n, batch=batch, init=init, crop_hw=crop_hw,
                                       bf16=bf16, arch=arch)
        return log["train_s"]

    first = run(1)
    total = run(steps)
    return {"s_per_step": round(total / steps, 4), "first_step_s": round(first, 2),
            "steps": steps}


def run_all(steps: int, batch: int) -> dict:
    frames, labels = _frames(48)
    report = {"python": platform.python_version(), "cpu_count": os.cpu_count(),
              **cpu_description(),  # bfloat16 is native with avx512_bf16 or amx_tile only
              "batch": batch, "arch": packaged_arch(), "runs": {}}
    for name, (init, crop_hw) in RUNS.items():
        f32 = time_steps(frames, labels, init=init, crop_hw=crop_hw, bf16=False, steps=steps,
                         batch=batch, arch=report["arch"])
        b16 = time_steps(frames, labels, init=init, crop_hw=crop_hw, bf16=True, steps=steps,
                         batch=batch, arch=report["arch"])
        report["runs"][name] = {"float32": f32, "bf16": b16,
                                "bf16_over_float32": round(b16["s_per_step"]
                                                           / f32["s_per_step"], 3)}
    report["load_avg_1min"] = os.getloadavg()[0]
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="directory for train_step.json")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args(argv)
    try:
        import torch  # noqa: F401
    except ImportError:
        sys.stderr.write("bench_train_step: needs torch, the optional training extra: "
                         "pip install -e '.[train]'\n")
        return 2
    report = run_all(args.steps, args.batch)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "train_step.json").write_text(json.dumps(report, indent=2))
    sys.stdout.write(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
