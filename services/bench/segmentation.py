"""Segmentation benchmark: per-class IoU of the packaged ONNX model on held-out rendered frames
(Karlsruhe Lanelet2 and Argoverse 2 worlds, never trained on) and its speed on one core.

    python -m services.bench.segmentation --out DIR [--quick] [--frames N] [--model M.onnx]
        [--no-border-net] [--flip off|average|alternate] [--no-roi-rows]
        [--baseline B.onnx [--baseline-borders rule|none]]
        -> DIR/segmentation.json

Frames: the simulator's renderer at seeded random poses on the world's routes (30 % facing a stop
line, crosswalk or sign), default camera with 0.3 deg vibration, a new look every 10 frames;
as `stop_facing`, as many Karlsruhe frames that all face one of its stop lines (the route
frames show too few to measure the stop line: services/bench/heldout.py FacingPoses); and,
as `sign_facing`, a third as many frames per world, each facing a ground sign 4-20 m ahead.
None of these worlds has ground signs in its map, so arrows and road text are painted in their
lanes for those frames (evaluate.py with_ground_signs: the towns' glyph shapes, words no town
paints); the route frames stay as the maps draw them.
IoU per class = sum of intersections / sum of unions over all frames of a world, at the camera's
full resolution (labels resized back from the model's input size), and also inside the IPM ROI
(the pixels the mapper actually uses), each with a 90 % bootstrap interval over the frames
(`iou_ci90`; for the mean over worlds, each world's frames redrawn). The model runs as the
product runs it: the rows above rays rising the model's sky margin above level (metadata
`sky_margin_deg`, else 10 degrees; the nominal camera's `sky_rows`) are not segmented
(`--sky-margin-deg D` for every model; -1: every row), nor, as segmentation.roi_rows_only
does, the rows above the car's IPM ROI (`first_row`: the network reads 80 of them as
context, and the rows above the ROI less 5 are labelled none, since 2026-12-02; --no-roi-rows:
every row below the sky), so that the full-frame IoU counts those rows as none: compare
`iou_roi` across the two; and the mirror image is used as segmentation.flip says
("alternate", one pass a frame; --flip for another). Speed:
p50/p95 ms of `segment_model_size` (resize, network, upsampling, argmax, border refinement) at
the model's input size on one core (one onnxruntime thread, OpenCV and the border
classifier's BLAS held to one thread), and of the whole `segment()` call at full
size, on the held-out route frames themselves (up to TIMED_FRAMES per world, in turn), with
the p50 of its parts timed apart (`parts_ms_p50`: network, labels, borders): until
2026-11-25 it timed random noise, which has almost no paint borders to upsample and refine
and so read 12 ms where road frames take 14.5 ms. `paint_gate`: precision and recall in the
ROI of the model as the mapping vehicles run it (paint it is unsure of left unknown:
vehicle.paint_min_margin) against
the plain argmax, per world and their mean. With `--baseline`, a second model is scored on the
same frames, and `baseline.diff` (and each world's) is the model's IoU minus the baseline's,
with a paired bootstrap interval (`diff_ci90`: both scored on each draw of frames), to compare
two training recipes far more finely than their own intervals allow. That interval covers the
frames, not the training: two seeds of one recipe differed by 0.006 in mean lane line with a
paired interval of [-0.009, -0.003] (training/HISTORY.md), so compare recipes over seeds."""

import argparse
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from common.camera import build_ipm_lookup, camera_from_config
from common.classes import NAMES, Cls
from common.config import FLIP_MODES, CameraConfig, RoiConfig, SegmentationConfig, VehicleConfig
from common.segmentation import DEFAULT_MODEL, get_segmenter, roi_first_row
from services.bench.heldout import (
    CLASSES,
    IouAccumulator,
    bootstrap_interval,
    render_heldout,
)
from services.bench.runner import cpu_description
from services.sim.worlds import shared_data_dir

logger = logging.getLogger("bench.segmentation")

SHARED = shared_data_dir()  # $ROADMAP_SHARED_DATA, else ../shared/data
TARGETS = {"lane_line": 0.80, "stop_line": 0.75, "crosswalk": 0.75, "ground_sign": 0.60}
# Frames per world. The first 100 are the 100 this benchmark rendered until 2026-11-24 (the same
# seeded sequence). 100 were too few for the Karlsruhe world: its next 100 frames moved the
# packaged model's lane-line IoU from 0.484 to 0.573.
FRAMES = 300
DRAWS = 1000  # bootstrap resamples of each world's frames
TIMED_FRAMES = 50  # route frames per world kept for the speed measurement


def heldout_worlds() -> list[tuple[str, str]]:
    """(name, load_world spec) of the benchmark worlds present in ../shared/data."""
    out = []
    osm = SHARED / "lanelet2-karlsruhe" / "mapping_example.osm"
    if osm.is_file():
        out.append(("karlsruhe", f"lanelet2:{osm}"))
    for log in sorted(p for p in (SHARED / "av2").glob("*-*-*-*-*") if p.is_dir()):
        out.append((f"av2-{log.name[:8]}", f"av2:{log}"))
    return out


def evaluate_world(seg, spec: str, *, frames: int, seed: int, rng, facing: Cls | None = None,
                   baseline=None, paired_rng=None, gated=None,
                   keep: list | None = None) -> tuple[dict, list[dict], list[dict] | None]:
    """The world's report entry, DRAWS bootstrap results of its full-frame IoU, and with a
    `baseline` segmenter, DRAWS paired bootstrap results (drawn with `paired_rng`, so that the
    model's own draws do not depend on whether a baseline is given) of seg's IoU minus the
    baseline's. With `gated` (the model as the mapping vehicles run it: unsure paint left
    unknown), `paint_gate` holds the ROI precision and recall of both. The first TIMED_FRAMES
    images are appended to `keep` (for speed())."""
    pairs, camera = render_heldout(spec, frames=frames, seed=seed, facing=facing)
    if keep is not None:
        keep.extend(rgb for rgb, _ in pairs[:TIMED_FRAMES])
    roi = RoiConfig()
    ipm = build_ipm_lookup(camera, x_min_m=roi.x_min_m, length_m=roi.length_m, width_m=roi.width_m)
    roi_mask = np.zeros(camera.width * camera.height, bool)
    roi_mask[ipm.pixel_index] = True
    roi_mask = roi_mask.reshape(camera.height, camera.width)
    full, in_roi, base, gate = (IouAccumulator() for _ in range(4))
    for rgb, truth in pairs:
        pred = seg.segment(rgb)
        full.add(pred, truth)
        in_roi.add(pred, truth, roi_mask)
        if baseline is not None:
            base.add(baseline.segment(rgb), truth)
        if gated is not None:
            gate.add(gated.segment(rgb), truth, roi_mask)
    draws = full.draws(DRAWS, rng)
    entry = {"frames": len(pairs), "iou": full.result(), "iou_ci90": bootstrap_interval(draws),
             "iou_roi": in_roi.result(), "iou_roi_ci90": in_roi.interval(DRAWS),
             "true_pixels": {NAMES[c]: full.true_px[c] for c in CLASSES}}
    if gated is not None:
        entry["paint_gate"] = {"min_margin": gated.min_margin, "roi": gate.precision_recall(),
                               "roi_plain": in_roi.precision_recall()}
    if baseline is None:
        return entry, draws, None
    paired = full.draws(DRAWS, paired_rng, minus=base)
    entry["baseline"] = {"iou": base.result(), "diff": _diff(entry["iou"], base.result()),
                         "diff_ci90": bootstrap_interval(paired)}
    return entry, draws, paired


def speed(seg, frames: list, *, repeats: int) -> dict:
    """p50/p95 of `segment_model_size` (with its thread's CPU time) and of `segment()` over
    `repeats` calls on the rendered `frames` in turn, after 5 warm-up calls, on one core: the
    segmenter's onnxruntime session and border classifier run one thread each, and OpenCV is
    held to the calling thread while it is timed (until 2026-11-27 its resizes and flips, and
    numpy's BLAS pool under the border classifier, could spread onto a second core)."""
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _speed(seg, frames, repeats=repeats)
    finally:
        cv2.setNumThreads(opencv_threads)


def _speed(seg, frames: list, *, repeats: int) -> dict:
    w, h = seg.input_size
    model_ms, model_cpu_ms, full_ms = [], [], []
    parts = {"network": [], "labels": [], "borders": []}
    for i in range(repeats + 5):
        frame = frames[i % len(frames)]
        small = frame if frame.shape[:2] == (h, w) else cv2.resize(frame, (w, h))
        t0, c0 = time.perf_counter(), time.thread_time()
        seg.segment_model_size(small)
        t1, c1 = time.perf_counter(), time.thread_time()
        seg.segment(frame)
        t2 = time.perf_counter()
        if i >= 5:  # warm-up
            model_ms.append((t1 - t0) * 1e3)
            model_cpu_ms.append((c1 - c0) * 1e3)
            full_ms.append((t2 - t1) * 1e3)
            for name, ms in _parts_ms(seg, small).items():
                parts[name].append(ms)
    pct = lambda v, q: round(float(np.percentile(v, q)), 2)  # noqa: E731
    return {
        "input_size": list(seg.input_size), "threads": 1, "load_avg_1min": os.getloadavg()[0],
        "frames": "held-out route frames", "distinct_frames": len(frames),
        "sky_rows": seg.sky_rows, "opencv_threads": cv2.getNumThreads(),
        "border_net_blas_threads": seg.border_net.threads if seg.border_net else None,
        "ms_p50": pct(model_ms, 50), "ms_p95": pct(model_ms, 95),
        # CPU time of the (single) inference thread: robust to other processes on the machine
        "cpu_ms_p50": pct(model_cpu_ms, 50), "cpu_ms_p95": pct(model_cpu_ms, 95),
        "segment_640x360_ms_p50": pct(full_ms, 50), "segment_640x360_ms_p95": pct(full_ms, 95),
        # where segment_model_size's time goes, timed apart on the same frames: network_labels
        # (`labels`: the input, the network's passes, the upsampled argmax) then
        # refined_borders (`borders`: the border classifier or the brightness rule), and the
        # network's passes alone (`network`: both, and their average, with flip averaging)
        "parts_ms_p50": {name: pct(v, 50) for name, v in parts.items()},
    }


def _parts_ms(seg, small: np.ndarray) -> dict:
    """ms of the parts of one `segment_model_size(small)` call, each timed on its own."""
    x = seg.preprocess(small)
    t0 = time.perf_counter()
    seg.run_network(x)
    t1 = time.perf_counter()
    small, labels, score_at = seg.network_labels(small)
    t2 = time.perf_counter()
    seg.refined_borders(small, small, labels, score_at)
    t3 = time.perf_counter()
    return {"network": (t1 - t0) * 1e3, "labels": (t2 - t1) * 1e3, "borders": (t3 - t2) * 1e3}


def run(quick: bool = False, model_path: str | None = None, frames: int = FRAMES,
        baseline_path: str | None = None, baseline_borders: str = "model",
        sky_margin_deg: float | None = None, border_net: bool | None = None,
        flip: str | None = None, seed: int = 1,
        roi_rows: bool = SegmentationConfig.roi_rows_only) -> dict:
    """seed: the draw of held-out frames (poses, cars, vibration) in every world; 1 is the
    benchmark's, another a fresh draw that checks a result found on it. border_net: None, the
    model's learned border classifier if it has one (as the product runs it); False, its
    brightness rule. baseline_borders: how the baseline decides its paint
    borders: "model" (as the product), "rule" (its brightness rule) or "none". flip: None, as
    the model's metadata asks (as the product runs it), else one of FLIP_MODES."""
    if not heldout_worlds():  # a result of nulls would read as a measurement
        raise FileNotFoundError(
            f"no held-out worlds under {SHARED} (Lanelet2 Karlsruhe, Argoverse 2 logs): put the "
            "shared data at ../shared/data or set ROADMAP_SHARED_DATA")
    flip = flip or SegmentationConfig.flip or None  # as the product runs it
    seg, gated, baseline = _segmenters(model_path, baseline_path, baseline_borders,
                                       sky_margin_deg=sky_margin_deg, border_net=border_net,
                                       flip=flip, roi_rows=roi_rows)
    rng, paired_rng = np.random.default_rng(0), np.random.default_rng(1)
    report = _header(seg, model_path, seed)
    timed = []  # route frames for the speed measurement
    worlds = heldout_worlds()
    common = {"seed": seed, "rng": rng, "baseline": baseline, "paired_rng": paired_rng}
    draws, paired = {}, {}
    for name, spec in worlds[:2] if quick else worlds:
        logger.info("rendering and segmenting %s", name)
        report["worlds"][name], draws[name], paired[name] = evaluate_world(
            seg, spec, frames=10 if quick else frames, gated=gated, keep=timed, **common)
    report["iou"] = _mean_over_worlds(report["worlds"], "iou")
    report["paint_gate"] = {"min_margin": gated.min_margin,
                            **_paint_gate_means(report["worlds"])}
    report["iou_ci90"] = bootstrap_interval(_means_of_draws(draws))
    report["iou_roi"] = _mean_over_worlds(report["worlds"], "iou_roi")
    if worlds and worlds[0][0] == "karlsruhe":  # the only world with stop lines
        logger.info("rendering and segmenting karlsruhe frames facing stop lines")
        report["stop_facing"], _, _ = evaluate_world(
            seg, worlds[0][1], frames=10 if quick else frames, facing=Cls.STOP_LINE, **common)
        report["stop_facing"]["world"] = "karlsruhe"
    signs = _sign_facing(seg, worlds[:2] if quick else worlds,
                         frames=10 if quick else max(frames // 3, 10), **common)
    if signs:
        report["sign_facing"] = signs
    if baseline is not None:  # the model minus the baseline, on the same frames
        report["baseline"] = _baseline_section(report, baseline, baseline_path, paired)
    if timed:
        logger.info("timing on %d route frames", len(timed))
        report["speed"] = speed(seg, timed, repeats=30 if quick else 200)
        report["ms_p50"], report["ms_p95"] = report["speed"]["ms_p50"], report["speed"]["ms_p95"]
    return report


def _segmenters(model_path, baseline_path, baseline_borders: str, *, sky_margin_deg,
                border_net, flip, roi_rows: bool = SegmentationConfig.roi_rows_only):
    """The model as the product runs it, the same gated as the mapping vehicles run it (paint
    it is unsure of left unknown), and the baseline (None without baseline_path)."""
    # the rows the product leaves out for render_heldout's camera (None: each model's own),
    # and with roi_rows (segmentation.roi_rows_only, as the product) those above the car's
    # IPM ROI, the larger of the two roles' (cfg.roi: 3-15 m ahead)
    camera = camera_from_config(CameraConfig())
    roi = RoiConfig()
    first_row = (roi_first_row(camera, roi.x_min_m, roi.length_m, roi.width_m)
                 if roi_rows else 0)
    sky = {"camera": camera, "sky_margin_deg": sky_margin_deg, "first_row": first_row}
    seg = get_segmenter("onnx", model_path=model_path, intra_op_threads=1, **sky,
                        border_net=border_net, flip=flip)
    gated = get_segmenter("onnx", model_path=model_path, intra_op_threads=1, **sky,
                          min_margin=VehicleConfig().paint_min_margin, flip=flip)
    borders = {"model": {}, "rule": {"border_net": False},
               "none": {"border_net": False, "refine": {}}}[baseline_borders]
    baseline = (get_segmenter("onnx", model_path=baseline_path, intra_op_threads=1,
                              **sky, **borders)
                if baseline_path else None)
    return seg, gated, baseline


def _header(seg, model_path, seed: int) -> dict:
    """What was measured, and where: the model, its runtime settings, the machine."""
    import onnxruntime

    return {
        "model": seg.name, "model_bytes": Path(model_path or DEFAULT_MODEL).stat().st_size,
        "refine": seg.refine,  # paint borders re-decided on the image ({}: off)
        "border_net": seg.border_net is not None,  # by the learned classifier instead
        "flip": seg.flip,  # what the network does with the mirror image (FLIP_MODES)
        "sky_margin_deg": seg.sky_margin_deg, "sky_rows": seg.sky_rows,  # rows not segmented
        "first_row": seg.first_row,  # the ROI's first row (0: every row below the sky)
        "python": platform.python_version(), "onnxruntime": onnxruntime.__version__,
        **cpu_description(),  # the speed depends on the vector units as much as on the model
        "seed": seed, "targets": TARGETS, "worlds": {},
    }


def _sign_facing(seg, worlds, *, frames: int, **common) -> dict | None:
    """IoU on frames facing ground signs, which every world gets painted (none has any)."""
    signs, sign_draws = {}, {}
    for name, spec in worlds:
        logger.info("rendering and segmenting %s frames facing ground signs", name)
        signs[name], sign_draws[name], _ = evaluate_world(
            seg, spec, frames=frames, facing=Cls.GROUND_SIGN, **common)
    if not signs:
        return None
    return {"iou": _mean_over_worlds(signs, "iou"),
            "iou_ci90": bootstrap_interval(_means_of_draws(sign_draws)),
            "iou_roi": _mean_over_worlds(signs, "iou_roi"), "worlds": signs}


def _baseline_section(report: dict, baseline, baseline_path, paired: dict) -> dict:
    base_iou = _mean_over_worlds(
        {w: {"iou": e["baseline"]["iou"]} for w, e in report["worlds"].items()}, "iou")
    return {"model": str(baseline_path), "refine": baseline.refine,
            "sky_rows": baseline.sky_rows, "border_net": baseline.border_net is not None,
            "flip": baseline.flip, "iou": base_iou, "diff": _diff(report["iou"], base_iou),
            "diff_ci90": bootstrap_interval(_means_of_draws(paired))}


def _means_of_draws(draws: dict) -> list[dict]:
    """{world: [draw i: {class: value}]} -> [draw i: mean over worlds]."""
    return [_mean_over_worlds({w: {"iou": d[i]} for w, d in draws.items()}, "iou")
            for i in range(DRAWS)]


def _diff(a: dict, b: dict) -> dict:
    return {k: None if a[k] is None or b[k] is None else round(a[k] - b[k], 4) for k in a}


def _mean_over_worlds(worlds: dict, key: str) -> dict:
    return {NAMES[c]: _mean([w[key][NAMES[c]] for w in worlds.values()]) for c in CLASSES}


def _paint_gate_means(worlds: dict) -> dict:
    """{"roi", "roi_plain"}: per marking class, the mean precision and recall over the worlds
    whose truth has the class (as the IoU means)."""
    out = {}
    for key in ("roi", "roi_plain"):
        out[key] = {}
        for name in TARGETS:
            entries = [e["paint_gate"][key][name] for e in worlds.values()]
            entries = [pr for pr in entries if pr["recall"] is not None]
            out[key][name] = {m: _mean([pr[m] for pr in entries])
                              for m in ("precision", "recall")}
    return out


def _mean(vals: list) -> float | None:
    """Mean of the values that are not None, to 4 places; None if there are none."""
    vals = [v for v in vals if v is not None]
    return round(float(np.mean(vals)), 4) if vals else None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--model", default=None, help="ONNX file (default: the packaged model)")
    parser.add_argument("--frames", type=int, default=FRAMES, help="frames per world")
    parser.add_argument("--seed", type=int, default=1,
                        help="the draw of held-out frames (default 1, the benchmark's; another "
                             "seed: a fresh draw of the same worlds, to check a result chosen "
                             "on the first)")
    parser.add_argument("--baseline", default=None,
                        help="a second ONNX file scored on the same frames: the JSON gains the "
                             "model's IoU minus the baseline's with paired 90 %% intervals")
    parser.add_argument("--baseline-borders", choices=("model", "rule", "none"), default="model",
                        help="how the baseline decides its paint borders: as the product does "
                             "(model: its learned classifier if it has one), by its brightness "
                             "rule, or not at all (with --baseline the same file: what the "
                             "classifier or the rule buys)")
    parser.add_argument("--sky-margin-deg", type=float, default=None,
                        help="leave out the rows above rays rising this far above level, as the "
                             "product does (default: each model's own, as the product's "
                             "default segmentation.sky_margin_deg; -1: none)")
    parser.add_argument("--border-net", action=argparse.BooleanOptionalAction, default=None,
                        help="decide paint borders by the model's learned border classifier "
                             "(default: if it has one, as segmentation.border_net does); "
                             "--no-border-net: by its brightness rule")
    parser.add_argument("--flip", choices=FLIP_MODES, default=None,
                        help="what the network does with each image's mirror image: off, "
                             "average (a second pass, averaged) or alternate (one pass, on the "
                             "image and on its mirror in turn) (default: the model's own, as "
                             "segmentation.flip does)")
    parser.add_argument("--roi-rows", action=argparse.BooleanOptionalAction,
                        default=SegmentationConfig.roi_rows_only,
                        help="segment only the rows of the IPM ROI (3-15 m ahead) and 80 above, "
                             "as segmentation.roi_rows_only does (default); --no-roi-rows: every "
                             "row below the sky (full-frame IoU)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    if not heldout_worlds():  # a JSON of nulls would read as a result
        logger.error("no held-out worlds under %s (Lanelet2 Karlsruhe, Argoverse 2 logs): put "
                     "the shared data at ../shared/data beside the repository or set "
                     "ROADMAP_SHARED_DATA; nothing written", SHARED)
        return 2
    report = run(args.quick, args.model, args.frames, args.baseline, args.baseline_borders,
                 args.sky_margin_deg, args.border_net, args.flip, args.seed, args.roi_rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "segmentation.json").write_text(json.dumps(report, indent=2))
    shown = {k: report.get(k) for k in ("iou", "iou_roi", "speed")}
    shown["stop_facing"] = report.get("stop_facing", {}).get("iou")
    shown["sign_facing"] = report.get("sign_facing", {}).get("iou")
    if "baseline" in report:
        shown["minus_baseline"] = report["baseline"]["diff"]
        shown["minus_baseline_ci90"] = report["baseline"]["diff_ci90"]
    sys.stdout.write(json.dumps(shown, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
