"""Segmentation benchmark: per-class IoU of the packaged ONNX model on held-out rendered frames
(Karlsruhe Lanelet2 and Argoverse 2 worlds, never trained on) and its speed on one core.

    python bench/bench_segmentation.py --out DIR [--quick]   -> DIR/segmentation.json

IoU per class = sum of intersections / sum of unions over all frames of a world, at the camera's
full resolution (labels resized back from the model's input size), and also inside the IPM ROI
(the pixels the mapper actually uses). Speed: p50/p95 ms of one forward pass + argmax at the
model's input size with one onnxruntime thread, and of the whole `segment()` call at full size."""

import argparse
import json
import logging
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common.camera import build_ipm_lookup  # noqa: E402
from common.classes import NAMES, Cls  # noqa: E402
from common.config import RoiConfig  # noqa: E402
from common.drivelog import DriveLog  # noqa: E402
from common.segmentation import DEFAULT_MODEL, get_segmenter  # noqa: E402

logger = logging.getLogger("bench.segmentation")

SHARED = REPO.parent / "shared" / "data"
TARGETS = {"lane_line": 0.80, "stop_line": 0.75, "crosswalk": 0.75, "ground_sign": 0.60}
CLASSES = (Cls.ROAD, Cls.LANE_LINE, Cls.STOP_LINE, Cls.CROSSWALK, Cls.GROUND_SIGN)


def heldout_worlds() -> list[tuple[str, str]]:
    """(name, load_world spec) of the benchmark worlds present in ../shared/data."""
    out = []
    osm = SHARED / "lanelet2-karlsruhe" / "mapping_example.osm"
    if osm.is_file():
        out.append(("karlsruhe", f"lanelet2:{osm}"))
    for log in sorted((SHARED / "av2").glob("*-*-*-*-*")):
        out.append((f"av2-{log.name[:8]}", f"av2:{log}"))
    return out


def render_heldout(spec: str, out_dir: Path, *, frames: int, seed: int):
    """Render a drive through a held-out world -> (`frames` evenly spaced (rgb, labels), camera)."""
    from services.sim.simulate import simulate_drives
    from services.sim.worlds import load_world

    world = load_world(spec, seed)
    logs = simulate_drives(world, out_dir, vehicles=1, drives=1, profile="production", seed=seed,
                           images=True, max_km=0.6)
    log = DriveLog(logs[0])
    idx = np.unique(np.linspace(0, len(log) - 1, frames).round().astype(int))
    pairs = [(log.image(i), log.labels(i)) for i in idx]
    return [(rgb, lab) for rgb, lab in pairs if rgb is not None and lab is not None], log.meta.camera


class IouAccumulator:
    def __init__(self):
        self.inter = {c: 0 for c in CLASSES}
        self.union = {c: 0 for c in CLASSES}
        self.true_px = {c: 0 for c in CLASSES}

    def add(self, pred, truth, mask=None):
        if mask is not None:
            pred, truth = pred[mask], truth[mask]
        for c in CLASSES:
            p, t = pred == c, truth == c
            self.inter[c] += int((p & t).sum())
            self.union[c] += int((p | t).sum())
            self.true_px[c] += int(t.sum())

    def result(self) -> dict:
        return {NAMES[c]: (round(self.inter[c] / self.union[c], 4) if self.true_px[c] else None)
                for c in CLASSES}


def evaluate_world(seg, spec: str, *, frames: int, seed: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="bench-seg-") as tmp:
        pairs, camera = render_heldout(spec, Path(tmp), frames=frames, seed=seed)
    roi = RoiConfig()
    ipm = build_ipm_lookup(camera, x_min_m=roi.x_min_m, length_m=roi.length_m, width_m=roi.width_m)
    roi_mask = np.zeros(camera.width * camera.height, bool)
    roi_mask[ipm.pixel_index] = True
    roi_mask = roi_mask.reshape(camera.height, camera.width)
    full, in_roi = IouAccumulator(), IouAccumulator()
    for rgb, truth in pairs:
        pred = seg.segment(rgb)
        full.add(pred, truth)
        in_roi.add(pred, truth, roi_mask)
    return {"frames": len(pairs), "iou": full.result(), "iou_roi": in_roi.result(),
            "true_pixels": {NAMES[c]: full.true_px[c] for c in CLASSES}}


def speed(seg, *, repeats: int, rng) -> dict:
    w, h = seg.input_size
    small = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    big = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    model_ms, full_ms = [], []
    for i in range(repeats + 5):
        t0 = time.perf_counter()
        seg.segment_model_size(small)
        t1 = time.perf_counter()
        seg.segment(big)
        t2 = time.perf_counter()
        if i >= 5:  # warm-up
            model_ms.append((t1 - t0) * 1e3)
            full_ms.append((t2 - t1) * 1e3)
    return {
        "input_size": list(seg.input_size), "threads": 1,
        "ms_p50": round(float(np.percentile(model_ms, 50)), 2),
        "ms_p95": round(float(np.percentile(model_ms, 95)), 2),
        "segment_640x360_ms_p50": round(float(np.percentile(full_ms, 50)), 2),
        "segment_640x360_ms_p95": round(float(np.percentile(full_ms, 95)), 2),
    }


def run(quick: bool = False) -> dict:
    import onnxruntime

    seg = get_segmenter("onnx", intra_op_threads=1)
    rng = np.random.default_rng(0)
    report = {
        "model": seg.name, "model_bytes": DEFAULT_MODEL.stat().st_size,
        "python": platform.python_version(), "onnxruntime": onnxruntime.__version__,
        "speed": speed(seg, repeats=30 if quick else 200, rng=rng),
        "targets": TARGETS, "worlds": {},
    }
    worlds = heldout_worlds()
    for name, spec in worlds[:2] if quick else worlds:
        logger.info("rendering and segmenting %s", name)
        report["worlds"][name] = evaluate_world(seg, spec, frames=8 if quick else 60, seed=1)
    report["iou"] = _mean_over_worlds(report["worlds"], "iou")
    report["iou_roi"] = _mean_over_worlds(report["worlds"], "iou_roi")
    report["ms_p50"], report["ms_p95"] = report["speed"]["ms_p50"], report["speed"]["ms_p95"]
    return report


def _mean_over_worlds(worlds: dict, key: str) -> dict:
    out = {}
    for c in CLASSES:
        vals = [w[key][NAMES[c]] for w in worlds.values() if w[key][NAMES[c]] is not None]
        out[NAMES[c]] = round(float(np.mean(vals)), 4) if vals else None
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    report = run(args.quick)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "segmentation.json").write_text(json.dumps(report, indent=2))
    sys.stdout.write(json.dumps({k: report[k] for k in ("iou", "iou_roi", "speed")}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
