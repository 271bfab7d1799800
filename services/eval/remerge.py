"""An earlier run's map rebuilt offline from the patches its shards stored, with today's merger:
the loop to iterate the evidence rule on, paired by drive (as replay.py is the car's).

Each drive's shards keep every applied patch in their SQLite files (RUN/drives/<drive>/run/
merger-s*.sqlite). They are applied again to one MergerShard with today's merger defaults and
`--set merger.KEY=VALUE`. The labels are scored against the world's truth as the demo's report
scores them (services/eval/map.py: the same mosaic of the run's tiles, the same observed area).
With nothing changed this reproduces the run's map cell for cell. It takes seconds a drive
instead of the suite's forty minutes. The car's figures stay the run's: the car localized on the
run's map.

    roadmap eval --remerge RUN --out DIR [--set merger.KEY=VALUE ...]"""

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from common.config import load_config
from common.errors import ConfigError
from common.grid import TILE_CELLS
from common.messages import GridPatch
from services.demo.fetch import load_tiles
from services.demo.report import mapping_logs, observed_area
from services.eval import map as ev
from services.eval.run import drive_world
from services.merger.shard import MergerShard
from services.merger.store import ShardStore


def stored_patches(drive_dir: Path) -> Iterator[GridPatch]:
    """Every patch the drive's shards applied, shard by shard."""
    stores = sorted((drive_dir / "run").glob("merger-s*.sqlite"))
    if not stores:
        raise ConfigError(f"{drive_dir}: no shard store (run/merger-s*.sqlite): --remerge reads "
                          "the embedded SQLite stores, not a PostgreSQL one")
    for path in stores:
        store = ShardStore.read_only(path)
        try:
            yield from store.load_patches()
        finally:
            store.close()


def merged_labels(patches, tiles: list[tuple[int, int]], merger_cfg) -> list[np.ndarray]:
    """The labels of `tiles` (empty where no patch fell) after applying `patches` (stored, so
    checked when they were first applied)."""
    shard = MergerShard.from_config(merger_cfg, owns=lambda tile: True)
    shard.apply_checked(list(patches))
    shard.flush()
    empty = np.zeros((TILE_CELLS, TILE_CELLS), np.uint8)
    return [shard.labels(t) if t in shard.tiles_state else empty for t in tiles]


def remerge_drive(drive_dir: Path, sets: list[str]) -> dict:
    """The map's per-class figures of the drive rebuilt with today's merger (+ sets), and how
    many cells differ from the run's map."""
    drive_dir = Path(drive_dir)
    run_cfg = load_config(drive_dir / "config.toml")  # the fleet's: ROI and vehicle range
    return scored_map(drive_dir, stored_patches(drive_dir), load_config(sets=sets).merger,
                      run_cfg)


def scored_map(drive_dir: Path, patches, merger_cfg, fleet_cfg, logs=None) -> dict:
    """The per-class figures of the map `patches` make with `merger_cfg` on the run's tiles,
    scored as the demo's report scores a map (the observed area of the mapping drive logs
    `logs`, default all of the run's, under `fleet_cfg`'s ROI and vehicle range), and how many
    cells differ from the run's map."""
    held = load_tiles(drive_dir / "run" / "tiles.npz")
    labels = merged_labels(patches, held["tiles"], merger_cfg)
    mosaic = ev.Mosaic(held["tiles"])
    raw = mosaic.paste(held["tiles"], labels)
    truth = ev.truth_mosaic(drive_world(drive_dir), mosaic, held["tiles"])
    observed = observed_area(fleet_cfg, mosaic, mapping_logs(drive_dir) if logs is None else logs)
    return {"per_class": ev.map_quality(raw, truth, observed),
            "changed_cells": int(np.count_nonzero(raw != mosaic.paste(held["tiles"],
                                                                        held["raw"])))}
