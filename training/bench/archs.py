"""Benchmark of segmentation network sizes on this CPU: one network pass of each named
architecture (`roadmap train-seg --arch`, training/archs.py) and of any widths given,
exported as the product exports them (`export_onnx`: channels padded to a multiple of the
alignment block, concatenations split) and run as the product runs them (OnnxSegmenter's
onnxruntime session of one thread, the input height fixed at the default camera's rows below
the sky cut: the packaged model's own sky margin unless `--sky-margin-deg` is given). Writes
JSON. Which network to train for a speed target is a question about the machine it must run
on: the passes are timed alternated, round by round, so that the ratios between sizes,
measured in one run, are the figures to compare; absolute times move with the machine and its
load (the least of the passes is the quietest moment's).

The weights are random (a pass's arithmetic does not depend on them). onnxruntime's blocked
(NCHWc) convolutions work in blocks of 16 channels on AVX-512 and of 8 on AVX2, so
`--block 8` shows what 8-channel stages would save on an AVX2 machine (the product's exports
use 16). Needs the optional training extra (`pip install -e '.[train]'`).

    python -m services.bench.archs --out DIR [--archs m64,p16] [--widths 8,8,64,128:1,2,4]
        [--block 16] [--rounds 15] [--passes 8] [--sky-margin-deg D]
"""

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from common.camera import camera_from_config
from common.config import CameraConfig
from services.bench.runner import cpu_description
from training.archs import ARCHS

DEFAULT_ARCHS = ("p16", "s", "m64", "d192")


def parse_widths(text: str) -> dict:
    """'8,8,64,128:1,2,4' -> an arch spec {widths, depths, rows: False}; ValueError if the
    text is not four widths and three depths."""
    bad = ValueError(f"--widths {text!r}: expected four widths and three depths, "
                     "as 8,8,64,128:1,2,4")
    try:
        widths, depths = text.split(":")
        spec = {"widths": [int(v) for v in widths.split(",")],
                "depths": [int(v) for v in depths.split(",")], "rows": False}
    except ValueError:
        raise bad from None
    if len(spec["widths"]) != 4 or len(spec["depths"]) != 3:
        raise bad
    return spec


def export(spec: dict, path: Path, block: int) -> int:
    """An export of a randomly initialised RoadSegNet of `spec` to `path` -> its parameters."""
    import torch

    from common.classes import NUM_CLASSES
    from training.data import TRAIN_CLASSES
    from training.net import RoadSegNet, count_parameters
    from training.train import export_onnx

    torch.manual_seed(0)
    model = RoadSegNet(num_classes=TRAIN_CLASSES, **spec)
    model.export_classes = NUM_CLASSES  # the auxiliary class folded into none, as exported
    model.eval()
    with warnings.catch_warnings():  # torch.onnx's tracer warnings on the shape logic
        warnings.simplefilter("ignore")
        export_onnx(model, path, seed=0, block=block)
    return count_parameters(model)


def time_passes(segmenters: dict, *, rounds: int, passes: int) -> dict:
    """{name: ms of each pass}: `passes` network passes of each segmenter in turn per round."""
    w, h = next(iter(segmenters.values())).input_size
    frame = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    inputs = {name: seg.preprocess(frame) for name, seg in segmenters.items()}
    ms = {name: [] for name in segmenters}
    for name, seg in segmenters.items():  # warm-up
        seg.run_network(inputs[name])
    for _ in range(rounds):
        for name, seg in segmenters.items():
            for _ in range(passes):
                t0 = time.perf_counter()
                seg.run_network(inputs[name])
                ms[name].append((time.perf_counter() - t0) * 1e3)
    return ms


def run(archs: list[str], widths: list[str], *, block: int, rounds: int, passes: int,
        sky_margin_deg: float | None = None) -> dict:
    from common.segmentation import OnnxSegmenter

    specs = {name: ARCHS[name] for name in archs}
    specs.update({text: parse_widths(text) for text in widths})
    camera = camera_from_config(CameraConfig())
    if sky_margin_deg is None:  # the rows the packaged model runs on
        sky_margin_deg = OnnxSegmenter(camera=camera).sky_margin_deg
    entries, segmenters = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, spec in specs.items():
            path = Path(tmp) / f"{len(entries)}.onnx"
            params = export(spec, path, block)
            seg = OnnxSegmenter(path, camera=camera, sky_margin_deg=sky_margin_deg,
                                flip="off", border_net=False)
            entries[name] = {"spec": spec, "parameters": params,
                             "input_rows": seg.input_size[1] - seg.sky_rows}
            segmenters[name] = seg
        ms = time_passes(segmenters, rounds=rounds, passes=passes)
    for name, v in ms.items():
        entries[name].update({"ms_p50": round(float(np.median(v)), 2),
                              "ms_p95": round(float(np.percentile(v, 95)), 2),
                              "ms_min": round(float(np.min(v)), 2)})
    import onnxruntime

    return {"block": block, "rounds": rounds, "passes_per_round": passes, "threads": 1,
            "sky_margin_deg": sky_margin_deg,
            "load_avg_1min": os.getloadavg()[0], "python": platform.python_version(),
            "onnxruntime": onnxruntime.__version__, **cpu_description(), "archs": entries}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--archs", default=",".join(DEFAULT_ARCHS),
                    help=f"named sizes, comma-separated (of {', '.join(ARCHS)})")
    ap.add_argument("--widths", action="append", default=[],
                    help="another size: four widths and three depths, as 8,8,64,128:1,2,4")
    ap.add_argument("--block", type=int, default=16, choices=(8, 16),
                    help="channel alignment of the exports (the product's: 16)")
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--passes", type=int, default=8, help="passes of each size per round")
    ap.add_argument("--sky-margin-deg", type=float, default=None,
                    help="rows above rays rising this much are left out (default: the "
                         "packaged model's own margin; -1: every row)")
    args = ap.parse_args(argv)
    archs = [a for a in args.archs.split(",") if a]
    unknown = [a for a in archs if a not in ARCHS]
    if unknown:
        ap.error(f"unknown arch(s) {unknown}; known: {sorted(ARCHS)}")
    for text in args.widths:
        try:
            parse_widths(text)
        except ValueError as exc:
            ap.error(str(exc))
    report = run(archs, args.widths, block=args.block, rounds=args.rounds, passes=args.passes,
                 sky_margin_deg=args.sky_margin_deg)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "archs.json").write_text(json.dumps(report, indent=2))
    for name, e in report["archs"].items():
        sys.stdout.write(f"{name:22s} {e['parameters']:7d} params  pass p50 "
                         f"{e['ms_p50']:6.2f}  min {e['ms_min']:6.2f} ms\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
