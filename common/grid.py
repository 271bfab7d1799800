"""Grid, tile and region math (DESIGN.md: Grid) and the owner-shard function.

World metres (ENU) -> 0.1 m cells -> tiles of 512 x 512 cells (51.2 m) -> regions of 8 x 8 tiles.
Inside a tile, cell (row, col) has row along +y (north) and col along +x (east); the flat index
on the wire is row * 512 + col. A region is the unit of sharding; its owner is chosen by
rendezvous hashing with zlib.crc32, so every process computes the same owner with no broker."""

import zlib
from collections.abc import Mapping

import numpy as np

from common.errors import TileError

CELL_M = 0.1
TILE_CELLS = 512
TILE_M = CELL_M * TILE_CELLS  # 51.2 m
REGION_TILES = 8
CELLS_PER_TILE = TILE_CELLS * TILE_CELLS

TileId = tuple[int, int]
RegionId = tuple[int, int]


def global_cells(points_xy_m: np.ndarray) -> np.ndarray:
    """World points (N, 2) in metres -> global integer cells (N, 2) as (gx, gy) = floor(x / 0.1)."""
    return np.floor(np.asarray(points_xy_m, dtype=np.float64) / CELL_M).astype(np.int64)


def tile_of_point(x_m: float, y_m: float) -> TileId:
    return (int(np.floor(x_m / TILE_M)), int(np.floor(y_m / TILE_M)))


def split_global_cells(gxy: np.ndarray):
    """Global cells (N, 2) -> (tiles (N, 2) int64, flat index in tile (N,) int64)."""
    tiles = np.floor_divide(gxy, TILE_CELLS)
    local = gxy - tiles * TILE_CELLS
    flat = local[:, 1] * TILE_CELLS + local[:, 0]
    return tiles, flat


def tile_origin_m(tile: TileId) -> tuple[float, float]:
    """South-west corner of a tile in world metres."""
    return tile[0] * TILE_M, tile[1] * TILE_M


def flat_to_rowcol(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    flat = np.asarray(flat)
    return flat // TILE_CELLS, flat % TILE_CELLS


def cell_centers_m(tile: TileId, flat: np.ndarray) -> np.ndarray:
    """Flat cell indices in a tile -> world coordinates (N, 2) of the cell centres."""
    rows, cols = flat_to_rowcol(flat)
    x0, y0 = tile_origin_m(tile)
    return np.stack([x0 + (cols + 0.5) * CELL_M, y0 + (rows + 0.5) * CELL_M], axis=1)


def check_flat_cells(flat: np.ndarray) -> None:
    if flat.size and (flat.min() < 0 or flat.max() >= CELLS_PER_TILE):
        raise TileError(f"cell index out of range [0, {CELLS_PER_TILE})")


def region_of_tile(tile: TileId) -> RegionId:
    return (tile[0] // REGION_TILES, tile[1] // REGION_TILES)


def tiles_of_region(region: RegionId) -> list[TileId]:
    rx, ry = region
    return [
        (rx * REGION_TILES + i, ry * REGION_TILES + j)
        for j in range(REGION_TILES)
        for i in range(REGION_TILES)
    ]


def _weight(region: RegionId, shard: int) -> int:
    return zlib.crc32(f"{region[0]}/{region[1]}/{shard}".encode())


def owner_shard(
    region: RegionId, shards: int, shard_map: Mapping[str, int] | None = None
) -> int:
    """Owner of a region: a shard-map entry "rx,ry" if configured, else rendezvous hashing.

    Rendezvous (highest random weight) hashing moves only 1/N of the regions when an N-th shard
    is added, so a fleet scales out by adding shards."""
    if shards < 1:
        raise TileError(f"shard count must be >= 1, got {shards}")
    if shard_map:
        key = f"{region[0]},{region[1]}"
        if key in shard_map:
            return int(shard_map[key])
    return max(range(shards), key=lambda s: _weight(region, s))


def owner_among(region: RegionId, members: list[str]) -> str | None:
    """The member (worker name) that rendezvous hashing picks for a region among the live ones:
    the PostgreSQL workers' region assignment (services/merger/worker.py). When a member joins,
    only the regions it now wins move; when one leaves, only its regions move.

    Weights: zlib.crc32 of the region and of the member, mixed by the splitmix64 finalizer. A
    bare crc32 of "region/member" would not do: crc32 is affine, so for two names of equal
    length the order of their weights barely depends on the region (every region would go to
    the same one of "w0" and "w1")."""
    if not members:
        return None
    key = zlib.crc32(f"{region[0]}/{region[1]}".encode()) << 32
    return max(sorted(members), key=lambda m: _mix64(key | zlib.crc32(m.encode())))


def _mix64(x: int) -> int:
    """splitmix64's finalizer: a bijective, well-mixing map of 64-bit integers."""
    mask = (1 << 64) - 1
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & mask
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & mask
    return x ^ (x >> 31)


def owner_of_tile(tile: TileId, shards: int, shard_map: Mapping[str, int] | None = None) -> int:
    return owner_shard(region_of_tile(tile), shards, shard_map)


def tiles_around(x_m: float, y_m: float, radius_m: float) -> list[TileId]:
    """Tiles intersecting the square of half-size radius_m about a point."""
    tx0, ty0 = tile_of_point(x_m - radius_m, y_m - radius_m)
    tx1, ty1 = tile_of_point(x_m + radius_m, y_m + radius_m)
    return [(tx, ty) for tx in range(tx0, tx1 + 1) for ty in range(ty0, ty1 + 1)]
