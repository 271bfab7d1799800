"""Tile codec benchmark: map size per km of road and fidelity, side by side in one run:
raw sparse grid (uint32 cell + uint8 class per labelled cell), PNG of the label raster, zlib of the
raster (raw/1), and our contour codec (contour/2); plus compression/decompression time per tile.

    python -m services.bench.codec --out DIR [--quick] [--world SPEC]   -> DIR/codec.json

Maps: the world's ground-truth label raster (world = Karlsruhe Lanelet2 when ../shared/data exists,
else the procedural town; --quick: town:1), and a merged map built by MergerShard from three
simulated noisy traversals of it (paint edges jittered, sparse speckles), which is what the cloud
actually compresses. Fidelity: per-class precision/recall of the decoded map against the
uncompressed map at 0.1 m tolerance (common.evaluation, tol_cells=1). Single core, in-process."""

import argparse
import logging
import time

import cv2
import numpy as np

from common.classes import NUM_CLASSES
from common.contours import decode_tile, encode_raw, encode_tile
from common.evaluation import per_class_precision_recall
from common.grid import TILE_CELLS, TILE_M
from common.messages import GridPatch
from services.bench.runner import write_result
from services.merger.shard import MergerShard

logger = logging.getLogger("bench.codec")


def load_world(spec: str | None, quick: bool):
    try:
        from services.sim.worlds import load_world as sim_load_world

        return sim_load_world("town:1" if quick and spec is None else spec)
    except ImportError:  # no simulator yet: the merger's synthetic network
        from services.merger.synthetic import synthetic_world

        return synthetic_world(km=1.0)


def world_tiles(world) -> dict[tuple[int, int], np.ndarray]:
    """Ground-truth label rasters of every non-empty tile, on the global tile grid."""
    x0, y0, x1, y1 = world.bounds(margin_m=2.0)
    tx0, ty0 = int(np.floor(x0 / TILE_M)), int(np.floor(y0 / TILE_M))
    tx1, ty1 = int(np.floor(x1 / TILE_M)), int(np.floor(y1 / TILE_M))
    rows, cols = (ty1 - ty0 + 1) * TILE_CELLS, (tx1 - tx0 + 1) * TILE_CELLS
    raster = world.rasterize(tx0 * TILE_M, ty0 * TILE_M, rows, cols)
    tiles = {}
    for j in range(ty1 - ty0 + 1):
        for i in range(tx1 - tx0 + 1):
            t = raster[j * TILE_CELLS:(j + 1) * TILE_CELLS, i * TILE_CELLS:(i + 1) * TILE_CELLS]
            if t.any():
                tiles[(tx0 + i, ty0 + j)] = np.ascontiguousarray(t)
    return tiles


def noisy_observation(labels: np.ndarray, rng) -> np.ndarray:
    """One traversal's view: paint edges grow or shrink by a cell at random, rare speckles."""
    obs = labels.copy()
    paint = labels >= 2
    grown = cv2.dilate(labels * paint, np.ones((3, 3), np.uint8))
    grow = (grown >= 2) & ~paint & (labels == 1) & (rng.random(labels.shape) < 0.25)
    obs[grow] = grown[grow]
    edge = paint & ~cv2.erode(paint.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    obs[edge & (rng.random(labels.shape) < 0.25)] = 1
    speck = (labels == 1) & (rng.random(labels.shape) < 2e-4)
    obs[speck] = rng.integers(2, NUM_CLASSES, int(speck.sum()))
    return obs


def merged_tiles(tiles: dict, traversals: int = 3, seed: int = 0) -> dict:
    """Merge `traversals` noisy observations of every tile with MergerShard."""
    rng = np.random.default_rng(seed)
    shard = MergerShard()
    for tile, labels in tiles.items():
        for k in range(traversals):
            obs = noisy_observation(labels, rng).ravel()
            cells = np.flatnonzero(obs).astype(np.uint32)
            votes = np.zeros((len(cells), NUM_CLASSES), np.uint16)
            votes[np.arange(len(cells)), obs[cells]] = 5
            shard.apply_patch(GridPatch(f"{tile}/{k}", "bench", tile, cells, votes, k, k, f"d{k}"))
    shard.flush()
    return {t: shard.labels(t) for t in tiles}


def measure(tiles: dict, km: float) -> dict:
    sizes = {"sparse_grid": 0, "png": 0, "raw_zlib": 0, "contour": 0}
    enc_ms, dec_ms = [], []
    decoded = {}
    for tile, labels in tiles.items():
        t0 = time.perf_counter()
        data = encode_tile(labels)
        t1 = time.perf_counter()
        decoded[tile] = decode_tile(data)
        t2 = time.perf_counter()
        enc_ms.append((t1 - t0) * 1e3)
        dec_ms.append((t2 - t1) * 1e3)
        sizes["contour"] += len(data)
        sizes["sparse_grid"] += int(np.count_nonzero(labels)) * 5
        sizes["png"] += len(cv2.imencode(".png", labels, [cv2.IMWRITE_PNG_COMPRESSION, 9])[1])
        sizes["raw_zlib"] += len(encode_raw(labels))
    src = np.concatenate([tiles[t] for t in tiles], axis=1)
    dec = np.concatenate([decoded[t] for t in tiles], axis=1)
    exact = per_class_precision_recall(dec, src, tol_cells=0)
    fidelity = {
        name: {"precision": round(v["precision"], 4), "recall": round(v["recall"], 4),
               "cells": v["cells_true"],
               # cell for cell (no tolerance), and decoded / source cell count: a codec that
               # draws lines too wide passes the 0.1 m check but not these
               "exact_iou": round(_iou(exact[name]), 4),
               "area_ratio": round(exact[name]["cells_pred"] / max(v["cells_true"], 1), 3)}
        for name, v in per_class_precision_recall(dec, src, tol_cells=1).items()
    }
    return {
        "tiles": len(tiles),
        "kb_per_km": {k: round(v / 1024 / km, 2) for k, v in sizes.items()},
        "fidelity": fidelity,
        "min_precision_recall": round(min(min(v["precision"], v["recall"])
                                          for v in fidelity.values() if v["cells"]), 4),
        "compress_ms": _quantiles(enc_ms),
        "decompress_ms": _quantiles(dec_ms),
    }


def _iou(pr: dict) -> float:
    tp = pr["recall"] * pr["cells_true"]
    union = pr["cells_true"] + pr["cells_pred"] - tp
    return float(tp / union) if union else float("nan")


def _quantiles(ms: list[float]) -> dict:
    a = np.asarray(ms)
    return {"p50_ms": round(float(np.percentile(a, 50)), 2),
            "p95_ms": round(float(np.percentile(a, 95)), 2),
            "per_s": round(float(len(a) / (a.sum() / 1e3)), 1)}


def run(quick: bool = False, world_spec: str | None = None) -> dict:
    world = load_world(world_spec, quick)
    km = float(world.km_of_road)
    tiles = world_tiles(world)
    truth = measure(tiles, km)
    merged = measure(merged_tiles(tiles), km)
    return {
        "stages": {"tile_compress": merged["compress_ms"],
                   "tile_decompress": merged["decompress_ms"]},
        "codec": {
            "world": {"name": world.name, "km": round(km, 3)},
            "goal": {"kb_per_km_max": 10.0, "precision_recall_min": 0.97},
            "truth_map": truth,
            "merged_map_3_noisy_traversals": merged,
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--world", default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO)
    result = run(args.quick, args.world)
    write_result(args.out, "codec.json", result, result["codec"])


if __name__ == "__main__":
    main()
