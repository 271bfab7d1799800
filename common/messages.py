"""Wire messages (DESIGN.md: Wire format) as plain dataclasses; common.codec makes them bytes."""

from dataclasses import dataclass, field

import numpy as np

from common.classes import NUM_CLASSES


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


@dataclass(frozen=True)
class IngestBatch:
    patches: list[GridPatch]


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


MESSAGE_TYPES = (GridPatch, IngestBatch, IngestAck, Tile, Pose, Stats)
