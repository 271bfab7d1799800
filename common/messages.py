"""Wire messages (DESIGN.md: Wire format) as plain dataclasses; common.codec makes them bytes."""

from dataclasses import dataclass, field

import numpy as np

from common.classes import NUM_CLASSES


def patch_id(vehicle: str, traversal: str, tile, seq: int) -> str:
    """A vehicle's idempotency key of its seq-th seal's patch of a tile: the same drive
    re-mapped gives the same ids (and common.codec sends such an id in a SparseBatch as seq)."""
    return f"{vehicle}.{traversal}.{tile[0]}_{tile[1]}.{seq:06d}"


@dataclass(frozen=True)
class GridPatch:
    """Occupied cells of one vehicle's local grid inside one tile: the idempotent upload unit."""

    patch_id: str  # unique per vehicle and patch: the idempotency key
    vehicle: str
    tile: tuple[int, int]
    cells: np.ndarray  # uint32 [n], flat row * 512 + col, sorted, unique
    votes: np.ndarray  # uint16 [n, NUM_CLASSES] counts per class (uint8 off a packed wire form)
    t_first_ns: int
    t_last_ns: int
    traversal: str  # id of the drive
    # cells + votes exactly as they came on the wire (common.codec.pack_cells_votes), set by the
    # decoder only, so the shard's store writes them without packing again; not part of the
    # value (encode always packs cells + votes afresh)
    packed: bytes | None = field(default=None, compare=False, repr=False)
    # the SparsePatch payload these cells + votes were expanded from (common.sparse.expand),
    # set by the shard only, so its store keeps the patch as it came (and replays expand it)
    sparse: bytes | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class IngestBatch:
    patches: list[GridPatch]


@dataclass(frozen=True)
class SparsePatch:
    """A GridPatch in the "sparse/1" form (common/sparse.py): the traversal's footprint and
    paint as polygons, its frames as key poses and the paint cells' pixel shares, from which
    the shard derives the cells and votes (common.sparse.expand). Same idempotency key."""

    patch_id: str
    vehicle: str
    tile: tuple[int, int]
    t_first_ns: int
    t_last_ns: int
    traversal: str
    data: bytes  # the sparse/1 payload (common.sparse.pack), uncompressed
    form: str = "sparse/1"


@dataclass(frozen=True)
class SparseBatch:
    """Sparse patches uploaded together: compressed as one (common.codec), so what the patches
    of one seal share (vehicle, traversal, key poses) costs once."""

    patches: list[SparsePatch]


def batch_of(patches: list) -> "IngestBatch | SparseBatch":
    """The upload message for patches of one form: SparseBatch for SparsePatch, else
    IngestBatch."""
    if patches and all(isinstance(p, SparsePatch) for p in patches):
        return SparseBatch(list(patches))
    return IngestBatch(list(patches))


ACCEPTED = "accepted"
DUPLICATE = "duplicate"
# IngestAck.error of a batch a shard refused for its sender's rate (services/merger/throttle.py):
# nothing was applied; the vehicle retries it after a backoff
THROTTLED = "throttled"


@dataclass(frozen=True)
class IngestAck:
    results: dict[str, str] = field(default_factory=dict)  # patch_id -> accepted | duplicate
    error: str | None = None  # set when the whole batch was rejected; then nothing was applied


@dataclass(frozen=True)
class Tile:
    tile: tuple[int, int]
    version: int  # monotonic per tile
    codec: str  # name/version of the tile codec, e.g. "contour/2"
    data: bytes
    classes: list[int] = field(default_factory=lambda: list(range(NUM_CLASSES)))


@dataclass(frozen=True)
class Pose:
    vehicle: str
    t_ns: int
    x: float
    y: float
    yaw: float
    cov: np.ndarray  # float64 [3, 3] over (x, y, yaw)
    ok: bool  # integrity: False when the filter cannot trust itself


@dataclass(frozen=True)
class Stats:
    role: str
    ident: str
    counters: dict[str, float | int | str] = field(default_factory=dict)


MESSAGE_TYPES = (GridPatch, IngestBatch, SparsePatch, SparseBatch, IngestAck, Tile, Pose, Stats)
