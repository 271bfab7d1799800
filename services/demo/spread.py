"""The demo's fleet across every shard: the world's route that reaches regions (8 x 8 tiles,
common/grid.py) the fleet's shared route does not, for the extra vehicles (demo.spread_vehicles),
and the grid.shard_map that spreads the regions the mapping drives touch over the shards.

Without both, a world whose first 0.4 km fit one region (Karlsruhe: region (-4,-1), and rendezvous
hashing gives every region its routes touch to the same shard of two) sends every patch to one
shard and the others idle. The drives' true poses pick regions and weights (the simulator's
knowledge, as the chaos step's busiest shard); the services only read the resulting config."""

from collections import Counter
from pathlib import Path

import numpy as np

from common.drivelog import DriveLog
from common.grid import RegionId, region_of_tile, tile_of_point
from services.sim import paint

ROUTE_STEP_M = 2.0


def route_regions(route_xy: np.ndarray, max_km: float) -> set[RegionId]:
    """Regions the first max_km of a route polyline pass through."""
    points = paint.resample(np.asarray(route_xy, float), ROUTE_STEP_M)
    points = points[: max(1, int(max_km * 1000.0 / ROUTE_STEP_M))]
    return {region_of_tile(tile_of_point(x, y)) for x, y in points}


def spread_route(routes: list[np.ndarray], max_km: float) -> int | None:
    """Index of the route (after the first, which the fleet shares) whose first max_km reach the
    most regions the first route's do not; None when no route reaches another region."""
    if not routes:
        return None
    shared = route_regions(routes[0], max_km)
    new = {i: len(route_regions(r, max_km) - shared) for i, r in enumerate(routes) if i}
    best = max(new, key=lambda i: (new[i], -i), default=None)
    return best if best is not None and new[best] > 0 else None


def frames_per_region(logs: list[Path]) -> Counter:
    """Frames of the drives' true poses per region (the work each region brings its shard)."""
    counts: Counter = Counter()
    for log in logs:
        poses = DriveLog(log).streams["frame_pose_true"]
        for x, y, _ in poses[np.all(np.isfinite(poses), axis=1)]:
            counts[region_of_tile(tile_of_point(x, y))] += 1
    return counts


def spread_shard_map(weights: Counter, shards: int) -> dict[str, int]:
    """grid.shard_map ("rx,ry" -> shard) of the touched regions: heaviest first, each to the
    least loaded shard (ties: lowest index), so K touched regions reach K shards."""
    load = [0] * max(1, shards)
    out: dict[str, int] = {}
    for region, n in sorted(weights.items(), key=lambda item: (-item[1], item[0])):
        shard = min(range(len(load)), key=lambda k: (load[k], k))
        out[f"{region[0]},{region[1]}"] = shard
        load[shard] += n
    return out
