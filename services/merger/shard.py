"""The merger's pure core: grid patches in -> per-tile label maps and compressed tiles out.

MergerShard applies each patch once (dedupe by patch id), keeps every tile's votes per traversal,
and recomputes the labels of changed (dirty) tiles with the evidence rule below, vectorised with
numpy. TileCodecCache keeps each tile's compressed form and a version that grows when it changes.
No I/O, no clocks: the node decides when to flush (debounce) and what to persist.

Evidence rule (DESIGN.md: Map updating), per cell:
  1. Each traversal (drive) that OBSERVED the cell casts ONE ballot. Where it has votes, the
     ballot is the class with the most of its votes there (ties go to the higher class: paint
     over road); patches of one traversal are summed first, so a car that idles or passes twice
     still votes once. Vehicles send votes only for labelled pixels (road and paint), not for
     ground they saw as nothing (class 0: islands, verges, hatched areas), so the shard
     reconstructs a traversal's footprint: its voted cells in the tile, closed (dilate, then
     erode) with a square of merger.footprint_cells (9: 0.9 m). A cell inside that footprint
     without votes of the traversal lay between cells it saw, so it was in view but showed no
     paint: it casts a "no paint" ballot (UNSEEN_PAINT, no votes behind it). Without it,
     paint removed from ground that is now nothing would never get a ballot against it and
     stay in the map.
  2. Only the ballots of the merger.window_traversals (3) most recent traversals that
     observed the cell count. Traversals are ordered by their own time in the tile (the
     earliest t_first_ns of their patches there), ties by traversal id: never by arrival.
  3. The label: paint (its class with the most ballots in the window; ties go to the class
     whose ballots carry more votes, then to the lower class) wins when it has more ballots than
     the ground ballots (road, none and no-paint together; ties to more votes, then to the
     ground). Pooling means that road, none and no-paint ballots, all "no paint here", never
     split the vote against old paint. Otherwise the cell is road or none, whichever has more
     voted ballots (ties to more votes: road); no-paint ballots take no side there, as a gap
     in a traversal's votes (a car in front, sparse far pixels) is no evidence against road.
     A label needs its ballots to carry at least merger.min_votes (2) votes, else the cell is
     unknown (0).
  4. A ground-sign blob too small to be a sign (fewer than merger.min_sign_cells (30) cells,
     parts up to BLOB_GAP_CELLS (0.3 m) apart joined; a painted arrow covers 100-150) is decided
     again by rule 3 with its sign ballots left out: the lane line a model half mistook for a
     sign, else unknown. A blob that touches the tile's edge is kept, as it may be part of a
     sign in the next tile: the rule stays a function of the tile's own ballots. The same for
     a stop-line blob of fewer than merger.min_stop_cells cells (a stop line spans a lane:
     90-150 cells). This departs from DESIGN.md's "the class with the most evidence"
     (docs/ARCHITECTURE.md).
Consequences: after any number (50) of traversals of the old paint, new paint (or its removal:
road, other paint or nothing) wins as soon as 2 of the last 3 traversals that saw the cell saw
it: the map follows within 2 traversals that pass the cell, within 3 when one of them misses
it. Road that becomes nothing follows once no road ballot is left in the window (3 traversals;
2 where vehicles send class-0 votes for what they see as nothing). One noisy traversal is 1
ballot against the 2 before it and never flips a cell they agree on (two noisy traversals in a
row can: the price of following in 2). A map of one traversal is the paper's plain vote argmax
(of two, ties go to the votes behind each ballot). Everything is integer arithmetic and a
deterministic morphology over the set of applied patches, so the map (and its digest) is
independent of arrival order, crashes and replays.

Retirement (bounded memory): a traversal none of whose observed cells is in its window any more
(every one has `window` newer observations) can never count again, since later traversals only
add observations. At a flush such a traversal is dropped from memory (its patches stay in the
store, its patch ids in the dedupe set) once it is also merger.retire_after_s (< 0: never)
older than the tile's window-th newest traversal: that margin keeps the rule exact in
practice, as a late patch could still make a traversal newer (lower its t_first_ns) or add to a
retired one. Such a late patch of a retired traversal starts it afresh from its new pieces
(counted as "revived"). So a tile's memory is that of the traversals still in some cell's
window, not of every traversal ever.
"""

import hashlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from common.classes import NUM_CLASSES, Cls
from common.config import MergerConfig
from common.contours import CODEC, encode_tile
from common.errors import ConfigError, TileError
from common.grid import CELLS_PER_TILE, TILE_CELLS
from common.messages import ACCEPTED, DUPLICATE, GridPatch

VOTE_CAP = 1 << 24  # per traversal and cell: window sums (window < 256) stay below 2^32
BALLOT = np.uint64(1 << 32)
UNSEEN_PAINT = NUM_CLASSES  # ballot slot of "in the footprint, no votes": no paint seen here
SLOTS = NUM_CLASSES + 1

TileId = tuple[int, int]


@dataclass
class _Traversal:
    """One traversal's votes in one tile: pieces as they arrive, reduced lazily to ballots."""

    t_first_ns: int
    pieces: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)
    _ballots: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    _footprint_cells: int = 0

    def add(self, cells: np.ndarray, votes: np.ndarray, t_first_ns: int) -> None:
        self.pieces.append((cells, votes))
        self.t_first_ns = min(self.t_first_ns, t_first_ns)
        self._ballots = None

    def ballots(self, footprint_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(cells, ballot slot, votes behind the ballot) per observed cell, cells unique: the
        voted cells (slot = class), then the unvoted cells of the footprint (UNSEEN_PAINT, 0)."""
        if self._ballots is None or self._footprint_cells != footprint_cells:
            cells, votes = self._rows()
            ballot, weight = _ballot(votes[:, c] for c in range(NUM_CLASSES))
            seen = weight > 0  # an all-zero row is no observation
            cells, ballot, weight = cells[seen], ballot[seen], weight[seen]
            none = _unvoted_footprint(cells, footprint_cells)
            self._ballots = (
                np.concatenate([cells, none]),
                np.concatenate([ballot, np.full(len(none), UNSEEN_PAINT, np.uint8)]),
                np.concatenate([weight, np.zeros(len(none), np.uint32)]),
            )
            self._footprint_cells = footprint_cells
        return self._ballots

    def _rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(cells, votes) with each cell once: the pieces concatenated where they share no cell
        (no sum needed), else summed per cell."""
        if len(self.pieces) > 1:
            hit = np.zeros(CELLS_PER_TILE, dtype=bool)
            for cells, _ in self.pieces:
                hit[cells] = True
            if np.count_nonzero(hit) == sum(len(cells) for cells, _ in self.pieces):
                self.pieces = [(np.concatenate([cells for cells, _ in self.pieces]),
                                np.concatenate([votes for _, votes in self.pieces]))]
            else:
                self._summed(np.flatnonzero(hit))
        return self.pieces[0]

    def _summed(self, unique: np.ndarray) -> None:
        """Replace the pieces by their sum per cell (`unique`: every cell of the pieces): a
        lookup table to compact rows, then one row-add per piece (a patch's cells are unique,
        so no scatter conflicts)."""
        lut = np.empty(CELLS_PER_TILE, dtype=np.int32)
        lut[unique] = np.arange(len(unique), dtype=np.int32)
        sums = np.zeros((len(unique), NUM_CLASSES), dtype=np.uint32)
        for cells, votes in self.pieces:
            sums[lut[cells]] += votes
        self.pieces = [(unique.astype(np.uint32), sums)]


def _unvoted_footprint(cells: np.ndarray, size: int) -> np.ndarray:
    """Cells (uint32, sorted) inside the closing of the voted `cells` by a size x size square
    that have no votes: in view of the traversal but seen as nothing. The tile's edge rows and
    columns are taken to go on beyond it (replicated border), so a gap that crosses the tile's
    edge is closed up to the edge, the same as in its middle."""
    if size <= 1 or not len(cells):
        return np.zeros(0, np.uint32)
    voted = np.zeros(CELLS_PER_TILE, np.uint8)
    voted[cells] = 1
    closed = cv2.morphologyEx(voted.reshape(TILE_CELLS, TILE_CELLS), cv2.MORPH_CLOSE,
                              np.ones((size, size), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return np.flatnonzero(closed.reshape(-1) > voted).astype(np.uint32)


def _ballot(columns) -> tuple[np.ndarray, np.ndarray]:
    """Per row: the class with the most votes (ties to the higher class: paint over road) and
    its votes, from the per-class vote columns in class order (1-D passes, no 2-D argmax)."""
    best = ballot = None
    for c, col in enumerate(columns):
        col = col.astype(np.uint32)
        if best is None:
            best, ballot = col, np.zeros(len(col), dtype=np.uint8)
            continue
        better = col >= best
        best = np.where(better, col, best)
        ballot[better] = c
    return ballot, np.minimum(best, VOTE_CAP)


@dataclass
class _TileState:
    traversals: dict[str, _Traversal] = field(default_factory=dict)
    retired: set[str] = field(default_factory=set)  # ids of traversals dropped from memory
    labels: np.ndarray = field(default_factory=lambda: np.zeros((TILE_CELLS, TILE_CELLS), np.uint8))
    dirty: bool = False


class MergerShard:
    """Exactly-once vote merging for the tiles this shard owns (see the module docstring)."""

    @classmethod
    def from_config(cls, merger_cfg, owns: Callable[[TileId], bool]) -> "MergerShard":
        return cls(
            owns=owns,
            window_traversals=merger_cfg.window_traversals,
            min_votes=merger_cfg.min_votes,
            footprint_cells=merger_cfg.footprint_cells,
            min_sign_cells=merger_cfg.min_sign_cells,
            min_stop_cells=merger_cfg.min_stop_cells,
            retire_after_s=merger_cfg.retire_after_s,
            max_batch_patches=merger_cfg.max_batch_patches,
            max_batch_cells=merger_cfg.max_batch_cells,
        )

    def __init__(
        self,
        *,
        owns: Callable[[TileId], bool] = lambda tile: True,
        window_traversals: int = MergerConfig.window_traversals,
        min_votes: int = MergerConfig.min_votes,
        footprint_cells: int = MergerConfig.footprint_cells,
        min_sign_cells: int = MergerConfig.min_sign_cells,
        min_stop_cells: int = MergerConfig.min_stop_cells,
        retire_after_s: float = MergerConfig.retire_after_s,
        max_batch_patches: int = MergerConfig.max_batch_patches,
        max_batch_cells: int = MergerConfig.max_batch_cells,
    ):
        self.owns = owns
        if not 1 <= window_traversals < 256 or min_votes < 1 or not 1 <= footprint_cells <= 63:
            raise ConfigError("merger.window_traversals must be in [1, 256), min_votes >= 1, "
                              "footprint_cells in [1, 63]")
        self.window = int(window_traversals)
        self.min_votes = int(min_votes)
        self.footprint_cells = int(footprint_cells)
        self.min_sign_cells = int(min_sign_cells)
        self.min_stop_cells = int(min_stop_cells)
        self.retire_after_ns = None if retire_after_s < 0 else int(retire_after_s * 1e9)
        self.max_batch_patches = int(max_batch_patches)
        self.max_batch_cells = int(max_batch_cells)
        self.seen: set[str] = set()
        self.tiles_state: dict[TileId, _TileState] = {}
        self.counters = {"patches_applied": 0, "duplicates": 0, "cell_votes": 0,
                         "traversals_retired": 0, "traversals_revived": 0}

    # -- ingest ----------------------------------------------------------------------------------

    def check_batch(self, patches: list[GridPatch]) -> list[GridPatch]:
        """Validate a batch without touching state; return the patches that are new here (first
        occurrence of each unseen id). Raises TileError for anything the shard must refuse."""
        if len(patches) > self.max_batch_patches:
            raise TileError(f"batch of {len(patches)} patches exceeds {self.max_batch_patches}")
        n_cells = sum(len(p.cells) for p in patches)
        if n_cells > self.max_batch_cells:
            raise TileError(f"batch of {n_cells} cells exceeds {self.max_batch_cells}")
        new, ids = [], set()
        for p in patches:
            _check_patch(p)
            if not self.owns(tuple(p.tile)):
                raise TileError(f"tile {tuple(p.tile)} is not owned by this shard")
            if p.patch_id not in self.seen and p.patch_id not in ids:
                ids.add(p.patch_id)
                new.append(p)
        return new

    def apply_batch(self, patches: list[GridPatch]) -> dict[str, str]:
        """Check then apply a whole batch: patch id -> accepted | duplicate. All or nothing."""
        self.check_batch(patches)
        return self.apply_checked(patches)

    def apply_checked(self, patches: list[GridPatch]) -> dict[str, str]:
        """Apply a batch that check_batch accepted (with no state change in between): patch id
        -> accepted | duplicate (seen before, or earlier in this batch)."""
        results = {}
        for p in patches:
            if p.patch_id not in self.seen:
                self._add(p)
                results[p.patch_id] = ACCEPTED
            else:
                self.counters["duplicates"] += 1
                results.setdefault(p.patch_id, DUPLICATE)
        return results

    def apply_patch(self, patch: GridPatch) -> str:
        return self.apply_batch([patch])[patch.patch_id]

    def _add(self, p: GridPatch) -> None:
        state = self.tiles_state.setdefault(tuple(p.tile), _TileState())
        trav = state.traversals.get(p.traversal)
        if trav is None and p.traversal in state.retired:
            state.retired.discard(p.traversal)
            self.counters["traversals_revived"] += 1  # a late patch (module docstring)
        if trav is None:
            trav = state.traversals[p.traversal] = _Traversal(t_first_ns=p.t_first_ns)
        trav.add(np.asarray(p.cells, dtype=np.uint32), np.asarray(p.votes), p.t_first_ns)
        state.dirty = True
        self.seen.add(p.patch_id)
        self.counters["patches_applied"] += 1
        self.counters["cell_votes"] += int(len(p.cells))

    # -- labels ----------------------------------------------------------------------------------

    def dirty_tiles(self) -> list[TileId]:
        return sorted(t for t, s in self.tiles_state.items() if s.dirty)

    def flush(self, tiles: Iterable[TileId] | None = None, *, keep_dirty: bool = False
              ) -> list[TileId]:
        """Recompute the labels of dirty tiles (all, or those given); returns those recomputed.
        keep_dirty: leave them dirty (a recovery retiring old traversals as it replays, whose
        caller still has to encode every replayed tile)."""
        done = []
        for t in self.dirty_tiles() if tiles is None else tiles:
            state = self.tiles_state.get(t)
            if state is None or not state.dirty:
                continue
            idle: list[str] = []
            state.labels = tile_labels(
                list(state.traversals.items()), window=self.window, min_votes=self.min_votes,
                footprint_cells=self.footprint_cells, idle=idle,
                min_sign_cells=self.min_sign_cells, min_stop_cells=self.min_stop_cells,
            )
            self._retire(state, idle)
            state.dirty = keep_dirty
            done.append(t)
        return done

    def _retire(self, state: _TileState, idle: list[str]) -> None:
        """Drop the idle traversals (no cell took an observation from them) that are also the
        retirement margin older than the tile's window-th newest traversal."""
        if self.retire_after_ns is None or not idle:
            return
        firsts = sorted((t.t_first_ns for t in state.traversals.values()), reverse=True)
        horizon = firsts[self.window - 1] - self.retire_after_ns
        for tid in idle:
            if state.traversals[tid].t_first_ns < horizon:
                del state.traversals[tid]
                state.retired.add(tid)
                self.counters["traversals_retired"] += 1

    def traversals_held(self) -> int:
        """Traversal-in-tile records held in memory (what retirement bounds)."""
        return sum(len(s.traversals) for s in self.tiles_state.values())

    def labels(self, tile: TileId) -> np.ndarray:
        """The merged (512, 512) label raster of a tile as of the last flush."""
        state = self.tiles_state.get(tuple(tile))
        if state is None:
            raise TileError(f"no data for tile {tuple(tile)}")
        return state.labels

    def tiles(self) -> list[TileId]:
        return sorted(self.tiles_state)

    def digest(self) -> str:
        """sha256 over the tiles (sorted) and their label rasters, as of the last flush."""
        h = hashlib.sha256()
        for t in self.tiles():
            h.update(np.asarray(t, dtype="<i8").tobytes())
            h.update(self.tiles_state[t].labels.tobytes())
        return h.hexdigest()

    def stats(self) -> dict:
        tiles = self.tiles()
        return {
            **self.counters,
            "tiles": len(tiles),
            "traversals_held": self.traversals_held(),
            "cells": int(sum(int(np.count_nonzero(self.tiles_state[t].labels)) for t in tiles)),
            "tile_list": ";".join(f"{tx},{ty}" for tx, ty in tiles),
            "digest": self.digest(),
        }


def _check_patch(p: GridPatch) -> None:
    cells, votes = np.asarray(p.cells), np.asarray(p.votes)
    if cells.ndim != 1 or votes.shape != (cells.shape[0], NUM_CLASSES):
        raise TileError(f"patch {p.patch_id!r}: expected cells [n] and votes [n, {NUM_CLASSES}]")
    if cells.size and (int(cells.min()) < 0 or int(cells.max()) >= CELLS_PER_TILE):
        raise TileError(f"patch {p.patch_id!r}: cell index out of range [0, {CELLS_PER_TILE})")
    if cells.size > 1 and not np.all(np.diff(cells.astype(np.int64)) > 0):
        raise TileError(f"patch {p.patch_id!r}: cells must be sorted and unique")
    if not np.issubdtype(votes.dtype, np.integer) or (votes.size and int(votes.min()) < 0):
        raise TileError(f"patch {p.patch_id!r}: votes must be non-negative integers")


def tile_labels(
    traversals: list[tuple[str, _Traversal]], *, window: int, min_votes: int,
    footprint_cells: int = MergerConfig.footprint_cells, idle: list[str] | None = None,
    min_sign_cells: int = MergerConfig.min_sign_cells,
    min_stop_cells: int = MergerConfig.min_stop_cells,
) -> np.ndarray:
    """The evidence rule (module docstring) for one tile -> (512, 512) uint8 labels.

    Dense per-tile accumulators; traversals are visited newest first and each cell stops taking
    observations once it has `window` of them, so no per-cell sort is needed. `idle`, if given,
    receives the ids of the traversals no cell took an observation from."""
    # 2. most recent first, by the traversals' own time then id (arrival order never matters)
    order = sorted(traversals, key=lambda kv: (kv[1].t_first_ns, kv[0]), reverse=True)
    ballots = [(tid, trav.ballots(footprint_cells)) for tid, trav in order]  # 1. one per cell
    # accumulators over the observed cells only (a tile's union of the traversals' cells, a
    # fraction of its 262144): compact rows, found through a lookup table
    hit = np.zeros(CELLS_PER_TILE, dtype=bool)
    for _, (cells, _, _) in ballots:
        hit[cells] = True
    observed = np.flatnonzero(hit)
    row_of = np.empty(CELLS_PER_TILE, dtype=np.intp)
    row_of[observed] = np.arange(len(observed))
    # per (cell, class): ballots in the high 32 bits, the votes behind them in the low 32 bits,
    # so one integer add counts both and an argmax ranks by ballots, then votes
    packed = np.zeros(len(observed) * SLOTS, dtype=np.uint64)
    seen = np.zeros(len(observed), dtype=np.uint16)  # observations taken per cell
    for tid, (cells, ballot, weight) in ballots:
        at = row_of[cells]
        if len(order) > window:  # 2. only each cell's `window` newest observations count
            fresh = seen[at] < window
            at, ballot, weight = at[fresh], ballot[fresh], weight[fresh]
            if idle is not None and not len(at):
                idle.append(tid)
        seen[at] += 1
        packed[at * SLOTS + ballot] += weight.astype(np.uint64) + BALLOT
    scores = packed.reshape(-1, SLOTS)
    winner = _decide(scores, min_votes)
    # 4. a ground-sign (stop-line) blob too small to be a sign (stop line) is decided again
    # without its sign (stop-line) ballots
    for cls, min_cells in ((Cls.GROUND_SIGN, min_sign_cells), (Cls.STOP_LINE, min_stop_cells)):
        small = _small_blob_cells(observed, winner, cls, min_cells)
        if small.size:
            scores[small, cls] = 0
            winner[small] = _decide(scores[small], min_votes)
    labels = np.zeros(CELLS_PER_TILE, dtype=np.uint8)
    labels[observed] = winner
    return labels.reshape(TILE_CELLS, TILE_CELLS)


def _decide(scores: np.ndarray, min_votes: int) -> np.ndarray:
    """Rule 3 on (cells, SLOTS) packed scores -> each cell's label (0 below min_votes)."""
    rows = np.arange(len(scores))
    low = np.uint64(BALLOT - 1)
    # paint (its best class) against the pooled ground ballots (road + none + no paint),
    # then road against none; argmax ranks by ballots, then votes, then the lower class
    paint = np.argmax(scores[:, 2:NUM_CLASSES], axis=1) + 2
    p_score = scores[rows, paint]
    ground = scores[:, 0] + scores[:, 1] + scores[:, UNSEEN_PAINT]  # ballots, votes: own bits
    p_ballots, g_ballots = p_score >> np.uint64(32), ground >> np.uint64(32)
    more_votes = (p_score & low) > (ground & low)
    paint_wins = (p_ballots > g_ballots) | ((p_ballots == g_ballots) & more_votes)
    winner = np.where(paint_wins, paint, np.argmax(scores[:, :2], axis=1))
    votes = scores[rows, winner] & low
    winner[votes < min_votes] = 0
    return winner


# cells of one class this close (0.3 m) belong to one marking (a sign's letters, arrow parts; a
# stop line's worn pieces)
BLOB_GAP_CELLS = 3


def _small_blob_cells(observed: np.ndarray, winner: np.ndarray, cls: int,
                      min_cells: int) -> np.ndarray:
    """Rows of `observed` whose label `cls` lies in a blob of fewer than `min_cells` cells
    (blobs joined across gaps of BLOB_GAP_CELLS) that does not touch the tile's edge: a blob cut
    by the edge may be part of a marking in the neighbouring tile, so it is kept."""
    hit = winner == cls
    if min_cells <= 1 or not hit.any():
        return np.empty(0, np.intp)
    mask = np.zeros(CELLS_PER_TILE, np.uint8)
    mask[observed[hit]] = 1
    mask = mask.reshape(TILE_CELLS, TILE_CELLS)
    k = 2 * BLOB_GAP_CELLS + 1
    n, blob = cv2.connectedComponents(cv2.dilate(mask, np.ones((k, k), np.uint8)), connectivity=8)
    blob = blob.ravel()
    area = np.bincount(blob[observed[hit]], minlength=n)
    edge = np.zeros(n, bool)
    for side in (blob[:TILE_CELLS], blob[-TILE_CELLS:], blob[::TILE_CELLS],
                 blob[TILE_CELLS - 1::TILE_CELLS]):
        edge[side] = True
    drop = (area < min_cells) & ~edge
    rows = np.flatnonzero(hit)
    return rows[drop[blob[observed[rows]]]]


class TileCodecCache:
    """Compressed form and version of each tile; a version grows only when the bytes change."""

    def __init__(self, encode: Callable[[np.ndarray], bytes] = encode_tile, codec: str = CODEC):
        self.encode = encode
        self.codec = codec
        self.entries: dict[TileId, tuple[int, bytes]] = {}

    def restore(self, tile: TileId, version: int, data: bytes) -> None:
        self.entries[tuple(tile)] = (int(version), bytes(data))

    def update(self, tile: TileId, labels: np.ndarray) -> bool:
        """Re-encode a tile; True (and version + 1) when its compressed bytes changed."""
        return self.put(tile, self.encode(labels))

    def put(self, tile: TileId, data: bytes) -> bool:
        """Store already encoded bytes; True (and version + 1) when they differ from the last."""
        version, old = self.entries.get(tuple(tile), (0, None))
        if data == old:
            return False
        self.entries[tuple(tile)] = (version + 1, data)
        return True

    def get(self, tile: TileId) -> tuple[int, bytes] | None:
        return self.entries.get(tuple(tile))
