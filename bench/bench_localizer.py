"""Localizer benchmark: per-frame latency of matching (ICP) and of the EKF, and tile decoding.

    python bench/bench_localizer.py --out DIR [--quick]   -> DIR/localizer.json

A seeded synthetic production drive along a two-lane road with stop lines, crosswalks and arrows
(tests/localizer/synthetic.py): the map is the ground-truth raster coded with common.contours
(contour/1) and decoded as the localizer does; the frame points come from the decoded map seen at
the true pose with noise and outliers (segmentation excluded). Timings on one core, in-process."""

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from common.config import LocalizerConfig  # noqa: E402
from common.contours import decode_tile, encode_tile  # noqa: E402
from services.localizer.localizer import get_localizer, replay  # noqa: E402
from services.localizer.map_cache import TileCache  # noqa: E402
from services.localizer.metrics import localization_metrics  # noqa: E402
from tests.localizer.synthetic import (  # noqa: E402
    frame_points, straight_road, synthetic_drive, world_tiles)

logger = logging.getLogger("bench.localizer")


class _Timed:
    """Proxy that records the wall time of one method of a component."""

    def __init__(self, target, method: str, sink: list):
        self._target, self._method, self._sink = target, method, sink

    def __getattr__(self, name):
        attr = getattr(self._target, name)
        if name != self._method:
            return attr

        def timed(*a, **kw):
            t0 = time.perf_counter()
            try:
                return attr(*a, **kw)
            finally:
                self._sink.append((time.perf_counter() - t0) * 1e3)

        return timed


def _stage(ms: list[float]) -> dict:
    a = np.asarray(ms, dtype=float)
    p50 = float(np.percentile(a, 50))
    return {"p50_ms": round(p50, 3), "p95_ms": round(float(np.percentile(a, 95)), 3),
            "per_s": round(1e3 / p50, 1) if p50 > 0 else None, "n": int(len(a))}


def run(quick: bool = False) -> dict:
    rng = np.random.default_rng(0)
    world = straight_road()
    cache = TileCache(capacity=30)
    decode_ms, sizes = [], []
    for tile, labels in world_tiles(world).items():
        data = encode_tile(labels)
        t0 = time.perf_counter()
        decoded = decode_tile(data)
        decode_ms.append((time.perf_counter() - t0) * 1e3)
        sizes.append(len(data))
        cache.put(tile, 1, decoded)
    fields_ms = []
    for tile in cache.tiles():
        t0 = time.perf_counter()
        cache.fields(tile)
        fields_ms.append((time.perf_counter() - t0) * 1e3)
    streams = synthetic_drive(rng, duration_s=8.0 if quick else 20.0)
    frames = [frame_points(cache, p, rng) for p in streams["frame_pose_true"]]
    loc = get_localizer(LocalizerConfig(), cache)
    match_ms, update_ms, predict_ms, frame_ms = [], [], [], []
    loc.icp = _Timed(loc.icp, "register", match_ms)
    ekf = loc.ekf
    loc.ekf = _Timed(_Timed(ekf, "update_pose", update_ms), "predict", predict_ms)
    t_frame = {}

    def points(i):
        t_frame["t"] = time.perf_counter()
        return frames[i]

    def done(i, est):
        frame_ms.append((time.perf_counter() - t_frame["t"]) * 1e3)

    est = replay(loc, streams, points, done)
    tracking = [ms for ms, e in zip(frame_ms, est) if e.diag.get("state") == "tracking"]
    m = localization_metrics(streams["frame_t_ns"], np.array([e.pose for e in est]),
                             streams["frame_pose_true"])
    # EKF per frame = its updates + the predictions between two frames
    predicts_per_frame = max(len(predict_ms) // max(len(frame_ms), 1), 1)
    ekf_frame = np.asarray(update_ms) + np.median(predict_ms) * predicts_per_frame
    return {
        "stages": {
            "localizer_match": _stage(match_ms[-len(tracking):] if tracking else match_ms),
            "localizer_ekf": _stage(ekf_frame),
            "localizer_frame": _stage(tracking),
            "tile_decode": _stage(decode_ms),
        },
        "localizer": {
            "tile_fields_ms": _stage(fields_ms),
            "ekf_predict": _stage(predict_ms),
            "ekf_update": _stage(update_ms),
            "tile_kb_mean": round(float(np.mean(sizes)) / 1024, 2),
            "frames": len(frame_ms),
            "points_per_frame": LocalizerConfig().max_points,
            "synthetic_accuracy": {k: m[k] for k in ("x_m", "y_m", "yaw_deg", "availability_0_5m",
                                                     "convergence_s")},
            "note": "synthetic straight road, ground-truth map coded contour/1; one core; "
                    "segmentation excluded",
        },
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="out")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO)
    result = {"cores_used": 1, "cpu_count": os.cpu_count(), **run(args.quick)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "localizer.json").write_text(json.dumps(result, indent=1))
    sys.stdout.write(json.dumps(result["stages"], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
